"""The servo loop in its own real-time process, owning the robot driver.

Parent side: :class:`ServoProcess` (a :class:`~hil.servo.link.ServoLink`). It creates the shared
regions, starts the child (``python -m hil.servo.child``: a fresh interpreter, so nothing of the
supervisor's threads, locks or heap comes along, and the caller's main module is never re-run),
sends it the spec over a socket pair, waits for it to report ready (the real-time grant, the
robot's rate and TCP), and answers the channel commands. Spawning, the ready handshake,
liveness, ending and restarting the child are :class:`hil.childproc.ChildProcess`'s, shared with
the perception process.

Child side: :func:`servo_main`. It builds the setup's robot through the driver registry on the
wall clock and opens it, starts a command thread (channel commands such as a recovery
may block for tens of ms; the loop never waits for them), asks for real time for the loop's thread
(:func:`~hil.servo.rt.apply_realtime`; once it is pinned, the parent keeps off its CPU,
``[servo] reserve_cpu``, :mod:`hil.servo.reserve`), and then every period: waits for the deadline (sleep, then
spin) and steps the :class:`~hil.servo.loop.ServoLoop`. A period missed by more than one is
skipped (never bunched), and counted by the loop.

Shutdown and crashes — the arm is stopped on every path:

- ``close``: the child stops the arm, closes the robot and exits (the parent waits, then
  terminates, then kills a child that does not exit);
- the parent dies (Ctrl-C, a crash, SIGKILL): the child's channel ends (or its parent changes,
  checked every 50 periods), it stops the arm, closes the robot and exits;
- the child crashes: it stops the arm if it still can and reports the traceback; the parent's
  :meth:`ServoProcess.gone` says why, and the supervisor's robot then raises DisconnectedError
  (the controller faults, the run ends and the session log says why). A UR arm also stops by
  itself when servo commands stop arriving (the RTDE control script's own timeout).

The child ignores SIGINT: Ctrl-C goes to the whole process group, and the parent decides.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import select
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from drivers.interfaces.errors import DisconnectedError, DriverError
from drivers.interfaces.robot import FollowingModel
from hil import childproc
from hil.childproc import ChildProcess
from hil.clock import MonotonicClock
from hil.config.setup import SetupConfig
from hil.geometry.transform import RigidTransform
from hil.servo.limiter import LimiterArgs, RateLimiter
from hil.servo.link import Regions
from hil.servo.loop import ServoLoop
from hil.servo.reserve import release_cpu, reserve_cpu
from hil.servo.rt import RtGranted, apply_realtime, default_cpu, wait_until
from hil.servo.shm import Stat
from hil.servo.wire import error_from_wire, error_to_wire

#: How long the child may take to start (a fresh interpreter importing numpy and the driver).
START_TIMEOUT_S = childproc.START_TIMEOUT_S
#: Periods between two checks that the parent is still alive.
PARENT_CHECK_PERIODS = 50
#: periods after the start before the loop's timing maxima and late causes are counted (the first
#: periods pay for first calls: caches, lazy imports in the driver)
TIMING_WARMUP_PERIODS = 100


#: How long the end of the channel waits for the child's exit to be reported (s).
CHANNEL_END_WAIT_S = childproc.CHANNEL_END_WAIT_S


@dataclass(frozen=True)
class ServoSpec:
    """What the child needs (picklable).

    Attributes:
        setup: the validated setup (its robot section is built in the child).
        limiter: the tracking's :class:`RateLimiter` arguments (:data:`LimiterArgs`: its limits and
            pivot).
        realtime: ask for SCHED_FIFO / pinning / mlockall.
        priority: the SCHED_FIFO priority (1-99).
        cpu: the CPU to pin to (None: the last one).
        reserve_cpu: once the loop is pinned at SCHED_FIFO, keep this (the parent) process off
            its CPU while the child runs (:mod:`hil.servo.reserve`).
    """

    setup: SetupConfig
    limiter: LimiterArgs
    realtime: bool = True
    priority: int = 80
    cpu: int | None = None
    reserve_cpu: bool = True


@dataclass(frozen=True)
class ServoReady:
    """What the child reports once running."""

    robot_name: str
    control_rate_hz: float
    T_flange_from_tcp: RigidTransform
    rt: RtGranted
    pid: int
    following: FollowingModel = field(default_factory=FollowingModel)
    #: the CPUs this (the supervisor's) process was moved to, off the loop's (None: not moved)
    supervisor_cpus: frozenset[int] | None = None


class ServoProcess:
    """Parent side of the servo process (module doc). ``start`` blocks until the child is ready.
    The child's lifecycle (spawn, ready handshake, liveness, ending, restart) is
    :class:`hil.childproc.ChildProcess`'s.

    Raises (start): DriverError from building or opening the robot in the child (same class,
    device and message); DeviceTimeoutError when the child does not start in time.
    """

    in_process = False

    def __init__(self, spec: ServoSpec, robot_name: str, T_flange_from_tcp: RigidTransform) -> None:
        self.spec = spec
        self._name, self._T_flange_from_tcp = robot_name, T_flange_from_tcp
        self._events: deque[tuple[str, dict[str, Any]]] = deque()
        self._crash: str | None = None
        self._next_id = 0
        self.ready: ServoReady | None = None
        self._child = ChildProcess("hil.servo.child", "servo process", robot_name, ("close", -1, ()))
        self._reserved_cpu: int | None = None   # the loop's CPU this process keeps off (reserve_cpu)
        #: one reader of the channel at a time (the controller's thread, observers' threads)
        self._channel_lock = threading.RLock()
        #: called with the new state ring's segment name after a successful :meth:`restart` (a
        #: perception process's simulated world follows the arm through that ring)
        self.restart_listeners: list[Callable[[str], None]] = []

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> ServoReady:
        """Create the shared regions and the channel, start the child, wait until it is ready.
        A failed start ends the child and frees the regions; :meth:`restart` may try again.
        Holds the channel lock throughout: an observer's :meth:`gone` waits for the new child
        instead of reading a half-swapped one (the channel of one, the exit code of the other)."""
        with self._channel_lock:
            return self._start()

    def _start(self) -> ServoReady:
        self.regions = Regions.create(shared=True)
        try:
            self._attach(self._child.spawn())
        except BaseException:
            self.regions.close()
            raise
        info = self._child.handshake(
            (self.spec, self.regions.names()),
            wait_ready=lambda: self._wait_for(lambda m: m[0] in ("ready", "failed"), START_TIMEOUT_S),
            failed=lambda payload: error_from_wire(*payload),
            # the first period's record: state reads work from here
            published=lambda: self.regions.ring.head != 0, pause=lambda: time.sleep(0.001),
            unpublished="servo loop did not read the robot after starting", on_failure=self._end_child,
            timeout_s=START_TIMEOUT_S)
        rt = RtGranted.from_dict(info["rt"])
        moved = None
        if self.spec.reserve_cpu and rt.realtime and rt.cpu is not None:
            moved = reserve_cpu(rt.cpu)
            self._reserved_cpu = rt.cpu if moved is not None else None
        self.ready = ServoReady(info["robot_name"], float(info["control_rate_hz"]),
                                RigidTransform.from_matrix(np.asarray(info["T_flange_from_tcp"])),
                                rt, int(info["pid"]), FollowingModel(**info["following"]), moved)
        return self.ready

    def _attach(self, conn: Connection) -> None:
        """Read the channel ``conn`` (a new child's) from here on."""
        self._conn = conn
        # whether a message waits, without the selector Connection.poll builds per call (the
        # supervisor asks at every robot state read, on the pair's path)
        self._readable = select.poll()
        self._readable.register(conn.fileno(), select.POLLIN)

    def restart(self) -> ServoReady:
        """Start a new child in place of one that ended on its own (:meth:`gone` says why: the
        robot library or the interpreter crashed, the OS killed it): the robot is built and opened
        anew in it -- new connections, its control program started again -- on new shared regions.
        Nothing commanded the arm meanwhile: a UR rests on its last servo target, and its control
        program stops when the RTDE watchdog sees no kick or is replaced by the new driver's.
        Blocks like :meth:`start` and raises what it raises; a failed restart may be tried again.
        Once the new child is ready, each of :attr:`restart_listeners` gets the new ring's name.

        Raises:
            LifecycleError: after :meth:`close`, or while the child runs (nothing to restart).
        """
        with self._channel_lock:   # observers' gone() never see the old child half replaced
            self._child.check_restart(crashed=self._crash is not None)
            self._end_child()
            self._crash, self.ready = None, None
            self._events.clear()
            ready = self._start()
        ring = self.regions.ring_region.name
        for listener in self.restart_listeners:
            listener(str(ring))
        return ready

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the arm and end the child (module doc). Idempotent; never raises."""
        if self._child.close(timeout_s):
            self._free_child()

    def _end_child(self, timeout_s: float = 5.0) -> None:
        """Ask the child to stop the arm and exit, then terminate, then kill it; free the channel
        and the regions. Once per child; never raises."""
        if self._child.end(timeout_s):
            self._free_child()

    def _free_child(self) -> None:
        """Free what the ended child used: the regions, the loop's CPU kept off."""
        self.regions.close()
        if self._reserved_cpu is not None:
            release_cpu(self._reserved_cpu)
            self._reserved_cpu = None

    @property
    def closed(self) -> bool:
        """:meth:`close` was called (a child that ended on its own leaves this False)."""
        return self._child.closed

    @property
    def exitcode(self) -> int | None:
        """The child's exit code (negative: the signal that ended it); None while it runs or
        before :meth:`start`."""
        return self._child.exitcode

    # ------------------------------------------------------------------ link contract
    @property
    def robot_name(self) -> str:
        return self._name

    @property
    def control_rate_hz(self) -> float:
        assert self.ready is not None, "start() first"
        return self.ready.control_rate_hz

    @property
    def following_model(self) -> FollowingModel:
        assert self.ready is not None, "start() first"
        return self.ready.following

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        return self.ready.T_flange_from_tcp if self.ready is not None else self._T_flange_from_tcp

    def request(self, command: str, *args: Any, timeout_s: float = 5.0) -> Any:
        with self._channel_lock:
            return self._request(command, args, timeout_s)

    def _request(self, command: str, args: tuple[Any, ...], timeout_s: float) -> Any:
        why = self.gone()
        if why is not None:
            raise DisconnectedError(self.robot_name, why)
        self._next_id += 1
        rid = self._next_id
        try:
            self._child.send((command, rid, args))
        except (OSError, ValueError) as exc:
            raise DisconnectedError(self.robot_name, f"servo process channel: {exc}") from exc
        msg = self._wait_for(lambda m: m[0] == "reply" and m[1] == rid, timeout_s)
        ok, payload = msg[2], msg[3]
        if not ok:
            raise error_from_wire(*payload)
        return payload

    def take_events(self) -> list[tuple[str, dict[str, Any]]]:
        with self._channel_lock:
            self._pump(0.0, None)
            out = list(self._events)
            self._events.clear()
            return out

    def gone(self) -> str | None:
        crash = self._crash
        if crash is not None:
            return crash
        if self._child.closed:
            return "servo process closed"
        if not self._child.started:
            return "servo process not started"
        if self._child.running:
            return None
        with self._channel_lock:
            # checked again under the lock: a restart (which holds it) may have replaced the child
            return self._gone_now()

    def _gone_now(self) -> str | None:
        """None while the child runs and reported no crash; else why it is gone (the channel
        read first, for a crash report sent before it went)."""
        if self._crash is None and self._child.running:
            return None
        self._pump(0.0, None)
        return self._exit_reason()

    def _exit_reason(self) -> str:
        return self._crash or self._child.exited()

    def kick(self) -> None:
        """Nothing: the process loop reads the block every period."""

    def wait_period(self) -> float:
        t0 = time.monotonic()
        time.sleep(0.005)
        return time.monotonic() - t0

    # ------------------------------------------------------------------ channel
    def _pump(self, timeout_s: float, want: Any) -> Any:
        """Receive messages for up to ``timeout_s``; events are queued; returns the first message
        ``want`` accepts (None: none)."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = max(deadline - time.monotonic(), 0.0)
            try:
                if not (self._conn.poll(remaining) if remaining > 0 else self._readable.poll(0)):
                    return None
                msg = self._conn.recv()
            except (EOFError, OSError):
                self._crash = self._crash or self._child.channel_end_reason(CHANNEL_END_WAIT_S)
                return None
            if msg[0] == "event":
                self._events.append((msg[1], msg[2]))
            elif msg[0] == "crashed":
                self._crash = f"servo process crashed: {msg[1]}"
            if want is not None and want(msg):
                return msg
            if remaining <= 0 and not self._readable.poll(0):
                return None

    def _wait_for(self, want: Any, timeout_s: float) -> Any:
        return self._child.wait_message(lambda wait_s: self._pump(wait_s, want), self._gone_now, timeout_s,
                                        f"servo process did not answer within {timeout_s} s")


# ---------------------------------------------------------------------------- child
def servo_main(conn: Connection, parent_pid: int) -> None:
    """The servo process (module doc): receives ``(spec, region names)`` first.

    Order matters: the process first moves off the loop's CPU, then the robot is built and opened
    and the command thread started, and only then the loop's thread takes its CPU and SCHED_FIFO.
    So the driver's own threads (ur-rtde's receivers, the watchdog kicker) and the command thread
    run on the normal scheduler on the other CPUs: when the loop waits inside a driver call for one
    of them (a stop waits for the controller's reply), its own priority cannot starve them (seen as
    an RTDE watchdog expiry after a servoStop before this order). Threads the driver starts later
    (a reconnect in ``recover``) are started from the command thread, so they are normal too.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from hil.log import configure_logging

    configure_logging(level="warning")
    spec, names = conn.recv()
    closing = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: closing.set())
    regions = Regions.attach(names)
    clock = MonotonicClock()
    loop_cpu = default_cpu() if spec.cpu is None else spec.cpu   # chosen once, before moving off it
    if spec.realtime:
        _keep_off_the_loop_cpu(loop_cpu)
    from hil.config.build import build_devices  # the registry, in the child only

    try:
        robot = build_devices(spec.setup, clock).robot
        robot.open()
    except DriverError as exc:
        conn.send(("failed", error_to_wire(exc)))
        regions.close()
        return
    except Exception as exc:  # noqa: BLE001 - a config the parent validated; report, never hang it
        conn.send(("failed", ("DeviceFaultError", "robot", f"{type(exc).__name__}: {exc}")))
        regions.close()
        return
    send_lock = threading.Lock()

    def send(msg: Any) -> None:
        with send_lock, contextlib.suppress(OSError, ValueError):
            conn.send(msg)

    loop = ServoLoop(robot, spec.setup.safety.motion_limits(), clock, regions.block, regions.ring,
                     regions.stats, period_s=1.0 / robot.control_rate_hz, limiter=RateLimiter(*spec.limiter),
                     report=lambda kind, fields: send(("event", kind, fields)))
    commands = threading.Thread(target=_serve, args=(conn, robot, send, closing), name="servo-commands",
                                daemon=True)
    commands.start()
    sys.setswitchinterval(0.0005)   # the loop thread gets the interpreter back within 0.5 ms
    rt = apply_realtime(spec.priority, loop_cpu) if spec.realtime else RtGranted()
    T_tcp = robot.T_flange_from_tcp
    send(("ready", {"robot_name": robot.name, "control_rate_hz": robot.control_rate_hz,
                    "T_flange_from_tcp": T_tcp.as_matrix().tolist(), "rt": rt.to_dict(), "pid": os.getpid(),
                    "following": dataclasses.asdict(loop.following.model)}))
    try:
        _run(loop, parent_pid, closing)
    except BaseException:  # noqa: BLE001 - a crash: stop the arm, say why, exit non-zero
        detail = traceback.format_exc(limit=6)
        _stop_quietly(robot)
        send(("crashed", detail))
        robot.close()
        os._exit(1)
    _stop_quietly(robot)
    robot.close()
    regions.close()


