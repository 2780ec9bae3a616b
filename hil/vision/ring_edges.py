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
    cnt = mask.sum(axis=1)
    med = np.take_along_axis(v, (cnt // 2)[:, None], axis=1)[:, 0].astype(np.float64)
    return med, cnt > 0


def ring_edges(
    img: U8Image, seeds: RingSeeds, n_rays: int, min_contrast: float, min_valid_fraction: float
) -> RingEdges:
    """Sub-pixel outer and inner edge points of every seeded ring of one image: see
    :func:`ring_edges_multi`."""
    return ring_edges_multi([(img, seeds)], n_rays, min_contrast, min_valid_fraction)


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
    rows: list[NDArray[np.uint8]] = []
    start = 0
    for img, sd in parts:
        stop = start + sd.count
        if stop > start:
            mx = mapx[start:stop].reshape(-1, S)
            my = mapy[start:stop].reshape(-1, S)
            rows.append(np.asarray(cv2.remap(img, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)))
        start = stop
    # grey levels are integers: float32 holds them and every threshold below exactly enough
    prof = np.concatenate(rows).astype(np.float32).reshape(E, n, S)
    dol = seeds.dark_on_light
    if not np.all(dol):
        prof = np.where(dol[:, None, None], prof, np.float32(255.0) - prof)
    return prof


def _ring_minimum(
    prof: F32Array, r_in: FloatArray, r_out: FloatArray, jr3: NDArray[np.int64], valid3: BoolArray
) -> tuple[NDArray[np.intp], FloatArray]:
    """Darkest sample of each ray within the ring ``[r_in - 0.5, r_out + 0.5]`` px.

    Returns its sample index (E, n_rays) and the ring's grey level (E,): the upper median of the
    rays' minima.
    """
    ds = RAY_STEP_PX
    j_ring_lo = np.ceil((r_in - 0.5) / ds - 1e-9).astype(np.int64)
    j_ring_hi = np.floor((r_out + 0.5) / ds + 1e-9).astype(np.int64)
    in_ring = (jr3 >= j_ring_lo[:, :, None]) & (jr3 <= j_ring_hi[:, :, None]) & valid3
    ring_prof = np.where(in_ring, prof, np.float32(np.inf))
    jmin = np.argmin(ring_prof, axis=2)  # (E, n)
    ring_min = np.take_along_axis(ring_prof, jmin[:, :, None], axis=2)[:, :, 0].astype(np.float64)
    ring_level, _ = _upper_median(ring_min, np.ones_like(ring_min, dtype=bool))
    return jmin, ring_level


def _background_level(
    prof: F32Array, r_out: FloatArray, n_samples: NDArray[np.int64], jr3: NDArray[np.int64], valid3: BoolArray
) -> FloatArray:
    """Background grey level of each ring (E,): upper median of the tail samples ``r >= r_out + 1.8``
    px of all its rays, or the mean of the rays' last samples when no ray reaches that far."""
    E = prof.shape[0]
    j_tail = np.ceil((r_out + 1.8) / RAY_STEP_PX - 1e-9).astype(np.int64)
    t0 = max(int(j_tail.min()), 0)  # only the tail columns are sorted for the background level
    tail = (jr3[:, :, t0:] >= j_tail[:, :, None]) & valid3[:, :, t0:]
    bg_level, has_tail = _upper_median(prof[:, :, t0:].reshape(E, -1), tail.reshape(E, -1))
    if not np.all(has_tail):
        last = prof[np.arange(E), :, n_samples - 1].mean(axis=1)
        bg_level = np.where(has_tail, bg_level, last)
    return bg_level


def _hole_level(prof: F32Array, r_in: FloatArray, jr: NDArray[np.int64], valid3: BoolArray) -> FloatArray:
    """Grey level of each ring's hole (E,): upper median of the samples within
    ``max(0.35 min(r_in), 0.3)`` px of the origin on all its rays."""
    E, n = prof.shape[0], prof.shape[1]
    ds = RAY_STEP_PX
    hole_r = np.maximum(0.35 * r_in.min(axis=1), 0.3)
    n_hole = np.floor(hole_r / ds + 1e-9).astype(np.int64) + 1  # samples with r <= hole_r
    J = int(n_hole.max())
    hole = np.broadcast_to(((jr[None, :J] < n_hole[:, None]) & valid3[:, 0, :J])[:, None, :], (E, n, J))
    hole_level, _ = _upper_median(prof[:, :, :J].reshape(E, -1), hole.reshape(E, -1))
    return hole_level


def _outer_edge(
    prof: F32Array,
    t_out: FloatArray,
    jmin: NDArray[np.intp],
    jr3: NDArray[np.int64],
    valid3: BoolArray,
    r: FloatArray,
    ee: NDArray[np.int64],
    nn: NDArray[np.int64],
) -> tuple[FloatArray, BoolArray]:
    """Outer edge radius (px, sub-sample by linear interpolation) on each ray, and whether found:
    the first sample past the ring minimum at or above the threshold ``t_out`` (E, 1, 1)."""
    ds = RAY_STEP_PX
    above_o = (prof >= t_out) & (jr3 > jmin[:, :, None]) & valid3
    jo = np.argmax(above_o, axis=2)
    ok_o = above_o[ee, nn, jo] & (jo > 0)
    jo1 = np.maximum(jo - 1, 0)
    p1, p0 = prof[ee, nn, jo].astype(np.float64), prof[ee, nn, jo1].astype(np.float64)
    ro_sub = r[jo1] + ds * (t_out[:, :, 0] - p0) / np.where(p1 - p0 == 0, 1e-9, p1 - p0)
    return ro_sub, ok_o


def _inner_edge(
    prof: F32Array,
    t_in: FloatArray,
    jmin: NDArray[np.intp],
    jr3: NDArray[np.int64],
    r: FloatArray,
    ee: NDArray[np.int64],
    nn: NDArray[np.int64],
) -> tuple[FloatArray, BoolArray]:
    """Inner edge radius (px, sub-sample by linear interpolation) on each ray, and whether found:
    the last sample before the ring minimum at or above the threshold ``t_in`` (E, 1, 1)."""
    ds, S = RAY_STEP_PX, prof.shape[2]
    above_i = (prof >= t_in) & (jr3 < jmin[:, :, None])
    ji = S - 1 - np.argmax(above_i[:, :, ::-1], axis=2)
    ok_i = above_i[ee, nn, ji] & (ji < S - 1)
    q0 = prof[ee, nn, ji].astype(np.float64)
    q1 = prof[ee, nn, np.minimum(ji + 1, S - 1)].astype(np.float64)
    ri_sub = r[ji] + ds * (q0 - t_in[:, :, 0]) / np.where(q0 - q1 == 0, 1e-9, q0 - q1)
    return ri_sub, ok_i


def ring_edges_multi(
    parts: Sequence[tuple[U8Image, RingSeeds]], n_rays: int, min_contrast: float, min_valid_fraction: float
) -> RingEdges:
    """Sub-pixel outer and inner edge points of every seeded ring (see the module doc) of several
    images at once (e.g. both of a stereo pair): the rows of the result follow ``parts`` in order.

    A ring fails (``ok`` False) when its ring is not ``min_contrast`` grey levels darker than the
    background (and 0.35 of that than its hole), or when both edges are found on fewer than
    ``min_valid_fraction`` of the rays; an edge further than ``1.5 + 0.15 r`` (outer) or
    ``1.5 + 0.25 r`` (inner) px from the seed's radius on a ray does not count. Pure CPU.
    """
    seeds = RingSeeds.stack([sd for _, sd in parts])
    E, n, ds = seeds.count, n_rays, RAY_STEP_PX
    theta: FloatArray = np.arange(n, dtype=np.float64) * (2 * math.pi / n)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    if E == 0:
        z, zb = np.zeros((0, n)), np.zeros((0, n), dtype=bool)
        return RingEdges(z, z, zb, z, z, zb, np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))
    r_out = ellipse_radius(seeds.outer[:, 0], seeds.outer[:, 1], seeds.outer[:, 2], theta)
    r_in = ellipse_radius(seeds.inner[:, 0], seeds.inner[:, 1], seeds.inner[:, 2], theta)
    r_max = r_out.max(axis=1) + 3.0
    n_samples = np.ceil(r_max / ds).astype(np.int64)  # len(np.arange(0, r_max, ds)) per ring
    S = int(n_samples.max())
    r = np.arange(S, dtype=np.float64) * ds
    jr = np.arange(S)
    valid3 = (jr[None, :] < n_samples[:, None])[:, None, :]  # (E, 1, S)
    ox, oy = seeds.origin_px[:, 0], seeds.origin_px[:, 1]
    prof = _ray_profiles(parts, seeds, r, cos_t, sin_t)
    jr3 = jr[None, None, :]
    jmin, ring_level = _ring_minimum(prof, r_in, r_out, jr3, valid3)
    bg_level = _background_level(prof, r_out, n_samples, jr3, valid3)
    hole_level = _hole_level(prof, r_in, jr, valid3)
    contrast_ok = (bg_level - ring_level >= min_contrast) & (hole_level - ring_level >= 0.35 * min_contrast)
    t_out = (0.5 * (bg_level + ring_level))[:, None, None]
    t_in = (0.5 * (hole_level + ring_level))[:, None, None]
    ee, nn = np.arange(E)[:, None], np.arange(n)[None, :]
    ro_sub, ok_o = _outer_edge(prof, t_out, jmin, jr3, valid3, r, ee, nn)
    ri_sub, ok_i = _inner_edge(prof, t_in, jmin, jr3, r, ee, nn)
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
