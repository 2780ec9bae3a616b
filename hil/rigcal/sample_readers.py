"""Readers of recorded hand-eye samples (docs/rig-calibration.md, "Offline, from recorded samples").

Formats (``--format``):

* ``csv``: our documented CSV. ``#`` lines are comments; the first other line is the header.
  Columns: ``t`` (seconds; optional for pairs, required for streams), then per stream
  (``robot`` = ``T_base_from_flange``, ``camera`` = ``T_camera_from_target``) either
  ``<s>_x, <s>_y, <s>_z, <s>_qx, <s>_qy, <s>_qz, <s>_qw`` (position and Hamilton quaternion,
  scalar LAST) or ``<s>_m00 ... <s>_m33`` (the 4x4 row by row). A row whose cells of one stream
  are all empty holds the other stream only: the file is then two unsynchronised streams.
* ``opencv-yaml``: OpenCV FileStorage with ``frameCount`` and ``T1_i`` (``T_base_from_flange``),
  ``T2_i`` (``T_camera_from_target``), 4x4, numbered from 0 (or from 1), read by
  ``cv2.FileStorage``.
* ``easy-handeye``: easy_handeye's saved samples (``*.samples``, YAML: ``samples: [{robot:
  {translation: {x,y,z}, rotation: {x,y,z,w}}, tracking: {...}}]``). ``tracking`` is
  ``T_trackingbase_from_marker`` = ``T_camera_from_target``; ``robot`` is the tf lookup
  ``T_base_from_effector`` for eye-in-hand but ``T_effector_from_base`` for eye-on-base, so it is
  inverted for eye-to-hand (easy_handeye's ``handeye_sampler.py``).
* ``eth``: a zip of ethz-asl/hand_eye_calibration CSV streams ``t, x, y, z, qx, qy, qz, qw``
  (seconds, metres, Hamilton quaternion scalar last): the hand stream ``T_B_H``
  (``T_base_from_flange``) and the eye stream ``T_W_E`` (the camera in the target/world frame,
  inverted to ``T_camera_from_target``); the eye stream is the member whose name holds
  ``camera``, ``target`` or ``W_``. Eye-in-hand only (the camera rides on the hand). Samples
  are sorted by time, a repeated stamp keeping its first sample.
* ``session-log``: the project's own session log (``hil run``'s JSONL; detected from a ``.jsonl``
  whose first record is ``session_started``): one pair per still pose of the arm, the hand frame
  being the needle guide (:mod:`hil.rigcal.session_samples`). Eye-to-hand only.

Units: translations in metres or millimetres, told apart per stream (:mod:`hil.rigcal.samples`).
"""

from __future__ import annotations

import itertools
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hil.rigcal.samples import (
    FloatArray,
    PosePairs,
    PoseStream,
    RecordedStreams,
    SamplesError,
    check_finite,
    check_rotation,
    inverse,
    make_pairs,
    quaternion_xyzw_to_matrix,
    to_mm,
    transform,
)
from hil.rigcal.session_samples import is_session_log, read_session_log

FORMATS = ("csv", "opencv-yaml", "easy-handeye", "eth", "session-log")
STREAMS = ("robot", "camera")
_QUAT_COLS = ("x", "y", "z", "qx", "qy", "qz", "qw")
_MAT_COLS = tuple(f"m{r}{c}" for r in range(4) for c in range(4))


def detect_format(path: Path) -> str:
    """The format from the file name and, for YAML, its content.

    Raises:
        SamplesError: unknown format (the extension and content fit none).
    """
    suffix = path.suffix.lower()
    if suffix == ".zip":
        return "eth"
    if suffix == ".csv":
        return "csv"
    if suffix == ".samples":
        return "easy-handeye"
    if suffix == ".jsonl" and is_session_log(path):
        return "session-log"
    if suffix in (".yaml", ".yml"):
        head = _read_text(path)
        if "frameCount" in head:
            return "opencv-yaml"
        if re.search(r"^samples\s*:", head, re.MULTILINE):
            return "easy-handeye"
    raise SamplesError(str(path), f"unknown format (give --format, one of {', '.join(FORMATS)})")


