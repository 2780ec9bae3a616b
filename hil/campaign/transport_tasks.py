"""The transport tier on an executor: every run a task that starts its own emulator on the worker
that runs it (:func:`hil.campaign.task.execute_task`), so ``--executor dask`` spreads the
transport matrix over machines the same way as the simulator tier."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from .executor import Executor, Progress
from .outputs import LogSink, write_summary
from .report import summarise
from .shard import Shard, matrix_identity
from .task import RunTask
from .transport import TRANSPORT_TIMEOUT_S, TransportScenario
from .version import PACKAGE_ROOT, code_version, config_digest


def transport_paths(scenarios: list[TransportScenario]) -> tuple[str, ...]:
    """The files a transport run's mixed setup is written from (base setups and their plans)."""
    configs = PACKAGE_ROOT / "configs"
    bases = sorted({sc.base for sc in scenarios})
    return tuple(str(p) for b in bases
                 for p in (configs / b, configs / "plans" / f"{Path(b).stem}_plan.json"))


def run_transport_matrix(
    scenarios: list[TransportScenario], seeds: list[int], *, out_dir: Path, executor: Executor,
    shard: Shard | None = None, keep_logs: bool = False, timeout_s: float = TRANSPORT_TIMEOUT_S,
    check_version: bool = True, progress: Progress | None = None,
) -> dict[str, Any]:
    """Run every scenario x seed (or the ``shard`` of them) on ``executor``; write
    ``transport.json``, ``transport.html`` and the failing runs' files in ``out_dir``; return the
    summary (the simulator tier's shape, ``tier`` "transport"). Blocking: ~15-30 s per run."""
    t_wall = time.perf_counter()
    say = progress or (lambda _m: None)
    paths = transport_paths(scenarios)
    digest = config_digest(paths)
    version = code_version()
    todo = [(sc, seed) for seed in seeds for sc in scenarios]
    ids = [f"{sc.name}_s{seed}" for sc, seed in todo]
    tasks = []
    for k, (sc, seed) in enumerate(todo):
        if shard is not None and not shard.owns(k):
            continue
        inputs = {"tier": "transport", "scenario": sc.name, "seed": seed, "kind": sc.kind.value,
                  "state": sc.state, "inject": sc.inject, "delay_s": sc.delay_s, "duration_s": sc.duration_s,
                  "config": sc.base, "config_sha256": digest, "code_version": version["id"]}
        tasks.append(RunTask("transport", ids[k], {"scenario": sc.name, "seed": seed}, inputs,
                             f"hil campaign --transport {sc.name} --seed {seed}", timeout_s,
                             str(version["id"]), digest, paths, keep_logs=keep_logs,
                             check_version=check_version))
    sink = LogSink(out_dir)
    say(f"transport: {len(tasks)} run(s) on {executor.description['kind']} "
        f"({executor.description['workers']} worker(s)), each starting its own emulator")
    results = executor.run(tasks, progress=say, on_files=sink)
    sink.attach(results)
    summary = summarise(results, config="(transport tier)")
    summary.update(tier="transport", code_version=version, config_sha256=digest,
                   executor=executor.description, shard=None if shard is None else shard.to_dict(),
                   matrix=matrix_identity(ids),
                   wall_s=round(time.perf_counter() - t_wall, 3))
    write_summary(summary, out_dir)
    return summary
