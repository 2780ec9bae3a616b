"""Run campaign runs in parallel processes, each bounded in wall time (a run that overruns is
killed and counted as a hang)."""

from __future__ import annotations

import json
import multiprocessing as mp
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from .runner import RunResult, RunSpec, following_note, run_one

Progress = Callable[[str], None]


def _worker(spec_dict: dict[str, Any], result_path: str, run: Callable[[Any], RunResult] = run_one,
            spec_type: type[Any] = RunSpec) -> None:
    """Child process: run one spec, write its result as JSON (a crash of the runner itself is
    written as a failed result with the traceback)."""
    from hil.log import configure_logging

    configure_logging(level="error")  # children stay quiet (stderr); the parent reports progress
    spec = spec_type(**spec_dict)
    try:
        out = run(spec).to_dict()
    except BaseException as exc:  # noqa: BLE001 - any escape is a campaign finding, not a crash of ours
        out = RunResult(
            spec.run_id,
            spec.scenario,
            spec.kind,
            spec.state,
            spec.seed,
            passed=False,
            reasons=[f"campaign run crashed: {type(exc).__name__}: {exc}"],
            outcome="crashed",
            error="".join(traceback.format_exception(exc))[-4000:],
        ).to_dict()
    Path(result_path).write_text(json.dumps(out, default=str))


def run_parallel(
    specs: list[Any], *, jobs: int, timeout_s: float, work_dir: Path, progress: Progress | None = None,
    run: Callable[[Any], RunResult] = run_one,
) -> list[dict[str, Any]]:
    """Run ``specs`` on ``jobs`` processes; returns their result dicts in the order of ``specs``.
    ``run`` (a module-level function, it crosses to the spawned process) runs one spec
    (a dataclass with ``run_id``, ``scenario``, ``kind``, ``state``, ``seed``).

    Blocking; at most ``timeout_s`` wall seconds per run.
    """
    say = progress or (lambda _m: None)
    ctx = mp.get_context("spawn")
    work_dir.mkdir(parents=True, exist_ok=True)
    pending = list(enumerate(specs))
    running: dict[int, tuple[Any, float, Path, Any]] = {}
    results: dict[int, dict[str, Any]] = {}
    while pending or running:
        while pending and len(running) < max(1, jobs):
            i, spec = pending.pop(0)
            path = work_dir / f"{spec.run_id}.result.json"
            path.unlink(missing_ok=True)
            proc = ctx.Process(
                target=_worker, args=(asdict(spec), str(path), run, type(spec)), name=spec.run_id, daemon=True
            )
            proc.start()
            running[i] = (proc, time.monotonic(), path, spec)
        for i, (proc, t0, path, spec) in list(running.items()):
            if proc.is_alive():
                if time.monotonic() - t0 > timeout_s:
                    proc.kill()
                    proc.join(5.0)
                    results[i] = RunResult(
                        spec.run_id,
                        spec.scenario,
                        spec.kind,
                        spec.state,
                        spec.seed,
                        passed=False,
                        outcome="hang",
                        reasons=[f"run did not finish within {timeout_s:.0f} s (hang)"],
                        wall_s=round(time.monotonic() - t0, 3),
                    ).to_dict()
                    del running[i]
                    say(f"{spec.run_id}: HANG (killed after {timeout_s:.0f} s)")
                continue
            proc.join()
            del running[i]
            if path.is_file():
                results[i] = json.loads(path.read_text())
                path.unlink()
            else:
                results[i] = RunResult(
                    spec.run_id,
                    spec.scenario,
                    spec.kind,
                    spec.state,
                    spec.seed,
                    passed=False,
                    outcome="crashed",
                    reasons=[f"run process died (exit code {proc.exitcode})"],
                ).to_dict()
            r = results[i]
            lat = r.get("safe_latency_ms")
            say(
                f"{spec.run_id}: {'pass' if r['passed'] else 'FAIL'} {r.get('outcome', '')}"
                + (f" {lat:.0f} ms" if isinstance(lat, int | float) else "")
                + following_note(r)
                + ("" if r["passed"] else f" ({'; '.join(r.get('reasons', []))})")
            )
        time.sleep(0.05)
    return [results[i] for i in range(len(specs))]

