"""Sub-pixel ring edges of many markers at once (steps 3-5 of :mod:`hil.vision.detect`).

Given an initial guess of each ring (a ray origin near its centre and the outer / inner ellipse
sizes), intensity profiles are sampled along ``n_rays`` rays from the origin (bicubic, every
0.25 px, one ``cv2.remap`` over the whole image for all rings), the outer and inner edges are the
mid-level crossings between the ring level and the background / hole level, each edge gets the
direct ellipse-specific fit (Fitzgibbon 1999) with one robust re-fit, and the ring check and the
centre estimate of :func:`hil.vision.detect.fit_rings` follow.

Full-frame detection seeds it from the coarse contours of each candidate; the tracking locator
(:mod:`hil.vision.tracking`) seeds it from each marker's predicted position and last ellipses. The
arithmetic is the same for both, so the two modes share one centre estimator. Cost grows with
the number of rings and their size, not with the image size.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from hil.vision import kernel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
U8Image = NDArray[np.uint8]
F32Array = NDArray[np.float32]

#: radial step of the profiles, px
RAY_STEP_PX = 0.25


@dataclass(frozen=True)
class RingSeeds:
    """Initial guesses of E rings (pixels, full-image coordinates).

    origin_px: (E, 2) ray origins (near each ring's centre). outer / inner: (E, 3) semi-axes
    ``a, b`` and major-axis angle (rad) of the expected outer / inner edge, centred on the origin.
    dark_on_light: (E,) polarity.
    """

    origin_px: FloatArray
    outer: FloatArray
    inner: FloatArray
    dark_on_light: BoolArray

    @property
    def count(self) -> int:
        return int(self.origin_px.shape[0])

    @staticmethod
    def stack(seeds: list[RingSeeds]) -> RingSeeds:
        if not seeds:
            return RingSeeds(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=bool))
        return RingSeeds(
            np.concatenate([s.origin_px for s in seeds]),
            np.concatenate([s.outer for s in seeds]),
            np.concatenate([s.inner for s in seeds]),
            np.concatenate([s.dark_on_light for s in seeds]),
        )


@dataclass(frozen=True)
class RingEdges:
    """Edge points of E rings on all rays: (E, n_rays) coordinates with masks (edge found), the
    fraction of rays with both edges, and ``ok`` (E,): contrast and fraction checks passed."""

    xo: FloatArray
    yo: FloatArray
    mo: BoolArray
    xi: FloatArray
    yi: FloatArray
    mi: BoolArray
    frac: FloatArray
    ok: BoolArray
    dark_on_light: BoolArray


def ellipse_radius(a: FloatArray, b: FloatArray, angle: FloatArray, theta: FloatArray) -> FloatArray:
    """Distance from an ellipse's centre to its edge along directions ``theta``: (E,) x (n,) -> (E, n)."""
    phi = theta[None, :] - angle[:, None]
    a2, b2 = a[:, None], b[:, None]
    return np.asarray(a2 * b2 / np.sqrt((b2 * np.cos(phi)) ** 2 + (a2 * np.sin(phi)) ** 2), dtype=np.float64)


def _upper_median(values: NDArray[np.floating[Any]], mask: BoolArray) -> tuple[FloatArray, BoolArray]:
    """Per row, the element of rank ``count // 2`` of the masked values (the upper median, as
    ``np.partition(x, x.size // 2)``), and whether the row had any value."""
    v = np.sort(np.where(mask, values, np.inf), axis=1)
    cnt = np.count_nonzero(mask, axis=1)
    med = v[np.arange(v.shape[0]), cnt // 2].astype(np.float64)
    return med, cnt > 0


def ring_edges(
    img: U8Image, seeds: RingSeeds, n_rays: int, min_contrast: float, min_valid_fraction: float
) -> RingEdges:
    """Sub-pixel outer and inner edge points of every seeded ring of one image: see
    :func:`ring_edges_multi`."""
    return ring_edges_multi([(img, seeds)], n_rays, min_contrast, min_valid_fraction)


_RAY_DIRS: dict[int, tuple[FloatArray, FloatArray, FloatArray]] = {}


def _ray_dirs(n: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Angles, cosines and sines of ``n`` rays (computed once per ``n``; read-only)."""
    dirs = _RAY_DIRS.get(n)
    if dirs is None:
        theta: FloatArray = np.arange(n, dtype=np.float64) * (2 * math.pi / n)
        dirs = (theta, np.cos(theta), np.sin(theta))
        for a in dirs:
            a.setflags(write=False)
        _RAY_DIRS[n] = dirs
    return dirs


def _ray_profiles(
    parts: Sequence[tuple[U8Image, RingSeeds]],
    seeds: RingSeeds,
    r: FloatArray,
    cos_t: FloatArray,
    sin_t: FloatArray,
) -> F32Array:
    """Grey levels along every ray of every ring, (E, n_rays, S) float32, ring dark on light.

    Ray ``k`` of ring ``e`` is sampled (bicubic, border replicated) at radii ``r`` (px) from the
    ring's origin in direction ``theta_k``; ``seeds`` are the rings of ``parts`` stacked in order.
    Light-on-dark rings are inverted (``255 - grey``) so that every ring is darker than its
    background.
    """
    E, n, S = seeds.count, cos_t.shape[0], r.shape[0]
    ox, oy = seeds.origin_px[:, 0], seeds.origin_px[:, 1]
    mapx = (ox[:, None, None] + r[None, None, :] * cos_t[None, :, None]).astype(np.float32)
    mapy = (oy[:, None, None] + r[None, None, :] * sin_t[None, :, None]).astype(np.float32)
    prof = np.empty((E, n, S), dtype=np.float32)
    start = 0
    for img, sd in parts:
        stop = start + sd.count
        if stop > start:
            mx = mapx[start:stop].reshape(-1, S)
            my = mapy[start:stop].reshape(-1, S)
            grey = cv2.remap(img, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            # grey levels are integers: float32 holds them and every threshold below exactly enough
            prof[start:stop] = grey.reshape(stop - start, n, S)
        start = stop
    dol = seeds.dark_on_light
    if not dol.all():
        prof = np.where(dol[:, None, None], prof, np.float32(255.0) - prof)
    return prof



def _crossings(prof: Any, jr3: Any, jmin: Any, valid3: Any, r: Any, t_out: Any,
               t_in: Any) -> tuple[Any, Any, Any, Any]:
    """The outer edge (the first sample past the ring minimum at or above ``t_out``) and the
    inner edge (the last sample before it at or above ``t_in``) on every ray of every ring,
    interpolated linearly between samples: ``(r_outer, ok_outer, r_inner, ok_inner)``, (E, n)."""
    E, n, S = prof.shape
    ds = RAY_STEP_PX
    ee, nn = np.arange(E)[:, None], np.arange(n)[None, :]
    rel = jr3 - jmin.astype(np.int16)[:, :, None]
    above_o = (prof >= t_out) & (rel > 0) & valid3
    jo = np.argmax(above_o, axis=2)
    ok_o = above_o[ee, nn, jo] & (jo > 0)
    jo1 = np.maximum(jo - 1, 0)
    p1, p0 = prof[ee, nn, jo].astype(np.float64), prof[ee, nn, jo1].astype(np.float64)
    ro_sub = r[jo1] + ds * (t_out[:, :, 0] - p0) / np.where(p1 - p0 == 0, 1e-9, p1 - p0)
    above_i = (prof >= t_in) & (rel < 0)
    ji = S - 1 - np.argmax(above_i[:, :, ::-1], axis=2)
    ok_i = above_i[ee, nn, ji] & (ji < S - 1)
    q0 = prof[ee, nn, ji].astype(np.float64)
    q1 = prof[ee, nn, np.minimum(ji + 1, S - 1)].astype(np.float64)
    ri_sub = r[ji] + ds * (q0 - t_in[:, :, 0]) / np.where(q0 - q1 == 0, 1e-9, q0 - q1)
    return ro_sub, ok_o, ri_sub, ok_i


def ring_edges_multi(
    parts: Sequence[tuple[U8Image, RingSeeds]], n_rays: int, min_contrast: float, min_valid_fraction: float
) -> RingEdges:
    """:func:`ring_edges_multi_numpy` by the compiled kernel when it is selected
    (:mod:`hil.vision.kernel`; the same results to rounding), else by the numpy code.

    Raises:
        ValueError: (kernel) a seed's radius is not finite or needs more than 1e6 samples.
    """
    k = kernel.active()
    if k is None:
        return ring_edges_multi_numpy(parts, n_rays, min_contrast, min_valid_fraction)
    return _ring_edges_kernel(k, parts, n_rays, min_contrast, min_valid_fraction)


def _ring_edges_kernel(
    k: Any, parts: Sequence[tuple[U8Image, RingSeeds]], n_rays: int, min_contrast: float,
    min_valid_fraction: float,
) -> RingEdges:
    """:func:`ring_edges_multi_numpy` with the per-ring work in ``hil.vision._kernel``: the rays'
    radii, the sample positions, one ``cv2.remap`` per image (the same bicubic samples), then the
    levels, crossings and checks of every ring in one compiled call."""
    seeds = parts[0][1] if len(parts) == 1 else RingSeeds.stack([sd for _, sd in parts])
    E, n = seeds.count, n_rays
    theta, cos_t, sin_t = _ray_dirs(n)
    if E == 0:
        z, zb = np.zeros((0, n)), np.zeros((0, n), dtype=bool)
        return RingEdges(z, z, zb, z, z, zb, np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))
    origin = np.ascontiguousarray(seeds.origin_px, dtype=np.float64)
    dol = np.ascontiguousarray(seeds.dark_on_light, dtype=np.bool_)
    r_out, r_in = np.empty((E, n)), np.empty((E, n))
    n_samples = np.empty(E, dtype=np.int64)
    S = k.ring_geometry(np.ascontiguousarray(seeds.outer, dtype=np.float64),
                        np.ascontiguousarray(seeds.inner, dtype=np.float64), theta, r_out, r_in, n_samples)
    mapx, mapy = np.empty((E, n, S), dtype=np.float32), np.empty((E, n, S), dtype=np.float32)
    k.ray_maps(origin, cos_t, sin_t, mapx, mapy)
    grey = np.empty((E, n, S), dtype=np.uint8)
    start = 0
    for img, sd in parts:
        stop = start + sd.count
        if stop > start:
            mx, my = mapx[start:stop].reshape(-1, S), mapy[start:stop].reshape(-1, S)
            grey[start:stop] = cv2.remap(img, mx, my, cv2.INTER_CUBIC,
                                         borderMode=cv2.BORDER_REPLICATE).reshape(-1, n, S)
        start = stop
    xo, yo, xi, yi = np.empty((E, n)), np.empty((E, n)), np.empty((E, n)), np.empty((E, n))
    mo, mi = np.empty((E, n), dtype=bool), np.empty((E, n), dtype=bool)
    frac, ok = np.empty(E), np.empty(E, dtype=bool)
    k.ring_edges(grey, dol, origin, cos_t, sin_t, r_out, r_in, n_samples, float(min_contrast),
                 float(min_valid_fraction), xo, yo, mo, xi, yi, mi, frac, ok)
    return RingEdges(xo, yo, mo, xi, yi, mi, frac, ok, dol.copy())


def ring_edges_multi_numpy(
    parts: Sequence[tuple[U8Image, RingSeeds]], n_rays: int, min_contrast: float, min_valid_fraction: float
) -> RingEdges:
    """Sub-pixel outer and inner edge points of every seeded ring (see the module doc) of several
    images at once (e.g. both of a stereo pair): the rows of the result follow ``parts`` in order.

    A ring fails (``ok`` False) when its ring is not ``min_contrast`` grey levels darker than the
    background (and 0.35 of that than its hole), or when both edges are found on fewer than
    ``min_valid_fraction`` of the rays; an edge further than ``1.5 + 0.15 r`` (outer) or
    ``1.5 + 0.25 r`` (inner) px from the seed's radius on a ray does not count. Pure CPU.

    On each ray (samples ``j``, radius ``j * 0.25`` px, up to ``3`` px beyond the ring's largest
    outer radius): the ring minimum is the darkest sample within ``[r_in - 0.5, r_out + 0.5]``;
    the ring level is the upper median of the rays' minima, the background level the upper median
    of all samples at ``r >= r_out + 1.8`` (or the mean of the rays' last samples), the hole level
    the upper median of the samples within ``max(0.35 min(r_in), 0.3)`` px of the origin. The
    outer edge is the first sample past the minimum at or above the mid-level of ring and
    background, the inner edge the last sample before it at or above the mid-level of ring and
    hole, both interpolated linearly between samples. One ``cv2.remap`` per image and a fixed
    number of array operations for all rings: the cost hardly grows with the ring count.
    """
    seeds = parts[0][1] if len(parts) == 1 else RingSeeds.stack([sd for _, sd in parts])
    E, n, ds = seeds.count, n_rays, RAY_STEP_PX
    theta, cos_t, sin_t = _ray_dirs(n)
    if E == 0:
        z, zb = np.zeros((0, n)), np.zeros((0, n), dtype=bool)
        return RingEdges(z, z, zb, z, z, zb, np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))
    axes = np.concatenate([seeds.outer, seeds.inner])
    radii = ellipse_radius(axes[:, 0], axes[:, 1], axes[:, 2], theta)
    r_out, r_in = radii[:E], radii[E:]
    r_max = r_out.max(axis=1) + 3.0
    n_samples = np.ceil(r_max / ds).astype(np.int64)  # len(np.arange(0, r_max, ds)) per ring
    S = int(n_samples.max())
    r = np.arange(S, dtype=np.float64) * ds
    # sample indices as small integers: the masks below are (E, n, S) comparisons
    jr3 = np.arange(S, dtype=np.int16)[None, None, :]
    valid3 = jr3 < n_samples.astype(np.int16)[:, None, None]  # (E, 1, S)
    ox, oy = seeds.origin_px[:, 0], seeds.origin_px[:, 1]
    prof = _ray_profiles(parts, seeds, r, cos_t, sin_t)
    # ring minimum per ray and the ring level
    j_ring_lo = np.ceil((r_in - 0.5) / ds - 1e-9).astype(np.int16)
    j_ring_hi = np.floor((r_out + 0.5) / ds + 1e-9).astype(np.int16)
    in_ring = (jr3 >= j_ring_lo[:, :, None]) & (jr3 <= j_ring_hi[:, :, None]) & valid3
    ring_prof = np.where(in_ring, prof, np.float32(np.inf))
    jmin = np.argmin(ring_prof, axis=2)  # (E, n)
    ee, nn = np.arange(E)[:, None], np.arange(n)[None, :]
    ring_level = np.sort(ring_prof[ee, nn, jmin], axis=1)[:, n // 2].astype(np.float64)
    # background level: the tail samples (only the tail columns are sorted)
    j_tail = np.ceil((r_out + 1.8) / ds - 1e-9).astype(np.int16)
    t0 = max(int(j_tail.min()), 0)
    tail = (jr3[:, :, t0:] >= j_tail[:, :, None]) & valid3[:, :, t0:]
    bg_level, has_tail = _upper_median(prof[:, :, t0:].reshape(E, -1), tail.reshape(E, -1))
    if not has_tail.all():
        last = prof[np.arange(E), :, n_samples - 1].mean(axis=1)
        bg_level = np.where(has_tail, bg_level, last)
    # hole level: the samples near the origin on all rays
    hole_r = np.maximum(0.35 * r_in.min(axis=1), 0.3)
    n_hole = np.floor(hole_r / ds + 1e-9).astype(np.int16) + 1  # samples with r <= hole_r
    J = int(n_hole.max())
    hole = (jr3[:, :, :J] < n_hole[:, None, None]) & valid3[:, :, :J]  # (E, 1, J)
    hole_level, _ = _upper_median(prof[:, :, :J].reshape(E, -1), np.repeat(hole, n, axis=1).reshape(E, -1))
    contrast_ok = (bg_level - ring_level >= min_contrast) & (hole_level - ring_level >= 0.35 * min_contrast)
    t_out = (0.5 * (bg_level + ring_level))[:, None, None]
    t_in = (0.5 * (hole_level + ring_level))[:, None, None]
    ro_sub, ok_o, ri_sub, ok_i = _crossings(prof, jr3, jmin, valid3, r, t_out, t_in)
    ok_o &= np.abs(ro_sub - r_out) < 1.5 + 0.15 * r_out
    ok_i &= np.abs(ri_sub - r_in) < 1.5 + 0.25 * r_in
    frac = np.count_nonzero(ok_o & ok_i, axis=1) / n
    ok = contrast_ok & (frac >= min_valid_fraction)
    return RingEdges(
        ox[:, None] + ro_sub * cos_t,
        oy[:, None] + ro_sub * sin_t,
        ok_o,
        ox[:, None] + ri_sub * cos_t,
        oy[:, None] + ri_sub * sin_t,
        ok_i,
        frac,
        ok,
        seeds.dark_on_light.copy(),
    )
