"""The simulated planning 4D CT: the phantom's fiducials, entry and target at the phases of one breath.

A 4D CT sorts many breaths into phase bins; each bin is the body at that phase of an average
breath. Here the average breath is the body model's (``[simulation.body]``) driven by a regular
cycle of the scripted breathing's shape (``[simulation.breathing]`` period, end-exhale dwell and
``shape_n``; no irregularity, coughs, wander or holds), sampled at ``phases`` equal steps over one
period. The skin field and the target's motion are the world's own (same seed), so the lag and the
hysteresis of the target are in the phases as a CT would record them. Each phase's points carry
an isotropic localisation error (``noise_mm`` per axis, seeded: stream ``planning_ct``), as a CT's
voxels and segmentation do; the registered phase (end-exhale, the plan's own points) is exact, as
the bundled plans are.

The CT frame holds no rigid motion of the patient (drift, tremor, shifts are the world's, after
the CT). The skin entry of each phase is where the skin field moves it (a CT's skin surface shows
it); its error is drawn from its own stream (``planning_ct_entry``), so the fiducials' and the
target's are those of a 4D CT without it.

A body driven by a recorded trace (``[simulation.body.trace]``) has no model cycle; its CT is
sorted from the recording as a 4D CT is from the patient's breaths: the :data:`TRACE_CT_WINDOW_S`
of the trace before the procedure's start (before the trace's start it wraps to its end, as the
world does), cut into breaths at their end-exhales (the lowest signal between two inhales, an
inhale being the signal rising through 0.5 after it was under 0.3), each breath's body sampled at
the phase fractions ``k / phases`` and averaged over the breaths. The recorded target's lag and hysteresis
against the skin are then in the phases as the recording has them; the plan's period
(``phases_period_s``) is the breaths' mean length. Fewer than :data:`MIN_TRACE_BREATHS` breaths in
the window is refused.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from drivers.sim.body import BodyPhantom, BodyState, DeformableBody, body_from_config
from drivers.sim.motion import PatientMotion, stream_rng
from drivers.sim.world import phantom_from_config, plan_document
from hil.config.simulation import BreathingConfig, SimulationConfig

FloatArray = NDArray[np.float64]

__all__ = ["DEFAULT_CT_NOISE_MM", "DEFAULT_PHASES", "MIN_TRACE_BREATHS", "TRACE_CT_WINDOW_S", "FourDCT",
           "RegularBreath", "four_d_ct", "four_d_ct_phases", "four_d_ct_plan"]

#: a 4D CT's usual phase bins
DEFAULT_PHASES = 10
#: localisation error of a fiducial or the target in one phase, mm per axis (1 mm voxels, segmented)
DEFAULT_CT_NOISE_MM = 0.3
#: a trace-driven body's 4D CT sorts the breaths of this long a stretch before the start, s
TRACE_CT_WINDOW_S = 60.0
#: the fewest whole breaths a trace's 4D CT is sorted from
MIN_TRACE_BREATHS = 3
#: the breaths are cut where the signal rises through this level after it was under the lower one
_INHALE_LEVEL, _REARM_LEVEL = 0.5, 0.3
#: the trace's signal is read this often to find its breaths, s
_SCAN_STEP_S = 0.02


class FourDCT(NamedTuple):
    """The simulated 4D CT: the plan's ``phases`` and ``phases_period_s``."""

    phases: list[dict[str, Any]]
    period_s: float


class RegularBreath:
    """A regular breathing cycle (:class:`drivers.sim.body.BreathingSignal`): every cycle the
    scripted breath's shape at amplitude 1, no holds."""

    def __init__(self, cfg: BreathingConfig) -> None:
        self.cfg = cfg

    @property
    def period_s(self) -> float:
        return self.cfg.period_s

    def s(self, t_s: float) -> float:
        period = self.cfg.period_s
        x = (t_s % period) / (period - self.cfg.end_exhale_dwell_s)
        if x >= 1.0:
            return 0.0
        return math.cos(math.pi * (x - 0.5)) ** (2 * self.cfg.shape_n)

    def hold(self, t_s: float) -> tuple[float, int]:
        return 0.0, -1


