"""Recording stereo sessions losslessly and replaying them as a camera."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from drivers.camera.recording import StereoRecorder, read_info, read_timestamps, record
from drivers.camera.replay import ReplayStereoCamera
from drivers.interfaces.camera import Frame, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError
from hil.clock import ManualClock
from hil.errors import InputFileError

PERIOD_NS = 33_333_333


def make_pairs(n: int, seed: int = 0) -> list[StereoFrame]:
    rng = np.random.default_rng(seed)
    pairs = []
    for k in range(n):
        t = 1_000_000_000 + k * PERIOD_NS
        left = Frame(rng.integers(0, 256, (48, 64), dtype=np.uint8), t, 10 + k, 5_000 + k)
        right = Frame(rng.integers(0, 256, (48, 64), dtype=np.uint8), t + 2_000_000, 20 + k, None)
        pairs.append(StereoFrame(left, right))
    return pairs


def write(directory: Path, pairs: list[StereoFrame], codec: str = "ffv1") -> Path:
    with StereoRecorder(directory, frame_rate_hz=30.0, exposure_us=4000.0, codec=codec) as rec:  # type: ignore[arg-type]
        for p in pairs:
            rec.write(p)
    return directory


@pytest.mark.parametrize("codec", ["ffv1", "png"])
def test_round_trip_is_bit_exact_with_metadata(tmp_path: Path, codec: str) -> None:
    pairs = make_pairs(4)
    rec_dir = write(tmp_path / "rec", pairs, codec)
    info = read_info(rec_dir)
    assert (info.codec, info.image_size, info.frame_rate_hz, info.exposure_us, info.pairs) == (
        codec, (64, 48), 30.0, 4000.0, 4)
    rows = read_timestamps(rec_dir)
    assert [(r.left_seq, r.left_t_ns, r.left_device_t_ns, r.right_device_t_ns) for r in rows] == [
        (10 + k, 1_000_000_000 + k * PERIOD_NS, 5_000 + k, None) for k in range(4)]
    cam = ReplayStereoCamera("camera", rec_dir, ManualClock(), speed=0.0)
    cam.open()
    out = [cam.grab(1.0) for _ in range(4)]
    cam.close()
    for got, want in zip(out, pairs, strict=True):
        assert np.array_equal(got.left.image, want.left.image)
        assert np.array_equal(got.right.image, want.right.image)
        assert (got.left.seq, got.right.seq) == (want.left.seq, want.right.seq)
        assert (got.left.device_t_ns, got.right.device_t_ns) == (want.left.device_t_ns, None)
        assert got.skew_ns == 2_000_000  # the recorded left/right skew is kept


def test_replay_keeps_the_recorded_pace_on_the_clock(tmp_path: Path) -> None:
    rec_dir = write(tmp_path / "rec", make_pairs(3))
    clock = ManualClock(start_ns=50_000_000_000)
    cam = ReplayStereoCamera("camera", rec_dir, clock, speed=1.0)
    cam.open()
    times = [cam.grab(1.0).t_ns for _ in range(3)]
    assert [t - times[0] for t in times] == [0, PERIOD_NS, 2 * PERIOD_NS]
    assert clock.now_ns() == 50_000_000_000 + 2 * PERIOD_NS
    cam.close()


def test_replay_twice_as_fast(tmp_path: Path) -> None:
    rec_dir = write(tmp_path / "rec", make_pairs(3))
    clock = ManualClock()
    cam = ReplayStereoCamera("camera", rec_dir, clock, speed=2.0)
    cam.open()
    times = [cam.grab(1.0).t_ns for _ in range(3)]
    assert [t - times[0] for t in times] == [0, round(PERIOD_NS / 2), PERIOD_NS]
    cam.close()


def test_timeout_when_the_next_pair_is_due_later(tmp_path: Path) -> None:
    rec_dir = write(tmp_path / "rec", make_pairs(2))
    clock = ManualClock()
    cam = ReplayStereoCamera("camera", rec_dir, clock, speed=0.01)
    cam.open()
    cam.grab(1.0)
    with pytest.raises(DeviceTimeoutError, match="due in"):
        cam.grab(0.5)
    assert clock.now_ns() == 500_000_000  # waited the timeout, not the 3.3 s
    cam.close()


def test_end_of_recording_and_loop(tmp_path: Path) -> None:
    pairs = make_pairs(2)
    rec_dir = write(tmp_path / "rec", pairs)
    cam = ReplayStereoCamera("camera", rec_dir, ManualClock(), speed=0.0)
    cam.open()
    cam.grab(1.0)
    cam.grab(1.0)
    with pytest.raises(DisconnectedError, match="ended after 2 pairs"):
        cam.grab(1.0)
    cam.close()
    looping = ReplayStereoCamera("camera", rec_dir, ManualClock(), speed=1.0, loop=True)
    looping.open()
    got = [looping.grab(1.0) for _ in range(5)]
    looping.close()
    assert [g.left.seq for g in got] == [10, 11, 10, 11, 10]
    assert np.array_equal(got[2].left.image, pairs[0].left.image)
    assert all(b.t_ns > a.t_ns for a, b in itertools.pairwise(got))


def test_record_from_a_camera(tmp_path: Path) -> None:
    rec_dir = write(tmp_path / "src", make_pairs(3))
    source = ReplayStereoCamera("camera", rec_dir, ManualClock(), speed=0.0)
    source.open()
    info = record(source, tmp_path / "copy", 3, codec="png")
    source.close()
    assert info.pairs == 3
    assert sorted(p.name for p in (tmp_path / "copy" / "left").iterdir()) == [
        "000000.png", "000001.png", "000002.png"]


def test_recorder_refuses_to_overwrite_and_size_changes(tmp_path: Path) -> None:
    rec_dir = write(tmp_path / "rec", make_pairs(1))
    with pytest.raises(InputFileError, match="already holds a recording"):
        StereoRecorder(rec_dir, frame_rate_hz=30.0)
    rec = StereoRecorder(tmp_path / "other", frame_rate_hz=30.0)
    rec.write(make_pairs(1)[0])
    small = Frame(np.zeros((10, 10), np.uint8), 0, 0)
    with pytest.raises(ValueError, match="image size changed"):
        rec.write(StereoFrame(small, small))
    rec.close()


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda d: (d / "recording.json").unlink(), "missing: not a stereo recording"),
        (lambda d: (d / "recording.json").write_text("{"), "not readable JSON"),
        (lambda d: (d / "recording.json").write_text(json.dumps({"format": "x"})), "'format' must be"),
        (lambda d: (d / "timestamps.csv").write_text("a,b\n"), "line 1: header must be"),
        (lambda d: (d / "timestamps.csv").write_text(
            "pair,left_seq,left_t_ns,left_device_t_ns,right_seq,right_t_ns,right_device_t_ns\n0,1,x,,1,2,\n"),
         "line 2: not an integer"),
        (lambda d: (d / "timestamps.csv").write_text(
            "pair,left_seq,left_t_ns,left_device_t_ns,right_seq,right_t_ns,right_device_t_ns\n0,1,2,,1,2,\n"),
         "1 rows but recording.json says 2 pairs"),
        (lambda d: (d / "left.mkv").unlink(), "left.mkv: missing"),
    ],
)
def test_damaged_recordings_are_input_file_errors(tmp_path: Path, damage, message: str) -> None:  # type: ignore[no-untyped-def]
    rec_dir = write(tmp_path / "rec", make_pairs(2))
    damage(rec_dir)
    cam = ReplayStereoCamera("camera", rec_dir, ManualClock())
    with pytest.raises(InputFileError, match=message):
        cam.open()


def test_record_the_simulated_camera_then_replay_it_from_a_setup(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from drivers.camera.record import main as record_main
    from hil.config.build import build_devices
    from hil.config.loader import load_setup

    root = Path(__file__).resolve().parents[2]
    assert record_main([str(root / "configs" / "sim.toml"), str(tmp_path / "rec"), "--pairs", "3"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (summary["pairs"], summary["image_size"], summary["frame_rate_hz"]) == (3, [1920, 1080], 15.0)

    text = (root / "configs" / "sim.toml").read_text()
    head, rest = text.split("[camera]", 1)
    replay_section = '[camera]\ndriver = "replay"\nrecording_dir = "rec"\nspeed = 0.0\n\n'
    text = head + replay_section + rest[rest.index("[robot]"):]
    text = text.replace('"calibration/', f'"{root / "configs" / "calibration"}/')
    (tmp_path / "replay.toml").write_text(text)
    setup = load_setup(tmp_path / "replay.toml")
    camera = build_devices(setup, ManualClock()).camera
    camera.open()
    pairs = [camera.grab(1.0) for _ in range(3)]
    with pytest.raises(DisconnectedError, match="ended after 3 pairs"):
        camera.grab(1.0)
    camera.close()
    rows = read_timestamps(tmp_path / "rec")
    assert [p.left.seq for p in pairs] == [r.left_seq for r in rows]
    assert [p.left.device_t_ns for p in pairs] == [r.left_device_t_ns for r in rows]
    assert all(p.left.image.shape == (1080, 1920) for p in pairs)
    assert not np.array_equal(pairs[0].left.image, pairs[0].right.image)  # two different views


def test_record_command_reports_bad_setup_in_one_line(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from drivers.camera.record import main as record_main

    assert record_main([str(tmp_path / "missing.toml"), str(tmp_path / "rec")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"record: {tmp_path / 'missing.toml'}")
    assert len(err.splitlines()) == 1
