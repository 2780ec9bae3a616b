"""Pixel-format conversion of raw camera payloads to Mono8 (the vision pipeline's input).

Pixel formats are GenICam PFNC codes (the values Aravis reports in ``ArvPixelFormat``).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

MONO_8 = 0x01080001
MONO_10 = 0x01100003
MONO_12 = 0x01100005
MONO_16 = 0x01100007
BAYER_GR_8 = 0x01080008
BAYER_RG_8 = 0x01080009
BAYER_GB_8 = 0x0108000A
BAYER_BG_8 = 0x0108000B
RGB_8 = 0x02180014
BGR_8 = 0x02180015

#: PFNC name -> code, for configs (names as GenICam spells them).
PIXEL_FORMATS: dict[str, int] = {
    "Mono8": MONO_8,
    "Mono10": MONO_10,
    "Mono12": MONO_12,
    "Mono16": MONO_16,
    "BayerGR8": BAYER_GR_8,
    "BayerRG8": BAYER_RG_8,
    "BayerGB8": BAYER_GB_8,
    "BayerBG8": BAYER_BG_8,
    "RGB8": RGB_8,
    "BGR8": BGR_8,
}

# PFNC Bayer names give the colour order of the first row; OpenCV names its codes by the
# second row's first two pixels, so PFNC BayerRG = OpenCV BayerBG and so on.
_BAYER_TO_GRAY = {
    BAYER_RG_8: cv2.COLOR_BayerBG2GRAY,
    BAYER_BG_8: cv2.COLOR_BayerRG2GRAY,
    BAYER_GR_8: cv2.COLOR_BayerGB2GRAY,
    BAYER_GB_8: cv2.COLOR_BayerGR2GRAY,
}


class PixelFormatError(ValueError):
    """The payload cannot be converted (unknown format or wrong size)."""


def bytes_per_pixel(pixel_format: int) -> int:
    """Bytes per pixel of an unpacked PFNC format (bits 16-23 of the code hold bits per pixel)."""
    return ((pixel_format >> 16) & 0xFF) // 8


def to_mono8(data: bytes | bytearray | memoryview, width_px: int, height_px: int,
             pixel_format: int) -> NDArray[np.uint8]:
    """Convert one raw image payload to an HxW uint8 image (a new, writable array).

    Mono10/12/16 (little-endian, unpacked) are scaled to their top 8 bits; Bayer 8-bit formats
    are demosaicked to grey; RGB8/BGR8 go through OpenCV's luma weights.

    Raises:
        PixelFormatError: unknown format code, or a payload shorter than the image.
    """
    if pixel_format not in PIXEL_FORMATS.values():
        raise PixelFormatError(f"unsupported pixel format 0x{pixel_format:08x}")
    n_bytes = width_px * height_px * bytes_per_pixel(pixel_format)
    if len(data) < n_bytes:
        raise PixelFormatError(
            f"payload of {len(data)} bytes is shorter than a {width_px}x{height_px} image "
            f"in format 0x{pixel_format:08x} ({n_bytes} bytes)"
        )
    raw = np.frombuffer(data, dtype=np.uint8, count=n_bytes)
    if pixel_format == MONO_8:
        return raw.reshape(height_px, width_px).copy()
    if pixel_format in (MONO_10, MONO_12, MONO_16):
        shift = {MONO_10: 2, MONO_12: 4, MONO_16: 8}[pixel_format]
        wide = raw.view("<u2").reshape(height_px, width_px)
        return np.asarray(np.minimum(wide >> shift, 255), dtype=np.uint8)
    if pixel_format in _BAYER_TO_GRAY:
        mosaic = raw.reshape(height_px, width_px)
        return np.ascontiguousarray(cv2.cvtColor(mosaic, _BAYER_TO_GRAY[pixel_format]), dtype=np.uint8)
    colour = raw.reshape(height_px, width_px, 3)
    code = cv2.COLOR_RGB2GRAY if pixel_format == RGB_8 else cv2.COLOR_BGR2GRAY
    return np.ascontiguousarray(cv2.cvtColor(colour, code), dtype=np.uint8)
