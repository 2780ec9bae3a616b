"""Command-line overrides of a loaded setup that more than one command offers (``hil run``,
``tools/bench accuracy``): a recorded trace driving the simulated patient."""

from __future__ import annotations

from pathlib import Path

from hil.config.body import BodyTraceConfig
from hil.config.setup import SetupConfig
from hil.errors import InputFileError

#: trace formats a command-line option may name (``auto``: told from the file)
TRACE_FORMATS: tuple[str, ...] = ("auto", "points-csv", "surrogate", "6dof", "paired")


def simulates_patient(setup: SetupConfig) -> bool:
    """Whether any device of the setup is simulated (so a simulated patient exists)."""
    return any(getattr(dev, "driver", None) == "sim" for dev in (setup.camera, setup.robot, setup.tracker))


def with_trace(setup: SetupConfig, path: str | Path, fmt: str = "auto") -> SetupConfig:
    """``setup`` with its simulated patient deformable and driven by the trace at ``path``
    (``[simulation.body] model = "deformable"``, ``[simulation.body.trace] path, format``); the
    other body keys (skin field, target, start, points) stay as configured.

    Raises:
        InputFileError: the setup simulates no patient, the file does not exist or the format is
            unknown. (The trace itself is read, and checked, when the simulated world is built.)
    """
    name = str(path)
    if not simulates_patient(setup):
        raise InputFileError(name, "--trace drives the simulated patient, and this setup simulates no device")
    if fmt not in TRACE_FORMATS:
        raise InputFileError(name, f"unknown trace format {fmt!r} (one of {', '.join(TRACE_FORMATS)})")
    p = Path(path)
    if not p.exists():
        raise InputFileError(name, "no such file or directory")
    body = setup.simulation.body
    trace = BodyTraceConfig.model_validate(
        {**body.trace.model_dump(), "path": p.resolve(), "format": fmt})
    sim = setup.simulation.model_copy(update={
        "body": body.model_copy(update={"model": "deformable", "trace": trace})})
    return setup.model_copy(update={"simulation": sim})
