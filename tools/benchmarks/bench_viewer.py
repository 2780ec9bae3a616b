"""Cost of the 3D replay and of the live viewer stream (docs/replay.md).

Run: ``tools/bench viewer [--json] [--seconds S] [--rate-hz HZ] [--session LOG]``

1. **Replay**: ``hil replay`` of the default ``hil run`` session (run here unless ``--session``):
   file size, time to write (best and median of 3; target <= 5 s), entities and records.
2. **Live hook**: the snapshots of that run, captured from the live plugin's hook, are offered
   to a :class:`LiveViewerPlugin` streaming to a ``.rrd`` through Rerun at ``--rate-hz`` (500)
   for ``--seconds`` (10), from a loop that does a fixed 0.5 ms of numpy work per tick, as the
   supervisor would. Figures: the hook's time per call (p50, p99, max; target p99 <= 0.1 ms), the
   loop's tick duration p99 with and without the stream (the worker thread competes for the
   GIL), snapshots written and dropped.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import hil.replay.live as live
from hil.cli import main
from hil.replay import write_replay


class _Capture:
    """A SnapshotWriter keeping the snapshots (to replay them at a fixed rate)."""

    snaps: ClassVar[list[Any]] = []

    def __init__(self, target: str, recording_id: str | None = None) -> None:
        pass

    def write_tick(self, snap: Any) -> None:
        _Capture.snaps.append(snap)

    def write_transition(self, text: str, snap: Any) -> None:
        pass

    def close(self) -> None:
        pass


def run_session(out_dir: Path) -> Path:
    """A default ``hil run`` whose snapshots are captured (the plugin with a capturing writer)."""
    real = live.RerunSnapshotWriter
    live.RerunSnapshotWriter = _Capture  # type: ignore[misc,assignment]
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
            code = main(["run", "--json", "--no-report", "--session-dir", str(out_dir),
                         "--viewer", str(out_dir / "capture.rrd")])
    finally:
        live.RerunSnapshotWriter = real  # type: ignore[misc]
    if code != 0:
        raise SystemExit(f"hil run failed ({code})")
    return Path(json.loads(buf.getvalue())["session_log"])


def bench_replay(log: Path, out_dir: Path) -> dict[str, Any]:
    times, result = [], None
    for i in range(3):
        t = time.perf_counter()
        result = write_replay(log, out_dir / f"replay{i}.rrd")
        times.append(time.perf_counter() - t)
    assert result is not None
    return {"session_log": str(log), "bytes": result.bytes, "entities": len(result.entities),
            "records": result.records, "write_s_best": min(times), "write_s_median": statistics.median(times)}


def _loop(snaps: list[Any], seconds: float, rate_hz: float, plugin: live.LiveViewerPlugin | None,
          ) -> list[float]:
    """Tick durations (s) of a paced loop doing 0.5 ms of work and offering a snapshot."""
    period = 1.0 / rate_hz
    a = np.random.default_rng(0).standard_normal((64, 64))
    ticks: list[float] = []
    n = int(seconds * rate_hz)
    nxt = time.perf_counter()
    for i in range(n):
        t0 = time.perf_counter()
        end = t0 + 0.0005
        while time.perf_counter() < end:
            a = a @ a.T * 1e-3 + 1.0
        if plugin is not None:
            plugin.hil_on_tick(snapshot=snaps[i % len(snaps)])
        ticks.append(time.perf_counter() - t0)
        nxt += period
        delay = nxt - time.perf_counter()
        if delay > 0:
            time.sleep(delay)  # pacing the benchmark's own loop, as the supervisor's clock does
    return ticks


def _us(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs) * 1e6, q))


def bench_live(snaps: list[Any], seconds: float, rate_hz: float, out_dir: Path) -> dict[str, Any]:
    base = _loop(snaps, seconds, rate_hz, None)
    plugin = live.open_live_viewer(str(out_dir / "live.rrd"))
    try:
        with_stream = _loop(snaps, seconds, rate_hz, plugin)
    finally:
        counts = plugin.close()
    cost = live.hook_cost_us(plugin)
    return {"rate_hz": rate_hz, "seconds": seconds, "snapshots_captured": len(snaps),
            "hook_us_p50": cost["p50"], "hook_us_p99": cost["p99"], "hook_us_max": cost["max"],
            "tick_us_p50_without": _us(base, 50), "tick_us_p99_without": _us(base, 99),
            "tick_us_p50_with": _us(with_stream, 50), "tick_us_p99_with": _us(with_stream, 99),
            **counts, "rrd_bytes": (out_dir / "live.rrd").stat().st_size}


def main_bench(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate-hz", type=float, default=500.0)
    ap.add_argument("--session", type=Path, default=None, help="replay this log instead of a new run")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="hil-bench-viewer-") as tmp:
        d = Path(tmp)
        log = run_session(d)
        replay = bench_replay(args.session or log, d)
        result = {"replay": replay, "live": bench_live(_Capture.snaps, args.seconds, args.rate_hz, d)}
    if args.json:
        print(json.dumps(result))
    else:
        r, lv = result["replay"], result["live"]
        print(f"replay   {r['bytes']} bytes, {r['entities']} entities, {r['records']} records, "
              f"written in {r['write_s_best']:.2f} s (median {r['write_s_median']:.2f} s)")
        print(f"live     hook p50 {lv['hook_us_p50']:.1f} us, p99 {lv['hook_us_p99']:.1f} us, "
              f"max {lv['hook_us_max']:.0f} us at {lv['rate_hz']:g} Hz; tick p99 "
              f"{lv['tick_us_p99_without']:.0f} us without, {lv['tick_us_p99_with']:.0f} us with; "
              f"{lv['written']} written, {lv['dropped']} dropped")
    return 0


if __name__ == "__main__":
    sys.exit(main_bench())
