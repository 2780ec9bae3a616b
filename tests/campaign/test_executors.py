"""The executors' contract without simulating: one record per run, in order; a run whose process
died or hung, or whose Dask worker was killed, is run once more, then recorded as an error -
never lost, never counted twice; a worker on other code or config refuses the run; an
unreachable scheduler and a missing ``distributed`` are one-line errors.

The Dask executor here is a 2-worker LocalCluster on 127.0.0.1 (processes, no dashboard), one
per module, closed by its fixture. Runs are replaced by light hooks (tests/campaign/executor_hooks.py).
"""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from hil.campaign import executor as executor_mod
from hil.campaign.campaign import SimTaskFactory
from hil.campaign.executor import DaskExecutor, Executor, ExecutorError, LocalExecutor
from hil.campaign.runner import RunSpec
from hil.campaign.task import RunTask
from hil.campaign.version import code_version
from hil.cli import main
from hil.config import default_setup_path

HOOKS = "tests.campaign.executor_hooks"


@pytest.fixture(scope="module")
def dask_executor() -> Iterator[DaskExecutor]:
    ex = DaskExecutor(workers=2)
    try:
        yield ex
    finally:
        ex.close()


@pytest.fixture
def local_executor() -> Iterator[LocalExecutor]:
    ex = LocalExecutor(2)
    try:
        yield ex
    finally:
        ex.close()


@pytest.fixture(params=["local", "dask"])
def executor(request: pytest.FixtureRequest) -> Executor:
    ex: Executor = request.getfixturevalue(f"{request.param}_executor")
    return ex


def _task(run_id: str, hook: str, *, timeout_s: float = 60.0) -> RunTask:
    factory = SimTaskFactory(default_setup_path(), None, timeout_s, False, True, hook)
    return factory.task(RunSpec(run_id, str(default_setup_path()), None, 1))


def test_dead_and_hung_runs_are_run_once_more_then_recorded(executor: Executor, tmp_path: Path) -> None:
    tasks = [
        _task("ok", f"{HOOKS}:passes"),
        _task("dies_once", f"{HOOKS}:dies_once:{tmp_path}"),
        _task("dies_always", f"{HOOKS}:dies_always"),
        _task("hangs", f"{HOOKS}:hangs", timeout_s=3.0),
    ]
    lines: list[str] = []
    records = executor.run(tasks, progress=lines.append)
    got = [(r["run_id"], r["passed"], r["outcome"], r["attempts"], r["reasons"]) for r in records]
    assert got == [
        ("ok", True, "baseline", 1, []),
        ("dies_once", True, "baseline", 2, []),
        ("dies_always", False, "crashed", 2, ["after 2 attempts: run process died (exit code -9)"]),
        ("hangs", False, "hang", 2, ["after 2 attempts: run did not finish within 3 s (hang)"]),
    ]
    retried = sorted(line.split(":")[0] for line in lines if "running it once more" in line)
    assert retried == ["dies_always", "dies_once", "hangs"]
    finished = sorted(line.split(":")[0] for line in lines if "running it once more" not in line)
    assert finished == ["dies_always", "dies_once", "hangs", "ok"]  # one final line per run


def test_every_record_is_self_contained(local_executor: LocalExecutor) -> None:
    (rec,) = local_executor.run([_task("ok", f"{HOOKS}:passes")])
    assert rec["tier"] == "simulator"
    assert rec["replay"] == f"hil run {default_setup_path().resolve()} --seed 1 --auto"
    assert rec["inputs"]["code_version"] == rec["code_version"] == code_version()["id"]
    assert rec["inputs"]["config_sha256"] == _task("x", "").config_sha256
    inputs = {"scenario", "seed", "kind", "state", "start_s", "duration_s", "config", "plan"}
    assert inputs <= set(rec["inputs"])
    assert rec["host"] == socket.gethostname()


def test_a_dask_worker_killed_once_is_replaced_and_the_run_done_once(
    dask_executor: DaskExecutor, tmp_path: Path
) -> None:
    lines: list[str] = []
    records = dask_executor.run([_task("kills_worker", f"{HOOKS}:kills_worker_once:{tmp_path}"),
                                 _task("ok", f"{HOOKS}:passes")], progress=lines.append)
    assert [(r["run_id"], r["passed"], r["attempts"]) for r in records] == [
        ("kills_worker", True, 2), ("ok", True, 1)]
    (retry,) = [line for line in lines if "running it once more" in line]
    assert retry.startswith("kills_worker: crashed on attempt 1 (worker lost: KilledWorker")


