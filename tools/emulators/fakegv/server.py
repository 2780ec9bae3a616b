"""A GigE Vision fake camera serving our own images, hosted in this Python process.

Aravis' ``ArvGvFakeCamera`` speaks real GVCP/GVSP on a loopback address; its images come from
a fill-pattern callback. PyGObject's ``set_fill_pattern`` frees the callback when the call
returns (segfault), so the callback is installed with ctypes on
``arv_fake_camera_set_fill_pattern`` and kept alive by this object (environment.md, Aravis).

The callback runs on the fake camera's streaming thread (ctypes takes the GIL): it copies image
``n % len(images)`` (n = frames filled so far by this camera; with a software trigger, n is the
trigger count) into the buffer, cropped or padded to the camera's current Width x Height.
Only Mono8 is served; other pixel formats get a mid-grey frame.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

U8Image = NDArray[np.uint8]

_MONO_8 = 0x01080001
_FILL_CB = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32,
                            ctypes.c_uint32)


class FakeGvError(RuntimeError):
    """The fake camera could not start (address not on any interface, port taken, no Aravis)."""


def _libaravis() -> ctypes.CDLL:
    name = ctypes.util.find_library("aravis-0.8") or "libaravis-0.8.so.0"
    try:
        lib = ctypes.CDLL(name)
    except OSError as exc:
        raise FakeGvError(f"cannot load {name}: {exc} (install libaravis-0.8-0)") from exc
    lib.arv_fake_camera_set_fill_pattern.argtypes = [
        ctypes.c_void_p, _FILL_CB, ctypes.c_void_p, ctypes.c_void_p]
    lib.arv_fake_camera_set_fill_pattern.restype = None
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    lib.arv_buffer_get_image_width.argtypes = [ctypes.c_void_p]
    lib.arv_buffer_get_image_width.restype = ctypes.c_int
    lib.arv_buffer_get_image_height.argtypes = [ctypes.c_void_p]
    lib.arv_buffer_get_image_height.restype = ctypes.c_int
    return lib


def gobject_pointer(obj: Any) -> int:
    """The C address of a PyGObject wrapper's GObject (from its ``__gpointer__`` capsule)."""
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype = ctypes.c_void_p
    get.argtypes = [ctypes.py_object, ctypes.c_char_p]
    address = get(obj.__gpointer__, None)
    if not address:
        raise FakeGvError("could not get the GObject pointer of the fake camera")
    return int(address)


def fit_image(image: U8Image, width_px: int, height_px: int, fill: int = 128) -> U8Image:
    """``image`` cropped or padded (top-left anchored, ``fill`` grey) to ``height_px x width_px``."""
    out = np.full((height_px, width_px), fill, dtype=np.uint8)
    h = min(height_px, image.shape[0])
    w = min(width_px, image.shape[1])
    out[:h, :w] = image[:h, :w]
    return out


class FakeGvCamera:
    """One fake GigE Vision camera on ``address`` (GVCP port 3956) serving ``images``.

    Args:
        address: an address of a local interface (127.0.0.1; a second camera needs a second
            address, e.g. 127.0.0.2 added to ``lo`` in a private network namespace).
        serial: serial number; the device id clients see is ``Aravis-Fake-<serial>``.
        images: HxW uint8 images served in turn.
    """

    def __init__(self, address: str, serial: str, images: Sequence[U8Image]) -> None:
        if not images:
            raise FakeGvError("no images to serve")
        for i, img in enumerate(images):
            if img.dtype != np.uint8 or img.ndim != 2:
                raise FakeGvError(f"image {i} must be HxW uint8 (mono), got {img.dtype} {img.shape}")
        self.address = address
        self.serial = serial
        self._images = [np.ascontiguousarray(img) for img in images]
        self._fitted: dict[tuple[int, int, int], U8Image] = {}
        self._lock = threading.Lock()
        self.frames_filled = 0
        self._gv: Any = None
        self._callback: Any = None

    @property
    def device_id(self) -> str:
        return f"Aravis-Fake-{self.serial}"

    def start(self) -> None:
        """Start serving. Raises FakeGvError when the camera does not run (bad address, port busy)."""
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis
        except (ImportError, ValueError) as exc:
            raise FakeGvError(f"Aravis is not available: {exc}") from exc
        lib = _libaravis()
        gv = Aravis.GvFakeCamera.new(self.address, self.serial)
        if gv is None or not gv.is_running():
            raise FakeGvError(f"fake camera {self.serial} did not start on {self.address} "
                              "(is the address on a local interface? is GVCP port 3956 free there?)")
        self._gv = gv
        self._lib = lib
        self._callback = _FILL_CB(self._fill)
        fake_camera = gobject_pointer(gv.get_fake_camera())
        lib.arv_fake_camera_set_fill_pattern(fake_camera, self._callback, None, None)

    def stop(self) -> None:
        """Stop serving (drops the fake camera; its thread ends)."""
        self._gv = None

    def _image(self, index: int, width_px: int, height_px: int) -> U8Image:
        key = (index, width_px, height_px)
        img = self._fitted.get(key)
        if img is None:
            img = fit_image(self._images[index], width_px, height_px)
            if len(self._fitted) > 64:
                self._fitted.clear()
            self._fitted[key] = img
        return img

    def _fill(self, buffer: int | None, _data: int | None, _exposure_us: int, _gain: int,
              pixel_format: int) -> None:
        # Runs on the fake camera's thread. Must never raise into C.
        try:
            width = int(self._lib.arv_buffer_get_image_width(buffer))
            height = int(self._lib.arv_buffer_get_image_height(buffer))
            dest = self._lib.arv_buffer_get_data(buffer, None)
            if not dest or width <= 0 or height <= 0:
                return
            with self._lock:
                index = self.frames_filled % len(self._images)
                self.frames_filled += 1
            if pixel_format == _MONO_8:
                img = self._image(index, width, height)
                ctypes.memmove(dest, img.ctypes.data, width * height)
            else:
                ctypes.memset(dest, 128, width * height)
        except Exception:  # noqa: BLE001 - an exception must not cross into C
            return
