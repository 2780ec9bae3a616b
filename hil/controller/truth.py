"""Protocols for what a simulated world may offer the controller, without the core importing it.

:class:`GroundTruth` lets a run measure its real error (the simulator knows where the patient
and the robot really are); :class:`BreathHoldCoach` stands for the surgeon asking the patient
to hold breath (a simulated patient obeys after a reaction time; on a real rig the operator
does it). The simulated world (``drivers.sim.world.SimWorld``) satisfies both structurally.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]


@runtime_checkable
class GroundTruth(Protocol):
    """The true state of the world (simulation only)."""

    @property
    def T_optical_from_robot(self) -> RigidTransform:
        """The true robot base pose in the optical frame (unknown to the controller)."""
        ...

    def entry_optical(self, t_ns: int) -> FloatArray:
        """True skin entry point (optical frame, mm) at ``t_ns``."""
        ...

    def target_optical(self, t_ns: int) -> FloatArray:
        """True target point (optical frame, mm) at ``t_ns``."""
        ...

    def body_rigid_residual_mm(self, t_ns: int) -> float:
        """How far the true skin markers are from rigid at ``t_ns``: the RMS residual of a rigid
        fit of the CT's markers onto them, mm (0 for a rigid body)."""
        ...

    def T_optical_from_flange(self, t_ns: int) -> RigidTransform | None:
        """The true flange pose at ``t_ns`` (optical frame; a simulator with a real rig's errors
        knows the real arm, not only its late, imprecise report), or None when it has no arm."""
        ...


@runtime_checkable
class BreathHoldCoach(Protocol):
    """Who asks the patient to hold breath."""

    def request_breath_hold(self, duration_s: float) -> object:
        """Ask for a breath-hold lasting ``duration_s`` (it starts after a reaction time)."""
        ...
