"""Plan and run a compound-fault campaign (``hil campaign --pairs``, :mod:`hil.campaign.pairs`):
per seed the baseline, the single-fault runs the recovery scenarios are placed from, then every
selected pair scenario, on an executor, optionally one shard of the matrix.

The matrix's fixed order, per seed: ``baseline_s<seed>``, the single-fault runs ``A@S_s<seed>``
(one per first kind and state of the selected recovery scenarios), then the pair scenarios
``<name>_s<seed>``. A shard runs the baselines and single-fault runs its scenarios need (placement
depends on them) but reports only those it owns.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .campaign import RUN_TIMEOUT_S, SimTaskFactory
from .executor import Executor, LocalExecutor, Progress
from .outputs import LogSink, write_summary
from .pairs import RECOVERY_SUFFIX, PairScenario, place_in_recovery, place_second
from .report import summarise
from .runner import RunSpec
from .scenarios import PROFILES, Scenario, place_fault
from .shard import Shard, matrix_identity
from .task import finish_record


def single_runs(scenarios: list[PairScenario]) -> list[Scenario]:
    """The single-fault runs the recovery scenarios among ``scenarios`` are placed from (first
    kind x state), in order of first use."""
    out: list[Scenario] = []
    for sc in scenarios:
        single = Scenario(sc.first, sc.state)
        if sc.recovery and single not in out:
            out.append(single)
    return out


def pairs_matrix_ids(scenarios: list[PairScenario], seeds: list[int]) -> list[str]:
    """The matrix's run ids in its fixed order (module doc)."""
    singles = single_runs(scenarios)
    return [rid for s in seeds for rid in (f"baseline_s{s}", *(f"{x.name}_s{s}" for x in singles),
                                           *(f"{sc.name}_s{s}" for sc in scenarios))]


def pair_spec(sc: PairScenario, seed: int, windows: dict[str, Any], single: dict[str, Any] | None,
              config: str, plan: str | None, max_duration_s: float) -> RunSpec | str:
    """The run of ``sc`` for ``seed``: the first fault placed in the baseline's window of the
    state (``windows``: the baseline's ``state_windows_s``), the second after it (overlapping) or
    in the recovery window of ``single`` (the result of the single-fault run ``first@state``).
    Returns why it cannot be placed instead (a string) when the baseline never reached the state
    or the single-fault run never recovered."""
    w = windows.get(sc.state)
    start = place_fault((w[0], w[1]) if w else None, sc.profile.duration_s)
    if start is None:
        return f"baseline of seed {seed} never reached {sc.state}"
    if sc.recovery:
        rw = (single or {}).get("recovery_window_s")
        second = place_in_recovery((float(rw[0]), float(rw[1]), str(rw[2])) if rw else None)
        if second is None or rw is None:
            return (f"the single-fault run {sc.first.value}@{sc.state} of seed {seed} never recovered "
                    f"(outcome {(single or {}).get('outcome')}): no recovery to place the second fault in")
        second_state = str(rw[2])
    else:
        second, second_state = place_second(start), sc.state
    return RunSpec(f"{sc.name}_s{seed}", config, plan, seed, kind=sc.first.value, state=sc.state,
                   start_s=start, duration_s=sc.profile.duration_s, max_duration_s=max_duration_s,
                   second_kind=sc.second.value, second_start_s=second,
                   second_duration_s=PROFILES[sc.second].duration_s, recovery=sc.recovery,
                   second_state=second_state)