def read_samples(path: Path, fmt: str, eye_in_hand: bool) -> PosePairs | RecordedStreams:
    """The pairs (or streams) a file holds, in mm, frames as in :mod:`hil.rigcal.samples`.

    Raises:
        SamplesError: unreadable file, unknown format, malformed line, bad rotation or quaternion,
            NaN, mismatched counts, units that cannot be told (one line naming file and place).
    """
    if fmt == "csv":
        return read_csv(path)
    if fmt == "opencv-yaml":
        return read_opencv_yaml(path)
    if fmt == "easy-handeye":
        return read_easy_handeye(path, eye_in_hand)
    if fmt == "eth":
        if not eye_in_hand:
            raise SamplesError(str(path), "the eth format is eye-in-hand (the camera rides on the "
                                          "hand); use --setup eye-in-hand")
        return read_eth_zip(path)
    if fmt == "session-log":
        if eye_in_hand:
            raise SamplesError(str(path), "a session log is eye-to-hand (the camera stands still, the "
                                          "markers ride on the arm); use --setup eye-to-hand")
        return read_session_log(path)
    raise SamplesError(str(path), f"unknown format {fmt!r} (one of {', '.join(FORMATS)})")


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SamplesError(str(path), f"cannot read: {exc}") from None


def _lines(text: str) -> Iterator[tuple[int, list[str]]]:
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            yield n, [c.strip() for c in line.split(",")]


def _pose_from_cells(cells: list[str], layout: str, path: str, where: str) -> FloatArray:
    try:
        v = np.array([float(c) for c in cells])
    except ValueError:
        bad = next(c for c in cells if not _is_float(c))
        raise SamplesError(path, f"{where}: {bad!r} is not a number") from None
    check_finite(v, path, where)
    if layout == "quat":
        return transform(quaternion_xyzw_to_matrix(v[3:], path, where), v[:3])
    M = v.reshape(4, 4)
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise SamplesError(path, f"{where}: the 4x4's last row is {M[3].tolist()}, not [0, 0, 0, 1]")
    return transform(check_rotation(M[:3, :3], path, where), M[:3, 3])


def _is_float(c: str) -> bool:
    try:
        float(c)
    except ValueError:
        return False
    return True


def _csv_columns(header: list[str], path: str, n: int) -> tuple[int | None, dict[str, tuple[str, list[int]]]]:
    names = [h.lower() for h in header]
    t_col = names.index("t") if "t" in names else None
    cols: dict[str, tuple[str, list[int]]] = {}
    for s in STREAMS:
        for layout, suffixes in (("quat", _QUAT_COLS), ("matrix", _MAT_COLS)):
            want = [f"{s}_{x}" for x in suffixes]
            if all(w in names for w in want):
                cols[s] = (layout, [names.index(w) for w in want])
                break
        else:
            raise SamplesError(path, f"line {n}: the header has no {s} pose columns ({s}_x, {s}_y, {s}_z, "
                                     f"{s}_qx, {s}_qy, {s}_qz, {s}_qw or {s}_m00 ... {s}_m33)")
    return t_col, cols


