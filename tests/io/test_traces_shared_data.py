"""hil.io.traces on the real InterACT traces in ../shared/data/respiration (IntERAct, University of
Sydney Image X Institute; see shared/data/README.md). Absent data fails the test naming the path."""

from __future__ import annotations

import numpy as np
import pytest

from hil.io.traces import read_trace, trace_summary
from tests.io.shared_data import shared_path

RESP = ("respiration", "interact")

#: file under respiration/interact -> (format, samples, first time s, duration s)
FILES: dict[str, tuple[str, int, float, float]] = {
    "6dof/Liver/Liver_Trace 1.txt": ("6dof", 6517, 0.0, 1303.2),
    "6dof/Liver/Liver_Trace 2.txt": ("6dof", 6370, 0.0, 1273.8),
    "6dof/Lung/Trace 1-Large AP motion.txt": ("6dof", 6543, 0.0, 1308.4),
    "6dof/Lung/Trace-2-Large rotational motion rSI.txt": ("6dof", 6543, 0.0, 1308.4),
    "6dof/Lung/Trace-3-Large translational motion SI.txt": ("6dof", 6016, 0.0, 1203.0),
    "6dof/Prostate/Trace 1-Stable target baseline.txt": ("6dof", 7149, 0.0, 1429.6),
    "6dof/Prostate/Trace 2-Persistant excursion.txt": ("6dof", 6737, 0.0, 1347.2),
    "6dof/Prostate/Trace 3-Erratic behaviour.txt": ("6dof", 6736, 0.0, 1347.0),
    "6dof/Prostate/Trace 4-Continuous target drift.txt": ("6dof", 8113, 0.0, 1622.4),
    "paired/LARK_Liver_Mean_Motion_1/3.Mean_motion_1_092_gradual_start.txt": ("6dof", 1500, 0.0, 299.8),
    "paired/LARK_Liver_Mean_Motion_1/3.Mean_motion_1_092_resp_shifted_rescaled_gradual_start.txt":
        ("surrogate", 1500, 0.0, 299.8),
    "paired/LARK_Liver_Mean_Motion_2/4.Mean_motion_2_111_gradual_start.txt": ("6dof", 1500, 0.0, 299.8),
    "paired/LARK_Liver_Mean_Motion_2/4.Mean_motion_2_111_resp_shifted_rescaled_gradual_start.txt":
        ("surrogate", 1500, 0.0, 299.8),
    "paired/LIGHT_SABR_Lung_High_Complexity/4.High_Complexity SI.txt": ("6dof", 1500, 0.0, 299.8),
    "paired/LIGHT_SABR_Lung_High_Complexity/4.High_Complexity_resp.txt": ("surrogate", 1500, 0.0, 299.8),
    "paired/LIGHT_SABR_Lung_High_Motion/2.High_Motion SI.txt": ("6dof", 1500, 0.0, 299.8),
    "paired/LIGHT_SABR_Lung_High_Motion/2.High_Motion_resp.txt": ("surrogate", 1500, 0.0, 299.8),
    "paired/LIGHT_SABR_Lung_Mean_Complexity/3.Mean_Complexity SI.txt": ("6dof", 1500, 0.0, 299.8),
    "paired/LIGHT_SABR_Lung_Mean_Complexity/3.Mean_Complexity_resp.txt": ("surrogate", 1500, 0.0, 299.8),
    "paired/LIGHT_SABR_Lung_Mean_Motion_1/1.Mean_Motion_gradual_start.txt": ("6dof", 1510, 0.0, 301.8),
    "paired/LIGHT_SABR_Lung_Mean_Motion_1/1.Mean_Motion_resp_shifted_rescaled_gradual_start.txt":
        ("surrogate", 1510, 0.0, 301.8),
    "paired/LIGHT_SABR_Lung_Mean_Motion_2/2.Mean_Motion2_gradual_start.txt": ("6dof", 1511, 0.0, 302.0),
    "paired/LIGHT_SABR_Lung_Mean_Motion_2/2.Mean_Motion2_resp_shifted_rescaled_gradual_start.txt":
        ("surrogate", 1510, 0.0, 301.8),
}

