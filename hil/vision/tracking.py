"""Region-of-interest tracking of ring markers: once acquired, each marker is searched for only in
a window around its predicted position, with the same sub-pixel estimator as a full-frame search.

Per camera (:class:`ImageTracker`), each tracked marker keeps its last detection (outer and inner
ellipses) and its image velocity. For a new frame:

1. Prediction: last centre + velocity x elapsed time (constant velocity; the elapsed time is the
   frames' timestamps when given, else one frame).
2. Windowed search: the rays of :mod:`hil.vision.ring_edges` are cast from each predicted centre
   with the last ellipses' radii, all markers of the image in one batch, and the ellipse fits,
   ring check and centre estimate of :func:`hil.vision.detect.fit_rings` follow -- the very
   estimator of full-frame detection. A marker that fails there (it moved further than the rays'
   tolerance, or part of it is hidden) gets the full-frame detector's coarse step inside its
   window (:func:`hil.vision.detect.refine_in_box`).
3. Gating: a result is the marker only when its centre lies inside the window and nearer to the
   prediction than half the distance to any other marker's prediction; two markers never take the
   same detection. Anything else is *lost* -- never snapped to a neighbour.
4. Re-acquisition: a full-frame search of the image (:func:`hil.vision.detect.detect_rings`)
   whenever a marker was lost in this frame (the same frame is searched again, so a marker that
   only outran its window is found), and on request. Every ``reacquire_every`` frames the whole
   image is scanned for a new marker (a stereo tracker staggers its two cameras by half that
   period): the full-frame search's candidate step (:func:`hil.vision.detect.find_candidates`)
   runs beside the windows, and when one of its candidates lies in no tracked marker's window
   (a new marker, or clutter), the full-frame search follows in the same frame. A scan that
   finds only the tracked markers costs the candidate step (~0.4 ms at 1920 x 1080), not the
   ring fits of every marker again (~0.7 ms more).
5. Recovery: a marker that a full-frame search no longer finds (hidden) is remembered where it
   was last predicted; while it is missing, every ``lost_retry_every`` frames the coarse step
   searches a window of twice its tracking window around that place (never reaching half-way to
   a tracked marker, and a ring overlapping a tracked one is refused), so a marker uncovered where
   it was is back within ``lost_retry_every`` frames for the cost of one window, not of a frame.
   A marker reappearing elsewhere is found by the periodic full-frame search; with
   ``reacquire_every`` 0 the retry is a full-frame search.

The stereo stage is unchanged (:func:`hil.vision.stereo.match_and_triangulate`): global pairing
on the rectified rows and ring sizes, the plane-normal perspective correction and the ray-gap
check. Pure CPU; the cost grows with the number of markers, not with the image size (a full-frame
search excepted).

Thread safety: a tracker holds mutable state; calls must not overlap (one thread at a time), but
successive calls may come from different threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.distance import cdist

from hil.vision.camera_model import StereoCalibration
from hil.vision.detect import (
    DetectParams,
    RingDetection,
    begin_search,
    detect_rings,
    detect_rings_multi,
    edges_of,
    find_candidates,
    finish_search,
    fit_rings,
    refine_in_box,
    validate_image,
)
from hil.vision.pipeline import LocateResult
from hil.vision.ring_edges import RingSeeds, ring_edges_multi
from hil.vision.stereo import StereoParams, match_and_triangulate

FloatArray = NDArray[np.float64]
U8Image = NDArray[np.uint8]


@dataclass(frozen=True)
class TrackingParams:
    """window_margin_px: how far beyond the marker's outer ellipse (px) its window reaches.
    reacquire_every: a scan of the whole image for new markers every this many frames, a full-frame
    search when it sees one (module doc, step 4; 0: full-frame searches only when needed).
    lost_retry_every: while fewer markers are tracked than were seen, the missing markers' last
    places are searched every this many frames (a full-frame search when ``reacquire_every`` is
    0 or no place is known; module doc, step 5). forget_after: after this many frames a missing
    marker is no longer searched for (the scene has fewer markers now). max_speed_px_per_frame:
    velocity clamp of the prediction.
    """

    window_margin_px: float = 8.0
    reacquire_every: int = 30
    lost_retry_every: int = 5
    forget_after: int = 150
    max_speed_px_per_frame: float = 20.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window_margin_px) and self.window_margin_px >= 0):
            raise ValueError(f"window_margin_px must be >= 0, got {self.window_margin_px}")
        if self.reacquire_every < 0 or self.lost_retry_every < 1 or self.forget_after < 1:
            raise ValueError("reacquire_every must be >= 0, lost_retry_every and forget_after >= 1")


@dataclass(frozen=True)
class _Step:
    """One frame in progress: full-frame search or windows, predicted centres (px), elapsed time,
    whether the missing markers' last places are searched after the windows, and whether the
    image is scanned for new markers (module doc, step 4)."""

    full: bool
    preds: FloatArray
    dt: float
    search_lost: bool = False
    scan: bool = False


@dataclass(frozen=True)
class _Tracks:
    """The tracked markers of one camera, one row each, as the arrays every frame reads (built
    once when the tracks change, not per use): latest detections, centres (n, 2) px, velocities
    (n, 2) px per second (or per frame without timestamps), outer and inner ellipses (n, 3):
    ``a``, ``b`` px and angle rad, and polarity (n,)."""

    dets: list[RingDetection]
    center_px: FloatArray
    velocity: FloatArray
    outer: FloatArray
    inner: FloatArray
    dark_on_light: NDArray[np.bool_]

    @staticmethod
    def of(dets: list[RingDetection], velocity: FloatArray | None = None) -> _Tracks:
        """Tracks of ``dets`` with ``velocity`` (n, 2) (None: at rest)."""
        n = len(dets)
        v = np.zeros((n, 2)) if velocity is None else velocity
        if n == 0:
            empty = np.zeros((0, 3))
            return _Tracks([], np.zeros((0, 2)), v, empty, empty, np.zeros(0, dtype=bool))
        rows = np.array([
            (*d.center_px.tolist(), d.outer.a_px, d.outer.b_px, d.outer.angle_rad,
             d.inner.a_px, d.inner.b_px, d.inner.angle_rad)
            for d in dets
        ])
        return _Tracks(
            list(dets), np.ascontiguousarray(rows[:, :2]), v, np.ascontiguousarray(rows[:, 2:5]),
            np.ascontiguousarray(rows[:, 5:]), np.array([d.dark_on_light for d in dets], dtype=bool),
        )

    def half_px(self, margin_px: float) -> FloatArray:
        """Each marker's window half side (px): :func:`_window_half_px` of every row."""
        return np.asarray(self.outer[:, 0] * 1.35 + 4.0 + margin_px, dtype=np.float64)


