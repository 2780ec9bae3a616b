"""The shared regions: a setpoint read back exactly as written, the ring's newest and older
records, and no torn read while another process writes as fast as it can (the seqlock)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.servo.shm import (
    SETPOINT_WORDS,
    RingRecord,
    ServoMode,
    Setpoint,
    SetpointBlock,
    ShmRegion,
    StateRing,
    ring_words,
)

finite = st.floats(-1e6, 1e6, allow_nan=False)
vec3 = st.tuples(finite, finite, finite)
Vec3 = tuple[float, float, float]


@settings(max_examples=60, deadline=None)
@given(t=vec3, v=vec3, w=vec3, t_ref=st.integers(0, 2**62), scale=st.floats(0.0, 1.0),
       track_id=st.integers(1, 2**40))
def test_a_setpoint_reads_back_exactly(t: Vec3, v: Vec3, w: Vec3, t_ref: int, scale: float,
                                       track_id: int) -> None:
    block = SetpointBlock(ShmRegion.local(SETPOINT_WORDS))
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    block.write_track(track_id=track_id, R=R, t_mm=np.array(t), v_mm_s=np.array(v), w_rad_s=np.array(w),
                      t_ref_ns=t_ref, valid_until_ns=t_ref + 5, exposure_t_ns=t_ref - 7, frame_seq=3,
                      speed_scale=scale, max_horizon_s=0.15, lead_s=0.03)
    sp = block.read(Setpoint())
    assert sp.mode == ServoMode.TRACK
    assert sp.track_id == track_id
    assert (sp.t_ref_ns, sp.valid_until_ns) == (t_ref, t_ref + 5)
    assert (sp.exposure_t_ns, sp.frame_seq) == (t_ref - 7, 3)
    assert np.array_equal(sp.R, R)
    assert tuple(sp.t_mm) == t
    assert tuple(sp.v_mm_s) == v
    assert tuple(sp.w_rad_s) == w
    assert (sp.speed_scale, sp.max_horizon_s, sp.lead_s) == (scale, 0.15, 0.03)
    assert sp.seq % 2 == 0


def test_a_read_during_a_preempted_write_gives_up_and_leaves_the_copy_as_it_was() -> None:
    import time

    block = SetpointBlock(ShmRegion.local(SETPOINT_WORDS))
    block.write_track(track_id=4, R=np.eye(3), t_mm=np.array([1.0, 2.0, 3.0]),
                      v_mm_s=np.array([4.0, 5.0, 6.0]), w_rad_s=np.zeros(3), t_ref_ns=7, valid_until_ns=8,
                      exposure_t_ns=6, frame_seq=2,
                      speed_scale=1.0, max_horizon_s=0.1, lead_s=0.0)
    sp = block.read(Setpoint())
    assert sp is not None
    block._begin()                               # the writer stops half-way (preempted)
    block.region.f[20:26] = 99.0                 # the velocities already overwritten
    t0 = time.monotonic_ns()
    assert block.read(sp, max_wait_ns=2_000_000) is None
    assert time.monotonic_ns() - t0 >= 2_000_000  # it retried for the time it was given, no longer
    assert (sp.track_id, sp.t_ref_ns) == (4, 7)  # the last consistent copy, untouched
    assert tuple(sp.t_mm) == (1.0, 2.0, 3.0)
    assert tuple(sp.v_mm_s) == (4.0, 5.0, 6.0)
    block._end()
    got = block.read(sp)
    assert got is sp
    assert tuple(sp.v_mm_s) == (99.0, 99.0, 99.0)


def test_stop_requests_are_numbered() -> None:
    block = SetpointBlock(ShmRegion.local(SETPOINT_WORDS))
    assert block.write_mode(ServoMode.STOP) == 1
    assert block.write_mode(ServoMode.IDLE) == 1
    assert block.write_mode(ServoMode.STOP) == 2
    sp = block.read(Setpoint())
    assert (sp.mode, sp.stop_id) == (ServoMode.STOP, 2)


def test_the_ring_returns_the_newest_and_older_records_until_overwritten() -> None:
    ring = StateRing(ShmRegion.local(ring_words(8)), 8)
    rec = RingRecord()
    assert ring.read_latest(rec) is None
    for k in range(20):
        pose = np.zeros(12)
        pose[9] = k
        ring.write(t_ns=1000 + k, cmd_t_ns=0, safety_code=0, mode_code=1, period=k, servo_mode=0,
                   pose=pose, q_rad=np.full(6, float(k)), tcp_speed_mm_s=float(k))
    got = ring.read_latest(rec)
    assert got is not None
    assert (got.t_ns, got.period, got.pose[9], got.q_rad[0]) == (1019, 19, 19.0, 19.0)
    older = ring.read_back(3, RingRecord())
    assert older is not None
    assert older.period == 16
    assert ring.read_back(7, RingRecord()) is None   # the slot being written next: never handed out


_WRITER = textwrap.dedent("""
    import sys, numpy as np
    from hil.servo.shm import ShmRegion, SetpointBlock, SETPOINT_WORDS
    block = SetpointBlock(ShmRegion.attach(sys.argv[1], SETPOINT_WORDS))
    for k in range(1, 200001):
        x = float(k)
        block.write_track(track_id=k, R=np.eye(3) * 1.0, t_mm=np.array([x, x, x]), v_mm_s=np.array([x, x, x]),
                          w_rad_s=np.array([x, x, x]), t_ref_ns=k, valid_until_ns=k, exposure_t_ns=k,
                          frame_seq=k, speed_scale=x, max_horizon_s=x, lead_s=x)
