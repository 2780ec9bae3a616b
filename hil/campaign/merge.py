"""``hil campaign merge DIR...``: combine the outputs of several campaign runs (the shards of one
matrix, usually) into one summary - the object ``hil campaign --json`` prints - with its JSON and
HTML files and the failing runs' logs.

Refused (one line each, :class:`MergeError`): a directory without a campaign output; outputs of
different tiers; a run that appears in two outputs (it would be counted twice); shards of
different splits or the same shard twice. Refused unless ``allow_mismatch``: different code
versions, config digests or matrices. Refused unless ``allow_partial``: shards missing.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from hil.errors import HilError

from .outputs import STEMS
from .pairs_campaign import pair_counts
from .report import summarise


class MergeError(HilError, ValueError):
    """Campaign outputs that cannot be merged (one line naming the directories and what differs)."""


def load_output(directory: Path) -> dict[str, Any]:
    """The summary in ``directory`` (``campaign.json`` or ``transport.json``).

    Raises:
        MergeError: none or both there, or not a campaign summary.
    """
    found = [directory / f"{stem}.json" for stem in STEMS.values() if (directory / f"{stem}.json").is_file()]
    if len(found) != 1:
        what = "no campaign.json or transport.json" if not found else "both campaign.json and transport.json"
        raise MergeError(f"{directory}: {what} (not one campaign output)")
    try:
        summary = json.loads(found[0].read_text())
    except (OSError, ValueError) as exc:
        raise MergeError(f"{found[0]}: cannot read it ({exc})") from None
    if not isinstance(summary, dict) or not isinstance(summary.get("results"), list):
        raise MergeError(f"{found[0]}: not a campaign summary (no results list)")
    summary.setdefault("tier", "simulator")
    return summary


def _same(outputs: list[tuple[Path, dict[str, Any]]], what: str, get: Any, allow: bool, hint: str) -> None:
    values = {json.dumps(get(s), sort_keys=True): d for d, s in outputs}
    if len(values) > 1 and not allow:
        (a, da), (b, db) = list(values.items())[:2]
        raise MergeError(f"{what} differ: {da} has {json.loads(a)}, {db} has {json.loads(b)}{hint}")


def _shard_text(shard: dict[str, int] | None) -> str:
    return "unsharded" if shard is None else f"shard {shard['index']}/{shard['count']}"


def _check_shards(outputs: list[tuple[Path, dict[str, Any]]], allow_partial: bool) -> None:
    shards = [(d, s.get("shard")) for d, s in outputs]
    if all(sh is None for _, sh in shards):
        return
    counts = {sh["count"] if sh else None for _, sh in shards}
    if len(counts) > 1:
        split = ", ".join(f"{d}: {_shard_text(sh)}" for d, sh in shards)
        raise MergeError(f"outputs of different splits ({split})")
    count = counts.pop()
    assert count is not None
    seen: dict[int, Path] = {}
    for d, sh in shards:
        assert sh is not None
        if sh["index"] in seen:
            raise MergeError(f"shard {sh['index']}/{count} given twice: {seen[sh['index']]} and {d}")
        seen[sh["index"]] = d
    missing = [i for i in range(count) if i not in seen]
    if missing and not allow_partial:
        raise MergeError(f"shard(s) {', '.join(f'{i}/{count}' for i in missing)} missing "
                         "(--allow-partial merges what is there)")


def merge_outputs(dirs: list[Path], *, out_dir: Path, allow_mismatch: bool = False,
                  allow_partial: bool = False) -> dict[str, Any]:
    """Check and merge the outputs in ``dirs``; write ``<stem>.json``, ``<stem>.html`` and the
    logs in ``out_dir``; return the merged summary (``merged_from`` lists the directories,
    ``shard`` is None, ``code_version``/``config_sha256``/``matrix`` those of the first output;
compound-fault outputs keep ``pairs``, counted over the merged runs).

    Raises:
        MergeError: see the module doc.
    """
    from .outputs import write_summary

    if not dirs:
        raise MergeError("give at least one campaign output directory")
    outputs = [(d, load_output(d)) for d in dirs]
    _same(outputs, "tiers", lambda s: s["tier"], False, "")
    hint = " (--allow-mismatch merges them anyway)"
    _same(outputs, "code versions", lambda s: (s.get("code_version") or {}).get("id"), allow_mismatch, hint)
    _same(outputs, "config digests", lambda s: s.get("config_sha256"), allow_mismatch, hint)
    _same(outputs, "matrices (scenarios x seeds)", lambda s: s.get("matrix"), allow_mismatch, hint)
    _check_shards(outputs, allow_partial)
    owner: dict[str, Path] = {}
    results: list[dict[str, Any]] = []
    for d, s in outputs:
        for r in s["results"]:
            rid = str(r.get("run_id"))
            if rid in owner:
                raise MergeError(f"run {rid} is in both {owner[rid]} and {d} (it would be counted twice)")
            owner[rid] = d
            results.append(_with_log(dict(r), d, out_dir))
    results.sort(key=lambda r: (int(r.get("seed", 0)), r.get("scenario") != "baseline", str(r["run_id"])))
    first = outputs[0][1]
    merged = summarise(results, config=str(first.get("config")))
    merged.update(tier=first["tier"], code_version=first.get("code_version"),
                  config_sha256=first.get("config_sha256"), executor={"kind": "merged"}, shard=None,
                  matrix=first.get("matrix"), wall_s=None, merged_from=[str(d) for d in dirs])
    if any(o.get("pairs") is not None for _, o in outputs):   # compound faults: counted again
        merged["pairs"] = pair_counts(results)
    if merged["tier"] == "transport":
        for f in merged["failing"]:
            f["replay"] = f"hil campaign --transport {f['scenario']} --seed {f['seed']}"
    write_summary(merged, out_dir)
    return merged


def _with_log(rec: dict[str, Any], src: Path, out_dir: Path) -> dict[str, Any]:
    """Copy the run's kept files from ``src/logs`` to ``out_dir/logs``; repoint ``session_log``."""
    logs = src / "logs"
    rid = str(rec["run_id"])
    kept = [logs / n for n in (rid, f"{rid}.jsonl", f"{rid}.jsonl.head") if (logs / n).exists()]
    for p in kept:
        dest = out_dir / "logs" / p.name
        if p.resolve() == dest.resolve():
            continue
        dest.parent.mkdir(parents=True, exist_ok=True)
        if p.is_dir():
            shutil.copytree(p, dest, dirs_exist_ok=True)
        else:
            shutil.copy2(p, dest)
    log = out_dir / "logs" / f"{rid}.jsonl"
    rec["session_log"] = str(log) if log.is_file() else None
    return rec
