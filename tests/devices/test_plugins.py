"""Plugin registration through the pluggy hooks: built-ins and a third-party plugin alike."""

from __future__ import annotations

import types
from typing import Literal

import pytest
from pydantic import BaseModel, ConfigDict

from drivers.interfaces.camera import StereoCamera, StereoFrame
from hil.clock import ManualClock
from hil.config import build_devices, parse_setup
from plugins.builtin import REAL_DRIVERS
from plugins.hookspecs import hookimpl
from plugins.manager import HilPlugins, PluginError
from plugins.registry import DriverContext, DriverRegistry, RegistryError


class NullCameraConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    driver: Literal["null"]
    frame_rate_hz: float = 10.0


class NullCamera(StereoCamera):
    def __init__(self, name: str, cfg: NullCameraConfig) -> None:
        super().__init__(name)
        self.cfg = cfg

    def _open(self) -> None: ...
    def _close(self) -> None: ...

    def grab(self, timeout_s: float) -> StereoFrame:
        raise NotImplementedError

    @property
    def calibration(self) -> None:
        return None

    @property
    def frame_rate_hz(self) -> float:
        return self.cfg.frame_rate_hz

    @property
    def exposure_us(self) -> float:
        return 1.0

    @property
    def image_size(self) -> tuple[int, int]:
        return (8, 8)


def _null_factory(cfg: NullCameraConfig, ctx: DriverContext) -> NullCamera:
    return NullCamera(ctx.role, cfg)


class ThirdPartyPlugin:
    @hookimpl
    def hil_register_drivers(self, registry: DriverRegistry) -> None:
        registry.add("camera", "null", NullCameraConfig, _null_factory, origin="acme")


def test_builtin_registers_the_simulated_drivers_through_the_hook() -> None:
    """The built-in plugin is registered under 'builtin' and adds sim camera, robot, tracker."""
    plugins = HilPlugins()
    assert "builtin" in plugins.plugin_names()
    reg = plugins.driver_registry()
    for kind in ("camera", "robot", "tracker"):
        info = reg.get(kind, "sim")
        assert info.origin == "builtin"
        assert info.simulated
    assert reg.world_factory is not None
    assert reg.fault_wrapper is not None


def test_builtin_is_loaded_by_name_without_distribution_metadata(monkeypatch: pytest.MonkeyPatch) -> None:
    """With no installed distribution metadata the built-ins still load (importlib fallback)."""
    import importlib.metadata

    monkeypatch.setattr(importlib.metadata, "distributions", lambda: iter(()))
    plugins = HilPlugins()
    assert plugins.plugin_names() == ["builtin"]
    assert "sim" in plugins.driver_registry().names("robot")


def test_entry_point_group_declares_the_builtin() -> None:
    """pyproject declares builtin = plugins.builtin in group 'hil' (the installed metadata)."""
    import importlib.metadata

    eps = importlib.metadata.entry_points(group="hil")
    assert {(e.name, e.value) for e in eps} >= {("builtin", "plugins.builtin")}


def test_third_party_plugin_adds_a_driver_usable_in_a_setup(tmp_path: object) -> None:
    """A plugin registered into the manager provides a driver a setup can name."""
    plugins = HilPlugins(plugins=[("acme", ThirdPartyPlugin())])
    reg = plugins.driver_registry()
    info = reg.get("camera", "null")
    assert info.origin == "acme"
    setup = parse_setup({"camera": {"driver": "null", "frame_rate_hz": 5.0}, "robot": {"driver": "sim"}},
                        source="mem.toml", config_dir=__import__("pathlib").Path("."), registry=reg)
    assert setup.camera == NullCameraConfig(driver="null", frame_rate_hz=5.0)
    devs = build_devices(setup, ManualClock(), reg)
    assert isinstance(devs.camera, NullCamera)
    assert devs.camera.frame_rate_hz == 5.0
    assert devs.world is not None  # the sim robot needs the world


