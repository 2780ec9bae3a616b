"""`hil run` argument and file errors: one line on stderr, exit 2, nothing started."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.cli import main


def test_missing_plan_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "configs/sim.toml", "--plan", str(tmp_path / "nope.json"),
                 "--session-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("hil run: error: ")
    assert "nope.json: cannot read plan" in err
    assert len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_config_without_a_bundled_plan(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "rig.toml"
    cal = Path("configs/calibration/sim_stereo.json").resolve()
    text = Path("configs/sim.toml").read_text(encoding="utf-8")
    text = text.replace('stereo = "calibration/sim_stereo.json"', f'stereo = "{cal}"')
    cfg.write_text(text, encoding="utf-8")
    assert main(["run", str(cfg), "--session-dir", str(tmp_path / "s")]) == 2
    assert "no bundled plan for this setup; give one with --plan" in capsys.readouterr().err


def test_bad_config_names_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[camera]\ndriver = "sim"\n[robot]\ndriver = "sim"\n[procedure.gate]\ntolerance_mm = -1\n',
                   encoding="utf-8")
    assert main(["run", str(cfg), "--plan", "configs/plans/sim_plan.json"]) == 2
    assert "procedure.gate.tolerance_mm" in capsys.readouterr().err


def test_a_setup_without_any_stereo_calibration_is_refused_before_opening(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A replay camera knows no calibration and the setup gives none: one line, exit 2, and no
    device opened (the recording directory does not even exist; no session log is written)."""
    cfg = tmp_path / "nocal.toml"
    cfg.write_text('[camera]\ndriver = "replay"\nrecording_dir = "rec"\n\n[robot]\ndriver = "sim"\n')
    code = main(["run", str(cfg), "--plan", "configs/plans/sim_plan.json", "--auto",
                 "--session-dir", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 2
    assert err == ("hil run: error: setup: calibration.stereo: missing, and the camera driver 'replay' does "
                   "not know its stereo calibration; set [calibration] stereo to a calibration file "
                   "(hil calibrate writes one)\n")
    assert not (tmp_path / "s").exists()


def test_negative_seed_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--seed", "-3"]) == 2
    assert "--seed: must be >= 0" in capsys.readouterr().err


def test_interactive_operator_asks_once_and_maps_answers() -> None:
    import io

    from hil.cli.cmd_run import InteractiveOperator
    from hil.controller.fsm import Event, State
    from hil.controller.operator_input import OperatorView

    out = io.StringIO()
    op = InteractiveOperator(io.StringIO("y\nx\ns\nq\n"), out)
    assert op.poll(OperatorView(State.IDLE, None, "", 0.0, False)) is Event.START_REQUESTED
    assert op.poll(OperatorView(State.PLAN, "plan_to_approach", "", 1.0, True)) is Event.CONFIRM_REQUESTED
    assert "confirm plan_to_approach?" in out.getvalue()
    assert op.poll(OperatorView(State.LOCK, None, "", 2.0, True)) is None  # nothing to decide
    paused = OperatorView(State.PAUSED, None, "patient moved", 3.0, True)
    assert op.poll(paused) is None  # "x" is no answer
    assert op.poll(paused) is Event.START_REQUESTED
    assert not op.finished(paused)
    assert op.poll(paused) is None
    assert op.finished(paused)  # "q"
