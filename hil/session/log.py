"""The session log writer and its verifier.

One JSON object per line (structlog's event-dict shape: ``event`` is a snake_case name, the data
are fields). Every record carries:

- ``seq``: 0, 1, 2 … (no gaps);
- ``t_ns``: the controller's monotonic clock (ns) — the time axis for replay;
- ``wall``: ISO-8601 UTC wall time (for people; never used for control);
- ``prev_sha256``: the SHA-256 (hex) of the previous line's bytes (without its newline);
  the first record's is :data:`GENESIS_SHA256`.

Changing, inserting, deleting or reordering any line breaks the chain from there on, which
:func:`verify_session_log` reports with the line number. The first record (``session_started``)
holds the session id and the config and calibration hashes.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import threading
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from hil.clock import Clock
from hil.errors import HilError, InputFileError
from hil.geometry.transform import RigidTransform

GENESIS_SHA256 = "0" * 64
SCHEMA_VERSION = 1


class SessionLogError(HilError):
    """The session log cannot be written (closed, unwritable)."""


def _jsonable(value: Any) -> Any:
    """Convert numpy values, transforms, enums, paths and non-finite floats to JSON-safe data."""
    if isinstance(value, RigidTransform):
        return {"rotvec_rad": _jsonable(value.as_rotvec()), "t_mm": _jsonable(value.t)}
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [_jsonable(v) for v in value]
    if value is None or isinstance(value, bool | int | str):
        return value
    return repr(value)


def _line_sha256(line: str) -> str:
    return hashlib.sha256(line.encode("utf-8")).hexdigest()


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, for the config and calibration hashes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 16), b""):
            h.update(chunk)
    return h.hexdigest()


class SessionLog:
    """Append-only, hash-chained JSON-lines session file. Thread-safe.

    Args:
        path: the file to create (its directory is created; an existing file is refused).
        clock: the controller's clock (``t_ns`` of every record).
        header: fields of the first record (config/calibration hashes, setup name …).

    Raises:
        SessionLogError: the file exists or cannot be created.
    """

    def __init__(self, path: str | Path, clock: Clock, header: Mapping[str, Any] | None = None) -> None:
        self.path = Path(path)
        self._clock = clock
        self._lock = threading.Lock()
        self._seq = 0
        self._prev = GENESIS_SHA256
        self.session_id = uuid.uuid4().hex
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh: TextIO | None = open(self.path, "x", encoding="utf-8")  # noqa: SIM115
        except OSError as exc:
            raise SessionLogError(f"{self.path}: cannot create session log: {exc.strerror or exc}") from None
        self.write("session_started", session_id=self.session_id, schema=SCHEMA_VERSION, **(header or {}))

    @property
    def records_written(self) -> int:
        return self._seq

    def write(self, event: str, **fields: Any) -> None:
        """Append one record. ``event`` is a snake_case name; fields must not use the reserved
        keys (``seq``, ``t_ns``, ``wall``, ``event``, ``prev_sha256``).

        Raises:
            SessionLogError: closed, or a reserved key was given.
        """
        reserved = {"seq", "t_ns", "wall", "event", "prev_sha256"} & fields.keys()
        if reserved:
            raise SessionLogError(f"reserved session log keys used: {sorted(reserved)}")
        with self._lock:
            if self._fh is None:
                raise SessionLogError(f"{self.path}: session log is closed")
            record: dict[str, Any] = {
                "seq": self._seq,
                "t_ns": self._clock.now_ns(),
                "wall": _dt.datetime.now(_dt.UTC).isoformat(timespec="microseconds"),
                "event": event,
                **{k: _jsonable(v) for k, v in fields.items()},
                "prev_sha256": self._prev,
            }
            line = json.dumps(record, separators=(",", ":"), allow_nan=False)
            self._fh.write(line + "\n")
            self._fh.flush()
            self._prev = _line_sha256(line)
            self._seq += 1

    def close(self, **fields: Any) -> None:
        """Write ``session_closed`` (with ``fields``) and close. Idempotent."""
        if self._fh is None:
            return
        self.write("session_closed", **fields)
        with self._lock:
            if self._fh is not None:
                self._fh.close()
                self._fh = None

    def __enter__(self) -> SessionLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class VerifyReport:
    """Result of :func:`verify_session_log`.

    ``ok``: the chain is intact and complete. ``records``: lines read. ``first_bad_line``:
    1-based line of the first broken link (None when ok). ``reason``: what is wrong.
    ``closed``: the last record is ``session_closed`` (False: the session ended abruptly).
    """

    ok: bool
    records: int
    first_bad_line: int | None
    reason: str
    closed: bool
    session_id: str | None


def read_session_log(path: str | Path) -> Iterator[dict[str, Any]]:
    """Yield the records of a session log (no chain check; see :func:`verify_session_log`).

    Raises:
        InputFileError: unreadable file or a line that is not a JSON object.
    """
    try:
        fh = open(path, encoding="utf-8")  # noqa: SIM115
    except OSError as exc:
        raise InputFileError(str(path), f"cannot read session log: {exc.strerror or exc}") from None
    with fh:
        for n, line in enumerate(fh, 1):
            try:
                rec = json.loads(line)
            except json.JSONDecodeError as exc:
                raise InputFileError(str(path), f"line {n}: not JSON ({exc.msg})") from None
            if not isinstance(rec, dict):
                raise InputFileError(str(path), f"line {n}: not a JSON object")
            yield rec


def verify_session_log(path: str | Path) -> VerifyReport:
    """Check the hash chain and the sequence numbers of a session log.

    Never raises for a tampered file (the report says where); raises InputFileError only when
    the file cannot be read at all.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(str(path), f"cannot read session log: {exc}") from None
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    prev = GENESIS_SHA256
    last_event = None
    session_id = None
    for n, line in enumerate(lines, 1):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            return VerifyReport(False, n - 1, n, "not JSON", False, session_id)
        if not isinstance(rec, dict):
            return VerifyReport(False, n - 1, n, "not a JSON object", False, session_id)
        if rec.get("prev_sha256") != prev:
            return VerifyReport(False, n - 1, n,
                                "hash chain broken (a line was changed, inserted or removed)",
                                False, session_id)
        if rec.get("seq") != n - 1:
            return VerifyReport(False, n - 1, n, f"sequence number {rec.get('seq')} where {n - 1} expected",
                                False, session_id)
        if n == 1:
            if rec.get("event") != "session_started":
                return VerifyReport(False, 0, 1, "first record is not session_started", False, None)
            session_id = rec.get("session_id")
        prev = _line_sha256(line)
        last_event = rec.get("event")
    if not lines:
        return VerifyReport(False, 0, None, "empty session log", False, None)
    closed = last_event == "session_closed"
    return VerifyReport(True, len(lines), None, "" if closed else "session not closed (ended abruptly)",
                        closed, session_id)
