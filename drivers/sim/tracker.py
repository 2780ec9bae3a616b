"""Simulated magnetic tracker: sensor poses from the simulated world, with noise and distortion.

Samples exist at ``t0 + k / update_rate_hz``; :meth:`SimTracker.latest` returns the newest one
(computed on demand, cached). Sensors are attached to the patient (moving with the phantom's rigid
part), the target (moving with the internal target: an EM-tracked marker placed at the tumour;
``T_target_from_sensor`` is oriented as the CT, at the target), the robot flange, or fixed in the
transmitter frame. Field distortion is a smooth radial error
``distortion_mm_per_m2 * r^2`` (r = distance from the transmitter, m), as metal near the field
would give; it also raises the quality figure. Sensors beyond ``volume_radius_mm`` are missing.

With ``[simulation.rig_errors] tracker_clock_offset_ms`` the samples are stamped that much after
(or, negative, before) the time they were measured at, and a sample is available once both its
measurement and its stamp are not in the future.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field, field_validator

from drivers.interfaces.tracker import PoseTracker, TrackerSample
from drivers.sim.world import SimWorld
from hil.clock import Clock
from hil.config.types import STRICT, TransformConfig
from hil.geometry.transform import RigidTransform
from plugins.registry import DriverContext


class SimSensorConfig(BaseModel):
    """One sensor: its name and where it is fixed (``T_<attached_to>_from_sensor``)."""

    model_config = STRICT

    name: str = Field(min_length=1)
    attached_to: Literal["patient", "target", "flange", "transmitter"] = Field(
        "patient", description="patient (its rigid part), target (the internal target, oriented as the "
                               "CT), flange, or transmitter (fixed)")
    T_attached_from_sensor: TransformConfig = TransformConfig.identity()


class SimTrackerConfig(BaseModel):
    """``[tracker] driver = "sim"``."""

    model_config = STRICT

    driver: Literal["sim"]
    update_rate_hz: float = Field(40.0, gt=0, le=1000, description="samples per second")
    sensors: tuple[SimSensorConfig, ...] = Field(
        (SimSensorConfig(name="reference", T_attached_from_sensor=TransformConfig(
            translation_mm=(-40.0, 60.0, -2.0), rotvec_rad=(0.0, 0.0, 0.0))),),
        description="sensors and where they are attached")
    position_noise_mm: float = Field(0.1, ge=0, description="sigma per axis")
    rotation_noise_rad: float = Field(0.002, ge=0, description="sigma per axis")
    distortion_mm_per_m2: float = Field(0.0, ge=0, description="radial field distortion coefficient")
    volume_radius_mm: float = Field(660.0, gt=0, description="sensors farther away are missing")

    @field_validator("sensors")
    @classmethod
    def _unique(cls, v: tuple[SimSensorConfig, ...]) -> tuple[SimSensorConfig, ...]:
        names = [s.name for s in v]
        if len(set(names)) != len(names) or not names:
            raise ValueError(f"sensor names must be unique and at least one, got {names}")
        return v


class SimTracker(PoseTracker):
    """Sensor poses ``T_tracker_from_sensor`` of the simulated world."""

    def __init__(self, name: str, cfg: SimTrackerConfig, clock: Clock, world: SimWorld) -> None:
        super().__init__(name)
        self.cfg = cfg
        self.clock = clock
        self.world = world
        self._attach = [s.T_attached_from_sensor.as_transform() for s in cfg.sensors]
        self._period_ns = round(1e9 / cfg.update_rate_hz)
        self._stamp_offset_ns = round(world.rig_errors.tracker_clock_offset_ms * 1e6)
        self._t0_ns = 0
        self._cache: tuple[int, dict[str, TrackerSample]] | None = None

    def _open(self) -> None:
        self._t0_ns = self.clock.now_ns()
        self._cache = None

    def _close(self) -> None:
        pass

    @property
    def sensors(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.cfg.sensors)

    def true_pose(self, sensor_index: int, t_ns: int) -> RigidTransform | None:
        """Ground truth ``T_tracker_from_sensor`` (None when attached to an absent flange)."""
        s = self.cfg.sensors[sensor_index]
        w = self.world
        T_tracker_from_optical = w.T_optical_from_tracker.inverse()
        if s.attached_to == "transmitter":
            return self._attach[sensor_index]
        if s.attached_to == "patient":
            T_opt = w.T_optical_from_image(t_ns)
        elif s.attached_to == "target":   # at the target, turned as the patient's rigid part
            T_opt = RigidTransform(w.T_optical_from_image(t_ns).R, w.target_optical(t_ns))
        else:
            T_flange = w.T_optical_from_flange(t_ns)
            if T_flange is None:
                return None
            T_opt = T_flange
        return T_tracker_from_optical @ T_opt @ self._attach[sensor_index]

    def _sample(self, k: int) -> dict[str, TrackerSample]:
        t_true = self._t0_ns + k * self._period_ns
        t = t_true + self._stamp_offset_ns  # the stamp
        rng = self.world.rng("tracker", k)
        out: dict[str, TrackerSample] = {}
        for i, s in enumerate(self.cfg.sensors):
            noise = rng.normal(size=6)
            T = self.true_pose(i, t_true)
            if T is None:
                out[s.name] = TrackerSample(s.name, None, None, t, k, missing=True, flags=("not_attached",))
                continue
            r_mm = float(np.linalg.norm(T.t))
            if r_mm > self.cfg.volume_radius_mm:
                out[s.name] = TrackerSample(s.name, None, None, t, k, missing=True, flags=("out_of_volume",))
                continue
            dist = self.cfg.distortion_mm_per_m2 * (r_mm / 1000.0) ** 2
            radial = T.t / r_mm if r_mm > 0 else np.zeros(3)
            p = T.t + radial * dist + noise[:3] * self.cfg.position_noise_mm
            R = RigidTransform.from_rotvec(noise[3:] * self.cfg.rotation_noise_rad).R @ T.R
            quality = math.sqrt(3.0) * self.cfg.position_noise_mm + dist
            out[s.name] = TrackerSample(s.name, RigidTransform(R, p), quality, t, k)
        return out

    def latest(self) -> dict[str, TrackerSample]:
        self.require_active("latest")
        k = max((self.clock.now_ns() - max(self._stamp_offset_ns, 0) - self._t0_ns) // self._period_ns, 0)
        if self._cache is None or self._cache[0] != k:
            self._cache = (k, self._sample(k))
        return dict(self._cache[1])


def make_sim_tracker(config: SimTrackerConfig, ctx: DriverContext) -> SimTracker:
    """Factory registered as tracker driver ``sim`` (needs the simulated world)."""
    if not isinstance(ctx.world, SimWorld):
        raise TypeError("the sim tracker needs the simulated world (DriverContext.world)")
    return SimTracker(ctx.role, config, ctx.clock, ctx.world)
