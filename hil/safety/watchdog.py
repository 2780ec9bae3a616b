"""Watchdogs on the age of device data: data older than the configured age counts as missing."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Watchdog:
    """One data stream's age check.

    Args:
        name: ``camera``, ``tracker``, ``robot`` (used in the fault reason).
        max_age_s: data older than this (on the controller clock) is missing.

    The watchdog is not armed until :meth:`arm` (or the first :meth:`feed`): a stream that never
    delivered after arming is reported missing once ``max_age_s`` has passed since arming.
    """

    name: str
    max_age_s: float
    last_t_ns: int | None = None
    armed_at_ns: int | None = None
    fed: int = field(default=0)

    def __post_init__(self) -> None:
        if not self.max_age_s > 0:
            raise ValueError(f"watchdog {self.name}: max_age_s must be > 0, got {self.max_age_s}")

    def arm(self, now_ns: int) -> None:
        if self.armed_at_ns is None:
            self.armed_at_ns = now_ns

    def feed(self, data_t_ns: int, now_ns: int) -> None:
        """Record a sample whose data time is ``data_t_ns`` (exposure / sample time)."""
        self.arm(now_ns)
        if self.last_t_ns is None or data_t_ns > self.last_t_ns:
            self.last_t_ns = data_t_ns
        self.fed += 1

    def age_s(self, now_ns: int) -> float | None:
        """Age of the newest data (s), or None when nothing arrived yet."""
        return None if self.last_t_ns is None else (now_ns - self.last_t_ns) * 1e-9

    def is_fresh(self, data_t_ns: int, now_ns: int) -> bool:
        """Whether data of time ``data_t_ns`` may be used at ``now_ns``."""
        return (now_ns - data_t_ns) * 1e-9 <= self.max_age_s

    def check(self, now_ns: int) -> str | None:
        """None when fine; otherwise the reason (``watchdog: camera data 0.412 s old > 0.200 s``)."""
        if self.armed_at_ns is None:
            return None
        if self.last_t_ns is None:
            waited = (now_ns - self.armed_at_ns) * 1e-9
            if waited > self.max_age_s:
                return f"watchdog: no {self.name} data for {waited:.3f} s > {self.max_age_s:.3f} s"
            return None
        age = (now_ns - self.last_t_ns) * 1e-9
        if age > self.max_age_s:
            return f"watchdog: {self.name} data {age:.3f} s old > {self.max_age_s:.3f} s"
        return None


class WatchdogSet:
    """The watchdogs of a setup, by stream name."""

    def __init__(self, ages_s: dict[str, float]) -> None:
        self.dogs = {name: Watchdog(name, age) for name, age in ages_s.items()}

    def __getitem__(self, name: str) -> Watchdog:
        return self.dogs[name]

    def arm(self, now_ns: int) -> None:
        for d in self.dogs.values():
            d.arm(now_ns)

    def check(self, now_ns: int, skip: frozenset[str] = frozenset()) -> list[str]:
        """Every violated watchdog's reason (empty when all fine), but those named in ``skip``."""
        return [r for name, d in self.dogs.items() if name not in skip and (r := d.check(now_ns)) is not None]
