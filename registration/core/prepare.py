"""The volume a registration needs, not the one it was given.

A scanner's CT holds far more than the X-ray field sees (a 511 mm field of view, the neck,
shoulders and couch) on a grid the scanner chose (1 x 1 x 3 mm, 0.5 x 0.5 x 2.5 mm, ...). A
registration only ever renders the part of the volume that rays through the collimated field
can reach while the search moves the anatomy within its bounds, and only at the resolutions
of its pyramid. :func:`prepare_volume` makes that volume once:

0. **The body** (:func:`probe_blocks`): the patient's body is found on blocks of about
   ``CROP_PROBE_MM`` (mostly above ``BODY_HU``, opened by ``BODY_OPENING_MM`` so that a CT's
   couch, head rest and immobilisation mask are cut off where thin parts join them to the body,
   its large parts, holes filled, grown by ``BODY_KEEP_MM``); what lies outside it, and air
   below ``AIR_HU`` anywhere, is set to -1000 HU in the prepared levels
   (:func:`mask_outside_body`): the angiography suite has its own table, the CT's couch is not
   in its images, and the renderer's rays leap over the exact zeros (:mod:`registration.core.drr`).
   (Images formed from the CT itself keep its couch: the DRRs then lack it, a small handicap.)
1. **Crop** (:func:`needed_box`): keep the voxels that hold tissue of the body (above
   ``TISSUE_HU``; the noisy air of a CT around the head is dropped, its attenuation is ~0) and that some ray
   through a view's field can reach under any motion of the search (:class:`Reach`: a
   translation and a rotation about the iso-center, every voxel displaced by at most
   ``translation_mm + 2 sin(rotation / 2) |X - c|``). The crop never changes a DRR inside
   the field for motions within the reach; it only removes what no such ray meets.
2. **Resample per pyramid level to isotropic grids chosen in millimetres**
   (:func:`level_spacing_mm`): level ``L`` has voxels of ``D / (256 / 2**L)`` mm, where ``D``
   is the diameter at the iso-center of what the image can show of the anatomy (the field's
   diameter there, or the anatomy's extent across the beam when that is smaller). So level 2,
   the capture level, has voxels as large as the pixels of a 64-pixel image of the field at
   the iso-center (2.85 mm for a 27 cm format), level 1, the polish level, those of a 128-pixel
   image (1.42 mm): DRR samples as fine as the image pixels they are compared with, whatever
   grid the scanner used, but level 0 is never finer than the volume's own finest spacing
   (resampling adds no detail; levels L then have 2**L times that): a 0.5 x 0.5 x 2.5 mm CT
   gets 1.42 and 2.85 mm at levels 1 and 2 of a 27 cm field, a 1 x 1 x 3 mm CT 2 and 4 mm,
   a coarse 64^3 volume its own pyramid. When a
   level's spacing lies within ``SNAP_TOLERANCE`` of a power-of-two multiple of an isotropic
   volume's own spacing (a 3DRA whose format is the image format), that grid is used and made
   by block averages, exactly the volume's own pyramid.
3. **Cache** (:func:`prepare_volume`): what does not depend on the views (the probe blocks
   and, per level spacing, the body's box of the volume resampled and set to air outside the
   body: :class:`PreparedBase`) is kept per volume (by identity) and, given a ``store``
   (:class:`PreparationStore`, for example :class:`registration.io.cache.PreparationCache` on
   disk), per volume content (a SHA-256 of its voxels and affine, with the preparation's
   parameters and ``PREPARE_VERSION``): a later process skips the resampling. Each view's
   levels are slices of the base levels (the level grid's voxels covering the view's crop
   box), so a cached and a freshly built preparation hold the same voxels. The prepared levels
   and their renderer are also kept per volume (by identity), per view and per reach, and
   reused by later registrations whose views and searches they cover.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, check_rigid, invert_rigid, rotation_angle_deg
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: Voxels above this HU are tissue (skin, fat at -100, soft tissue, bone); a CT's air lies at
#: -1000 +- noise and contributes ~0 attenuation: the crop drops what lies outside the tissue.
TISSUE_HU = -500.0
#: Image pixels across the field at pyramid level 0 (level L: 256 / 2**L).
LEVEL0_PIXELS = 256
#: A level's spacing this close (relative) to a power-of-two multiple of an isotropic volume's
#: own spacing uses that grid (block averages of the volume, no resampling).
SNAP_TOLERANCE = 0.1
#: Grid step (mm) at which the crop tests voxels for reach (each tested block counts whole).
CROP_PROBE_MM = 4.0
#: Cached preparations kept in memory (each holds a few million voxels).
CACHE_ENTRIES = 4
#: Levels prepared by default: the capture and refine level (2) and the polish level (1).
DEFAULT_LEVELS = (1, 2)
#: The body (:func:`body_blocks`): probe blocks mostly (at least half their voxels) above this
#: HU are body (fat -100, skin, soft tissue, bone); the CT's couch, head rest and mask are too.
BODY_HU = -300.0
#: Structures thinner than this (mm) that join the body (a couch plate, a head rest's legs, a
#: thermoplastic mask) are cut at the join by a morphological opening of this width.
BODY_OPENING_MM = 20.0
#: What lies within this (mm) of the opened body is kept (skin, ears and nose the opening
#: shaved, the interpolation at the skin); everything farther is set to air.
BODY_KEEP_MM = 12.0
#: Voxels below this HU are air (their attenuation, < 10 % of water's, is a CT's noise around
#: -1000 HU): set to -1000 with the outside of the body, so that rays leap over them.
AIR_HU = -900.0
#: Bump when what a preparation computes changes (it is part of the keys of stored bases).
PREPARE_VERSION = 1
#: Parts of the opened body at least this share of the largest one are body (a head and, cut
#: from it by the scan's edge or the opening, shoulders); smaller ones (pieces of a couch or a
#: mask the opening left) are not.
BODY_PART_SHARE = 0.1
#: The body is used only if its parts hold at least this share of the body blocks (a body, not
#: a collection of small objects).
BODY_MIN_SHARE = 0.5


@dataclass(frozen=True)
class Reach:
    """How far the search may move anatomy from where the volume shows it.

    Every point X moves by at most ``translation_mm + 2 sin(rotation_deg / 2) |X - c|`` with
    c the iso-center: a rigid motion within the reach is a rotation of at most
    ``rotation_deg`` about c followed by a translation of at most ``translation_mm``.
    """

    translation_mm: float
    rotation_deg: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.translation_mm) and self.translation_mm >= 0):
            raise ValueError(f"reach translation must be finite and >= 0 mm, got {self.translation_mm}")
        if not (math.isfinite(self.rotation_deg) and 0 <= self.rotation_deg <= 180):
            raise ValueError(f"reach rotation must lie in [0, 180] degrees, got {self.rotation_deg}")

    @classmethod
    def of_search(
        cls,
        bound_mm: float,
        bound_deg: float,
        *,
        initial_motion: ArrayLike | None = None,
        isocenter_mm: ArrayLike = (0.0, 0.0, 0.0),
        translations: int = 3,
    ) -> Reach:
        """The reach of a search of +-``bound_mm`` on ``translations`` view-frame axes and
        +-``bound_deg`` on three rotation angles about the iso-center, around ``initial_motion``."""
        t_search = bound_mm * math.sqrt(translations)
        # three Euler angles of at most b each compose to a rotation of at most ~ sqrt(3) b
        theta_search = min(180.0, bound_deg * math.sqrt(3.0) * 1.05)
        search = cls(t_search, theta_search)
        return search if initial_motion is None else search.around(initial_motion, isocenter_mm)

    def around(self, motion: ArrayLike, isocenter_mm: ArrayLike = (0.0, 0.0, 0.0)) -> Reach:
        """The reach of this search started at ``motion`` instead of at the volume's pose: the
        motion's shift of the iso-center c and its rotation added (and the search's rotation of
        the moved iso-center)."""
        return self._moved(check_rigid(motion, name="initial motion"), isocenter_mm)

    def _moved(self, m: Array, isocenter_mm: ArrayLike) -> Reach:
        c = np.asarray(isocenter_mm, dtype=np.float64)
        t_init = float(np.linalg.norm(m[:3, :3] @ c + m[:3, 3] - c))
        theta_init = rotation_angle_deg(m)
        # the search rotates the moved iso-center
        lever = 2.0 * math.sin(math.radians(self.rotation_deg) / 2.0) * t_init
        return Reach(self.translation_mm + t_init + lever, min(180.0, self.rotation_deg + theta_init))

    def grown(self, translation_mm: float, rotation_deg: float) -> Reach:
        """This reach with some slack added."""
        return Reach(self.translation_mm + translation_mm, min(180.0, self.rotation_deg + rotation_deg))

    def covers(self, other: Reach) -> bool:
        return self.translation_mm >= other.translation_mm - 1e-9 and self.rotation_deg >= other.rotation_deg - 1e-9

    def displacement_mm(self, distance_mm: ArrayLike) -> NDArray[np.float64]:
        """The largest displacement of points at ``distance_mm`` from the iso-center."""
        lever = 2.0 * math.sin(math.radians(self.rotation_deg) / 2.0)
        return self.translation_mm + lever * np.asarray(distance_mm, dtype=np.float64)


def _axes_and_spacing(volume: Volume) -> tuple[Array, Array]:
    lin = volume.index_to_world[:3, :3]
    spacing = np.linalg.norm(lin, axis=0)
    return lin / spacing, spacing


def field_extent_mm(geometry: CArm) -> float:
    """Diameter of the collimated field at the iso-center (mm)."""
    return geometry.field_diameter_mm / geometry.magnification


def level_spacing_mm(extent_mm: float, level: int) -> float:
    """Voxel size (mm) of pyramid ``level`` for an image showing ``extent_mm`` at the iso-center:
    the pixel of a ``256 / 2**level``-pixel image of it."""
    if not math.isfinite(extent_mm) or extent_mm <= 0:
        raise ValueError(f"extent must be positive, got {extent_mm} mm")
    if isinstance(level, bool) or int(level) != level or level < 0:
        raise ValueError(f"level must be an integer >= 0, got {level}")
    return float(extent_mm) * 2**level / LEVEL0_PIXELS


def _reach_mask(points: Array, geometries: Sequence[CArm], reach: Reach, margin_mm: float) -> NDArray[np.bool_]:
    """Points (N, 3) that a ray through some view's field meets under a motion within ``reach``."""
    needed = np.zeros(len(points), dtype=bool)
    for g in geometries:
        iso = np.asarray(g.isocenter_mm)
        delta = reach.displacement_mm(np.linalg.norm(points - iso, axis=1)) + margin_mm
        p = g.projection_matrix
        h = points @ p[:, :3].T + p[:, 3]
        depth = h[:, 2]  # distance from the source along the detector normal (mm)
        ahead = depth > delta + 1.0
        safe = np.where(ahead, depth, 1.0)
        col, row = h[:, 0] / safe, h[:, 1] / safe
        x = (col - (g.cols - 1) / 2.0) * g.pixel_mm[1]
        y = (row - (g.rows - 1) / 2.0) * g.pixel_mm[0]
        r_det = np.hypot(x, y)
        focal = g.sid_mm  # source to detector (nominal; calibrated shifts are sub-millimetre)
        # a displacement delta at depth a moves the projection by at most delta * focal / (a - delta)
        slack = delta * focal / np.maximum(safe - delta, 1.0) * (1.0 + r_det / focal)
        needed |= ahead & (r_det - slack <= g.field_diameter_mm / 2.0)
    return needed


