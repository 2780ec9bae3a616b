"""A GigE Vision fake camera serving our own images, hosted in this Python process.

Aravis' ``ArvGvFakeCamera`` speaks real GVCP/GVSP on a loopback address; its images come from
a fill-pattern callback. PyGObject's ``set_fill_pattern`` frees the callback when the call
returns (segfault), so the callback is installed with ctypes on
``arv_fake_camera_set_fill_pattern`` and kept alive by this object (environment.md, Aravis).

The callback runs on the fake camera's streaming thread (ctypes takes the GIL): it copies image
``n % len(images)`` (n = frames filled so far by this camera; with a software trigger, n is the
trigger count) into the buffer, cropped or padded to the camera's current Width x Height. With a
``source`` instead of images, frame n is ``source(n)``: :class:`SharedPairSource` serves the newest
pair of a shared-memory frame block (:mod:`hil.campaign.frameshm`), the same pair on both sides for
the same n. Only Mono8 is served; other pixel formats get a mid-grey frame.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil.campaign.frameshm import FrameBlockReader, SharedPair

U8Image = NDArray[np.uint8]
#: frame n of a camera -> its image (any size; fitted to the camera's region), or None (grey)
ImageSource = Callable[[int], "U8Image | None"]

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
    lib.g_object_ref.argtypes = [ctypes.c_void_p]
    lib.g_object_ref.restype = ctypes.c_void_p
    lib.g_object_unref.argtypes = [ctypes.c_void_p]
    lib.g_object_unref.restype = None
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


class SharedPairSource:
    """Both cameras' images from a shared-memory frame block (``tools/fakegv --shm``).

    With a software trigger each camera's n-th fill answers the n-th trigger; whichever side
    fills frame n first takes a snapshot of the newest pair, the other side gets the same
    snapshot for its frame n, and the snapshot is dropped once both used it.

    A camera that missed a trigger (its n-th fill answers trigger n+1) would pair every later
    frame with the other side's previous trigger. It is noticed and realigned: when a side's
    frame-n snapshot is older than ``window_s`` while the other side's frame n+1 snapshot is
    fresh (taken within ``window_s``: the same trigger), this side skips to n+1 for good
    (``realigned``). A late fill (no fresh n+1 yet) still gets its own frame's snapshot.
    ``window_s`` must be shorter than the interval between two triggers (67 ms at 15 pairs/s).
    Snapshots older than ``keep`` frames are dropped (a side that stopped filling must not grow
    the table). Thread-safe.
    """

    def __init__(self, reader: FrameBlockReader, keep: int = 16, window_s: float = 0.05,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.reader = reader
        self.keep = keep
        self.window_s = window_s
        self._clock = clock
        self._lock = threading.Lock()
        self._pending: dict[int, tuple[float, SharedPair | None, str]] = {}  # key -> (t, pair, taker)
        self._offset = {"left": 0, "right": 0}
        self.served = {"left": 0, "right": 0}
        self.grey = 0  # frames served before any pair was written
        self.realigned = 0  # times a side skipped a frame number to get back in step

    def side(self, side: str) -> ImageSource:
        """The image source of one camera (``left`` / ``right``)."""
        return lambda n: self.image(side, n)

    def image(self, side: str, n: int) -> U8Image | None:
        with self._lock:
            now = self._clock()
            key = n + self._offset[side]
            entry, nxt = self._pending.get(key), self._pending.get(key + 1)
            if (entry is not None and entry[2] != side and now - entry[0] > self.window_s
                    and nxt is not None and nxt[2] != side and now - nxt[0] <= self.window_s):
                del self._pending[key]  # this side missed a trigger: skip to the other's next frame
                self._offset[side] += 1
                self.realigned += 1
                key, entry = key + 1, nxt
            if entry is None or entry[2] == side:
                snap = self.reader.read()
                self._pending[key] = (now, snap, side)
                for old in [k for k in self._pending if k < key - self.keep]:
                    del self._pending[old]
            else:
                snap = entry[1]
                del self._pending[key]  # both sides used it
            self.served[side] += 1
            if snap is None:
                self.grey += 1
                return None
            return snap.left if side == "left" else snap.right

    def reset(self) -> None:
        """Forget the snapshots and offsets (the cameras restarted: their counts start again at 0)."""
        with self._lock:
            self._pending.clear()
            self._offset = {"left": 0, "right": 0}


class FakeGvCamera:
    """One fake GigE Vision camera on ``address`` (GVCP port 3956) serving ``images`` in turn, or
    ``source(n)`` for its n-th frame.

    Args:
        address: an address of a local interface (127.0.0.1; a second camera needs a second
            address, e.g. 127.0.0.2 added to ``lo`` in a private network namespace).
        serial: serial number; the device id clients see is ``Aravis-Fake-<serial>``.
        images: HxW uint8 images served in turn.
        source: frame index -> image (instead of ``images``).
    """

    def __init__(self, address: str, serial: str, images: Sequence[U8Image] = (),
                 source: ImageSource | None = None) -> None:
        if not images and source is None:
            raise FakeGvError("no images to serve")
        for i, img in enumerate(images):
            if img.dtype != np.uint8 or img.ndim != 2:
                raise FakeGvError(f"image {i} must be HxW uint8 (mono), got {img.dtype} {img.shape}")
        self.address = address
        self.serial = serial
        self._images = [np.ascontiguousarray(img) for img in images]
        self._fitted: dict[tuple[int, int, int], U8Image] = {}
        self._source = source
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

    @property
    def running(self) -> bool:
        return self._gv is not None

    def stop(self) -> None:
        """Stop serving (drops the fake camera; its thread ends, its sockets close). ``start()``
        serves again on the same address, counting frames from 0."""
        gv, self._gv = self._gv, None
        if gv is not None:
            # The last unref finalises the fake camera: it joins its streaming thread, which may be
            # waiting for the GIL to run our fill callback. Take a C reference, drop Python's, and
            # release the C one through ctypes (which releases the GIL) -- no deadlock.
            address = gobject_pointer(gv)
            self._lib.g_object_ref(address)
            del gv
            self._lib.g_object_unref(address)
        with self._lock:
            self.frames_filled = 0

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
                index = self.frames_filled
                if self._source is None:
                    index %= len(self._images)
                self.frames_filled += 1
            if pixel_format == _MONO_8 and self._source is not None:
                src = self._source(index)
                if src is None:
                    ctypes.memset(dest, 128, width * height)
                    return
                if src.shape != (height, width):
                    src = fit_image(src, width, height)
                ctypes.memmove(dest, np.ascontiguousarray(src).ctypes.data, width * height)
            elif pixel_format == _MONO_8:
                img = self._image(index, width, height)
                ctypes.memmove(dest, img.ctypes.data, width * height)
            else:
                ctypes.memset(dest, 128, width * height)
        except Exception:  # noqa: BLE001 - an exception must not cross into C
            return
