"""What ``hil probe`` found: one :class:`Check` per step, grouped per device, rendered as a
plain-word checklist (human) or one JSON object (``--json``).

Statuses: ``ok`` (the step passed), ``warn`` (works, but something needs attention: a sensor
out of the field, a frame rate below the configured one), ``fail`` (the step failed; the
device's later steps were not run). A device is ``fail`` when any of its checks failed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

EXIT_OK = 0
EXIT_DEVICE_FAILED = 1
EXIT_CONFIG_ERROR = 2


class Status(StrEnum):
    OK = "ok"
    WARN = "warn"
    FAIL = "fail"


@dataclass(frozen=True)
class Check:
    """One step of a device's checklist.

    Attributes:
        name: a stable snake_case id (``port_exists``, ``baud_rate``, ``tcp_30004`` ...).
        status: ok / warn / fail.
        message: what was found, in plain words.
        hint: for warn/fail, the likely cause and what to try ("" otherwise).
        data: machine-readable figures (JSON-ready: str, int, float, bool, lists, dicts).
        duration_s: wall time the step took, s.
    """

    name: str
    status: Status
    message: str
    hint: str = ""
    data: dict[str, Any] = field(default_factory=dict)
    duration_s: float = 0.0

    def as_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "status": self.status.value, "message": self.message}
        if self.hint:
            out["hint"] = self.hint
        if self.data:
            out["data"] = self.data
        out["duration_s"] = round(self.duration_s, 3)
        return out


@dataclass
class DeviceReport:
    """The checklist of one configured device (``role`` = camera / robot / tracker)."""

    role: str
    driver: str
    simulated: bool = False
    checks: list[Check] = field(default_factory=list)
    stopped_early: bool = False

    @property
    def status(self) -> Status:
        statuses = {c.status for c in self.checks}
        if Status.FAIL in statuses:
            return Status.FAIL
        if Status.WARN in statuses:
            return Status.WARN
        return Status.OK

    def add(self, check: Check) -> Check:
        self.checks.append(check)
        return check

    def as_json(self) -> dict[str, Any]:
        return {"role": self.role, "driver": self.driver, "simulated": self.simulated,
                "status": self.status.value, "stopped_early": self.stopped_early,
                "checks": [c.as_json() for c in self.checks]}


@dataclass
class ProbeReport:
    """Every device of one setup."""

    config: str
    timeout_s: float
    devices: list[DeviceReport] = field(default_factory=list)

    @property
    def status(self) -> Status:
        statuses = {d.status for d in self.devices}
        if Status.FAIL in statuses:
            return Status.FAIL
        if Status.WARN in statuses:
            return Status.WARN
        return Status.OK

    @property
    def exit_code(self) -> int:
        """0 when no device failed (warnings included), 1 otherwise."""
        return EXIT_DEVICE_FAILED if self.status is Status.FAIL else EXIT_OK

    def as_json(self) -> dict[str, Any]:
        return {"config": self.config, "status": self.status.value, "exit_code": self.exit_code,
                "timeout_s": self.timeout_s, "devices": [d.as_json() for d in self.devices]}


_MARK = {Status.OK: "OK  ", Status.WARN: "WARN", Status.FAIL: "FAIL"}


def render_text(report: ProbeReport) -> str:
    """The human checklist: one block per device, one line per check, causes and fixes indented."""
    lines = [f"hil probe {report.config} (each check times out after {report.timeout_s:g} s)"]
    for dev in report.devices:
        kind = "simulated" if dev.simulated else "real"
        lines.append("")
        lines.append(f"{dev.role}: driver {dev.driver} ({kind}) -> {_MARK[dev.status].strip()}")
        for c in dev.checks:
            lines.append(f"  {_MARK[c.status]}  {c.message}")
            if c.hint:
                for i, hint_line in enumerate(c.hint.splitlines()):
                    lines.append(f"        {'try: ' if i == 0 else '     '}{hint_line}")
        if dev.stopped_early:
            lines.append("        (checks of this device stop at the first failure)")
    lines.append("")
    summary = ", ".join(f"{d.role} {_MARK[d.status].strip()}" for d in report.devices)
    lines.append(f"summary: {summary} -> exit {report.exit_code}")
    return "\n".join(lines)
