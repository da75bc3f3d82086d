"""Live motion compensation over a fluoroscopy run (CONVENTIONS §7).

Per frame, the engine compares the frame with a DRR at the **last applied pose** (the pose the
roadmap shows). The measure (gradient difference, on a small copy of the frame) has a level
that it keeps on the frames of a still patient, with a frame-to-frame noise the tracker
learns; a drop of more than ``detect_sigmas`` noise units (and more than ``detect_relative``
of the level) means the patient moved:

- a small drop is **refined** from the last applied pose: a few Newton steps on each
  parameter from central differences (the probes of one step render side by side on the
  cores), a cheap single level;
- a large drop, or a refinement that does not bring the measure back to its level, runs the
  **full capture** (:func:`registration.core.register.register`, capture runs and polish) from
  the last applied pose, then the same refinement at the tracking level.

Every estimate is assessed (:mod:`registration.core.confidence`: the level the measure
recovered, its margin over perturbed poses, the capture runs' agreement, the field's edges,
the planes' agreement) and ``applied`` or ``withheld``; a withheld estimate keeps the last
applied pose and says why. Frames with no detected motion are ``unchanged``.

:func:`track_run` replays a run at its frame times: a frame that arrives while the engine is
still busy is **skipped**, never queued (the roadmap must follow the newest frame), and counted.
One view searches the paper's five parameters; two views (biplane) all six.

A renderer of prepared levels (:func:`registration.core.prepare.prepare_volume`) holds a crop
of the volume: what the field reaches over one capture's search from the pose it was prepared
at. The tracker keeps the crop's margin for a capture from the applied pose
(:meth:`registration.core.prepare.Crop.margin`, a few 4x4 products when the pose changed) and,
when it falls short, prepares the crop again around the applied pose in a thread of its own
(:func:`registration.core.prepare.recrop`: slices of the same levels), swapped in at the first
frame after it is ready; that frame says so (``reprepared``). A crop of the whole body never is.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.anneal import POLISH_XTOL
from registration.core.confidence import DEFAULT_RULE, Assessment, ConfidenceRule, Evidence, edge_fraction
from registration.core.depth import DepthProbe
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, apply, check_rigid, invert_rigid, offsets_to_matrix, rotation_angle_deg
from registration.core.images import XRayImage
from registration.core.prepare import Crop, PreparedVolume, Reach, crop_of, recrop
from registration.core.register import RegistrationOptions, register, support_mask
from registration.core.similarity import GradientDifference
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: Statuses of a frame (CONVENTIONS §7).
STATUSES = ("applied", "withheld", "unchanged")
#: How a frame was processed.
PATHS = ("check", "refine", "capture")


def light_capture(options: RegistrationOptions | None = None) -> RegistrationOptions:
    """``options`` (default: register's) with only the first (capture) level and the polish.

    Without register's second (refine) annealing level the polish starts from the capture's estimate,
    so it searches the whole range (60 evaluations, Powell's default tolerance) as it did when
    this was measured, not register's +- 2 mm / 1.5 deg around an annealed estimate."""
    from dataclasses import replace

    o = options or RegistrationOptions()
    margins = None if o.support_margin_mm is None else (o.support_margin_mm[0], o.support_margin_mm[-1])
    if options is None:
        o = replace(o, polish_reach=None, polish_evaluations=60, polish_xtol=POLISH_XTOL)
    # no depth correction: the tracker refines the capture's estimate at its own level, five
    # parameters (validate tracking was measured without it); no walk beyond the search box (a
    # frame at the bounds is withheld, the next frame tries again)
    return replace(o, levels=o.levels[:1], support_margin_mm=margins, depth_correction=False, start=False)


@dataclass(frozen=True)
class TrackingOptions:
    """How the tracker detects, refines and captures (defaults: the benchmarked configuration)."""

    #: The tracking level: frames block-averaged to about this many pixels across, and the
    #: volume's pyramid level with about this many voxels across.
    image_px: int = 64
    volume_voxels: int = 64
    #: Pixels compared: the field, shrunk to rays passing this far inside the volume's support.
    support_margin_mm: float = 6.0
    #: Motion is detected when the measure at the last applied pose drops below its level by
    #: more than ``detect_sigmas`` noise units and more than ``detect_relative`` of the level.
    detect_sigmas: float = 5.0
    detect_relative: float = 0.0006
    #: A smaller drop (or ``probe_every`` frames without a refinement) makes the tracker look:
    #: a refinement that finds no pose better than the last applied one by ``detect_sigmas``
    #: (and ``detect_relative``) means no motion (the image changed, e.g. a wire advanced).
    suspect_sigmas: float = 2.5
    probe_every: int = 4
    #: Floor of the learned noise, relative to the level, and its ceiling in floors (the
    #: learned deviations include slow image changes: a guidewire advancing, drift).
    noise_floor_relative: float = 0.0002
    noise_ceiling_floors: float = 2.0
    #: A refinement that moves the pose by less than this (iso-center mm, in-plane for one
    #: view; degrees) is the tracking level's jitter, not motion: the frame is unchanged.
    min_correction_mm: float = 0.15
    min_correction_deg: float = 0.15
    #: A drop beyond this fraction of the level goes straight to the full capture.
    capture_relative: float = 0.02
    #: A refinement whose measure stays more than this many noise units below the level
    #: (and more than ``detect_relative``) did not find the patient: full capture.
    recover_sigmas: float = 6.0
    #: After a full capture the level is expected back to within this fraction of itself.
    capture_tolerance: float = 0.004
    #: Newton iterations of the refinement, its probe steps and its smallest step.
    refine_iterations: int = 3
    refine_step_mm: float = 0.5
    refine_step_deg: float = 0.5
    refine_tolerance: float = 0.03
    #: The refinement stays within this range of the pose it starts from.
    refine_bound_mm: float = 8.0
    refine_bound_deg: float = 5.0
    #: Memory of the level and noise on unchanged frames (0: forget at once).
    level_memory: float = 0.9
    #: Run the full capture on the first frame (else the run starts registered: the first
    #: frame's pose is the initial pose, as after the roadmap's initial registration).
    register_first: bool = False
    #: Options of the full capture (None: the defaults of :func:`register`). The default
    #: keeps register's capture level (four runs at 64 px) and polish but not its second
    #: (refine) annealing level: the tracker refines the result at its own level anyway. Measured on
    #: the quick run's two moves: 1.5-1.65 s CPU instead of 2.4-2.8 s, residuals 0.31/0.35 mm
    #: instead of 0.31/0.30 mm.
    capture: RegistrationOptions | None = field(default_factory=lambda: light_capture())
    #: Threads that render probes side by side (None: one per core, at most 2).
    threads: int | None = None
    rule: ConfidenceRule = DEFAULT_RULE
    #: A renderer of prepared levels (:mod:`registration.core.prepare`) holds the anatomy of a
    #: crop: what the field reaches while the patient stays within one capture's search of
    #: where the crop was prepared. When the applied pose leaves the next capture too little of
    #: that reach, the crop is prepared again around the applied pose (in a thread of its own,
    #: swapped in when ready), with this much slack (mm, deg) beyond the capture's search.
    #: A crop that holds the whole body never is. False: never re-prepare. The margin may fall
    #: ``reprepare_tolerance_mm`` / ``_deg`` short first: then only a capture's farthest poses
    #: could render that much of the anatomy the crop lacks, beyond the two coarsest voxels the
    #: crop keeps past its reach anyway (a still patient's applied pose never moves: its crop is
    #: never prepared again).
    reprepare: bool = True
    reprepare_slack_mm: float = 10.0
    reprepare_slack_deg: float = 5.0
    reprepare_tolerance_mm: float = 1.0
    reprepare_tolerance_deg: float = 0.5

    def __post_init__(self) -> None:
        if self.image_px < 16 or self.volume_voxels < 8:
            raise ValueError("image_px must be >= 16 and volume_voxels >= 8")
        for name in ("detect_sigmas", "recover_sigmas", "refine_step_mm", "refine_step_deg", "refine_tolerance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0.0 <= self.level_memory < 1.0:
            raise ValueError(f"level_memory must lie in [0, 1), got {self.level_memory}")
        if self.refine_iterations < 1:
            raise ValueError(f"refine_iterations must be >= 1, got {self.refine_iterations}")
        for name in ("reprepare_slack_mm", "reprepare_slack_deg", "reprepare_tolerance_mm", "reprepare_tolerance_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")


@dataclass
class FrameEstimate:
    """What the tracker decided for one frame (CONVENTIONS §7)."""

    frame: int
    t_s: float
    status: str
    #: The pose the roadmap shows after this frame (the last applied estimate).
    patient_motion: Array
    #: The engine's estimate for this frame (None when no motion was detected).
    estimate: Array | None
    path: str
    confidence: float | None
    reason: str
    latency_ms: float
    similarity: float
    drop_sigmas: float
    drr_count: int
    evidence: dict = field(default_factory=dict)
    #: CPU time of the process over the frame (ms, all threads): the work, whatever else
    #: shares the machine (on a busy machine ``latency_ms`` grows, this does not).
    cpu_ms: float = 0.0
    #: The volume's crop was prepared again (around the applied pose) and used from this frame
    #: on; ``crop`` then says what it holds and when it was started.
    reprepared: bool = False
    crop: dict | None = None
    #: What the crop leaves the next capture from the applied pose (mm at the iso-center, deg;
    #: None when nothing is cropped away: a whole volume's pyramid or a crop of the whole body).
    crop_margin_mm: float | None = None
    crop_margin_deg: float | None = None

    def to_dict(self) -> dict:
        out = {
            "frame": self.frame,
            "t_s": self.t_s,
            "status": self.status,
            "patient_motion": np.asarray(self.patient_motion).tolist(),
            "estimate": None if self.estimate is None else np.asarray(self.estimate).tolist(),
            "path": self.path,
            "confidence": self.confidence,
            "reason": self.reason,
            "latency_ms": self.latency_ms,
            "cpu_ms": self.cpu_ms,
            "similarity": self.similarity,
            "drop_sigmas": self.drop_sigmas,
            "drr_count": self.drr_count,
            "evidence": self.evidence,
            "reprepared": self.reprepared,
            "crop_margin_mm": self.crop_margin_mm,
            "crop_margin_deg": self.crop_margin_deg,
        }
        if self.crop is not None:
            out["crop"] = self.crop
        return out


class _Level:
    """One view at the tracking level: geometry, field mask, measures (one per thread)."""

    def __init__(self, view: XRayImage, factor: int, mask: NDArray[np.bool_], threads: int) -> None:
        small = view.downsample(factor) if factor > 1 else view
        self.geometry: CArm = small.geometry
        self.mask = mask & small.mask
        if self.mask.sum() < 0.25 * small.mask.sum():
            self.mask = small.mask
        self.image = small.image
        self.measures = [GradientDifference(small.image, self.mask) for _ in range(threads)]


def _level_factor(geometry: CArm, image_px: int) -> int:
    factor = max(1, round(geometry.cols / image_px))
    while factor > 1 and (geometry.rows % factor or geometry.cols % factor):
        factor -= 1
    return factor


class Tracker:
    """Follows the patient over a run of one plane (five parameters) or two (six).

    ``process(views, frame, t_s)`` takes one frame per plane (taken at the same moment) and
    returns a :class:`FrameEstimate`; ``shown_pose`` is the last applied pose.

    A renderer of prepared (cropped) levels is watched (:class:`_CropWatch`): after each frame,
    the crop's margin for a capture from the applied pose; when it falls short, the crop is
    prepared again around that pose in a thread while frames go on being processed with the old
    one, and swapped in at the first frame after it is ready (``wait_for_preparation``: that
    frame waits for it, so a replay's decisions do not depend on the machine's speed).
    """

    def __init__(
        self,
        volume: Volume,
        *,
        options: TrackingOptions | None = None,
        initial_motion: ArrayLike | None = None,
        renderer: DRRRenderer | None = None,
        seed: int = 0,
        wait_for_preparation: bool = False,
    ) -> None:
        self.volume = volume
        self.options = options or TrackingOptions()
        self.pose = np.eye(4) if initial_motion is None else check_rigid(initial_motion, name="initial motion")
        if renderer is None:
            renderer = DRRRenderer(volume, levels=3)
        elif renderer.volume is not volume:
            raise ValueError("renderer was prepared for another volume")
        self.renderer = renderer
        self.seed = int(seed)
        self.volume_level = renderer.level_nearest(self.options.volume_voxels)
        self.threads = max(1, min(2, self.options.threads or os.cpu_count() or 1))
        self._pool = ThreadPoolExecutor(max_workers=self.threads) if self.threads > 1 else None
        self.level: float | None = None
        self.noise: float | None = None
        self._masks: dict[int, NDArray[np.bool_]] = {}
        self._mask_pose = self.pose.copy()
        self._lock = threading.Lock()
        self.frames_processed = 0
        self._since_refine = 0
        #: shown pose = the tracking level's pose @ _bias (see process(), first frame): the
        #: coarse level's bias sits on the volume's side
        self._bias = np.eye(4)
        self._cpu_start = time.process_time()
        #: Biplane: each plane's own level.
        self.plane_levels: list[float] | None = None
        capture = self.options.capture or RegistrationOptions()
        self._frame_views: list[XRayImage] = []
        self._crop_watch = _CropWatch(crop_of(renderer), capture, self.options, wait=wait_for_preparation)

    @property
    def shown_pose(self) -> Array:
        """The pose the roadmap shows: the last applied estimate (CONVENTIONS §4)."""
        return self.pose @ self._bias

    @property
    def repreparations(self) -> int:
        """How many times the crop was prepared again and swapped in."""
        return self._crop_watch.swaps

    def close(self) -> None:
        self._crop_watch.close()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----- the measure at the tracking level ----------------------------------------
    def _levels(self, views: Sequence[XRayImage]) -> list[_Level]:
        out = []
        for p, view in enumerate(views):
            factor = _level_factor(view.geometry, self.options.image_px)
            key = p
            mask = self._masks.get(key)
            small_geom = view.geometry.resized(view.geometry.rows // factor, view.geometry.cols // factor)
            if mask is None or mask.shape != (small_geom.rows, small_geom.cols):
                mask = support_mask(self.volume, small_geom, self._mask_pose, self.options.support_margin_mm)
                self._masks[key] = mask
            out.append(_Level(view, factor, mask, self.threads))
        return out

    def _motion(self, x: Array, reference: Array, geometry: CArm) -> Array:
        six = np.array([x[0], x[1], x[5] if len(x) == 6 else 0.0, x[2], x[3], x[4]])
        return offsets_to_matrix(six, geometry) @ reference

    def _evaluate(self, levels: list[_Level], motions: list[Array]) -> list[float]:
        """Mean measure over the views for each motion (probes rendered side by side)."""

        def one(args: tuple[int, Array]) -> float:
            slot, m = args
            total = 0.0
            for lv in levels:
                drr = self.renderer.render(lv.geometry, m, level=self.volume_level, mask=lv.mask, parallel=False)
                total += lv.measures[slot](drr)
            return total / len(levels)

        if self._pool is None or len(motions) == 1:
            return [one((0, m)) for m in motions]
        # each thread uses its own measure (their scratch buffers are not shared)
        chunks = [list(range(i, len(motions), self.threads)) for i in range(self.threads)]

        def run_chunk(slot: int) -> list[tuple[int, float]]:
            return [(i, one((slot, motions[i]))) for i in chunks[slot]]

        values = [0.0] * len(motions)
        for part in self._pool.map(run_chunk, range(self.threads)):
            for i, v in part:
                values[i] = v
        return values

    # ----- refinement ---------------------------------------------------------------
    def _refine(self, levels: list[_Level], reference: Array, f_start: float) -> tuple[Array, float, float, int]:
        """Newton steps per parameter from central differences; returns (motion, measure,
        relative margin of the final pose over its probes, DRRs rendered)."""
        o = self.options
        geom = levels[0].geometry
        n = 6 if len(levels) > 1 else 5
        steps = np.array([o.refine_step_mm, o.refine_step_mm, o.refine_step_deg, o.refine_step_deg, o.refine_step_deg]
                         + ([o.refine_step_mm] if n == 6 else []))  # fmt: skip
        bounds = np.array([o.refine_bound_mm] * 2 + [o.refine_bound_deg] * 3 + ([o.refine_bound_mm] if n == 6 else []))
        x, f = np.zeros(n), f_start
        count = 0
        margin = 0.0
        for _ in range(o.refine_iterations):
            probes = []
            for i in range(n):
                for sign in (1.0, -1.0):
                    xp = x.copy()
                    xp[i] += sign * steps[i]
                    probes.append(xp)
            values = self._evaluate(levels, [self._motion(p, reference, geom) for p in probes])
            count += len(probes)
            fp = np.array(values[0::2])
            fm = np.array(values[1::2])
            margin = float(np.mean(f - np.maximum(fp, fm))) / max(abs(f), 1e-12)
            grad = (fp - fm) / (2.0 * steps)
            curv = (fp - 2.0 * f + fm) / (steps * steps)
            # maximise: Newton where the measure curves down, else a full step uphill
            newton = np.where(curv < 0, -grad / np.where(curv < 0, curv, -1.0), np.sign(grad) * steps)
            delta = np.clip(newton, -2.0 * steps, 2.0 * steps)
            candidates = [np.clip(x + delta, -bounds, bounds)]
            best_probe = int(np.argmax(values))
            x_new = candidates[0]
            f_new = self._evaluate(levels, [self._motion(x_new, reference, geom)])[0]
            count += 1
            options = [(f, x), (f_new, x_new), (values[best_probe], probes[best_probe])]
            f_best, x_best = max(options, key=lambda t: t[0])
            moved = np.max(np.abs(x_best - x) / steps) if f_best > f else 0.0
            x, f = x_best, f_best
            if moved < o.refine_tolerance / 0.5:  # less than tolerance x the probe step: converged
                break
        return self._motion(x, reference, geom), f, margin, count

    # ----- one frame ----------------------------------------------------------------
    def _scale(self) -> float:
        assert self.level is not None
        floor = self.options.noise_floor_relative * abs(self.level)
        return min(max(self.noise or 0.0, floor), self.options.noise_ceiling_floors * floor)

    def process(self, views: XRayImage | Sequence[XRayImage], frame: int = 0, t_s: float = 0.0) -> FrameEstimate:
        """Decide for one frame (one image per plane, taken at the same moment)."""
        start = time.perf_counter()
        self._cpu_start = time.process_time()
        views = [views] if isinstance(views, XRayImage) else list(views)
        if not 1 <= len(views) <= 2:
            raise ValueError(f"one or two views per frame, got {len(views)}")
        o = self.options
        swapped = self._crop_watch.take()
        if swapped is not None:  # the crop prepared around the applied pose: from this frame on
            self.renderer = swapped.renderer
        self._frame_views = views
        drrs0 = self.renderer.count
        levels = self._levels(views)
        f0_planes = self._per_plane(levels, self.pose)
        f0 = float(np.mean(f0_planes))
        self.frames_processed += 1
        self._since_refine += 1
        first = self.level is None
        if first and not o.register_first:
            f_ref = self._start_registered(levels, f0)
            return self._result(frame, t_s, "unchanged", None, "check", None, "", start, f_ref, 0.0, drrs0, {})
        if first:
            self.level = f0
        scale = self._scale()
        drop = (self.level - f0) / scale
        relative_drop = (self.level - f0) / max(abs(self.level), 1e-12)
        significant = drop > o.detect_sigmas and relative_drop > o.detect_relative
        if not first and not significant and drop <= o.suspect_sigmas and self._since_refine < o.probe_every:
            self._learn(f0, f0_planes)
            return self._result(frame, t_s, "unchanged", None, "check", None, "", start, f0, drop, drrs0, {})
        path = "refine"
        estimate, f_est, margin = self.pose, f0, 0.0
        agreement: float | None = None
        capture = first or relative_drop > o.capture_relative
        if not capture:
            estimate, f_est, margin, _ = self._refine(levels, self.pose, f0)
            self._since_refine = 0
            if self._no_motion(views, estimate, (f_est - f0) / scale, significant):
                self._learn(f0, f0_planes)
                return self._result(frame, t_s, "unchanged", None, "refine", None, "", start, f0, drop, drrs0, {})
            capture = not (
                (self.level - f_est) / scale <= o.recover_sigmas
                or (self.level - f_est) / max(abs(self.level), 1e-12) <= o.detect_relative
            )
        if capture:
            path = "capture"
            estimate, f_est, margin, agreement = self._capture(levels, views, frame)
            if first:
                self.level = max(self.level, f_est)
                scale = self._scale()
        evidence = Evidence(
            deficit=float(self._deficit(levels, estimate, f_est, path, scale)),
            margin=float(margin),
            agreement=agreement,
            edges=float(np.mean([edge_fraction(lv.image, lv.mask) for lv in levels])),
            plane_disagreement_mm=None,
        )
        assessment: Assessment = o.rule.assess(evidence)
        status = "withheld"
        if assessment.applied:
            self._apply(levels, views, estimate, f_est, path)
            status = "applied"
        return self._result(
            frame, t_s, status, estimate, path, assessment.confidence, assessment.reason, start, f_est, drop, drrs0,
            evidence.to_dict(),
        )  # fmt: skip

    def _start_registered(self, levels: list, f0: float) -> float:
        """The run starts registered: the pose the tracking level prefers near the initial pose on
        this frame stands for the initial pose from now on (the coarse level's own bias is not a
        motion). Returns the level."""
        tracked, f_ref, _, _ = self._refine(levels, self.pose, f0)
        self._bias = invert_rigid(tracked) @ self.pose
        self.pose = tracked
        self.level = f_ref
        self.plane_levels = self._per_plane(levels, tracked)
        return f_ref

    def _no_motion(self, views: list[XRayImage], estimate: np.ndarray, gain: float, significant: bool) -> bool:
        """A probe that found no better pose (or one within the tracking level's own jitter, or a
        correction too small to show): the patient did not move, whatever else changed in the image."""
        o = self.options
        moved_mm, moved_deg = self._correction(estimate, views)
        small = moved_mm < o.min_correction_mm and moved_deg < o.min_correction_deg
        return small or (not significant and gain <= o.suspect_sigmas)

    def _capture(
        self, levels: list, views: list[XRayImage], frame: int
    ) -> tuple[np.ndarray, float, float, float | None]:
        """A full registration from the shown pose, refined at the tracking level (the measure the
        level is kept in): the estimate, its level, its margin and the capture runs' agreement."""
        result = register(
            self.volume,
            views,  # two planes: all six parameters
            initial_motion=self.shown_pose,
            options=self.options.capture,
            seed=self.seed + frame,
            renderer=self.renderer,
        )
        agreement = None
        motions = getattr(result, "capture_motions", None)
        if motions:
            from registration.core.confidence import capture_agreement

            agreement = capture_agreement(list(motions), result.patient_motion, views[0].geometry.isocenter_mm)
        captured = result.patient_motion @ invert_rigid(self._bias)
        f_cap = self._evaluate(levels, [captured])[0]
        estimate, f_est, margin, _ = self._refine(levels, captured, f_cap)
        self._since_refine = 0
        return estimate, f_est, margin, agreement

    def _deficit(self, levels: list, estimate: np.ndarray, f_est: float, path: str, scale: float) -> float:
        """How far the estimate's measure falls short of the level, in the level's noise (the
        confidence rule's deficit); biplane: the worse of the two planes' own levels too."""
        o = self.options
        assert self.level is not None
        deficit = (self.level - f_est) / scale
        if path == "capture":
            # After a large move the compared anatomy changed (other pixels inside the support,
            # other overlaps): the level holds only to ``capture_tolerance`` of itself.
            deficit = (self.level - f_est) / max(o.capture_tolerance * abs(self.level), scale)
        elif (self.level - f_est) / max(abs(self.level), 1e-12) <= o.detect_relative:
            deficit = min(deficit, o.rule.deficit_free)  # within the level's own drift
        if len(levels) > 1 and self.plane_levels is not None:
            # Biplane: each plane must recover its own level (the planes agree on the estimate).
            f_planes = self._per_plane(levels, estimate)
            tolerance = o.capture_tolerance if path == "capture" else o.noise_floor_relative * o.noise_ceiling_floors
            worst = max((lv - f) / max(tolerance * abs(lv), 1e-12) for lv, f in zip(self.plane_levels, f_planes,
                                                                                   strict=True))  # fmt: skip
            deficit = max(deficit, worst)
        return deficit

    def _apply(self, levels: list, views: list[XRayImage], estimate: np.ndarray, f_est: float, path: str) -> None:
        """The estimate becomes the shown pose and its measure the level; after a large move the
        compared pixels follow the patient."""
        self.pose = estimate
        self.level = f_est
        if len(levels) > 1:
            self.plane_levels = self._per_plane(levels, estimate)
        if path == "capture" and self._moved_mm(estimate, self._mask_pose, views[0].geometry) > 5.0:
            self._mask_pose = estimate.copy()
            self._masks.clear()

    def warm_up(self, views: XRayImage | Sequence[XRayImage]) -> None:
        """Compile and touch everything one frame needs (before a run's clock starts)."""
        views = [views] if isinstance(views, XRayImage) else list(views)
        levels = self._levels(views)
        self._evaluate(levels, [self.pose, self.pose])
        edge_fraction(levels[0].image, levels[0].mask)

    def _correction(self, estimate: Array, views: Sequence[XRayImage]) -> tuple[float, float]:
        """How far ``estimate`` is from the applied pose: the iso-center's shift (in-plane for
        one view, 3-D for two; mm) and the rotation (deg)."""
        g = views[0].geometry
        iso = np.asarray(g.isocenter_mm)
        err = estimate @ invert_rigid(self.pose)
        shift = apply(err, iso) - iso
        if len(views) == 1:
            shift = shift - (shift @ g.direction) * g.direction
        return float(np.linalg.norm(shift)), rotation_angle_deg(err)

    def _moved_mm(self, a: Array, b: Array, geometry: CArm) -> float:
        iso = np.asarray(geometry.isocenter_mm)
        err = a @ invert_rigid(b)
        return float(np.linalg.norm(apply(err, iso) - iso)) + rotation_angle_deg(err)

    def _per_plane(self, levels: list[_Level], motion: Array) -> list[float]:
        """Each view's measure at ``motion`` (one view: the measure itself)."""
        return [
            lv.measures[0](
                self.renderer.render(lv.geometry, motion, level=self.volume_level, mask=lv.mask, parallel=False)
            )
            for lv in levels
        ]

    def _learn(self, f: float, planes: list[float] | None = None) -> None:
        """Follow the level and its noise on a frame without motion."""
        assert self.level is not None
        m = self.options.level_memory
        if planes is not None and self.plane_levels is not None and len(planes) == len(self.plane_levels):
            self.plane_levels = [m * lv + (1 - m) * p for lv, p in zip(self.plane_levels, planes, strict=True)]
        dev = f - self.level
        var = dev * dev if self.noise is None else m * self.noise**2 + (1 - m) * dev * dev
        self.noise = math.sqrt(var)
        self.level = m * self.level + (1 - m) * f

    def _result(
        self,
        frame: int,
        t_s: float,
        status: str,
        estimate: Array | None,
        path: str,
        confidence: float | None,
        reason: str,
        start: float,
        similarity: float,
        drop: float,
        drrs0: int,
        evidence: dict,
    ) -> FrameEstimate:
        # the pose is decided: does the next capture from it still find the anatomy in the crop?
        views = self._frame_views
        margin = self._crop_watch.check(self.shown_pose, views[0].geometry.isocenter_mm, len(views), frame)
        event = self._crop_watch.event
        self._crop_watch.event = None
        return FrameEstimate(
            frame=int(frame),
            t_s=float(t_s),
            status=status,
            patient_motion=self.shown_pose,
            estimate=None if estimate is None else np.asarray(estimate) @ self._bias,
            path=path,
            confidence=confidence,
            reason=reason,
            latency_ms=(time.perf_counter() - start) * 1e3,
            cpu_ms=(time.process_time() - self._cpu_start) * 1e3,
            similarity=float(similarity),
            drop_sigmas=float(drop),
            drr_count=self.renderer.count - drrs0,
            evidence=evidence,
            reprepared=event is not None and "error" not in event,
            crop=event,
            crop_margin_mm=None if margin is None else margin[0],
            crop_margin_deg=None if margin is None else margin[1],
        )


class _CropWatch:
    """The tracker's crop: its margin at the applied pose and its re-preparation in a thread.

    ``check`` (after a frame, cheap: a few 4x4 products) starts :func:`registration.core.prepare.recrop`
    around the applied pose when a capture from it would search beyond the crop's reach
    (:meth:`registration.core.prepare.Crop.margin` < 0 in mm or degrees); ``take`` (before a
    frame) returns the new preparation once it is ready (``wait``: waits for a pending one)."""

    def __init__(self, crop: Crop | None, capture: RegistrationOptions, options: TrackingOptions, *,
                 wait: bool) -> None:  # fmt: skip
        self.crop = crop
        self.active = options.reprepare
        self.capture = capture
        self.slack = (options.reprepare_slack_mm, options.reprepare_slack_deg)
        self.tolerance = (options.reprepare_tolerance_mm, options.reprepare_tolerance_deg)
        self.wait = wait
        self.swaps = 0
        #: What the frame that swapped a crop in reports (FrameEstimate.crop).
        self.event: dict | None = None
        self._thread: threading.Thread | None = None
        self._done: PreparedVolume | BaseException | None = None
        self._started: tuple[int, float] = (0, 0.0)
        self._failed = False
        #: The last pose checked and its margin (the applied pose changes only when an estimate is applied).
        self._last: tuple[Array, int, tuple[float, float]] | None = None
        self._searches: dict[int, Reach] = {}

    def search(self, planes: int) -> Reach:
        """The reach of a capture's search of ``planes`` views (about the pose it starts from)."""
        reach = self._searches.get(planes)
        if reach is None:
            c = self.capture
            reach = Reach.of_search(c.bound_mm, c.bound_deg, translations=3 if c.optimizes_tz(planes) else 2)
            self._searches[planes] = reach
        return reach

    def check(self, pose: Array, isocenter_mm: ArrayLike, planes: int, frame: int) -> tuple[float, float] | None:
        """The crop's margin for a capture from ``pose`` (None: nothing is cropped away);
        starts a re-preparation when it is negative."""
        crop = self.crop
        if crop is None or crop.complete:
            return None
        last = self._last
        if last is not None and last[1] == planes and np.array_equal(last[0], pose):
            mm, deg = last[2]
        else:
            mm, deg = crop.margin(pose, self.search(planes))
            self._last = (np.array(pose, dtype=np.float64), planes, (mm, deg))
        short = mm < -self.tolerance[0] or deg < -self.tolerance[1]
        if short and self.active and self._thread is None and not self._failed:
            reach = self.search(planes).grown(*self.slack)
            center = np.array(pose, dtype=np.float64)
            self._started = (int(frame), time.perf_counter())

            def job() -> None:
                try:
                    self._done = recrop(crop, center, reach)
                except BaseException as exc:  # noqa: BLE001 - reported by the frame that takes it
                    self._done = exc

            self._thread = threading.Thread(target=job, name="roadmap3d-recrop", daemon=True)
            self._thread.start()
        return mm, deg

    def take(self) -> PreparedVolume | None:
        """The new preparation, once ready (None otherwise); records the event."""
        thread = self._thread
        if thread is None:
            return None
        if self.wait:
            thread.join()
        elif thread.is_alive():
            return None
        thread.join()
        done, self._done, self._thread = self._done, None, None
        frame, t0 = self._started
        if not isinstance(done, PreparedVolume):
            self._failed = True  # keep the old crop; do not retry on every frame
            self.event = {"error": f"the crop could not be prepared again: {done}", "started_frame": frame}
            return None
        self.swaps += 1
        self.crop = done.crop
        self._last = None
        self.event = {
            "started_frame": frame,
            "ready_after_ms": (time.perf_counter() - t0) * 1e3,
            "prepare_ms": done.seconds * 1e3,
            "box_lo": list(done.box_lo),
            "box_hi": list(done.box_hi),
            "voxels_per_level": done.voxels_per_level,
            "complete": done.crop.complete if done.crop is not None else None,
            "reach": {"translation_mm": done.reach.translation_mm, "rotation_deg": done.reach.rotation_deg},
        }
        return done

    def close(self) -> None:
        if self._thread is not None:
            self._thread.join()


# --------------------------------------------------------------------------------------
# A whole run at its frame times
# --------------------------------------------------------------------------------------
@dataclass
class TrackingRun:
    """The outcome of :func:`track_run`: processed frames, skipped frames, the volume's label."""

    frames: list[FrameEstimate]
    skipped: list[int]
    frame_count: int
    volume_label: str
    planes: int

    def summary(self) -> dict:
        lat = np.array([f.latency_ms for f in self.frames]) if self.frames else np.zeros(0)
        refine = np.array([f.latency_ms for f in self.frames if f.path in ("check", "refine")])
        capture = np.array([f.latency_ms for f in self.frames if f.path == "capture"])
        cpu = np.array([f.cpu_ms for f in self.frames])
        cpu_refine = np.array([f.cpu_ms for f in self.frames if f.path in ("check", "refine")])
        cpu_capture = np.array([f.cpu_ms for f in self.frames if f.path == "capture"])

        def q(a: np.ndarray, p: float) -> float | None:
            return float(np.percentile(a, p)) if len(a) else None

        return {
            "frames": self.frame_count,
            "processed": len(self.frames),
            "skipped": len(self.skipped),
            "applied": sum(f.status == "applied" for f in self.frames),
            "withheld": sum(f.status == "withheld" for f in self.frames),
            "unchanged": sum(f.status == "unchanged" for f in self.frames),
            "captures": sum(f.path == "capture" for f in self.frames),
            "refines": sum(f.path == "refine" for f in self.frames),
            "reprepared": sum(f.reprepared for f in self.frames),
            "ms_per_frame_median": q(lat, 50),
            "ms_per_frame_p95": q(lat, 95),
            "refine_path_ms_median": q(refine, 50),
            "refine_path_ms_p95": q(refine, 95),
            "capture_ms_median": q(capture, 50),
            "cpu_ms_per_frame_median": q(cpu, 50),
            "cpu_ms_per_frame_p95": q(cpu, 95),
            "refine_path_cpu_ms_p95": q(cpu_refine, 95),
            "capture_cpu_ms_median": q(cpu_capture, 50),
        }

    def to_dict(self) -> dict:
        return {
            "frames": [f.to_dict() for f in self.frames],
            "skipped": list(self.skipped),
            "frame_count": self.frame_count,
            "planes": self.planes,
            "volume_label": self.volume_label,
            "summary": self.summary(),
        }


def track_run(
    volume: Volume,
    runs: Sequence[Sequence[XRayImage]],
    times_s: ArrayLike,
    *,
    options: TrackingOptions | None = None,
    initial_motion: ArrayLike | None = None,
    renderer: DRRRenderer | None = None,
    seed: int = 0,
    realtime: bool = True,
    wait: bool = False,
    clock: Callable[[], float] | None = None,
    on_frame: Callable[[FrameEstimate], bool | None] | None = None,
) -> TrackingRun:
    """Track a run of one plane (``runs = [run]``) or two synchronised planes.

    ``realtime``: frames arrive at ``times_s``; when the engine finishes a frame it takes the
    newest frame that has arrived and skips the ones in between (never queued); with
    ``realtime=False`` every frame is processed (a replay, deterministic). ``wait``: sleep
    until each frame's time (a live replay, e.g. for the app); otherwise time is virtual: the
    replay runs as fast as it can while the measured processing times decide what is skipped.
    ``clock``: the time source of the processing times (tests inject a deterministic one).
    ``on_frame``: called with every :class:`FrameEstimate`; return True to stop.
    """
    runs = list(runs)
    if not 1 <= len(runs) <= 2:
        raise ValueError(f"one or two planes, got {len(runs)}")
    times = np.asarray(times_s, dtype=np.float64).reshape(-1)
    n = len(times)
    if any(len(r) != n for r in runs):
        raise ValueError(f"every plane needs one frame per time ({n}); got {[len(r) for r in runs]}")
    if n == 0:
        raise ValueError("the run has no frames")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
        raise ValueError("frame times must be finite and non-decreasing")
    clock = clock or time.perf_counter
    estimates: list[FrameEstimate] = []
    skipped: list[int] = []
    # a replay's decisions must not depend on how fast a crop is prepared again: it waits for it
    tracker = Tracker(volume, options=options, initial_motion=initial_motion, renderer=renderer, seed=seed,
                      wait_for_preparation=not realtime)  # fmt: skip
    tracker.warm_up([r[0] for r in runs])
    wall0 = time.perf_counter()
    try:
        now = times[0]
        i = 0
        while i < n:
            if wait:
                ahead = times[i] - (time.perf_counter() - wall0) - times[0]
                if ahead > 0:
                    time.sleep(ahead)
            c0 = clock()
            est = tracker.process([r[i] for r in runs], frame=i, t_s=float(times[i] - times[0]))
            busy = clock() - c0
            if clock is not time.perf_counter:
                est.latency_ms = busy * 1e3
            estimates.append(est)
            if on_frame is not None and on_frame(est):
                break
            if not realtime:
                i += 1
                continue
            now = (time.perf_counter() - wall0 + times[0]) if wait else max(now, times[i]) + busy
            newest = int(np.searchsorted(times, now, side="right")) - 1
            nxt = max(i + 1, newest)
            skipped.extend(range(i + 1, min(nxt, n)))
            i = nxt
    finally:
        tracker.close()
    return TrackingRun(estimates, skipped, n, volume.label, len(runs))


# --------------------------------------------------------------------------------------
# Confidence of a single registration
# --------------------------------------------------------------------------------------
def registration_evidence(
    volume: Volume,
    xray: XRayImage,
    motion: ArrayLike,
    *,
    renderer: DRRRenderer | None = None,
    capture_motions: Sequence[ArrayLike] | None = None,
    image_px: int = 128,
    volume_voxels: int = 128,
    support_margin_mm: float = 4.0,
    depth: DepthProbe | None = None,
    agreement_in_plane: bool = False,
) -> Evidence:
    """What the engine can tell about one registration result without a run around it.

    ``margin``: the measure's mean margin at ``motion`` over poses perturbed by PERTURB_MM /
    PERTURB_DEG along each of the five parameters (10 DRRs at about ``image_px`` pixels),
    relative to the measure; ``rotation_margin``: the smaller margin over the out-of-plane
    rotations (rx, ry) perturbed by ROTATION_PROBE_DEG (4 DRRs); ``edges``: the field's edge
    fraction; ``agreement``: the capture runs' agreement with the result (when
    ``capture_motions`` are given); ``depth``: a
    :class:`~registration.core.depth.DepthProbe` of the result (its ``shift_mm`` and ``tz_mm``
    become the evidence ``depth_shift_mm`` and ``depth_tz_mm``); ``agreement_in_plane``: the
    capture runs compared across the beam only (a single-plane result, whose tz the captures do
    not estimate: :func:`registration.core.confidence.capture_agreement`).
    """
    from registration.core.confidence import PERTURB_DEG, PERTURB_MM, ROTATION_PROBE_DEG, capture_agreement

    m = check_rigid(motion, name="motion")
    if renderer is None:
        renderer = DRRRenderer(volume, levels=3)
    level = renderer.level_nearest(volume_voxels)
    factor = _level_factor(xray.geometry, image_px)
    small_geom = xray.geometry.resized(xray.geometry.rows // factor, xray.geometry.cols // factor)
    lv = _Level(xray, factor, support_mask(volume, small_geom, m, support_margin_mm), 1)
    geometry = xray.geometry

    def f(pose: Array) -> float:
        return lv.measures[0](renderer.render(lv.geometry, pose, level=level, mask=lv.mask))

    f_est = f(m)
    steps = [PERTURB_MM, PERTURB_MM, PERTURB_DEG, PERTURB_DEG, PERTURB_DEG]
    slots = [0, 1, 3, 4, 5]  # tx, ty, rx, ry, rz of the six offsets

    def margin(slot: int, step: float) -> float:
        # the measure's margin over the better of the two poses moved by +-step along one offset
        worst = -math.inf
        for sign in (1.0, -1.0):
            o = np.zeros(6)
            o[slot] = sign * step
            worst = max(worst, f(offsets_to_matrix(o, geometry) @ m))
        return f_est - worst

    margins = [margin(slot, step) for slot, step in zip(slots, steps, strict=True)]
    # the out-of-plane rotations (about the view's x and y axes), which one view sees least,
    # at ROTATION_PROBE_DEG: a wrong local optimum of rx / ry is flat there
    rotation_margins = [margin(slot, ROTATION_PROBE_DEG) for slot in (3, 4)]
    agreement = None
    if capture_motions:
        along = geometry.direction if agreement_in_plane else None
        agreement = capture_agreement([np.asarray(c) for c in capture_motions], m, geometry.isocenter_mm, along)
    return Evidence(
        margin=float(np.mean(margins)) / max(abs(f_est), 1e-12),
        rotation_margin=float(min(rotation_margins)) / max(abs(f_est), 1e-12),
        agreement=agreement,
        edges=edge_fraction(lv.image, lv.mask),
        depth_shift_mm=None if depth is None else float(depth.shift_mm),
        depth_tz_mm=None if depth is None else float(depth.tz_mm),
    )
