"""Run a device's checks one after another, each bounded by a timeout, stopping at the first
failure; turn every error into a plain-word :class:`~hil.probe.report.Check`.

A step is a function returning an :class:`Outcome` (ok or warn) or raising :class:`Finding`
(a failure with its likely cause). It runs in a daemon worker thread: when it does not return
within its timeout the step fails with "no answer within S s" and the thread is abandoned (it
may be stuck in a blocking library call; it dies with the process). No traceback ever reaches
the user for a device problem: typed driver errors become their message plus a hint, anything
else becomes "unexpected <type>: <message>".
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from drivers.interfaces.errors import (
    DeviceFaultError,
    DeviceTimeoutError,
    DisconnectedError,
    DriverError,
    LifecycleError,
    ProtocolError,
    SafetyStopError,
)
from hil.errors import HilError
from hil.log import get_logger
from hil.probe.report import Check, DeviceReport, Status

T = TypeVar("T")
_log = get_logger(__name__)


@dataclass
class Outcome:
    """What a passing step found. ``value`` is handed back to the caller (not reported)."""

    message: str
    status: Status = Status.OK
    hint: str = ""
    data: dict[str, Any] = field(default_factory=dict)
    value: Any = None


class Finding(Exception):  # noqa: N818 - a finding, not an error of the program
    """Raise inside a step to fail it with a plain-word message and what to try."""

    def __init__(self, message: str, hint: str = "", data: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.hint = hint
        self.data = data or {}


class WireProblem(Exception):  # noqa: N818 - a finding about the bytes on a line
    """Base of the probe's own protocol errors: a device went quiet mid-exchange or answered with
    something that is not its protocol (a step failing with one says so in plain words)."""


class StepTimeoutError(Exception):
    """A step did not return within its timeout."""


def call_with_timeout(fn: Callable[[], T], timeout_s: float, name: str = "probe-step") -> T:
    """Run ``fn`` in a daemon thread; its result, its exception, or StepTimeoutError after
    ``timeout_s`` (the thread is then abandoned)."""
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            box["error"] = exc

    worker = threading.Thread(target=target, name=name, daemon=True)
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        raise StepTimeoutError(f"no answer within {timeout_s:g} s")
    if "error" in box:
        raise box["error"]
    return box["value"]  # type: ignore[no-any-return]


_HINTS: tuple[tuple[type[DriverError], str], ...] = (
    (SafetyStopError, "release the protective/emergency stop on the teach pendant, then run the probe again"),
    (DeviceTimeoutError, "the device did not answer in time: check power, cable, address and baud rate"),
    (DisconnectedError, "the connection could not be made or was lost: check cable, address and that "
                        "no other program holds the device"),
    (ProtocolError, "the device answered with bytes that do not parse: wrong baud rate, wrong device "
                    "on this port, or a noisy line"),
    (DeviceFaultError, "the device reports a fault of its own: see its front panel / manual, "
                       "power-cycle it"),
    (LifecycleError, "a driver lifecycle problem (report it as a bug)"),
)


def hint_for(exc: BaseException) -> str:
    for kind, hint in _HINTS:
        if isinstance(exc, kind):
            return hint
    return ""


class Checklist:
    """The steps of one device: :meth:`step` runs one, records its Check and returns its
    Outcome, or None when it failed (or an earlier step failed: later steps are not run)."""

    def __init__(self, report: DeviceReport, timeout_s: float) -> None:
        self.report = report
        self.timeout_s = timeout_s

    @property
    def failed(self) -> bool:
        return self.report.stopped_early or any(c.status is Status.FAIL for c in self.report.checks)

    def step(
        self, name: str, fn: Callable[[], Outcome], *, timeout_s: float | None = None,
        what: str = "", timeout_hint: str = "",
    ) -> Outcome | None:
        """Run ``fn`` as step ``name`` (``what`` names it in a timeout message).

        Returns the Outcome, or None when the step failed or the checklist had already stopped.
        """
        if self.failed:
            return None
        limit = self.timeout_s if timeout_s is None else timeout_s
        t0 = time.monotonic()
        outcome: Outcome | None = None
        try:
            outcome = call_with_timeout(fn, limit, f"probe-{self.report.role}-{name}")
            check = Check(name, outcome.status, outcome.message, outcome.hint, outcome.data)
        except Finding as f:
            check = Check(name, Status.FAIL, f.message, f.hint, f.data)
        except StepTimeoutError:
            check = Check(name, Status.FAIL, f"{what or name}: no answer within {limit:g} s",
                          timeout_hint or "the device or the network did not answer: check power, cable, "
                                          "address; raise --timeout-s if the device is just slow")
        except DriverError as exc:
            check = Check(name, Status.FAIL, f"{what or name}: {exc.message}", hint_for(exc))
        except HilError as exc:
            check = Check(name, Status.FAIL, f"{what or name}: {exc}")
        except WireProblem as exc:
            check = Check(name, Status.FAIL, f"{what or name}: {exc}",
                          "the device stopped answering or answered with something unexpected: check "
                          "power and cable, then probe again")
        except OSError as exc:  # sockets, serial ports (serial.SerialException is an OSError)
            check = Check(name, Status.FAIL, f"{what or name}: {exc.strerror or exc}",
                          "the connection or the port failed: check cable and power; unplug and replug a "
                          "USB adapter")
        except Exception as exc:  # noqa: BLE001 - a device problem must never become a traceback
            check = Check(name, Status.FAIL, f"{what or name}: unexpected {type(exc).__name__}: {exc}",
                          "this looks like a driver bug; run with --log-level debug and report it")
            _log.debug("probe_step_unexpected", role=self.report.role, step=name, error=repr(exc))
        check = Check(check.name, check.status, check.message, check.hint, check.data,
                      time.monotonic() - t0)
        self.report.add(check)
        _log.info("probe_step", role=self.report.role, step=name, status=check.status.value,
                  duration_s=round(check.duration_s, 3))
        if check.status is Status.FAIL:
            self.report.stopped_early = True
            return None
        return outcome