def read_csv(path: Path) -> PosePairs | RecordedStreams:
    """Our documented CSV (module doc): pairs when every row holds both poses, else streams."""
    p = str(path)
    rows = list(_lines(_read_text(path)))
    if not rows:
        raise SamplesError(p, "no header line")
    (hn, header), body = rows[0], rows[1:]
    t_col, cols = _csv_columns(header, p, hn)
    got: dict[str, list[tuple[float, FloatArray, str]]] = {s: [] for s in STREAMS}
    complete = True
    for n, cells in body:
        where = f"line {n}"
        if len(cells) != len(header):
            raise SamplesError(p, f"{where}: {len(cells)} cells, the header has {len(header)}")
        t = float("nan")
        if t_col is not None:
            t = _time(cells[t_col], p, where)
        for s, (layout, idx) in cols.items():
            sc = [cells[i] for i in idx]
            if all(c == "" for c in sc):
                complete = False
                continue
            got[s].append((t, _pose_from_cells(sc, layout, p, f"{where} ({s})"), where))
    if complete:
        Tr = np.array([g[1] for g in got["robot"]]).reshape(-1, 4, 4)
        Tc = np.array([g[1] for g in got["camera"]]).reshape(-1, 4, 4)
        t_s = np.array([g[0] for g in got["robot"]]) if t_col is not None else None
        return make_pairs(Tr, Tc, tuple(g[2] for g in got["robot"]), p, t_s)
    if t_col is None:
        raise SamplesError(p, "rows with one stream only need a time column t (seconds)")
    return RecordedStreams(*(_stream([g[0] for g in got[s]], [g[1] for g in got[s]],
                                     [g[2] for g in got[s]], p, s) for s in STREAMS))


def _time(cell: str, path: str, where: str) -> float:
    if not _is_float(cell):
        raise SamplesError(path, f"{where}: time {cell!r} is not a number")
    t = float(cell)
    check_finite(np.array([t]), path, where)
    return t


def _stream(t: list[float], T: list[FloatArray], where: list[str], path: str, name: str) -> PoseStream:
    if len(t) < 2:
        raise SamplesError(path, f"the {name} stream has {len(t)} samples (need >= 2)")
    ts = np.array(t)
    bad = np.nonzero(np.diff(ts) <= 0)[0]
    if len(bad):
        raise SamplesError(path, f"{where[bad[0] + 1]}: {name} time {ts[bad[0] + 1]:.6f} s is not after "
                                 f"the previous one ({ts[bad[0]]:.6f} s)")
    return PoseStream(ts, to_mm(np.array(T), path, name), tuple(where))