@dataclass(frozen=True)
class ProbeBlocks:
    """The volume seen in blocks of about ``CROP_PROBE_MM`` (``step`` voxels along i, j, k).

    ``tissue[bk, bj, bi]``: some voxel of the block is above the tissue threshold; ``body``:
    the block lies within ``BODY_KEEP_MM`` of the patient's body (:func:`probe_blocks`), None
    when no single body was found (then nothing is removed as outside it).
    """

    step: NDArray[np.int64]
    tissue: NDArray[np.bool_]
    body: NDArray[np.bool_] | None

    @property
    def needed(self) -> NDArray[np.bool_]:
        """Blocks whose tissue a DRR of the prepared volume can meet."""
        return self.tissue if self.body is None else self.tissue & self.body


@numba.njit(parallel=True, cache=True)
def _block_counts(data, sk, sj, si, tissue_hu, body_hu, any_out, count_out) -> None:  # noqa: ANN001
    """Per block: whether a voxel is above ``tissue_hu``, how many are above ``body_hu``."""
    nk, nj, ni = data.shape
    for b in numba.prange(any_out.shape[0]):
        for k in range(b * sk, min((b + 1) * sk, nk)):
            for j in range(nj):
                cj = j // sj
                for i in range(ni):
                    v = data[k, j, i]
                    ci = i // si
                    if v > tissue_hu:
                        any_out[b, cj, ci] = 1
                    if v > body_hu:
                        count_out[b, cj, ci] += 1


