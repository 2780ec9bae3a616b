"""Hypothesis strategies shared by the geometry tests."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hil.geometry.transform import RigidTransform

finite = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False, allow_infinity=False)


@st.composite
def rotations(draw: st.DrawFn) -> RigidTransform:
    """Uniform-ish random rotations from a random (non-degenerate) quaternion."""
    q = draw(arrays(np.float64, 4, elements=finite))
    if np.linalg.norm(q) < 0.1:
        q = np.array([1.0, 0.0, 0.0, 0.0]) + q
    return RigidTransform.from_quaternion(q)


@st.composite
def rigid_transforms(draw: st.DrawFn, max_translation_mm: float = 1000.0) -> RigidTransform:
    R = draw(rotations())
    t = draw(
        arrays(np.float64, 3, elements=st.floats(-max_translation_mm, max_translation_mm, allow_nan=False))
    )
    return RigidTransform(R.R, t)


@st.composite
def point_sets(
    draw: st.DrawFn, min_points: int = 3, max_points: int = 12, scale_mm: float = 100.0
) -> np.ndarray:
    """Well-conditioned point sets: second singular value at least 10% of the first."""
    n = draw(st.integers(min_points, max_points))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    while True:
        pts = rng.uniform(-scale_mm, scale_mm, size=(n, 3))
        sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if sv[1] > 0.1 * sv[0]:
            return pts
