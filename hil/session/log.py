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

No record follows the last one, so the chain alone cannot see an edit of the last line. On
close the writer therefore publishes the **chain head** (SHA-256 of the last line) outside the
file: :attr:`SessionLog.head_sha256` (``hil run`` prints it as ``session_log_sha256``) and a
sidecar ``<log>.head`` (one JSON object: ``format``, ``session_id``, ``records``,
``head_sha256``). The verifier checks the head when it is given or the sidecar exists.
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
HEAD_FORMAT = "hil-session-head"


def head_path(path: str | Path) -> Path:
    """The chain-head sidecar of a session log: ``<log>.head``."""
    p = Path(path)
    return p.with_name(p.name + ".head")


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

    @property
    def head_sha256(self) -> str:
        """SHA-256 (hex) of the last line written: the chain head (published on close)."""
        return self._prev

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
        """Write ``session_closed`` (with ``fields``), close, and publish the chain head in the
        sidecar ``<log>.head`` (see module doc). Idempotent.

        Raises:
            SessionLogError: the sidecar cannot be written (the log itself is closed).
        """
        if self._fh is None:
            return
        self.write("session_closed", **fields)
        with self._lock:
            if self._fh is not None:
                self._fh.close()
                self._fh = None
        head = {"format": HEAD_FORMAT, "session_id": self.session_id, "records": self._seq,
                "head_sha256": self._prev}
        try:
            head_path(self.path).write_text(json.dumps(head) + "\n", encoding="utf-8")
        except OSError as exc:
            raise SessionLogError(f"{head_path(self.path)}: cannot publish the chain head: "
                                  f"{exc.strerror or exc}") from None

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
    ``head``: the published chain head (see module doc): ``absent`` (none given, no sidecar,
    or not checked because the chain broke first),
    ``matched`` (the last line is the one published), ``mismatch`` (an edited last line makes
    ``ok`` False; a cut-off end reads as not closed, with the number of missing records).
    """

    ok: bool
    records: int
    first_bad_line: int | None
    reason: str
    closed: bool
    session_id: str | None
    head: str = "absent"


def _parse_line(raw: bytes) -> tuple[dict[str, Any] | None, str]:
    """One line's bytes -> (the record, "") or (None, what is wrong with it). Never raises:
    non-UTF-8 bytes, malformed or hostile JSON (nested too deeply, huge integer literals) and
    non-objects are all reported."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None, "not UTF-8"
    try:
        rec = json.loads(text)
    except json.JSONDecodeError as exc:
        return None, f"not JSON ({exc.msg})"
    except ValueError as exc:  # JSONDecodeError is a ValueError; this is the rest (digit limit)
        return None, f"unusable JSON ({exc})"
    except RecursionError:
        return None, "unusable JSON (nested too deeply)"
    if not isinstance(rec, dict):
        return None, "not a JSON object"
    return rec, ""


def read_session_log(path: str | Path) -> Iterator[dict[str, Any]]:
    """Yield the records of a session log (no chain check; see :func:`verify_session_log`).

    Raises:
        InputFileError: unreadable file, or a line that is not UTF-8 or not a JSON object
            (``"line N: ..."``).
    """
    try:
        fh = open(path, "rb")  # noqa: SIM115
    except OSError as exc:
        raise InputFileError(str(path), f"cannot read session log: {exc.strerror or exc}") from None
    with fh:
        for n, raw in enumerate(fh, 1):
            rec, why = _parse_line(raw)
            if rec is None:
                raise InputFileError(str(path), f"line {n}: {why}")
            yield rec


def _published_head(path: Path, expected_head_sha256: str | None) -> tuple[str | None, int | None, str]:
    """(head sha, records, problem) from the argument or the sidecar; (None, None, "") when
    neither exists; a problem string when the sidecar is unusable."""
    if expected_head_sha256 is not None:
        return expected_head_sha256.lower(), None, ""
    side = head_path(path)
    try:
        raw = side.read_bytes()
    except FileNotFoundError:
        return None, None, ""
    except OSError as exc:
        return None, None, f"chain head sidecar {side.name} unreadable: {exc.strerror or exc}"
    doc, why = _parse_line(raw.strip())
    if doc is None:
        return None, None, f"chain head sidecar {side.name} unusable: {why}"
    head, records = doc.get("head_sha256"), doc.get("records")
    if (doc.get("format") != HEAD_FORMAT or not isinstance(head, str) or len(head) != 64
            or not isinstance(records, int) or isinstance(records, bool) or records < 1):
        return None, None, f"chain head sidecar {side.name} unusable: not a {HEAD_FORMAT} record"
    return head.lower(), records, ""


def verify_session_log(path: str | Path, expected_head_sha256: str | None = None) -> VerifyReport:
    """Check the hash chain and the sequence numbers of a session log, and its last line
    against the published chain head (``expected_head_sha256``, e.g. a run summary's
    ``session_log_sha256``; else the sidecar ``<log>.head`` when it exists).

    Never raises for a damaged or tampered file: a line that is not UTF-8 or not JSON (also
    hostile JSON: nested too deeply, huge integer literals), a broken link, an edited last line
    all give a failed report naming the line. Raises InputFileError only when the file cannot be
    read at all.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputFileError(str(path), f"cannot read session log: {exc.strerror or exc}") from None
    lines = data.split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()
    prev = GENESIS_SHA256
    last_event = None
    session_id = None
    for n, line in enumerate(lines, 1):
        rec, why = _parse_line(line)
        if rec is None:
            return VerifyReport(False, n - 1, n, why, False, session_id)
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
        prev = hashlib.sha256(line).hexdigest()
        last_event = rec.get("event")
    if not lines:
        return VerifyReport(False, 0, None, "empty session log", False, None)
    closed = last_event == "session_closed"
    n = len(lines)
    head, head_records, problem = _published_head(p, expected_head_sha256)
    if problem:
        return VerifyReport(False, n, None, problem, closed, session_id, "mismatch")
    if head is None:
        return VerifyReport(True, n, None, "" if closed else "session not closed (ended abruptly)",
                            closed, session_id)
    if head == prev and (head_records is None or head_records == n):
        return VerifyReport(True, n, None, "" if closed else "session not closed (ended abruptly)",
                            closed, session_id, "matched")
    if head_records is not None and head_records > n and not closed:
        return VerifyReport(True, n, None, f"session not closed: the published chain head names "
                            f"{head_records} records, {n} found (the end was cut off)",
                            closed, session_id, "mismatch")
    return VerifyReport(False, n, n, "last line does not match the published chain head "
                        "(the last record was changed, or records were added after it)",
                        closed, session_id, "mismatch")
