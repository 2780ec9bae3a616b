"""Scripted patient motion: pure ``t -> displacement / pose`` functions of the seed and the config.

Evaluating a script at a time never changes what it returns at another time, so a procedure
reproduces exactly from a seed whatever order (or rate) the devices sample the world in.

Breathing follows Lujan et al. 1999 (Med. Phys. 26(5)): ``z(t) = z0 - b cos^(2n)(pi t / tau - phi)``;
here written as the displacement from end-exhale, ``d = A cos^(2n)(pi (s - 1/2))`` over the
active part ``s in [0, 1]`` of each cycle, followed by an explicit end-exhale dwell, with the
amplitude and period of every cycle varied by the irregularity (seeded per cycle).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.config.simulation import (
    BreathHoldConfig,
    BreathingConfig,
    DriftConfig,
    ShiftConfig,
    SimulationConfig,
    TremorConfig,
)
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]


def stream_rng(seed: int, name: str, *index: int) -> np.random.Generator:
    """An independent, reproducible random stream for (seed, name, index...)."""
    return np.random.default_rng([seed, zlib.crc32(name.encode()), *index])


def smoothstep(x: float) -> float:
    """0 for x <= 0, 1 for x >= 1, C1-smooth in between."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    return x * x * (3.0 - 2.0 * x)


