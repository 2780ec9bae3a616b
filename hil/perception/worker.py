"""The perception process's main (child side; see :mod:`hil.perception.process`).

Threads: the main thread grabs, locates and publishes; a channel thread receives ``close`` and
breath-hold relays (and ends the loop when the channel ends: the supervisor is gone).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
import traceback
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from drivers.interfaces.camera import FrameTime, StereoCamera, StereoFrame
from drivers.interfaces.errors import DriverError
from hil.clock import MonotonicClock
from hil.geometry.transform import RigidTransform
from hil.heap import HeapTrimmer, use_one_arena
from hil.perception.follow import FollowingWorld, RingFlangeSource
from hil.perception.process import PerceptionSpec
from hil.perception.ring import MarkerRing, RecordKind, ring_words
from hil.servo.shm import ShmRegion
from hil.servo.wire import error_to_wire

_SOURCES = tuple(FrameTime)


def perception_main(conn: Connection, notify_fd: int, parent_pid: int) -> None:
    """The perception process (module doc): receives ``(spec, ring name)`` first, builds and
    opens the camera, reports ``ready`` (or ``failed`` with the driver error), then publishes
    until closed or orphaned. A crash reports its traceback and exits with code 1."""
    use_one_arena()   # before any thread: its frees must stay trimmable (hil/heap.py)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from hil.log import configure_logging

    configure_logging(level="warning")
    os.set_blocking(notify_fd, False)
    spec, ring_name = conn.recv()
    closing = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: closing.set())
    region = ShmRegion.attach(ring_name, ring_words())
    ring = MarkerRing(region)
    cpus = _place(spec)
    send_lock = threading.Lock()

    def send(msg: Any) -> None:
        with send_lock, contextlib.suppress(OSError, ValueError):
            conn.send(msg)

    try:
        camera, locate, world, follower = _build(spec)
        camera.open()
        opened_ns = time.monotonic_ns()   # a fault schedule's origin (drivers/faults.py), system-wide
    except DriverError as exc:
        send(("failed", error_to_wire(exc)))
        region.close()
        return
    except Exception as exc:  # noqa: BLE001 - a config the parent validated; report, never hang it
        send(("failed", ("DeviceFaultError", "camera", f"{type(exc).__name__}: {exc}")))
        region.close()
        return
    channel = threading.Thread(target=_serve, args=(conn, world, follower, closing),
                               name="perception-channel", daemon=True)
    channel.start()
    send(("ready", {"camera_name": camera.name, "pid": os.getpid(), "cpus": sorted(cpus),
                    "opened_ns": opened_ns}))
    try:
        _run(camera, locate, ring, notify_fd, parent_pid, closing,
             HeapTrimmer(spec.setup.procedure.heap_trim_every_s))
    except BaseException:  # noqa: BLE001 - a crash: say why, exit non-zero
        send(("crashed", traceback.format_exc(limit=6)))
        with contextlib.suppress(Exception):
            camera.close()
        os._exit(1)
    camera.close()
    if follower is not None:
        follower.close()
    region.close()


#: The fewest CPUs the perception process is left when it keeps off the servo loop's CPU.
MIN_CPUS_OFF_SERVO = 2


def _place(spec: PerceptionSpec) -> set[int]:
    """Keep the process on ``spec.cpu`` when given; else off the servo loop's CPU (when that loop
    asks for real time) provided :data:`MIN_CPUS_OFF_SERVO` CPUs remain. The process starts on the
    supervisor's CPUs: with ``[servo] reserve_cpu`` (the default) the supervisor already keeps off
    a pinned loop's CPU (:mod:`hil.servo.reserve`), so on a two-CPU machine both share the other
    one; without it this process may use both there. Returns the CPUs."""
    from hil.servo.rt import default_cpu

    cpus = os.sched_getaffinity(0)
    servo = spec.setup.servo
    if spec.cpu is not None:
        want = {spec.cpu} & cpus
    elif servo.realtime and len(cpus) > MIN_CPUS_OFF_SERVO:
        want = cpus - {default_cpu() if servo.cpu is None else servo.cpu}
    else:
        want = cpus
    if want and want != cpus:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, want)
            return want
    return cpus


def _build(spec: PerceptionSpec) -> tuple[StereoCamera, Any, FollowingWorld | None, RingFlangeSource | None]:
    """The camera (rig time offsets applied), the locator, the world and its flange source."""
    from hil.config.build import build_devices  # the registry, in the child only
    from hil.controller.assembly import marker_locator
    from hil.rigcal.apply import with_rig_time_offsets

    clock = MonotonicClock()
    devices = build_devices(spec.setup, clock)
    world = devices.world if isinstance(devices.world, FollowingWorld) else None
    follower = None
    if world is not None:
        if spec.world_t0_ns is not None:
            world.t0_ns = spec.world_t0_ns
        if spec.servo_ring is not None and spec.T_flange_from_tcp is not None:
            follower = RingFlangeSource(spec.servo_ring,
                                        RigidTransform.from_matrix(np.asarray(spec.T_flange_from_tcp)))
            world.attach_robot(follower)
            devices.robot.close()   # never opened here; ends a pose follower the builder started
    if devices.tracker is not None:
        devices.tracker.close()     # never opened here
    camera = with_rig_time_offsets(spec.setup, devices).camera
    return camera, marker_locator(spec.setup, camera), world, follower


def _run(camera: StereoCamera, locate: Any, ring: MarkerRing, notify_fd: int, parent_pid: int,
         closing: threading.Event, heap: HeapTrimmer) -> None:
    """Grab, locate and publish until closed or orphaned; after each pair's notification the
    heap policy (hil/heap.py: this process renders and searches whole images; its cycles are
    collected each period from the first pair on, until the process exits)."""
    from hil.controller.located import locate_in

    timeout_s = max(4.0 / camera.frame_rate_hz, 0.2)
    clock = MonotonicClock()
    pair_seq = 0
    heap.start()   # this process's objects so far frozen, cycles collected each period (hil/heap.py)
    while not closing.is_set() and os.getppid() == parent_pid:
        try:
            frame = camera.grab(timeout_s=timeout_s)
        except DriverError as exc:
            pair_seq += 1
            ring.write_error(RecordKind.GRAB_ERROR, pair_seq, error_to_wire(exc), clock.now_ns())
            _notify(notify_fd)
            closing.wait(timeout_s)   # a dead stream does not spin
            continue
        done_ns = clock.now_ns()
        pair_seq += 1
        t0 = time.perf_counter_ns()
        try:
            found = locate_in(locate, frame)
            _publish(ring, pair_seq, frame, found, done_ns, (time.perf_counter_ns() - t0) * 1e-6)
        except Exception as exc:  # noqa: BLE001 - raised in the supervisor where it perceives
            ring.write_error(RecordKind.LOCATE_ERROR, pair_seq, (type(exc).__name__, camera.name, str(exc)),
                             done_ns)
        _notify(notify_fd)
        heap.after_tick(clock.now_ns())


def _publish(ring: MarkerRing, pair_seq: int, frame: StereoFrame, found: Any, done_ns: int,
             locate_ms: float) -> None:
    l, r = frame.left, frame.right
    h, w = l.image.shape[:2]
    ring.write_markers(pair_seq=pair_seq, left=(l.seq, l.t_ns, l.device_t_ns),
                       right=(r.seq, r.t_ns, r.device_t_ns), time_source=_SOURCES.index(l.time_source),
                       grab_done_t_ns=done_ns, locate_ms=locate_ms, image_size=(int(w), int(h)),
                       points_mm=found.points_mm, left_px=found.left_px, right_px=found.right_px)


def _notify(fd: int) -> None:
    """One byte down the pipe (a full pipe: the parent is not reading; the ring has the record)."""
    with contextlib.suppress(BlockingIOError, BrokenPipeError, OSError):
        os.write(fd, b"\x01")


def _serve(conn: Connection, world: FollowingWorld | None, follower: RingFlangeSource | None,
           closing: threading.Event) -> None:
    """The channel thread: ``close``, breath-hold relays, the ring a restarted servo process
    records the arm in; the channel's end ends the loop."""
    try:
        while not closing.is_set():
            msg = conn.recv()
            if msg[0] == "close":
                break
            if msg[0] == "hold" and world is not None:
                _, start_s, duration_s, level = msg
                world.request_breath_hold(duration_s, level, delay_s=start_s - world.now_s())
            elif msg[0] == "follow" and follower is not None:
                follower.follow(msg[1])
    except (EOFError, OSError):
        pass   # the supervisor is gone
    finally:
        closing.set()
