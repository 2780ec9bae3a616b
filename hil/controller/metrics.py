"""What a run measured: the per-tick figures the controller collects, the simulator-truth meter
(an observer of the tick, never part of the control path) and the :class:`RunSummary` that
``hil run`` prints (docs/run.md)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from hil.controller import events as ev
from hil.controller.compensation import rigid_change
from hil.controller.estimate import Estimate
from hil.controller.fsm import State
from hil.controller.series import SampleSeries
from hil.controller.truth import GroundTruth
from hil.session.log import SessionLog

FloatArray = NDArray[np.float64]

if TYPE_CHECKING:
    from hil.controller.planning import RigGeometry
    from hil.controller.snapshot import ControllerSnapshot


@dataclass
class RunSummary:
    """What ``hil run`` reports (see docs/run.md)."""

    final_state: str
    states: list[str]
    timeline: list[dict[str, Any]]
    fre_mm: float | None
    tre_expected_mm: float | None
    robot_fre_mm: float | None
    lock_error_mm: float | None
    lock_error_max_mm: float | None
    lock_direction_error_deg: float | None
    comp_error_rms_mm: float | None
    comp_error_p95_mm: float | None
    comp_error_max_mm: float | None
    latency_ms: dict[str, float | None]
    processing_ms: dict[str, float | None]
    gate_open_fraction: float | None
    time_to_lock_s: float | None
    duration_s: float
    frames: int
    commands_sent: int
    commands_refused: int
    faults: list[str]
    session_log: str
    needle_direction_error_deg: float | None = None
    #: with ``target_model = "surrogate"``: the share of judged pairs that kept the rigid direction
    #: (docs/compensation.md "The direction"); None without the model
    target_model_fallback_fraction: float | None = None
    #: with ``target_model = "surrogate"``: the share of judged pairs it steered with its score or
    #: turn held at a bound (breathing deeper than the 4D CT); None without the model
    target_model_held_fraction: float | None = None
    #: with ``[procedure.tracking] target_sensor``: the share of judged pairs whose path pointed at
    #: the sensor's target (the rest: the model's, or the rigid direction); None without the sensor
    target_sensor_fraction: float | None = None
    #: the published chain head: SHA-256 of the session log's last line (set once it is closed)
    session_log_sha256: str | None = None
    #: the HTML report built after the run (``hil run``; None when not built)
    report: str | None = None
    #: the tracked needle tip against the planned target while locked (last sample; see docs/run.md)
    tracked_needle: dict[str, float] | None = None
    #: marker-location time per stereo pair, p50 / p95 (ms; set by hil run from its locator)
    locate_ms: dict[str, float | None] = field(default_factory=lambda: {"p50": None, "p95": None})
    #: the guide axis line's closest distance to the true target at lock (first LOCK sample), and
    #: its largest over the hold (every LOCK sample), mm (simulation only)
    target_error_mm: float | None = None
    target_error_max_mm: float | None = None
    #: the guide axis line's closest distance to the true entry at lock, mm
    entry_axis_error_mm: float | None = None
    #: the true skin markers' rigid-fit residual over the run: p95 and max, mm
    body_rigid_residual_mm_p95: float | None = None
    body_rigid_residual_mm_max: float | None = None
    #: the guide axis line to the true target, and to the true entry, while compensating: p95, mm
    comp_target_error_p95_mm: float | None = None
    comp_entry_error_p95_mm: float | None = None
    #: the measured rigid change's FRE (live skin markers against the registered reference) over
    #: the run after registration: p50 and p95, mm
    change_fre_mm: dict[str, float | None] = field(default_factory=lambda: {"p50": None, "p95": None})
    #: simulation only: the share of COMPENSATE / LOCK ticks with the gate's checks passing during
    #: which the true target was more than 2 mm from the guide axis line, and the open ticks counted
    gate_false_open_rate: float | None = None
    gate_open_ticks: int = 0
    comp_errors_mm: list[float] = field(default_factory=list, repr=False)
    comp_error_age_s: list[float] = field(default_factory=list, repr=False)
    lock_target_errors_mm: list[float] = field(default_factory=list, repr=False)
    #: every LOCK sample's guide axis line to the true entry, mm (simulation only)
    lock_entry_errors_mm: list[float] = field(default_factory=list, repr=False)
    comp_entry_errors_mm: list[float] = field(default_factory=list, repr=False)
    #: simulation only, while compensating: the path the controller follows against the true body
    #: (:class:`PathSample`), p95 mm: its stand-off point against the ideal one when its pair was
    #: taken, and now
    comp_path_error_p95_mm: float | None = None
    comp_path_now_error_p95_mm: float | None = None
    #: per COMPENSATE sample, aligned with ``comp_errors_mm`` (NaN: no path yet): the
    #: :class:`PathSample` fields
    comp_path_errors_mm: list[float] = field(default_factory=list, repr=False)
    comp_path_now_errors_mm: list[float] = field(default_factory=list, repr=False)
    comp_path_entry_errors_mm: list[float] = field(default_factory=list, repr=False)
    comp_path_direction_errors_deg: list[float] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """The JSON summary (docs/run.md); the per-tick error series are left out."""
        d = dict(self.__dict__)
        for series in _SERIES_FIELDS:
            d.pop(series)
        return d


#: :class:`RunSummary`'s per-tick series, left out of its JSON
_SERIES_FIELDS: Final = ("comp_errors_mm", "comp_error_age_s", "lock_target_errors_mm",
                         "lock_entry_errors_mm", "comp_entry_errors_mm", "comp_path_errors_mm",
                         "comp_path_now_errors_mm", "comp_path_entry_errors_mm",
                         "comp_path_direction_errors_deg")


def percentile(values: Sequence[float] | SampleSeries, q: float) -> float | None:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else None


def samples() -> SampleSeries:
    """A per-tick or per-frame sample series whose memory does not grow with the run
    (:class:`~hil.controller.series.SampleSeries`: exact up to its capacity)."""
    return SampleSeries()


@dataclass
class RunMetrics:
    """Figures collected during the run (ms on the controller clock unless said)."""

    detect_ms: SampleSeries = field(default_factory=samples)       # exposure -> markers perceived
    processing_ms: SampleSeries = field(default_factory=samples)   # tick work, wall clock (profiling)
    gate_samples: int = 0
    gate_open_samples: int = 0
    #: pairs the surrogate target model judged (steered or fell back), those it fell back on, and
    #: those it steered with its score or turn held at a bound
    target_model_pairs: int = 0
    target_model_fallbacks: int = 0
    target_model_held: int = 0
    #: of those, the pairs whose path pointed at the target sensor's target (None: no sensor)
    target_sensor_pairs: int | None = None
    lock_time_s: float | None = None
    frames: int = 0
    frames_overwritten: int = 0   # prefetched pairs replaced before a tick took them (latest wins)

    def on_frame(self, est: Estimate, state: State) -> None:
        """After perception: the gate-open fraction counts every registered pair outside REGISTER
        (open: the body back in the registered state by every check of ``[procedure.gate]``)."""
        if est.patient_reg is not None and state is not State.REGISTER:
            self.gate_samples += 1
            self.gate_open_samples += int(est.gate_problem() is None)
        if est.target_steer is not None:
            self.target_model_pairs += 1
            self.target_model_fallbacks += int(bool(est.target_steer.fallback))
            self.target_model_held += int(bool(est.target_steer.limited))
            if est.target_sensor is not None:
                self.target_sensor_pairs = ((self.target_sensor_pairs or 0)
                                            + int(est.target_steer.source == "sensor"))

    @property
    def gate_open_fraction(self) -> float | None:
        return (self.gate_open_samples / self.gate_samples) if self.gate_samples else None

    @property
    def target_model_fallback_fraction(self) -> float | None:
        """Share of the pairs the surrogate target model judged that kept the rigid direction
        (None without the model)."""
        return (self.target_model_fallbacks / self.target_model_pairs) if self.target_model_pairs else None

    @property
    def target_model_held_fraction(self) -> float | None:
        """Share of the pairs the surrogate target model judged that it steered with its score or
        turn held at a bound (None without the model)."""
        return (self.target_model_held / self.target_model_pairs) if self.target_model_pairs else None

    @property
    def target_sensor_fraction(self) -> float | None:
        """Share of the pairs the surrogate target model judged whose path pointed at the target
        sensor's target (None without a target sensor or before a judged pair)."""
        if self.target_sensor_pairs is None or not self.target_model_pairs:
            return None
        return self.target_sensor_pairs / self.target_model_pairs


