"""Setup configs: pydantic models, TOML loading with one line per problem, device building.

The device sections are validated against the driver registry (:mod:`plugins.registry`); the
core never imports a concrete driver.
"""

from hil.config.build import Devices, ScenarioWorld, build_devices, clock_for
from hil.config.faults import FAULT_DEVICE, FaultKind, FaultSpec
from hil.config.loader import (
    default_setup_path,
    load_fault_schedule,
    load_setup,
    parse_setup,
    with_faults,
)
from hil.config.setup import CalibrationConfig, FramesConfig, SafetyConfig, SetupConfig
from hil.config.simulation import (
    BreathHoldConfig,
    BreathingConfig,
    DriftConfig,
    PatientConfig,
    ShiftConfig,
    SimulationConfig,
    TremorConfig,
)
from hil.config.types import ConfigPath, TransformConfig

__all__ = [
    "FAULT_DEVICE",
    "BreathHoldConfig",
    "BreathingConfig",
    "CalibrationConfig",
    "ConfigPath",
    "Devices",
    "DriftConfig",
    "FaultKind",
    "FaultSpec",
    "FramesConfig",
    "PatientConfig",
    "SafetyConfig",
    "ScenarioWorld",
    "SetupConfig",
    "ShiftConfig",
    "SimulationConfig",
    "TransformConfig",
    "TremorConfig",
    "build_devices",
    "clock_for",
    "default_setup_path",
    "load_fault_schedule",
    "load_setup",
    "parse_setup",
    "with_faults",
]
