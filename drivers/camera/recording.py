"""Lossless recording of stereo sessions: frames + a timestamps sidecar, readable by the replay camera.

Layout of a recording directory (format version 1):

- ``recording.json``: ``{"format": "hil-stereo-recording", "version": 1, "codec": "ffv1"|"png",
  "image_size": [w, h], "frame_rate_hz", "exposure_us", "pairs": N}``
- ``timestamps.csv``: one row per pair, header
  ``pair,left_seq,left_t_ns,left_device_t_ns,right_seq,right_t_ns,right_device_t_ns``
  (``*_t_ns`` on the recording controller's clock; ``*_device_t_ns`` empty when the camera has none).
- frames: ``left.mkv`` / ``right.mkv`` (FFV1, 8-bit grey, lossless) or ``left/000000.png`` ...

FFV1 and PNG are lossless in OpenCV's headless wheel (environment.md, OpenCV video I/O), so a
replayed frame is bit-identical to the recorded one.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoCamera, StereoFrame
from hil.errors import InputFileError

FORMAT_NAME = "hil-stereo-recording"
FORMAT_VERSION = 1
CSV_FIELDS = ("pair", "left_seq", "left_t_ns", "left_device_t_ns", "right_seq", "right_t_ns",
              "right_device_t_ns")
Codec = Literal["ffv1", "png"]


@dataclass(frozen=True)
class RecordingInfo:
    directory: Path
    codec: Codec
    image_size: tuple[int, int]
    frame_rate_hz: float
    exposure_us: float
    pairs: int


@dataclass(frozen=True)
class PairRow:
    pair: int
    left_seq: int
    left_t_ns: int
    left_device_t_ns: int | None
    right_seq: int
    right_t_ns: int
    right_device_t_ns: int | None


class StereoRecorder:
    """Writes stereo pairs to ``directory`` (created; must not already hold a recording).

    Blocking: each ``write`` encodes two frames (FFV1 1920x1080 grey: a few ms each).
    Use as a context manager, or call ``close()`` to finish the files and metadata.
    """

    def __init__(self, directory: Path, *, frame_rate_hz: float, exposure_us: float = float("nan"),
                 codec: Codec = "ffv1") -> None:
        self.directory = Path(directory)
        if (self.directory / "recording.json").exists():
            raise InputFileError(str(self.directory), "already holds a recording; choose a new directory")
        self.directory.mkdir(parents=True, exist_ok=True)
        self.codec: Codec = codec
        self.frame_rate_hz = frame_rate_hz
        self.exposure_us = exposure_us
        self._size: tuple[int, int] | None = None
        self._writers: dict[str, cv2.VideoWriter] = {}
        self._csv_file = (self.directory / "timestamps.csv").open("w", newline="")
        self._csv = csv.writer(self._csv_file)
        self._csv.writerow(CSV_FIELDS)
        self.pairs = 0

    def __enter__(self) -> StereoRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write(self, pair: StereoFrame) -> None:
        """Append one pair. Raises ValueError for an image size or type change."""
        size = (pair.left.image.shape[1], pair.left.image.shape[0])
        for side, image in (("left", pair.left.image), ("right", pair.right.image)):
            if image.dtype != np.uint8 or image.ndim != 2 or (image.shape[1], image.shape[0]) != size:
                raise ValueError(f"{side} image must be HxW uint8 of size {size}, got {image.dtype} "
                                 f"{image.shape}")
        if self._size is None:
            self._size = size
            self._start(size)
        elif size != self._size:
            raise ValueError(f"image size changed from {self._size} to {size}")
        for side, image in (("left", pair.left.image), ("right", pair.right.image)):
            if self.codec == "ffv1":
                self._writers[side].write(image)
            else:
                path = self.directory / side / f"{self.pairs:06d}.png"
                if not cv2.imwrite(str(path), image):
                    raise OSError(f"{path}: could not write")
        self._csv.writerow([
            self.pairs, pair.left.seq, pair.left.t_ns, _opt(pair.left.device_t_ns),
            pair.right.seq, pair.right.t_ns, _opt(pair.right.device_t_ns),
        ])
        self.pairs += 1

    def _start(self, size: tuple[int, int]) -> None:
        for side in ("left", "right"):
            if self.codec == "ffv1":
                path = self.directory / f"{side}.mkv"
                writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter.fourcc(*"FFV1"),
                                         self.frame_rate_hz, size, False)
                if not writer.isOpened():
                    raise OSError(f"{path}: the FFV1 writer did not open")
                self._writers[side] = writer
            else:
                (self.directory / side).mkdir(exist_ok=True)

    def close(self) -> None:
        """Finish the video files and write ``recording.json``. Idempotent."""
        if self._csv_file.closed:
            return
        for writer in self._writers.values():
            writer.release()
        self._csv_file.close()
        w, h = self._size if self._size is not None else (0, 0)
        meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "codec": self.codec,
                "image_size": [w, h], "frame_rate_hz": self.frame_rate_hz,
                "exposure_us": None if self.exposure_us != self.exposure_us else self.exposure_us,
                "pairs": self.pairs}
        (self.directory / "recording.json").write_text(json.dumps(meta, indent=1) + "\n")


def record(camera: StereoCamera, directory: Path, pairs: int, *, timeout_s: float = 2.0,
           codec: Codec = "ffv1") -> RecordingInfo:
    """Grab ``pairs`` pairs from an ACTIVE ``camera`` into a new recording at ``directory``."""
    with StereoRecorder(directory, frame_rate_hz=camera.frame_rate_hz, exposure_us=camera.exposure_us,
                        codec=codec) as rec:
        for _ in range(pairs):
            rec.write(camera.grab(timeout_s))
    return read_info(directory)


def _opt(value: int | None) -> str:
    return "" if value is None else str(value)


def read_info(directory: Path) -> RecordingInfo:
    """Read and check ``recording.json``. Raises InputFileError naming the file and the field."""
    path = Path(directory) / "recording.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise InputFileError(str(path), "missing: not a stereo recording directory") from exc
    except (OSError, json.JSONDecodeError) as exc:
        raise InputFileError(str(path), f"not readable JSON ({exc})") from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise InputFileError(str(path), f"'format' must be {FORMAT_NAME!r}")
    if doc.get("version") != FORMAT_VERSION:
        raise InputFileError(str(path),
                             f"unsupported version {doc.get('version')!r} (reader: {FORMAT_VERSION})")
    try:
        codec = doc["codec"]
        if codec not in ("ffv1", "png"):
            raise InputFileError(str(path), f"'codec' must be 'ffv1' or 'png', got {codec!r}")
        w, h = (int(v) for v in doc["image_size"])
        return RecordingInfo(directory=Path(directory), codec=codec, image_size=(w, h),
                             frame_rate_hz=float(doc["frame_rate_hz"]),
                             exposure_us=float("nan") if doc.get("exposure_us") is None
                             else float(doc["exposure_us"]),
                             pairs=int(doc["pairs"]))
    except KeyError as exc:
        raise InputFileError(str(path), f"missing field {exc.args[0]!r}") from exc
    except (TypeError, ValueError) as exc:
        raise InputFileError(str(path), f"bad field value ({exc})") from exc


def read_timestamps(directory: Path) -> list[PairRow]:
    """Read ``timestamps.csv``. Raises InputFileError naming the file and line."""
    path = Path(directory) / "timestamps.csv"
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputFileError(str(path), f"not readable ({exc})") from exc
    reader = csv.reader(text.splitlines())
    header = next(reader, None)
    if header is None or tuple(header) != CSV_FIELDS:
        raise InputFileError(str(path), f"line 1: header must be {','.join(CSV_FIELDS)}")
    rows: list[PairRow] = []
    for line_no, cells in enumerate(reader, start=2):
        if len(cells) != len(CSV_FIELDS):
            raise InputFileError(str(path),
                                 f"line {line_no}: {len(cells)} fields, expected {len(CSV_FIELDS)}")
        try:
            v = [None if (c == "" and i in (3, 6)) else int(c) for i, c in enumerate(cells)]
        except ValueError as exc:
            raise InputFileError(str(path), f"line {line_no}: not an integer ({exc})") from exc
        if v[0] != len(rows):
            raise InputFileError(str(path),
                                 f"line {line_no}: pair {v[0]} out of order (expected {len(rows)})")
        rows.append(PairRow(*v))  # type: ignore[arg-type]
    return rows


def read_png(path: Path) -> NDArray[np.uint8]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputFileError(str(path), "missing or not a readable PNG")
    return np.asarray(image, dtype=np.uint8)