#: a gate open while the true target is farther than this from the guide axis line is a false open
FALSE_OPEN_MM = 2.0
#: Session-log event: where the simulator's truth put the skin markers, the entry and the target
#: (optical frame, mm), once per new stereo pair (:meth:`TruthMeter.positions`; docs/run.md).
TRUTH_POSITIONS: Final = "truth_positions"


@runtime_checkable
class SkinMarkerTruth(Protocol):
    """A ground truth that also knows where the skin markers truly are (the simulated world)."""

    def patient_markers_optical(self, t_ns: int) -> tuple[FloatArray, FloatArray]:
        """True skin marker centres (N,3, mm) and unit normals (N,3), optical frame, at ``t_ns``."""
        ...


@dataclass(frozen=True)
class TruthSample:
    """The real guide against the real body at one snapshot (simulation only).

    Attributes:
        position_mm: guide origin to the ideal stand-off point on the true moving path (the
            lock error's measure).
        direction_deg: guide axis against the true entry -> target direction.
        target_mm: the guide axis line's closest distance to the true (internal) target: how far
            a needle inserted now would pass from it.
        entry_mm: the guide axis line's closest distance to the true (skin) entry.
    """

    position_mm: float
    direction_deg: float
    target_mm: float
    entry_mm: float


@dataclass(frozen=True)
class PathSample:
    """The path the controller follows (``ControllerSnapshot.path_optical_mm``) against the true
    body, at one snapshot (simulation only). It splits the guide's following error
    (:attr:`TruthSample.position_mm`) into what the estimate got wrong at its own pair and what the
    time since then added; the rest is the filter, the prediction and the arm.

    Attributes:
        standoff_at_pair_mm: the path's stand-off point against the ideal one on the true path when
            the pair was taken (as stamped): the estimator, the target model and the sensing (the
            camera's noise, the rig's calibration, the clocks).
        entry_at_pair_mm: the path's entry against the true entry then.
        direction_at_pair_deg: the path's direction against the true entry -> target direction then.
        standoff_now_mm: the same stand-off point against the ideal one now: adds the body's motion
            since the pair (what the prediction over the latency is for).
    """

    standoff_at_pair_mm: float
    entry_at_pair_mm: float
    direction_at_pair_deg: float
    standoff_now_mm: float


