"""The dashboard server's commands (port 29999): one command line in, one reply line out.

The replies follow Universal Robots' dashboard server command lists (CB3 3.x, e-Series 5.x) for the
commands a client uses; the controller model acts on them. No sockets here (the server reads lines).
"""

from __future__ import annotations

from emulators.ursim.controller import RuntimeState, SafetyMode, UrController


def dashboard_reply(ctl: UrController, line: str) -> tuple[str, bool]:
    """The reply line to one dashboard command line, and whether the server then closes the
    connection (``quit``). A command it does not know gets ``could not understand: '<line>'``."""
    cmd = line.lower()
    v = ctl.version
    prog = ctl.program.name + ".urp" if ctl.program else "<unnamed>"
    if cmd == "polyscopeversion":
        return f"URSoftware {v} (Nov 21 2026)", False
    if cmd == "get serial number":
        return "20265500001", False
    if cmd == "get robot model":
        return "UR3", False
    if cmd == "is in remote control":
        return "true", False
    if cmd == "get operational mode" and not v.is_cb3:
        # e-Series command list (5.6+): MANUAL / AUTOMATIC when a mode password is set, else NONE;
        # CB3's list has no such command (the unknown-command answer below)
        return "NONE", False
    if cmd == "stop":
        ctl.dashboard_stop()
        return "Stopped", False
    if cmd == "play":
        return ("Starting program", False) if ctl.dashboard_play() else ("Failed to execute: play", False)
    if cmd == "pause":
        ctl.dashboard_pause()
        return "Pausing program", False
    if cmd == "unlock protective stop":
        if ctl.unlock_protective_stop():
            return "Protective stop releasing", False
        return "Cannot unlock protective stop: the robot is in emergency stop", False
    if cmd == "close safety popup":
        return "closing safety popup", False
    if cmd == "power on":
        return ("Powering on", False) if ctl.power_on() else ("Failed to execute: power on", False)
    if cmd == "power off":
        ctl.power_off()
        return "Powering off", False
    if cmd == "brake release":
        return ("Brake releasing", False) if ctl.brake_release() else ("Failed to execute: brake release",
                                                                        False)
    if cmd == "robotmode":
        return f"Robotmode: {ctl.robot_mode.name}", False
    if cmd == "safetymode":
        return f"Safetymode: {ctl.safety_mode.name}", False
    if cmd == "safetystatus":
        return f"Safetystatus: {ctl.safety_mode.name}", False
    if cmd == "programstate":
        state = "PLAYING" if ctl.runtime_state is RuntimeState.PLAYING else (
            "PAUSED" if ctl.runtime_state is RuntimeState.PAUSED else "STOPPED")
        return f"{state} {prog}", False
    if cmd == "running":
        return f"Program running: {str(ctl.runtime_state is RuntimeState.PLAYING).lower()}", False
    if cmd == "get loaded program":
        return f"Loaded program: /programs/{prog}", False
    if cmd == "isprogramsaved":
        return f"true {prog}", False
    if cmd == "restart safety":
        if ctl.safety_mode is SafetyMode.PROTECTIVE_STOP:
            ctl.unlock_protective_stop()
        ctl.power_off()
        return "Restarting safety", False
    if cmd.startswith("addtolog"):
        return "Added log message", False
    if cmd.startswith("popup"):
        return "showing popup", False
    if cmd == "close popup":
        return "closing popup", False
    if cmd.startswith("setuserrole"):
        return "Setting user role: " + line.split(" ", 1)[-1], False
    if cmd.startswith("load "):
        return f"File not found: {line[5:]}", False
    if cmd == "quit":
        return "Disconnected", True
    if cmd == "shutdown":
        return "Shutting down", False
    return f"could not understand: '{line}'", False
