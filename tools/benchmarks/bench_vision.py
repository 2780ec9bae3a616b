"""Benchmark the stereo ring-marker pipeline against ground truth, the first-order lower bound and
a plain OpenCV baseline.

Run: ``tools/bench vision [--pairs N] [--markers M] [--noise SIGMA] [--seed S] [--frames F]
[--passes P] [--scaling] [--json]``

Scene (seed-001-like): 1920x1080, f = 1394 px, baseline 120 mm, mild radial distortion, M ring
markers (7/3 mm) on a curved skin patch ~1 m away, tilted up to 45 degrees, Gaussian sensor noise
of SIGMA grey levels on a 160-level contrast, 0.7 px defocus blur, vignetting.

Printed side by side:
- centre error (px RMS, per detection) and 3D error (mm RMS, per triangulated marker) of this
  pipeline (with the plane-normal perspective correction, with the concentric-conic correction and
  without correction), of the seed-001 pipeline (ROI/median/Otsu/Canny/LSQ conic; centres only),
  and of the baseline (cv2.SimpleBlobDetector + cv2.fitEllipse on the blob contour, rectified-row
  pairing, cv2.triangulatePoints);
- the first-order lower bound: per marker and camera the Cramer-Rao bound of the centre of the
  noise-free rendered pattern (Fisher information sum(grad I grad I^T) / sigma^2, sigma^2 including
  the 1/12 quantisation variance), propagated through the triangulation Jacobian to 3D;
- time per stereo pair (median, p95) and pairs/s on one core: CPU time of the benchmark thread
  (``time.thread_time``) with ``cv2.setNumThreads(1)``, so that other load on a shared machine does
  not count; the wall-clock median is in the JSON too. For the full pipeline (both detections +
  pairing + correction + triangulation) and for the baseline. The pairs are rendered first; the
  pipeline then runs over all of them ``--passes`` times (each correction on its own) and its
  figures are the fastest pass's, the median pass in the JSON beside them (as for the sequence:
  tools/benchmarks/vision_sequence.py); the baseline runs once;
- a near-range scene (450 mm, tilts up to 60 degrees) where the perspective bias is larger, with
  and without the correction.
- region-of-interest tracking (hil.vision.tracking) on a sequence of F pairs with the markers
  moving at breathing speed and one hidden for a while (tools/benchmarks/vision_sequence.py), side
  by side with the full-frame pipeline and the OpenCV baseline on the same pairs: pairs/s (of the
  fastest of P passes over the sequence, and of the median pass; see vision_sequence.py), 3D
  error against the bound of that sequence, full-frame re-acquisitions and losses;
- with ``--scaling``: pairs/s and 3D error of both modes for 4, 8, 16, 32 markers and for
  1280x720, 1920x1080 and 3840x2160 images (the table of docs/benchmarks.md).
Wall-clock figures depend on the machine; the accuracy figures do not (fixed seed).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from hil.geometry.triangulation import triangulate_dlt
from hil.vision.camera_model import StereoCalibration, undistort_pixels
from hil.vision.detect import detect_rings, detect_rings_multi, detect_rings_paper
from hil.vision.render import RenderedPair, RenderOptions, random_marker_layout, render_stereo
from hil.vision.stereo import Correction, StereoParams, match_and_triangulate

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from vision_sequence import _same_every_pass, run_sequence, scaled_rig, scaling_sweep

FloatArray = NDArray[np.float64]
MATCH_PX = 2.0


@dataclass
class Tally:
    center_err: list[FloatArray] = field(default_factory=list)
    err3d: list[FloatArray] = field(default_factory=list)
    times: list[float] = field(default_factory=list)  # CPU seconds of this thread per pair
    wall: list[float] = field(default_factory=list)  # wall-clock seconds per pair
    pass_pairs_per_s: list[float] = field(default_factory=list)  # of every pass, in order
    missed: int = 0
    false: int = 0

    def add_pass(self, times: list[float], wall: list[float]) -> None:
        """One pass's CPU and wall seconds per pair; the fastest pass so far is kept."""
        self.pass_pairs_per_s.append(float(1.0 / np.mean(times)))
        if not self.times or np.mean(times) < np.mean(self.times):
            self.times, self.wall = times, wall

    def median_pass_pairs_per_s(self) -> float:
        return float(np.median(self.pass_pairs_per_s)) if self.pass_pairs_per_s else float("nan")

    def center_rms(self) -> float:
        e = np.array(self.center_err).reshape(-1, 2)
        return float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if e.size else float("nan")

    def err3d_rms(self) -> float:
        e = np.array(self.err3d).reshape(-1, 3)
        return float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if e.size else float("nan")

    def time_stats(self) -> tuple[float, float, float]:
        if not self.times:
            return float("nan"), float("nan"), float("nan")
        t = np.array(self.times)
        return float(np.median(t) * 1e3), float(np.percentile(t, 95) * 1e3), float(1.0 / np.mean(t))


