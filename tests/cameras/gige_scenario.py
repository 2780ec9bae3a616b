"""GigE Vision scenarios run in a private network namespace (``unshare -n``), one process each.

A stereo pair of fake GigE cameras needs two local addresses (GVCP port 3956 is fixed); inside
``unshare -n`` we own ``lo`` and add 127.0.0.2. The namespace also keeps these tests from
meeting other fake cameras on the machine. Run by tests/cameras/test_aravis_gige.py:

    unshare -n python tests/cameras/gige_scenario.py binary|images WORKDIR

The last stdout line is ``RESULT {json}``; the test asserts on it. Not collected by pytest.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tools")]

from drivers.camera.aravis import AravisStereoCamera, import_aravis  # noqa: E402
from drivers.camera.config import AravisCameraConfig  # noqa: E402
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError  # noqa: E402
from hil.clock import MonotonicClock  # noqa: E402

FAKE_BIN = "arv-fake-gv-camera-0.8"


def setup_loopback() -> None:
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    subprocess.run(["ip", "addr", "add", "127.0.0.2/8", "dev", "lo"], check=True)


def wait_for_devices(ids: set[str], timeout_s: float = 10.0) -> None:
    Aravis, _ = import_aravis()
    deadline = time.monotonic() + timeout_s
    while True:
        Aravis.update_device_list()
        found = {Aravis.get_device_id(i) for i in range(Aravis.get_n_devices())}
        if ids <= found:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"fake cameras {sorted(ids - found)} not discovered (found {sorted(found)})")
        time.sleep(0.1)


def config(**kw: Any) -> AravisCameraConfig:
    base: dict[str, Any] = {"driver": "aravis", "left_device_id": "127.0.0.1",
                            "right_device_id": "127.0.0.2", "width_px": 640, "height_px": 480,
                            "frame_rate_hz": 50.0, "exposure_us": 10000.0}
    base.update(kw)
    return AravisCameraConfig(**base)


def ramp_offset(image: np.ndarray) -> int | None:
    """The fake camera's ramp: pixel = (x + y + frame_id) % 255 (exposure 10 ms, gain 0).
    Returns frame_id % 255 when the whole image is that ramp, else None."""
    h, w = image.shape
    offset = int(image[0, 0])
    yy, xx = np.mgrid[0:h, 0:w]
    return offset if np.array_equal(image, ((xx + yy + offset) % 255).astype(np.uint8)) else None


def scenario_binary() -> dict[str, Any]:
    procs = [subprocess.Popen([FAKE_BIN, "-i", addr, "-s", serial], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
             for addr, serial in (("127.0.0.1", "GV01"), ("127.0.0.2", "GV02"))]
    out: dict[str, Any] = {}
    try:
        wait_for_devices({"Aravis-Fake-GV01", "Aravis-Fake-GV02"})
        clock = MonotonicClock()
        # Software trigger: one frame per trigger, paired by trigger id.
        cam = AravisStereoCamera("camera", config(trigger="software"), clock)
        cam.open()
        pairs = [cam.grab(2.0) for _ in range(12)]
        out["software"] = {
            "rule": str(cam.pair_rule),
            "left_seq": [p.left.seq for p in pairs], "right_seq": [p.right.seq for p in pairs],
            "left_ramp": [ramp_offset(p.left.image) for p in pairs],
            "right_ramp": [ramp_offset(p.right.image) for p in pairs],
            "shape": list(pairs[0].left.image.shape), "dtype": str(pairs[0].left.image.dtype),
            "device_t_ns_present": all(p.left.device_t_ns and p.right.device_t_ns for p in pairs),
            "t_ns_increasing": all(b.t_ns > a.t_ns for a, b in itertools.pairwise(pairs)),
            "stats": cam.stats,
        }
        cam.close()
        # Free run at 50 Hz: paired by device time (the fake cameras' clocks are the host wall clock).
        cam = AravisStereoCamera("camera", config(trigger="free_run", device_clocks_synchronised=True), clock)
        cam.open()
        t0 = time.monotonic()
        pairs = [cam.grab(2.0) for _ in range(25)]
        elapsed = time.monotonic() - t0
        out["free_run"] = {
            "rule": str(cam.pair_rule),
            "device_skew_ns": [p.right.device_t_ns - p.left.device_t_ns for p in pairs],  # type: ignore[operator]
            "host_skew_ns": [p.skew_ns for p in pairs],
            "left_seq": [p.left.seq for p in pairs],
            "pairs_per_s": 25 / elapsed,
            "left_ramp": [ramp_offset(p.left.image) for p in pairs],
            "right_ramp": [ramp_offset(p.right.image) for p in pairs],
        }
        cam.close()
        cam = AravisStereoCamera("camera", config(trigger="free_run", pairing="host_time"), clock)
        cam.open()
        pairs = [cam.grab(2.0) for _ in range(10)]
        out["host_time"] = {"rule": str(cam.pair_rule), "host_skew_ns": [p.skew_ns for p in pairs]}
        cam.close()
        # Unknown device: typed error naming it.
        t_unknown = time.monotonic()
        try:
            AravisStereoCamera("camera", config(right_device_id="Aravis-Fake-NOPE"), clock).open()
            out["unknown"] = None
        except DisconnectedError as exc:
            out["unknown"] = str(exc)
        out["unknown_s"] = time.monotonic() - t_unknown
        # Disconnect: the right camera dies mid-session.
        cam = AravisStereoCamera("camera", config(trigger="software"), clock)
        cam.open()
        cam.grab(2.0)
        procs[1].send_signal(signal.SIGKILL)
        procs[1].wait()
        errors: list[list[str]] = []
        t_kill = time.monotonic()
        for _ in range(40):
            try:
                cam.grab(0.5)
                errors.append(["pair", ""])
            except (DeviceTimeoutError, DisconnectedError) as exc:
                errors.append([type(exc).__name__, str(exc)])
                if isinstance(exc, DisconnectedError):
                    break
        out["disconnect"] = {"errors": errors, "seconds_to_disconnected": time.monotonic() - t_kill}
        t_close = time.monotonic()
        cam.close()
        out["disconnect"]["close_s"] = time.monotonic() - t_close
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(5)
    return out


def render_pairs(workdir: Path) -> dict[str, Any]:
    """Two stereo pairs of 6 ring markers (the second moved 5 mm along x) as PNGs + truth."""
    from hil.vision.camera_model import StereoCalibration, save_calibration
    from hil.vision.render import RenderOptions, markers_on_patch, render_stereo

    size = (1280, 720)
    cal = StereoCalibration.synthetic(f_px=1394.0 * size[0] / 1920, baseline_mm=120.0, image_size=size)
    save_calibration(cal, workdir / "calibration.json")
    centers = np.array([[-40.0, -30.0, 600.0], [10.0, -35.0, 620.0], [60.0, -20.0, 590.0],
                        [-30.0, 25.0, 610.0], [20.0, 30.0, 640.0], [70.0, 20.0, 600.0]])
    truth = []
    rng = np.random.default_rng(7)
    for k, shift in enumerate((0.0, 5.0)):
        c = centers + np.array([shift, 0.0, 0.0])
        pair = render_stereo(cal, markers_on_patch(c), RenderOptions(), rng)
        cv2.imwrite(str(workdir / f"left_{k:03d}.png"), pair.left)
        cv2.imwrite(str(workdir / f"right_{k:03d}.png"), pair.right)
        truth.append(c.tolist())
    return {"size": size, "truth": truth}


def detect_ring_centres(image: np.ndarray) -> np.ndarray:
    """Dark rings on light skin: Otsu threshold, outer contours, ``cv2.fitEllipse`` centres (N, 2)."""
    blur = cv2.GaussianBlur(image, (5, 5), 1.0)
    _, dark = cv2.threshold(blur, 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    centres = []
    for cnt in contours:
        if len(cnt) < 12 or cv2.contourArea(cnt) < 30:
            continue
        (cx, cy), (a, b), _ = cv2.fitEllipse(cnt)
        if min(a, b) / max(a, b) > 0.5:
            centres.append((cx, cy))
    return np.array(centres, dtype=np.float64).reshape(-1, 2)


def triangulate(cal: Any, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Match along rows (the synthetic rig is rectified) and triangulate (DLT, cv2)."""
    uv_l, uv_r = detect_ring_centres(left), detect_ring_centres(right)
    pts_l, pts_r = [], []
    for u, v in uv_l:
        dy = np.abs(uv_r[:, 1] - v)
        disparity = u - uv_r[:, 0]
        ok = (dy < 2.0) & (disparity > 0)
        if ok.sum() == 1:
            j = int(np.flatnonzero(ok)[0])
            pts_l.append((u, v))
            pts_r.append(tuple(uv_r[j]))
    if not pts_l:
        return np.zeros((0, 3))
    X = cv2.triangulatePoints(cal.P_left(), cal.P_right(), np.array(pts_l).T, np.array(pts_r).T)
    return np.asarray((X[:3] / X[3]).T, dtype=np.float64)


