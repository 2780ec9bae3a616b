"""Fault injection for the tracker emulators (thread-safe).

Kinds:
    garbage     random bytes inserted into an outgoing record/reply (``bytes=N``, default 1..8;
                ``mask=0x7F`` clears bit 7 of each, i.e. noise without Flock phasing bits)
    truncate    the tail of an outgoing record/reply is dropped
    lost_phase  (Flock) the phasing bit of a record's first byte is cleared
    bad_crc     (Aurora) the CRC of a reply (ASCII or BX body) is wrong
    silence     the device sends nothing (for ``seconds=S``, or until cleared)
    wrong_baud  the device runs at ``baud=B`` instead of what the host expects (Flock: its dip
                switch; Aurora: where COMM switches it)
    tool_missing  (Aurora) the tools on ``handles=0A+0B`` (default: every tool) are not seen: TX
                ``MISSING`` / BX handle status 0x02, port status and frame number still sent
                (for ``seconds=S``, or until cleared)
    out_of_volume (Aurora) the tools on ``handles`` are out of the measurement volume: port status
                bit 0x40; with reply option 0x0800 the transform is still sent, without it the
                tool is reported ``MISSING`` (for ``seconds=S``, or until cleared)
    reset       (Aurora) the device resets by itself mid-session (a power dip): it sends
                ``RESET`` + CRC at 9600 baud, is back at 9600 baud, not initialised, not tracking
    comm_baud   (Aurora) the next COMM (``count=N``: the next N) is answered ``OKAY`` at the old
                rate as usual, but the device then runs at ``baud=B`` instead of the rate asked

A spec string (command line ``--fault``, control interface ``fault``):
``KIND[,count=N][,p=P][,seconds=S][,after=S][,bytes=N][,mask=M][,baud=B][,handles=H+H][,seed=K]``.
``count`` arms the fault for the next N records/replies (default 1 when neither ``count`` nor ``p``
is given; ``silence``, ``tool_missing`` and ``out_of_volume`` then hold for ``seconds``, or until
cleared), ``p`` fires it with probability P on each, ``after`` delays arming by S seconds of
emulator time.
"""

from __future__ import annotations

import random
import threading
from dataclasses import dataclass

KINDS = ("garbage", "truncate", "lost_phase", "bad_crc", "silence", "wrong_baud", "tool_missing",
         "out_of_volume", "reset", "comm_baud")
#: Kinds that hold for a time window (``seconds=S`` or until cleared) when given no count and no p.
WINDOW_KINDS = ("tool_missing", "out_of_volume")


@dataclass
class FaultSpec:
    kind: str
    count: int | None = None
    p: float | None = None
    seconds: float | None = None
    after_s: float = 0.0
    n_bytes: int | None = None
    mask: int = 0xFF
    baud: int | None = None
    handles: tuple[int, ...] | None = None  # Aurora port handles hit (None: every tool)
    seed: int | None = None

    def hits(self, handle: int) -> bool:
        """Whether the fault applies to the Aurora port handle ``handle``."""
        return self.handles is None or handle in self.handles


def parse_fault(spec: str) -> FaultSpec:
    """Parse ``KIND[,key=value...]``.

    Raises:
        ValueError: unknown kind or key, bad number.
    """
    parts = [p.strip() for p in spec.split(",") if p.strip()]
    if not parts or parts[0] not in KINDS:
        raise ValueError(f"fault {spec!r}: kind must be one of {', '.join(KINDS)}")
    out = FaultSpec(parts[0])
    for part in parts[1:]:
        key, _, value = part.partition("=")
        try:
            if key == "count":
                out.count = int(value)
            elif key == "p":
                out.p = float(value)
                if not 0.0 <= out.p <= 1.0:
                    raise ValueError("p must be in [0, 1]")
            elif key == "seconds":
                out.seconds = float(value)
            elif key == "after":
                out.after_s = float(value)
            elif key == "bytes":
                out.n_bytes = int(value)
            elif key == "mask":
                out.mask = int(value, 0) & 0xFF
            elif key == "baud":
                out.baud = int(value)
            elif key == "handles":
                out.handles = tuple(int(h, 16) for h in value.split("+"))
                if not out.handles or any(not 0 <= h <= 0xFF for h in out.handles):
                    raise ValueError("handles must be port handles (2 hex digits) joined by +")
            elif key == "seed":
                out.seed = int(value)
            else:
                raise ValueError(f"unknown key {key!r}")
        except ValueError as exc:
            raise ValueError(f"fault {spec!r}: {exc}") from exc
    if out.kind in ("wrong_baud", "comm_baud") and out.baud is None:
        raise ValueError(f"fault {spec!r}: {out.kind} needs baud=B")
    return out


