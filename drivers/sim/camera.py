"""Simulated stereo camera: renders every frame of the simulated world with the synthetic renderer.

Frames are exposed at ``t0 + k / frame_rate_hz`` on the injected clock and become available
``latency_ms`` later; :meth:`SimStereoCamera.grab` blocks (``clock.sleep``) until the next one
is available and returns the newest available pair (older ones are dropped, like a camera
driver that keeps the latest buffer). A frame is rendered only when grabbed, so a fast
simulation pays only for the frames it uses. The right camera exposes ``skew_ms`` after the left
one: with a non-zero skew the right image is rendered from the world at its own exposure time
(a second render, so skewed rigs cost twice as much per pair).

With ``render_needle`` the needle carried by the guide is drawn into both images too (seed 004
§III's cylinder, :func:`hil.vision.render_instrument.render_instrument_stereo`): a dark cylinder of
``needle_radius_mm`` from the guide origin (the needle tip, resting in the guide) back along the
guide's -z over ``needle_length_mm``, at the left exposure time. The guide is mounted on the flange
at ``T_flange_from_needle_guide`` when given (the *true* mounting, to simulate a guide that differs
from what the controller believes), else at the setup's ``[frames] T_flange_from_guide``. With
``needle_bead_count`` >= 1 the needle also carries bright bead markers (seed 004 §II-A) at
``needle_bead_offset_mm + i * needle_bead_spacing_mm`` from the tip.

Rig errors (``[simulation.rig_errors]``, all off by default): with ``camera_calibration_error_px``
the images are rendered through true cameras that differ from the calibration the controller
uses (:attr:`SimStereoCamera.calibration` stays the told one); with ``camera_timestamp =
"reception"`` frames are stamped ``camera_reception_offset_ms`` (+ jitter) after their exposure
(``Frame.time_source`` says so), never later than they are delivered; with
``camera_clock_rate_error_ppm`` the camera's own clock runs that much fast: it exposes every
``1 / frame_rate_hz`` on that clock (its ``device_t_ns``), so on the host clock the pairs come
slightly more often and drift in phase against anything the host paces, as a free-running camera
does against a robot controller's cycle.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from typing import Literal

from pydantic import BaseModel, Field

from drivers.interfaces.camera import Frame, FrameTime, StereoCamera, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError
from drivers.sim.rig_errors import reception_offset_ns, true_calibration
from drivers.sim.world import FLANGE_MARKER_ID_BASE, SimWorld
from hil.clock import Clock, MonotonicClock
from hil.config.types import STRICT, TransformConfig
from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import StereoCalibration, load_calibration
from hil.vision.render import MarkerTruth, RenderedPair, RenderOptions, RingMarker3D, render_stereo
from hil.vision.render_instrument import Instrument3D, render_instrument_stereo
from plugins.registry import DriverContext

#: never render further ahead of the clock than this (real time only; see SimStereoCamera.grab)
_MAX_RENDER_LEAD_NS = 500_000_000
#: the lead follows the median of this many of the last render times (SimStereoCamera.render_lead_ns)
_RENDER_LEAD_WINDOW = 5
#: ... and covers the longest of this many (3 s at 30 Hz), up to the latency less a guard
_RENDER_PEAK_WINDOW = 90
#: how long after the exposure a render covering a peak starts, at the earliest (ns)
_RENDER_PEAK_GUARD_NS = 2_000_000


class SimCameraConfig(BaseModel):
    """``[camera] driver = "sim"``. Uses ``[calibration] stereo`` when given, else a synthetic rig."""

    model_config = STRICT

    driver: Literal["sim"]
    frame_rate_hz: float = Field(15.0, gt=0, le=240, description="exposures per second")
    exposure_us: float = Field(5000.0, gt=0, description="reported exposure time")
    latency_ms: float = Field(30.0, ge=0, description="exposure to availability")
    skew_ms: float = Field(0.0, ge=-50, le=50, description="right timestamp minus left timestamp")
    noise_sigma: float = Field(2.0, ge=0, description="sensor noise, grey levels")
    blur_sigma_px: float = Field(0.7, ge=0, description="defocus blur")
    glare_spots: int = Field(0, ge=0, le=20, description="specular highlights per image")
    flange_marker_diameter_mm: float = Field(7.0, gt=0, description="outer diameter of flange markers")
    flange_marker_inner_diameter_mm: float = Field(3.0, gt=0)
    synthetic_f_px: float = Field(1394.0, gt=0, description="focal length without a calibration file")
    synthetic_baseline_mm: float = Field(120.0, gt=0, description="baseline without a calibration file")
    render_needle: bool = Field(False, description="draw the needle carried by the guide (seed 004 check)")
    needle_radius_mm: float = Field(0.6, gt=0, le=10, description="radius of the rendered needle")
    needle_length_mm: float = Field(100.0, gt=0, le=500,
                                    description="rendered needle length, from the guide tip back along -z")
    T_flange_from_needle_guide: TransformConfig | None = Field(
        None, description="true guide mounting of the rendered needle (default [frames] T_flange_from_guide)")
    needle_bead_count: int = Field(0, ge=0, le=10, description="bright bead markers on the needle (0: none)")
    needle_bead_spacing_mm: float = Field(30.0, gt=0, description="distance between neighbouring beads")
    needle_bead_offset_mm: float = Field(20.0, ge=0, description="first bead's distance from the tip")
    needle_bead_radius_mm: float = Field(2.5, gt=0, le=10, description="radius of the rendered beads")


class SimStereoCamera(StereoCamera):
    """Stereo frames of the simulated world (skin markers and flange markers)."""

    def __init__(self, name: str, cfg: SimCameraConfig, clock: Clock, world: SimWorld,
                 calibration: StereoCalibration) -> None:
        super().__init__(name)
        self.cfg = cfg
        self.clock = clock
        self.world = world
        self._calibration = calibration  # what the controller is told
        errors = world.rig_errors
        self.true_calibration = true_calibration(calibration, errors.camera_calibration_error_px,
                                                 world.rng("camera_calibration_error"))
        self._reception = errors.camera_timestamp == "reception"
        self.options = RenderOptions(noise_sigma=cfg.noise_sigma, blur_sigma_px=cfg.blur_sigma_px,
                                     glare_spots=cfg.glare_spots, seed=world.seed)
        self._period_ns = round(1e9 / cfg.frame_rate_hz)   # on the camera's own clock
        ppm = errors.camera_clock_rate_error_ppm
        #: the frame period on the host clock (the camera's clock runs ``ppm`` fast)
        self._true_period_ns: float = self._period_ns / (1.0 + ppm * 1e-6)
        self._clock_exact = ppm == 0.0
        self._latency_ns = round(cfg.latency_ms * 1e6)
        self._skew_ns = round(cfg.skew_ms * 1e6)
        self._t0_ns = 0
        self._last_k = -1
        tg = cfg.T_flange_from_needle_guide
        self.T_flange_from_guide: RigidTransform = (
            tg.as_transform() if tg is not None else world.frames.T_flange_from_guide.as_transform())
        self.last_truth: tuple[MarkerTruth, ...] = ()        # markers at the left exposure
        self.last_truth_right: tuple[MarkerTruth, ...] = ()  # markers at the right exposure
        self.frames_rendered = 0
        # clock time the last renders took (none on a manual clock): the lead (render_lead_ns)
        self._render_ns: deque[int] = deque(maxlen=_RENDER_PEAK_WINDOW)

    def _open(self) -> None:
        self._t0_ns = self.clock.now_ns()
        self._last_k = -1
        if isinstance(self.clock, MonotonicClock):
            self._warm_up()

    def _warm_up(self) -> None:
        """On the wall clock: render one pair and discard it, so the renderer's one-off set-up
        (first calls, caches: 0.1-0.3 s) is paid at open and never taken for a render time. The
        lead (:attr:`render_lead_ns`) is learned from real grabs only: learned from a first render
        that paid the set-up, it made the second grab render a pair that far ahead and deliver
        nothing until it was due (a camera fault at the start of a real-time run). On a manual
        clock rendering takes no clock time: nothing to warm up. Its own random stream: the
        pairs' noise is unchanged."""
        render_stereo(self.true_calibration, self.markers_at(self._t0_ns), self.options,
                      self.world.rng("camera_warm_up"))

    def _close(self) -> None:
        pass

    @property
    def calibration(self) -> StereoCalibration:
        """What the controller is told: ``[calibration] stereo`` when given, else the synthetic rig
        (the images are rendered through :attr:`true_calibration`, which differs by the rig errors)."""
        return self._calibration

    @property
    def frame_rate_hz(self) -> float:
        return self.cfg.frame_rate_hz

    @property
    def exposure_us(self) -> float:
        return self.cfg.exposure_us

    @property
    def image_size(self) -> tuple[int, int]:
        return self.calibration.image_size

    @property
    def render_lead_ns(self) -> int:
        """How long before a pair is due its render starts (ns of clock time): the longest of the
        last :data:`_RENDER_PEAK_WINDOW` render times, but at most the latency less
        :data:`_RENDER_PEAK_GUARD_NS`, and at least the median of the last
        :data:`_RENDER_LEAD_WINDOW`; never more than :data:`_MAX_RENDER_LEAD_NS`. 0 before the first
        render and on a manual clock (rendering takes no simulated time).

        The peak: render times on a shared machine come in runs (18 ms for a while, then 25-30 ms
        for a while, on this project's 2-CPU VM), and a pair whose render overruns the lead is
        delivered that much late. The lead used to be the median of the last five, so every
        render above it was late: a 30 ms camera delivered at p99 40 ms, and that spike ate the
        issue's whole frame -> command margin. Covered up to the latency less
        :data:`_RENDER_PEAK_GUARD_NS`, a render starts once its exposure is in the past; the arm's
        pose at the exposure then comes from the servo loop's records around it (with the
        perception process: :class:`hil.perception.follow.RingFlangeSource`, which carries the
        last records' motion on for up to one servo period when the newest is older).

        The cap: a render stretched by a stall of the whole process (the host, or a library
        holding the interpreter lock -- ur_rtde's client constructors do, for ~0.65 s, when
        recover() rebuilds them) says nothing of the next one. A lead that took such a stall whole
        made the camera render the next pair that far ahead and deliver nothing until it was due:
        every stall was followed by a silence as long again (a transport run's camera data 1.5 s
        old after the robot's recovery). Capped below the latency, a stall costs nothing after it.

        The median floor: a renderer slower than the latency every time (a loaded machine) still
        starts that long ahead, so its pairs are delivered latency-old; the exposure then lies up
        to the render time ahead of the clock (see :meth:`grab`)."""
        if not self._render_ns:
            return 0
        recent = list(self._render_ns)[-_RENDER_LEAD_WINDOW:]
        covered = min(max(self._render_ns), max(self._latency_ns - _RENDER_PEAK_GUARD_NS, 0))
        return min(max(round(statistics.median_low(recent)), covered), _MAX_RENDER_LEAD_NS)

    def exposure_time_ns(self, k: int) -> int:
        """Pair ``k``'s exposure on the host clock: ``k`` periods of the camera's own clock."""
        if self._clock_exact:
            return self._t0_ns + k * self._period_ns
        return self._t0_ns + round(k * self._true_period_ns)

    def markers_at(self, t_ns: int) -> list[RingMarker3D]:
        """The ring markers the rig sees at ``t_ns`` (optical frame): skin, then flange."""
        w = self.world
        centres, normals = w.patient_markers_optical(t_ns)
        lost = w.lost_markers(t_ns)
        out = [RingMarker3D(center_mm=c, normal=n, outer_diameter_mm=w.phantom.outer_diameter_mm,
                            inner_diameter_mm=w.phantom.inner_diameter_mm, marker_id=i)
               for i, (c, n) in enumerate(zip(centres, normals, strict=True)) if i not in lost]
        fc, fn = w.flange_markers_optical(t_ns)
        out += [RingMarker3D(center_mm=c, normal=n, outer_diameter_mm=self.cfg.flange_marker_diameter_mm,
                             inner_diameter_mm=self.cfg.flange_marker_inner_diameter_mm,
                             marker_id=FLANGE_MARKER_ID_BASE + i)
                for i, (c, n) in enumerate(zip(fc, fn, strict=True))]
        return out

    def grab(self, timeout_s: float) -> StereoFrame:
        self.require_active("grab")
        now = self.clock.now_ns()
        # At real time rendering takes clock time (none on a manual clock, where the lead stays 0):
        # pick the newest pair that is due once rendered, start rendering ``lead`` before it is due,
        # and hand it over when due -- so a frame is ``latency_ms`` old on delivery, as the camera
        # model says, however slow rendering is on a loaded machine. The exposure may lie up to
        # ``lead`` minus ``latency_ms`` ahead of the clock (about zero once the lead has settled
        # to the render time): the world is a function of time and of the robot's commands known
        # when the render starts. Without the controller's prefetch thread its only commander waits
        # here, so nothing changes; with it (real time) a servo command sent during the render
        # that changes the motion before the exposure is not in the image -- at most the
        # command's change of velocity times that small lead.
        lead = min(self.render_lead_ns, round(timeout_s * 1e9))
        newest = math.floor((now + lead - self._latency_ns - self._t0_ns) / self._true_period_ns)
        k = max(newest, self._last_k + 1)
        ready_ns = self.exposure_time_ns(k) + self._latency_ns
        if ready_ns > now:
            wait_s = (ready_ns - now) * 1e-9
            if wait_s > timeout_s:
                self.clock.sleep(timeout_s)
                raise DeviceTimeoutError(self.name, f"no stereo pair within {timeout_s} s")
            if ready_ns - lead > now:
                self.clock.sleep((ready_ns - lead - now) * 1e-9)
        self._last_k = k
        t_render_ns = self.clock.now_ns()
        t_exp = self.exposure_time_ns(k)
        pair = render_stereo(self.true_calibration, self.markers_at(t_exp), self.options,
                             self.world.rng("camera", k))
        pair = self._with_needle(pair, t_exp, k)
        right_image = pair.right
        self.last_truth = pair.truth
        self.last_truth_right = pair.truth
        if self._skew_ns != 0:
            skewed = render_stereo(self.true_calibration, self.markers_at(t_exp + self._skew_ns),
                                   self.options, self.world.rng("camera_right", k))
            skewed = self._with_needle(skewed, t_exp + self._skew_ns, k)
            right_image = skewed.right
            self.last_truth_right = skewed.truth
        self.frames_rendered += 1
        done_ns = self.clock.now_ns()
        self._render_ns.append(done_ns - t_render_ns)
        if done_ns < ready_ns:
            self.clock.sleep((ready_ns - done_ns) * 1e-9)  # never before the camera would deliver it
        stamp_ns, source = t_exp, FrameTime.EXPOSURE
        if self._reception:
            e = self.world.rig_errors
            off = reception_offset_ns(e.camera_reception_offset_ms, e.camera_timestamp_jitter_ms,
                                      self.world.rng("camera_stamp", k))
            stamp_ns, source = t_exp + min(off, self._latency_ns), FrameTime.RECEPTION
        device_ns = k * self._period_ns   # the camera's clock (the host's when it has no rate error)
        left = Frame(image=pair.left, t_ns=stamp_ns, seq=k, device_t_ns=device_ns, time_source=source)
        right = Frame(image=right_image, t_ns=stamp_ns + self._skew_ns, seq=k,
                      device_t_ns=device_ns + self._skew_ns, time_source=source)
        return StereoFrame(left, right)

    def needle_at(self, t_ns: int) -> Instrument3D | None:
        """The needle resting in the guide at ``t_ns`` (optical frame; tip at the guide origin,
        hub ``needle_length_mm`` back along the guide's -z), or None without a robot."""
        T_of = self.world.T_optical_from_flange(t_ns)
        if T_of is None:
            return None
        T_og = T_of @ self.T_flange_from_guide
        tip = T_og.t
        c = self.cfg
        if c.needle_bead_count > 0:
            return Instrument3D.needle_with_beads(
                tip, -T_og.R[:, 2], c.needle_length_mm, radius_mm=c.needle_radius_mm,
                marker_positions_mm=[c.needle_bead_offset_mm + i * c.needle_bead_spacing_mm
                                     for i in range(c.needle_bead_count)],
                bead_radius_mm=c.needle_bead_radius_mm)
        return Instrument3D(tip, tip - c.needle_length_mm * T_og.R[:, 2], radius_mm=c.needle_radius_mm)

    def _with_needle(self, pair: RenderedPair, t_ns: int, k: int) -> RenderedPair:
        if not self.cfg.render_needle:
            return pair
        inst = self.needle_at(t_ns)
        if inst is None:
            return pair
        ri = render_instrument_stereo(self.true_calibration, inst, self.options, self.world.rng("needle", k),
                                      base=pair)
        return RenderedPair(ri.left, ri.right, pair.truth)


def make_sim_camera(config: SimCameraConfig, ctx: DriverContext) -> SimStereoCamera:
    """Factory registered as camera driver ``sim`` (needs the simulated world)."""
    if not isinstance(ctx.world, SimWorld):
        raise TypeError("the sim camera needs the simulated world (DriverContext.world)")
    if ctx.calibration_path is not None:
        cal = load_calibration(ctx.calibration_path)
    else:
        cal = StereoCalibration.synthetic(f_px=config.synthetic_f_px,
                                          baseline_mm=config.synthetic_baseline_mm)
    return SimStereoCamera(ctx.role, config, ctx.clock, ctx.world, cal)
