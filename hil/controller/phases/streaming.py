"""The in-process servo loop of a simulated run, stepped by the phase that commands it (APPROACH
and RETRACT while moving, COMPENSATE while tracking, LOCK while holding) between two stereo
pairs. The servo process needs none of
this: its loop runs on its own clock."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from hil.controller import events as ev
from hil.controller.deadline import DeadlineTimer

if TYPE_CHECKING:
    from drivers.interfaces.camera import StereoFrame
    from hil.controller.inputs import TickInputs
    from hil.controller.phases.base import PhaseContext, PhaseResult


def stream_until_next_pair(ctx: PhaseContext, frame: StereoFrame, now_ns: int, t_send_ns: int,
                           step: Callable[[int], None]) -> None:
    """Step the in-process servo loop at the robot's rate from ``t_send_ns`` until the next pair
    is due, on absolute deadlines one period apart (a slot missed by more than a period is
    skipped, counted in ``ctx.servo_deadlines_missed`` and logged ``servo_deadline_missed``).

    ``now_ns`` is the tick's time and ``frame`` its pair (controller clock). Without a
    prefetcher the next grab blocks this thread, so the stream stops half a period before the
    pair is due; with one it streams until the prefetcher has the next pair (or its error)
    ready, capped, and never on a pair the camera watchdog would call stale, so the tick judges
    a missing or late pair as it would without the prefetcher. Blocks for that time."""
    servo_dt = 1.0 / ctx.robot.control_rate_hz
    timer = DeadlineTimer(ctx.clock, servo_dt)
    timer.start(t_send_ns)
    half_ns = timer.period_ns // 2
    step(t_send_ns)
    timing = ctx.servo_timing()
    ready = timing.next_pair_ready
    if ready is None:
        next_ready_ns = now_ns + round(ctx.frame_period_s * 1e9)

        def more() -> bool:
            return max(timer.next_ns(), ctx.clock.now_ns()) + half_ns <= next_ready_ns
    else:
        cap_ns = min(now_ns + round((2 * ctx.frame_period_s + timing.grab_timeout_s) * 1e9),
                     frame.left.t_ns + round(timing.camera_max_age_s * 1e9))

        def more() -> bool:
            return not ready() and max(timer.next_ns(), ctx.clock.now_ns()) <= cap_ns
    while more():
        skipped = timer.wait()
        if skipped:
            ctx.servo_deadlines_missed += 1
            ctx.session.write(ev.SERVO_DEADLINE_MISSED, slots_skipped=skipped, period_s=servo_dt)
        step(ctx.clock.now_ns())


def judge_then_stream(ctx: PhaseContext, inputs: TickInputs, judge: Callable[[], PhaseResult]) -> PhaseResult:
    """A holding or moving phase's step: ``judge`` the pair, then (in-process loop, and the
    phase fired no event) stream the loop from the step's start until the next pair is due."""
    now = ctx.clock.now_ns()
    out = judge()
    if ctx.step_servo is not None and not out.events:
        stream_until_next_pair(ctx, inputs.frame, now, now, ctx.step_servo)
    return out
