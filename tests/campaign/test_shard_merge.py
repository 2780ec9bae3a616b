"""``--shard I/N`` (0-based) and ``hil campaign merge``, on synthetic campaign outputs (no
simulation): the shards partition the matrix; merge combines them into the summary object of
``hil campaign --json`` and refuses, in one line with exit code 2, what cannot be combined."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.campaign.merge import MergeError, merge_outputs
from hil.campaign.report import summarise
from hil.campaign.shard import Shard, ShardSpecError, matrix_identity, parse_shard
from hil.cli import main

MATRIX = matrix_identity(["baseline_s1", "frame_drop@lock_s1", "glare@gate_s1"])


@given(count=st.integers(1, 40), size=st.integers(0, 200))
def test_shards_partition_the_matrix(count: int, size: int) -> None:
    owners = [[i for i in range(count) if parse_shard(f"{i}/{count}").owns(k)] for k in range(size)]
    assert owners == [[k % count] for k in range(size)]


@given(index=st.integers(0, 99), extra=st.integers(1, 50))
def test_parse_shard_round_trips(index: int, extra: int) -> None:
    shard = parse_shard(f"{index}/{index + extra}")
    assert shard == Shard(index, index + extra)
    assert str(shard) == f"{index}/{index + extra}"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("3/3", "--shard '3/3': the shard index is 0-based, so it must be 0..2"),
        ("a/b", "--shard 'a/b': expected I/N with 0 <= I < N (0-based), e.g. 0/4"),
        ("0/0", "--shard '0/0': the shard count N must be >= 1"),
        ("-1/3", "--shard '-1/3': expected I/N with 0 <= I < N (0-based), e.g. 0/4"),
        ("1/2/3", "--shard '1/2/3': expected I/N with 0 <= I < N (0-based), e.g. 0/4"),
        ("", "--shard '': expected I/N with 0 <= I < N (0-based), e.g. 0/4"),
    ],
)
def test_bad_shard_specs(text: str, message: str) -> None:
    with pytest.raises(ShardSpecError) as err:
        parse_shard(text)
    assert str(err.value) == message


def _rec(run_id: str, *, passed: bool = True) -> dict[str, Any]:
    scenario, _, seed = run_id.rpartition("_s")
    kind, _, state = scenario.partition("@")
    return {"run_id": run_id, "scenario": scenario, "kind": kind if state else None, "state": state or None,
            "seed": int(seed), "passed": passed, "reasons": [] if passed else ["no safe state"],
            "outcome": "safe_state" if passed else "tolerated", "safe_latency_ms": 100.0 if state else None,
            "replay": f"hil campaign {scenario} --seed {seed} --config sim.toml"}


def _output(d: Path, records: list[dict[str, Any]], *, shard: tuple[int, int] | None, code: str = "git:aa",
            digest: str = "c0", tier: str = "simulator", matrix: dict[str, Any] = MATRIX) -> Path:
    d.mkdir(parents=True)
    summary = summarise(records, config="sim.toml")
    summary.update(tier=tier, code_version={"id": code}, config_sha256=digest, matrix=matrix,
                   shard=None if shard is None else {"index": shard[0], "count": shard[1]})
    stem = "campaign" if tier == "simulator" else "transport"
    (d / f"{stem}.json").write_text(json.dumps(summary))
    for r in records:
        if not r["passed"]:
            (d / "logs").mkdir(exist_ok=True)
            (d / "logs" / f"{r['run_id']}.jsonl").write_text('{"event": "session_started"}\n')
    return d


@pytest.fixture
def shards(tmp_path: Path) -> tuple[Path, Path]:
    a = _output(tmp_path / "s0", [_rec("baseline_s1"), _rec("glare@gate_s1", passed=False)], shard=(0, 2))
    b = _output(tmp_path / "s1", [_rec("frame_drop@lock_s1")], shard=(1, 2))
    return a, b


def test_merge_gives_the_campaign_summary_object(
    shards: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "merged"
    assert main(["campaign", "merge", str(shards[1]), str(shards[0]), "--out", str(out), "--json"]) == 1
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads((out / "campaign.json").read_text())
    assert (printed["runs"], printed["passed"], printed["failed"]) == (3, 2, 1)
    assert [r["run_id"] for r in printed["results"]] == ["baseline_s1", "frame_drop@lock_s1", "glare@gate_s1"]
    assert set(summarise([], config="x")) <= set(printed)  # every key of the campaign summary
    assert (printed["tier"], printed["code_version"], printed["config_sha256"], printed["shard"]) == (
        "simulator", {"id": "git:aa"}, "c0", None)
    assert printed["merged_from"] == [str(shards[1]), str(shards[0])]
    (failing,) = printed["failing"]
    assert failing["replay"] == "hil campaign glare@gate --seed 1 --config sim.toml"
    log = out / "logs" / "glare@gate_s1.jsonl"
    assert failing["session_log"] == str(log)
    assert log.read_text() == '{"event": "session_started"}\n'
    assert "glare" in (out / "campaign.html").read_text()


def _pair(run_id: str, second: str, *, passed: bool = True) -> dict[str, Any]:
    rec = _rec(run_id, passed=passed)
    rec["second_kind"] = second
    rec["replay"] = rec["replay"].replace("hil campaign ", "hil campaign --pairs ")
    return rec


def test_merging_compound_fault_shards_keeps_the_pair_counts(tmp_path: Path) -> None:
    """``pairs`` (pair runs, overlapping, in recovery, passed) is counted over the merged runs, and
    the page is the compound-fault one."""
    ids = ["baseline_s1", "frame_drop+glare@lock_s1", "glare+tracker_timeout@gate_s1",
           "robot_disconnect+glare@compensate+recovery_s1"]
    matrix = matrix_identity(ids)
    a = _output(tmp_path / "s0", [_rec(ids[0]), _pair(ids[2], "tracker_timeout", passed=False)],
                shard=(0, 2), matrix=matrix)
    b = _output(tmp_path / "s1", [_pair(ids[1], "glare"), _pair(ids[3], "glare")], shard=(1, 2),
                matrix=matrix)
    for d, n in ((a, 1), (b, 2)):   # as run_pairs_campaign writes it
        summary = json.loads((d / "campaign.json").read_text())
        summary["pairs"] = {"runs": n, "overlapping": 1, "recovery": n - 1, "passed": n - 1 if d == a else n}
        (d / "campaign.json").write_text(json.dumps(summary))
    merged = merge_outputs([a, b], out_dir=tmp_path / "merged")
    assert merged["pairs"] == {"runs": 3, "overlapping": 2, "recovery": 1, "passed": 2}
    assert merged["failing"][0]["replay"].startswith("hil campaign --pairs glare+tracker_timeout@gate ")
    assert "Compound-fault campaign" in (tmp_path / "merged" / "campaign.html").read_text()


def test_merging_single_fault_shards_adds_no_pair_counts(shards: tuple[Path, Path], tmp_path: Path) -> None:
    assert "pairs" not in merge_outputs(list(shards), out_dir=tmp_path / "merged")


def test_merge_table_output(shards: tuple[Path, Path], tmp_path: Path,
                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["campaign", "merge", *map(str, shards), "--out", str(tmp_path / "m")]) == 1
    text = capsys.readouterr().out
    assert "3 runs: 2 passed, 1 failed; worst safe-state latency 100.0 ms" in text
    assert "FAIL glare@gate seed 1: no safe state" in text


@pytest.mark.parametrize(
    ("other", "message"),
    [
        ({"code": "git:bb"}, "code versions differ: {a} has git:aa, {b} has git:bb (--allow-mismatch merges "
                             "them anyway)"),
        ({"digest": "c1"}, "config digests differ: {a} has c0, {b} has c1 (--allow-mismatch merges "
                           "them anyway)"),
    ],
)
def test_merge_refuses_mismatched_outputs_unless_told(
    shards: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], other: dict[str, str],
    message: str,
) -> None:
    a = shards[0]
    b = _output(tmp_path / "other", [_rec("frame_drop@lock_s1")], shard=(1, 2), **other)
    assert main(["campaign", "merge", str(a), str(b), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["hil campaign: error: " + message.format(a=a, b=b)]
    assert not (tmp_path / "m").exists()
    assert main(["campaign", "merge", str(a), str(b), "--out", str(tmp_path / "m"), "--allow-mismatch"]) == 1


def test_merge_never_counts_a_run_twice(shards: tuple[Path, Path], tmp_path: Path) -> None:
    again = _output(tmp_path / "again", [_rec("frame_drop@lock_s1"), _rec("baseline_s1")], shard=None)
    with pytest.raises(MergeError, match=r"^outputs of different splits"):
        merge_outputs([shards[0], again], out_dir=tmp_path / "m")
    whole = _output(tmp_path / "whole", [_rec("baseline_s1")], shard=None)
    with pytest.raises(MergeError) as err:
        merge_outputs([whole, again], out_dir=tmp_path / "m", allow_mismatch=True)
    assert str(err.value) == (f"run baseline_s1 is in both {whole} and {again} (it would be counted twice)")


def test_merge_refuses_missing_or_repeated_shards(shards: tuple[Path, Path], tmp_path: Path) -> None:
    with pytest.raises(MergeError) as err:
        merge_outputs([shards[0]], out_dir=tmp_path / "m")
    assert str(err.value) == "shard(s) 1/2 missing (--allow-partial merges what is there)"
    partial = merge_outputs([shards[0]], out_dir=tmp_path / "m", allow_partial=True)
    assert partial["runs"] == 2
    copy = _output(tmp_path / "copy", [_rec("glare@gate_s1")], shard=(0, 2))
    with pytest.raises(MergeError) as err:
        merge_outputs([shards[0], copy], out_dir=tmp_path / "m2")
    assert str(err.value) == f"shard 0/2 given twice: {shards[0]} and {copy}"


def test_merge_refuses_other_tiers_matrices_and_non_outputs(shards: tuple[Path, Path],
                                                            tmp_path: Path) -> None:
    transport = _output(tmp_path / "t", [_rec("rtde_estop@lock_s1")], shard=(1, 2), tier="transport")
    with pytest.raises(MergeError, match=r"^tiers differ: .* has simulator, .* has transport$"):
        merge_outputs([shards[0], transport], out_dir=tmp_path / "m", allow_mismatch=True)
    other = _output(tmp_path / "o", [_rec("frame_drop@lock_s1")], shard=(1, 2),
                    matrix=matrix_identity(["baseline_s2"]))
    with pytest.raises(MergeError, match=r"^matrices \(scenarios x seeds\) differ: "):
        merge_outputs([shards[0], other], out_dir=tmp_path / "m")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(MergeError) as err:
        merge_outputs([empty], out_dir=tmp_path / "m")
    assert str(err.value) == f"{empty}: no campaign.json or transport.json (not one campaign output)"