def _score_centres(centres: list[FloatArray], truth: FloatArray, visible: list[bool], tally: Tally) -> None:
    used: set[int] = set()
    for c in centres:
        d = np.linalg.norm(truth - c, axis=1)
        j = int(np.argmin(d))
        if d[j] < MATCH_PX and j not in used:
            tally.center_err.append(c - truth[j])
            used.add(j)
        else:
            tally.false += 1
    tally.missed += sum(1 for j, v in enumerate(visible) if v and j not in used)


def _score_points(points: FloatArray, truth_mm: FloatArray, tally: Tally) -> None:
    for p in points:
        d = np.linalg.norm(truth_mm - p, axis=1)
        j = int(np.argmin(d))
        if d[j] < 5.0:
            tally.err3d.append(p - truth_mm[j])
        else:
            tally.false += 1


# ---- baseline: SimpleBlobDetector + fitEllipse, rectified-row pairing, cv2.triangulatePoints -----
def _blob_detector() -> Any:
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor = False  # a ring's centre pixel is its light hole
    p.filterByArea, p.minArea, p.maxArea = True, 15, 5000
    p.filterByCircularity = False
    p.filterByConvexity = False
    p.filterByInertia, p.minInertiaRatio = True, 0.2
    return cv2.SimpleBlobDetector_create(p)


def baseline_centres(det: Any, img: NDArray[np.uint8]) -> list[FloatArray]:
    out = []
    h, w = img.shape
    for kp in det.detect(img):
        r = int(kp.size) + 4
        x0, y0 = max(int(kp.pt[0]) - r, 0), max(int(kp.pt[1]) - r, 0)
        roi = img[y0 : min(int(kp.pt[1]) + r + 1, h), x0 : min(int(kp.pt[0]) + r + 1, w)]
        _, binary = cv2.threshold(roi, 0, 255, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
        contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not contours:
            continue
        cnt = max(contours, key=cv2.contourArea)
        if len(cnt) < 5:
            continue
        (cx, cy), _, _ = cv2.fitEllipse(cnt)
        out.append(np.array([cx + x0, cy + y0]))
    return out


def baseline_points(cal: StereoCalibration, cl: list[FloatArray], cr: list[FloatArray]) -> FloatArray:
    if not cl or not cr:
        return np.zeros((0, 3))
    rect = cal.rectification
    L = cv2.undistortPoints(np.array(cl).reshape(-1, 1, 2), cal.K_left, cal.dist_left, R=rect.R1, P=rect.P1)
    R = cv2.undistortPoints(np.array(cr).reshape(-1, 1, 2), cal.K_right, cal.dist_right, R=rect.R2, P=rect.P2)
    L, R = L.reshape(-1, 2), R.reshape(-1, 2)
    pl, pr = [], []
    taken: set[int] = set()
    for i in range(len(L)):  # greedy nearest row
        dv = np.abs(R[:, 1] - L[i, 1])
        dv[list(taken)] = np.inf
        dv[R[:, 0] >= L[i, 0]] = np.inf
        j = int(np.argmin(dv))
        if dv[j] <= 2.0:
            taken.add(j)
            pl.append(L[i])
            pr.append(R[j])
    if not pl:
        return np.zeros((0, 3))
    X = cv2.triangulatePoints(rect.P1, rect.P2, np.array(pl).T, np.array(pr).T)
    pts_rect = (X[:3] / X[3]).T
    return np.asarray(pts_rect @ rect.R1, dtype=np.float64)  # rectified-left -> optical frame


# ---- first-order lower bound ------------------------------------------------------------------
def centre_crlb(img: NDArray[np.uint8], uv: FloatArray, radius_px: float, sigma: float) -> FloatArray:
    """2x2 Cramer-Rao covariance of a pattern's position from the noise-free image (px^2)."""
    r = int(radius_px) + 5
    x, y = round(uv[0]), round(uv[1])
    patch = img[y - r : y + r + 1, x - r : x + r + 1].astype(np.float64)
    gy, gx = np.gradient(patch)
    F = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]])
    return np.asarray(np.linalg.inv(F) * (sigma**2 + 1.0 / 12.0), dtype=np.float64)


