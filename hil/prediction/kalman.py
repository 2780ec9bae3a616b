"""Kalman filter with a breathing oscillator: an extended Kalman filter whose state is a
baseline, a harmonic oscillator per axis and one shared breathing frequency (after Ramrath,
Schlaefer, Ernst, Dieterich and Schweikard, "Prediction of respiratory motion with a
multi-frequency based extended Kalman filter", Proc. CARS 2007, 56-58; the "EKF" of Ernst et al.,
Phys. Med. Biol. 58 (2013) 3911; here one frequency, the base of that multi-frequency
model).

State ``s = (c_xyz, a_xyz, b_xyz, omega)``: per axis the measured position is
``y = c + a`` (measurement model H), and over ``dt`` the oscillator turns,
``(a, b) <- R(omega dt) (a, b)``, ``c`` and ``omega`` are random walks (process noise ``q_*``).
The standard EKF predict/update equations (Jacobian of the turn with respect to omega:
``d a'/d omega = -dt b'``, ``d b'/d omega = dt a'``) updates the state on each sample; the
forecast ``h`` ahead turns the oscillator by ``omega h``: ``y(t + h) = c + a cos(omega h) - b sin(omega h)``.
omega is kept in ``[2 pi / 15, 2 pi / 1.5]`` rad/s (breathing periods 1.5-15 s).
"""

from __future__ import annotations

import math

import numpy as np

from hil.prediction.base import FloatArray

__all__ = ["OscillatorKalmanModel"]

_OMEGA_MIN = 2 * math.pi / 15.0
_OMEGA_MAX = 2 * math.pi / 1.5


class OscillatorKalmanModel:
    """The oscillator EKF (module docstring).

    Args:
        period_s: the sample period, s (> 0).
        noise_mm: measurement noise standard deviation per axis, mm (> 0).
        q_baseline_mm: baseline random-walk standard deviation per second, mm.
        q_oscillator_mm: oscillator-state random-walk standard deviation per second, mm.
        q_omega: frequency random-walk standard deviation per second, rad/s.
        breath_period_s: the initial breathing period, s.
        warmup: samples before :attr:`ready`.
    """

    name = "kalman-osc"

    def __init__(self, period_s: float, noise_mm: float = 0.1, q_baseline_mm: float = 0.3,
                 q_oscillator_mm: float = 6.0, q_omega: float = 0.3, breath_period_s: float = 4.0,
                 warmup: int = 30) -> None:
        if not (period_s > 0 and noise_mm > 0 and min(q_baseline_mm, q_oscillator_mm, q_omega) >= 0
                and breath_period_s > 0 and warmup >= 0):
            raise ValueError("kalman-osc: period, noise and breathing period > 0, process noises >= 0")
        self.period_s = period_s
        self.r = noise_mm**2
        self.q = np.concatenate([np.full(3, q_baseline_mm**2), np.full(6, q_oscillator_mm**2), [q_omega**2]])
        self.omega0 = 2 * math.pi / breath_period_s
        self.warmup = warmup
        self._H = np.zeros((3, 10))
        self._H[:, 0:3] = np.eye(3)
        self._H[:, 3:6] = np.eye(3)
        self._s: FloatArray | None = None
        self._P = np.eye(10)
        self._n = 0

    @property
    def ready(self) -> bool:
        return self._n >= self.warmup

    def reset(self) -> None:
        self._s = None
        self._n = 0

    def _turn(self, s: FloatArray, dt: float) -> FloatArray:
        th = s[9] * dt
        c, sn = math.cos(th), math.sin(th)
        out = s.copy()
        out[3:6] = c * s[3:6] - sn * s[6:9]
        out[6:9] = sn * s[3:6] + c * s[6:9]
        return out

    def feed(self, x_mm: FloatArray, steps: float) -> None:
        self._n += 1
        if self._s is None:
            self._s = np.concatenate([x_mm, np.zeros(6), [self.omega0]])
            self._P = np.diag(np.concatenate([np.full(3, self.r), np.full(6, 25.0), [0.5**2]]))
            return
        dt = steps * self.period_s
        s = self._turn(self._s, dt)
        F = np.eye(10)
        th = self._s[9] * dt
        c, sn = math.cos(th), math.sin(th)
        for i in range(3):
            F[3 + i, 3 + i], F[3 + i, 6 + i] = c, -sn
            F[6 + i, 3 + i], F[6 + i, 6 + i] = sn, c
        F[3:6, 9] = -dt * s[6:9]
        F[6:9, 9] = dt * s[3:6]
        P = F @ self._P @ F.T + np.diag(self.q * dt)
        H = self._H
        innov = x_mm - (s[0:3] + s[3:6])
        S = H @ P @ H.T + self.r * np.eye(3)
        K = np.linalg.solve(S, H @ P).T
        s = s + K @ innov
        P = (np.eye(10) - K @ H) @ P
        s[9] = min(max(s[9], _OMEGA_MIN), _OMEGA_MAX)
        self._s, self._P = s, 0.5 * (P + P.T)

    def forecast(self, steps: float) -> FloatArray:
        assert self._s is not None
        s = self._turn(self._s, max(steps, 0.0) * self.period_s)
        out: FloatArray = s[0:3] + s[3:6]
        return out
