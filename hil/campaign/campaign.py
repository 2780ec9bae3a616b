"""Plan and run a campaign: baselines per seed, then every selected scenario per seed, on an
executor (:mod:`hil.campaign.executor`), optionally one shard of the matrix
(:mod:`hil.campaign.shard`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from hil.errors import InputFileError

from .executor import Executor, LocalExecutor, Progress
from .outputs import LogSink, write_summary
from .report import summarise
from .runner import RunSpec
from .scenarios import Scenario, place_fault
from .shard import Shard, matrix_identity
from .task import RunTask, finish_record
from .version import code_version, config_digest

#: Wall-time bound of one run (s): a run beyond it is killed and counted as a hang.
RUN_TIMEOUT_S = 300.0


def _plan_path(config: Path, plan: str | None) -> Path:
    return Path(plan).resolve() if plan else config.parent / "plans" / f"{config.stem}_plan.json"


def replay_command(scenario: str, seed: int, config: Path, plan: str | None) -> str:
    """The command that runs this one run again (the same on every machine with this checkout)."""
    extra = f" --plan {plan}" if plan else ""
    if scenario == "baseline":
        return f"hil run {config} --seed {seed} --auto"
    pairs = " --pairs" if "+" in scenario else ""  # a compound-fault scenario (A+B@S)
    return f"hil campaign{pairs} {scenario} --seed {seed} --config {config}{extra}"


def matrix_ids(scenarios: list[Scenario], seeds: list[int]) -> list[str]:
    """The matrix's run ids in its fixed order: per seed, the baseline then every scenario."""
    return [rid for s in seeds for rid in (f"baseline_s{s}", *(f"{sc.name}_s{s}" for sc in scenarios))]


class SimTaskFactory:
    """What every task of one simulator campaign shares."""

    def __init__(self, config: Path, plan: str | None, timeout_s: float, keep_logs: bool,
                 check_version: bool, hook: str | None) -> None:
        self.config, self.plan = config, plan
        self.paths = (str(config), str(_plan_path(config, plan)))
        for path, option in zip(self.paths, ("--config", "--plan"), strict=True):
            if not Path(path).is_file():
                raise InputFileError(path, f"no such file ({option})")
        self.digest = config_digest(self.paths)
        self.version = code_version()
        self.timeout_s, self.keep_logs = timeout_s, keep_logs
        self.check_version, self.hook = check_version, hook

    def task(self, spec: RunSpec) -> RunTask:
        fields = {k: v for k, v in spec.__dict__.items() if k != "log_dir"}
        inputs = {"tier": "simulator", "scenario": spec.scenario, "seed": spec.seed, "kind": spec.kind,
                  "state": spec.state, "start_s": spec.start_s, "duration_s": spec.duration_s,
                  "max_duration_s": spec.max_duration_s, "config": str(self.config), "plan": self.plan,
                  "config_sha256": self.digest, "code_version": self.version["id"]}
        if spec.second_kind is not None:
            inputs.update(second_kind=spec.second_kind, second_start_s=spec.second_start_s,
                          second_duration_s=spec.second_duration_s, recovery=spec.recovery,
                          second_state=spec.second_state)
        return RunTask("simulator", spec.run_id, fields, inputs,
                       replay_command(spec.scenario, spec.seed, self.config, self.plan), self.timeout_s,
                       str(self.version["id"]), self.digest, self.paths, keep_logs=self.keep_logs,
                       check_version=self.check_version, hook=self.hook)


def run_campaign(
    scenarios: list[Scenario],
    seeds: list[int],
    *,
    config: Path,
    plan: str | None,
    out_dir: Path,
    jobs: int = 1,
    executor: Executor | None = None,
    shard: Shard | None = None,
    keep_logs: bool = False,
    timeout_s: float = RUN_TIMEOUT_S,
    max_duration_s: float = 90.0,
    check_version: bool = True,
    hook: str | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run the matrix (or the ``shard`` of it) on ``executor`` (default: a local one of ``jobs``
    processes); write ``campaign.json``, ``campaign.html`` and the failing runs' logs in
    ``out_dir``; return the summary (:func:`hil.campaign.report.summarise` plus ``tier``,
    ``code_version``, ``config_sha256``, ``executor``, ``shard``, ``matrix``, ``wall_s``).

    A shard runs the baselines of the seeds its scenarios need (fault placement depends on them)
    but reports only the baselines it owns. Blocking (minutes for the full matrix).
    """
    if executor is None:
        with LocalExecutor(jobs) as local:
            return run_campaign(scenarios, seeds, config=config, plan=plan, out_dir=out_dir, executor=local,
                                shard=shard, keep_logs=keep_logs, timeout_s=timeout_s,
                                max_duration_s=max_duration_s, check_version=check_version, hook=hook,
                                progress=progress)
    t_wall = time.perf_counter()
    say = progress or (lambda _m: None)
    config = config.resolve()
    plan = str(Path(plan).resolve()) if plan else None
    ctx = SimTaskFactory(config, plan, timeout_s, keep_logs, check_version, hook)
    ids = matrix_ids(scenarios, seeds)
    owned = {rid for k, rid in enumerate(ids) if shard is None or shard.owns(k)}
    need = [s for s in seeds
            if f"baseline_s{s}" in owned or any(f"{sc.name}_s{s}" in owned for sc in scenarios)]
    sink = LogSink(out_dir)
    where = executor.description
    base_tasks = [ctx.task(RunSpec(f"baseline_s{s}", str(config), plan, s, max_duration_s=max_duration_s))
                  for s in need]
    say(f"baselines: {len(base_tasks)} run(s) on {where['kind']} ({where['workers']} worker(s))")
    baselines = executor.run(base_tasks, progress=say, on_files=sink)
    specs: list[RunSpec] = []
    skipped: list[dict[str, Any]] = []
    for seed, base in zip(need, baselines, strict=True):
        windows = base.get("state_windows_s") or {}
        for sc in scenarios:
            run_id = f"{sc.name}_s{seed}"
            if run_id not in owned:
                continue
            w = windows.get(sc.state)
            start = place_fault((w[0], w[1]) if w else None, sc.profile.duration_s)
            spec = RunSpec(run_id, str(config), plan, seed, kind=sc.kind.value, state=sc.state,
                           start_s=start, duration_s=sc.profile.duration_s, max_duration_s=max_duration_s)
            if start is None:
                t = ctx.task(spec)
                rec = {"run_id": run_id, "scenario": sc.name, "kind": sc.kind.value, "state": sc.state,
                       "seed": seed, "passed": False, "outcome": "not_reached",
                       "reasons": [f"baseline of seed {seed} never reached {sc.state}"]}
                skipped.append(finish_record(t, rec))
                continue
            specs.append(spec)
    say(f"scenarios: {len(specs)} run(s) on {where['kind']} ({where['workers']} worker(s))")
    results = executor.run([ctx.task(s) for s in specs], progress=say, on_files=sink)
    everything = [*(b for b in baselines if b["run_id"] in owned), *results, *skipped]
    everything.sort(key=lambda r: ids.index(r["run_id"]))
    sink.attach(everything)
    summary = summarise(everything, config=str(config))
    summary.update(tier="simulator", code_version=ctx.version, config_sha256=ctx.digest, executor=where,
                   shard=None if shard is None else shard.to_dict(), matrix=matrix_identity(ids),
                   wall_s=round(time.perf_counter() - t_wall, 3))
    write_summary(summary, out_dir)
    return summary
