"""The tracker: one frame at a time against the level the measure keeps, refined or captured,
assessed, applied or withheld; the crop prepared again around the applied pose in a thread.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.confidence import Assessment, Evidence, edge_fraction
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, apply, check_rigid, invert_rigid, offsets_to_matrix, rotation_angle_deg
from registration.core.images import XRayImage
from registration.core.prepare import crop_of
from registration.core.register import RegistrationOptions, register, support_mask
from registration.core.similarity import GradientDifference
from registration.core.tracking.crop_watch import CropWatch
from registration.core.tracking.options import FrameEstimate, TrackingOptions
from registration.core.volume import Volume

Array = NDArray[np.float64]


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

    A renderer of prepared (cropped) levels is watched (:class:`CropWatch`): after each frame,
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
        self._crop_watch = CropWatch(crop_of(renderer), capture, self.options, wait=wait_for_preparation)

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
        views = self._take_frame(views)
        o = self.options
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
        edges = float(np.mean([edge_fraction(lv.image, lv.mask) for lv in levels]))
        evidence = Evidence(deficit=float(self._deficit(levels, estimate, f_est, path, scale)), margin=float(margin),
                            agreement=agreement, edges=edges, plane_disagreement_mm=None)  # fmt: skip
        assessment: Assessment = o.rule.assess(evidence)
        status = "withheld"
        if assessment.applied:
            self._apply(levels, views, estimate, f_est, path)
            status = "applied"
        return self._result(
            frame, t_s, status, estimate, path, assessment.confidence, assessment.reason, start, f_est, drop, drrs0,
            evidence.to_dict(),
        )  # fmt: skip

    def _take_frame(self, views: XRayImage | Sequence[XRayImage]) -> list[XRayImage]:
        """The frame's views (one or two), checked; a crop prepared around the applied pose is
        swapped in from this frame on."""
        views = [views] if isinstance(views, XRayImage) else list(views)
        if not 1 <= len(views) <= 2:
            raise ValueError(f"one or two views per frame, got {len(views)}")
        swapped = self._crop_watch.take()
        if swapped is not None:
            self.renderer = swapped.renderer
        self._frame_views = views
        return views

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