#: paired directory -> (samples on the common time stamps, SI peak to peak mm, note or None)
PAIRED: dict[str, tuple[int, float, str | None]] = {
    "LARK_Liver_Mean_Motion_1": (1500, 12.9726, None),
    "LARK_Liver_Mean_Motion_2": (1500, 24.9277, None),
    "LIGHT_SABR_Lung_High_Complexity": (1500, 18.4714, None),
    "LIGHT_SABR_Lung_High_Motion": (1500, 21.04, None),
    "LIGHT_SABR_Lung_Mean_Complexity": (1500, 16.1748, None),
    "LIGHT_SABR_Lung_Mean_Motion_1": (1510, 7.93569, None),
    "LIGHT_SABR_Lung_Mean_Motion_2": (
        1510, 6.3888, "common span 0-301.8 s: dropped 1 sample(s) of 2.Mean_Motion2_gradual_start.txt"),
}


def test_every_trace_file_is_listed() -> None:
    root = shared_path(*RESP)
    found = {str(p.relative_to(root)) for p in root.rglob("*.txt")}
    assert found == set(FILES)
    assert {p.name for p in (root / "paired").iterdir()} == set(PAIRED)


@pytest.mark.parametrize("rel", sorted(FILES))
def test_trace_file_reads(rel: str) -> None:
    fmt, samples, t0, duration = FILES[rel]
    tr = read_trace(shared_path(*RESP, rel))
    assert tr.format == fmt
    assert tr.time_s.size == samples
    assert tr.time_s[0] == t0
    assert tr.duration_s == pytest.approx(duration, abs=1e-9)
    assert tr.rate_hz == pytest.approx(5.0, abs=1e-9)
    assert tr.gaps() == []
    np.testing.assert_allclose(np.diff(tr.time_s), 0.2, atol=1e-9)


@pytest.mark.parametrize("name", sorted(PAIRED))
def test_paired_directory_reads(name: str) -> None:
    samples, si_ptp_mm, note = PAIRED[name]
    tr = read_trace(shared_path(*RESP, "paired", name))
    assert tr.format == "paired"
    assert tr.time_s.size == samples
    assert tr.rate_hz == pytest.approx(5.0, abs=1e-9)
    assert tr.target_mm is not None
    assert tr.surrogate is not None
    assert tr.surrogate.shape == (samples,)
    # the superior-inferior motion lands on image y alone
    assert np.ptp(tr.target_mm[:, 1]) == pytest.approx(si_ptp_mm, abs=1e-9)
    assert not np.any(tr.target_mm[:, [0, 2]])
    assert tr.units.get("note") == note
    assert trace_summary(tr)["amplitude_mm"] == [pytest.approx(si_ptp_mm, abs=1e-6)]


def test_6dof_axes_match_the_trace_names() -> None:
    """The PDF's trace names check the column mapping: the 'large translational motion SI' lung trace
    moves most along image y (superior), the 'large AP motion' one most along z (anterior)."""
    si = read_trace(shared_path(*RESP, "6dof/Lung/Trace-3-Large translational motion SI.txt"))
    ap = read_trace(shared_path(*RESP, "6dof/Lung/Trace 1-Large AP motion.txt"))
    rsi = read_trace(shared_path(*RESP, "6dof/Lung/Trace-2-Large rotational motion rSI.txt"))
    assert si.target_mm is not None
    assert ap.target_mm is not None
    assert rsi.target_rotation_deg is not None
    assert int(np.argmax(np.ptp(si.target_mm, axis=0))) == 1
    assert int(np.argmax(np.ptp(ap.target_mm, axis=0))) == 2
    assert int(np.argmax(np.ptp(rsi.target_rotation_deg, axis=0))) == 1
    # the PDF's plot of the AP trace: RL up to 4.8 mm, SI up to 4.2 mm, AP down to -6.1 mm
    np.testing.assert_allclose(ap.target_mm.max(axis=0)[:2], [4.8, 4.2], atol=0.05)
    assert ap.target_mm[:, 2].min() == pytest.approx(-6.1, abs=0.05)
