"""``tools/fakegv --shm`` against the real Aravis driver, in a private network namespace.

Run by tests/campaign/test_gige_campaign.py as ``python tests/campaign/gige_fakegv_scenario.py``
(as root): the process enters its own network namespace (``hil.campaign.gige.enter_private_netns``),
publishes numbered pairs into a shared-memory frame block from a thread (60 pairs/s, faster than
the triggers, so the newest pair changes between the two cameras' fills), serves them with
``python -m emulators.fakegv --shm NAME --right-address 127.0.0.2 --control PATH`` and grabs with
the real driver (software trigger, trigger-id pairing). Pair k carries k in its first pixels,
left and right differently shaded. The last stdout line is ``RESULT {json}``. Not collected.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tools")]

from drivers.camera.aravis import AravisStereoCamera  # noqa: E402
from drivers.camera.config import AravisCameraConfig  # noqa: E402
from drivers.interfaces.errors import DriverError  # noqa: E402
from hil.campaign.emulators import EmulatorError, start_fakegv  # noqa: E402
from hil.campaign.frameshm import FrameBlockWriter  # noqa: E402
from hil.campaign.gige import enter_private_netns, wait_for_cameras  # noqa: E402
from hil.clock import MonotonicClock  # noqa: E402
from hil.log import configure_logging  # noqa: E402

W, H = 640, 480


def pair_image(k: int, side: int) -> np.ndarray:
    """Pair k's image: a ramp shaded by side, pair number k (32 bit) in the first 4 pixels."""
    img = ((np.arange(W)[None, :] + np.arange(H)[:, None] + 40 * side) % 251).astype(np.uint8)
    img[0, :4] = np.frombuffer(np.uint32(k).tobytes(), dtype=np.uint8)
    return img


def pair_number(img: np.ndarray) -> int:
    return int(np.frombuffer(img[0, :4].tobytes(), dtype=np.uint32)[0])


def main() -> int:
    configure_logging(level="error")
    enter_private_netns()
    out: dict[str, Any] = {}
    writer = FrameBlockWriter(W * H)
    stop = threading.Event()

    published = [0]  # the newest pair number written (read by the grab loop)

    def publish() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            writer.write(pair_image(k, 0), pair_image(k, 1), t_ns=k)
            published[0] = k
            stop.wait(1 / 60)

    def wait_for_pair_after(k: int) -> None:
        """Until a pair newer than k is in the block (bounded): on a loaded machine the publisher
        can be starved for longer than a trigger period, and "fresh every trigger" is about the
        camera serving the newest pair, not about the publisher's scheduling."""
        deadline = time.monotonic() + 5.0
        while published[0] <= k and time.monotonic() < deadline:
            time.sleep(0.001)

    pump = threading.Thread(target=publish, daemon=True)
    pump.start()
    fake = start_fakegv(Path(sys.argv[1]), writer.name)
    try:
        out["cameras"] = fake.cameras
        wait_for_cameras({c["device_id"] for c in fake.cameras})
        cfg = AravisCameraConfig(driver="aravis", left_device_id="127.0.0.1", right_device_id="127.0.0.2",
                                 width_px=W, height_px=H, frame_rate_hz=30.0, trigger="software",
                                 packet_size_bytes=16000)
        cam = AravisStereoCamera("camera", cfg, MonotonicClock())
        cam.open()
        pairs = []
        last = 0
        for _ in range(20):  # ~15 pairs/s, as in the campaign (triggers farther apart than the window)
            t_next = time.monotonic() + 1 / 15
            wait_for_pair_after(last)
            pairs.append(cam.grab(2.0))
            last = pair_number(pairs[-1].left.image)
            time.sleep(max(0.0, t_next - time.monotonic()))
        out["numbers"] = [[pair_number(p.left.image), pair_number(p.right.image)] for p in pairs]
        out["whole"] = all(np.array_equal(p.left.image, pair_image(pair_number(p.left.image), 0))
                           and np.array_equal(p.right.image, pair_image(pair_number(p.right.image), 1))
                           for p in pairs)
        out["seq"] = [[p.left.seq, p.right.seq] for p in pairs]
        out["status_before"] = fake.status()
        for line in ("help", "bogus 1", "stream_loss abc", "stream_loss 0"):
            try:
                out[line] = fake.command(line)
            except EmulatorError as exc:
                out[line] = f"EmulatorError: {exc}"
        out["stream_loss"] = fake.command("stream_loss 1.0")
        out["status_during"] = fake.status()
        # grab through the loss until pairs come again (bounded)
        t0 = time.monotonic()
        errors: list[str] = []
        back: list[list[int]] = []
        while time.monotonic() - t0 < 20 and len(back) < 5:
            try:
                p = cam.grab(0.5)
                back.append([pair_number(p.left.image), pair_number(p.right.image)])
            except DriverError as exc:
                errors.append(type(exc).__name__)
        out["loss_errors"] = sorted(set(errors))
        out["after_loss"] = back
        out["recovered_s"] = time.monotonic() - t0
        out["stats"] = cam.stats
        out["status_after"] = fake.status()
        cam.close()
    finally:
        fake.stop()
        stop.set()
        pump.join()
        writer.close()
    out["fakegv_rc"] = fake.proc.returncode
    print("RESULT " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
