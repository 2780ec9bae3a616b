"""The deformable patient: a skin displacement field and an internal target with its own motion.

Pure functions of the config, the seed, the breath-holds and (optionally) a recorded trace, like
every script of :mod:`drivers.sim.motion`: evaluating the body at a time never changes what it
returns at another time.

Model (``[simulation.body]``, :mod:`hil.config.body`; docs/config.md "The body"):

- the normalised breathing signal ``s(t)`` (0 end-exhale, ~1 end-inhale) comes from
  ``[simulation.breathing]`` (Lujan et al. 1999, with holds, baseline wander and coughs) or from a
  recorded trace (:mod:`drivers.sim.body_trace`);
- a skin point at image (x, y) moves by a thoracic and an abdominal component, each ``s`` taken at
  its own lag, with amplitude and direction varying smoothly over the skin
  (:class:`SkinField`); recorded skin points replace the field by a thin-plate spline through
  their displacements (:class:`drivers.sim.body_trace.TraceDrive`);
- the target moves by ``amplitude s(t - lag) u + hysteresis h(t) v`` plus, during breath-hold
  number k, a seeded reproducibility offset (:class:`TargetMotion`), or by a recorded tumour trace;
- drift, sudden shifts and tremor stay one rigid transform applied on top (``T_rigid``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.sim.motion import ModelSignal, PatientMotion, stream_rng
from hil.config.body import BodyConfig, SkinFieldConfig, TargetMotionConfig
from hil.config.simulation import SimulationConfig
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]

#: finite-difference step for the deformed skin's normals, mm
NORMAL_STEP_MM = 0.5


def skin_point(x_mm: float, y_mm: float, radius_mm: float) -> tuple[FloatArray, FloatArray]:
    """Point on the cylinder skin (axis along y, top line z = 0) above (x, y), and its outward
    unit normal (image frame, mm)."""
    z = math.sqrt(radius_mm**2 - x_mm**2) - radius_mm
    n = np.array([x_mm, 0.0, z + radius_mm]) / radius_mm
    return np.array([x_mm, y_mm, z]), n


def skin_points(xy_mm: FloatArray, radius_mm: float) -> FloatArray:
    """Skin points (M, 3) above image (x, y) positions (M, 2)."""
    x = xy_mm[:, 0]
    z = np.sqrt(radius_mm**2 - x**2) - radius_mm
    return np.column_stack([x, xy_mm[:, 1], z])


def _unit(v: tuple[float, float, float] | FloatArray) -> FloatArray:
    a = np.asarray(v, dtype=np.float64)
    out: FloatArray = a / np.linalg.norm(a)
    return out


class SmoothField:
    """A smooth seeded scalar field on the skin's (x, y), values in [-1, 1]: the mean of three
    plane waves of wavelength ``wavelength_mm`` with seeded directions and phases."""

    def __init__(self, seed: int, name: str, wavelength_mm: float) -> None:
        rng = stream_rng(seed, f"skin_field/{name}")
        angles = rng.uniform(0.0, math.pi, size=3)
        k = 2.0 * math.pi / wavelength_mm
        self._k: FloatArray = k * np.column_stack([np.cos(angles), np.sin(angles)])
        self._phase: FloatArray = rng.uniform(0.0, 2.0 * math.pi, size=3)

    def __call__(self, xy_mm: FloatArray) -> FloatArray:
        out: FloatArray = np.cos(xy_mm @ self._k.T + self._phase).mean(axis=1)
        return out


@dataclass(frozen=True)
class FieldBasis:
    """The skin field at fixed skin positions: ``d(t) = s_th(t) thoracic + s_ab(t) abdominal``
    with (M, 3) displacement vectors per unit of the normalised breathing signal, mm."""

    thoracic_mm: FloatArray
    abdominal_mm: FloatArray


class SkinField:
    """The model's skin displacement field (:class:`hil.config.body.SkinFieldConfig`)."""

    def __init__(self, cfg: SkinFieldConfig, seed: int) -> None:
        self.cfg = cfg
        lam = cfg.variation_wavelength_mm
        self._amp = {r: SmoothField(seed, f"{r}_amplitude", lam) for r in ("thoracic", "abdominal")}
        self._tilt = {r: (SmoothField(seed, f"{r}_tilt_x", lam), SmoothField(seed, f"{r}_tilt_y", lam))
                      for r in ("thoracic", "abdominal")}

    def thoracic_weight(self, y_mm: FloatArray) -> FloatArray:
        """Logistic blend: 1 deep in the thorax (above the boundary), 0 in the abdomen."""
        z = (y_mm - self.cfg.boundary_y_mm) / (self.cfg.transition_mm / 4.0)
        out: FloatArray = 1.0 / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))
        return out

    def _component(self, region: str, xy_mm: FloatArray, amplitude_mm: float,
                   direction: tuple[float, float, float]) -> FloatArray:
        c = self.cfg
        amp = amplitude_mm * (1.0 + c.amplitude_variation * self._amp[region](xy_mm))
        max_rad = math.radians(c.direction_variation_deg)
        gx, gy = self._tilt[region]
        rotvecs = np.column_stack([max_rad * gx(xy_mm), max_rad * gy(xy_mm), np.zeros(len(xy_mm))])
        u = _unit(direction)
        dirs = np.array([RigidTransform.from_rotvec(r).R @ u for r in rotvecs]).reshape(-1, 3)
        out: FloatArray = amp[:, None] * dirs
        return out

    def basis(self, xy_mm: FloatArray) -> FieldBasis:
        """Displacement per unit breathing signal at skin positions ``xy_mm`` (M, 2), mm."""
        w = self.thoracic_weight(xy_mm[:, 1])
        c = self.cfg
        th = self._component("thoracic", xy_mm, c.thoracic_amplitude_mm, c.thoracic_direction)
        ab = self._component("abdominal", xy_mm, c.abdominal_amplitude_mm, c.abdominal_direction)
        return FieldBasis(thoracic_mm=w[:, None] * th, abdominal_mm=(1.0 - w)[:, None] * ab)


