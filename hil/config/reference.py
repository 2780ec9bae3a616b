"""Generate the key reference of ``docs/config.md`` from the models (types, defaults, meaning).

``python -m hil.config.reference`` prints the markdown tables; ``--update docs/config.md``
rewrites what follows the marker comment in the document (the introduction above it is
hand-written). Driver sections come from the registry, so a
plugin's driver is documented the same way as a built-in one.
"""

from __future__ import annotations

import json
import re
from typing import Any

from pydantic import BaseModel

from hil.config.body import BodyConfig, BodyTraceConfig, SkinFieldConfig, TargetMotionConfig
from hil.config.faults import FaultChannelConfig, FaultSpec
from hil.config.setup import (
    CalibrationConfig,
    FramesConfig,
    PerceptionConfig,
    SafetyConfig,
    ServoConfig,
    SetupConfig,
)
from hil.config.simulation import (
    BreathHoldConfig,
    BreathingConfig,
    DriftConfig,
    PatientConfig,
    RigErrorsConfig,
    ShiftConfig,
    SimulationConfig,
    TremorConfig,
)
from hil.config.types import TransformConfig
from hil.controller.config import LockConfig, NeedleCheckConfig, ProcedureConfig
from hil.log import configure_logging
from hil.rigcal.config import RigCalibrationConfig, TemporalConfig
from plugins.registry import DriverRegistry


def _type_name(annotation: Any) -> str:
    text = annotation.__name__ if isinstance(annotation, type) else str(annotation)
    for prefix in ("typing.", "hil.config.types.", "hil.config.faults.", "pathlib."):
        text = text.replace(prefix, "")
    text = re.sub(r"Annotated\[Path, AfterValidator\(func=<function _resolve_path at 0x[0-9a-f]+>\)\]",
                  "ConfigPath", text)
    return text.replace("|", "\\|")


def _default(field: Any) -> str:
    if field.is_required():
        return "**required**"
    value = field.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        dumped = value.model_dump(mode="json", exclude_none=True)
        if len(json.dumps(dumped)) > 120:
            return "see its table"
        value = dumped
    return "`" + json.dumps(value, default=str) + "`"


def model_table(title: str, model: type[BaseModel]) -> str:
    """One markdown table: key, type, default, meaning."""
    doc = " ".join((model.__doc__ or "").strip().split("\n\n")[0].split())
    lines = [f"### `{title}`", "", doc, "", "| key | type | default | meaning |", "|---|---|---|---|"]
    for name, field in model.model_fields.items():
        meaning = (field.description or "").replace("|", "/")
        lines.append(f"| `{name}` | {_type_name(field.annotation)} | {_default(field)} | {meaning} |")
    return "\n".join(lines) + "\n"


def _nested(model: type[BaseModel]) -> list[tuple[str, type[BaseModel]]]:
    out = []
    for name, field in model.model_fields.items():
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out.append((name, ann))
    return out


def config_reference_markdown(registry: DriverRegistry) -> str:
    """Every table of the reference, in document order."""
    parts = [
        model_table("top level", SetupConfig),
        model_table("[safety]", SafetyConfig),
        model_table("[frames]", FramesConfig),
        model_table("[calibration]", CalibrationConfig),
        model_table("transform value (any T_… key)", TransformConfig),
        model_table("[simulation]", SimulationConfig),
        model_table("[simulation.patient]", PatientConfig),
        model_table("[simulation.breathing]", BreathingConfig),
        model_table("[simulation.drift]", DriftConfig),
        model_table("[[simulation.shifts]]", ShiftConfig),
        model_table("[simulation.tremor]", TremorConfig),
        model_table("[[simulation.breath_holds]]", BreathHoldConfig),
        model_table("[simulation.rig_errors]", RigErrorsConfig),
        model_table("[simulation.body]", BodyConfig),
        model_table("[simulation.body.skin]", SkinFieldConfig),
        model_table("[simulation.body.target]", TargetMotionConfig),
        model_table("[simulation.body.trace]", BodyTraceConfig),
        model_table("[[faults]]", FaultSpec),
        model_table("[fault_channel]", FaultChannelConfig),
        model_table("[servo]", ServoConfig),
        model_table("[perception]", PerceptionConfig),
    ]
    for d in registry.drivers():
        parts.append(model_table(f'[{d.kind}] driver = "{d.name}" ({d.origin})', d.config_model))
        for name, sub in _nested(d.config_model):
            if sub is not TransformConfig:
                parts.append(model_table(f"[{d.kind}.{name}] ({d.name})", sub))
        if d.kind == "tracker" and d.name == "sim":
            sensors = d.config_model.model_fields.get("sensors")
            args = getattr(sensors.annotation, "__args__", ()) if sensors is not None else ()
            for a in args:
                if isinstance(a, type) and issubclass(a, BaseModel):
                    parts.append(model_table("[[tracker.sensors]] (sim)", a))
    parts.append(model_table("[procedure]", ProcedureConfig))
    for name, sub in _nested(ProcedureConfig):
        parts.append(model_table(f"[procedure.{name}]", sub))
        if sub is LockConfig:  # optional (absent = off), so not found by _nested
            parts.append(model_table("[procedure.lock.needle_check]", NeedleCheckConfig))
    parts.append(model_table("[rig_calibration]", RigCalibrationConfig))
    parts.append(model_table("[rig_calibration.temporal]", TemporalConfig))
    return "\n".join(parts)


MARKER = "<!-- generated below by hil.config.reference; do not edit by hand -->"


def update_document(text: str, generated: str) -> str:
    """``text`` up to and including :data:`MARKER`, then ``generated``.

    Raises:
        ValueError: the marker is missing.
    """
    head, sep, _ = text.partition(MARKER)
    if not sep:
        raise ValueError(f"marker {MARKER!r} not found")
    return f"{head}{MARKER}\n\n{generated.rstrip()}\n"


def main(argv: list[str] | None = None) -> int:
    """Print the reference, or with ``--update FILE`` rewrite the generated part of FILE."""
    import argparse
    from pathlib import Path

    from plugins.manager import default_registry

    parser = argparse.ArgumentParser(prog="python -m hil.config.reference")
    parser.add_argument("--update", metavar="FILE", help="rewrite the generated part of FILE")
    args = parser.parse_args(argv)
    configure_logging(level="warning")
    generated = config_reference_markdown(default_registry())
    if args.update is None:
        print(generated)
        return 0
    path = Path(args.update)
    path.write_text(update_document(path.read_text(encoding="utf-8"), generated), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
