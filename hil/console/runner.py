"""The controller loop in its own thread, so the UI never blocks it (and it never blocks the UI).

Each iteration: one :meth:`Controller.tick` (which blocks on the camera for at most a few frame
periods), then a :class:`~hil.console.view.ConsoleView` built from the controller's frozen
snapshot (bounded work). The OpenIGTLink stream, when enabled, is a runtime plugin of the
controller (``hil_on_tick``), not the runner's business. On a simulated clock the loop can be paced to
the wall clock (the simulator then runs in real time when the machine keeps up).

On quit the runner aborts any procedure under way (ABORT_REQUESTED through the state machine:
the robot is stopped by the SAFE_STOP entry action) before it returns. An unexpected exception
in the loop stops the robot and is shown to the operator; it never passes silently.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import TYPE_CHECKING

from hil.console.operator import ConsoleOperator
from hil.console.view import ConsoleView, ViewSetup, build_view
from hil.controller.fsm import Event, State
from hil.controller.gate import rms_deviation_mm
from hil.log import get_logger

if TYPE_CHECKING:
    from hil.controller.controller import Controller
    from hil.igtl.server import IgtlServer

_log = get_logger(__name__)
_BREATHING_SAMPLES = 150
_MAX_PACE_SLEEP_S = 0.25
#: States left alone on quit (the robot is already stopped or never moved).
_AT_REST = frozenset({State.IDLE, State.DONE, State.SAFE_STOP, State.FAULT})


class ControllerRunner:
    """Runs ``ctl`` until the operator quits.

    Args:
        ctl: the controller, its operator must be ``operator``.
        operator: the console's operator queue.
        pace: sleep so the controller clock does not run ahead of the wall clock (simulated
            clocks only; a real clock is paced by the camera).
        igtl: the session's OpenIGTLink server (its address and clients are shown), or None.
        session_log: path shown to the operator.
    """

    def __init__(self, ctl: Controller, operator: ConsoleOperator, *, pace: bool,
                 igtl: IgtlServer | None = None, session_log: str = "") -> None:
        self.ctl, self.operator, self.pace, self.igtl = ctl, operator, pace, igtl
        self.session_log = session_log
        self._breathing: collections.deque[float] = collections.deque(maxlen=_BREATHING_SAMPLES)
        cfg = ctl.cfg
        self._setup = ViewSetup(ctl.plan, cfg.gate.tolerance_mm, cfg.gate.dwell_s,
                                int(ctl.rig.flange_markers_mm.shape[0]))
        self._lock = threading.Lock()
        self._view: ConsoleView | None = None
        self._thread: threading.Thread | None = None
        self._done = threading.Event()
        self.error = ""
        self.ticks = 0

    # ---------------------------------------------------------------- UI side
    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="controller", daemon=True)
        self._thread.start()

    def latest(self) -> ConsoleView | None:
        """The most recent snapshot (None before the first). Never blocks on the loop."""
        with self._lock:
            return self._view

    @property
    def ended(self) -> bool:
        return self._done.is_set()

    def stop(self, timeout_s: float = 10.0) -> bool:
        """Ask the loop to end (abort under way, robot stopped) and wait up to ``timeout_s``.
        Returns True when the loop has ended."""
        self.operator.request_quit()
        if self._thread is not None:
            self._thread.join(timeout_s)
        return self._done.is_set()

    # ---------------------------------------------------------------- controller side
    def _igtl_text(self) -> str:
        if self.igtl is None:
            return "off"
        host, port = self.igtl.address
        return f"{host}:{port}, {self.igtl.clients} client(s)"

    def _publish(self, ended: bool = False) -> None:
        """One view from a fresh snapshot (the controller's thread; bounded work)."""
        snap = self.ctl.snapshot()
        if snap.reference_optical_mm is not None and snap.live_mm is not None:
            dev, n = rms_deviation_mm(snap.reference_optical_mm, snap.live_mm)
            if n > 0 and not ended:
                self._breathing.append(dev)
        view = build_view(snap, self._setup, breathing_mm=list(self._breathing),
                          session_log=self.session_log, igtl=self._igtl_text(), ended=ended, error=self.error)
        with self._lock:
            self._view = view

    def _abort_if_under_way(self) -> None:
        ctl = self.ctl
        if ctl.state not in _AT_REST:
            ctl.session.write("operator_command", input=Event.ABORT_REQUESTED, origin="console_quit")
            ctl.fire(Event.ABORT_REQUESTED, "console closed")

    def _loop(self) -> None:
        ctl = self.ctl
        clock = ctl.clock
        try:
            ctl.watchdogs.arm(clock.now_ns())
            wall0, sim0 = time.monotonic(), clock.now_ns()
            self._publish()
            while not self.operator.quit_requested:
                ctl.tick()
                self.ticks += 1
                self._publish()
                if self.pace:
                    ahead = (clock.now_ns() - sim0) * 1e-9 - (time.monotonic() - wall0)
                    if ahead > 0:
                        time.sleep(min(ahead, _MAX_PACE_SLEEP_S))
            self._abort_if_under_way()
        except Exception as exc:  # noqa: BLE001 - the loop must report, stop the robot, never vanish
            self.error = f"controller loop stopped: {type(exc).__name__}: {exc}"
            _log.error("console_loop_failed", error=str(exc), kind=type(exc).__name__)
            try:
                ctl.session.write("console_loop_failed", error=self.error)
                ctl.safety.stop("console loop failed")
            except Exception as exc2:  # noqa: BLE001
                _log.error("stop_failed", reason=str(exc2))
        finally:
            try:
                ctl.log_refused_inputs()  # keys refused while the console was closing
                self._publish(ended=True)
            finally:
                self._done.set()
