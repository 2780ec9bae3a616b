"""``hil probe``'s device checks come from the drivers through the ``hil_register_probes`` hook: the
built-in drivers' probes, and a third-party driver's own probe run before its driver-level checks."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import pytest
from pydantic import BaseModel, ConfigDict

import configs
from drivers.interfaces.tracker import PoseTracker, TrackerSample
from hil.clock import Clock
from hil.config import parse_setup
from hil.config.setup import SetupConfig
from hil.geometry.transform import RigidTransform
from hil.probe import Checklist, Finding, Outcome, ProbeContext, ProbeRegistry, probe_setup, render_text
from plugins.builtin import REAL_DRIVERS
from plugins.hookspecs import hookimpl
from plugins.manager import HilPlugins
from plugins.registry import DriverContext, DriverRegistry, RegistryError

CONFIGS = Path(configs.__file__).parent


class AcmeTrackerConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    driver: Literal["acme"]
    answer: str = "ACME-1"


class AcmeTracker(PoseTracker):
    """One sensor at a fixed pose, on the context clock."""

    def __init__(self, name: str, clock: Clock) -> None:
        super().__init__(name)
        self.clock = clock
        self.seq = 0

    def _open(self) -> None: ...
    def _close(self) -> None: ...

    @property
    def sensors(self) -> tuple[str, ...]:
        return ("tip",)

    def latest(self) -> dict[str, TrackerSample]:
        self.seq += 1
        return {"tip": TrackerSample("tip", RigidTransform.from_rotvec([0, 0, 0], [1.0, 2.0, 3.0]), 0.1,
                                     self.clock.now_ns(), self.seq)}


def _acme_factory(cfg: AcmeTrackerConfig, ctx: DriverContext) -> AcmeTracker:
    return AcmeTracker(ctx.role, ctx.clock)


def acme_probe(cl: Checklist, cfg: AcmeTrackerConfig, ctx: ProbeContext) -> None:
    """The device's own wire check: its identity string must be the one it should be."""

    def identity() -> Outcome:
        if cfg.answer != "ACME-1":
            raise Finding(f"the box answers {cfg.answer!r}, not ACME-1", "is this an ACME tracker?")
        return Outcome("identity: ACME-1", data={"id": cfg.answer})

    cl.step("acme_identity", identity, what="asking the ACME box who it is")


class AcmePlugin:
    @hookimpl
    def hil_register_drivers(self, registry: DriverRegistry) -> None:
        registry.add("tracker", "acme", AcmeTrackerConfig, _acme_factory, origin="acme")

    @hookimpl
    def hil_register_probes(self, registry: ProbeRegistry) -> None:
        registry.add("tracker", "acme", acme_probe, origin="acme")


def _setup(answer: str) -> SetupConfig:
    return parse_setup({"camera": {"driver": "sim"}, "robot": {"driver": "sim"},
                        "tracker": {"driver": "acme", "answer": answer},
                        "calibration": {"stereo": "calibration/sim_stereo.json"}},
                       source="acme.toml", config_dir=CONFIGS, registry=_plugins().driver_registry())


def _plugins() -> HilPlugins:
    return HilPlugins(plugins=[("acme", AcmePlugin())])


def test_builtin_plugin_registers_the_probe_of_every_real_driver() -> None:
    probes = HilPlugins().probe_registry()
    got = {(p.kind, p.driver): (p.origin, p.driver_checks) for p in probes.probes()}
    assert got == {
        ("robot", "ur_rtde"): ("builtin", False),  # read-only: opening the driver would start a script
        ("tracker", "fob"): ("builtin", True),
        ("tracker", "aurora"): ("builtin", True),
        ("camera", "aravis"): ("builtin", True),
        ("camera", "v4l2"): ("builtin", True),
        ("camera", "replay"): ("builtin", True),
    }
    assert set(got) == {(d.kind, d.name) for d in REAL_DRIVERS}
    assert probes.get("tracker", "sim") is None  # simulated drivers get the driver-level checks only


def test_a_third_party_probe_runs_before_the_driver_checks() -> None:
    plugins = _plugins()
    report = probe_setup(_setup("ACME-1"), config_name="acme.toml",
                         registry=plugins.driver_registry(), probes=plugins.probe_registry(),
                         timeout_s=2.0, window_s=0.2)
    tracker = next(d for d in report.devices if d.role == "tracker")
    assert [c.name for c in tracker.checks] == ["acme_identity", "driver_builds", "driver_opens", "streams",
                                                "sensor_tip"]
    assert tracker.checks[0].message == "identity: ACME-1"
    assert tracker.checks[-1].message.startswith("sensor 'tip': pose at [1.0, 2.0, 3.0] mm")
    assert report.exit_code == 0


def test_a_failing_third_party_probe_stops_that_device_in_plain_words() -> None:
    plugins = _plugins()
    report = probe_setup(_setup("EVIL"), config_name="acme.toml",
                         registry=plugins.driver_registry(), probes=plugins.probe_registry(),
                         timeout_s=2.0, window_s=0.2)
    tracker = next(d for d in report.devices if d.role == "tracker")
    assert [(c.name, c.status.value) for c in tracker.checks] == [("acme_identity", "fail")]
    assert report.exit_code == 1
    text = render_text(report)
    assert "  FAIL  the box answers 'EVIL', not ACME-1\n        try: is this an ACME tracker?" in text


def test_a_probe_is_registered_once_per_driver() -> None:
    reg = ProbeRegistry()
    reg.add("tracker", "acme", acme_probe, origin="acme")
    with pytest.raises(RegistryError, match="already registered by acme"):
        reg.add("tracker", "acme", acme_probe, origin="other")
    with pytest.raises(RegistryError, match="unknown driver kind 'lidar'"):
        reg.add("lidar", "acme", acme_probe)