def scenario_images(workdir: Path) -> dict[str, Any]:
    from hil.vision.camera_model import load_calibration
    from hil.vision.pipeline import locate_markers

    scene = render_pairs(workdir)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "tools"), str(ROOT)]))
    server = subprocess.Popen([sys.executable, "-m", "emulators.fakegv", "--images", str(workdir),
                               "--right-address", "127.0.0.2"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    out: dict[str, Any] = {}
    try:
        assert server.stdout is not None
        first = json.loads(server.stdout.readline())
        out["server"] = first
        ids = {c["side"]: c["device_id"] for c in first["cameras"]}
        wait_for_devices(set(ids.values()))
        w, h = scene["size"]
        cfg = config(left_device_id=ids["left"], right_device_id=ids["right"], width_px=w, height_px=h,
                     frame_rate_hz=30.0)
        cam = AravisStereoCamera("camera", cfg, MonotonicClock())
        cam.open()
        served = {(side, k): cv2.imread(str(workdir / f"{side}_{k:03d}.png"), cv2.IMREAD_GRAYSCALE)
                  for side in ("left", "right") for k in (0, 1)}
        cal = load_calibration(workdir / "calibration.json")
        model_mm = np.array(scene["truth"][0])  # the marker layout; pair 1 is it moved 5 mm along x
        identical, errors_mm, counts = [], [], []
        for k in range(4):
            pair = cam.grab(3.0)
            identical.append([bool(np.array_equal(pair.left.image, served["left", k % 2])),
                              bool(np.array_equal(pair.right.image, served["right", k % 2]))])
            if k < 2:
                located = locate_markers(cal, pair.left.image, pair.right.image, model_mm=model_mm)
                truth_k = np.array(scene["truth"][k])
                d_loc = np.linalg.norm(located.points_mm[:, None, :] - truth_k[None, :, :], axis=2)
                match = located.match
                pose_error_mm = None
                if match is not None:
                    moved = match.T_measured_from_model.apply(model_mm)
                    pose_error_mm = float(np.linalg.norm(moved - truth_k, axis=1).max())
                out.setdefault("pipeline", []).append({
                    "points": len(located.points_mm),
                    "max_error_mm": float(d_loc.min(axis=1).max()) if len(located.points_mm) else None,
                    "matched_model": sorted(match.model_to_measured) if match else None,
                    "fre_rms_mm": match.fre_rms_mm if match else None,
                    # The fitted pose moves the layout onto this frame's truth (frame 1: +5 mm x).
                    "pose_error_mm": pose_error_mm,
                    "match_error": located.match_error,
                })
                pts = triangulate(cal, pair.left.image, pair.right.image)
                truth = np.array(scene["truth"][k])
                counts.append(len(pts))
                d = np.linalg.norm(pts[:, None, :] - truth[None, :, :], axis=2)
                errors_mm.append(float(d.min(axis=1).max()) if len(pts) else None)
                out.setdefault("assigned", []).append(sorted(int(i) for i in d.argmin(axis=1)))
        cam.close()
        out.update(identical=identical, max_error_mm=errors_mm, detected=counts,
                   markers=len(scene["truth"][0]))
    finally:
        server.send_signal(signal.SIGTERM)
        _, err = server.communicate(timeout=10)
        out["server_rc"] = server.returncode
        out["server_stderr_tail"] = err.strip().splitlines()[-2:]
    return out


def main() -> int:
    name, workdir = sys.argv[1], Path(sys.argv[2])
    setup_loopback()
    t0 = time.monotonic()
    result = scenario_binary() if name == "binary" else scenario_images(workdir)
    result["scenario_s"] = time.monotonic() - t0
    print("RESULT " + json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
