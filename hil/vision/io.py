"""Reading image files, with typed errors naming the file (marker sets: :mod:`hil.io.points`)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from hil.errors import InputFileError

U8Image = NDArray[np.uint8]


def load_grey_image(path: str | Path) -> U8Image:
    """Read an 8-bit image file as grey (colour files are converted with OpenCV's BGR->grey).

    Raises:
        InputFileError: missing, unreadable, not an image, empty, or not 8-bit.
    """
    return load_grey_image_channels(path)[0]


def load_grey_image_channels(path: str | Path) -> tuple[U8Image, int]:
    """:func:`load_grey_image` and the file's channel count (1 grey, 3 colour, 4 colour + alpha).

    Raises:
        InputFileError: missing, unreadable, not an image, empty, or not 8-bit.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError(str(path), "image file not found")
    data = np.fromfile(str(p), dtype=np.uint8)
    if data.size == 0:
        raise InputFileError(str(path), "image file is empty")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputFileError(str(path), "not an image OpenCV can decode")
    if img.dtype != np.uint8:
        raise InputFileError(str(path), f"expected 8-bit pixels, got {img.dtype}")
    channels = 1 if img.ndim == 2 else int(img.shape[2])
    if img.ndim == 3 and channels == 1:
        img = img[:, :, 0]
    elif img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if channels == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    return np.ascontiguousarray(img, dtype=np.uint8), channels