""")


def test_no_torn_read_while_another_process_writes() -> None:
    region = ShmRegion.create(SETPOINT_WORDS)
    block = SetpointBlock(region)
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(region.name)])
    try:
        sp, reads, distinct = Setpoint(), 0, set()
        while proc.poll() is None or reads == 0:
            block.read(sp)
            reads += 1
            k = sp.track_id
            distinct.add(k)
            # every field of one write carries the same k: a torn read would mix two writes
            assert sp.t_ref_ns == sp.valid_until_ns == sp.exposure_t_ns == sp.frame_seq == k
            assert np.all(sp.t_mm == float(k))
            assert np.all(sp.v_mm_s == float(k))
            assert np.all(sp.w_rad_s == float(k))
            assert sp.speed_scale == sp.max_horizon_s == sp.lead_s == (float(k) if k else 0.0)
        assert proc.returncode == 0
        assert len(distinct) > 10   # the reads really interleaved with the writes
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        region.close()


_READ_AFTER_CLOSE = textwrap.dedent("""
    import os
    from hil.servo.link import Regions
    from hil.servo.shm import ShmRegion, _LINGERING
    regions = Regions.create(shared=True)
    names = regions.names()
    stats = regions.stats                      # a reader's view, as StatsEverySecond holds
    stats.c[3] = 7
    regions.close()                            # another thread closes them (ServoProcess.restart)
    assert tuple(int(x) for x in stats.c)[3] == 7, "the view no longer reads the segment"
    assert not any(os.path.exists("/dev/shm/" + str(n).lstrip("/")) for n in names), names
    assert len(_LINGERING) >= 1                # kept mapped for the view ...
    del stats, regions
    ShmRegion.create(1).close()                # ... and closed by a later close once free
    assert _LINGERING == [], _LINGERING
    attached = ShmRegion.create(4)
    other = ShmRegion.attach(str(attached.name), 4)
    view = other.i[1:3]
    other.close()
    assert int(view.sum()) == 0                # an attached mapping also outlives its close
    attached.close()
    print("ok")
""")


def test_a_view_held_past_close_still_reads_and_the_segment_is_unlinked() -> None:
    """Closing a region never unmaps memory a view still reads: a supervisor thread reading the
    loop statistics while ServoProcess.restart freed the old regions died of SIGSEGV (CI). Run in
    a child so that a regression is a failed test, not a dead test run."""
    proc = subprocess.run([sys.executable, "-c", _READ_AFTER_CLOSE], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.strip() == "ok"
    assert "Exception ignored" not in proc.stderr
