"""The perception process with the real Aravis driver on two fake GigE cameras, in a private network
namespace, one process. Run by tests/cameras/test_perception_gige.py (as root):

    python tests/cameras/perception_gige_scenario.py WORKDIR

The camera run's mixed setup (``hil campaign --transport camera_stream_loss@...``: simulated world,
robot and tracker; the ``aravis`` camera on ``tools/fakegv`` serving the simulated camera's images)
with ``[perception] process = "on"``: the perception process builds and opens the Aravis cameras
itself, grabs, locates and publishes; this process takes the marker sets from shared memory, as
the controller does. The last stdout line is ``RESULT {json}``. Not collected by pytest.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT)]

from hil.campaign import gige  # noqa: E402
from hil.campaign.transport import BY_NAME, write_gige_setup  # noqa: E402
from hil.clock import MonotonicClock  # noqa: E402
from hil.config import build_devices, load_setup  # noqa: E402
from hil.controller.assembly import with_perception_process, with_servo_process  # noqa: E402
from hil.perception.camera import PerceptionCamera  # noqa: E402
from hil.servo.shm import ShmRegion  # noqa: E402

PAIRS = 12


def main(workdir: Path) -> dict[str, object]:
    gige.enter_private_netns()
    created: list[str] = []   # the shared-memory regions this process creates (servo, marker ring)
    real_create = ShmRegion.create

    def create(cls: type[ShmRegion], words: int) -> ShmRegion:
        region = real_create(words)
        created.append(str(region.name).lstrip("/"))
        return region

    ShmRegion.create = classmethod(create)  # type: ignore[method-assign, assignment]
    path = write_gige_setup(BY_NAME["camera_stream_loss@compensate"], workdir, seed=1)
    path.write_text(path.read_text() + '\n[servo]\nprocess = "on"\nrealtime = false\n'
                    '\n[perception]\nprocess = "on"\n')
    setup = load_setup(path)
    clock = MonotonicClock()
    devices = build_devices(setup, clock)
    rig = gige.GigeRig(workdir / "rig")
    out: dict[str, object] = {"camera_driver": str(setup.camera.driver)}
    with gige.gige_rig(rig, setup, devices, clock):
        devices = with_perception_process(setup, with_servo_process(setup, devices, clock), clock)
        camera = devices.camera
        assert isinstance(camera, PerceptionCamera)
        devices.open_all()
        try:
            feed = camera.perception_feed
            sets = []
            t_end = time.monotonic() + 30.0
            while len(sets) < PAIRS and time.monotonic() < t_end:
                got = feed.take(5.0)
                if got is not None:
                    sets.append(got)
            located = [s.located for s in sets]
            out.update({
                "pairs": len(sets),
                "errors": [repr(s.error) for s in sets if s.error is not None],
                "points": [0 if m is None else len(m.points_mm) for m in located],
                "markers_left": [0 if m is None or m.left_px is None else len(m.left_px) for m in located],
                "markers_right": [0 if m is None or m.right_px is None else len(m.right_px) for m in located],
                "frame_seqs": [0 if m is None else m.frame_seq for m in located],
                "locate_ms": feed.locate_figures(),
                "pid": feed.pid,
            })
        finally:
            devices.close_all()
    out["shm_created"] = created
    return out


if __name__ == "__main__":
    print("RESULT " + json.dumps(main(Path(sys.argv[1]))), flush=True)
