"""What the built-in plugin registers for the real stereo cameras: the driver factories and the
``hil probe`` device checks.

The top of the package: it imports the configs (:mod:`drivers.camera.config`, a leaf) and builds
the devices CONFIGURED (not opened). The driver modules are imported when a device is built, so a
setup without Aravis does not need PyGObject.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.camera.config import AravisCameraConfig, ReplayCameraConfig, V4l2CameraConfig
from plugins.registry import DriverContext

if TYPE_CHECKING:
    from drivers.camera.aravis import AravisStereoCamera
    from drivers.camera.replay import ReplayStereoCamera
    from drivers.camera.v4l2 import V4l2StereoCamera
    from hil.probe.registry import ProbeRegistry

__all__ = ["AravisCameraConfig", "ReplayCameraConfig", "V4l2CameraConfig", "aravis_factory",
           "register_probes", "replay_factory", "v4l2_factory"]


def aravis_factory(config: AravisCameraConfig, ctx: DriverContext) -> AravisStereoCamera:
    """Registered as camera driver ``aravis``: two GigE Vision / USB3 Vision cameras."""
    from drivers.camera.aravis import AravisStereoCamera

    return AravisStereoCamera(ctx.role, config, ctx.clock)


def v4l2_factory(config: V4l2CameraConfig, ctx: DriverContext) -> V4l2StereoCamera:
    """Registered as camera driver ``v4l2``: two V4L2 (UVC) cameras, or one side-by-side device."""
    from drivers.camera.v4l2 import V4l2StereoCamera

    return V4l2StereoCamera(ctx.role, config, ctx.clock)


def replay_factory(config: ReplayCameraConfig, ctx: DriverContext) -> ReplayStereoCamera:
    """Registered as camera driver ``replay``: a recording (``recording_dir`` relative to the
    setup file's directory unless absolute)."""
    from drivers.camera.replay import ReplayStereoCamera

    path = config.recording_dir
    if not path.is_absolute():
        path = ctx.config_dir / path
    return ReplayStereoCamera(ctx.role, path, ctx.clock, speed=config.speed, loop=config.loop)


def register_probes(registry: ProbeRegistry) -> None:
    """The ``hil probe`` device checks of the three cameras (called by the built-in plugin's
    ``hil_register_probes``): are the devices (or the recording) there?"""
    from drivers.camera.probe import probe_aravis, probe_replay, probe_v4l2

    registry.add("camera", "aravis", probe_aravis)
    registry.add("camera", "v4l2", probe_v4l2)
    registry.add("camera", "replay", probe_replay)
