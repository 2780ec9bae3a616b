"""A recorded trace drives the deformable body (issue 40): surrogate, tumour, skin points; bad traces."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.sim.world import SimWorld
from hil.cli import main
from hil.clock import ManualClock
from hil.config.body import BodyConfig, BodyTraceConfig
from hil.config.setup import FramesConfig
from hil.config.simulation import BreathHoldConfig, SimulationConfig, TremorConfig
from hil.errors import InputFileError
from tests.io.shared_data import shared_path

STILL = TremorConfig(amplitude_mm=0.0)
RATE_HZ = 10.0


def _surrogate(tmp_path: Path, seconds: float = 60.0) -> Path:
    t = np.arange(0.0, seconds, 1.0 / RATE_HZ)
    p = tmp_path / "resp.txt"
    p.write_text("".join(f"{a:.3f} {math.sin(2 * math.pi * a / 4.0):.9f}\n" for a in t))
    return p


def _tumour(tmp_path: Path) -> Path:
    """A 6-DoF trace: 8 mm superior-inferior (inhale: inferior, -y), 2 mm anterior, 4 s period."""
    t = np.arange(0.0, 60.0, 1.0 / RATE_HZ)
    s = 0.5 - 0.5 * np.cos(2 * np.pi * t / 4.0)
    p = tmp_path / "tumour.txt"
    p.write_text("".join(f"{a:.3f} 0.0 {-8.0 * b:.9f} {2.0 * b:.9f} 0.0 0.0 0.0\n"
                         for a, b in zip(t, s, strict=True)))
    return p


def _world(trace: Path, tmp_path: Path, **trace_kw: object) -> tuple[SimWorld, ManualClock]:
    cfg = BodyTraceConfig(path=trace, start_s=0.0, rate_hz=RATE_HZ, **trace_kw)
    sim = SimulationConfig(seed=2, tremor=STILL, body=BodyConfig(model="deformable", trace=cfg))
    clock = ManualClock()
    return SimWorld(sim, FramesConfig(), clock), clock


def _image(world: SimWorld, p: np.ndarray) -> np.ndarray:
    return world.T_optical_from_image0.inverse().apply(p)


def test_a_surrogate_is_the_breathing_signal(tmp_path: Path) -> None:
    world, _ = _world(_surrogate(tmp_path), tmp_path)
    assert world.body is not None
    sig = world.body.signal
    raw = np.sin(2 * np.pi * np.arange(0.0, 60.0, 0.1) / 4.0)
    lo, hi = np.percentile(raw, [5.0, 95.0])
    for t in (0.0, 1.0, 2.5, 13.3):
        assert sig.s(t) == pytest.approx((math.sin(2 * math.pi * t / 4.0) - lo) / (hi - lo), abs=2e-3)
    # the trace (0 .. 59.9 s) wraps at its end
    assert sig.s(59.9 + 1.3) == pytest.approx(sig.s(1.3), abs=1e-9)


def test_a_tumour_trace_drives_the_target(tmp_path: Path) -> None:
    world, clock = _world(_tumour(tmp_path), tmp_path)
    rest = world.phantom.target_mm
    for t in (0.0, 1.0, 2.0, 3.3):
        b = 0.5 - 0.5 * math.cos(2 * math.pi * t / 4.0)
        got = _image(world, world.target_optical(clock.now_ns() + round(t * 1e9))[None, :])[0] - rest
        assert np.allclose(got, [0.0, -8.0 * b, 2.0 * b], atol=0.05)
    # without a surrogate the skin follows the tumour's own normalised motion: inhale = inferior
    assert world.body is not None
    assert world.body.signal.s(2.0) > 0.9 > 0.1 > world.body.signal.s(0.0)


def test_a_breath_hold_brings_a_recorded_target_back_but_not_exactly(tmp_path: Path) -> None:
    cfg = BodyTraceConfig(path=_tumour(tmp_path), start_s=0.0, rate_hz=RATE_HZ)
    holds = (BreathHoldConfig(start_s=1.0, duration_s=5.0),)
    sim = SimulationConfig(seed=2, tremor=STILL, breath_holds=holds,
                           body=BodyConfig(model="deformable", trace=cfg))
    clock = ManualClock()
    world = SimWorld(sim, FramesConfig(), clock)
    assert world.body is not None
    got = _image(world, world.target_optical(clock.now_ns() + 4_000_000_000)[None, :])[0]
    expected = world.phantom.target_mm + world.body.target_motion.hold_offset_mm(0)
    assert np.allclose(got, expected, atol=0.05)


def _points(tmp_path: Path, places: dict[str, tuple[float, float]], sidecar: bool = True) -> Path:
    """Recorded skin points moving by an affine field of their place: d = s (a x + b y + c) per axis."""
    t = np.arange(0.0, 40.0, 1.0 / RATE_HZ)
    s = 0.5 - 0.5 * np.cos(2 * np.pi * t / 4.0)
    names = sorted(places)
    header = ["time_s"] + [f"{n}_{ax}_mm" for n in names for ax in "xyz"]
    rows = []
    for a, b in zip(t, s, strict=True):
        vals = [f"{a:.3f}"]
        for n in names:
            x, y = places[n]
            d = _affine(x, y) * b
            vals += [f"{x + d[0]:.9f}", f"{y + d[1]:.9f}", f"{d[2]:.9f}"]
        rows.append(",".join(vals))
    p = tmp_path / "skin.csv"
    p.write_text(",".join(header) + "\n" + "\n".join(rows) + "\n")
    if sidecar:
        (tmp_path / "skin.csv.points.json").write_text(json.dumps({n: list(v) for n, v in places.items()}))
    return p


def _affine(x: float, y: float) -> np.ndarray:
    return np.array([0.01 * x, 0.02 * y + 1.0, 6.0 + 0.03 * x - 0.02 * y])


PLACES = {"A": (-80.0, -70.0), "B": (90.0, -60.0), "C": (70.0, 85.0), "D": (-60.0, 75.0)}


def test_recorded_skin_points_drive_the_skin_between_them(tmp_path: Path) -> None:
    world, clock = _world(_points(tmp_path, PLACES), tmp_path)
    t = 2.0                                                   # the recording's end-inhale
    markers, _ = world.patient_markers_optical(clock.now_ns() + round(t * 1e9))
    got = _image(world, markers) - world.phantom.markers_mm
    # displacements count from end-exhale, the recording's 5th percentile (docs/config.md)
    b5 = float(np.percentile(0.5 - 0.5 * np.cos(2 * np.pi * np.arange(0.0, 40.0, 0.1) / 4.0), 5.0))
    expected = np.array([_affine(x, y) for x, y in world.phantom.markers_mm[:, :2]]) * (1.0 - b5)
    assert np.allclose(got, expected, atol=1e-6)


def test_places_from_the_config_stand_in_for_a_sidecar(tmp_path: Path) -> None:
    world, _ = _world(_points(tmp_path, PLACES, sidecar=False), tmp_path, points=PLACES)
    assert world.body is not None


@pytest.mark.parametrize(("places", "match"), [
    ({"A": (0.0, 0.0), "B": (50.0, 0.0)}, "at least 3"),
    ({"A": (0.0, 0.0), "B": (50.0, 50.0), "C": (100.0, 100.0)}, "collinear"),
])
def test_too_few_or_collinear_points_are_refused(tmp_path: Path, places: dict[str, tuple[float, float]],
                                                 match: str) -> None:
    path = _points(tmp_path, places)
    with pytest.raises(InputFileError, match=match) as info:
        _world(path, tmp_path)
    assert info.value.path == str(path)


def test_points_without_a_place_are_refused(tmp_path: Path) -> None:
    path = _points(tmp_path, PLACES, sidecar=False)
    with pytest.raises(InputFileError, match="no place on the skin for recorded point"):
        _world(path, tmp_path, points={"A": (0.0, 0.0)})


def test_a_short_trace_is_refused(tmp_path: Path) -> None:
    path = _surrogate(tmp_path, seconds=12.0)
    with pytest.raises(InputFileError, match="a procedure needs at least 20 s") as info:
        _world(path, tmp_path)
    assert info.value.path == str(path)


def test_hil_run_trace_drives_the_procedure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "--json", "--no-report", "--session-dir", str(tmp_path), "--trace",
                 str(_surrogate(tmp_path))])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert out["final_state"] == "done"
    assert out["body_rigid_residual_mm_p95"] > 0.1          # the body is deformable now
    assert out["target_error_mm"] is not None
    assert out["target_error_mm"] >= 0.0
    assert out["target_error_max_mm"] >= out["target_error_mm"]


def test_hil_run_refuses_a_bad_trace_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1\n0.1 nan\n")
    code = main(["run", "--json", "--no-report", "--session-dir", str(tmp_path), "--trace", str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1
    assert err[0].startswith(f"hil run: error: {bad}:2:")


def test_a_shared_paired_trace_drives_sim_patient(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trace = shared_path("respiration", "interact", "paired", "LARK_Liver_Mean_Motion_1")
    code = main(["run", "configs/sim_patient.toml", "--auto", "--json", "--no-report", "--session-dir",
                 str(tmp_path), "--trace", str(trace)])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert out["final_state"] == "done"
    assert out["lock_error_mm"] is not None
    assert out["target_error_mm"] is not None
