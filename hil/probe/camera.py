"""Probe a stereo camera: the devices are there (Aravis device list, V4L2 nodes, replay files),
then the driver opens and grabs pairs for a short window: resolution, frame rate achieved versus
configured, left/right timestamp skew (median, max) and frames dropped (gaps in frame ids).
"""

from __future__ import annotations

import itertools
import os
import statistics
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from drivers.interfaces.camera import StereoCamera, StereoFrame
from hil.probe.context import ProbeContext, build_step, close_quietly, open_step
from hil.probe.report import Check, DeviceReport, Status
from hil.probe.runner import Checklist, Finding, Outcome
from plugins.registry import DriverInfo

_VIDEO_GROUP_HINT = ("add your user to the group owning the device (usually video): "
                     "sudo usermod -aG video $USER, then log out and in")


def probe_camera(ctx: ProbeContext, cfg: BaseModel, info: DriverInfo, role: str = "camera") -> DeviceReport:
    report = DeviceReport(role, info.name, info.simulated)
    cl = Checklist(report, ctx.timeout_s)
    if info.simulated:
        cl.step("simulated", lambda: Outcome("simulated stereo camera: no hardware, checking that it starts"))
    elif info.name == "aravis":
        cl.step("devices_found", lambda: _aravis_devices(cfg), timeout_s=2 * ctx.timeout_s + 1.0,
                what="listing Aravis devices")
    elif info.name == "v4l2":
        cl.step("devices_found", lambda: _v4l2_devices(cfg), what="looking for the V4L2 devices")
    elif info.name == "replay":
        cl.step("recording_found", lambda: _replay_files(cfg, ctx.setup.config_dir),
                what="looking for the recording")
    if not cl.failed:
        _driver_checks(cl, ctx, cfg, info, role)
    return report


# ------------------------------------------------------------------------------------- presence
def _aravis_devices(cfg: Any) -> Outcome:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise Finding(f"Aravis is not available here ({exc})",
                      "install the 'aravis' extra and the Debian packages gir1.2-aravis-0.8 "
                      "libaravis-0.8-0 (tools/setup_aravis.sh)") from None
    if getattr(cfg, "enable_fake_interface", False):
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


def _v4l2_devices(cfg: Any) -> Outcome:
    paths = [p for p in (cfg.left_device, cfg.right_device, cfg.side_by_side_device) if p is not None]
    if getattr(cfg, "source", "device") == "file":
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


def _replay_files(cfg: Any, config_dir: Path) -> Outcome:
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


# ---------------------------------------------------------------------------------------- driver
def _driver_checks(cl: Checklist, ctx: ProbeContext, cfg: BaseModel, info: DriverInfo, role: str) -> None:
    device = build_step(cl, ctx, role, cfg, info)
    if device is None:
        return
    if not isinstance(device, StereoCamera):
        cl.report.add(Check("driver_builds", Status.FAIL,
                            f"driver {info.name} did not build a stereo camera"))
        return
    try:
        if not open_step(cl, device, cfg, f"{info.name} camera"):
            return
        window_s = ctx.window_s

        def grab() -> Outcome:
            device.grab(cl.timeout_s)  # the first pair may be slow (buffers, rendering set-up)
            pairs: list[StereoFrame] = []
            clock = ctx.clock  # a ManualClock (all-simulated setup) advances in the simulated grab
            t_end_ns = clock.now_ns() + round(window_s * 1e9)
            while clock.now_ns() < t_end_ns or len(pairs) < 2:
                pairs.append(device.grab(cl.timeout_s))
                if len(pairs) >= 2000:
                    break
            return Outcome(f"grabbed {len(pairs)} stereo pairs in {window_s:g} s (after a first one)",
                           value=pairs)

        out = cl.step("grab", grab, timeout_s=window_s + 3 * cl.timeout_s, what="grabbing stereo pairs",
                      timeout_hint="no frames: trigger wiring/mode, exposure longer than the frame period, "
                                   "GigE packet loss (MTU, packet size), another program streaming")
        if out is None:
            return
        for check in frame_checks(out.value, device.image_size, device.frame_rate_hz):
            cl.report.add(check)
    finally:
        close_quietly(device, cl.timeout_s)


