"""The rig of the camera scenario of the transport tier: camera stream loss over GigE Vision.

The controller runs the whole procedure with the REAL Aravis driver receiving the SIMULATED world
over real GVCP/GVSP on loopback (docs/campaign.md, "Camera stream loss over GigE Vision"):

    simulated world -> simulated camera (pump thread) -> shared-memory frame block
      -> tools/fakegv --shm (two fake GigE cameras, 127.0.0.1 and 127.0.0.2) -> GVSP
      -> Aravis driver (software trigger, trigger-id pairing) -> controller

Everything lives in the run's process (spawned by the pool), which first enters a **private
network namespace** (the second camera needs 127.0.0.2 on ``lo``; GVCP's port 3956 is fixed): so
the fake cameras are started by the run itself, not by the campaign's parent. The simulated camera
is built through the driver registry from ``configs/sim.toml``'s ``[camera]`` on the world that
``build_devices`` made for the mixed setup (simulated robot and tracker); the core never imports
a driver. The fault is a real stream loss: ``stream_loss S`` on the fake cameras' control channel
stops both cameras and starts them again S seconds later on the same addresses.

This module is the rig only (namespace, frame pump, fake cameras, the ``[camera]`` section); the
camera run itself (:func:`hil.campaign.transport.run_gige_one`) is one of the transport tier's
runs, so the dependency goes one way: ``transport`` -> ``gige``.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from drivers.interfaces.camera import StereoCamera
from drivers.interfaces.errors import DriverError
from hil.clock import Clock
from hil.config import Devices, load_setup
from hil.config.setup import SetupConfig
from hil.log import get_logger
from hil.vision.camera_model import load_calibration
from plugins.registry import DriverContext

from .emulators import CONFIGS_DIR, EmulatorError, FakeGv, start_fakegv
from .frameshm import FrameBlockError, FrameBlockWriter

_log = get_logger(__name__)

CLONE_NEWNET = 0x40000000
LEFT_ADDRESS = "127.0.0.1"
RIGHT_ADDRESS = "127.0.0.2"
#: The setup whose ``[camera]`` (simulated) renders the world the fake cameras serve.
SIM_CAMERA_SETUP = CONFIGS_DIR / "sim.toml"
#: Bound on waiting for both fake cameras to be discoverable (s).
DISCOVERY_TIMEOUT_S = 15.0
#: GVSP packet size on loopback (bytes; lo's MTU is 64 KiB): ~130 packets per 1920x1080 frame
#: instead of ~1400 at 1500 bytes -- p99 pair latency 59 ms instead of 129 ms on the loaded
#: 2-core machine (software trigger, 15 Hz).
GIGE_PACKET_SIZE_BYTES = 16000
#: Extra wait before the operator recovers (s): the driver sees the loss ~1.5 s after the onset
#: (a GVCP command retried to a silent camera, then its heartbeat fails), after the cameras came
#: back, and reconnects in the background (~0.3 s).
GIGE_RECOVER_EXTRA_S = 2.0


def why_not_runnable() -> str | None:
    """Why the camera scenario cannot run here (one line), or None."""
    if os.geteuid() != 0:
        return "the camera scenario needs a private network namespace (unshare(CLONE_NEWNET)): run as root"
    if shutil.which("ip") is None:
        return "iproute2 ('ip') is missing: tools/setup_aravis.sh installs it"
    return aravis_missing()


def aravis_missing() -> str | None:
    """Why Aravis 0.8 cannot be imported here through PyGObject (one line), or None."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as exc:
        return f"Aravis is not available ({exc}): run tools/setup_aravis.sh as root"
    return None


def enter_private_netns() -> None:
    """Move this process into a new network namespace with ``lo`` up and 127.0.0.2 on it.

    Call it first in the run's process, before any Aravis object or thread exists. Children
    started later inherit the namespace.

    Raises:
        EmulatorError: not allowed (not root) or ``ip`` failed; one line naming why.
    """
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.unshare(CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise EmulatorError(f"cannot enter a private network namespace (unshare(CLONE_NEWNET): "
                            f"{os.strerror(err)}); the camera scenario needs root")
    for cmd in (["ip", "link", "set", "lo", "up"], ["ip", "addr", "add", f"{RIGHT_ADDRESS}/8", "dev", "lo"]):
        try:
            subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError) as exc:
            detail = getattr(exc, "stderr", "") or exc
            raise EmulatorError(f"network namespace set-up: {' '.join(cmd)}: {str(detail).strip()}") from exc


def wait_for_cameras(device_ids: set[str], timeout_s: float = DISCOVERY_TIMEOUT_S) -> None:
    """Block until Aravis discovers every id in ``device_ids`` (~1 s per round).

    Raises:
        EmulatorError: not all found within ``timeout_s`` (names the missing ones).
    """
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    deadline = time.monotonic() + timeout_s
    while True:
        Aravis.update_device_list()
        found = {Aravis.get_device_id(i) for i in range(Aravis.get_n_devices())}
        if device_ids <= found:
            return
        if time.monotonic() > deadline:
            raise EmulatorError(f"fake GigE cameras {sorted(device_ids - found)} not discovered in "
                                f"{timeout_s:g} s (found {sorted(found)})")
        time.sleep(0.1)