def test_a_camera_without_calibration_needs_the_setup_file() -> None:
    """The null camera knows no stereo calibration: without ``[calibration] stereo`` the
    controller's assembly refuses with one line naming the key and the driver."""
    from hil.controller.assembly import marker_locator
    from hil.errors import ConfigError

    reg = HilPlugins(plugins=[("acme", ThirdPartyPlugin())]).driver_registry()
    setup = parse_setup({"camera": {"driver": "null"}, "robot": {"driver": "sim"}},
                        source="mem.toml", config_dir=__import__("pathlib").Path("."), registry=reg)
    devs = build_devices(setup, ManualClock(), reg)
    assert devs.camera.calibration is None
    expected = (r"^setup: calibration.stereo: missing, and the camera driver 'null' does not know its "
                r"stereo calibration; set \[calibration\] stereo")
    with pytest.raises(ConfigError, match=expected):
        marker_locator(setup, devs.camera)


def test_plugin_with_an_unknown_hook_is_refused() -> None:
    """check_pending() catches a misspelt hook at start-up."""
    bad = types.SimpleNamespace()

    @hookimpl
    def hil_register_driverz(registry: DriverRegistry) -> None: ...

    bad.hil_register_driverz = hil_register_driverz
    with pytest.raises(PluginError, match="hil_register_driverz"):
        HilPlugins(plugins=[("bad", bad)])


def test_registering_the_same_plugin_name_twice_is_refused() -> None:
    plugins = HilPlugins()
    plugins.register(ThirdPartyPlugin(), "acme")
    with pytest.raises(PluginError, match="acme"):
        plugins.register(ThirdPartyPlugin(), "acme")


def test_duplicate_driver_name_is_refused() -> None:
    reg = DriverRegistry()
    reg.add("camera", "null", NullCameraConfig, _null_factory, origin="acme")
    with pytest.raises(RegistryError, match="already registered by acme"):
        reg.add("camera", "null", NullCameraConfig, _null_factory, origin="other")


def test_driver_literal_must_match_the_registered_name() -> None:
    reg = DriverRegistry()
    with pytest.raises(RegistryError, match="Literal\\['other'\\]"):
        reg.add("camera", "other", NullCameraConfig, _null_factory)


def test_config_model_must_forbid_extra_keys() -> None:
    class Loose(BaseModel):
        driver: Literal["loose"]

    with pytest.raises(RegistryError, match="extra='forbid'"):
        DriverRegistry().add("camera", "loose", Loose, _null_factory)


def test_unknown_kind_is_refused() -> None:
    with pytest.raises(RegistryError, match="unknown driver kind"):
        DriverRegistry().add("lidar", "null", NullCameraConfig, _null_factory)  # type: ignore[arg-type]


def test_every_real_driver_is_registered_or_reported_unavailable(registry: DriverRegistry) -> None:
    """The table of real drivers: importable ones are registered, others listed with a reason."""
    unavailable = {(u.kind, u.name): u for u in registry.unavailable()}
    for spec in REAL_DRIVERS:
        key = (spec.kind, spec.name)
        if key in unavailable:
            assert spec.module in unavailable[key].reason
            with pytest.raises(RegistryError, match="not available here"):
                registry.get(*key)
        else:
            assert registry.get(*key).origin == "builtin"


def test_a_real_driver_that_does_not_import_is_reported(tmp_path: object) -> None:
    """A table entry whose module is missing is registered as unavailable, and a setup naming it
    gets one line saying why."""
    from pathlib import Path

    from hil.errors import ConfigError
    from plugins.builtin import RealDriver, _register_real

    reg = DriverRegistry()
    _register_real(reg, RealDriver("robot", "ghost", "drivers.no_such_driver.config", "GhostConfig",
                                   "factory", "a driver that is not written yet"))
    _register_real(reg, RealDriver("camera", "half", "drivers.sim.camera", "NoSuchModel", "factory", ""))
    assert [(u.kind, u.name) for u in reg.unavailable()] == [("camera", "half"), ("robot", "ghost")]
    with pytest.raises(ConfigError) as info:
        parse_setup({"camera": {"driver": "half"}, "robot": {"driver": "ghost"}}, source="s.toml",
                     config_dir=Path("."), registry=reg)
    assert info.value.problems == [
        "camera.driver: camera driver 'half' is not available here: drivers.sim.camera: module "
        "'drivers.sim.camera' has no attribute 'NoSuchModel'",
        "robot.driver: robot driver 'ghost' is not available here: cannot import "
        "drivers.no_such_driver.config: No module named 'drivers.no_such_driver'",
    ]
