"""The arm as a simulated world in the perception process sees it: the servo process's state ring,
attached read-only by name (the same records the supervisor's robot reads)."""

from __future__ import annotations

import threading
from typing import Protocol, runtime_checkable

import numpy as np

from hil.geometry.transform import RigidTransform
from hil.servo.link import RING_SLOTS
from hil.servo.shm import RingRecord, ShmRegion, StateRing, ring_words

#: How many records back (from the newest) a pose is looked for: 1000 periods is 2 s at 500 Hz.
MAX_BACK = RING_SLOTS - 24
#: How far past the newest record a pose is extrapolated, in the spacing of the last two records
#: (one servo period): a camera renders a pair from 2 ms after its exposure, before the loop of a
#: CB3 (8 ms a period) may have recorded the arm there. Further on the pose stays at that bound.
MAX_AHEAD_SPANS = 1.0


@runtime_checkable
class FollowingWorld(Protocol):
    """What the perception process asks of a simulated world (without importing the simulator):
    its time origin (set to the supervisor's world's), a flange source, breath-hold requests."""

    t0_ns: int

    def attach_robot(self, robot: RingFlangeSource) -> None: ...

    def now_s(self) -> float: ...

    def request_breath_hold(self, duration_s: float, level: float = 0.0,
                            delay_s: float | None = None) -> float: ...


class RingFlangeSource:
    """``T_robot_from_flange_at`` from the servo's state ring (a world's flange source).

    The pose at ``t_ns`` is interpolated between the two records around it (translation linear,
    rotation along the geodesic); after the newest record, extrapolated along the last two records
    for up to :data:`MAX_AHEAD_SPANS` of their spacing and held there (the newest alone: held);
    before the oldest still kept, the oldest. Before the loop's first record: None (the world then
    sees no flange).
    A restarted servo process records the arm in a new ring: :meth:`follow` moves to it.

    Args:
        ring_name: the servo process's state-ring segment.
        T_flange_from_tcp: the robot's TCP in the flange frame (mm).
    """

    def __init__(self, ring_name: str, T_flange_from_tcp: RigidTransform) -> None:
        self.region = ShmRegion.attach(ring_name, ring_words(RING_SLOTS))
        self.ring = StateRing(self.region, RING_SLOTS)
        self.T_tcp_from_flange = T_flange_from_tcp.inverse()
        self._newer, self._older = RingRecord(), RingRecord()
        self._follow_next: str | None = None
        self._follow_lock = threading.Lock()

    def follow(self, ring_name: str) -> None:
        """From the next pose asked for, read the ring ``ring_name`` (a restarted servo process's)
        instead. Safe from another thread: the switch happens in the reading thread, and of names
        given before it, the last is followed."""
        with self._follow_lock:
            self._follow_next = ring_name

    def close(self) -> None:
        self.region.close()

    def _switch_if_asked(self) -> None:
        with self._follow_lock:   # a follow() between the read and the clear would be lost
            name, self._follow_next = self._follow_next, None
        if name is None:
            return
        try:
            region = ShmRegion.attach(name, ring_words(RING_SLOTS))
        except OSError:   # already gone (restarted again since): the next follow() says where
            return
        self.region.close()
        self.region, self.ring = region, StateRing(region, RING_SLOTS)

    def _pose(self, rec: RingRecord) -> RigidTransform:
        T = RigidTransform(rec.pose[:9].reshape(3, 3).copy(), rec.pose[9:].copy())
        return T @ self.T_tcp_from_flange

    def T_robot_from_flange_at(self, t_ns: int) -> RigidTransform | None:
        if self._follow_next is not None:
            self._switch_if_asked()
        newer = self.ring.read_latest(self._newer)
        if newer is None:
            return None
        if newer.t_ns <= t_ns:
            older = self.ring.read_back(1, self._older)
            if older is None or older.t_ns >= newer.t_ns:
                return self._pose(newer)
            span = newer.t_ns - older.t_ns
            return self._between(older, newer, min((t_ns - older.t_ns) / span, 1.0 + MAX_AHEAD_SPANS))
        for back in range(1, MAX_BACK):
            older = self.ring.read_back(back, self._older)
            if older is None:
                break
            if older.t_ns <= t_ns:
                span = newer.t_ns - older.t_ns
                return self._between(older, newer, 0.0 if span <= 0 else (t_ns - older.t_ns) / span)
            self._newer, self._older = self._older, self._newer
            newer = self._newer
        return self._pose(newer)

    def _between(self, older: RingRecord, newer: RingRecord, s: float) -> RigidTransform:
        """The flange pose a fraction ``s`` of the way from ``older`` to ``newer`` (beyond 1:
        extrapolated along the same line and geodesic)."""
        a, b = self._pose(older), self._pose(newer)
        rel = RigidTransform(a.R.T @ b.R, np.zeros(3))
        R = a.R @ RigidTransform.from_rotvec(s * rel.as_rotvec()).R
        return RigidTransform(R, a.t + s * (b.t - a.t))
