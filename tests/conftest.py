"""Shared pytest configuration."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

from hil.geometry import native

#: The session fails when tests leave threads, child processes or sockets behind (tests/leakcheck.py).
pytest_plugins = ["tests.leakcheck"]

settings.register_profile(
    "ci", deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
settings.register_profile("dev", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci")


@pytest.fixture
def compiled_geometry() -> Iterator[Any]:
    """The compiled geometry (hil/geometry/_native.c) selected for the test, the previous selection
    restored after; it must be built (tools/test builds it)."""
    assert native.is_built(), native.native_status()
    previous = native.use_native(True)
    k = native.active()
    assert k is not None
    yield k
    native.use_native(previous)
