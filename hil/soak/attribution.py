"""Which injected fault explains which fault record of a soak's session log (``hil soak
--faults-every``; the rules in hil/soak/soak.py's module doc): a fault is *detected* when a fault is
recorded from a second before its onset to a second after its window ends, and then explains every
fault record until the procedure is compensating again (else until the next fault's onset)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.config.faults import FaultSpec

#: The devices open up to about a second apart (the servo process opens the robot in its own
#: process): a fault reason this long before the scheduled onset, or this long after the fault's
#: window ends, still counts as its effect.
ATTRIBUTION_SLACK_NS = 1_000_000_000


@dataclass(frozen=True)
class _Attribution:
    """One injected fault and the fault records it explains (controller clock, ns)."""

    onset_ns: int
    #: the fault records from ``onset - slack`` until the procedure was compensating again (else
    #: the next fault's onset); empty: tolerated
    window: list[tuple[int, str]]
    #: when the procedure was compensating again after a detected fault (None: never, or tolerated)
    back_ns: int | None


_Faults = list[tuple[int, str]]


def _attribute(schedule: tuple[FaultSpec, ...], session_log: str, t_open_ns: int,
               opened_ns: Mapping[str, int] | None = None) -> tuple[list[_Attribution], _Faults]:
    """Each injected fault's attribution (module doc) and every fault record of the log; a fault's
    onset is relative to when its device opened (``opened_ns`` by device, else ``t_open_ns``)."""
    def origin(f: FaultSpec) -> int:
        return (opened_ns or {}).get(f.device, t_open_ns)

    records = [json.loads(line) for line in Path(session_log).read_text().splitlines() if line.strip()]
    faults = [(r["t_ns"], str(r.get("reason", ""))) for r in records if r.get("event") == "fault_detected"]
    comp = [r["t_ns"] for r in records
            if r.get("event") == "state_entered" and r.get("state") == "compensate"]
    out: list[_Attribution] = []
    for k, f in enumerate(schedule):
        onset_ns = origin(f) + round(f.start_s * 1e9)
        next_ns = (origin(schedule[k + 1]) + round(schedule[k + 1].start_s * 1e9)
                   if k + 1 < len(schedule) else None)
        seen_by_ns = onset_ns + round(f.duration_s * 1e9) + ATTRIBUTION_SLACK_NS
        if not any(onset_ns - ATTRIBUTION_SLACK_NS <= t <= seen_by_ns for t, _ in faults):
            out.append(_Attribution(onset_ns, [], None))   # tolerated
            continue
        back = next((t for t in comp if t > onset_ns and (next_ns is None or t < next_ns)), None)
        end_ns = max(seen_by_ns, back if back is not None else (next_ns or max(t for t, _ in faults) + 1))
        window = [(t, why) for t, why in faults if onset_ns - ATTRIBUTION_SLACK_NS <= t < end_ns]
        out.append(_Attribution(onset_ns, window, back))
    return out, faults


def fault_outcomes(schedule: tuple[FaultSpec, ...], session_log: str, t_open_ns: int,
                   opened_ns: Mapping[str, int] | None = None) -> list[dict[str, Any]]:
    """What became of each injected fault, from the session log (module doc): ``detected`` is the
    first reason naming the faulted device, else the first reason at all, else ``tolerated``;
    ``reasons`` every distinct reason it explains. The onsets are relative to the device's
    opening: ``opened_ns[device]`` where known (the perception process's camera), else
    ``t_open_ns`` (controller clock, within the second the devices take to open)."""
    attributions, _ = _attribute(schedule, session_log, t_open_ns, opened_ns)
    out: list[dict[str, Any]] = []
    for f, a in zip(schedule, attributions, strict=True):
        said = next((why for _, why in a.window if f.device in why), a.window[0][1] if a.window else None)
        back_s = None if a.back_ns is None else round((a.back_ns - a.onset_ns) * 1e-9, 3)
        out.append({"kind": f.kind.value, "onset_s": f.start_s, "duration_s": f.duration_s,
                    "detected": "tolerated" if said is None else said, "back_in_compensation_s": back_s,
                    "reasons": list(dict.fromkeys(why for _, why in a.window))})
    return out


def unexplained_faults(schedule: tuple[FaultSpec, ...], session_log: str, t_open_ns: int,
                       opened_ns: Mapping[str, int] | None = None) -> list[str]:
    """The fault reasons of the session log that no injected fault explains (module doc; the
    onsets as in :func:`fault_outcomes`): each one is a defect the soak found (with no injected
    faults, every fault is)."""
    attributions, faults = _attribute(schedule, session_log, t_open_ns, opened_ns)
    explained = {fault for a in attributions for fault in a.window}
    return [why for t, why in faults if (t, why) not in explained]