def run_pairs_campaign(
    scenarios: list[PairScenario],
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
    """Run the pairs matrix (or the ``shard`` of it) on ``executor`` (default: a local one of
    ``jobs`` processes); write ``campaign.json``, ``campaign.html`` and the failing runs' logs in
    ``out_dir``; return the summary (the single-fault campaign's, plus ``pairs``: the counts of
    pair scenarios run, overlapping and in recovery). Blocking (an hour for the whole matrix on
    2 cores)."""
    if executor is None:
        with LocalExecutor(jobs) as local:
            return run_pairs_campaign(scenarios, seeds, config=config, plan=plan, out_dir=out_dir,
                                      executor=local, shard=shard, keep_logs=keep_logs, timeout_s=timeout_s,
                                      max_duration_s=max_duration_s, check_version=check_version, hook=hook,
                                      progress=progress)
    t_wall = time.perf_counter()
    say = progress or (lambda _m: None)
    config = config.resolve()
    plan = str(Path(plan).resolve()) if plan else None
    ctx = SimTaskFactory(config, plan, timeout_s, keep_logs, check_version, hook)
    ids = pairs_matrix_ids(scenarios, seeds)
    owned, mine, need_singles, need = _selection(scenarios, seeds, ids, shard)
    sink = LogSink(out_dir)
    where = executor.description
    say(f"baselines: {len(need)} run(s) on {where['kind']} ({where['workers']} worker(s))")
    base_specs = [RunSpec(f"baseline_s{s}", str(config), plan, s, max_duration_s=max_duration_s)
                  for s in need]
    baselines = executor.run([ctx.task(sp) for sp in base_specs], progress=say, on_files=sink)
    windows = {s: b.get("state_windows_s") or {} for s, b in zip(need, baselines, strict=True)}
    skipped: list[dict[str, Any]] = []

    def skip(spec: RunSpec, why: str) -> None:
        rec = {"run_id": spec.run_id, "scenario": spec.scenario, "kind": spec.kind, "state": spec.state,
               "second_kind": spec.second_kind, "seed": spec.seed, "passed": False,
               "outcome": "not_reached", "reasons": [why]}
        skipped.append(finish_record(ctx.task(spec), rec))

    single_specs = _single_specs(need, need_singles, windows, str(config), plan, max_duration_s, skip)
    say(f"single-fault runs for placement in recovery: {len(single_specs)} run(s)")
    single_results = executor.run([ctx.task(sp) for sp in single_specs], progress=say, on_files=sink)
    by_single = {r["run_id"]: r for r in single_results}
    specs: list[RunSpec] = []
    for s in need:
        for sc in mine[s]:
            made = pair_spec(sc, s, windows[s], by_single.get(f"{sc.first.value}@{sc.state}_s{s}"),
                             str(config), plan, max_duration_s)
            if isinstance(made, str):
                skip(RunSpec(f"{sc.name}_s{s}", str(config), plan, s, kind=sc.first.value, state=sc.state,
                             second_kind=sc.second.value, recovery=sc.recovery), made)
            else:
                specs.append(made)
    say(f"pair scenarios: {len(specs)} run(s) on {where['kind']} ({where['workers']} worker(s))")
    results = executor.run([ctx.task(sp) for sp in specs], progress=say, on_files=sink)
    everything = [r for r in (*baselines, *single_results) if r["run_id"] in owned] + [*results, *skipped]
    everything.sort(key=lambda r: ids.index(r["run_id"]))
    sink.attach(everything)
    summary = summarise(everything, config=str(config))
    summary.update(tier="simulator", code_version=ctx.version, config_sha256=ctx.digest, executor=where,
                   shard=None if shard is None else shard.to_dict(), matrix=matrix_identity(ids),
                   pairs=pair_counts(everything), wall_s=round(time.perf_counter() - t_wall, 3))
    write_summary(summary, out_dir)
    return summary



def _selection(scenarios: list[PairScenario], seeds: list[int], ids: list[str], shard: Shard | None
               ) -> tuple[set[str], dict[int, list[PairScenario]], dict[int, list[Scenario]], list[int]]:
    """What this shard runs: the run ids it owns, its pair scenarios per seed, the single-fault
    runs each seed needs (owned, or placing an owned recovery scenario), the seeds that need a
    baseline."""
    owned = {rid for k, rid in enumerate(ids) if shard is None or shard.owns(k)}
    singles = single_runs(scenarios)
    mine = {s: [sc for sc in scenarios if f"{sc.name}_s{s}" in owned] for s in seeds}
    need_singles = {s: [x for x in singles if f"{x.name}_s{s}" in owned
                        or any(sc.recovery and sc.first is x.kind and sc.state == x.state for sc in mine[s])]
                    for s in seeds}
    need = [s for s in seeds if f"baseline_s{s}" in owned or mine[s] or need_singles[s]]
    return owned, mine, need_singles, need

def _single_specs(need: list[int], need_singles: dict[int, list[Scenario]],
                  windows: dict[int, dict[str, Any]], config: str, plan: str | None, max_duration_s: float,
                  skip: Callable[[RunSpec, str], None]) -> list[RunSpec]:
    """The single-fault runs whose logs place the second faults in recovery (placed in the
    baseline's window of their state, as single faults are); one the baseline never reached is
    skipped with the reason."""
    out: list[RunSpec] = []
    for s in need:
        for x in need_singles[s]:
            w = windows[s].get(x.state)
            spec = RunSpec(f"{x.name}_s{s}", config, plan, s, kind=x.kind.value, state=x.state,
                           start_s=place_fault((w[0], w[1]) if w else None, x.profile.duration_s),
                           duration_s=x.profile.duration_s, max_duration_s=max_duration_s)
            if spec.start_s is None:
                skip(spec, f"baseline of seed {s} never reached {x.state}")
            else:
                out.append(spec)
    return out


def pair_counts(everything: list[dict[str, Any]]) -> dict[str, int]:
    """The summary's ``pairs``: pair runs, overlapping, in recovery, passed."""
    pair_runs = [r for r in everything if r.get("second_kind")]
    in_recovery = sum(1 for r in pair_runs if str(r["scenario"]).endswith(RECOVERY_SUFFIX))
    return {"runs": len(pair_runs), "overlapping": len(pair_runs) - in_recovery, "recovery": in_recovery,
            "passed": sum(1 for r in pair_runs if r.get("passed"))}
