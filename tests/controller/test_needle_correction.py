"""The needle-axis checkers take the path in the controller's corrected optical frame and search
the images where the stereo calibration sees it (the rig calibration's optical correction undone)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from drivers.interfaces.camera import Frame, StereoFrame
from hil.controller import perception
from hil.controller.perception import CollinearNeedleChecker, StereoNeedleChecker
from hil.geometry.projective import ProjectiveCorrection, warp_matrix
from hil.vision.camera_model import StereoCalibration

POINTS = [np.array(p) for p in ([10.0, 20.0, 900.0], [12.0, 25.0, 960.0], [15.0, 30.0, 1000.0],
                                [20.0, 40.0, 1080.0])]
CORRECTION = ProjectiveCorrection.undoing(warp_matrix((60.0, 120.0, 860.0), (0.004, 0.003, 0.006, 0.0, 0.001,
                                                                              0.0, 3e-6, 1e-6, -2e-6)))


def _frame() -> StereoFrame:
    img = np.zeros((8, 8), dtype=np.uint8)
    return StereoFrame(Frame(image=img, t_ns=1, seq=1), Frame(image=img, t_ns=1, seq=1))


@pytest.mark.parametrize("correction", [None, CORRECTION], ids=["none", "corrected"])
@pytest.mark.parametrize("kind", ["cylinder", "collinear"])
def test_the_path_is_searched_where_the_cameras_see_it(monkeypatch: pytest.MonkeyPatch, kind: str,
                                                       correction: ProjectiveCorrection | None) -> None:
    seen: list[Any] = []

    def record(_cal: Any, _left: Any, _right: Any, *pts: Any, **_kw: Any) -> str:
        seen.extend(pts[:4])
        return "measured"

    monkeypatch.setattr(perception, "measure_needle_axis", record)
    monkeypatch.setattr(perception, "measure_bead_axis", record)
    cal = StereoCalibration.synthetic()
    checker = (StereoNeedleChecker(cal, 1.0, correction) if kind == "cylinder"
               else CollinearNeedleChecker(cal, (20.0, 50.0, 80.0), 10.0, correction))
    assert checker(_frame(), *POINTS) == "measured"
    want = POINTS if correction is None else list(correction.to_measured(np.array(POINTS)))
    assert len(seen) == 4
    for got, w in zip(seen, want, strict=True):
        np.testing.assert_allclose(got, w, rtol=0, atol=1e-12)
    if correction is not None:
        assert min(float(np.linalg.norm(g - p)) for g, p in zip(seen, POINTS, strict=True)) > 0.1
