"""Open everything a console session needs: the setup's devices, the session log, the
controller with the console's operator, the runner thread and (optionally) the OpenIGTLink
server — the same controller ``hil run`` drives, built the same way.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.clock import Clock, ManualClock
from hil.config import build_devices, default_setup_path, load_setup
from hil.config.build import Devices, clock_for
from hil.config.setup import SetupConfig
from hil.console.operator import ConsoleOperator
from hil.console.runner import ControllerRunner
from hil.controller.assembly import (
    build_controller,
    runtime_plugins,
    session_header,
    stereo_calibration,
    with_perception_process,
    with_servo_process,
)
from hil.controller.controller import Controller
from hil.controller.plan_file import ProcedurePlan, load_plan
from hil.errors import InputFileError
from hil.igtl.config import IgtlConfig
from hil.session.log import SessionLog


@dataclass
class ConsoleSession:
    """A running console session. :meth:`close` ends it (idempotent)."""

    config_path: Path
    setup: SetupConfig
    plan: ProcedurePlan
    devices: Devices
    session: SessionLog
    ctl: Controller
    operator: ConsoleOperator
    runner: ControllerRunner
    igtl: Any  # IgtlServer | None (pyigtl is optional)
    clock: Clock
    closed: bool = False
    viewer: Any = None  # LiveViewerPlugin | None (rerun-sdk is optional)

    def close(self) -> dict[str, Any]:
        """Stop the loop (aborting a procedure under way), close the devices, the OpenIGTLink
        server and the session log. Returns a summary (final state, session log, faults)."""
        if not self.closed:
            self.closed = True
            if self.runner.stop():
                self.ctl.log_refused_inputs()  # refused after the loop ended (it owned the log)
            try:
                self.devices.close_all()
            finally:
                if self.igtl is not None:
                    self.igtl.close()
                if self.viewer is not None:
                    self.viewer.close()
                self.session.close(final_state=self.ctl.state.value, origin="console")
        out: dict[str, Any] = {"viewer": None if self.viewer is None else self.viewer.counts()}
        return {**out, "final_state": self.ctl.state.value, "session_log": str(self.session.path),
                "session_log_sha256": self.session.head_sha256,  # the chain head (also <log>.head)
                "faults": list(self.ctl.faults), "frames": self.ctl.frames,
                "error": self.runner.error or None}


def resolve_plan_path(config_path: Path, plan: str | Path | None) -> Path:
    """``plan`` when given, else ``plans/<config stem>_plan.json`` next to the config (as ``hil run``).

    Raises:
        InputFileError: no plan given and none bundled.
    """
    if plan is not None:
        return Path(plan)
    p = config_path.resolve().parent / "plans" / f"{config_path.stem}_plan.json"
    if not p.is_file():
        raise InputFileError(str(p), "no bundled plan for this setup; give one with --plan")
    return p


def igtl_config_for(setup: SetupConfig, port: int | None) -> IgtlConfig:
    """The setup's ``[igtl]`` table when it has one, overridden by ``--igtl-port`` (enables it)."""
    cfg = getattr(setup, "igtl", None)
    base = cfg if isinstance(cfg, IgtlConfig) else IgtlConfig()
    if port is not None:
        base = base.model_copy(update={"enabled": True, "port": port})
    return base


def _close_outputs(igtl: Any, live: Any) -> None:
    """Close the OpenIGTLink server and the live viewer stream, those that were started."""
    if igtl is not None:
        igtl.close()
    if live is not None:
        live.close()


def _load_setup(config_path: Path, seed: int | None) -> SetupConfig:
    """The setup, with ``[simulation] seed`` overridden when ``seed`` is given (>= 0)."""
    setup = load_setup(config_path)
    if seed is None:
        return setup
    if seed < 0:
        raise InputFileError("--seed", f"must be >= 0, got {seed}")
    return setup.model_copy(update={"simulation": setup.simulation.model_copy(update={"seed": seed})})


def open_console_session(config: str | Path | None, *, plan: str | Path | None = None,
                         session_dir: str | Path = "sessions", seed: int | None = None,
                         fast: bool = False, igtl_port: int | None = None,
                         clock: Clock | None = None, viewer: str | None = None) -> ConsoleSession:
    """Load the setup and plan, build and open the devices, create the session log and the
    controller, start the OpenIGTLink server when enabled, start the controller thread.

    ``fast``: on a simulated clock, do not pace to the wall clock (faster than real time).
    ``viewer``: stream the run live to Rerun (a ``.rrd`` path or a viewer address;
    :mod:`hil.replay.live`); the summary's ``viewer`` holds its counts.

    Raises:
        ConfigError, InputFileError: bad setup or plan (names file and key).
        IgtlError: the OpenIGTLink server cannot start.
        DriverError: a device cannot be opened.
    """
    config_path = Path(config) if config is not None else default_setup_path()
    setup = _load_setup(config_path, seed)
    the_plan = load_plan(resolve_plan_path(config_path, plan))
    igtl_cfg = igtl_config_for(setup, igtl_port)
    clk = clock if clock is not None else clock_for(setup)
    igtl = None
    if igtl_cfg.enabled:
        from hil.igtl.server import IgtlServer

        igtl = IgtlServer(igtl_cfg, clk)
        igtl.start()
    live: Any = None
    try:
        if viewer is not None:
            from hil.replay.live import open_live_viewer

            live = open_live_viewer(viewer)
        devices = build_devices(setup, clk)
    except BaseException:
        _close_outputs(igtl, live)
        raise
    try:
        stereo_calibration(setup, devices.camera)  # none anywhere: refused before any device opens
        devices = with_servo_process(setup, devices, clk)  # [servo] process: on the wall clock
        devices = with_perception_process(setup, devices, clk)  # [perception] process: likewise
    except BaseException:
        _close_outputs(igtl, live)
        raise
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%S%fZ")
    header: dict[str, Any] = {**session_header(config_path, setup, the_plan, devices, clk),
                              "origin": "console", "igtl": igtl_cfg.model_dump(mode="json")}
    session = SessionLog(Path(session_dir) / f"session_{stamp}.jsonl", clk, header)
    try:
        devices.open_all()
    except BaseException:
        session.close(final_state="idle", error="devices could not be opened")
        _close_outputs(igtl, live)
        raise
    operator = ConsoleOperator()
    # The very controller `hil run` builds (locator, rig, limits, watchdogs, needle check, tracker use).
    try:
        hooks = runtime_plugins(igtl, the_plan)
        if live is not None:
            from hil.replay.live import PLUGIN_NAME as LIVE_PLUGIN

            hooks.register(live, LIVE_PLUGIN)
        ctl = build_controller(setup, the_plan, devices, clock=clk, session=session, operator=operator,
                               hooks=hooks)
        if live is not None:   # the simulator's true positions too (one attribute read a tick)
            meter = ctl.truth_meter
            live.follow_truth(lambda: meter.last_positions)
    except BaseException:   # the servo process and every opened device are closed, the log says why
        devices.close_all()
        session.close(final_state="idle", error="the controller could not be built")
        _close_outputs(igtl, live)
        raise
    runner = ControllerRunner(ctl, operator, pace=isinstance(clk, ManualClock) and not fast, igtl=igtl,
                              session_log=str(session.path))
    runner.start()
    return ConsoleSession(config_path, setup, the_plan, devices, session, ctl, operator, runner, igtl, clk,
                          viewer=live)
