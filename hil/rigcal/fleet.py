"""Accuracy over many rigs (issue 43): each rig drawn within tolerances (:mod:`hil.rigcal.draw`),
run through the procedure with the CAD values, calibrated with ``hil rig-calibrate --auto``'s
path (:func:`hil.rigcal.runner.run_rig_calibration`) and run again calibrated; the distribution of
lock error across rigs, the refusals with their reasons, and the worst rig with its draw.

The rigs run on the campaign executors (:mod:`hil.campaign.executor`): ``local`` (this machine,
``workers`` rigs at a time, each in its own process) or ``dask`` (a scheduler, or a LocalCluster on
loopback). One rig is one :class:`~hil.campaign.task.RunTask` (tier ``simulator``, scenario
``rig``); on the worker :func:`execute_rig_task` checks the code version and config digest as a
campaign run does, then runs the rig in a child process (``python -m hil.rigcal.fleet TASK
RESULT``) bounded by the task's ``timeout_s`` (past it the child's process group is killed: a
*hang*, retried once by the executor like a campaign run).

Simulated setups only (the rig's errors are the simulator's): every run is on a ManualClock, so a
rig's figures are a function of (config, plan, tolerances, seed, code) and rerun exactly.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import sys
import tempfile
import threading
import traceback
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from hil.campaign.executor import DaskExecutor, Executor, ExecutorError, LocalExecutor
from hil.campaign.runner import RunResult
from hil.campaign.task import RunTask, TaskOutcome, finish_record, kill_running, run_child_module
from hil.campaign.version import code_version, config_digest
from hil.clock import ManualClock
from hil.config import build_devices, load_setup
from hil.config.build import clock_for
from hil.config.setup import SetupConfig
from hil.config.simulation import BreathingConfig
from hil.controller.assembly import (
    build_controller,
    session_header,
    stereo_calibration,
    with_perception_process,
    with_servo_process,
)
from hil.controller.operator_input import AutoOperator
from hil.controller.plan_file import ProcedurePlan, load_plan
from hil.errors import ConfigError, HilError
from hil.log import get_logger
from hil.rigcal.collect import auto_confirm
from hil.rigcal.draw import RigDraw, RigTolerances, apply_draw, draw_rig
from hil.rigcal.runner import run_rig_calibration
from hil.session.log import SessionLog

_log = get_logger(__name__)
#: The scenario name of a rig's task (records' ``scenario``).
RIG_SCENARIO = "rig"
#: Outcomes of a rig's record.
OUTCOME_CALIBRATED, OUTCOME_REFUSED = "calibrated", "refused"
#: structlog events
EV_RIG_DONE = "rig_done"
EV_RIG_REFUSED = "rig_refused"
#: Wall-time bound of one rig (calibration and two procedures), s.
DEFAULT_RIG_TIMEOUT_S = 900.0
#: Exit code of a rig process whose worker died.
EXIT_ORPHANED = 70
#: Simulated-time bound of one procedure run, s (a run that neither locks nor gives up).
MAX_PROCEDURE_S = 120.0



def check_simulated(setup: SetupConfig, config_path: Path) -> None:
    """Refuse a setup that is not wholly simulated on a manual clock: drawn rigs are simulated
    ones, and nothing here may move a real arm.

    Raises:
        ConfigError: a device is not simulated, or ``[simulation] real_time`` is set.
    """
    if not isinstance(clock_for(setup), ManualClock):
        raise ConfigError(str(config_path), ["drawn rigs run on a simulated setup only (every device's "
                                             "driver simulated, [simulation] real_time = false)"])


def rig_setup(base: SetupConfig, draw: RigDraw) -> SetupConfig:
    """``base`` with the drawn rig in its ``[simulation]`` (seed, rig errors, placements)."""
    return base.model_copy(update={"simulation": apply_draw(base.simulation, draw)})


def _procedure(config_path: Path, setup: SetupConfig, plan: ProcedurePlan, log_path: Path) -> dict[str, Any]:
    """One auto-confirmed procedure on ``setup`` (simulated, ManualClock); its figures. Blocking;
    the devices are closed on every path."""
    clock = ManualClock(1_000_000_000)
    devices = build_devices(setup, clock)
    stereo_calibration(setup, devices.camera)
    devices = with_perception_process(setup, with_servo_process(setup, devices, clock), clock)
    session = SessionLog(log_path, clock, {**session_header(config_path, setup, plan, devices, clock),
                                          "auto": True})
    final = "error"
    try:
        devices.open_all()
        ctl = build_controller(setup, plan, devices, clock=clock, session=session, operator=AutoOperator())
        s = ctl.run(MAX_PROCEDURE_S)
        final = s.final_state
    finally:
        devices.close_all()
        session.close(final_state=final)
    return {"final_state": s.final_state, "lock_error_mm": s.lock_error_mm,
            "lock_direction_error_deg": s.lock_direction_error_deg, "time_to_lock_s": s.time_to_lock_s}


def run_rig(config_path: Path, plan_path: Path, tolerances: RigTolerances, seed: int, work_dir: Path,
            breathing: dict[str, Any] | None = None) -> dict[str, Any]:
    """Rig ``seed``: draw it, run the procedure with the CAD values, calibrate it (``hil
    rig-calibrate --auto``'s path), run it calibrated. ``breathing``: ``[simulation.breathing]``
    keys set on the config first (the bench's 10 mm / 4 s). Blocking (~15-30 s on one core).

    Returns ``{"seed", "draw", "cad", "calibrated", "refused", "calibration"}``: ``cad`` and
    ``calibrated`` the runs' figures (``calibrated`` None when the calibration was refused),
    ``refused`` the refusal's one line (else None), ``calibration`` the calibration's distance from
    the simulator's truth.

    Raises:
        HilError: the config or plan cannot be read, the setup is not simulated (a calibration
            refusal is not raised).
    """
    base = load_setup(config_path)
    check_simulated(base, config_path)
    if breathing:
        b = BreathingConfig.model_validate({**base.simulation.breathing.model_dump(), **breathing})
        base = base.model_copy(update={"simulation": base.simulation.model_copy(update={"breathing": b})})
    plan = load_plan(plan_path)
    draw = draw_rig(seed, tolerances)
    setup = rig_setup(base, draw)
    out: dict[str, Any] = {"seed": seed, "draw": draw.model_dump(mode="json"), "calibrated": None,
                           "refused": None, "calibration": None}
    out["cad"] = _procedure(config_path, setup, plan, work_dir / f"rig_{seed}_cad.jsonl")
    rig_path = work_dir / f"rig_{seed}.json"
    clock = clock_for(setup)   # as hil rig-calibrate
    try:
        cal = run_rig_calibration(setup, config_path, build_devices(setup, clock), clock, auto_confirm,
                                  out_path=rig_path).summary
    except HilError as exc:
        out["refused"] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
        _log.info(EV_RIG_REFUSED, seed=seed, reason=out["refused"])
        return out
    out["calibration"] = {"layout_mm_rms": cal.get("truth_layout_error_mm_rms"),
                          "time_offset_error_ms": cal.get("truth_time_offset_error_ms")}
    with_rig = setup.calibration.model_copy(update={"rig": rig_path})
    calibrated = setup.model_copy(update={"calibration": with_rig})
    out["calibrated"] = _procedure(config_path, calibrated, plan, work_dir / f"rig_{seed}_calibrated.jsonl")
    _log.info(EV_RIG_DONE, seed=seed, cad_mm=out["cad"]["lock_error_mm"],
              calibrated_mm=out["calibrated"]["lock_error_mm"])
    return out


def rig_task(config_path: Path, plan_path: Path, tolerances: RigTolerances, seed: int, *, replay: str,
             timeout_s: float = DEFAULT_RIG_TIMEOUT_S, breathing: dict[str, Any] | None = None,
             check_version: bool = True) -> RunTask:
    """The task of rig ``seed`` for an executor (``replay``: the command that reruns it alone)."""
    paths = (str(config_path), str(plan_path))
    spec = {"config": str(config_path), "plan": str(plan_path), "seed": seed,
            "tolerances": tolerances.model_dump(mode="json"), "breathing": breathing or {}}
    return RunTask(tier="simulator", run_id=f"rig-{seed:04d}", spec=spec,
                   inputs={"scenario": RIG_SCENARIO, "seed": seed, "kind": None, "state": None},
                   replay=replay, timeout_s=timeout_s, code_version=str(code_version()["id"]),
                   config_sha256=config_digest(paths), paths=paths, check_version=check_version)


def _record(task: RunTask, outcome: str, reasons: list[str], **fields: Any) -> dict[str, Any]:
    r = RunResult(task.run_id, RIG_SCENARIO, None, None, int(task.spec["seed"]),
                  passed=outcome == OUTCOME_CALIBRATED, outcome=outcome, reasons=reasons).to_dict()
    return {**r, **fields}


def _mismatch(task: RunTask, worker_version: str) -> list[str]:
    """Why this worker must not run ``task`` (another code version or config), as a campaign's."""
    if not task.check_version:
        return []
    host = socket.gethostname()
    wrong = []
    if worker_version != task.code_version:
        wrong.append(f"worker {host} runs code {worker_version}, the bench {task.code_version}")
    try:
        if config_digest(task.paths) != task.config_sha256:
            wrong.append(f"worker {host} sees a different config: {', '.join(task.paths)}")
    except OSError as exc:
        wrong.append(f"worker {host} cannot read the config: {exc}")
    return wrong


def execute_rig_task(task: RunTask) -> TaskOutcome:
    """Run one rig's task on this worker (module doc). Blocking, at most ``task.timeout_s`` of wall
    time. Never raises for a rig's problem (its record says it)."""
    host, version = socket.gethostname(), str(code_version()["id"])
    wrong = _mismatch(task, version)
    if wrong:
        rec = _record(task, "error", wrong)
        return TaskOutcome(finish_record(task, rec, worker_version=version, host=host))
    tmp = Path(tempfile.mkdtemp(prefix="hil-rig-"))
    try:
        outcome = _run_child(task, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    outcome.record = finish_record(task, outcome.record, worker_version=version, host=host)
    return outcome


def _run_child(task: RunTask, tmp: Path) -> TaskOutcome:
    payload = {"run_id": task.run_id, "spec": task.spec}
    run = run_child_module("hil.rigcal.fleet", payload, tmp, task.timeout_s)
    if run.result is not None:
        return TaskOutcome(run.result)
    if run.hung:
        hang = [f"rig did not finish within {task.timeout_s:g} s (hang)"]
        rec = _record(task, "hang", hang, wall_s=run.wall_s)
        return TaskOutcome(rec, retryable=True)
    died = [f"rig process died (exit code {run.returncode})"]
    return TaskOutcome(_record(task, "crashed", died, error=run.stderr_tail), retryable=True)


def kill_running_rigs() -> int:
    """Kill every rig process this process started that still runs; returns how many (the
    campaign's set: :func:`hil.campaign.task.kill_running`)."""
    return kill_running()


class RigLocalExecutor(LocalExecutor):
    """The campaign's local executor running rig tasks (``workers`` rig processes at a time)."""

    def _submit(self, task: RunTask, attempt: int) -> Any:
        return self._pool.submit(execute_rig_task, task)

    def close(self) -> None:
        """Cancel the rigs not started, kill the running ones, wait for the threads."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        kill_running_rigs()
        super().close()


class RigDaskExecutor(DaskExecutor):
    """The campaign's Dask executor running rig tasks."""

    def _submit(self, task: RunTask, attempt: int) -> Any:
        assert self._client is not None
        key = f"hil-rig-{self._token}-{task.run_id}-a{attempt}"
        fut = self._client.submit(execute_rig_task, task, key=key, retries=0)
        if self._done is None:
            self._done = self._distributed.as_completed(loop=self._client.loop)
        self._done.add(fut)
        return fut


def open_rig_executor(kind: str, *, workers: int, scheduler: str | None = None) -> Executor:
    """``--executor kind`` (``local`` or ``dask``) for rig tasks.

    Raises:
        ExecutorError: ``--scheduler`` without dask; ``distributed`` missing; no scheduler answered.
    """
    if kind == "local":
        if scheduler is not None:
            raise ExecutorError("--scheduler applies to --executor dask only")
        return RigLocalExecutor(workers)
    if kind == "dask":
        return RigDaskExecutor(scheduler=scheduler, workers=workers)
    raise ExecutorError(f"--executor {kind!r}: choose local or dask")


def _exit_when_orphaned(parent: int) -> None:
    """Exit this rig process when the worker that started it is gone (its parent changed)."""
    def watch() -> None:
        while not threading.Event().wait(1.0):
            if os.getppid() != parent:
                os._exit(EXIT_ORPHANED)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _child_main(argv: list[str]) -> int:
    """``python -m hil.rigcal.fleet TASK_JSON RESULT_JSON``: run one rig, write its record (a
    crash of the rig is written as a ``crashed`` record with its traceback)."""
    from hil.log import configure_logging

    _exit_when_orphaned(os.getppid())
    configure_logging(level="error")
    task_path, result_path = argv
    payload = json.loads(Path(task_path).read_text())
    spec, run_id = payload["spec"], payload["run_id"]
    base = RunResult(run_id, RIG_SCENARIO, None, None, int(spec["seed"]), passed=False).to_dict()
    try:
        with tempfile.TemporaryDirectory(prefix="hil-rig-run-") as work:
            tolerances = RigTolerances.model_validate(spec["tolerances"])
            rig = run_rig(Path(spec["config"]), Path(spec["plan"]), tolerances, int(spec["seed"]), Path(work),
                          spec.get("breathing") or None)
        outcome = OUTCOME_REFUSED if rig["refused"] else OUTCOME_CALIBRATED
        rec = {**base, "passed": outcome == OUTCOME_CALIBRATED, "outcome": outcome,
               "reasons": [rig["refused"]] if rig["refused"] else [], "rig": rig}
    except BaseException as exc:  # noqa: BLE001 - a crash of one rig is a finding of the bench, not ours
        rec = {**base, "outcome": "crashed", "reasons": [f"rig crashed: {type(exc).__name__}: {exc}"[:500]],
               "error": "".join(traceback.format_exception(exc))[-4000:]}
    Path(result_path).write_text(json.dumps(rec, default=str))
    return 0


def _pct(xs: list[float], q: float) -> float | None:
    return float(np.percentile(xs, q)) if xs else None


def _lock(rec: dict[str, Any], column: str) -> float | None:
    run = (rec.get("rig") or {}).get(column)
    return None if run is None or run.get("lock_error_mm") is None else float(run["lock_error_mm"])


def summarize(records: list[dict[str, Any]], rerun: dict[int, str]) -> dict[str, Any]:
    """The distribution over rigs from the tasks' records (``rerun``: seed -> the command that
    reruns that rig alone). Lock-error percentiles are over the rigs whose run locked; ``refused``
    counts calibrations refused, ``crashed`` rigs that gave no figures (crash, hang, wrong
    worker), each with its reasons counted; ``done_*`` the runs that ended in ``done``."""
    cal = {int(r["seed"]): x for r in records if (x := _lock(r, "calibrated")) is not None}
    cad = {int(r["seed"]): x for r in records if (x := _lock(r, "cad")) is not None}
    refused = [r for r in records if r.get("outcome") == OUTCOME_REFUSED]
    broken = [r for r in records if r.get("outcome") not in (OUTCOME_REFUSED, OUTCOME_CALIBRATED)]
    ran = [r for r in records if r.get("rig")]
    out: dict[str, Any] = {"rigs": len(records)}
    for name, xs in (("calibrated", list(cal.values())), ("cad", list(cad.values()))):
        for q in (50, 95, 99):
            out[f"lock_err_mm_p{q}_{name}"] = _pct(xs, q)
        out[f"lock_err_mm_max_{name}"] = max(xs) if xs else None
        out[f"locked_{name}"] = len(xs)
    for name in ("cad", "calibrated"):   # locked, then retracted (e.g. the drift alarm) counts here
        out[f"done_{name}"] = sum(1 for r in ran if (r["rig"].get(name) or {}).get("final_state") == "done")
    out["not_locked_cad"] = sum(1 for r in ran if _lock(r, "cad") is None)
    out["not_locked_calibrated"] = sum(1 for r in ran
                                       if r["rig"].get("calibrated") and _lock(r, "calibrated") is None)
    out["refused"] = len(refused)
    out["refused_reasons"] = dict(Counter(str(r["reasons"][0]) for r in refused))
    out["crashed"] = len(broken)
    out["crashed_reasons"] = dict(Counter("; ".join(r.get("reasons") or [str(r.get("outcome"))])
                                          for r in broken))
    layout = [float(c["layout_mm_rms"]) for r in ran if (c := r["rig"].get("calibration"))
              and c.get("layout_mm_rms") is not None]
    out["calibration_layout_error_mm_rms_p95"] = _pct(layout, 95)
    out["worst"] = _worst(records, cal or cad, "calibrated" if cal else "cad", rerun)
    out["per_rig"] = [_row(r) for r in records]
    return out


def _worst(records: list[dict[str, Any]], errors: dict[int, float], column: str,
           rerun: dict[int, str]) -> dict[str, Any] | None:
    if not errors:
        return None
    seed = max(errors, key=lambda k: errors[k])
    rec = next(r for r in records if int(r["seed"]) == seed)
    return {"seed": seed, "by": f"lock_err_mm_{column}", "lock_err_mm_calibrated": _lock(rec, "calibrated"),
            "lock_err_mm_cad": _lock(rec, "cad"), "draw": rec["rig"]["draw"], "rerun": rerun.get(seed)}


def _row(rec: dict[str, Any]) -> dict[str, Any]:
    rig = rec.get("rig") or {}
    return {"seed": int(rec["seed"]), "outcome": rec.get("outcome"), "reasons": rec.get("reasons", []),
            "lock_err_mm_cad": _lock(rec, "cad"), "lock_err_mm_calibrated": _lock(rec, "calibrated"),
            "final_state_cad": (rig.get("cad") or {}).get("final_state"),
            "final_state_calibrated": (rig.get("calibrated") or {}).get("final_state"),
            "calibration": rig.get("calibration"), "host": rec.get("host"), "attempts": rec.get("attempts")}


if __name__ == "__main__":
    sys.exit(_child_main(sys.argv[1:]))
