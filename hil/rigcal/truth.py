"""What a simulated world can tell about the true rig, without the core importing it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RigTruth:
    """The true rig (simulation only).

    Attributes:
        flange_markers_mm: (M, 3) true flange-marker centres, flange frame.
        T_optical_from_robot: true robot base pose seen from the left camera.
        time_offsets_ms: per device (``camera``, ``robot``, ``tracker``), its reported timestamp
            minus the true time of what it reports, ms.
    """

    flange_markers_mm: FloatArray
    T_optical_from_robot: RigidTransform
    time_offsets_ms: dict[str, float]


@runtime_checkable
class RigTruthSource(Protocol):
    """A world that knows the true rig (``drivers.sim.world.SimWorld``)."""

    def rig_truth(self) -> RigTruth | None:
        """The true rig, or None when the world does not know it (its arm is a real driver's)."""
        ...
