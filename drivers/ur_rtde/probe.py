"""``hil probe`` for a UR over RTDE (``driver = "ur_rtde"``), read-only, over plain sockets with
timeouts, so an unreachable robot is one clear line rather than a library hang: the host
resolves; TCP 30004 (RTDE), 29999 (dashboard), 30003 (script) accept; the RTDE controller version
(CB3 3.x -> 125 Hz, e-Series 5.x -> 500 Hz) matches the config; the RTDE stream runs at that rate;
then, from the dashboard, safety mode, robot mode, remote control (e-Series) and whether a program
runs.

Registered through ``hil_register_probes`` (:mod:`drivers.ur_rtde.plugin`) with
``driver_checks=False``: the probe never opens the driver, as that would start a control script on
the robot. It never moves the arm, uploads a script or takes control.
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any

from drivers.ur_rtde import probe_wire as uw
from drivers.ur_rtde import wire
from drivers.ur_rtde.config import UrRtdeRobotConfig
from hil.probe.context import ProbeContext
from hil.probe.report import Status
from hil.probe.runner import Checklist, Finding, Outcome

_PORT_ROLE = {wire.RTDE_PORT: "RTDE", wire.DASHBOARD_PORT: "dashboard", wire.SCRIPT_PORT: "script"}
_FAMILY_TEXT = {"cb3": f"CB3 (PolyScope 3.x, RTDE {wire.CONTROLLER_RATE_HZ['cb3']:g} Hz)",
                "e_series": f"e-Series (PolyScope 5.x, RTDE {wire.CONTROLLER_RATE_HZ['e_series']:g} Hz)"}
#: Safety modes in which the arm moves (the dashboard names them like RTDE's ``safety_mode``).
_MOVING_SAFETY_MODES = (wire.SafetyModeCode.NORMAL.name, wire.SafetyModeCode.REDUCED.name)
_SAFETY_HINT = {
    "PROTECTIVE_STOP": "find what stopped the arm (collision, limit), then press 'unlock protective stop' "
                       "on the teach pendant",
    "SAFEGUARD_STOP": "the safeguard input is open (door, light curtain): close it / reset it",
    "AUTOMATIC_MODE_SAFEGUARD_STOP": "the automatic-mode safeguard input is open: close it / reset it",
    "ROBOT_EMERGENCY_STOP": "release the emergency-stop button on the teach pendant, then reset it there",
    "SYSTEM_EMERGENCY_STOP": "release the system emergency stop (external e-stop circuit), then reset",
    "VIOLATION": "a safety limit was violated: restart safety from the teach pendant",
    "FAULT": "the safety system reports a fault: restart safety from the pendant; see the log tab",
    "RECOVERY": "the arm is outside its safety limits: jog it back inside in recovery mode",
}
_MODE_HINT = {
    "POWER_OFF": "power the arm on and release the brakes (teach pendant: ON, then START)",
    "POWER_ON": "release the brakes (teach pendant: START)",
    "IDLE": "release the brakes (teach pendant: START)",
    "BOOTING": "the arm is booting: wait and probe again",
    "CONFIRM_SAFETY": "confirm the safety configuration on the teach pendant",
    "BACKDRIVE": "leave backdrive mode on the teach pendant",
    "DISCONNECTED": "the controller does not see the arm: check the arm cable, restart the controller",
    "NO_CONTROLLER": "the controller software is not running: restart it",
    "UPDATING_FIRMWARE": "wait for the firmware update to finish",
}


def probe_ur(cl: Checklist, cfg: UrRtdeRobotConfig, ctx: ProbeContext) -> None:
    """Steps ``host_resolves``, ``tcp_30004``/``tcp_29999``/``tcp_30003``, ``rtde_version``,
    ``rtde_stream``, then the dashboard's (``dashboard``, ``safety_mode``, ``robot_mode``,
    ``remote_control`` on an e-Series, ``program``); every socket is closed on return."""
    t = cl.timeout_s
    host = cfg.host
    if cl.step("host_resolves", lambda: _resolves(host), what=f"resolving {host}") is None:
        return
    for port in (wire.RTDE_PORT, wire.DASHBOARD_PORT, wire.SCRIPT_PORT):
        if cl.step(f"tcp_{port}", _tcp(host, port, t), timeout_s=t + 1.0,
                   what=f"connecting to {host}:{port} ({_PORT_ROLE[port]})") is None:
            return
    out = cl.step("rtde_version", lambda: _version(cfg, t), timeout_s=2 * t + 1.0,
                  what=f"RTDE handshake with {host}")
    if out is None:
        return
    window_s = ctx.window_s
    if cl.step("rtde_stream", lambda: _stream(cfg, t, window_s), timeout_s=window_s + 2 * t + 1.0,
               what="reading the RTDE stream") is None:
        return
    _dashboard_checks(cl, host, out.value)


def _resolves(host: str) -> Outcome:
    try:
        addrs = uw.resolve(host)
    except (socket.gaierror, UnicodeError) as exc:
        raise Finding(f"robot host {host!r} does not resolve ({exc})",
                      "check [robot] host; use the IP address the teach pendant shows "
                      "(Settings > System > Network)") from None
    return Outcome(f"host {host} resolves to {', '.join(addrs)}", data={"addresses": addrs})


def _version(cfg: UrRtdeRobotConfig, timeout_s: float) -> Outcome:
    host = cfg.host
    rtde = uw.RtdeProbe(host, timeout_s)
    try:
        if not rtde.request_protocol_version(wire.PROTOCOL_VERSION):
            raise Finding(f"the controller refuses RTDE protocol version {wire.PROTOCOL_VERSION}",
                          "PolyScope is older than 3.4: update the controller software")
        v = rtde.controller_version()
    except uw.WireError as exc:
        raise Finding(f"RTDE on {host}:{wire.RTDE_PORT} does not answer the protocol: {exc}",
                      "is this a UR controller? is another program using all RTDE connections?") from None
    finally:
        rtde.close()
    want = str(cfg.controller)
    data = {"controller_version": str(v), "family": v.family, "rtde_rate_hz": v.rtde_rate_hz,
            "configured": want}
    text = f"controller version {v}: {_FAMILY_TEXT.get(v.family, 'unknown family')}"
    if v.family == "other":
        raise Finding(f"{text}; only CB3 (3.x) and e-Series (5.x) are supported", "", data)
    if want and want != v.family:
        raise Finding(f"{text}, but the config says controller = {want!r}",
                      f"set controller = {v.family!r} in [robot] (RTDE rate {v.rtde_rate_hz:g} Hz)", data)
    return Outcome(f"{text}, as configured", data=data, value=v)


def _stream(cfg: UrRtdeRobotConfig, timeout_s: float, window_s: float) -> Outcome:
    rate = cfg.rate_hz
    rtde = uw.RtdeProbe(cfg.host, timeout_s)
    try:
        rtde.request_protocol_version(wire.PROTOCOL_VERSION)
        stats = rtde.stream(rate, window_s)
    except uw.WireError as exc:
        raise Finding(f"the RTDE data stream does not run: {exc}",
                      "restart the controller; check that nothing floods its network link") from None
    finally:
        rtde.close()
    data: dict[str, Any] = {"packages": stats.packages, "requested_hz": rate,
                            "rate_hz": None if stats.rate_hz is None else round(stats.rate_hz, 1)}
    if stats.rate_hz is None:
        return Outcome(f"RTDE stream: {stats.packages} package(s) in {window_s:g} s (too few for a rate)",
                       Status.WARN, "probe again with a longer window", data)
    if abs(stats.rate_hz - rate) > 0.1 * rate:
        return Outcome(f"RTDE stream at {stats.rate_hz:.0f} Hz (controller clock), asked {rate:g} Hz",
                       Status.WARN, "the controller is overloaded or the rate is not what the "
                                    "config assumes", data)
    return Outcome(f"RTDE streams at {stats.rate_hz:.0f} Hz (controller clock; {stats.packages} packages "
                   f"in {window_s:g} s)", data=data)


def _tcp(host: str, port: int, timeout_s: float) -> Callable[[], Outcome]:
    def connect() -> Outcome:
        try:
            dt = uw.tcp_connect(host, port, timeout_s)
        except ConnectionRefusedError:
            raise Finding(f"{host}:{port} ({_PORT_ROLE[port]}) refuses connections",
                          "the host is up but nothing listens there: is it the robot controller? is "
                          "PolyScope running? (e-Series: Settings > Security > Services must enable it)"
                          ) from None
        except TimeoutError:
            raise Finding(f"no answer from {host}:{port} ({_PORT_ROLE[port]}) within {timeout_s:g} s",
                          "is the controller on? is the address right and on this PC's subnet "
                          "(ping it)? a firewall?") from None
        except OSError as exc:
            raise Finding(f"cannot reach {host}:{port} ({_PORT_ROLE[port]}): {exc.strerror or exc}",
                          "check the network cable and this PC's address/route to the robot") from None
        return Outcome(f"{host}:{port} ({_PORT_ROLE[port]}) accepts connections ({dt * 1000:.0f} ms)",
                       data={"connect_ms": round(dt * 1000, 1)})

    return connect


def _dashboard_checks(cl: Checklist, host: str, v: uw.ControllerVersion) -> None:
    t = cl.timeout_s
    dash: list[uw.DashboardProbe] = []

    def connect() -> Outcome:
        try:
            d = uw.DashboardProbe(host, t)
            polyscope = d.ask("PolyscopeVersion")
        except uw.WireError as exc:
            raise Finding(f"dashboard server: {exc}", "restart PolyScope") from None
        dash.append(d)
        return Outcome(f"dashboard server answers ({polyscope})", data={"polyscope": polyscope})

    try:
        if cl.step("dashboard", connect, timeout_s=2 * t + 1.0, what="dashboard server") is None:
            return
        d = dash[0]

        def safety() -> Outcome:
            reply = d.ask("safetystatus")
            if ":" not in reply:  # before 5.4 / CB3
                reply = d.ask("safetymode")
            mode = reply.split(":", 1)[-1].strip().upper()
            if mode in _MOVING_SAFETY_MODES:
                return Outcome(f"safety mode {mode}", data={"safety_mode": mode})
            raise Finding(f"safety mode {mode}: the arm will not move", _SAFETY_HINT.get(mode, ""),
                          {"safety_mode": mode})

        if cl.step("safety_mode", safety, what="asking the safety mode") is None:
            return

        def robot_mode() -> Outcome:
            mode = d.ask("robotmode").split(":", 1)[-1].strip().upper()
            if mode == wire.RobotModeCode.RUNNING.name:
                return Outcome("robot mode RUNNING (powered, brakes released)", data={"robot_mode": mode})
            raise Finding(f"robot mode {mode}: not ready to move", _MODE_HINT.get(mode, ""),
                          {"robot_mode": mode})

        if cl.step("robot_mode", robot_mode, what="asking the robot mode") is None:
            return
        if v.family == "e_series":
            def remote() -> Outcome:
                reply = d.ask("is in remote control").strip().lower()
                if reply == "true":
                    return Outcome("remote control enabled", data={"remote_control": True})
                if reply == "false":
                    raise Finding("the arm is in local control: hil cannot start its control script",
                                  "on the teach pendant switch to Remote Control (enable it in Settings > "
                                  "System > Remote Control, then pick it in the header)",
                                  {"remote_control": False})
                return Outcome(f"remote control: cannot tell ({reply!r}; PolyScope < 5.6?)", Status.WARN,
                               "check that the pendant is in Remote Control")

            if cl.step("remote_control", remote, what="asking for remote control") is None:
                return

        def program() -> Outcome:
            running = d.ask("running").split(":", 1)[-1].strip().lower() == "true"
            if running:
                loaded = d.ask("get loaded program")
                return Outcome(f"a program is running ({loaded})", Status.WARN,
                               "hil stops it and starts its own control script when it connects; "
                               "stop it on the pendant if it must not be interrupted",
                               {"program_running": True})
            return Outcome("no program running (hil starts its control script when it connects)",
                           data={"program_running": False})

        cl.step("program", program, what="asking whether a program runs")
    finally:
        for d in dash:
            d.close()
