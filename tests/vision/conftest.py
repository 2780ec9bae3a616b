"""Shared fixtures of the vision tests: a seed-001-like rig and rendered scenes with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from hil.vision.camera_model import StereoCalibration
from hil.vision.render import RenderedPair, RenderOptions, RingMarker3D, random_marker_layout, render_stereo

DIST = (-0.05, 0.02, 0.0005, -0.0003, 0.0)


@pytest.fixture(scope="session")
def cal() -> StereoCalibration:
    return StereoCalibration.synthetic(dist=DIST)


@pytest.fixture(scope="session")
def scene(cal: StereoCalibration) -> tuple[list[RingMarker3D], RenderedPair]:
    rng = np.random.default_rng(11)
    markers = random_marker_layout(rng, 8)
    return markers, render_stereo(cal, markers, RenderOptions(), rng)
