"""The ring markers located in one stereo pair, per camera and triangulated, before identification.

:class:`LocatedMarkers` is immutable (read-only array copies), so the controller can hand the same
object to every snapshot without copying it again. A locator that knows the per-camera centres
(:class:`~hil.controller.perception.StereoMarkerLocator`) gives them through
:class:`LocatesPerCamera`; one that returns only 3-D points (a test's, a wrapper's) leaves them
unknown (None), never invented.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drivers.interfaces.camera import StereoFrame

FloatArray = NDArray[np.float64]


def _frozen(a: ArrayLike, cols: int) -> FloatArray:
    out = np.array(a, dtype=np.float64, copy=True).reshape(-1, cols)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class LocatedMarkers:
    """What the locator found in one pair (any order, unidentified; arrays read-only).

    Attributes:
        frame_seq: the pair's left frame counter (``frame.left.seq``).
        exposure_t_ns: the pair's left exposure time (controller clock, ns).
        points_mm: (M, 3) triangulated marker centres, optical frame, mm.
        left_px, right_px: (L, 2) / (R, 2) ring centres detected in the left / right image (each
            image's own distorted pixel coordinates, px); None when the locator does not say.
    """

    frame_seq: int
    exposure_t_ns: int
    points_mm: FloatArray
    left_px: FloatArray | None = None
    right_px: FloatArray | None = None

    @classmethod
    def of(cls, frame: StereoFrame, points_mm: ArrayLike, left_px: ArrayLike | None = None,
           right_px: ArrayLike | None = None) -> LocatedMarkers:
        """Read-only copies of the arrays, stamped with ``frame``'s left sequence number and time."""
        return cls(frame.left.seq, frame.left.t_ns, _frozen(points_mm, 3),
                   None if left_px is None else _frozen(left_px, 2),
                   None if right_px is None else _frozen(right_px, 2))

    @property
    def counts(self) -> tuple[int | None, int | None, int]:
        """(left, right, triangulated) marker counts; None where the locator did not say."""
        return (None if self.left_px is None else int(self.left_px.shape[0]),
                None if self.right_px is None else int(self.right_px.shape[0]),
                int(self.points_mm.shape[0]))


@runtime_checkable
class LocatesPerCamera(Protocol):
    """A locator that also gives the per-camera centres (``locate_pair``); its plain call still
    returns the triangulated points only."""

    def __call__(self, frame: StereoFrame) -> FloatArray:
        """The triangulated marker centres of ``frame`` (M, 3), optical frame, mm."""
        ...

    def locate_pair(self, frame: StereoFrame) -> LocatedMarkers:
        """The markers of ``frame``, per camera and triangulated."""
        ...


def locate_in(locate: Callable[[StereoFrame], FloatArray], frame: StereoFrame) -> LocatedMarkers:
    """``frame``'s markers through ``locate``: per camera when it can say (:class:`LocatesPerCamera`),
    else its 3-D points with the per-camera sets unknown. Raises what ``locate`` raises."""
    if isinstance(locate, LocatesPerCamera):
        return locate.locate_pair(frame)
    return LocatedMarkers.of(frame, np.asarray(locate(frame), dtype=np.float64))
