"""Fixtures for the tracker tests: in-process emulators on real pseudo-terminals.

The emulator package lives in ``tools/`` (``tools/trackersim``), so ``tools`` goes on sys.path.
The drivers talk to the emulators through the real pyserial on the pty's slave side.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[2] / "tools"
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))

from emulators.trackersim.aurora_device import AuroraDevice  # noqa: E402
from emulators.trackersim.faults import Faults  # noqa: E402
from emulators.trackersim.fob_device import FobDevice  # noqa: E402
from emulators.trackersim.poses import PoseSource, StaticPoses  # noqa: E402
from emulators.trackersim.pty_link import PtyLink  # noqa: E402


def wait_until(predicate: Callable[[], bool], timeout_s: float = 10.0, what: str = "condition") -> None:
    """Poll ``predicate`` until true (real I/O with the emulator; no timing is asserted)."""
    deadline = time.monotonic() + timeout_s
    ev = threading.Event()
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        ev.wait(0.005)


FobFactory = Callable[..., FobDevice]
AuroraFactory = Callable[..., AuroraDevice]


@pytest.fixture
def fob_emulator() -> Iterator[FobFactory]:
    started: list[FobDevice] = []

    def make(*, n_birds: int = 1, baud: int = 115200, poses: PoseSource | None = None,
             rate_hz: float = 100.0) -> FobDevice:
        link = PtyLink()
        order = ("0",) if n_birds == 1 else tuple(str(a) for a in range(1, n_birds + 1))
        dev = FobDevice(link, poses or StaticPoses(order=order), Faults(seed=7), baud=baud,
                        n_birds=n_birds, rate_hz=rate_hz)
        dev.start()
        started.append(dev)
        return dev

    yield make
    for dev in started:
        dev.stop()


@pytest.fixture
def aurora_emulator() -> Iterator[AuroraFactory]:
    started: list[AuroraDevice] = []

    def make(*, n_tools: int = 2, poses: PoseSource | None = None,
             frame_rate_hz: float = 40.0) -> AuroraDevice:
        link = PtyLink()
        order = tuple(f"{0x0A + i:02X}" for i in range(n_tools))
        dev = AuroraDevice(link, poses or StaticPoses(order=order, default_mm=(0.0, 0.0, -250.0),
                                                      spacing_mm=(40.0, 0.0, 0.0)),
                           Faults(seed=7), n_tools=n_tools, frame_rate_hz=frame_rate_hz)
        dev.start()
        started.append(dev)
        return dev

    yield make
    for dev in started:
        dev.stop()
