"""What every phase is given and returns.

A phase is one state of the procedure's forward path. The controller calls :meth:`Phase.enter`
when the state machine enters its state and :meth:`Phase.step` once per stereo pair while it is
current. Both return a :class:`PhaseResult`: the commands for the robot (executed by the
controller, in order, through the safety layer) and the events for the state machine (queued and
processed in order after the commands, never fired from inside a phase). A phase keeps its
scratch data in its own dataclass, reset on every entry, and exposes its sub-state as an enum
value (shown in the controller snapshot).

A phase reads and updates the :class:`~hil.controller.estimate.Estimate`; it never touches a
device except through what :class:`PhaseContext` offers (the robot's state read on entry, the
servo stream's command sink in COMPENSATE).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, ClassVar

from drivers.interfaces.robot import Robot
from hil.clock import Clock
from hil.controller.commands import Command
from hil.controller.config import ProcedureConfig
from hil.controller.cost import CostHistogram
from hil.controller.estimate import Estimate
from hil.controller.fsm import Event, State
from hil.controller.needle import NeedleCheck
from hil.controller.series import SampleSeries
from hil.controller.tracker_roles import TrackerRoles
from hil.controller.truth import BreathHoldCoach
from hil.safety.layer import SafetyLayer
from hil.session.log import SessionLog

if TYPE_CHECKING:
    from hil.controller.inputs import TickInputs


@dataclass
class PhaseResult:
    """Commands to execute, then events to process (each ``(event, reason)``)."""

    commands: list[Command] = field(default_factory=list)
    events: list[tuple[Event, str]] = field(default_factory=list)

    def fire(self, event: Event, reason: str = "") -> PhaseResult:
        self.events.append((event, reason))
        return self

    def command(self, cmd: Command) -> PhaseResult:
        self.commands.append(cmd)
        return self


@dataclass
class ServoTiming:
    """What COMPENSATE's servo stream needs to know of the camera pipeline (read each step).

    ``next_pair_ready``: None without a prefetcher (the next grab then blocks the control
    thread), else whether the prefetcher has the next pair (or its error) ready.
    ``grab_timeout_s``: how long a grab may block. ``camera_max_age_s``: the camera watchdog's
    bound (a stream never runs on a pair it would call stale).
    """

    next_pair_ready: Callable[[], bool] | None
    grab_timeout_s: float
    camera_max_age_s: float


@dataclass
class PhaseContext:
    """The procedure's parts a phase may use (module doc). ``execute`` runs one command at once
    (COMPENSATE's sub-frame servo stream; other phases return their commands).
    ``pending`` names the confirmation the state machine waits for, if any."""

    cfg: ProcedureConfig
    est: Estimate
    clock: Clock
    session: SessionLog
    safety: SafetyLayer
    robot: Robot
    roles: TrackerRoles
    needle: NeedleCheck
    coach: BreathHoldCoach | None
    frame_period_s: float
    pending: Callable[[], str | None]
    execute: Callable[[Command], None]
    servo_timing: Callable[[], ServoTiming]
    #: steps the in-process servo loop at a time, ns (None: the servo process runs its own loop)
    step_servo: Callable[[int], None] | None = None
    #: latency of each frame's setpoint (exposure -> setpoint published), ms
    latency_ms: SampleSeries = field(default_factory=SampleSeries)
    #: COMPENSATE's setpoint work per pair (the predictor's update, then the setpoint), µs
    setpoint_cost: CostHistogram = field(default_factory=CostHistogram)
    #: per pair, its change estimate (the estimator and the target model) and its setpoint work
    #: added: what the three parts together put on the frame -> command path, µs
    pair_model_cost: CostHistogram = field(default_factory=CostHistogram)
    servo_deadlines_missed: int = 0


class Phase:
    """Base of the phases: its state, entry time and sub-state."""

    state: ClassVar[State]

    def __init__(self, ctx: PhaseContext) -> None:
        self.ctx = ctx
        self.entered_ns = 0
        self.resumed = False

    @property
    def sub_state(self) -> Enum | None:
        """The phase's sub-state (None when it has none)."""
        return None

    def elapsed_s(self) -> float:
        """Seconds on the controller clock since this phase was entered."""
        return (self.ctx.clock.now_ns() - self.entered_ns) * 1e-9

    def enter(self, now_ns: int, transition: str, resumed: bool) -> PhaseResult:
        """Start the phase afresh (scratch reset); returns the entry action's commands."""
        self.entered_ns, self.resumed = now_ns, resumed
        return self.on_enter(transition)

    def on_enter(self, transition: str) -> PhaseResult:
        return PhaseResult()

    def command(self, inputs: TickInputs, flange: Callable[[], None]) -> None:
        """The latency-critical part of a pair, before the tick's slower supervision and records:
        a phase that streams a setpoint per pair publishes it here (COMPENSATE). It fires
        nothing: whatever it cannot decide is left to :meth:`step`, which the tick calls after it
        for the same pair unless the pair faulted meanwhile. ``inputs.tracker`` may still hold
        the previous read's samples here (the tracker is read after it unless its samples take
        part in the markers); :meth:`step` gets this pair's. The estimate's flange markers are
        the previous pair's until ``flange()`` brings this pair's in (once; the tick calls it
        after this returns): a command that uses them calls it first. Default: nothing."""

    def step(self, inputs: TickInputs) -> PhaseResult:
        """One stereo pair while the phase is current."""
        return PhaseResult()

    def request_hold(self, why: str, duration_s: float) -> None:
        """Ask for a breath-hold (logged; the coach asks the simulated patient)."""
        from hil.controller import events as ev

        self.ctx.session.write(ev.BREATH_HOLD_REQUESTED, purpose=why, duration_s=duration_s)
        if self.ctx.coach is not None:
            self.ctx.coach.request_breath_hold(duration_s)