def frame_checks(pairs: list[StereoFrame], configured_size: tuple[int, int],
                 configured_rate_hz: float) -> list[Check]:
    """Resolution, achieved frame rate, left/right skew and dropped frames of a grab window."""
    out: list[Check] = []
    h_l, w_l = pairs[0].left.image.shape[:2]
    h_r, w_r = pairs[0].right.image.shape[:2]
    size_data = {"left_px": [w_l, h_l], "right_px": [w_r, h_r], "configured_px": list(configured_size)}
    if (w_l, h_l) != (w_r, h_r):
        out.append(Check("resolution", Status.FAIL, f"left is {w_l}x{h_l} px but right is {w_r}x{h_r} px",
                         "both cameras must deliver the same region: check their settings", size_data))
    elif (w_l, h_l) != tuple(configured_size):
        out.append(Check("resolution", Status.WARN,
                         f"images are {w_l}x{h_l} px, configured "
                         f"{configured_size[0]}x{configured_size[1]} px",
                         "the device did not accept the configured size; the calibration must match "
                         "what it delivers", size_data))
    else:
        out.append(Check("resolution", Status.OK, f"resolution {w_l}x{h_l} px, as configured",
                         data=size_data))
    t = [p.t_ns for p in pairs]
    span_s = (t[-1] - t[0]) * 1e-9
    rate = (len(pairs) - 1) / span_s if span_s > 0 else None
    rate_data = {"pairs": len(pairs), "rate_hz": None if rate is None else round(rate, 2),
                 "configured_hz": configured_rate_hz}
    if rate is None:
        out.append(Check("frame_rate", Status.WARN, "frame rate: the pairs carry no increasing timestamps",
                         "", rate_data))
    elif rate < 0.9 * configured_rate_hz:
        out.append(Check("frame_rate", Status.WARN,
                         f"frame rate {rate:.1f} Hz achieved, configured {configured_rate_hz:g} Hz",
                         "exposure longer than the frame period? bandwidth (GigE packet size / USB hub)? "
                         "the host too slow to keep up?", rate_data))
    else:
        out.append(Check("frame_rate", Status.OK,
                         f"frame rate {rate:.1f} Hz achieved (configured {configured_rate_hz:g} Hz)",
                         data=rate_data))
    skews_ms = [abs(p.skew_ns) * 1e-6 for p in pairs]
    med, worst = statistics.median(skews_ms), max(skews_ms)
    period_ms = 1000.0 / configured_rate_hz
    skew_data = {"median_ms": round(med, 3), "max_ms": round(worst, 3)}
    if worst > 0.5 * period_ms:
        out.append(Check("skew", Status.WARN,
                         f"left/right timestamp skew median {med:.2f} ms, max {worst:.2f} ms "
                         f"(over half a frame period, {period_ms:.1f} ms)",
                         "the pair is not synchronised: use a common (hardware) trigger, or pairing by "
                         "trigger/frame id", skew_data))
    else:
        out.append(Check("skew", Status.OK,
                         f"left/right timestamp skew median {med:.2f} ms, max {worst:.2f} ms",
                         data=skew_data))
    dropped = sum(max(0, b.left.seq - a.left.seq - 1) for a, b in itertools.pairwise(pairs))
    drop_data = {"dropped": dropped, "pairs": len(pairs)}
    if dropped:
        out.append(Check("dropped_frames", Status.WARN,
                         f"{dropped} frame(s) dropped in the window (gaps in frame ids)",
                         "bandwidth or host load: lower the frame rate or resolution, raise the GigE "
                         "packet size / socket buffer, close other programs", drop_data))
    else:
        out.append(Check("dropped_frames", Status.OK, "no frame dropped (frame ids consecutive)",
                         data=drop_data))
    return out