@dataclass
class _Armed:
    spec: FaultSpec
    remaining: int | None
    start_s: float
    until_s: float | None = None  # a window kind's end (None: until cleared)


class Faults:
    """The armed faults of one emulated device. Device code calls :meth:`fire` per record."""

    def __init__(self, seed: int = 0) -> None:
        self._lock = threading.Lock()
        self._armed: dict[str, _Armed] = {}
        self.rng = random.Random(seed)
        self._silence_until_s: float | None = None
        self._silence_forever = False
        self.wrong_baud: int | None = None
        self.fired: dict[str, int] = dict.fromkeys(KINDS, 0)

    def inject(self, spec: FaultSpec | str, now_s: float = 0.0) -> None:
        """Arm a fault (a spec or a spec string)."""
        s = parse_fault(spec) if isinstance(spec, str) else spec
        with self._lock:
            if s.seed is not None:
                self.rng.seed(s.seed)
            if s.kind == "wrong_baud":
                self.wrong_baud = s.baud
                return
            if s.kind == "silence" and s.count is None and s.p is None:
                if s.seconds is None:
                    self._silence_forever = True
                else:
                    self._silence_until_s = now_s + s.after_s + s.seconds
                self._armed["silence"] = _Armed(s, None, now_s + s.after_s)
                return
            if s.kind in WINDOW_KINDS and s.count is None and s.p is None:
                start = now_s + s.after_s
                self._armed[s.kind] = _Armed(s, None, start, None if s.seconds is None else start + s.seconds)
                return
            remaining = s.count if s.count is not None else (None if s.p is not None else 1)
            self._armed[s.kind] = _Armed(s, remaining, now_s + s.after_s)

    def clear(self, kind: str | None = None) -> None:
        with self._lock:
            if kind is None:
                self._armed.clear()
                self._silence_forever = False
                self._silence_until_s = None
                self.wrong_baud = None
                return
            self._armed.pop(kind, None)
            if kind == "silence":
                self._silence_forever = False
                self._silence_until_s = None
            if kind == "wrong_baud":
                self.wrong_baud = None

    def silent(self, now_s: float) -> bool:
        """True while a silence fault holds the device quiet."""
        with self._lock:
            a = self._armed.get("silence")
            if a is None or now_s < a.start_s:
                return False
            if self._silence_forever:
                return True
            if self._silence_until_s is not None and now_s < self._silence_until_s:
                return True
            if a.remaining is None and a.spec.p is None:
                self._armed.pop("silence", None)
                return False
        return self.fire("silence", now_s) is not None

    def fire(self, kind: str, now_s: float) -> FaultSpec | None:
        """The spec of ``kind`` when it hits the record being sent now (consumes one count), else None."""
        with self._lock:
            a = self._armed.get(kind)
            if a is None or now_s < a.start_s:
                return None
            if a.until_s is not None and now_s >= a.until_s:
                del self._armed[kind]
                return None
            hit = self.rng.random() < a.spec.p if a.spec.p is not None else True
            if hit and a.remaining is not None:
                a.remaining -= 1
                if a.remaining <= 0:
                    del self._armed[kind]
            if hit:
                self.fired[kind] += 1
            return a.spec if hit else None

    def n_bytes(self, spec: FaultSpec, default_max: int = 8) -> int:
        """The fault's ``bytes=N`` or a random 1..default_max."""
        if spec.n_bytes is not None:
            return spec.n_bytes
        return self.randint(1, default_max)

    def random_bytes(self, n: int, mask: int = 0xFF) -> bytes:
        with self._lock:
            return bytes(self.rng.randrange(256) & mask for _ in range(n))

    def randint(self, a: int, b: int) -> int:
        with self._lock:
            return self.rng.randint(a, b)