def triangulation_jacobian(cal: StereoCalibration, uvl: FloatArray, uvr: FloatArray) -> FloatArray:
    """d(point)/d(uL, vL, uR, vR) (3x4), numerically, on distorted pixels."""
    PL, PR = cal.P_left(), cal.P_right()

    def tri(a: FloatArray, b: FloatArray) -> FloatArray:
        ia = undistort_pixels(a[None, :], cal.K_left, cal.dist_left)
        ib = undistort_pixels(b[None, :], cal.K_right, cal.dist_right)
        return np.asarray(triangulate_dlt(PL, PR, ia, ib)[0], dtype=np.float64)

    J = np.zeros((3, 4))
    h = 1e-3
    for k in range(4):
        d = np.zeros(4)
        d[k] = h
        J[:, k] = (tri(uvl + d[:2], uvr + d[2:]) - tri(uvl - d[:2], uvr - d[2:])) / (2 * h)
    return J


def bound_for_scene(
    cal: StereoCalibration,
    markers: list[Any],
    clean: RenderedPair,
    sigma: float,
    px_var: list[float],
    mm_var: list[float],
) -> None:
    f = float(cal.K_left[0, 0])
    for m, t in zip(markers, clean.truth, strict=True):
        if not (t.visible_left and t.visible_right):
            continue
        rad = f * m.outer_diameter_mm / 2 / float(m.center_mm[2])
        Cl = centre_crlb(clean.left, t.center_left_px, rad, sigma)
        Cr = centre_crlb(clean.right, t.center_right_px, rad, sigma)
        px_var.extend([float(np.trace(Cl)), float(np.trace(Cr))])
        J = triangulation_jacobian(cal, t.center_left_px, t.center_right_px)
        cov = np.zeros((4, 4))
        cov[:2, :2], cov[2:, 2:] = Cl, Cr
        mm_var.append(float(np.trace(J @ cov @ J.T)))


# ---- scenes -----------------------------------------------------------------------------------
def _locate_passes(
    cal: StereoCalibration, pairs: list[RenderedPair], params: StereoParams, passes: int, tally: Tally
) -> list[tuple[list[Any], list[Any], Any]]:
    """Full-frame location of every pair, ``passes`` times over all of them (timed into
    ``tally``: the fastest pass is kept); returns the first pass's detections and stereo results.

    Raises:
        RuntimeError: a pass located other points than the first.
    """
    first: dict[str, list[FloatArray]] = {}
    out: list[tuple[list[Any], list[Any], Any]] = []
    for p in range(max(passes, 1)):
        times, wall, points = [], [], []
        for pair in pairs:
            t0, w0 = time.thread_time(), time.perf_counter()
            dl, dr = detect_rings_multi([(pair.left, "left image"), (pair.right, "right image")])
            st = match_and_triangulate(cal, dl, dr, params)
            times.append(time.thread_time() - t0)
            wall.append(time.perf_counter() - w0)
            points.append(st.points_mm)
            if p == 0:
                out.append((dl, dr, st))
        tally.add_pass(times, wall)
        _same_every_pass(f"full frame ({params.correction})", p, points, first)
    return out


