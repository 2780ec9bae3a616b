"""Safety: watchdogs on data age and a command gate in front of the robot."""

from hil.safety.layer import CommandLog, SafetyLayer, SafetyViolationError
from hil.safety.watchdog import Watchdog, WatchdogSet

__all__ = ["CommandLog", "SafetyLayer", "SafetyViolationError", "Watchdog", "WatchdogSet"]