def test_a_worker_on_other_code_or_config_refuses_the_run(local_executor: LocalExecutor) -> None:
    base = _task("other_code", f"{HOOKS}:passes")
    other_code = replace(base, code_version="git:" + "0" * 40)
    other_config = replace(base, run_id="other_config", config_sha256="f" * 64)
    recs = local_executor.run([other_code, other_config])
    assert [(r["outcome"], r["attempts"]) for r in recs] == [("error", 1), ("error", 1)]
    here = code_version()["id"]
    assert recs[0]["reasons"][0].startswith(f"worker {socket.gethostname()} runs code {here}, "
                                            f"the campaign git:{'0' * 40}")
    assert "sees a different config" in recs[1]["reasons"][0]
    (allowed,) = local_executor.run([replace(other_code, check_version=False)])
    assert allowed["passed"] is True


def _free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_two_local_clusters_on_one_machine_do_not_collide() -> None:
    """The LocalCluster's scheduler HTTP server takes a free loopback port: with 8787 (distributed's
    default) taken by another campaign it starts without a warning (the suite makes warnings
    errors; a campaign beside another used to fail to start here)."""
    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
        holder.listen()
    except OSError:
        pass   # someone already holds it: the same collision
    try:
        ex = DaskExecutor(workers=1)
        try:
            cluster = ex._cluster
            assert cluster is not None
            (http_host, http_port), *_ = [sock.getsockname()
                                          for sock in cluster.scheduler.http_server._sockets.values()]
            assert http_host == "127.0.0.1"
            assert http_port != 8787
        finally:
            ex.close()
    finally:
        holder.close()


def test_an_unreachable_scheduler_is_an_error_within_the_bound() -> None:
    address = f"tcp://127.0.0.1:{_free_loopback_port()}"
    expected = rf"^--scheduler {address}: no Dask scheduler answered within 2 s"
    with pytest.raises(ExecutorError, match=expected):
        DaskExecutor(scheduler=address, connect_timeout_s=2.0)


def test_cli_unreachable_scheduler_one_line_exit_2(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    monkeypatch.setattr(executor_mod, "SCHEDULER_CONNECT_TIMEOUT_S", 2.0)
    address = f"tcp://127.0.0.1:{_free_loopback_port()}"
    code = main(["campaign", "frame_drop@lock", "--executor", "dask", "--scheduler", address,
                 "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1
    assert err[0].startswith(f"hil campaign: error: --scheduler {address}: "
                             "no Dask scheduler answered within 2 s")
    assert not (tmp_path / "out").exists()


def test_without_distributed_the_dask_executor_names_the_extra(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` raises ImportError
    assert main(["campaign", "frame_drop@lock", "--executor", "dask", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("hil campaign: error: --executor dask needs the 'campaign-dask' extra "
                             "(Dask's distributed): pip install 'needle-guide-hil[campaign-dask]'")


def test_scheduler_needs_the_dask_executor(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["campaign", "--scheduler", "tcp://127.0.0.1:8786"]) == 2
    assert capsys.readouterr().err.strip() == ("hil campaign: error: --scheduler: applies to --executor "
                                               "dask only")


def _git(repo: Path, *args: str) -> None:
    subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@example.invalid",
                    *args], check=True, capture_output=True, timeout=30)


def test_code_version_is_the_commit_and_whether_the_tree_is_dirty(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    (repo / "a.py").write_text("x = 1\n")
    _git(repo, "add", "a.py")
    _git(repo, "commit", "-q", "-m", "one")
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], check=True, capture_output=True,
                          text=True, timeout=30).stdout.strip()
    clean = code_version(repo)
    assert (clean["id"], clean["source"], clean["commit"], clean["dirty"], clean["diff_sha256"]) == (
        f"git:{head}", "git", head, False, None)
    (repo / "untracked.txt").write_text("not counted\n")
    assert code_version(repo) == clean  # untracked files do not count
    (repo / "a.py").write_text("x = 2\n")
    dirty = code_version(repo)
    assert dirty["dirty"] is True
    assert dirty["id"] == f"git:{head}+dirty.{dirty['diff_sha256'][:12]}"


def test_code_version_without_git_is_the_package_version(tmp_path: Path) -> None:
    from hil import __version__

    assert code_version(tmp_path) == {"id": f"package:{__version__}", "source": "package",
                                      "package": __version__}


def test_a_missing_plan_is_one_line_exit_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    plan = tmp_path / "none.json"
    assert main(["campaign", "frame_drop@lock", "--plan", str(plan), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    expected = f"hil campaign: error: {plan}: no such file (--plan)"
    assert [line for line in err if "error" in line] == [expected]
    assert not (tmp_path / "o" / "campaign.json").exists()