def run(
    n_pairs: int,
    n_markers: int,
    noise: float,
    seed: int,
    distance_mm: float,
    tilt_deg: float,
    with_baseline: bool = True,
    passes: int = 1,
) -> dict[str, Any]:
    cal = StereoCalibration.synthetic(dist=[-0.05, 0.02, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(seed)
    opt = RenderOptions(noise_sigma=noise)
    clean_opt = RenderOptions(noise_sigma=0.0)
    corrections: tuple[Correction, ...] = ("normal", "concentric", "none")
    ours = {c: Tally() for c in corrections}
    paper, base = Tally(), Tally()
    blob = _blob_detector()
    px_var: list[float] = []
    mm_var: list[float] = []
    # warm-up (caches, imports)
    warm = render_stereo(cal, random_marker_layout(rng, n_markers, distance_mm=distance_mm), opt, rng)
    match_and_triangulate(cal, detect_rings(warm.left), detect_rings(warm.right))
    scenes = []
    for _ in range(n_pairs):
        markers = random_marker_layout(
            rng,
            n_markers,
            distance_mm=distance_mm,
            max_tilt_deg=tilt_deg,
            spread_mm=120.0 * distance_mm / 1000.0,
            min_separation_mm=20.0 * max(distance_mm / 1000.0, 0.6),
        )
        pair = render_stereo(cal, markers, opt, rng)
        clean = render_stereo(cal, markers, clean_opt, rng)
        truth_l = np.array([t.center_left_px for t in pair.truth])
        truth_r = np.array([t.center_right_px for t in pair.truth])
        truth_mm = np.array([m.center_mm for m in markers])
        bound_for_scene(cal, markers, clean, noise, px_var, mm_var)
        scenes.append((pair, truth_l, truth_r, truth_mm))
    for corr in corrections:
        params = StereoParams(correction=corr)
        located = _locate_passes(cal, [sc[0] for sc in scenes], params, passes, ours[corr])
        for (pair, truth_l, truth_r, truth_mm), (dl, dr, st) in zip(scenes, located, strict=True):
            if corr == "none":
                _score_centres(
                    [d.center_px for d in dl], truth_l, [t.visible_left for t in pair.truth], ours[corr]
                )
                _score_centres(
                    [d.center_px for d in dr], truth_r, [t.visible_right for t in pair.truth], ours[corr]
                )
            _score_points(st.points_mm, truth_mm, ours[corr])
    for pair, truth_l, truth_r, truth_mm in scenes if with_baseline else []:
        _score_centres(
            detect_rings_paper(pair.left), truth_l, [t.visible_left for t in pair.truth], paper
        )
        _score_centres(
            detect_rings_paper(pair.right), truth_r, [t.visible_right for t in pair.truth], paper
        )
        t0, w0 = time.thread_time(), time.perf_counter()
        cl, cr = baseline_centres(blob, pair.left), baseline_centres(blob, pair.right)
        pts = baseline_points(cal, cl, cr)
        base.times.append(time.thread_time() - t0)
        base.wall.append(time.perf_counter() - w0)
        _score_centres(cl, truth_l, [t.visible_left for t in pair.truth], base)
        _score_centres(cr, truth_r, [t.visible_right for t in pair.truth], base)
        _score_points(pts, truth_mm, base)
    return {
        "ours": ours,
        "paper": paper,
        "baseline": base,
        "bound_px": float(np.sqrt(np.mean(px_var))) if px_var else float("nan"),
        "bound_mm": float(np.sqrt(np.mean(mm_var))) if mm_var else float("nan"),
    }


def _result(args: argparse.Namespace, main_res: dict[str, Any], near: dict[str, Any],
            seq: dict[str, Any]) -> dict[str, Any]:
    """The JSON object of a run (docs/benchmarks.md lists its fields)."""
    sq_t, sq_f, sq_b = seq["track"], seq["full"], seq["baseline"]
    ours, base, paper = main_res["ours"], main_res["baseline"], main_res["paper"]
    best = ours["normal"]
    t_med, t_p95, pps = best.time_stats()
    b_med, b_p95, b_pps = base.time_stats()
    result: dict[str, Any] = {
        "pairs": args.pairs,
        "markers": args.markers,
        "noise_sigma": args.noise,
        "pairs_per_s": pps,
        "pairs_per_s_median_pass": best.median_pass_pairs_per_s(),
        "pairs_per_s_passes": best.pass_pairs_per_s,
        "time_per_pair_ms_median": t_med,
        "time_per_pair_ms_p95": t_p95,
        "wall_time_per_pair_ms_median": float(np.median(best.wall) * 1e3),
        "baseline_wall_time_per_pair_ms_median": float(np.median(base.wall) * 1e3) if base.wall else None,
        "baseline_pairs_per_s": b_pps,
        "baseline_time_per_pair_ms_median": b_med,
        "baseline_time_per_pair_ms_p95": b_p95,
        "center_err_px_rms": ours["none"].center_rms(),
        "center_err_bound_px": main_res["bound_px"],
        "paper_center_err_px_rms": paper.center_rms(),
        "baseline_center_err_px_rms": base.center_rms(),
        "err3d_mm_rms": best.err3d_rms(),
        "err3d_bound_mm": main_res["bound_mm"],
        "err3d_mm_rms_concentric": ours["concentric"].err3d_rms(),
        "err3d_mm_rms_uncorrected": ours["none"].err3d_rms(),
        "baseline_err3d_mm_rms": base.err3d_rms(),
        "missed_detections": ours["none"].missed,
        "false_detections": ours["none"].false,
        "baseline_missed": base.missed,
        "baseline_false": base.false,
        "tracking_pairs_per_s": sq_t.pairs_per_s(),
        "tracking_pairs_per_s_median_pass": sq_t.median_pass_pairs_per_s(),
        "tracking_time_per_pair_ms_median": sq_t.ms(50),
        "tracking_time_per_pair_ms_p95": sq_t.ms(95),
        "tracking_err3d_mm_rms": sq_t.rms(),
        "tracking_err3d_bound_mm": seq["bound_mm"],
        "reacquisitions": seq["reacquisitions"],
        "losses": seq["losses"],
        "recoveries": seq["recoveries"],
        "scans": seq["scans"],
        "sequence": {
            "frames": seq["frames"],
            "hidden_frames": seq["hidden_frames"],
            "passes": args.passes,
            "tracking": {"pairs_per_s": sq_t.pairs_per_s(), "err3d_mm_rms": sq_t.rms(),
                         "pairs_per_s_passes": sq_t.pass_pairs_per_s,
                         "time_per_pair_ms_median": sq_t.ms(50), "time_per_pair_ms_p95": sq_t.ms(95),
                         "missed": sq_t.missed, "false": sq_t.false},
            "full_frame": {"pairs_per_s": sq_f.pairs_per_s(), "err3d_mm_rms": sq_f.rms(),
                           "pairs_per_s_passes": sq_f.pass_pairs_per_s,
                           "time_per_pair_ms_median": sq_f.ms(50), "time_per_pair_ms_p95": sq_f.ms(95),
                           "missed": sq_f.missed, "false": sq_f.false},
            "baseline": {"pairs_per_s": sq_b.pairs_per_s(), "err3d_mm_rms": sq_b.rms(),
                         "time_per_pair_ms_median": sq_b.ms(50), "missed": sq_b.missed, "false": sq_b.false},
            "err3d_bound_mm": seq["bound_mm"],
            "reacquisitions": seq["reacquisitions"],
            "losses": seq["losses"],
            "recoveries": seq["recoveries"],
            "scans": seq["scans"],
        },
        "near_450mm": {
            "err3d_mm_rms_normal": near["ours"]["normal"].err3d_rms(),
            "err3d_mm_rms_concentric": near["ours"]["concentric"].err3d_rms(),
            "err3d_mm_rms_uncorrected": near["ours"]["none"].err3d_rms(),
            "err3d_bound_mm": near["bound_mm"],
            "center_err_px_rms": near["ours"]["none"].center_rms(),
            "center_err_bound_px": near["bound_px"],
        },
    }
    return result


def _print_main(args: argparse.Namespace, result: dict[str, Any]) -> None:
    """The main and near scenes' table."""
    r = result
    nr = r["near_450mm"]
    t_med, b_med = r["time_per_pair_ms_median"], r["baseline_time_per_pair_ms_median"]
    rows = [
        ("", "ours", "baseline", "bound", "ours/bound", "base/ours"),
        (
            "centre error, px RMS",
            f"{r['center_err_px_rms']:.4f}",
            f"{r['baseline_center_err_px_rms']:.4f}",
            f"{r['center_err_bound_px']:.4f}",
            f"{r['center_err_px_rms'] / r['center_err_bound_px']:.2f}",
            f"{r['baseline_center_err_px_rms'] / r['center_err_px_rms']:.1f}",
        ),
        (
            "3D error, mm RMS",
            f"{r['err3d_mm_rms']:.4f}",
            f"{r['baseline_err3d_mm_rms']:.4f}",
            f"{r['err3d_bound_mm']:.4f}",
            f"{r['err3d_mm_rms'] / r['err3d_bound_mm']:.2f}",
            f"{r['baseline_err3d_mm_rms'] / r['err3d_mm_rms']:.1f}",
        ),
        ("time per pair, ms median", f"{t_med:.2f}", f"{b_med:.2f}", "", "", f"{b_med / t_med:.1f}"),
        ("time per pair, ms p95", f"{r['time_per_pair_ms_p95']:.2f}",
         f"{r['baseline_time_per_pair_ms_p95']:.2f}", "", "", ""),
        ("pairs/s (one core)", f"{r['pairs_per_s']:.1f}", f"{r['baseline_pairs_per_s']:.1f}", "", "", ""),
        ("pairs/s, median pass", f"{r['pairs_per_s_median_pass']:.1f}", "", "", "", ""),
        (
            "missed / false detections",
            f"{r['missed_detections']} / {r['false_detections']}",
            f"{r['baseline_missed']} / {r['baseline_false']}",
            "",
            "",
            "",
        ),
    ]
    print(
        f"vision benchmark: {args.pairs} pairs, {args.markers} markers, 1920x1080, f=1394 px, "
        f"baseline 120 mm, ~1 m, noise sigma {args.noise}"
    )
    for row in rows:
        print(f"{row[0]:<28}{row[1]:>14}{row[2]:>14}{row[3]:>10}{row[4]:>12}{row[5]:>11}")
    print(
        "seed-001 pipeline (median/Otsu/Canny/LSQ conic) centre error: "
        f"{r['paper_center_err_px_rms']:.4f} px RMS"
    )
    print(
        "perspective correction, 3D error mm RMS: "
        f"1 m: normal {r['err3d_mm_rms']:.4f} | concentric {r['err3d_mm_rms_concentric']:.4f} | "
        f"none {r['err3d_mm_rms_uncorrected']:.4f}"
    )
    print(
        f"                                   450 mm, 60 deg tilt: normal {nr['err3d_mm_rms_normal']:.4f} | "
        f"concentric {nr['err3d_mm_rms_concentric']:.4f} | none {nr['err3d_mm_rms_uncorrected']:.4f} | "
        f"bound {nr['err3d_bound_mm']:.4f}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=60)
    ap.add_argument("--markers", type=int, default=8)
    ap.add_argument("--noise", type=float, default=2.0, help="sensor noise sigma, grey levels (default 2)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--frames", type=int, default=90, help="pairs of the tracking sequence (default 90, 3 s)")
    ap.add_argument("--scaling", action="store_true",
                    help="also sweep marker count (4-32) and image size (1280x720-3840x2160)")
    ap.add_argument("--scaling-frames", type=int, default=30, help="pairs per scaling case (default 30)")
    ap.add_argument("--passes", type=int, default=5,
                    help="passes of tracking and full frame over each sequence; pairs/s is the fastest "
                         "pass's, the median pass is printed beside it (default 5)")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    main_res = run(args.pairs, args.markers, args.noise, args.seed, 1000.0, 45.0, passes=args.passes)
    near = run(
        max(args.pairs // 3, 5), args.markers, args.noise, args.seed + 1, 450.0, 60.0, with_baseline=False,
    )
    seq = run_sequence(
        scaled_rig(1920), args.markers, args.frames, args.noise, args.seed,
        baseline=(_blob_detector(), baseline_centres, baseline_points), bound_every=3, bound=bound_for_scene,
        passes=args.passes,
    )
    result = _result(args, main_res, near, seq)
    if args.scaling:
        result["scaling"] = scaling_sweep(args.noise, args.seed, args.scaling_frames, args.passes)
    if args.json:
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
        return 0
    _print_main(args, result)
    _print_sequence(result)
    if args.scaling:
        _print_scaling(result["scaling"])
    return 0


def _print_sequence(r: dict[str, Any]) -> None:
    sq = r["sequence"]
    b = sq["err3d_bound_mm"]
    print(
        f"\ntracking sequence: {sq['frames']} pairs at 30/s, {r['markers']} markers breathing (8 mm, 4 s), "
        f"marker 0 hidden in pairs {sq['hidden_frames'][0]}-{sq['hidden_frames'][1] - 1}"
    )
    print(f"{'':<28}{'tracking':>14}{'full frame':>14}{'OpenCV':>14}")
    rows = [("tracking", sq["tracking"]), ("full frame", sq["full_frame"]), ("OpenCV", sq["baseline"])]
    print(f"{'pairs/s (one core)':<28}" + "".join(f"{m['pairs_per_s']:>14.1f}" for _, m in rows)
          + f"   (fastest of {sq['passes']} passes; OpenCV: 1)")
    print(f"{'pairs/s, median pass':<28}"
          + "".join(f"{float(np.median(m['pairs_per_s_passes'])):>14.1f}" for _, m in rows[:2]))
    print(f"{'time per pair, ms median':<28}"
          + "".join(f"{m['time_per_pair_ms_median']:>14.2f}" for _, m in rows))
    print(f"{'3D error, mm RMS':<28}" + "".join(f"{m['err3d_mm_rms']:>14.4f}" for _, m in rows))
    print(f"{'3D error / bound':<28}" + "".join(f"{m['err3d_mm_rms'] / b:>14.2f}" for _, m in rows)
          + f"   (bound {b:.4f} mm)")
    print(f"{'missed / false':<28}" + "".join(f"{m['missed']:>8} / {m['false']:<3}" for _, m in rows))
    print(f"full-frame re-acquisitions (both images): {sq['reacquisitions']}, "
          f"periodic scans for new markers: {sq['scans']}, "
          f"markers lost from their window: {sq['losses']}, "
          f"hidden markers recovered at their last place: {sq['recoveries']}")


def _print_scaling(rows: list[dict[str, Any]]) -> None:
    print("\nscaling (pairs/s one core; 3D error mm RMS)")
    print(f"{'image':<12}{'markers':>8}{'track pairs/s':>15}{'full pairs/s':>14}{'track err':>11}"
          f"{'full err':>10}{'reacq':>7}{'scans':>7}{'lost':>6}{'recovered':>10}")
    for row in rows:
        print(f"{row['image']:<12}{row['markers']:>8}{row['tracking_pairs_per_s']:>15.1f}"
              f"{row['pairs_per_s']:>14.1f}{row['tracking_err3d_mm_rms']:>11.4f}{row['err3d_mm_rms']:>10.4f}"
              f"{row['reacquisitions']:>7}{row['scans']:>7}{row['losses']:>6}{row['recoveries']:>10}")


if __name__ == "__main__":
    sys.exit(main())
