"""Field types shared by setup and driver config models: paths, vectors, transforms."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationInfo, model_validator

from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform

#: Every config model's settings. ``allow_inf_nan=False``: TOML has ``inf``/``nan`` literals, and an
#: infinite watchdog age or fault start would pass ``gt=0``/``ge=0`` and silently disable it.
STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

Vec3 = tuple[float, float, float]


def _resolve_path(value: Path, info: ValidationInfo) -> Path:
    """Resolve a relative path against the config file's directory (validation context
    ``config_dir``); absolute paths and ``~`` are kept (``~`` expanded)."""
    value = value.expanduser()
    ctx: Any = info.context
    if not value.is_absolute() and isinstance(ctx, dict) and ctx.get("config_dir") is not None:
        value = Path(ctx["config_dir"]) / value
    return value


#: A file path in a config: relative paths are resolved against the config file's directory.
ConfigPath = Annotated[Path, AfterValidator(_resolve_path)]


class TransformConfig(BaseModel):
    """A rigid transform in a config: ``translation_mm`` + ``rotvec_rad`` (axis * angle), or a
    4x4 homogeneous ``matrix`` (mm) — one or the other, not both."""

    model_config = STRICT

    translation_mm: Vec3 | None = Field(None, description="translation, mm")
    rotvec_rad: Vec3 | None = Field(None, description="rotation vector (axis * angle), rad")
    matrix: tuple[tuple[float, float, float, float], ...] | None = Field(
        None, description="4x4 homogeneous matrix, rows, mm")

    @model_validator(mode="after")
    def _one_form(self) -> TransformConfig:
        parts = self.translation_mm is not None or self.rotvec_rad is not None
        if self.matrix is not None and parts:
            raise ValueError("give either matrix or translation_mm/rotvec_rad, not both")
        if self.matrix is not None and len(self.matrix) != 4:
            raise ValueError(f"matrix must have 4 rows, has {len(self.matrix)}")
        try:
            self.as_transform()
        except GeometryError as exc:
            raise ValueError(str(exc)) from None
        return self

    def as_transform(self) -> RigidTransform:
        if self.matrix is not None:
            return RigidTransform.from_matrix(self.matrix)
        return RigidTransform.from_rotvec(
            self.rotvec_rad if self.rotvec_rad is not None else (0.0, 0.0, 0.0),
            self.translation_mm if self.translation_mm is not None else (0.0, 0.0, 0.0),
        )

    @classmethod
    def identity(cls) -> TransformConfig:
        return cls(translation_mm=(0.0, 0.0, 0.0), rotvec_rad=(0.0, 0.0, 0.0))