class BreathingScript:
    """Breathing displacement along the configured direction (mm from end-exhale)."""

    def __init__(self, cfg: BreathingConfig, seed: int) -> None:
        self.cfg = cfg
        self.seed = seed
        d = np.asarray(cfg.direction, dtype=np.float64)
        self.direction: FloatArray = d / np.linalg.norm(d)
        self._starts: list[float] = [0.0]
        self._periods: list[float] = []
        self._amplitudes: list[float] = []

    def _cycle(self, k: int) -> tuple[float, float, float]:
        while len(self._periods) <= k:
            i = len(self._periods)
            u = stream_rng(self.seed, "breathing", i).uniform(-1.0, 1.0, size=2)
            irr = self.cfg.irregularity
            self._periods.append(self.cfg.period_s * (1.0 + irr * float(u[0])))
            self._amplitudes.append(self.cfg.amplitude_mm * (1.0 + irr * float(u[1])))
            self._starts.append(self._starts[-1] + self._periods[-1])
        return self._starts[k], self._periods[k], self._amplitudes[k]

    def amplitude_at(self, t_s: float) -> float:
        """The current cycle's amplitude (mm): a hold level is relative to it."""
        return self._cycle(self._index(t_s))[2]

    def _index(self, t_s: float) -> int:
        t = max(t_s, 0.0)
        k = max(int(t // self.cfg.period_s) - 1, 0)
        while True:
            start, period, _ = self._cycle(k)
            if t < start:
                k -= 1
            elif t >= start + period:
                k += 1
            else:
                return k

    def displacement_mm(self, t_s: float) -> float:
        """Scalar displacement from end-exhale at ``t_s`` (0 before t = 0 and when disabled)."""
        if not self.cfg.enabled or self.cfg.amplitude_mm == 0.0 or t_s <= 0.0:
            return 0.0
        k = self._index(t_s)
        start, period, amp = self._cycle(k)
        active = period - self.cfg.end_exhale_dwell_s
        s = (t_s - start) / active
        if s >= 1.0:
            return 0.0  # end-exhale dwell
        return amp * math.cos(math.pi * (s - 0.5)) ** (2 * self.cfg.shape_n)


class IrregularityScript:
    """What makes breathing irregular beyond the per-cycle spread: a slow baseline wander of the
    end-exhale position and occasional coughs, both along the breathing direction (mm).

    The wander is two sinusoids (periods ``baseline_period_s`` and 0.37 times it, weights 0.6/0.4,
    seeded phases) scaled to ``baseline_wander_mm``. Coughs are a Poisson process of
    ``cough_rate_per_min``: each minute of world time draws its own count and times (seeded per
    minute, so a time's value never depends on what was sampled before); a cough is a
    ``sin^2`` pulse of ``cough_amplitude_mm`` over ``cough_duration_s``.
    """

    def __init__(self, cfg: BreathingConfig, seed: int) -> None:
        self.cfg = cfg
        self.seed = seed
        self._phases: FloatArray = stream_rng(seed, "baseline_wander").uniform(0.0, 2.0 * math.pi, size=2)
        self._coughs: dict[int, FloatArray] = {}

    def _cough_starts(self, minute: int) -> FloatArray:
        if minute not in self._coughs:
            rng = stream_rng(self.seed, "cough", minute)
            n = int(rng.poisson(self.cfg.cough_rate_per_min))
            self._coughs[minute] = np.sort(60.0 * minute + 60.0 * rng.uniform(0.0, 1.0, size=n))
        return self._coughs[minute]

    def offset_mm(self, t_s: float) -> float:
        """Displacement along the breathing direction at ``t_s`` (0 before t = 0 and when off)."""
        c = self.cfg
        if t_s <= 0.0 or not c.enabled:
            return 0.0
        out = 0.0
        if c.baseline_wander_mm > 0.0:
            w = 2.0 * math.pi * t_s / c.baseline_period_s
            out += c.baseline_wander_mm * (0.6 * math.sin(w + self._phases[0])
                                           + 0.4 * math.sin(w / 0.37 + self._phases[1]))
        if c.cough_rate_per_min > 0.0 and c.cough_amplitude_mm > 0.0:
            minute = int(t_s // 60.0)
            for m in (minute - 1, minute):
                if m < 0:
                    continue
                for start in self._cough_starts(m):
                    s = (t_s - float(start)) / c.cough_duration_s
                    if 0.0 <= s <= 1.0:
                        out += c.cough_amplitude_mm * math.sin(math.pi * s) ** 2
        return out


def hold_weight(t_s: float, hold: BreathHoldConfig, ramp_s: float) -> float:
    """How far breathing is replaced by the hold level at ``t_s`` (0..1, eased at both ends)."""
    end = hold.start_s + hold.duration_s
    if ramp_s <= 0.0:
        return 1.0 if hold.start_s <= t_s < end else 0.0
    return min(smoothstep((t_s - hold.start_s) / ramp_s), 1.0 - smoothstep((t_s - end) / ramp_s))


def drift_mm(t_s: float, cfg: DriftConfig) -> FloatArray:
    """Linear drift, clamped to ``max_mm`` in magnitude."""
    d = np.asarray(cfg.velocity_mm_s, dtype=np.float64) * max(t_s, 0.0)
    n = float(np.linalg.norm(d))
    return d * (cfg.max_mm / n) if n > cfg.max_mm else d


class TremorScript:
    """Three sinusoids per axis at 0.8, 1.0, 1.25 x ``frequency_hz`` with seeded phases."""

    def __init__(self, cfg: TremorConfig, seed: int) -> None:
        self.cfg = cfg
        rng = stream_rng(seed, "tremor")
        self._phases: FloatArray = rng.uniform(0.0, 2.0 * math.pi, size=(3, 3))
        self._freqs: FloatArray = cfg.frequency_hz * np.array([0.8, 1.0, 1.25])

    def offset_mm(self, t_s: float) -> FloatArray:
        if self.cfg.amplitude_mm == 0.0:
            return np.zeros(3)
        waves = np.sin(2.0 * math.pi * self._freqs[None, :] * t_s + self._phases)  # (axis, wave)
        out: FloatArray = self.cfg.amplitude_mm / math.sqrt(3.0) * waves.sum(axis=1)
        return out


def shift_transform(t_s: float, shifts: Sequence[ShiftConfig]) -> RigidTransform:
    """The composition of every (ramped) sudden shift reached by ``t_s``, about the image origin."""
    T = RigidTransform.identity()
    for sh in shifts:
        if t_s < sh.at_s:
            continue
        f = 1.0 if sh.ramp_s <= 0.0 else smoothstep((t_s - sh.at_s) / sh.ramp_s)
        step = RigidTransform.from_rotvec(np.asarray(sh.rotvec_rad) * f, np.asarray(sh.translation_mm) * f)
        T = step @ T
    return T


@dataclass(frozen=True)
class MotionSample:
    """The patient's motion at one time: ``T_image0_from_image`` maps phantom (CT) coordinates to
    where they are now, in the rest pose's image frame; plus the parts, for tests and logs."""

    T_image0_from_image: RigidTransform
    breathing_mm: float
    hold_weight: float


class PatientMotion:
    """All scripted motion of the phantom. ``holds`` may grow at run time (requested holds)."""

    def __init__(self, sim: SimulationConfig) -> None:
        self.sim = sim
        self.breathing = BreathingScript(sim.breathing, sim.seed)
        self.tremor = TremorScript(sim.tremor, sim.seed)
        self.irregular = IrregularityScript(sim.breathing, sim.seed)
        self.holds: list[BreathHoldConfig] = list(sim.breath_holds)

    def hold_at(self, t_s: float) -> tuple[float, int]:
        """(weight 0..1, index in ``holds``) of the breath-hold in force at ``t_s``: the heaviest,
        the first of equals; (0.0, -1) when none is."""
        best_w, best_i = 0.0, -1
        for i, h in enumerate(self.holds):
            w = hold_weight(t_s, h, self.sim.hold_ramp_s)
            if w > best_w:
                best_w, best_i = w, i
        return best_w, best_i

    def breathing_mm(self, t_s: float) -> tuple[float, float, float]:
        """(breathing displacement with holds, hold weight, that plus the baseline wander and
        coughs), mm along the breathing direction, at ``t_s``."""
        b = self.breathing.displacement_mm(t_s)
        w, i = self.hold_at(t_s)
        if w > 0.0:
            active = self.holds[i]
            b = (1.0 - w) * b + w * active.level * self.breathing.amplitude_at(active.start_s)
        return b, w, b + self.irregular.offset_mm(t_s)

    def rigid_offset_mm(self, t_s: float) -> FloatArray:
        """The rigid translation besides breathing: drift and tremor (image frame, mm)."""
        out: FloatArray = drift_mm(t_s, self.sim.drift) + self.tremor.offset_mm(t_s)
        return out

    def T_rigid(self, t_s: float) -> RigidTransform:
        """The deformable body's rigid part: shifts after drift and tremor (no breathing)."""
        T_offset = RigidTransform.from_translation(self.rigid_offset_mm(t_s))
        return shift_transform(t_s, self.sim.shifts) @ T_offset

    def sample(self, t_s: float) -> MotionSample:
        """The rigid body's motion at ``t_s``: breathing along its direction, drift, tremor, shifts."""
        b, w, b_total = self.breathing_mm(t_s)
        offset = (self.breathing.direction * b_total + drift_mm(t_s, self.sim.drift)
                  + self.tremor.offset_mm(t_s))
        T = shift_transform(t_s, self.sim.shifts) @ RigidTransform.from_translation(offset)
        return MotionSample(T, b, w)


class ModelSignal:
    """The body's breathing signal from the scripted breathing (:class:`PatientMotion`): its
    displacement with holds, wander and coughs over ``[simulation.breathing] amplitude_mm``
    (0 end-exhale, about 1 end-inhale; 0 when the amplitude is 0)."""

    def __init__(self, motion: PatientMotion) -> None:
        self.motion = motion
        self._amplitude_mm = motion.sim.breathing.amplitude_mm

    @property
    def period_s(self) -> float:
        return self.motion.sim.breathing.period_s

    def s(self, t_s: float) -> float:
        if self._amplitude_mm <= 0.0:
            return 0.0
        return self.motion.breathing_mm(t_s)[2] / self._amplitude_mm

    def hold(self, t_s: float) -> tuple[float, int]:
        return self.motion.hold_at(t_s)