def _keep_off_the_loop_cpu(cpu: int) -> None:
    """Move this (still single) thread off the loop's CPU, so every thread started from here on —
    the driver's receivers and watchdog kicker, the command thread — runs on the other CPUs. The
    loop thread then pins itself to that CPU at SCHED_FIFO: a driver call it makes that waits for
    one of those threads (a stop waiting for the controller's reply) is never starved by the loop's
    own priority on a shared CPU."""
    others = os.sched_getaffinity(0) - {cpu}
    if others:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, others)


def _stop_quietly(robot: Any) -> None:
    with contextlib.suppress(DriverError):
        robot.stop()


def _run(loop: ServoLoop, parent_pid: int, closing: threading.Event) -> None:
    period_ns = loop.period_ns
    c = loop.stats.c
    next_ns = time.monotonic_ns() + period_ns
    k = 0
    while not closing.is_set():
        now = wait_until(next_ns)
        cpu0 = time.thread_time_ns()
        loop.step(now)
        # the CPU-clock interval inside the wall-clock one: an interrupt charged to this thread
        # just after the step can then never make its CPU time exceed its wall time
        cpu_ns = time.thread_time_ns() - cpu0
        done = time.monotonic_ns()
        k += 1
        if k % PARENT_CHECK_PERIODS == 0 and os.getppid() != parent_pid:
            return   # the supervisor is gone: stop the arm (the caller) and exit
        if k > TIMING_WARMUP_PERIODS:
            _count_late_causes(c, now - next_ns, done - now, done - next_ns - period_ns, period_ns, cpu_ns)
        next_ns += period_ns
        late = done - next_ns
        if late > period_ns:   # missed more than one period: skip the slots, never bunch them
            next_ns += (late // period_ns) * period_ns


def _count_late_causes(c: Any, wake_late_ns: int, step_ns: int, overrun_ns: int, period_ns: int,
                       step_cpu_ns: int) -> None:
    """Where a late period came from (:class:`~hil.servo.shm.Stat` words marked (*)): the loop
    woke more than a period after its deadline (the OS or the host did not run it: ``LATE_WAKES``)
    or its work ran more than a period past the next deadline (``OVERRUNS``); and the longest of
    each. An overrun during whose work the loop thread was off its CPU for more than a period
    (``step_ns - step_cpu_ns``: wall time the thread's CPU clock did not see, which on a virtual
    machine with steal accounting includes the time the host ran other guests on this CPU; also a
    driver call that blocked) is counted in ``OVERRUNS_OFF_CPU`` too; the rest ran long on the CPU.
    A few integer compares per period (about a microsecond), nothing logged or sent.

    Args:
        wake_late_ns: when the loop woke after its deadline, ns. step_ns: the step's wall time, ns.
        overrun_ns: how far the step ended past the next deadline, ns (negative: in time).
        period_ns: the loop's period, ns. step_cpu_ns: the step's time on the loop thread's CPU
            clock (``CLOCK_THREAD_CPUTIME_ID``), ns.
    """
    if wake_late_ns > c[Stat.WAKE_LATE_MAX_NS]:
        c[Stat.WAKE_LATE_MAX_NS] = wake_late_ns
    if wake_late_ns > period_ns:
        c[Stat.LATE_WAKES] += 1
    if step_ns > c[Stat.STEP_NS_MAX]:
        c[Stat.STEP_NS_MAX] = step_ns
    if step_cpu_ns > c[Stat.STEP_CPU_NS_MAX]:
        c[Stat.STEP_CPU_NS_MAX] = step_cpu_ns
    off_cpu_ns = step_ns - step_cpu_ns
    if off_cpu_ns > c[Stat.STEP_OFF_CPU_NS_MAX]:
        c[Stat.STEP_OFF_CPU_NS_MAX] = off_cpu_ns
    if overrun_ns > c[Stat.WORST_OVERRUN_NS]:
        c[Stat.WORST_OVERRUN_NS] = overrun_ns
    if overrun_ns > period_ns:
        c[Stat.OVERRUNS] += 1
        if off_cpu_ns > period_ns:
            c[Stat.OVERRUNS_OFF_CPU] += 1


def _serve(conn: Connection, robot: Any, send: Any, closing: threading.Event) -> None:
    """The command thread: serve channel commands until ``close`` or the channel ends (the
    supervisor is gone); then tell the loop to end."""
    try:
        while not closing.is_set():
            command, rid, _args = conn.recv()
            if command == "close":
                break
            try:
                if command == "recover":
                    robot.recover()
                    result: Any = None
                else:
                    raise ValueError(f"unknown servo command {command!r}")
                send(("reply", rid, True, result))
            except DriverError as exc:
                send(("reply", rid, False, error_to_wire(exc)))
            except Exception as exc:  # noqa: BLE001 - a bad command is the supervisor's fault, not the loop's
                why = f"servo process could not run {command!r}: {type(exc).__name__}: {exc}"
                send(("reply", rid, False, ("DeviceFaultError", robot.name, why)))
    except (EOFError, OSError):
        pass   # the supervisor is gone
    finally:
        closing.set()
