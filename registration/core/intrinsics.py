"""The C-arm's own geometry estimated with the pose, for systems nobody calibrated.

A file may lack the source-image distance or give a nominal one, and the principal point (where
the central ray meets the detector) moves with the C-arm's sag. :func:`refine_geometry` polishes
the pose and, per view, the source-image distance (a scale of the nominal, within
``max_sid_change``) and the principal point (a shift in detector pixels, within
``max_shift_px``) on the gradient difference, from a registration's estimate.

What one view can tell: a longer source-image distance magnifies the anatomy as moving it
toward the source does, and a shifted principal point moves its projection as an in-plane
translation does; one view cannot tell them apart (the registration's depth and in-plane
translation absorb them), so :func:`refine_geometry` refuses a single view. A second plane sees
the first plane's depth and one in-plane direction across its own image: with two planes both
are estimated. A pixel scale error is the source-image distance's (the projection depends on
their ratio only): give ``--pixel-mm`` when it is known, the refinement estimates the ratio.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from registration.core.blas import with_one_blas_thread
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, check_rigid
from registration.core.images import XRayImage
from registration.core.problem import LevelProblem
from registration.core.search import SearchSpace
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: What can be estimated.
INTRINSICS = ("sid", "principal_point")


@dataclass(frozen=True)
class ViewIntrinsics:
    """One view's estimated geometry: its source-image distance (mm; ``sid_change``: relative to
    the nominal) and its principal point's shift from the nominal (detector pixels: column, row)."""

    sid_mm: float
    sid_change: float
    principal_point_shift_px: tuple[float, float]

    def to_dict(self) -> dict:
        return {"sid_mm": self.sid_mm, "sid_change": self.sid_change,
                "principal_point_shift_px": list(self.principal_point_shift_px)}  # fmt: skip


@dataclass(frozen=True)
class GeometryRefinement:
    """The pose and the views' geometry estimated together (:func:`refine_geometry`)."""

    patient_motion: Array
    views: tuple[XRayImage, ...]
    intrinsics: tuple[ViewIntrinsics, ...]
    estimated: tuple[str, ...]
    similarity: float
    similarity_before: float
    evaluations: int
    seconds: float

    def to_dict(self) -> dict:
        return {
            "patient_motion": np.asarray(self.patient_motion).tolist(),
            "estimated": list(self.estimated),
            "views": [i.to_dict() for i in self.intrinsics],
            "similarity": self.similarity,
            "similarity_before": self.similarity_before,
            "evaluations": self.evaluations,
            "seconds": self.seconds,
        }


def with_intrinsics(geometry: CArm, sid_scale: float, shift_px: ArrayLike) -> CArm:
    """``geometry`` with its source-image distance scaled and its detector shifted in its own
    plane by ``shift_px`` (columns, rows) of ``geometry``'s pixels (the principal point moves
    the other way)."""
    u, v, _ = geometry.detector_axes()
    cols, rows = np.asarray(shift_px, dtype=np.float64)
    shift = np.asarray(geometry.detector_shift_mm) + u * cols * geometry.pixel_mm[1] + v * rows * geometry.pixel_mm[0]
    moved = tuple(float(s) for s in shift)
    return replace(geometry, sid_mm=geometry.sid_mm * float(sid_scale), detector_shift_mm=moved)


@dataclass(frozen=True)
class _Parameters:
    """The refinement's parameter vector: the six pose offsets, then per view its source-image
    distance change in per cent (``sid``) and its principal point shift in pixels (``shift``)."""

    views: int
    sid: bool
    shift: bool
    #: One detector for every view (one C-arm at several angles): its intrinsics once.
    shared: bool = False

    @property
    def sets(self) -> int:
        return 1 if self.shared else self.views

    @property
    def size(self) -> int:
        return 6 + ((1 if self.sid else 0) + (2 if self.shift else 0)) * self.sets

    def unpack(self, x: Array) -> tuple[Array, list[tuple[float, Array]]]:
        """The pose offsets, and per view (the SID factor, the shift in pixels)."""
        pose, rest, per_set = x[:6], x[6:], []
        for _ in range(self.sets):
            sid = 1.0 + (rest[0] / 100.0 if self.sid else 0.0)  # in per cent
            rest = rest[1:] if self.sid else rest
            shift = rest[:2] if self.shift else np.zeros(2)
            rest = rest[2:] if self.shift else rest
            per_set.append((sid, np.asarray(shift, dtype=np.float64)))
        return pose, per_set * self.views if self.shared else per_set

    def bounds(
        self, reach_mm: float, reach_deg: float, max_sid_change: float, max_shift_px: float
    ) -> list[tuple[float, float]]:
        per = ([(-100 * max_sid_change, 100 * max_sid_change)] if self.sid else []) + (
            [(-max_shift_px, max_shift_px)] * 2 if self.shift else []
        )
        return [(-reach_mm, reach_mm)] * 3 + [(-reach_deg, reach_deg)] * 3 + per * self.sets