def probe_blocks(volume: Volume, *, tissue_hu: float = TISSUE_HU, body: bool = True) -> ProbeBlocks:
    """The volume's tissue per probe block, and (``body``) the patient's body.

    The body: blocks mostly above ``BODY_HU``, opened by a box of ``BODY_OPENING_MM`` (what
    joins the body through anything thinner, a CT's couch under the head rest, a mask, is cut
    off there), its large connected parts, their holes filled (sinuses, airways), grown by
    ``BODY_KEEP_MM``; its parts are the connected pieces of at least ``BODY_PART_SHARE`` of
    the largest. A CT's couch, head rest and the air around the patient lie outside and are
    set to air in the prepared levels (as are voxels below ``AIR_HU``): an angiography suite
    has its own table, and rays leap over empty space. None when the parts hold less than
    ``BODY_MIN_SHARE`` of the body blocks.
    """
    _, spacing = _axes_and_spacing(volume)
    nk, nj, ni = volume.shape
    step = np.maximum(1, np.round(CROP_PROBE_MM / spacing).astype(np.int64))  # (i, j, k)
    si, sj, sk = (int(x) for x in step)
    shape = (-(-nk // sk), -(-nj // sj), -(-ni // si))
    tissue = np.zeros(shape, dtype=np.uint8)
    counts = np.zeros(shape, dtype=np.int32)
    data = volume.data if volume.data.dtype == np.float32 else volume.data.astype(np.float32)
    _block_counts(np.ascontiguousarray(data), sk, sj, si, float(tissue_hu), BODY_HU, tissue, counts)
    if not body:
        return ProbeBlocks(step, tissue.astype(bool), None)
    # voxels per block (the last block along an axis may be partial)
    sizes = [np.minimum(s, n - np.arange(b) * s) for s, n, b in zip((sk, sj, si), (nk, nj, ni), shape, strict=True)]
    seed = 2 * counts >= sizes[0][:, None, None] * sizes[1][None, :, None] * sizes[2][None, None, :]
    block_mm = (step * spacing)[::-1]  # (k, j, i)
    opening = tuple(2 * max(1, round(BODY_OPENING_MM / 2.0 / b)) + 1 for b in block_mm)
    opened = ndimage.maximum_filter(ndimage.minimum_filter(seed, size=opening, mode="nearest"), size=opening,
                                    mode="nearest")  # fmt: skip
    labels, n = ndimage.label(opened)
    if n == 0:
        return ProbeBlocks(step, tissue.astype(bool), None)
    sizes_of = np.bincount(labels.ravel())
    sizes_of[0] = 0
    parts = sizes_of >= BODY_PART_SHARE * sizes_of.max()
    if sizes_of[parts].sum() < BODY_MIN_SHARE * seed.sum():
        return ProbeBlocks(step, tissue.astype(bool), None)
    core = _fill_holes(parts[labels])
    keep = tuple(2 * math.ceil(BODY_KEEP_MM / b) + 1 for b in block_mm)
    grown = ndimage.maximum_filter(core, size=keep, mode="constant", cval=False)
    return ProbeBlocks(step, tissue.astype(bool), grown)


def _fill_holes(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``mask`` with the background parts that do not reach the array's faces filled (the
    same as ``ndimage.binary_fill_holes``, by one labelling instead of repeated dilations)."""
    background, n = ndimage.label(~mask)
    if n == 0:
        return mask
    faces = [background[[0, -1]], background[:, [0, -1]], background[..., [0, -1]]]
    open_to_faces = np.zeros(n + 1, dtype=bool)
    for face in faces:
        open_to_faces[face.ravel()] = True
    open_to_faces[0] = False  # label 0: the mask itself
    return ~open_to_faces[background]


def mask_outside_body(level: Volume, volume: Volume, blocks: ProbeBlocks) -> Volume:
    """``level`` (a grid of ``volume``'s region) with the voxels outside the body set to air."""
    if blocks.body is None:
        return level
    # level index -> source index; the level grids keep the source's axes (diagonal map)
    a = volume.index_from_world @ level.index_to_world
    nk, nj, ni = level.shape
    nb = blocks.body.shape[::-1]  # (i, j, k)
    if np.abs(a[:3, :3] - np.diag(np.diag(a[:3, :3]))).max() > 1e-6 * np.abs(a[:3, :3]).max():
        raise ValueError("the level's axes differ from the volume's")
    idx = []
    for ax, n in enumerate((ni, nj, nk)):
        src = a[ax, ax] * np.arange(n) + a[ax, 3]
        idx.append(np.clip(np.floor((src + 0.5) / blocks.step[ax]).astype(np.int64), 0, nb[ax] - 1))
    inside = blocks.body[np.ix_(idx[2], idx[1], idx[0])]
    inside &= level.data > AIR_HU
    if inside.all():
        return level
    return Volume(np.where(inside, level.data, np.float32(-1000.0)), level.index_to_world, label=level.label,
                  meta=level.meta)  # fmt: skip


def needed_box(
    volume: Volume,
    geometries: Sequence[CArm],
    reach: Reach,
    *,
    margin_mm: float = 0.0,
    tissue_hu: float = TISSUE_HU,
    blocks: ProbeBlocks | None = None,
    center_motion: ArrayLike | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Index box (lo, hi inclusive, as (i, j, k)) of the tissue some field ray can reach.

    Voxels are tested in blocks of about ``CROP_PROBE_MM``: a block counts when any voxel in
    it is above ``tissue_hu`` and its center is within reach (the margin adds the block's half
    diagonal) and the box grows by ``margin_mm`` on every side (the partial-volume edge of the
    tissue and interpolation). None when no tissue is within reach. ``blocks``: the probe
    blocks (:func:`probe_blocks`) when the caller has them; with a body, only its blocks count
    (a CT's couch and the air around the patient are not kept). ``center_motion``: the reach
    is about this motion of the patient (motions ``S @ center_motion`` with S within ``reach``:
    a crop around where a tracked patient is now) instead of about the volume's own pose.
    """
    if not geometries:
        raise ValueError("at least one view geometry is needed to crop a volume")
    _, spacing = _axes_and_spacing(volume)
    nk, nj, ni = volume.shape
    if blocks is None:
        blocks = probe_blocks(volume, tissue_hu=tissue_hu, body=False)
    step = blocks.step
    si, sj, sk = (int(x) for x in step)
    needed = blocks.needed
    half_diagonal = 0.5 * float(np.linalg.norm(step * spacing))
    center = None if center_motion is None else check_rigid(center_motion, name="center motion")

    def any_kept(kk: NDArray[np.int64], jj: NDArray[np.int64], ii: NDArray[np.int64]) -> bool:
        centers = np.stack([(ii + 0.5) * si - 0.5, (jj + 0.5) * sj - 0.5, (kk + 0.5) * sk - 0.5], axis=1)
        world = centers @ volume.index_to_world[:3, :3].T + volume.index_to_world[:3, 3]
        if center is not None:
            world = world @ center[:3, :3].T + center[:3, 3]  # where the moved patient has them
        return bool(_reach_mask(world, geometries, reach, margin_mm + half_diagonal).any())

    # The box is the extent of the kept blocks: along each axis, from either end, the first slab
    # of blocks holding a kept one. The same box as testing every block; usually a few slabs
    # are tested (all of them only when nothing is within reach).
    ends = []  # (k, j, i): (first, last) block index
    for axis in range(3):
        occupied = np.flatnonzero(needed.any(axis=tuple(a for a in range(3) if a != axis)))
        found = []
        for order in (occupied, occupied[::-1]):
            for b in order:
                u, v = np.nonzero(np.take(needed, b, axis=axis))
                index = [u, v]
                index.insert(axis, np.full(u.size, b, dtype=np.int64))
                if any_kept(*index):
                    found.append(int(b))
                    break
            else:
                return None  # no block within reach
        ends.append(found)
    (k0, k1), (j0, j1), (i0, i1) = ends
    pad = np.ceil(margin_mm / spacing).astype(np.int64)  # the tissue's partial-volume edge and interpolation
    lo = np.array([i0 * si, j0 * sj, k0 * sk], dtype=np.int64) - pad
    hi = np.array([(i1 + 1) * si - 1, (j1 + 1) * sj - 1, (k1 + 1) * sk - 1], dtype=np.int64) + pad
    return np.maximum(lo, 0), np.minimum(hi, np.array([ni - 1, nj - 1, nk - 1]))


def _crop(volume: Volume, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> Volume:
    data = volume.data[lo[2] : hi[2] + 1, lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
    affine = volume.index_to_world.copy()
    affine[:3, 3] = volume.index_to_world[:3, :3] @ lo + volume.index_to_world[:3, 3]
    return Volume(np.ascontiguousarray(data), affine, label=volume.label, meta=volume.meta)


def _snap_factor(spacing: Array, target_mm: float) -> int | None:
    """The power-of-two block size of an isotropic grid that lands within the tolerance."""
    if np.ptp(spacing) > 1e-3 * spacing.max():
        return None
    ratio = target_mm / float(spacing[0])
    factor = 2 ** max(0, round(math.log2(ratio))) if ratio > 0 else 1
    return factor if abs(factor / ratio - 1.0) <= SNAP_TOLERANCE else None


def resample_isotropic(
    volume: Volume, spacing_mm: float, lo: ArrayLike | None = None, hi: ArrayLike | None = None
) -> Volume:
    """The volume (or its index box ``lo..hi``) on an isotropic grid of ``spacing_mm``.

    The grid keeps the volume's own axes (their directions, not their spacing) and covers the
    box; values are trilinear samples of the volume smoothed against aliasing along each
    axis it coarsens (Gaussian, sigma = (ratio - 1) / 2 source voxels). Outside the volume: air.
    """
    spacing_mm = float(spacing_mm)
    if not math.isfinite(spacing_mm) or spacing_mm <= 0:
        raise ValueError(f"spacing_mm must be positive, got {spacing_mm}")
    axes, spacing = _axes_and_spacing(volume)
    nk, nj, ni = volume.shape
    lo_i = np.zeros(3, dtype=np.int64) if lo is None else np.asarray(lo, dtype=np.int64)
    hi_i = np.array([ni - 1, nj - 1, nk - 1], dtype=np.int64) if hi is None else np.asarray(hi, dtype=np.int64)
    ratio = spacing_mm / spacing
    sigma = np.maximum(0.0, (ratio - 1.0) / 2.0)  # (i, j, k), in source voxels
    pad = np.ceil(3 * sigma + 1).astype(np.int64)
    a = np.maximum(lo_i - pad, 0)
    b = np.minimum(hi_i + pad, [ni - 1, nj - 1, nk - 1])
    src = volume.data[a[2] : b[2] + 1, a[1] : b[1] + 1, a[0] : b[0] + 1]
    if np.any(sigma > 0.05):
        src = ndimage.gaussian_filter(src, sigma[::-1], mode="nearest", truncate=3.0)
    extent_mm = (hi_i - lo_i) * spacing
    n = np.maximum(np.floor(extent_mm / spacing_mm + 1e-6).astype(np.int64) + 1, 2)  # (i, j, k)
    # center the new grid on the box
    start_idx = lo_i + ((hi_i - lo_i) * spacing - (n - 1) * spacing_mm) / 2.0 / spacing
    # trilinear samples; the grids share their axes, so the weights are separable. Outside: air.
    tables = [_axis_table(start_idx[ax] - a[ax] + np.arange(n[ax]) * ratio[ax], src.shape[2 - ax]) for ax in range(3)]
    out = np.empty((n[2], n[1], n[0]), dtype=np.float32)
    _trilinear_grid(np.ascontiguousarray(src, dtype=np.float32), *tables[0], *tables[1], *tables[2], out)
    affine = np.eye(4)
    affine[:3, :3] = axes * spacing_mm
    affine[:3, 3] = volume.index_to_world[:3, :3] @ start_idx + volume.index_to_world[:3, 3]
    return Volume(out, affine, label=volume.label, meta=volume.meta)


def _axis_table(coords: Array, n: int) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.bool_]]:
    """Lower neighbour, weight of the upper one, and inside-ness of sample ``coords`` on an axis of ``n``."""
    i0 = np.clip(np.floor(coords).astype(np.int64), 0, max(n - 2, 0))
    w = np.clip(coords - i0, 0.0, 1.0).astype(np.float32)
    inside = (coords >= -1e-6) & (coords <= n - 1 + 1e-6)
    return i0, w, inside


@numba.njit(parallel=True, cache=True, fastmath=True)
def _trilinear_grid(src, i0, wi, ini, j0, wj, inj, k0, wk, ink, out) -> None:  # noqa: ANN001
    """out[k, j, i] = trilinear sample of src at (k0[k] + wk[k], j0[j] + wj[j], i0[i] + wi[i])."""
    nk, nj, ni = out.shape
    sk, sj, si = src.shape
    for k in numba.prange(nk):
        ka = k0[k]
        kb = min(ka + 1, sk - 1)
        fk = wk[k]
        for j in range(nj):
            ja = j0[j]
            jb = min(ja + 1, sj - 1)
            fj = wj[j]
            for i in range(ni):
                if not (ink[k] and inj[j] and ini[i]):
                    out[k, j, i] = -1000.0
                    continue
                ia = i0[i]
                ib = min(ia + 1, si - 1)
                fi = wi[i]
                c00 = src[ka, ja, ia] + fi * (src[ka, ja, ib] - src[ka, ja, ia])
                c01 = src[ka, jb, ia] + fi * (src[ka, jb, ib] - src[ka, jb, ia])
                c10 = src[kb, ja, ia] + fi * (src[kb, ja, ib] - src[kb, ja, ia])
                c11 = src[kb, jb, ia] + fi * (src[kb, jb, ib] - src[kb, jb, ia])
                c0 = c00 + fj * (c01 - c00)
                c1 = c10 + fj * (c11 - c10)
                out[k, j, i] = c0 + fk * (c1 - c0)


@dataclass
class PreparedVolume:
    """A volume cropped and resampled for the views and search it was prepared for.

    ``levels[L]`` is pyramid level L (None when it was not prepared); ``renderer`` renders
    them and keeps ``volume`` (the original) as its identity.
    """

    volume: Volume
    levels: tuple[Volume | None, ...]
    spacing_mm: tuple[float | None, ...]
    #: Index box of the original volume that was kept ((i, j, k) low and high, inclusive).
    box_lo: tuple[int, int, int]
    box_hi: tuple[int, int, int]
    reach: Reach
    geometries: tuple[CArm, ...]
    seconds: float
    renderer: DRRRenderer = field(repr=False)
    #: Whether the levels hold only the body (what lies outside it set to air, ``probe_blocks``).
    body: bool = False
    #: Where the view-independent part came from: "built", "memory" or "disk" (a store).
    base_source: str = "built"
    #: What the levels hold (:class:`Crop`; also :func:`crop_of` the renderer).
    crop: Crop | None = field(default=None, repr=False)

    @property
    def voxels_per_level(self) -> list[int | None]:
        return [None if v is None else int(np.prod(v.shape)) for v in self.levels]

    def summary(self) -> dict:
        """JSON-ready description (spacing, shape and voxels per level, crop, time)."""
        return {
            "spacing_mm": list(self.spacing_mm),
            "shape_per_level": [None if v is None else list(v.shape[::-1]) for v in self.levels],
            "voxels_per_level": self.voxels_per_level,
            "source_voxels": int(np.prod(self.volume.shape)),
            "box_lo": list(self.box_lo),
            "box_hi": list(self.box_hi),
            "reach": {"translation_mm": self.reach.translation_mm, "rotation_deg": self.reach.rotation_deg},
            "body_only": self.body,
            "base_source": self.base_source,
            "prepare_seconds": self.seconds,
            "complete": None if self.crop is None else self.crop.complete,
        }


def _field_key(geometry: CArm) -> tuple:
    """What the crop and the spacing depend on: the projection of the whole field (not the
    number of pixels it is sampled with)."""
    g = geometry.resized(64, 64)
    return tuple(np.round(g.projection_matrix.ravel() / np.linalg.norm(g.projection_matrix[2, :3]), 5))


def _anatomy_extent_mm(volume: Volume, lo: NDArray[np.int64], hi: NDArray[np.int64], geometry: CArm) -> float:
    """Largest extent of the box across the beam (mm), projected to the iso-center plane."""
    idx = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)
    corners = idx @ volume.index_to_world[:3, :3].T + volume.index_to_world[:3, 3]
    view = corners @ geometry.view_from_world[:3, :3].T + geometry.view_from_world[:3, 3]
    return float(max(np.ptp(view[:, 0]), np.ptp(view[:, 1])))


class PreparationStore(Protocol):
    """Where prepared bases outlive a process (:class:`registration.io.cache.PreparationCache`).

    ``load`` returns the arrays stored under ``key`` (a JSON-ready dict), or None when there
    are none or they cannot be read (a store never raises for a damaged entry: the preparation
    is then built again and saved over it); ``save`` stores them (atomically).
    """

    def load(self, kind: str, key: dict) -> dict[str, np.ndarray] | None: ...

    def save(self, kind: str, key: dict, arrays: dict[str, np.ndarray]) -> None: ...


@dataclass(frozen=True)
class PreparedBase:
    """What a preparation computes whatever the views: the probe blocks and, per pyramid
    level, the volume's box of needed tissue (the body's, all views alike) on the level's grid,
    set to air outside the body. A view's levels are slices of these (:func:`_slice_level`).
    ``source``: "built", or "memory" / "disk" where it was found."""

    blocks: ProbeBlocks
    levels: dict[int, Volume]
    box_lo: NDArray[np.int64]
    box_hi: NDArray[np.int64]
    source: str = "built"


def volume_digest(volume: Volume) -> str:
    """SHA-256 of the volume's voxels (float32, C order), shape and affine: what a stored
    preparation belongs to (hashing its 94 MB takes ~0.1 s; decoding the series 0.4 s)."""
    h = hashlib.sha256()
    h.update(json.dumps([list(volume.shape), str(volume.data.dtype)]).encode())
    h.update(np.ascontiguousarray(volume.index_to_world, dtype=np.float64).tobytes())
    h.update(memoryview(np.ascontiguousarray(volume.data)).cast("B"))
    return h.hexdigest()


def _blocks_key(digest: str, body: bool) -> dict:
    return {
        "volume_sha256": digest,
        "prepare_version": PREPARE_VERSION,
        "body": body,
        "thresholds_hu": [TISSUE_HU, BODY_HU, AIR_HU],
        "probe_mm": CROP_PROBE_MM,
        "body_mm": [BODY_OPENING_MM, BODY_KEEP_MM],
        "body_shares": [BODY_PART_SHARE, BODY_MIN_SHARE],
    }


def _levels_key(blocks_key: dict, targets: dict[int, float], margin_mm: float) -> dict:
    return blocks_key | {
        "targets_mm": [[lv, round(t, 9)] for lv, t in sorted(targets.items())],
        "margin_mm": round(margin_mm, 9),
        "snap_tolerance": SNAP_TOLERANCE,
    }


def _blocks_arrays(blocks: ProbeBlocks) -> dict[str, np.ndarray]:
    out = {"step": np.asarray(blocks.step, dtype=np.int64), "tissue": np.asarray(blocks.tissue, dtype=bool)}
    if blocks.body is not None:
        out["body"] = np.asarray(blocks.body, dtype=bool)
    return out


def _blocks_from(arrays: dict[str, np.ndarray], volume: Volume) -> ProbeBlocks | None:
    """The stored probe blocks, None unless they fit ``volume`` (a foreign or damaged entry)."""
    try:
        step = np.asarray(arrays["step"])
        tissue = np.asarray(arrays["tissue"])
        body = arrays.get("body")
        if step.shape != (3,) or step.dtype != np.int64 or np.any(step < 1) or tissue.dtype != bool:
            return None
        shape = tuple(-(-n // int(s)) for n, s in zip(volume.shape, step[::-1], strict=True))
        if tissue.shape != shape or (body is not None and (body.dtype != bool or body.shape != shape)):
            return None
    except (KeyError, TypeError, ValueError):
        return None
    return ProbeBlocks(step, tissue, None if body is None else np.asarray(body))


def _base_arrays(base: PreparedBase) -> dict[str, np.ndarray]:
    out = {"box": np.stack([base.box_lo, base.box_hi]).astype(np.int64)}
    for lv, v in base.levels.items():
        out[f"level{lv}"] = v.data
        out[f"affine{lv}"] = v.index_to_world
    return out


def _base_from(
    arrays: dict[str, np.ndarray], volume: Volume, blocks: ProbeBlocks, levels: Sequence[int]
) -> PreparedBase | None:
    """The stored levels, None unless they are those of ``levels`` for ``volume``'s grid."""
    try:
        box = np.asarray(arrays["box"])
        if box.shape != (2, 3) or box.dtype != np.int64:
            return None
        built = {}
        for lv in levels:
            data, affine = np.asarray(arrays[f"level{lv}"]), np.asarray(arrays[f"affine{lv}"])
            if data.dtype != np.float32 or data.ndim != 3 or affine.shape != (4, 4) or affine.dtype != np.float64:
                return None
            level = Volume(data, affine, label=volume.label, meta=volume.meta)
            a = volume.index_from_world @ level.index_to_world  # the level keeps the volume's axes
            if np.abs(a[:3, :3] - np.diag(np.diag(a[:3, :3]))).max() > 1e-6 * np.abs(a[:3, :3]).max():
                return None
            built[int(lv)] = level
    except (KeyError, TypeError, ValueError):
        return None
    return PreparedBase(blocks, built, box[0], box[1], source="disk")


def _build_levels(
    volume: Volume, targets: dict[int, float], lo: NDArray[np.int64], hi: NDArray[np.int64], blocks: ProbeBlocks
) -> tuple[dict[int, Volume], NDArray[np.int64], NDArray[np.int64]]:
    """The levels of ``targets`` (level -> spacing) over the index box ``lo..hi``, set to air
    outside the body; and the box they cover (aligned for block averages)."""
    nk, nj, ni = volume.shape
    top = np.array([ni - 1, nj - 1, nk - 1], dtype=np.int64)
    _, spacing = _axes_and_spacing(volume)
    snaps = {lv: _snap_factor(spacing, t) for lv, t in targets.items()}
    largest = max([f for f in snaps.values() if f is not None], default=1)
    if largest > 1:  # crop on block boundaries, so block averages are the volume's own pyramid's
        lo = (lo // largest) * largest
        span = np.maximum(-(-(hi - lo + 1) // largest) * largest, 2 * largest)
        hi = np.minimum(lo + span - 1, top)
    base = _crop(volume, lo, hi) if any(f is not None for f in snaps.values()) else None
    built: dict[int, Volume] = {}
    for lv in sorted(targets):  # finest first
        finer = built.get(lv - 1)
        if snaps[lv] is not None and base is not None:
            built[lv] = base.downsample(snaps[lv]) if snaps[lv] > 1 else base
        elif finer is not None and abs(targets[lv] / float(finer.spacing_mm[0]) - 2.0) < 1e-6 and min(finer.shape) >= 4:
            built[lv] = finer.downsample(2)
        elif finer is not None and abs(targets[lv] - float(finer.spacing_mm[0])) < 1e-6:
            built[lv] = finer
        else:
            built[lv] = resample_isotropic(volume, targets[lv], lo, hi)
    # outside the body: air
    return {lv: mask_outside_body(v, volume, blocks) for lv, v in built.items()}, lo, hi


def _slice_level(level: Volume, volume: Volume, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> Volume:
    """The voxels of ``level`` (a grid of ``volume``'s axes) that span the source index box
    ``lo..hi``: from the voxel nearest its low face to the one nearest its high face (the box
    holds the crop's margin of two coarsest voxels; at least two voxels along each axis)."""
    a = volume.index_from_world @ level.index_to_world  # level index -> source index (diagonal)
    scale, offset = np.diag(a)[:3], a[:3, 3]
    n = np.array(level.shape[::-1], dtype=np.int64)  # (i, j, k)
    g_lo = np.round((lo - offset) / scale).astype(np.int64)
    g_hi = np.round((hi - offset) / scale).astype(np.int64)
    g_lo = np.clip(g_lo, 0, n - 2)
    g_hi = np.clip(np.maximum(g_hi, g_lo + 1), 1, n - 1)
    if np.all(g_lo == 0) and np.all(g_hi == n - 1):
        return level
    data = level.data[g_lo[2] : g_hi[2] + 1, g_lo[1] : g_hi[1] + 1, g_lo[0] : g_hi[0] + 1]
    affine = level.index_to_world.copy()
    affine[:3, 3] = level.index_to_world[:3, :3] @ g_lo + level.index_to_world[:3, 3]
    return Volume(np.ascontiguousarray(data), affine, label=level.label, meta=level.meta)


_BLOCKS: OrderedDict[tuple, tuple[Volume, ProbeBlocks]] = OrderedDict()
_BASES: OrderedDict[tuple, tuple[Volume, PreparedBase]] = OrderedDict()


def _remember(table: OrderedDict, key: tuple, value: tuple) -> None:
    with _CACHE_LOCK:
        table[key] = value
        table.move_to_end(key)
        while len(table) > CACHE_ENTRIES:
            table.popitem(last=False)


def _recall(table: OrderedDict, key: tuple, volume: Volume):  # noqa: ANN202
    with _CACHE_LOCK:
        hit = table.get(key)
        if hit is None or hit[0] is not volume:
            return None
        table.move_to_end(key)
        return hit[1]


class _Digest:
    """The volume's digest, computed once and only when a store asks for it."""

    def __init__(self, volume: Volume) -> None:
        self.volume, self._value = volume, None

    def __call__(self) -> str:
        if self._value is None:
            self._value = volume_digest(self.volume)
        return self._value


def _probe(volume: Volume, body: bool, store: PreparationStore | None, remember: bool, digest: _Digest) -> ProbeBlocks:
    key = (id(volume), body)
    blocks = _recall(_BLOCKS, key, volume) if remember else None
    if blocks is not None:
        return blocks
    if store is not None:
        stored = store.load("prepared-blocks", _blocks_key(digest(), body))
        blocks = None if stored is None else _blocks_from(stored, volume)
    if blocks is None:
        blocks = probe_blocks(volume, body=body)
        if store is not None:
            store.save("prepared-blocks", _blocks_key(digest(), body), _blocks_arrays(blocks))
    if remember:
        _remember(_BLOCKS, key, (volume, blocks))
    return blocks


def _base(
    volume: Volume, blocks: ProbeBlocks, targets: dict[int, float], margin_mm: float, body: bool,
    store: PreparationStore | None, remember: bool, digest: _Digest,
) -> PreparedBase:  # fmt: skip
    """The base levels of ``targets``: remembered, stored, or built over the needed tissue's box."""
    key = (id(volume), body, tuple(sorted(targets.items())), round(margin_mm, 9))
    base = _recall(_BASES, key, volume) if remember else None
    if base is not None:
        return PreparedBase(base.blocks, base.levels, base.box_lo, base.box_hi, source="memory")
    if store is not None:
        stored = store.load("prepared-levels", _levels_key(_blocks_key(digest(), body), targets, margin_mm))
        base = None if stored is None else _base_from(stored, volume, blocks, sorted(targets))
    if base is None:
        nk, nj, ni = volume.shape
        full = (np.zeros(3, dtype=np.int64), np.array([ni - 1, nj - 1, nk - 1], dtype=np.int64))
        lo, hi = _tissue_box(volume, blocks, margin_mm) or full
        levels, lo, hi = _build_levels(volume, targets, lo, hi, blocks)
        base = PreparedBase(blocks, levels, lo, hi)
        if store is not None:
            store.save("prepared-levels", _levels_key(_blocks_key(digest(), body), targets, margin_mm),
                       _base_arrays(base))  # fmt: skip
    if remember:
        _remember(_BASES, key, (volume, base))
    return base


def _tissue_box(
    volume: Volume, blocks: ProbeBlocks, margin_mm: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Index box (lo, hi inclusive, (i, j, k)) of the needed blocks (tissue of the body) grown
    by ``margin_mm``: what any view's crop (:func:`needed_box`) lies within."""
    _, spacing = _axes_and_spacing(volume)
    nk, nj, ni = volume.shape
    si, sj, sk = (int(x) for x in blocks.step)
    kk, jj, ii = np.nonzero(blocks.needed)
    if kk.size == 0:
        return None
    pad = np.ceil(margin_mm / spacing).astype(np.int64)
    lo = np.array([ii.min() * si, jj.min() * sj, kk.min() * sk], dtype=np.int64) - pad
    hi = np.array([(ii.max() + 1) * si - 1, (jj.max() + 1) * sj - 1, (kk.max() + 1) * sk - 1], dtype=np.int64) + pad
    return np.maximum(lo, 0), np.minimum(hi, np.array([ni - 1, nj - 1, nk - 1]))


def _prepare(
    volume: Volume, geometries: tuple[CArm, ...], reach: Reach, levels: tuple[int, ...], body: bool,
    store: PreparationStore | None = None, remember: bool = True,
) -> PreparedVolume:  # fmt: skip
    start = time.perf_counter()
    digest = _Digest(volume)
    _, spacing = _axes_and_spacing(volume)
    nk, nj, ni = volume.shape
    full = (np.zeros(3, dtype=np.int64), np.array([ni - 1, nj - 1, nk - 1], dtype=np.int64))
    # the coarsest level's voxels plus a voxel of the source for interpolation at the crop's faces
    extent_guess = max(field_extent_mm(g) for g in geometries)
    margin = 2.0 * level_spacing_mm(extent_guess, max(levels)) + float(spacing.max())
    blocks = _probe(volume, body, store, remember, digest)
    lo, hi = needed_box(volume, geometries, reach, margin_mm=margin, blocks=blocks) or full
    extent = min(extent_guess, max(_anatomy_extent_mm(volume, lo, hi, g) for g in geometries))
    # level 0 never finer than the volume's own finest spacing (resampling cannot add detail)
    base_mm = max(level_spacing_mm(extent, 0), float(spacing.min()))
    targets = {lv: base_mm * 2**lv for lv in levels}
    base = _base(volume, blocks, targets, margin, body, store, remember, digest)
    return _assemble(volume, geometries, reach, np.eye(4), levels, base, margin, lo, hi, start)


def _assemble(
    volume: Volume, geometries: tuple[CArm, ...], reach: Reach, center: Array, levels: tuple[int, ...],
    base: PreparedBase, margin_mm: float, lo: NDArray[np.int64], hi: NDArray[np.int64], start: float,
) -> PreparedVolume:  # fmt: skip
    """The view's crop ``lo..hi``: the base levels' voxels that cover it, their renderer, and
    the :class:`Crop` that says what they hold (kept for :func:`crop_of`)."""
    sliced = {lv: _slice_level(v, volume, lo, hi) for lv, v in base.levels.items()}
    pyramid = tuple(sliced.get(lv) for lv in range(max(levels) + 1))
    renderer = DRRRenderer(volume, levels=list(pyramid))
    tissue = _tissue_box(volume, base.blocks, margin_mm)
    complete = tissue is None or bool(np.all(lo <= tissue[0]) and np.all(hi >= tissue[1]))
    crop = Crop(
        volume=volume, geometries=geometries, reach=reach, center_motion=np.array(center, dtype=np.float64),
        levels=levels, box_lo=tuple(int(x) for x in lo), box_hi=tuple(int(x) for x in hi),  # type: ignore[arg-type]
        complete=complete, margin_mm=float(margin_mm), base=base,
    )  # fmt: skip
    with _CACHE_LOCK:
        _CROPS[renderer] = crop
    return PreparedVolume(
        volume=volume,
        levels=pyramid,
        spacing_mm=tuple(None if v is None else float(v.spacing_mm.max()) for v in pyramid),
        box_lo=crop.box_lo,
        box_hi=crop.box_hi,
        reach=reach,
        geometries=geometries,
        seconds=time.perf_counter() - start,
        renderer=renderer,
        body=base.blocks.body is not None,
        base_source=base.source,
        crop=crop,
    )


@dataclass(frozen=True, eq=False)
class Crop:
    """What a preparation's levels hold: the tissue of the volume's index box ``box_lo..box_hi``
    ((i, j, k), inclusive), which holds everything a ray through ``geometries`` meets while the
    patient's motion is ``S @ center_motion`` with S within ``reach`` (about the views'
    iso-center, CONVENTIONS §4). Outside that the levels may lack anatomy: a DRR at such a
    motion can be missing tissue at the field's edge. ``complete``: the box holds all of the
    body's tissue (no motion can need more). ``base``: the levels it was sliced from (a new
    crop is sliced from them too: :func:`recrop`)."""

    volume: Volume = field(repr=False)
    geometries: tuple[CArm, ...]
    reach: Reach
    center_motion: Array
    levels: tuple[int, ...]
    box_lo: tuple[int, int, int]
    box_hi: tuple[int, int, int]
    complete: bool
    margin_mm: float
    base: PreparedBase = field(repr=False)

    def margin(self, motion: ArrayLike, search: Reach) -> tuple[float, float]:
        """What is left of the crop's reach (mm at the iso-center, degrees) when a search of
        ``search`` starts at the patient motion ``motion``; negative: that search can render
        anatomy the crop lacks. Infinite for a complete crop."""
        if self.complete:
            return math.inf, math.inf
        # a tracker asks after every applied frame: its poses are rigid already (no check_rigid)
        moved = np.asarray(motion, dtype=np.float64) @ invert_rigid(self.center_motion)
        need = search._moved(moved, self.geometries[0].isocenter_mm)
        return self.reach.translation_mm - need.translation_mm, self.reach.rotation_deg - need.rotation_deg


#: The crop behind each prepared renderer (weak: a renderer no longer used is forgotten).
_CROPS: weakref.WeakKeyDictionary[DRRRenderer, Crop] = weakref.WeakKeyDictionary()


def crop_of(renderer: DRRRenderer) -> Crop | None:
    """The :class:`Crop` of a renderer made by :func:`prepare_volume` or :func:`recrop` (None
    for any other renderer, e.g. a pyramid of the whole volume: nothing is missing from it)."""
    with _CACHE_LOCK:
        return _CROPS.get(renderer)


def recrop(crop: Crop, center_motion: ArrayLike, reach: Reach) -> PreparedVolume:
    """The crop's levels again, around the patient motion ``center_motion`` and for ``reach``
    about it: the same grids (slices of the same base levels, so a DRR of anatomy both crops
    hold is the same), another box. Not cached. Used by a tracker whose patient moved toward
    the crop's edge (:mod:`registration.core.tracking`)."""
    start = time.perf_counter()
    center = check_rigid(center_motion, name="center motion")
    volume = crop.volume
    found = needed_box(volume, crop.geometries, reach, margin_mm=crop.margin_mm, blocks=crop.base.blocks,
                       center_motion=center)  # fmt: skip
    if found is None:  # no tissue within reach of the fields: keep all of it
        found = _tissue_box(volume, crop.base.blocks, crop.margin_mm)
    if found is None:
        found = (np.asarray(crop.box_lo, dtype=np.int64), np.asarray(crop.box_hi, dtype=np.int64))
    lo, hi = found
    return _assemble(volume, crop.geometries, reach, center, crop.levels, crop.base, crop.margin_mm, lo, hi, start)


_CACHE: OrderedDict[tuple, tuple[Volume, PreparedVolume]] = OrderedDict()
_CACHE_LOCK = threading.Lock()


def prepare_volume(
    volume: Volume,
    geometries: CArm | Sequence[CArm],
    *,
    reach: Reach | None = None,
    levels: Sequence[int] = DEFAULT_LEVELS,
    cache: bool = True,
    body: bool = True,
    store: PreparationStore | None = None,
) -> PreparedVolume:
    """The cropped, resampled pyramid of ``volume`` for ``geometries`` (cached per volume).

    ``reach``: how far the search may move the anatomy (default: the default search of
    +-30 mm and +-15 degrees, :meth:`Reach.of_search`). ``levels``: the pyramid levels to
    prepare. ``body``: keep only the patient's body (:func:`probe_blocks`: a CT's couch, head
    rest and the air around set to air). A cached preparation of the same volume object for the same fields and levels
    whose reach covers ``reach`` is returned as it is (its ``seconds`` are those of its making).
    ``store``: where the view-independent part (:class:`PreparedBase`) is looked up by the
    volume's content and saved (``PreparedVolume.base_source`` says "disk" when it came from
    there). ``cache=False``: nothing remembered, looked up or stored.
    """
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a Volume, got {type(volume).__name__}")
    views = (geometries,) if isinstance(geometries, CArm) else tuple(geometries)
    if not views or not all(isinstance(g, CArm) for g in views):
        raise ValueError("geometries must be one or more CArm views")
    levels_t = tuple(sorted({int(lv) for lv in levels}))
    if not levels_t or levels_t[0] < 0:
        raise ValueError(f"levels must be integers >= 0, got {list(levels)}")
    reach = reach or Reach.of_search(30.0, 15.0)
    key = (id(volume), tuple(_field_key(g) for g in views), levels_t, bool(body))
    if cache:
        with _CACHE_LOCK:
            hit = _CACHE.get(key)
            if hit is not None and hit[0] is volume and hit[1].reach.covers(reach):
                _CACHE.move_to_end(key)
                return hit[1]
    prepared = _prepare(volume, views, reach, levels_t, bool(body), store if cache else None, remember=cache)
    if cache:
        _remember(_CACHE, key, (volume, prepared))
    return prepared


def clear_cache() -> None:
    """Forget every cached preparation (and the remembered bases and probe blocks)."""
    with _CACHE_LOCK:
        _CACHE.clear()
        _BASES.clear()
        _BLOCKS.clear()
