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
target's are those of a 4D CT without it. A body driven by a recorded trace has no model cycle:
:func:`four_d_ct_phases` refuses it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.sim.body import DeformableBody
from drivers.sim.motion import stream_rng
from drivers.sim.world import phantom_from_config, plan_document
from hil.config.simulation import BreathingConfig, SimulationConfig

FloatArray = NDArray[np.float64]

__all__ = ["DEFAULT_CT_NOISE_MM", "DEFAULT_PHASES", "RegularBreath", "four_d_ct_phases", "four_d_ct_plan"]

#: a 4D CT's usual phase bins
DEFAULT_PHASES = 10
#: localisation error of a fiducial or the target in one phase, mm per axis (1 mm voxels, segmented)
DEFAULT_CT_NOISE_MM = 0.3


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


def four_d_ct_phases(sim: SimulationConfig, phases: int = DEFAULT_PHASES,
                     noise_mm: float = DEFAULT_CT_NOISE_MM) -> list[dict[str, Any]]:
    """The plan's ``phases`` (hil/controller/plan_file.py) for this simulated patient (module doc):
    ``phases - 1`` phases after the registered one, image frame, mm, rounded to 0.1 um.

    Raises:
        ValueError: a rigid body (``[simulation.body] model = "rigid"``: no phases to show), a body
            driven by a trace, fewer than 3 phases or a negative noise.
    """
    if sim.body.model == "rigid":
        raise ValueError("a 4D CT of a rigid phantom: [simulation.body] model is 'rigid'")
    if sim.body.trace.path is not None:
        raise ValueError("a 4D CT is drawn from the body model; this body is driven by a trace")
    if phases < 3:
        raise ValueError(f"a 4D CT needs >= 3 phases (got {phases})")
    if not noise_mm >= 0.0:
        raise ValueError(f"CT localisation noise must be >= 0 mm (got {noise_mm})")
    ph = phantom_from_config(sim.patient)
    body = DeformableBody(sim.body, sim.seed, ph.markers_mm, ph.entry_mm, ph.target_mm,
                          sim.patient.torso_radius_mm, RegularBreath(sim.breathing))
    period = sim.breathing.period_s
    rng = stream_rng(sim.seed, "planning_ct")
    rng_entry = stream_rng(sim.seed, "planning_ct_entry")   # its own: the other points' draws stay
    out: list[dict[str, Any]] = []
    for k in range(1, phases):
        state = body.state(period * (1.0 + k / phases))     # one period in: the lags are settled
        fid = state.markers_mm + rng.normal(scale=noise_mm, size=state.markers_mm.shape)
        target = state.target_mm + rng.normal(scale=noise_mm, size=3)
        entry = state.entry_mm + rng_entry.normal(scale=noise_mm, size=3)
        out.append({"fiducials_mm": np.round(fid, 4).tolist(), "target_mm": np.round(target, 4).tolist(),
                    "entry_mm": np.round(entry, 4).tolist()})
    return out


def four_d_ct_plan(sim: SimulationConfig, phases: int = DEFAULT_PHASES,
                   noise_mm: float = DEFAULT_CT_NOISE_MM) -> dict[str, Any]:
    """The phantom's plan document with the 4D CT's ``phases`` (:func:`four_d_ct_phases`)."""
    doc = plan_document(sim.patient)
    doc["phases"] = four_d_ct_phases(sim, phases, noise_mm)
    doc["phases_period_s"] = sim.breathing.period_s
    return doc