def four_d_ct(sim: SimulationConfig, phases: int = DEFAULT_PHASES,
              noise_mm: float = DEFAULT_CT_NOISE_MM) -> FourDCT:
    """The plan's ``phases`` (hil/controller/plan_file.py) for this simulated patient (module doc):
    ``phases - 1`` phases after the registered one, image frame, mm, rounded to 0.1 um; and the
    breathing period they were sorted at, s.

    Raises:
        ValueError: a rigid body (``[simulation.body] model = "rigid"``: no phases to show), fewer
            than 3 phases, a negative noise, or a trace with fewer than :data:`MIN_TRACE_BREATHS`
            breaths before the start.
        InputFileError: a trace that cannot be read or cannot drive the body (naming it).
    """
    if sim.body.model == "rigid":
        raise ValueError("a 4D CT of a rigid phantom: [simulation.body] model is 'rigid'")
    if phases < 3:
        raise ValueError(f"a 4D CT needs >= 3 phases (got {phases})")
    if not noise_mm >= 0.0:
        raise ValueError(f"CT localisation noise must be >= 0 mm (got {noise_mm})")
    ph = phantom_from_config(sim.patient)
    if sim.body.trace.path is not None:
        states, period = _trace_states(sim, ph, phases)
    else:
        body = DeformableBody(sim.body, sim.seed, ph.markers_mm, ph.entry_mm, ph.target_mm,
                              sim.patient.torso_radius_mm, RegularBreath(sim.breathing))
        period = sim.breathing.period_s
        # one period in: the lags are settled
        states = [body.state(period * (1.0 + k / phases)) for k in range(1, phases)]
    rng = stream_rng(sim.seed, "planning_ct")
    rng_entry = stream_rng(sim.seed, "planning_ct_entry")   # its own: the other points' draws stay
    out: list[dict[str, Any]] = []
    for state in states:
        fid = state.markers_mm + rng.normal(scale=noise_mm, size=state.markers_mm.shape)
        target = state.target_mm + rng.normal(scale=noise_mm, size=3)
        entry = state.entry_mm + rng_entry.normal(scale=noise_mm, size=3)
        out.append({"fiducials_mm": np.round(fid, 4).tolist(), "target_mm": np.round(target, 4).tolist(),
                    "entry_mm": np.round(entry, 4).tolist()})
    return FourDCT(out, period)


def four_d_ct_phases(sim: SimulationConfig, phases: int = DEFAULT_PHASES,
                     noise_mm: float = DEFAULT_CT_NOISE_MM) -> list[dict[str, Any]]:
    """:func:`four_d_ct`'s phases."""
    return four_d_ct(sim, phases, noise_mm).phases


def _trace_states(sim: SimulationConfig, phantom: BodyPhantom, phases: int) -> tuple[list[BodyState], float]:
    """The trace-driven body's phase states, averaged over the breaths before the start, and the
    breaths' mean length (module doc)."""
    free = sim.model_copy(update={"breath_holds": []})              # the CT's breaths hold nothing
    body = body_from_config(free, phantom, PatientMotion(free))
    if body is None:                                  # four_d_ct refused the rigid model already
        raise ValueError("a 4D CT of a rigid phantom: [simulation.body] model is 'rigid'")
    t = np.arange(-TRACE_CT_WINDOW_S, 0.0, _SCAN_STEP_S)
    s = np.array([body.signal.s(float(x)) for x in t])
    inhales, armed = [], bool(s[0] < _REARM_LEVEL)
    for i in range(1, len(s)):
        if s[i] < _REARM_LEVEL:
            armed = True
        elif armed and s[i - 1] < _INHALE_LEVEL <= s[i]:
            inhales.append(i)
            armed = False
    exhales = [a + int(np.argmin(s[a:b])) for a, b in itertools.pairwise(inhales)]
    if len(exhales) < MIN_TRACE_BREATHS + 1:
        raise ValueError(f"a 4D CT of the trace needs {MIN_TRACE_BREATHS} whole breaths in the "
                         f"{TRACE_CT_WINDOW_S:g} s before the start; it has {max(len(exhales) - 1, 0)}")
    breaths = list(itertools.pairwise(float(t[i]) for i in exhales))
    out: list[BodyState] = []
    for k in range(1, phases):
        at = [body.state(a + (b - a) * k / phases) for a, b in breaths]
        out.append(BodyState(markers_mm=np.mean([x.markers_mm for x in at], axis=0),
                             normals=np.mean([x.normals for x in at], axis=0),
                             entry_mm=np.mean([x.entry_mm for x in at], axis=0),
                             target_mm=np.mean([x.target_mm for x in at], axis=0)))
    return out, float(np.mean([b - a for a, b in breaths]))


def four_d_ct_plan(sim: SimulationConfig, phases: int = DEFAULT_PHASES,
                   noise_mm: float = DEFAULT_CT_NOISE_MM) -> dict[str, Any]:
    """The phantom's plan document with the 4D CT's ``phases`` (:func:`four_d_ct_phases`)."""
    doc = plan_document(sim.patient)
    ct = four_d_ct(sim, phases, noise_mm)
    doc["phases"] = ct.phases
    doc["phases_period_s"] = ct.period_s
    return doc
