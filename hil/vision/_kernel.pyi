"""Type stub of the compiled kernel (hil/vision/_kernel.c); the docstrings there state the contract."""

from typing import Any

def ring_geometry(outer: Any, inner: Any, theta: Any, r_out: Any, r_in: Any, n_samples: Any) -> int: ...
def ray_maps(origin: Any, cos_t: Any, sin_t: Any, mapx: Any, mapy: Any) -> None: ...
def ring_edges(
    grey: Any, dark_on_light: Any, origin: Any, cos_t: Any, sin_t: Any, r_out: Any, r_in: Any,
    n_samples: Any, min_contrast: float, min_valid_fraction: float, xo: Any, yo: Any, mo: Any,
    xi: Any, yi: Any, mi: Any, frac: Any, ok: Any,
) -> None: ...
def fit_ellipses(
    X: Any, Y: Any, M: Any, conic: Any, center: Any, a: Any, b: Any, angle: Any, residual: Any,
    n_points: Any, good: Any, used: Any,
) -> None: ...
def normal_correction(
    C: Any, w: Any, K_left: Any, K_right: Any, R_right_from_left: Any, UL: Any, UR: Any, normals: Any,
    ok: Any,
) -> None: ...
def ring_check(
    a: Any, b: Any, center: Any, residual: Any, n_points: Any, good: Any, max_residual: float,
    concentric_tol: float, ratio: float, ratio_tol: float, eccentricity_tol: float, ok: Any,
    ring_center: Any, sigma: Any, resid: Any,
) -> None: ...
def triangulate_dlt(P_left: Any, P_right: Any, uv_left: Any, uv_right: Any, points: Any, ok: Any) -> None: ...
def ray_gaps(
    UL: Any, UR: Any, K_left_inv: Any, K_right_inv: Any, R_right_from_left: Any, right_center: Any,
    gaps: Any, ok: Any,
) -> None: ...
