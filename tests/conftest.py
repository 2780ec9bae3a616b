"""Shared pytest configuration."""

from __future__ import annotations

from hypothesis import HealthCheck, settings

#: The session fails when tests leave threads, child processes or sockets behind (tests/leakcheck.py).
pytest_plugins = ["tests.leakcheck"]

settings.register_profile(
    "ci", deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
settings.register_profile("dev", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci")
