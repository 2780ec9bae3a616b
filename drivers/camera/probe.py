"""``hil probe`` for the built-in stereo cameras: are the devices there? The Aravis device list
holds both cameras (``driver = "aravis"``), both V4L2 nodes exist and are accessible (``v4l2``), the
recording directory and its ``timestamps.csv`` exist (``replay``).

Registered through ``hil_register_probes`` (:mod:`drivers.camera.plugin`); the driver-level checks
(open, grab for a window: resolution, frame rate, skew, dropped frames) follow.
"""

from __future__ import annotations

import os
from pathlib import Path

from drivers.camera.config import AravisCameraConfig, ReplayCameraConfig, V4l2CameraConfig
from hil.probe.context import ProbeContext
from hil.probe.runner import Checklist, Finding, Outcome

_VIDEO_GROUP_HINT = ("add your user to the group owning the device (usually video): "
                     "sudo usermod -aG video $USER, then log out and in")


def probe_aravis(cl: Checklist, cfg: AravisCameraConfig, ctx: ProbeContext) -> None:
    """Step ``devices_found``: the Aravis device list (2 x the timeout: discovery is slow)."""
    cl.step("devices_found", lambda: _aravis_devices(cfg), timeout_s=2 * ctx.timeout_s + 1.0,
            what="listing Aravis devices")


def probe_v4l2(cl: Checklist, cfg: V4l2CameraConfig, ctx: ProbeContext) -> None:
    """Step ``devices_found``: the V4L2 device nodes (or the video files with ``source = "file"``)."""
    cl.step("devices_found", lambda: _v4l2_devices(cfg), what="looking for the V4L2 devices")


def probe_replay(cl: Checklist, cfg: ReplayCameraConfig, ctx: ProbeContext) -> None:
    """Step ``recording_found``: the recording directory and its ``timestamps.csv``."""
    cl.step("recording_found", lambda: _replay_files(cfg, ctx.setup.config_dir),
            what="looking for the recording")


def _aravis_devices(cfg: AravisCameraConfig) -> Outcome:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise Finding(f"Aravis is not available here ({exc})",
                      "install the 'aravis' extra and the Debian packages gir1.2-aravis-0.8 "
                      "libaravis-0.8-0 (tools/setup_aravis.sh)") from None
    if cfg.enable_fake_interface:
        Aravis.enable_interface("Fake")
    Aravis.update_device_list()
    found: list[dict[str, str]] = []
    for i in range(Aravis.get_n_devices()):
        found.append({"id": str(Aravis.get_device_id(i)),
                      "serial": str(Aravis.get_device_serial_nbr(i) or ""),
                      "address": str(Aravis.get_device_address(i) or ""),
                      "model": str(Aravis.get_device_model(i) or "")})
    wanted = {"left": str(cfg.left_device_id), "right": str(cfg.right_device_id)}
    missing = [f"{side} {dev_id!r}" for side, dev_id in wanted.items()
               if not any(dev_id in (d["id"], d["serial"], d["address"]) for d in found)]
    listing = "; ".join(f"{d['id']} at {d['address']}" for d in found) or "none"
    data = {"found": found, "wanted": wanted}
    if missing:
        raise Finding(f"Aravis does not list the {' and '.join(missing)} camera(s); it lists: {listing}",
                      "GigE: is the camera powered (PoE), on this PC's subnet (arv-tool-0.8 lists what "
                      "answers discovery), not held by another program? USB3: plugged into a USB3 port? "
                      "ids may be the device id, serial number or IP address", data)
    return Outcome(f"Aravis lists both cameras ({wanted['left']}, {wanted['right']})", data=data)


def _node_problem(path: str) -> str | None:
    if not os.path.exists(path):
        return f"{path} does not exist"
    if not os.access(path, os.R_OK | os.W_OK):
        return f"no read/write permission on {path}"
    return None


def _v4l2_devices(cfg: V4l2CameraConfig) -> Outcome:
    paths = [p for p in (cfg.left_device, cfg.right_device, cfg.side_by_side_device) if p is not None]
    if cfg.source == "file":
        missing = [p for p in paths if not os.path.isfile(p)]
        if missing:
            raise Finding(f"video file(s) not found: {', '.join(missing)}", "check the paths in [camera]")
        return Outcome(f"video files found: {', '.join(paths)} (source = file)")
    problems = [p for p in (_node_problem(path) for path in paths) if p is not None]
    if problems:
        nodes = sorted(str(p) for p in Path("/dev").glob("video*"))
        hint = _VIDEO_GROUP_HINT if all("permission" in p for p in problems) else (
            "is the camera plugged in? video devices here: " + (", ".join(nodes) or "none")
            + "\n(v4l2-ctl --list-devices names them; prefer /dev/v4l/by-id/... paths)")
        raise Finding("; ".join(problems), hint, {"video_devices": nodes})
    return Outcome(f"V4L2 device(s) present and accessible: {', '.join(paths)}")


def _replay_files(cfg: ReplayCameraConfig, config_dir: Path) -> Outcome:
    path = Path(cfg.recording_dir)
    if not path.is_absolute():
        path = config_dir / path
    if not path.is_dir():
        raise Finding(f"recording directory {path} does not exist", "check [camera] recording_dir")
    stamps = path / "timestamps.csv"
    if not stamps.is_file():
        raise Finding(f"{path} holds no timestamps.csv: not a recording",
                      "point recording_dir at a directory the recorder wrote")
    with stamps.open(encoding="utf-8", errors="replace") as f:
        n_lines = max(0, sum(1 for _ in f) - 1)
    return Outcome(f"recording {path} found ({n_lines} pairs listed)", data={"pairs_listed": n_lines})
