"""6-DOF pose tracker interface (the magnetic tracker)."""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass

from drivers.interfaces.lifecycle import Device
from hil.geometry.transform import RigidTransform


@dataclass(frozen=True)
class TrackerSample:
    """The latest pose of one sensor.

    Attributes:
        sensor: sensor/port name as configured (e.g. ``reference``, ``stylus``, ``needle``).
        T_tracker_from_sensor: pose in the transmitter frame (mm); None when ``missing``.
        quality: device error/quality figure (lower is better; device-specific scale, e.g. NDI
            RMS error in mm); None when the device gives none.
        t_ns: host monotonic time the sample was received (or device frame time mapped to it).
        seq: device frame number when the device has one, else a host counter.
        missing: the sensor is not seen / out of volume / disabled: no pose.
        flags: device status words in plain words (``out_of_volume``, ``partially_out`` …).
    """

    sensor: str
    T_tracker_from_sensor: RigidTransform | None
    quality: float | None
    t_ns: int
    seq: int
    missing: bool = False
    flags: tuple[str, ...] = ()


class PoseTracker(Device):
    """A tracker of 6-DOF sensors. A sensor: it has no command that moves anything."""

    kind = "tracker"

    @abstractmethod
    def latest(self) -> dict[str, TrackerSample]:
        """The newest sample per configured sensor, without blocking.

        Raises:
            LifecycleError: not active.
            DeviceTimeoutError: no valid record for longer than the driver's timeout.
            ProtocolError: the stream is corrupt beyond resynchronisation.
        """

    @property
    @abstractmethod
    def sensors(self) -> tuple[str, ...]:
        """Configured sensor names."""
