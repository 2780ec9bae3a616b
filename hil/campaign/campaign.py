"""Plan and run a campaign: baselines per seed, then every selected scenario per seed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from .pool import Progress, run_parallel
from .report import render_html, summarise
from .runner import RunSpec
from .scenarios import Scenario, place_fault

#: Wall-time bound of one run (s): a run beyond it is killed and counted as a hang.
RUN_TIMEOUT_S = 300.0


def run_campaign(
    scenarios: list[Scenario],
    seeds: list[int],
    *,
    config: Path,
    plan: str | None,
    jobs: int,
    out_dir: Path,
    keep_logs: bool = False,
    timeout_s: float = RUN_TIMEOUT_S,
    max_duration_s: float = 90.0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run the matrix; write ``campaign.json`` and ``campaign.html`` in ``out_dir``; return the
    summary (see :func:`hil.campaign.report.summarise`). Blocking (minutes for the full matrix)."""
    say = progress or (lambda _m: None)
    logs = out_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    base_specs = [
        RunSpec(f"baseline_s{s}", str(config), plan, s, max_duration_s=max_duration_s, log_dir=str(logs))
        for s in seeds
    ]
    say(f"baselines: {len(base_specs)} run(s) on {jobs} process(es)")
    baselines = run_parallel(base_specs, jobs=jobs, timeout_s=timeout_s, work_dir=logs, progress=say)
    specs: list[RunSpec] = []
    skipped: list[dict[str, Any]] = []
    for seed, base in zip(seeds, baselines, strict=True):
        windows = base.get("state_windows_s") or {}
        for sc in scenarios:
            dur = sc.profile.duration_s
            w = windows.get(sc.state)
            start = place_fault((w[0], w[1]) if w else None, dur)
            if start is None:
                skipped.append(
                    {
                        "run_id": f"{sc.kind.value}@{sc.state}_s{seed}",
                        "scenario": sc.name,
                        "kind": sc.kind.value,
                        "state": sc.state,
                        "seed": seed,
                        "passed": False,
                        "outcome": "not_reached",
                        "reasons": [f"baseline of seed {seed} never reached {sc.state}"],
                    }
                )
                continue
            specs.append(
                RunSpec(
                    f"{sc.kind.value}@{sc.state}_s{seed}",
                    str(config),
                    plan,
                    seed,
                    kind=sc.kind.value,
                    state=sc.state,
                    start_s=start,
                    duration_s=dur,
                    max_duration_s=max_duration_s,
                    log_dir=str(logs),
                )
            )
    say(f"scenarios: {len(specs)} run(s) on {jobs} process(es)")
    results = run_parallel(specs, jobs=jobs, timeout_s=timeout_s, work_dir=logs, progress=say)
    everything = [*baselines, *results, *skipped]
    summary = summarise(everything, config=str(config))
    if not keep_logs:  # keep the session logs of failing runs only
        failing = {f"{r['run_id']}.jsonl" for r in everything if not r.get("passed")}
        for p in logs.glob("*.jsonl"):
            if p.name not in failing:
                p.unlink()
                p.with_name(p.name + ".head").unlink(missing_ok=True)  # its chain-head sidecar
        if not any(logs.iterdir()):
            shutil.rmtree(logs)
    (out_dir / "campaign.json").write_text(json.dumps(summary, indent=1, default=str) + "\n")
    (out_dir / "campaign.html").write_text(render_html(summary))
    return summary
