"""Driver-level checks of any stereo camera (simulated, real, plugin): the driver opens and grabs
pairs for a short window: resolution, frame rate achieved versus configured, left/right timestamp
skew (median, max) and frames dropped (gaps in frame ids).

Whether the devices are there (Aravis device list, V4L2 nodes, replay files) is the driver's own
probe, registered through ``hil_register_probes`` (the built-in cameras': ``drivers.camera``).
"""

from __future__ import annotations

import itertools
import statistics

from pydantic import BaseModel

from drivers.interfaces.camera import StereoCamera, StereoFrame
from hil.probe.context import ProbeContext, build_step, close_quietly, open_step
from hil.probe.report import Check, Status
from hil.probe.runner import Checklist, Outcome
from plugins.registry import DriverInfo


def camera_driver_checks(
    cl: Checklist, ctx: ProbeContext, cfg: BaseModel, info: DriverInfo, role: str,
) -> None:
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