class BreathingSignal(Protocol):
    """What drives the body: the normalised breathing signal and the hold in force."""

    @property
    def period_s(self) -> float:
        """The typical breathing period, s (sets the hysteresis quarter-period)."""
        ...

    def s(self, t_s: float) -> float:
        """Normalised breathing signal at world time ``t_s`` (0 end-exhale, ~1 end-inhale),
        holds included."""
        ...

    def hold(self, t_s: float) -> tuple[float, int]:
        """(weight 0..1 of the breath-hold in force at ``t_s``, its index; -1 when none)."""
        ...


class TargetMotion:
    """The model's internal target displacement (:class:`hil.config.body.TargetMotionConfig`)."""

    def __init__(self, cfg: TargetMotionConfig, seed: int) -> None:
        self.cfg = cfg
        self.seed = seed
        self.u: FloatArray = _unit(cfg.direction)
        v = np.asarray(cfg.hysteresis_direction, dtype=np.float64)
        v = v - (v @ self.u) * self.u
        self.v: FloatArray = v / np.linalg.norm(v)
        self.w: FloatArray = np.cross(self.u, self.v)
        self._holds: dict[int, FloatArray] = {}

    def hold_offset_mm(self, index: int) -> FloatArray:
        """Where breath-hold ``index`` leaves the target, against the hold level alone (mm)."""
        if index not in self._holds:
            sd = self.cfg.hold_reproducibility_mm
            z = stream_rng(self.seed, "hold_reproducibility", index).normal(size=3)
            self._holds[index] = sd * (z[0] * self.u + 0.4 * z[1] * self.v + 0.4 * z[2] * self.w)
        return self._holds[index]

    def displacement_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray:
        """Target displacement from its planned (end-exhale) position at ``t_s``, image frame, mm."""
        c = self.cfg
        s_lag = signal.s(t_s - c.lag_s)
        q = 0.25 * signal.period_s
        h = signal.s(t_s - c.lag_s - q) - s_lag
        d: FloatArray = c.amplitude_mm * s_lag * self.u + 0.5 * c.hysteresis_mm * h * self.v
        return d + self.hold_part_mm(signal, t_s)

    def hold_part_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray:
        """The breath-hold reproducibility part of the displacement at ``t_s`` (mm)."""
        weight, index = signal.hold(t_s)
        if index < 0 or weight <= 0.0:
            return np.zeros(3)
        out: FloatArray = weight * self.hold_offset_mm(index)
        return out


@dataclass(frozen=True)
class BodyQuery:
    """Fixed skin positions the world asks about: the markers (with finite-difference neighbours
    for their normals) and the entry. Skin points (M, 3) at rest, image frame, mm."""

    xy_mm: FloatArray          # (M, 2): markers, markers + dx, markers + dy, entry
    rest_mm: FloatArray        # (M, 3)
    n_markers: int

    @classmethod
    def for_phantom(cls, markers_mm: FloatArray, entry_mm: FloatArray) -> BodyQuery:
        xy = markers_mm[:, :2]
        dx = xy + np.array([NORMAL_STEP_MM, 0.0])
        dy = xy + np.array([0.0, NORMAL_STEP_MM])
        all_xy = np.vstack([xy, dx, dy, entry_mm[None, :2]])
        rest = np.vstack([markers_mm, np.zeros((2 * len(xy), 3)), entry_mm[None, :]])
        return cls(xy_mm=all_xy, rest_mm=rest, n_markers=len(xy))

    def with_rest(self, radius_mm: float) -> BodyQuery:
        """The neighbours' rest points on the skin (the markers and entry keep theirs)."""
        rest = self.rest_mm.copy()
        n = self.n_markers
        rest[n:3 * n] = skin_points(self.xy_mm[n:3 * n], radius_mm)
        return BodyQuery(xy_mm=self.xy_mm, rest_mm=rest, n_markers=n)