def _check_estimable(views: Sequence[XRayImage], estimate: Sequence[str]) -> None:
    unknown = set(estimate) - set(INTRINSICS)
    if unknown:
        raise ValueError(f"cannot estimate {sorted(unknown)}: choose from {', '.join(INTRINSICS)}")
    if len(views) < 2:
        raise ValueError(
            "one view cannot tell its source-image distance from the depth, nor its principal point from an "
            "in-plane translation: estimating the geometry needs two planes (or give --sid-mm / --pixel-mm)"
        )


def refine_geometry(
    volume_renderer: DRRRenderer,
    views: Sequence[XRayImage],
    motion: ArrayLike,
    *,
    estimate: Sequence[str] = INTRINSICS,
    image_px: int = 128,
    volume_level: int = 1,
    reach_mm: float = 4.0,
    reach_deg: float = 3.0,
    max_sid_change: float = 0.10,
    max_shift_px: float = 20.0,
    evaluations: int = 1500,
    shared: bool = False,
) -> GeometryRefinement:
    """Polish the pose (six parameters, +- ``reach_mm`` / ``reach_deg`` around ``motion``) and each
    view's ``estimate``\\ d intrinsics on the gradient difference of ``image_px`` DRRs.

    ``volume_renderer``: the registration's renderer; ``views``: two or more views of one moment
    with their nominal geometry; ``motion``: the registration's estimate (4x4). ValueError for one
    view (see the module) or an unknown name in ``estimate``. ``shared``: the views come from one
    detector (one C-arm at several angulations of a still patient): one set of intrinsics for all
    of them; with three or more angulations the principal point's shift across the orbit becomes
    observable, along the patient's long axis it does not (docs/validation/geometry.md)."""
    began = time.perf_counter()
    views = tuple(views)
    _check_estimable(views, estimate)
    start = check_rigid(motion, name="motion")
    problem = LevelProblem.prepare(volume_renderer, views, image_px=image_px, volume_level=volume_level,
                                   motion=start, margin_mm=None)  # fmt: skip
    space = SearchSpace.for_views(views[0].geometry, start, optimize_tz=True, bound_mm=reach_mm, bound_deg=reach_deg)
    params = _Parameters(len(views), "sid" in estimate, "principal_point" in estimate, shared)
    unpack = params.unpack
    # per view: the level's pixels per full-resolution pixel (the shift is in the file's pixels)
    ratio = [pv.geometry.pixel_mm[1] / v.geometry.pixel_mm[1] for pv, v in zip(problem.views, views, strict=True)]

    buffers = [np.empty((pv.geometry.rows, pv.geometry.cols), np.float32) for pv in problem.views]
    count = [0]

    def cost(x: Array) -> float:
        pose, per_view = unpack(np.asarray(x, dtype=np.float64))
        m = space.motion(pose)
        total = 0.0
        for pv, buf, r, (sid, shift) in zip(problem.views, buffers, ratio, per_view, strict=True):
            g = with_intrinsics(pv.geometry, sid, shift / r)
            drr = volume_renderer.render(g, m, level=problem.volume_level, mask=pv.mask, out=buf)
            total += pv.measure(drr)
        count[0] += 1
        return -total / len(views)

    x0 = np.zeros(params.size)
    bounds = params.bounds(reach_mm, reach_deg, max_sid_change, max_shift_px)
    before = -cost(x0)
    found = minimize(cost, x0, method="Powell", bounds=bounds, options={"maxfev": evaluations, "xtol": 1e-3})
    pose, per_view = unpack(np.asarray(found.x, dtype=np.float64))
    refined_views, intrinsics = [], []
    for view, (sid, shift) in zip(views, per_view, strict=True):
        g = with_intrinsics(view.geometry, sid, shift)
        refined_views.append(replace(view, geometry=g))
        intrinsics.append(ViewIntrinsics(g.sid_mm, sid - 1.0, (float(-shift[0]), float(-shift[1]))))
    return GeometryRefinement(
        patient_motion=space.motion(pose),
        views=tuple(refined_views),
        intrinsics=tuple(intrinsics),
        estimated=tuple(e for e in INTRINSICS if e in estimate),
        similarity=-float(found.fun),
        similarity_before=before,
        evaluations=count[0],
        seconds=time.perf_counter() - began,
    )


