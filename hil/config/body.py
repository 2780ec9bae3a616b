"""``[simulation.body]``: how the simulated patient's body moves (docs/config.md "The body").

``model = "rigid"`` (the default) is the simulator as it always was: skin markers, entry and
target move by one rigid transform (breathing along ``[simulation.breathing] direction``, drift,
shifts, tremor). ``model = "deformable"`` gives every skin point its own breathing displacement
(a thoracic and an abdominal component with their own amplitude, direction and phase, varying
smoothly over the skin) and the internal target its own trajectory (superior-inferior dominant,
with a phase lag and hysteresis against the skin and a per-breath-hold reproducibility error).
Drift, shifts and tremor stay rigid, on top.

The breathing signal (when each breath happens, holds, coughs, baseline wander) is still the one
of ``[simulation.breathing]``: its displacement divided by ``amplitude_mm`` is the normalised
breathing phase ``s(t)`` (0 at end-exhale, about 1 at end-inhale) that drives every component.
``[simulation.body.trace]`` replaces it (and, depending on the file, the skin field or the
target) by a recorded trace.

Image frame: x = patient's left, y = superior (cranial), z = anterior (up), mm.
"""

from __future__ import annotations

import math
import re
from typing import Literal

from pydantic import BaseModel, Field, model_validator

from hil.config.types import STRICT, ConfigPath, Vec3

_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


class SkinFieldConfig(BaseModel):
    """The skin's breathing displacement field (deformable model).

    A skin point at image-frame (x, y) moves by
    ``d = w_th(y) a_th(x, y) s(t - lag_th) u_th(x, y) + (1 - w_th(y)) a_ab(x, y) s(t - lag_ab) u_ab(x, y)``
    where ``w_th`` is a logistic blend from the abdominal to the thoracic region across
    ``boundary_y_mm`` (width ``transition_mm``), the amplitudes ``a`` vary by up to
    ``amplitude_variation`` (fraction) and the directions ``u`` turn by up to
    ``direction_variation_deg`` over the skin, both as smooth seeded fields of wavelength
    ``variation_wavelength_mm``.
    """

    model_config = STRICT

    thoracic_amplitude_mm: float = Field(
        4.0, ge=0, le=40, description="peak-to-peak skin displacement of the thoracic region, mm")
    abdominal_amplitude_mm: float = Field(
        9.0, ge=0, le=40, description="peak-to-peak skin displacement of the abdominal region, mm")
    thoracic_direction: Vec3 = Field(
        (0.0, 0.6, 1.0), description="thoracic displacement direction on inhale (image frame)")
    abdominal_direction: Vec3 = Field(
        (0.0, -0.1, 1.0), description="abdominal displacement direction on inhale (image frame)")
    thoracic_lag_s: float = Field(
        0.35, ge=-2, le=2, description="the thoracic component follows the breathing signal this late, s")
    abdominal_lag_s: float = Field(
        0.0, ge=-2, le=2, description="the abdominal component follows the breathing signal this late, s")
    boundary_y_mm: float = Field(
        10.0, ge=-500, le=500, description="image y of the thoraco-abdominal boundary (thorax above), mm")
    transition_mm: float = Field(
        40.0, gt=0, le=500, description="width of the logistic blend between the regions, mm")
    amplitude_variation: float = Field(
        0.45, ge=0, le=0.9, description="amplitude varies over the skin by up to this fraction")
    direction_variation_deg: float = Field(
        25.0, ge=0, le=60, description="direction turns over the skin by up to this angle, deg")
    variation_wavelength_mm: float = Field(
        140.0, gt=20, le=2000, description="spatial wavelength of the amplitude/direction variation, mm")

    @model_validator(mode="after")
    def _check(self) -> SkinFieldConfig:
        for name in ("thoracic_direction", "abdominal_direction"):
            if math.hypot(*getattr(self, name)) < 1e-9:
                raise ValueError(f"{name} must not be zero")
        return self


