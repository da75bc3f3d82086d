"""One level of a registration, prepared once and shared by its capture runs.

A :class:`LevelProblem` holds, for every view (an :class:`XRayImage`: image, field mask and
geometry), the image at the level's resolution, the pixels that may be compared (the field
mask, less the rays that graze the volume's support) and the prepared gradient difference;
plus the pyramid level of the volume the DRRs come from. All of it is read-only: each thread
that evaluates the cost takes an :class:`Evaluator`, which owns only scratch buffers.

The measure of several views is a weighted mean of their gradient differences. Each view's value
is already normalised by its number of compared pixels (it lies in (0, 2], see
:class:`GradientDifference`), so a view's size, format or pixel count gives it no weight: a large
lateral image does not outweigh a small frontal one, and neither view's measure can dominate by
its scale. The weights (``field_share_weights``) are each view's share of its own field that it
compares (the field less the rays that graze the volume's support): a view whose field the
patient has partly left, or that sees much beyond the 3DRA's reconstructed cylinder, counts for
what it still compares (docs/decisions/2026-12-06-planes-weighted-by-field-share.md); without
them the plain mean. With one view the measure is that view's gradient difference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.core.similarity import GradientDifference
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: A support mask is used only if it keeps at least this share of the field's pixels.
MIN_SUPPORT_SHARE = 0.25


def support_mask(volume: Volume, geometry: CArm, motion: ArrayLike, margin_mm: float) -> NDArray[np.bool_]:
    """Pixels whose rays pass through the volume's support shrunk by ``margin_mm``.

    The support is the volume's box intersected with the cylinder (axis along the volume's
    k axis) inscribed in it: a cone-beam 3DRA reconstructs only that cylinder, and a CT box
    contains it. Rays that graze the support's outline see its truncation edge, which the
    X-ray image does not have; ``motion`` (a rigid 4x4) places the volume as in the DRR.
    """
    rows, cols = np.mgrid[0 : geometry.rows, 0 : geometry.cols]
    targets = geometry.pixel_to_world(cols, rows).reshape(-1, 3)
    index_from_world = volume.index_from_world @ np.linalg.inv(np.asarray(motion, dtype=np.float64))
    src = index_from_world[:3, :3] @ geometry.source_mm + index_from_world[:3, 3]
    dirs = targets @ index_from_world[:3, :3].T + index_from_world[:3, 3] - src
    spacing = volume.spacing_mm
    # Work in index units scaled to mm along each axis (the 3DRA grids are orthogonal).
    src_mm, dirs_mm = src * spacing, dirs * spacing
    n = np.array(volume.shape[::-1], dtype=np.float64)  # (ni, nj, nk)
    lo, hi = np.full(3, margin_mm) - 0.5 * spacing, (n - 0.5) * spacing - margin_mm
    # The inscribed cylinder about the k axis.
    center = (n[:2] - 1) / 2.0 * spacing[:2]
    radius = min(n[0] * spacing[0], n[1] * spacing[1]) / 2.0 - margin_mm
    p, d = src_mm[:2] - center, np.ascontiguousarray(dirs_mm[:, :2])
    a = np.sum(d * d, axis=1)
    b = 2.0 * d @ p
    c = p @ p - radius * radius
    out = np.empty(a.shape[0], dtype=np.bool_)
    _support_hits(src_mm, np.ascontiguousarray(dirs_mm), lo, hi, a, b, c, radius, out)
    return out.reshape(geometry.rows, geometry.cols)


@numba.njit(cache=True)
def _support_hits(src, dirs, lo, hi, a, b, c, radius, out) -> None:  # noqa: ANN001
    """Per ray ``src + t dirs``: whether it crosses the box [lo, hi] within the cylinder (``a``,
    ``b``, ``c``: its quadratic in t; ``radius`` <= 0: no cylinder): the slab intervals of the
    box (a ray parallel to a slab must start inside it), then the cylinder's, in the operations
    and order of the NumPy statement (``test_support_mask_equals_its_definition``)."""
    for n in range(dirs.shape[0]):
        near, far, outside = -np.inf, np.inf, False
        for k in range(3):
            t1 = (lo[k] - src[k]) / dirs[n, k]
            t2 = (hi[k] - src[k]) / dirs[n, k]
            if np.isfinite(t1):
                near = max(near, _nan_min(t1, t2))
                far = min(far, _nan_max(t1, t2))
            if dirs[n, k] == 0.0 and (src[k] < lo[k] or src[k] > hi[k]):
                outside = True
        if outside:
            far = -np.inf
        disc = b[n] * b[n] - 4 * a[n] * c
        if disc > 0 and a[n] > 0 and radius > 0:
            root = math.sqrt(disc)
            near = _nan_max(near, (-b[n] - root) / (2 * a[n]))
            far = _nan_min(far, (-b[n] + root) / (2 * a[n]))
        else:
            far = -np.inf
        out[n] = far > near


@numba.njit(cache=True, inline="always")
def _nan_min(x, y):  # noqa: ANN001, ANN202
    return x if (x != x or x <= y) and y == y else y  # np.minimum: NaN if either is


@numba.njit(cache=True, inline="always")
def _nan_max(x, y):  # noqa: ANN001, ANN202
    return x if (x != x or x >= y) and y == y else y  # np.maximum: NaN if either is


def level_factor(geometry: CArm, image_px: int, voxel_mm: float) -> int:
    """Block size that brings ``geometry``'s image to about ``image_px`` pixels across.

    Pixels stay as fine as the volume level's voxels (``voxel_mm``) seen at the iso-center
    when those are finer: a volume much smaller than the image still gets enough pixels
    (the support mask keeps their number small). The factor divides rows and cols.
    """
    factor_image = max(1, round(geometry.cols / image_px))
    voxel_px = voxel_mm * geometry.magnification / max(geometry.pixel_mm)
    factor = min(factor_image, 2 ** max(0, math.floor(math.log2(max(voxel_px, 1.0)))))
    while factor > 1 and (geometry.rows % factor or geometry.cols % factor):
        factor -= 1
    return factor


def iso_pixel_mm(geometry: CArm, factor: int) -> float:
    """The size at the iso-center of a ``factor``-block-averaged pixel of ``geometry`` (mm)."""
    return factor * max(geometry.pixel_mm) / geometry.magnification


def matched_factor(geometry: CArm, image_px: int, voxel_mm: float, pixel_at_iso_mm: float) -> int:
    """The block size of a further view of a multi-view level: its pixel at the iso-center as
    close to the first view's (``pixel_at_iso_mm``) as it can be without being coarser.

    Every view then samples the anatomy alike (no view gets more pixels, hence more weight
    in cost and time, because of its detector's pixel size) and the result is never coarser
    than :func:`level_factor`'s rule for the view alone would give. Plane B of the biplane
    study (22 cm / 384 px, magnification 1.51) compared 96 px and 192 px images beside plane
    A's 64 and 128 by the power-of-two rule: 2.25x the pixels for the same anatomy.
    """
    own = level_factor(geometry, image_px, voxel_mm)
    cap = max(own, round(geometry.cols / image_px))
    best = own
    for factor in range(own, cap + 1):
        if geometry.rows % factor or geometry.cols % factor:
            continue
        if iso_pixel_mm(geometry, factor) <= pixel_at_iso_mm * (1.0 + 1e-6):
            best = factor
    return best


@dataclass(frozen=True)
class PreparedView:
    """One view at one level: its geometry, its image, the compared pixels and the prepared
    measure (set up when first used: the depth scans compare the image high-passed instead)."""

    geometry: CArm
    mask: NDArray[np.bool_]
    image: NDArray[np.floating]

    @cached_property
    def measure(self) -> GradientDifference:
        return GradientDifference(self.image, self.mask)

    @property
    def pixel_at_iso_mm(self) -> float:
        """The level's pixel at the iso-center (mm)."""
        return iso_pixel_mm(self.geometry, 1)


@dataclass(frozen=True)
class LevelProblem:
    """The cost of one level, prepared once: ``-sum_v w_v GD_v(DRR_v(x)) / sum_v w_v`` over the
    views (``weights`` w_v; None: all 1)."""

    renderer: DRRRenderer
    volume_level: int
    views: tuple[PreparedView, ...]
    weights: tuple[float, ...] | None = None

    @classmethod
    def prepare(
        cls,
        renderer: DRRRenderer,
        views: tuple[XRayImage, ...],
        *,
        image_px: int,
        volume_level: int,
        motion: Array,
        margin_mm: float | None,
        pixel_at_iso_mm: float | None = None,
        field_share_weights: bool = False,
    ) -> LevelProblem:
        """Downsample each view, mask it to the support seen at ``motion``, set up GD.

        The first view's block size follows :func:`level_factor`, further views match its
        pixel at the iso-center (:func:`matched_factor`); ``pixel_at_iso_mm`` makes every view
        match that size instead (plane B's own capture at plane A's resolution).
        ``field_share_weights``: several views are weighted by the share of their field that
        they compare (see the module's docstring).
        """
        level = renderer_level(renderer, volume_level)
        voxel_mm = float(renderer.level_volume(level).spacing_mm.max())
        prepared = []
        shares = []
        first_pixel_mm = 0.0 if pixel_at_iso_mm is None else float(pixel_at_iso_mm)
        for n, view in enumerate(views):
            if n == 0 and pixel_at_iso_mm is None:
                factor = level_factor(view.geometry, image_px, voxel_mm)
                first_pixel_mm = iso_pixel_mm(view.geometry, factor)
            else:
                factor = matched_factor(view.geometry, image_px, voxel_mm, first_pixel_mm)
            image = view.downsample(factor) if factor > 1 else view
            mask = image.mask
            if margin_mm is not None:
                inside = mask & support_mask(renderer.volume, image.geometry, motion, margin_mm)
                # Keep the whole field when the support would leave too little to compare.
                if inside.sum() >= MIN_SUPPORT_SHARE * mask.sum():
                    mask = inside
            prepared.append(PreparedView(image.geometry, mask, image.image))
            shares.append(float(mask.sum()) / max(1.0, float(image.mask.sum())))
        weights = tuple(shares) if field_share_weights and len(prepared) > 1 else None
        return cls(renderer, level, tuple(prepared), weights)

    def evaluator(self, *, parallel: bool | None = None) -> Evaluator:
        """A cost function of the motion for one thread (its own scratch buffers)."""
        return Evaluator(self, parallel)


def renderer_level(renderer: DRRRenderer, volume_level: int) -> int:
    """The pyramid level the DRRs of a search level come from (the coarsest there is if the
    volume has fewer levels). The one place that picks the per-level volume."""
    return min(volume_level, renderer.n_levels - 1)


class Evaluator:
    """``evaluator(motion) -> cost`` for one thread: renders each view's DRR into its own
    buffer and scores it with its own copy of the measure's scratch space.

    ``parallel``: None or True when this evaluator has the cores to itself (one annealing
    run, the polish): the views render one after the other, each on every core (no thread
    hand-over per evaluation, no core idle while the other view finishes). False when capture
    runs already fill the cores: each view renders serially in the caller's thread.
    """

    def __init__(self, problem: LevelProblem, parallel: bool | None) -> None:
        self.problem = problem
        self.parallel = parallel
        self._measures = [v.measure.with_scratch() for v in problem.views]
        self._buffers = [np.empty((v.geometry.rows, v.geometry.cols), np.float32) for v in problem.views]

    @property
    def drrs_per_evaluation(self) -> int:
        return len(self._measures)

    @property
    def rays_per_evaluation(self) -> int:
        """DRR pixels one evaluation renders (the compared pixels of every view)."""
        return int(sum(int(v.mask.sum()) for v in self.problem.views))

    def _score(self, n: int, motion: Array, parallel: bool | None) -> float:
        p, view = self.problem, self.problem.views[n]
        drr = p.renderer.render(view.geometry, motion, level=p.volume_level, mask=view.mask, parallel=parallel,
                                out=self._buffers[n])  # fmt: skip
        return self._measures[n](drr)

    def similarity(self, motion: Array) -> float:
        """The views' gradient differences, averaged with the problem's weights (higher is more
        similar)."""
        n_views = len(self._measures)
        scores = [self._score(n, motion, self.parallel) for n in range(n_views)]
        weights = self.problem.weights
        if weights is None:
            return (scores[0] + sum(scores[1:])) / n_views
        return sum(w * v for w, v in zip(weights, scores, strict=True)) / sum(weights)

    def per_view(self, motion: Array) -> list[float]:
        """Each view's gradient difference at ``motion`` (the parts of :meth:`similarity`)."""
        p = self.problem
        return [
            measure(p.renderer.render(view.geometry, motion, level=p.volume_level, mask=view.mask, out=out))
            for view, measure, out in zip(p.views, self._measures, self._buffers, strict=True)
        ]