@dataclass(frozen=True)
class _Lost:
    """A marker no longer found: its last detection and where it was last predicted (px)."""

    det: RingDetection
    center_px: FloatArray


@dataclass
class ImageStats:
    """Counters of one camera: frames, full-frame searches (``reacquisitions``), markers lost from
    their window (``losses``), missing markers found again at their last place (``recoveries``),
    periodic scans for new markers (``scans``; one that finds a candidate is also a search)."""

    frames: int = 0
    reacquisitions: int = 0
    losses: int = 0
    recoveries: int = 0
    scans: int = 0


@dataclass
class ImageTracker:
    """The markers of one camera (see the module doc). Not thread-safe: one call at a time."""

    params: TrackingParams = field(default_factory=TrackingParams)
    detect_params: DetectParams = field(default_factory=DetectParams)
    name: str = "image"
    #: frames by which this camera's periodic full-frame searches are offset (a stereo tracker
    #: staggers its two cameras so that one pair never pays for both)
    phase: int = 0
    stats: ImageStats = field(default_factory=ImageStats)
    _tracks: _Tracks = field(default_factory=lambda: _Tracks.of([]))
    _lost: list[_Lost] = field(default_factory=list)
    _t_s: float | None = None
    _expected: int = 0
    _missing_since: int | None = None
    _force: bool = False

    def request_reacquire(self) -> None:
        """The next frame gets a full-frame search."""
        self._force = True

    @property
    def tracked(self) -> int:
        return len(self._tracks.dets)

    @property
    def markers(self) -> list[RingDetection]:
        """The tracked markers' latest detections."""
        return list(self._tracks.dets)

    def update(self, img: U8Image, t_s: float | None = None) -> list[RingDetection]:
        """The markers in ``img`` (a validated grey frame); see the module doc. ``t_s``: the
        frame's time (s, any monotonic origin) for the velocity; None: one unit per frame."""
        step = self.begin(t_s)
        found = None
        if not step.full:
            dp = self.detect_params
            found = fit_rings(edges_of(img, self.seeds(step), dp), dp)
        return self.finish(img, step, found)

    def begin(self, t_s: float | None) -> _Step:
        """Start a frame: elapsed time, predictions, and whether it gets a full-frame search or a
        scan for new markers beside its windows."""
        self.stats.frames += 1
        dt = 1.0 if t_s is None or self._t_s is None else max(t_s - self._t_s, 1e-6)
        self._t_s = t_s
        missing_for = self._missing_for()
        every = self.params.reacquire_every
        retry = missing_for is not None and missing_for % self.params.lost_retry_every == 0
        local = retry and every > 0 and bool(self._lost)
        full = self._force or not self._tracks.dets or (retry and not local)
        periodic = every > 0 and (self.stats.frames + self.phase) % every == 0
        return _Step(full, self._predict(dt), dt, local and not full, periodic and not full)

    def seeds(self, step: _Step) -> RingSeeds:
        """The windowed search's ray seeds: each marker's last ellipses at its prediction."""
        t = self._tracks
        return RingSeeds(step.preds, t.outer, t.inner, t.dark_on_light)

    def finish(
        self, img: U8Image, step: _Step, found: list[RingDetection | None] | None
    ) -> list[RingDetection]:
        """End a frame: :meth:`resolve_windows`, else a full-frame search (:meth:`reacquire`).
        Returns the markers of this frame."""
        if step.full or found is None or not self.resolve_windows(img, step, found):
            self.reacquire(detect_rings(img, self.detect_params, self.name), step)
        return self.markers

    def resolve_windows(self, img: U8Image, step: _Step, found: list[RingDetection | None]) -> bool:
        """Gate the windowed results ``found`` (one per track, from :meth:`seeds`), search a
        failed marker's window with the coarse step, scan for new markers when the step says so;
        True when every marker was found and nothing new seen (tracks updated), False when one is
        lost (counted) or the scan saw a candidate that is no tracked marker: the frame needs a
        full-frame search (tracks not updated)."""
        found = self._windowed(img, step.preds, found)
        lost = sum(1 for d in found if d is None)
        if lost:
            self.stats.losses += lost
            return False
        dets = [d for d in found if d is not None]
        if step.scan:
            self.stats.scans += 1
            if self._scan_sees_new(img, dets):
                return False
        self._advance(dets, step.dt)
        if step.search_lost:
            self._recover(img)
        return True

    def reacquire(self, dets: list[RingDetection], step: _Step) -> None:
        """Take a full-frame search's detections as the tracks (see :meth:`_reacquired`)."""
        self.stats.reacquisitions += 1
        self._force = False
        self._reacquired(dets, step.preds, step.dt)

    # ---- internals --------------------------------------------------------------------------
    def _missing_for(self) -> int | None:
        """Frames since fewer markers are tracked than were seen (None: none missing, or missing
        longer than ``forget_after``: then the smaller count becomes the expected one)."""
        if self._expected <= self.tracked:
            self._missing_since = None
            return None
        if self._missing_since is None:
            self._missing_since = self.stats.frames
        since = self.stats.frames - self._missing_since
        if since > self.params.forget_after:
            self._expected, self._missing_since = self.tracked, None
            self._lost = []
            return None
        return since

    def _scan_sees_new(self, img: U8Image, dets: list[RingDetection]) -> bool:
        """Whether a full-frame candidate (:func:`hil.vision.detect.find_candidates`) lies in none
        of the windows (half side :func:`_window_half_px`) around this frame's markers ``dets``."""
        boxes = find_candidates(img, self.detect_params)
        if not boxes:
            return False
        b = np.array(boxes, dtype=np.float64)
        centres = 0.5 * np.column_stack([b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]])
        here = np.array([d.center_px for d in dets]).reshape(-1, 2)
        half = self._tracks.half_px(self.params.window_margin_px)
        dx = np.abs(centres[:, None, 0] - here[None, :, 0])
        dy = np.abs(centres[:, None, 1] - here[None, :, 1])
        inside = (dx <= half[None, :]) & (dy <= half[None, :])
        return not bool(inside.any(axis=1).all())

    def _predict(self, dt: float) -> FloatArray:
        t = self._tracks
        return np.asarray(t.center_px + t.velocity * dt, dtype=np.float64)

    def _gates(self, preds: FloatArray) -> FloatArray:
        """Per track, the largest accepted distance of a detection from its prediction (px): its
        window's half side, at most half the distance to the nearest other prediction."""
        half = self._tracks.half_px(self.params.window_margin_px)
        if half.shape[0] > 1:
            near = _pairwise_px(preds)
            np.fill_diagonal(near, np.inf)
            half = np.minimum(half, 0.5 * near.min(axis=1))
        return half

    def _windowed(
        self, img: U8Image, preds: FloatArray, found: list[RingDetection | None]
    ) -> list[RingDetection | None]:
        found = list(found)
        gates = self._gates(preds)
        halves = self._tracks.half_px(self.params.window_margin_px).tolist()
        h, w = img.shape
        nan = math.nan
        centres = np.array([(nan, nan) if d is None else d.center_px.tolist() for d in found]).reshape(-1, 2)
        off = centres - preds
        dist = np.sqrt(off[:, 0] * off[:, 0] + off[:, 1] * off[:, 1])
        for i in np.flatnonzero(~(dist <= gates)).tolist():  # NaN (not found): searched again
            half = halves[i]
            x, y = preds[i].tolist()
            box = (
                max(int(x - half), 0),
                max(int(y - half), 0),
                min(math.ceil(x + half), w),
                min(math.ceil(y + half), h),
            )
            det = refine_in_box(img, box, self.detect_params) if box[2] > box[0] and box[3] > box[1] else None
            ok = det is not None and float(np.linalg.norm(det.center_px - preds[i])) <= gates[i]
            found[i] = det if ok else None
            centres[i] = det.center_px if det is not None and ok else (nan, nan)
            dist[i] = float(np.linalg.norm(centres[i] - preds[i]))
        # two markers never take the same detection: the one nearer its prediction keeps it
        b = np.array([nan if d is None else d.outer.b_px for d in found])
        close = _pairwise_px(centres) < 0.5 * np.minimum(b[:, None], b[None, :])  # NaN: False
        np.fill_diagonal(close, False)
        if not close.any():
            return found
        for i in range(len(found)):
            for j in range(i + 1, len(found)):
                if close[i, j] and found[i] is not None and found[j] is not None:
                    found[j if dist[i] <= dist[j] else i] = None
        return found

    def _advance(self, dets: list[RingDetection], dt: float) -> None:
        if not dets:
            return
        new = _Tracks.of(dets)
        step = new.center_px - self._tracks.center_px
        move = np.sqrt(step[:, 0] * step[:, 0] + step[:, 1] * step[:, 1])
        vmax = self.params.max_speed_px_per_frame
        scale = np.where(move <= vmax, 1.0, vmax / np.where(move > 0, move, 1.0))
        new.velocity[:] = step * (scale / dt)[:, None]  # :meth:`_velocity` of every track at once
        self._tracks = new

    def _velocity(self, step_px: FloatArray, dt: float) -> FloatArray:
        """Velocity (px per second, or per frame without timestamps) of a move of ``step_px`` in
        ``dt``, its move per frame clamped to ``max_speed_px_per_frame``."""
        move = math.sqrt(float(step_px[0]) ** 2 + float(step_px[1]) ** 2)
        vmax = self.params.max_speed_px_per_frame
        scale = 1.0 if move <= vmax else vmax / move
        return np.asarray(step_px * (scale / dt), dtype=np.float64)

    def _reacquired(self, dets: list[RingDetection], preds: FloatArray, dt: float) -> None:
        """New tracks from a full-frame search; a detection near an old track's prediction keeps
        that track's velocity (the nearest pairs first)."""
        old = self._tracks
        velocities = np.zeros((len(dets), 2))
        used: set[int] = set()
        gates = self._gates(preds) if old.dets else np.zeros(0)
        for i, det in enumerate(dets):
            if old.dets:
                d = np.linalg.norm(preds - det.center_px, axis=1)
                j = int(np.argmin(d))
                if d[j] <= gates[j] and j not in used:
                    used.add(j)
                    velocities[i] = self._velocity(det.center_px - old.center_px[j], dt)
        self._tracks = _Tracks.of(dets, velocities)
        if len(dets) >= self._expected:
            self._expected, self._missing_since = len(dets), None
            self._lost = []
            return
        if self._missing_since is None:
            self._missing_since = self.stats.frames
        # the markers not found again are remembered where they were (module doc, step 5)
        margin = self.params.window_margin_px
        lost = self._lost + [_Lost(t, preds[j].copy()) for j, t in enumerate(old.dets) if j not in used]
        self._lost = [
            m for m in lost
            if not any(float(np.linalg.norm(det.center_px - m.center_px)) <= _window_half_px(m.det, margin)
                       for det in dets)
        ]

    def _recover(self, img: U8Image) -> None:
        """Search each missing marker's last place (module doc, step 5); a ring found there that
        overlaps no tracked marker becomes a track again (``recoveries``)."""
        h, w = img.shape
        for m in list(self._lost):
            half = 2.0 * _window_half_px(m.det, self.params.window_margin_px)
            x, y = float(m.center_px[0]), float(m.center_px[1])
            for tx, ty in self._tracks.center_px.tolist():
                half = min(half, 0.5 * math.sqrt((tx - x) * (tx - x) + (ty - y) * (ty - y)))
            box = (max(int(x - half), 0), max(int(y - half), 0), min(math.ceil(x + half), w),
                   min(math.ceil(y + half), h))
            det = refine_in_box(img, box, self.detect_params) if box[2] > box[0] and box[3] > box[1] else None
            if det is None or any(
                float(np.linalg.norm(d.center_px - det.center_px)) < d.outer.a_px + det.outer.a_px
                for d in self._tracks.dets
            ):
                continue
            tracks = self._tracks
            self._tracks = _Tracks.of([*tracks.dets, det], np.vstack([tracks.velocity, np.zeros((1, 2))]))
            self._lost.remove(m)
            self.stats.recoveries += 1
        if self.tracked >= self._expected:
            self._expected, self._missing_since = self.tracked, None
            self._lost = []