#: The second pass of :func:`estimate_geometry`: image size (pixels across), its reach around
#: the first pass (mm, degrees, source-image distance fraction) and its evaluations.
FINE_IMAGE_PX = 256
FINE_REACH = (2.0, 2.0, 0.03)
FINE_EVALUATIONS = 600


@with_one_blas_thread
def estimate_geometry(
    volume: Volume,
    renderer: DRRRenderer,
    views: Sequence[XRayImage],
    motion: ArrayLike,
    *,
    estimate: Sequence[str] = ("sid",),
    fine_image_px: int = FINE_IMAGE_PX,
    fine_evaluations: int = FINE_EVALUATIONS,
    shared: bool = False,
) -> GeometryRefinement:
    """:func:`refine_geometry` on the registration's levels (``renderer``: 128 px, level 1), then
    :func:`refine_on_own_grid` from its estimate: the first pass leaves the source-image distance
    0.2-1.8 % off (a coarse level's bias), the second 0.06-0.41 % (decision record
    2026-12-04-geometry-estimate). The result is relative to ``views``."""
    coarse = refine_geometry(renderer, views, motion, estimate=estimate, shared=shared)
    return refine_on_own_grid(volume, views, coarse, estimate=estimate, image_px=fine_image_px,
                              evaluations=fine_evaluations, shared=shared)  # fmt: skip


def refine_on_own_grid(
    volume: Volume,
    views: Sequence[XRayImage],
    first: GeometryRefinement,
    *,
    estimate: Sequence[str] = ("sid",),
    image_px: int = FINE_IMAGE_PX,
    evaluations: int = FINE_EVALUATIONS,
    shared: bool = False,
) -> GeometryRefinement:
    """The second pass of :func:`estimate_geometry`: :func:`refine_geometry` from ``first`` (a
    first pass on ``views``) on the volume's own grid (level 0, prepared here for the views) at
    ``image_px``, within :data:`FINE_REACH`. The result is relative to ``views``; its
    evaluations and seconds are both passes', its similarities the second pass's (one level)."""
    from registration.core.prepare import Reach, prepare_volume

    views = tuple(views)
    iso = views[0].geometry.isocenter_mm
    reach_mm, reach_deg, sid_reach = FINE_REACH
    reach = Reach.of_search(reach_mm, reach_deg, initial_motion=first.patient_motion, isocenter_mm=iso)
    level0 = prepare_volume(volume, [v.geometry for v in first.views], reach=reach, levels=(0,))
    fine = refine_geometry(level0.renderer, first.views, first.patient_motion, estimate=estimate,
                           image_px=image_px, volume_level=0, reach_mm=reach_mm, reach_deg=reach_deg,
                           max_sid_change=sid_reach, evaluations=evaluations, shared=shared)  # fmt: skip
    intrinsics = []
    for view, before, found in zip(views, first.intrinsics, fine.intrinsics, strict=True):
        shift = np.add(before.principal_point_shift_px, found.principal_point_shift_px)
        intrinsics.append(ViewIntrinsics(found.sid_mm, found.sid_mm / view.geometry.sid_mm - 1.0,
                                         (float(shift[0]), float(shift[1]))))  # fmt: skip
    return replace(
        fine,
        intrinsics=tuple(intrinsics),
        evaluations=first.evaluations + fine.evaluations,
        seconds=first.seconds + fine.seconds,
    )