# ---------------------------------------------------------------------- world -> shared memory
@dataclass
class FramePump:
    """A thread grabbing pairs from the simulated ``camera`` (its own pace: it blocks until each
    frame is due) and publishing each into ``writer``. Grab errors are counted, never raised."""

    camera: StereoCamera
    writer: FrameBlockWriter
    errors: int = 0
    last_error: str = ""
    _stop: threading.Event = field(default_factory=threading.Event)
    _first: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="gige-frame-pump", daemon=True)
        self._thread.start()

    def wait_first(self, timeout_s: float) -> None:
        """Block until the first pair is published.

        Raises:
            EmulatorError: none within ``timeout_s``.
        """
        if not self._first.wait(timeout_s):
            raise EmulatorError(f"the simulated camera published no pair in {timeout_s:g} s "
                                f"({self.last_error or 'no error'})")

    def _run(self) -> None:
        period_s = 1.0 / self.camera.frame_rate_hz
        while not self._stop.is_set():
            try:
                pair = self.camera.grab(timeout_s=max(4 * period_s, 1.0))
                self.writer.write(pair.left.image, pair.right.image, pair.left.t_ns)
                self._first.set()
            except (DriverError, FrameBlockError) as exc:
                self.errors += 1
                self.last_error = str(exc)
                self._stop.wait(period_s)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)


def build_sim_camera(setup: SetupConfig, devices: Devices, clock: Clock) -> StereoCamera:
    """The simulated camera of :data:`SIM_CAMERA_SETUP` (``[camera] driver = "sim"``) on the world
    of ``devices`` (built from the mixed setup), through the driver registry. CONFIGURED.

    Raises:
        EmulatorError: the mixed setup has no simulated world, or the factory made no camera.
    """
    from plugins.manager import default_registry

    if devices.world is None:
        raise EmulatorError("the camera scenario's setup built no simulated world")
    base = load_setup(SIM_CAMERA_SETUP)
    info = default_registry().get("camera", str(base.camera.driver))
    ctx = DriverContext(role="sim_camera", clock=clock, limits=setup.safety.motion_limits(),
                        config_dir=base.config_dir, world=devices.world,
                        calibration_path=setup.calibration.stereo)
    camera = info.factory(base.camera, ctx)
    if not isinstance(camera, StereoCamera):
        raise EmulatorError(f"camera driver {info.name!r} built a {type(camera).__name__}, not a camera")
    return camera


@dataclass
class GigeRig:
    """What a camera run starts around the controller; ``fakegv`` once :func:`gige_rig` runs."""

    run_dir: Path
    fakegv: FakeGv | None = None

    def send(self, line: str) -> str:
        """A line on the fake cameras' control channel (the fault channel of the scenario)."""
        if self.fakegv is None:
            raise EmulatorError("fakegv is not running")
        return self.fakegv.command(line)


@contextlib.contextmanager
def gige_rig(rig: GigeRig, setup: SetupConfig, devices: Devices, clock: Clock) -> Iterator[None]:
    """Simulated camera + pump -> frame block -> fakegv, until the block exits; yields once both
    fake cameras are discoverable (the Aravis driver of ``devices`` can then be opened).

    Raises:
        EmulatorError: the simulated camera, the frame block or fakegv did not come up.
    """
    rig.run_dir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        sim_camera = build_sim_camera(setup, devices, clock)
        sim_camera.open()
        stack.callback(sim_camera.close)
        width, height = sim_camera.image_size
        try:
            writer = FrameBlockWriter(width * height)
        except FrameBlockError as exc:
            raise EmulatorError(str(exc)) from exc
        stack.callback(writer.close)
        pump = FramePump(sim_camera, writer)
        pump.start()
        stack.callback(pump.stop)
        pump.wait_first(10.0)
        rig.fakegv = start_fakegv(rig.run_dir, writer.name, left=LEFT_ADDRESS, right=RIGHT_ADDRESS)
        stack.callback(rig.fakegv.stop)
        wait_for_cameras({c["device_id"] for c in rig.fakegv.cameras})
        _log.info("gige_rig_ready", shm=writer.name, cameras=[c["device_id"] for c in rig.fakegv.cameras])
        yield
        with contextlib.suppress(EmulatorError):
            _log.info("gige_rig_status", pump_errors=pump.errors, **rig.fakegv.status())


# ---------------------------------------------------------------------- setup and operator
def aravis_camera_section(setup: SetupConfig) -> str:
    """The ``[camera]`` TOML section of the mixed setup: the Aravis driver on both fake cameras,
    software trigger, trigger-id pairing, the size of the setup's calibration, the simulated
    camera's frame rate."""
    base = load_setup(SIM_CAMERA_SETUP)
    cal = load_calibration(setup.calibration.stereo) if setup.calibration.stereo is not None else None
    if cal is None:
        raise EmulatorError("the camera scenario needs [calibration] stereo (the image size)")
    width, height = cal.image_size
    rate_hz = float(getattr(base.camera, "frame_rate_hz", 15.0))
    return (f'[camera]\ndriver = "aravis"\nleft_device_id = "{LEFT_ADDRESS}"\n'
            f'right_device_id = "{RIGHT_ADDRESS}"\nwidth_px = {width}\nheight_px = {height}\n'
            f'frame_rate_hz = {rate_hz}\ntrigger = "software"\npairing = "trigger_id"\n'
            f"packet_size_bytes = {GIGE_PACKET_SIZE_BYTES}\n\n")