def _pairwise_px(points: FloatArray) -> FloatArray:
    """Distances (px) between every two of the (n, 2) points, (n, n); NaN where one is NaN."""
    return np.asarray(cdist(points, points), dtype=np.float64)


def _window_half_px(det: RingDetection, margin_px: float) -> float:
    """Half the side of a marker's search window: its outer ellipse's major semi-axis, the
    full-frame ROI's slack (x 1.35 + 4 px) and the margin."""
    return det.outer.a_px * 1.35 + 4.0 + margin_px


@dataclass
class TrackingStats:
    """Both cameras' counters (see :class:`ImageStats`)."""

    frames: int
    reacquisitions: int
    losses: int
    recoveries: int = 0
    scans: int = 0


class MarkerTracker:
    """Stereo ring-marker localisation with region-of-interest tracking (module doc).

    Args:
        cal: the rig's calibration; both images must have its size.
        params / detect_params / stereo_params: tracking, detection and stereo settings.

    :meth:`locate` returns the same :class:`~hil.vision.pipeline.LocateResult` as
    :func:`hil.vision.pipeline.locate_markers` (without identification). Not thread-safe: one
    call at a time (from any thread).
    """

    def __init__(
        self,
        cal: StereoCalibration,
        params: TrackingParams | None = None,
        detect_params: DetectParams | None = None,
        stereo_params: StereoParams | None = None,
    ) -> None:
        self.cal = cal
        self.params = params or TrackingParams()
        dp = detect_params or DetectParams()
        self.stereo_params = stereo_params or StereoParams()
        self.left = ImageTracker(self.params, dp, "left image")
        self.right = ImageTracker(self.params, dp, "right image", phase=self.params.reacquire_every // 2)

    def request_reacquire(self) -> None:
        """Both images of the next pair get a full-frame search."""
        self.left.request_reacquire()
        self.right.request_reacquire()

    @property
    def stats(self) -> TrackingStats:
        a, b = self.left.stats, self.right.stats
        return TrackingStats(a.frames, a.reacquisitions + b.reacquisitions, a.losses + b.losses,
                             a.recoveries + b.recoveries, a.scans + b.scans)

    def locate(self, left_img: object, right_img: object, t_s: float | None = None) -> LocateResult:
        """Markers of one stereo pair (optical frame, mm). ``t_s``: the pair's time, s.

        Raises:
            VisionError: an image is empty, colour, not uint8 or not the calibration's size.
        """
        left = validate_image(left_img, "left image", self.cal.image_size)
        right = validate_image(right_img, "right image", self.cal.image_size)
        trackers = ((self.left, left), (self.right, right))
        dp = self.left.detect_params
        steps = [tr.begin(t_s) for tr, _ in trackers]
        # one batch of rings for the pair: the windows of a tracked image and the first hypotheses
        # of an image due for a full-frame search (known now: periodic, retry or requested)
        windowed = [k for k in range(2) if not steps[k].full]
        searches = {k: begin_search(trackers[k][1], dp) for k in range(2) if steps[k].full}
        parts = [(trackers[k][1], trackers[k][0].seeds(steps[k])) for k in windowed]
        parts += [(sr.frame, sr.seeds) for sr in searches.values()]
        fitted: list[RingDetection | None] = []
        if parts:
            fitted = fit_rings(ring_edges_multi(parts, dp.n_rays, dp.min_contrast, dp.min_valid_fraction), dp)
        found: dict[int, list[RingDetection | None]] = {}
        start = 0
        for k, (_, sd) in zip([*windowed, *searches], parts, strict=True):
            found[k] = fitted[start : start + sd.count]
            start += sd.count
        for k, sr in searches.items():
            trackers[k][0].reacquire(finish_search(sr, found[k], dp), steps[k])
        need = [k for k in windowed if not trackers[k][0].resolve_windows(trackers[k][1], steps[k], found[k])]
        if need:  # a marker lost from its window: full-frame searches, both images in one batch
            images = [(trackers[k][1], trackers[k][0].name) for k in need]
            for k, dets in zip(need, detect_rings_multi(images, dp), strict=True):
                trackers[k][0].reacquire(dets, steps[k])
        dl, dr = self.left.markers, self.right.markers
        stereo = match_and_triangulate(self.cal, dl, dr, self.stereo_params)
        return LocateResult(tuple(dl), tuple(dr), stereo)