class TargetMotionConfig(BaseModel):
    """The internal target's own breathing trajectory (deformable model).

    ``p(t) = target + amplitude_mm s(t - lag_s) u + hysteresis_mm h(t) v + hold offset``:
    ``u`` is ``direction`` (superior-inferior dominant), ``v`` the unit vector of
    ``hysteresis_direction`` orthogonal to ``u``, and ``h(t) = (s(t - lag_s - q) - s(t - lag_s))``
    with ``q`` a quarter of the breathing period (negative on inhale, positive on exhale: the
    inhale and exhale paths differ along ``v``, Seppenwoolde et al. 2002). During breath-hold
    number k the target sits ``hold offset_k`` away from where the hold level alone would put it:
    a seeded draw with standard deviation ``hold_reproducibility_mm`` along ``u`` and 0.4 times
    that across.
    """

    model_config = STRICT

    amplitude_mm: float = Field(
        12.0, ge=0, le=50, description="peak-to-peak target displacement along direction, mm")
    direction: Vec3 = Field(
        (0.0, -1.0, 0.25), description="target displacement on inhale (image frame; -y = inferior)")
    lag_s: float = Field(
        0.2, ge=-2, le=2, description="the target follows the breathing signal this late, s")
    hysteresis_mm: float = Field(
        2.0, ge=0, le=10, description="separation of the inhale and exhale paths (about), mm")
    hysteresis_direction: Vec3 = Field(
        (0.0, 0.0, 1.0), description="the direction the two paths separate along (image frame)")
    hold_reproducibility_mm: float = Field(
        1.5, ge=0, le=10, description="SD of where each breath-hold leaves the target, along direction, mm")

    @model_validator(mode="after")
    def _check(self) -> TargetMotionConfig:
        u = self.direction
        if math.hypot(*u) < 1e-9:
            raise ValueError("direction must not be zero")
        v = self.hysteresis_direction
        nu, nv = math.hypot(*u), math.hypot(*v)
        if nv < 1e-9:
            raise ValueError("hysteresis_direction must not be zero")
        cos = abs(sum(a * b for a, b in zip(u, v, strict=True))) / (nu * nv)
        if cos > 0.99:
            raise ValueError("hysteresis_direction must not be parallel to direction")
        return self


class BodyTraceConfig(BaseModel):
    """``[simulation.body.trace]``: drive the deformable body from a recorded trace (docs/traces.md).

    A surrogate trace (1-D) replaces the breathing signal; a tumour trace (6-DoF or paired) drives
    the target directly and, through its own normalised motion (6-DoF) or its surrogate (paired),
    the skin; a points CSV drives the skin at the recorded points (interpolated over the skin
    between them by a thin-plate spline) and the target through the model from the points' mean
    normalised motion.
    """

    model_config = STRICT

    path: ConfigPath | None = Field(None, description="trace file or directory (relative to the config)")
    format: Literal["auto", "points-csv", "surrogate", "6dof", "paired"] = Field(
        "auto", description="the trace's format (auto: told from the file)")
    start_s: float | None = Field(
        None, ge=0, description="trace time at world time 0, s (default: a seeded end-exhale of the trace)")
    rate_hz: float = Field(
        50.0, gt=0, le=1000, description="the trace is resampled (linear) to this rate before use")
    points: dict[str, tuple[float, float]] = Field(
        default_factory=dict,
        description="points CSV: where each recorded point sits on the skin, image (x, y) mm")
    invert_surrogate: bool = Field(
        False, description="the surrogate falls on inhale (default: it rises)")

    @model_validator(mode="after")
    def _check(self) -> BodyTraceConfig:
        for name in self.points:
            if not _NAME.match(name):
                raise ValueError(f"points: {name!r} is not a point name ([A-Za-z0-9_-]+)")
        return self


class BodyConfig(BaseModel):
    """``[simulation.body]``: rigid (default) or deformable patient."""

    model_config = STRICT

    model: Literal["rigid", "deformable"] = Field(
        "rigid", description="rigid: one transform moves everything; deformable: skin field + target")
    skin: SkinFieldConfig = Field(SkinFieldConfig(), description="the skin displacement field")
    target: TargetMotionConfig = Field(TargetMotionConfig(), description="the internal target's motion")
    trace: BodyTraceConfig = Field(BodyTraceConfig(), description="a recorded trace driving the body")

    @model_validator(mode="after")
    def _check(self) -> BodyConfig:
        if self.trace.path is not None and self.model != "deformable":
            raise ValueError('trace.path needs model = "deformable"')
        return self
