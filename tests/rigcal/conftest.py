"""Fixtures for the rig-calibration tests: the realistic simulator on a ManualClock."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.config import SetupConfig, load_setup
from plugins.manager import HilPlugins
from plugins.registry import DriverRegistry

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"


@pytest.fixture(scope="session")
def registry() -> DriverRegistry:
    return HilPlugins().driver_registry()


@pytest.fixture(scope="session")
def realistic(registry: DriverRegistry) -> SetupConfig:
    return load_setup(CONFIGS / "sim_realistic.toml", registry)


@pytest.fixture(scope="session")
def perfect(registry: DriverRegistry) -> SetupConfig:
    return load_setup(CONFIGS / "sim.toml", registry)
