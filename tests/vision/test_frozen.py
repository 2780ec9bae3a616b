"""The hot-path builder of frozen dataclasses gives the objects their constructors give."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from hil.vision.camera_model import StereoCalibration
from hil.vision.detect import RingDetection, detect_rings
from hil.vision.ellipse import Ellipse
from hil.vision.frozen import frozen_instance
from hil.vision.render import RenderedPair, RingMarker3D
from hil.vision.stereo import StereoPoint, match_and_triangulate


def _rebuilt(obj: Any) -> Any:
    """``obj`` built again by its class's constructor from its fields."""
    return type(obj)(**{f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)})


def _same(a: Any, b: Any) -> None:
    assert type(a) is type(b)
    assert vars(a).keys() == vars(b).keys() == {f.name for f in dataclasses.fields(a)}
    for name, value in vars(a).items():
        other = vars(b)[name]
        if isinstance(value, np.ndarray):
            assert np.array_equal(value, other)
        else:
            assert value is other or value == other


def test_every_batch_built_object_equals_its_constructors(
    cal: StereoCalibration, scene: tuple[list[RingMarker3D], RenderedPair]
) -> None:
    _, pair = scene
    dl, dr = detect_rings(pair.left), detect_rings(pair.right)
    st = match_and_triangulate(cal, dl, dr)
    assert len(dl) == len(dr) == len(st.points) == 8
    for det in dl + dr:
        _same(det, _rebuilt(det))
        _same(det.outer, _rebuilt(det.outer))
        _same(det.inner, _rebuilt(det.inner))
    for p in st.points:
        _same(p, _rebuilt(p))
    # and they stay frozen
    with pytest.raises(dataclasses.FrozenInstanceError):
        dl[0].center_sigma_px = 0.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        dl[0].outer.a_px = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        st.points[0].gap_mm = 0.0  # type: ignore[misc]


@pytest.mark.parametrize("cls", [Ellipse, RingDetection, StereoPoint])
def test_the_built_classes_have_no_defaults_or_post_init(cls: type) -> None:
    # frozen_instance skips __init__: a default or a __post_init__ would be silently lost
    assert dataclasses.is_dataclass(cls)
    assert all(
        f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        for f in dataclasses.fields(cls)
    )
    assert not hasattr(cls, "__post_init__")


def test_frozen_instance_builds_the_class_with_the_given_fields() -> None:
    c, C = np.array([1.0, 2.0]), np.eye(3)
    e = frozen_instance(Ellipse, {"center_px": c, "a_px": 3.0, "b_px": 2.0, "angle_rad": 0.5, "conic": C,
                                  "residual_rms_px": 0.01, "n_points": 32})
    _same(e, Ellipse(c, 3.0, 2.0, 0.5, C, 0.01, 32))