def _angle_deg(a: FloatArray, b: FloatArray) -> float:
    """The angle between unit vectors ``a`` and ``b``, degrees (atan2: exact near 0)."""
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(a @ b)))


def line_distance_mm(origin: FloatArray, axis: FloatArray, point: FloatArray) -> float:
    """Distance (mm) from ``point`` to the line through ``origin`` along the unit ``axis``."""
    d = point - origin
    return float(np.linalg.norm(d - (d @ axis) * axis))


class TruthMeter:
    """Simulation only, an observer of the controller's snapshots (never used for control): after
    each tick in COMPENSATE or LOCK, the real guide's error against the real moving path
    (``truth_error``), from the simulator's truth and the arm's pose the snapshot read when it was
    built (``ControllerSnapshot.robot_now``, at ``t_ns``): :class:`TruthSample`. After every
    tick, the true body's rigid-fit residual (how far it is from rigid) and the FRE of the
    measured rigid change (what the controller could see of it). Its lists feed the run summary."""

    def __init__(self, truth: GroundTruth | None, rig: RigGeometry, session: SessionLog) -> None:
        self.truth, self.rig, self.session = truth, rig, session
        self.comp_errors_mm = samples()
        self.comp_error_age_s = samples()   # time since COMPENSATE was entered, per sample
        self.comp_target_errors_mm = samples()
        self.comp_entry_errors_mm = samples()   # the guide axis line to the true entry, per sample
        #: the controller's path against the truth (:class:`PathSample`), per sample (NaN: no path)
        self.comp_path_errors_mm = samples()
        self.comp_path_now_errors_mm = samples()
        self.comp_path_entry_errors_mm = samples()
        self.comp_path_direction_errors_deg = samples()
        self.lock_errors: list[tuple[float, float]] = []
        self.lock_samples: list[TruthSample] = []
        self.rigid_residuals_mm = samples()
        self.change_fre_mm = samples()      # the measured rigid change's FRE, per registered pair
        #: COMPENSATE / LOCK ticks with the gate's checks passing, and those of them with the true
        #: target more than FALSE_OPEN_MM off the guide axis line (a needle inserted then would miss)
        self.gate_open_ticks = 0
        self.gate_false_open_ticks = 0
        self.__name__ = "truth_meter"   # how the observer is named in an observer_failed record
        self._positions_frame = -1   # the snapshot frame count of the last truth_positions record
        #: the latest ``truth_positions`` fields (a new dict each time, never mutated): what a live
        #: view reads from another thread (hil.replay.live); None before the first
        self.last_positions: dict[str, Any] | None = None

    def errors(self, snap: ControllerSnapshot) -> tuple[float, float] | None:
        """(position error mm, direction error deg) of the guide, or None without a plan or a
        robot state."""
        sample = self.sample(snap)
        return None if sample is None else (sample.position_mm, sample.direction_deg)

    def sample(self, snap: ControllerSnapshot) -> TruthSample | None:
        """The guide against the true body at the snapshot, or None without a plan or a robot
        state."""
        state, standoff_mm = snap.robot_now, snap.standoff_mm
        if self.truth is None or state is None or standoff_mm is None:
            return None
        now = state.t_ns
        T_robot_from_guide = state.T_robot_from_tcp @ self.rig.T_tcp_from_guide
        T_guide = self.truth.T_optical_from_robot @ T_robot_from_guide
        # a simulator with a real rig's errors knows the real arm, not only its (late, imprecise) report
        if (T_of := self.truth.T_optical_from_flange(now := snap.t_ns)) is not None:
            T_guide = T_of @ self.rig.T_flange_from_guide
        entry, target, u = self._true_path(now)
        ideal = entry - standoff_mm * u
        pos = float(np.linalg.norm(T_guide.t - ideal))
        axis = T_guide.R[:, 2]
        cosang = float(np.clip(axis @ u, -1.0, 1.0))
        return TruthSample(position_mm=pos, direction_deg=math.degrees(math.acos(cosang)),
                           target_mm=line_distance_mm(T_guide.t, axis, target),
                           entry_mm=line_distance_mm(T_guide.t, axis, entry))

    def _true_path(self, t_ns: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The true entry, target (optical, mm) and the unit entry -> target direction at ``t_ns``."""
        assert self.truth is not None
        entry = np.asarray(self.truth.entry_optical(t_ns), dtype=np.float64)
        target = np.asarray(self.truth.target_optical(t_ns), dtype=np.float64)
        return entry, target, (target - entry) / np.linalg.norm(target - entry)

    def path_sample(self, snap: ControllerSnapshot) -> PathSample | None:
        """The controller's path at the snapshot against the true body (:class:`PathSample`), or
        None without a path, a stand-off or a truth."""
        path, t_pair, standoff_mm = snap.path_optical_mm, snap.path_t_ns, snap.standoff_mm
        if self.truth is None or path is None or t_pair is None or standoff_mm is None:
            return None
        d = path[1] - path[0]
        u_path = d / np.linalg.norm(d)
        point = path[0] - standoff_mm * u_path
        entry, _target, u = self._true_path(t_pair)
        entry_now, _target_now, u_now = self._true_path(snap.t_ns)
        return PathSample(standoff_at_pair_mm=float(np.linalg.norm(point - (entry - standoff_mm * u))),
                          entry_at_pair_mm=float(np.linalg.norm(path[0] - entry)),
                          direction_at_pair_deg=_angle_deg(u_path, u),
                          standoff_now_mm=float(np.linalg.norm(point - (entry_now - standoff_mm * u_now))))

    def positions(self, t_ns: int) -> dict[str, Any]:
        """The true positions at ``t_ns`` (optical frame, mm), as the ``truth_positions`` record's
        fields: ``truth_t_ns``, ``entry_optical_mm`` and ``target_optical_mm`` (3), and
        ``markers_optical_mm`` (N,3, the phantom's marker order) when the truth knows the skin
        markers (:class:`SkinMarkerTruth`). Empty without a truth."""
        if self.truth is None:
            return {}
        truth = self.truth
        out: dict[str, Any] = {
            "truth_t_ns": t_ns,
            "entry_optical_mm": np.asarray(truth.entry_optical(t_ns), dtype=np.float64),
            "target_optical_mm": np.asarray(truth.target_optical(t_ns), dtype=np.float64)}
        if isinstance(truth, SkinMarkerTruth):
            markers, _normals = truth.patient_markers_optical(t_ns)
            out["markers_optical_mm"] = np.asarray(markers, dtype=np.float64)
        return out

    def __call__(self, snap: ControllerSnapshot) -> None:
        """Observe one snapshot (the controller's thread, after the tick)."""
        if self.truth is None:
            return
        if snap.frames != self._positions_frame:
            self._positions_frame = snap.frames
            positions = self.positions(snap.t_ns)
            self.session.write(TRUTH_POSITIONS, **positions, frame=snap.frames)
            self.last_positions = positions
        residual = float(self.truth.body_rigid_residual_mm(snap.t_ns))
        self.rigid_residuals_mm.append(residual)
        if snap.reference_optical_mm is not None and snap.live_mm is not None:
            change = rigid_change(snap.reference_optical_mm, snap.live_mm)
            if change is not None:
                self.change_fre_mm.append(change.fre_rms_mm)
        state = State(snap.state)
        if state not in (State.COMPENSATE, State.LOCK):
            return
        sample = self.sample(snap)
        if sample is None:
            return
        if snap.gate_ok:
            self.gate_open_ticks += 1
            self.gate_false_open_ticks += int(sample.target_mm > FALSE_OPEN_MM)
        if state is State.COMPENSATE:
            entered_s = snap.timeline[-1].t_s if snap.timeline else 0.0
            self.comp_errors_mm.append(sample.position_mm)
            self.comp_error_age_s.append(snap.t_s - entered_s)
            self.comp_target_errors_mm.append(sample.target_mm)
            self.comp_entry_errors_mm.append(sample.entry_mm)
            self._append_path(self.path_sample(snap))
        else:
            self.lock_errors.append((sample.position_mm, sample.direction_deg))
            self.lock_samples.append(sample)
        self.session.write(ev.TRUTH_ERROR, state=state, position_mm=sample.position_mm,
                           direction_deg=sample.direction_deg, target_mm=sample.target_mm,
                           entry_axis_mm=sample.entry_mm, body_rigid_residual_mm=residual)

    def _append_path(self, p: PathSample | None) -> None:
        """One COMPENSATE sample's path figures (NaN without a path: the series stay aligned
        with ``comp_errors_mm``)."""
        nan = math.nan
        self.comp_path_errors_mm.append(nan if p is None else p.standoff_at_pair_mm)
        self.comp_path_now_errors_mm.append(nan if p is None else p.standoff_now_mm)
        self.comp_path_entry_errors_mm.append(nan if p is None else p.entry_at_pair_mm)
        self.comp_path_direction_errors_deg.append(nan if p is None else p.direction_at_pair_deg)