def read_opencv_yaml(path: Path) -> PosePairs:
    """OpenCV FileStorage ``frameCount``, ``T1_i``, ``T2_i`` (module doc)."""
    import cv2  # the core imports OpenCV lazily (startup time of commands that never need it)

    p = str(path)
    try:
        fs = cv2.FileStorage(p, cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        why = str(exc).strip().splitlines()[-1]
        raise SamplesError(p, f"not an OpenCV FileStorage file: {why}") from None
    if not fs.isOpened():
        raise SamplesError(p, "cannot open as an OpenCV FileStorage file")
    try:
        node = fs.getNode("frameCount")
        if node.empty():
            raise SamplesError(p, "no frameCount")
        count = int(node.real())
        base = 0 if not fs.getNode("T1_0").empty() else 1
        Ts: dict[str, list[FloatArray]] = {"T1": [], "T2": []}
        for key in Ts:
            i = base
            while not fs.getNode(f"{key}_{i}").empty():
                Ts[key].append(_yaml_matrix(fs.getNode(f"{key}_{i}").mat(), p, f"{key}_{i}"))
                i += 1
    finally:
        fs.release()
    n1, n2 = len(Ts["T1"]), len(Ts["T2"])
    if n1 != count or n2 != count:
        raise SamplesError(p, f"mismatched counts: frameCount {count}, {n1} T1_i and {n2} T2_i")
    where = tuple(f"pair {i}" for i in range(base, base + count))
    return make_pairs(np.array(Ts["T1"]).reshape(-1, 4, 4), np.array(Ts["T2"]).reshape(-1, 4, 4), where, p)


def _yaml_matrix(m: Any, path: str, where: str) -> FloatArray:
    if m is None or np.asarray(m).shape != (4, 4):
        raise SamplesError(path, f"{where}: not a 4x4 matrix")
    return _pose_from_cells([repr(float(x)) for x in np.asarray(m, dtype=np.float64).ravel()], "matrix",
                            path, where)


def read_easy_handeye(path: Path, eye_in_hand: bool) -> PosePairs:
    """easy_handeye's saved samples (module doc)."""
    p = str(path)
    try:
        doc = yaml.safe_load(_read_text(path))
    except yaml.YAMLError as exc:
        raise SamplesError(p, f"not YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("samples"), list):
        raise SamplesError(p, "no 'samples' list (easy_handeye saved samples expected)")
    ctype = str((doc.get("parameters") or {}).get("calibration_type", "") or "")
    if ctype and (ctype == "eye_in_hand") != eye_in_hand:
        raise SamplesError(p, f"the file says calibration_type {ctype!r}; give the matching --setup")
    Tr, Tc = [], []
    for i, s in enumerate(doc["samples"]):
        where = f"sample {i}"
        if not isinstance(s, dict) or "robot" not in s or "tracking" not in s:
            raise SamplesError(p, f"{where}: needs both 'robot' and 'tracking'")
        Tr.append(_tf(s["robot"], p, f"{where} robot"))
        Tc.append(_tf(s["tracking"], p, f"{where} tracking"))
    T_robot = np.array(Tr).reshape(-1, 4, 4)
    if not eye_in_hand:
        T_robot = inverse(T_robot)   # eye-on-base samples hold T_effector_from_base
    return make_pairs(T_robot, np.array(Tc).reshape(-1, 4, 4),
                      tuple(f"sample {i}" for i in range(len(Tr))), p)


def _tf(d: Any, path: str, where: str) -> FloatArray:
    try:
        tr, rot = d["translation"], d["rotation"]
        cells = [str(tr[k]) for k in "xyz"] + [str(rot[k]) for k in "xyzw"]
    except (KeyError, TypeError):
        raise SamplesError(path, f"{where}: needs translation {{x, y, z}} and rotation "
                                 "{x, y, z, w}") from None
    return _pose_from_cells(cells, "quat", path, where)


def read_eth_zip(path: Path) -> RecordedStreams:
    """The ETH recordings' zip, read in place (module doc)."""
    p = str(path)
    try:
        with zipfile.ZipFile(path) as z:
            members = [m for m in z.namelist() if m.lower().endswith(".csv")]
            eye = [m for m in members
                   if re.search(r"camera|target|(^|_)W_", m.rsplit("/", 1)[-1], re.IGNORECASE)]
            hand = [m for m in members if m not in eye]
            if len(eye) != 1 or len(hand) != 1:
                raise SamplesError(p, f"expected one hand and one eye CSV, found eye {eye} and hand {hand}")
            texts = {k: z.read(m[0]).decode("utf-8") for k, m in (("hand", hand), ("eye", eye))}
            names = {"hand": hand[0], "eye": eye[0]}
    except (OSError, zipfile.BadZipFile, UnicodeDecodeError) as exc:
        raise SamplesError(p, f"cannot read the zip: {exc}") from None
    streams = {k: _eth_stream(texts[k], f"{p}:{names[k]}") for k in texts}
    eye_s = streams["eye"]
    cam = PoseStream(eye_s.t_s, inverse(eye_s.T), eye_s.where)   # T_W_E -> T_camera_from_target
    return RecordedStreams(streams["hand"], cam)


def _eth_stream(text: str, where_file: str) -> PoseStream:
    t, T, where = [], [], []
    for n, cells in _lines(text):
        w = f"line {n}"
        if len(cells) != 8:
            raise SamplesError(where_file, f"{w}: {len(cells)} values, expected 8 "
                                           "(t, x, y, z, qx, qy, qz, qw)")
        t.append(_time(cells[0], where_file, w))
        T.append(_pose_from_cells(cells[1:], "quat", where_file, w))
        where.append(w)
    # the recordings' stamps are not always in order (the simulated hand stream steps back now
    # and then) and repeat: sorted by time, a repeated stamp keeps its first sample
    order = sorted(range(len(t)), key=lambda i: t[i])
    keep = [order[0]] + [b for a, b in itertools.pairwise(order) if t[b] != t[a]]
    return _stream([t[i] for i in keep], [T[i] for i in keep], [where[i] for i in keep], where_file,
                   "stream")

