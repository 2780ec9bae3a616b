"""Fixtures for the device tests: the simulator on a ManualClock."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.clock import ManualClock
from hil.config import Devices, SetupConfig, build_devices, load_setup
from plugins.manager import HilPlugins
from plugins.registry import DriverRegistry

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"


@pytest.fixture(scope="session")
def registry() -> DriverRegistry:
    return HilPlugins().driver_registry()


@pytest.fixture(scope="session")
def sim_setup(registry: DriverRegistry) -> SetupConfig:
    return load_setup(CONFIGS / "sim.toml", registry)


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(start_ns=1_000_000_000)


@pytest.fixture
def devices(sim_setup: SetupConfig, clock: ManualClock, registry: DriverRegistry) -> Iterator[Devices]:
    devs = build_devices(sim_setup, clock, registry)
    devs.open_all()
    yield devs
    devs.close_all()
