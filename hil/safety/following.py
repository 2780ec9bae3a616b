"""Following-error supervision: is the arm following the servo targets it is sent?

The servo loop (:mod:`hil.servo.loop`) feeds every period's command and the arm's reported pose
to a :class:`FollowingMonitor`. The monitor keeps the pose the arm is *expected* at: the commands
through the arm's first-order servo lag (:class:`~drivers.interfaces.robot.FollowingModel`,
``time_constant_s`` = tau): at each update, over the time ``dt`` since the previous one (the
actual interval, so a late period or a loop stepped at the camera rate is modelled right),

    expected += (previous command - expected) * (1 - exp(-dt / tau))

(translation; the rotation matrix is blended the same way, entry by entry: the per-period
rotation is small, so the blend stays a rotation to second order and the angle read from its trace
is exact to that order). The *following error* is the distance between the expected and the
reported TCP pose: translation in mm, rotation in degrees. The reported pose is compared with the
expectation *at the time the arm sampled it* (``sample_t_ns``, when the driver knows it: a UR
stamps every state with its controller clock, :mod:`drivers.ur_rtde.stream_age`), interpolated in
the expectations of the last :data:`HISTORY` updates: a state that is some milliseconds old (RTDE
transport, a controller or a host that paused) is then not mistaken for an arm that lags, which
matters at approach speeds (50 mm/s: 2 mm per 40 ms of age). Without a sample time the state is
compared with the expectation at the update. A healthy arm stays within a fraction of
a millimetre of its expectation at any speed (the lag is modelled, not bounded); an arm that stalls,
answers late or drifts leaves it. A divergence beyond ``max_error_mm`` or ``max_error_deg`` held
for ``max_duration_s`` is a :class:`FollowingFault` that states the figures.

Hot path: :meth:`FollowingMonitor.update` works in preallocated arrays (a few Python floats
aside); a fault (rare) builds its report. Frames: every pose is ``T_robot_from_tcp`` (robot base frame, mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.robot import FollowingModel

FloatArray = NDArray[np.float64]

#: How many updates' expectations are kept for a sample time in the past (128: 256 ms at 500 Hz,
#: 1 s at 125 Hz; a state older than that is compared with the oldest, and the driver refuses a
#: stream that old first: ``state_max_age_s``).
HISTORY = 128


@dataclass(frozen=True)
class FollowingFault:
    """An arm that did not follow: the figures of the divergence.

    Attributes:
        error_mm, error_deg: the following error when the fault was declared.
        max_error_mm, max_error_deg: the largest during the divergence.
        duration_s: how long it had been beyond a bound.
        model: the bounds and lag in force (and where they came from).
        expected_mm, actual_mm: expected and reported TCP positions (robot frame, mm).
    """

    error_mm: float
    error_deg: float
    max_error_mm: float
    max_error_deg: float
    duration_s: float
    model: FollowingModel
    expected_mm: tuple[float, float, float]
    actual_mm: tuple[float, float, float]

    def message(self) -> str:
        """One line for the FAULT reason and the session log."""
        m = self.model
        return (f"arm not following its servo targets: {self.error_mm:.2f} mm / {self.error_deg:.2f} deg "
                f"from the expected pose for {self.duration_s * 1e3:.0f} ms (max {self.max_error_mm:.2f} mm "
                f"/ {self.max_error_deg:.2f} deg; bound {m.max_error_mm:g} mm / {m.max_error_deg:g} deg for "
                f"{m.max_duration_s * 1e3:.0f} ms, servo lag {m.time_constant_s * 1e3:.0f} ms: {m.source})")

    def fields(self) -> dict[str, object]:
        """The figures as session-log fields."""
        m = self.model
        return {"error_mm": round(self.error_mm, 3), "error_deg": round(self.error_deg, 3),
                "max_error_mm": round(self.max_error_mm, 3), "max_error_deg": round(self.max_error_deg, 3),
                "duration_ms": round(self.duration_s * 1e3, 1), "bound_mm": m.max_error_mm,
                "bound_deg": m.max_error_deg, "bound_ms": m.max_duration_s * 1e3,
                "lag_ms": round(m.time_constant_s * 1e3, 2), "bounds_from": m.source,
                "expected_mm": [round(v, 3) for v in self.expected_mm],
                "actual_mm": [round(v, 3) for v in self.actual_mm]}


class FollowingMonitor:
    """The expected pose and the divergence timer (module doc).

    Args:
        model: the arm's lag and the bounds (:meth:`MotionLimits.following` applied).
    """

    def __init__(self, model: FollowingModel) -> None:
        self.model = model
        self._R = np.eye(3)
        self._t = np.zeros(3)
        self._dR = np.zeros((3, 3))   # scratch: no allocation per period
        self._dt = np.zeros(3)
        self._R_cmd = np.eye(3)       # the previous command, and when it was sent
        self._t_cmd = np.zeros(3)
        self._cmd_ns: int | None = None
        # the expectation at each of the last HISTORY updates (a ring; newest at _hist_i - 1)
        self._hist_ns = np.zeros(HISTORY, dtype=np.int64)
        self._hist_t = np.zeros((HISTORY, 3))
        self._hist_R = np.zeros((HISTORY, 3, 3))
        self._hist_n = 0
        self._hist_i = 0
        self._at_t = np.zeros(3)       # scratch: the expectation at the sample time
        self._at_R = np.zeros((3, 3))
        self._active = False
        self._beyond_since_ns: int | None = None
        self._max_mm = 0.0
        self._max_deg = 0.0
        #: the following error of the latest :meth:`update` (mm, degrees)
        self.last_error_mm = 0.0
        self.last_error_deg = 0.0

    @property
    def active(self) -> bool:
        return self._active

    def start(self, R_actual: FloatArray, t_actual_mm: FloatArray) -> None:
        """Begin a tracking session at the arm's actual pose (it is at rest there)."""
        self._R[:] = R_actual
        self._t[:] = t_actual_mm
        self._active = True
        self._beyond_since_ns = None
        self._cmd_ns = None
        self._hist_n = 0   # before the first update, the arm was expected where it rests

    def stop(self) -> None:
        """No servo targets any more (idle, stop, a refused step): nothing to follow."""
        self._active = False
        self._beyond_since_ns = None

    def update(self, now_ns: int, R_cmd: FloatArray, t_cmd_mm: FloatArray,
               R_actual: FloatArray, t_actual_mm: FloatArray,
               sample_t_ns: int | None = None) -> FollowingFault | None:
        """One period at ``now_ns``: advance the expectation toward the previous command over
        the time since it was sent, compare the pose the arm reported this period with the
        expectation at ``sample_t_ns`` (host clock, ns: when the arm sampled that pose; None: now),
        and keep ``(R_cmd, t_cmd_mm)`` (the command sent now) for the next update. Returns the fault
        once the divergence has lasted ``max_duration_s`` (then the monitor stops), else None."""
        if not self._active:
            self.start(R_actual, t_actual_mm)
        if self._cmd_ns is not None:
            self._advance((now_ns - self._cmd_ns) * 1e-9)
        self._R_cmd[:] = R_cmd
        self._t_cmd[:] = t_cmd_mm
        self._cmd_ns = now_ns
        self._remember(now_ns)
        e, eR = self._expected_at(now_ns if sample_t_ns is None else sample_t_ns)
        a = t_actual_mm
        dx, dy, dz = float(e[0] - a[0]), float(e[1] - a[1]), float(e[2] - a[2])
        err_mm = math.sqrt(dx * dx + dy * dy + dz * dz)
        cos = (float(np.vdot(eR, R_actual)) - 1.0) * 0.5   # (trace(R_actual^T R_expected) - 1) / 2
        err_deg = math.degrees(math.acos(1.0 if cos > 1.0 else (-1.0 if cos < -1.0 else cos)))
        self.last_error_mm, self.last_error_deg = err_mm, err_deg
        m = self.model
        fault: FollowingFault | None = None
        if err_mm > m.max_error_mm or err_deg > m.max_error_deg:
            if self._beyond_since_ns is None:
                self._beyond_since_ns = now_ns
                self._max_mm, self._max_deg = err_mm, err_deg
            else:
                self._max_mm = max(self._max_mm, err_mm)
                self._max_deg = max(self._max_deg, err_deg)
            held_s = (now_ns - self._beyond_since_ns) * 1e-9
            if held_s >= m.max_duration_s:
                fault = FollowingFault(err_mm, err_deg, self._max_mm, self._max_deg, held_s, m,
                                       (float(e[0]), float(e[1]), float(e[2])),
                                       (float(a[0]), float(a[1]), float(a[2])))
                self.stop()
                return fault
        else:
            self._beyond_since_ns = None
        return None

    def _remember(self, now_ns: int) -> None:
        """Append the expectation at ``now_ns`` to the ring."""
        i = self._hist_i
        self._hist_ns[i] = now_ns
        self._hist_t[i] = self._t
        self._hist_R[i] = self._R
        self._hist_i = (i + 1) % HISTORY
        if self._hist_n < HISTORY:
            self._hist_n += 1

    def _expected_at(self, t_ns: int) -> tuple[FloatArray, FloatArray]:
        """The expected pose ``(t_mm, R)`` at ``t_ns``: linear between the two remembered updates
        around it (the rotation blended entry by entry, as :meth:`_advance` does); at or after the
        newest update, the newest; before the oldest, the oldest (or the resting pose the session
        started from). Returns views of internal arrays, valid until the next call."""
        n, newest = self._hist_n, (self._hist_i - 1) % HISTORY
        if n == 0 or t_ns >= self._hist_ns[newest]:
            return self._t, self._R
        hist_ns = self._hist_ns
        k = newest
        for _ in range(n - 1):   # back from the newest: a sample is a few updates old
            older = (k - 1) % HISTORY
            t_old = int(hist_ns[older])
            if t_old <= t_ns:
                span = int(hist_ns[k]) - t_old
                w = (t_ns - t_old) / span if span > 0 else 1.0
                np.subtract(self._hist_t[k], self._hist_t[older], out=self._at_t)
                self._at_t *= w
                self._at_t += self._hist_t[older]
                np.subtract(self._hist_R[k], self._hist_R[older], out=self._at_R)
                self._at_R *= w
                self._at_R += self._hist_R[older]
                return self._at_t, self._at_R
            k = older
        return self._hist_t[k], self._hist_R[k]

    def _advance(self, dt_s: float) -> None:
        tau = self.model.time_constant_s
        alpha = 1.0 if tau <= 0.0 else 1.0 - math.exp(-max(dt_s, 0.0) / tau)
        np.subtract(self._t_cmd, self._t, out=self._dt)
        self._dt *= alpha
        self._t += self._dt
        np.subtract(self._R_cmd, self._R, out=self._dR)
        self._dR *= alpha
        self._R += self._dR