@dataclass(frozen=True)
class BodyState:
    """The body at one time, before the rigid part (image frame at rest, mm): skin markers and
    their outward normals, the entry, the target."""

    markers_mm: FloatArray
    normals: FloatArray
    entry_mm: FloatArray
    target_mm: FloatArray


def normals_from_neighbours(points: FloatArray, dx_points: FloatArray, dy_points: FloatArray) -> FloatArray:
    """Outward unit normals of the deformed skin from each point and its deformed neighbours one
    step along +x and +y (``(P_x - P) x (P_y - P)``, which points anterior on the skin)."""
    n = np.cross(dx_points - points, dy_points - points)
    out: FloatArray = n / np.linalg.norm(n, axis=1, keepdims=True)
    return out


class SkinDrive(Protocol):
    """Skin displacement at the query positions (M, 3), mm, at world time ``t_s``."""

    def skin_displacement_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray: ...


class ModelSkinDrive:
    """The model's skin field evaluated at a fixed query: two lagged components."""

    def __init__(self, field: SkinField, query: BodyQuery) -> None:
        self.cfg = field.cfg
        self.basis = field.basis(query.xy_mm)

    def skin_displacement_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray:
        s_th = signal.s(t_s - self.cfg.thoracic_lag_s)
        s_ab = signal.s(t_s - self.cfg.abdominal_lag_s)
        out: FloatArray = s_th * self.basis.thoracic_mm + s_ab * self.basis.abdominal_mm
        return out


class TargetDrive(Protocol):
    """Target displacement (3,), mm, at world time ``t_s``."""

    def target_displacement_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray: ...


class ModelTargetDrive:
    def __init__(self, motion: TargetMotion) -> None:
        self.motion = motion

    def target_displacement_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray:
        return self.motion.displacement_mm(signal, t_s)


class DeformableBody:
    """The whole deformable body at the phantom's markers and entry.

    Args:
        cfg: ``[simulation.body]``.
        seed: the world's seed.
        markers_mm, entry_mm, target_mm: the phantom at rest (image frame, mm).
        radius_mm: the skin cylinder's radius.
        signal: the breathing signal.
        skin, target: what drives them (default: the model).
    """

    def __init__(self, cfg: BodyConfig, seed: int, markers_mm: FloatArray, entry_mm: FloatArray,
                 target_mm: FloatArray, radius_mm: float, signal: BreathingSignal,
                 skin: SkinDrive | None = None, target: TargetDrive | None = None) -> None:
        self.cfg = cfg
        self.signal = signal
        self.query = BodyQuery.for_phantom(markers_mm, entry_mm).with_rest(radius_mm)
        self.target_rest_mm = np.asarray(target_mm, dtype=np.float64)
        self.target_motion = TargetMotion(cfg.target, seed)
        self.skin: SkinDrive = skin or ModelSkinDrive(SkinField(cfg.skin, seed), self.query)
        self.target: TargetDrive = target or ModelTargetDrive(self.target_motion)

    def state(self, t_s: float) -> BodyState:
        """The body at world time ``t_s``, before the rigid part (image frame, mm)."""
        q, n = self.query, self.query.n_markers
        moved = q.rest_mm + self.skin.skin_displacement_mm(self.signal, t_s)
        markers = moved[:n]
        normals = normals_from_neighbours(markers, moved[n:2 * n], moved[2 * n:3 * n])
        return BodyState(markers_mm=markers, normals=normals, entry_mm=moved[-1],
                         target_mm=self.target_rest_mm + self.target.target_displacement_mm(self.signal, t_s))


class BodyPhantom(Protocol):
    """What the body needs of the phantom (``drivers.sim.world.Phantom``): rest positions, mm."""

    @property
    def markers_mm(self) -> FloatArray: ...

    @property
    def entry_mm(self) -> FloatArray: ...

    @property
    def target_mm(self) -> FloatArray: ...


def model_body(sim: SimulationConfig, phantom: BodyPhantom, motion: PatientMotion) -> DeformableBody:
    """The deformable body driven by the model and the scripted breathing."""
    return DeformableBody(sim.body, sim.seed, phantom.markers_mm, phantom.entry_mm, phantom.target_mm,
                          sim.patient.torso_radius_mm, ModelSignal(motion))


def body_from_config(sim: SimulationConfig, phantom: BodyPhantom,
                     motion: PatientMotion) -> DeformableBody | None:
    """The world's body: None for the rigid model (``[simulation.body] model = "rigid"``), the
    model, or the model driven by the configured trace (:mod:`drivers.sim.body_trace`, imported
    only then)."""
    if sim.body.model == "rigid":
        return None
    if sim.body.trace.path is None:
        return model_body(sim, phantom, motion)
    from drivers.sim.body_trace import traced_body

    return traced_body(sim, phantom, motion)
