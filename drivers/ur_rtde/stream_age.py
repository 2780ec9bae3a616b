"""How old the newest sample of the RTDE state stream is, from the controller's own timestamps.

The driver reads the stream only when asked (once per control tick), so "the time we first saw
this timestamp" can be up to a tick after the sample arrived: a stalled stream was reported up to
one tick late. The controller stamps every sample with its own clock (``timestamp``, s since it
started); the host-minus-controller offset with the smallest transport delay seen so far maps a
sample to host time, so its age is known to within that delay. The estimate is clamped to what the
observations prove: the sample is at least ``now - (first seen)`` old and at most
``now - (last observation of the previous sample)`` old -- so a controller clock that lags the host
(an emulator on a loaded machine) can never make the age look larger than that.
"""

from __future__ import annotations

from dataclasses import dataclass

#: How fast the estimated clock offset may grow, s per s (200 ppm: crystal drift, with margin).
DRIFT_ALLOWANCE = 2e-4


@dataclass
class StreamAge:
    """Feed every observation with :meth:`observe`; it returns the newest sample's age (s).

    Observations must be in host-time order. A controller timestamp going backwards (a restarted
    controller) starts the estimate afresh.
    """

    _ts_s: float | None = None           # controller timestamp of the newest sample
    _first_seen_s: float = 0.0           # host time it was first observed
    _prev_seen_s: float | None = None    # host time of the last observation of the sample before it
    _last_obs_s: float = 0.0             # host time of the latest observation
    _offset_s: float | None = None       # host - controller clock, smallest delay seen (drift-relaxed)
    _offset_at_s: float = 0.0            # host time the offset was last updated

    def reset(self) -> None:
        """Forget everything (a new connection)."""
        self._ts_s, self._prev_seen_s, self._offset_s = None, None, None

    def observe(self, ts_s: float, host_s: float) -> float:
        """The age, s (>= 0), at ``host_s`` (host clock, s) of the sample stamped ``ts_s``
        (controller clock, s) that the stream holds now."""
        if self._ts_s is not None and ts_s < self._ts_s:
            self.reset()
        if ts_s != self._ts_s:
            self._prev_seen_s = None if self._ts_s is None else self._last_obs_s
            self._ts_s, self._first_seen_s = ts_s, host_s
            off = host_s - ts_s
            if self._offset_s is None:
                self._offset_s = off
            else:
                relaxed = self._offset_s + DRIFT_ALLOWANCE * max(host_s - self._offset_at_s, 0.0)
                self._offset_s = min(off, relaxed)
            self._offset_at_s = host_s
        self._last_obs_s = host_s
        assert self._offset_s is not None
        estimate = host_s - (ts_s + self._offset_s)
        low = host_s - self._first_seen_s
        high = host_s - self._prev_seen_s if self._prev_seen_s is not None else low
        return min(max(estimate, low), high)
