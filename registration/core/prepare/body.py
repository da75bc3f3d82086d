"""The patient's body on probe blocks, and the air set outside it."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from registration.core.geometry import CArm, check_rigid
from registration.core.prepare.params import (
    AIR_HU,
    BODY_HU,
    BODY_KEEP_MM,
    BODY_MIN_SHARE,
    BODY_OPENING_MM,
    BODY_PART_SHARE,
    CROP_PROBE_MM,
    TISSUE_HU,
)
from registration.core.prepare.reach import Reach, _axes_and_spacing, _reach_mask
from registration.core.protrusions import with_protrusions
from registration.core.volume import Volume

Array = NDArray[np.float64]


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
    core, _ = with_protrusions(_fill_holes(parts[labels]), seed, block_mm)
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
    out = np.empty(level.shape, dtype=np.float32)
    _masked_copy(level.data, blocks.body.view(np.uint8), idx[2], idx[1], idx[0], np.float32(AIR_HU), out)
    return Volume(out, level.index_to_world, label=level.label, meta=level.meta)


def body_region(volume: Volume, lo: ArrayLike, hi: ArrayLike, blocks: ProbeBlocks) -> Volume:
    """The index box ``lo..hi`` ((i, j, k), inclusive) of ``volume`` with the voxels outside the
    body set to air: ``mask_outside_body`` of the box's crop, in one pass over the source."""
    lo_i, hi_i = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    affine = volume.index_to_world.copy()
    affine[:3, 3] = volume.index_to_world[:3, :3] @ lo_i + volume.index_to_world[:3, 3]
    data = volume.data[lo_i[2] : hi_i[2] + 1, lo_i[1] : hi_i[1] + 1, lo_i[0] : hi_i[0] + 1]
    if blocks.body is None:
        return Volume(data, affine, label=volume.label, meta=volume.meta)
    nb = blocks.body.shape[::-1]  # (i, j, k)
    idx = [np.clip((lo_i[ax] + np.arange(hi_i[ax] - lo_i[ax] + 1)) // int(blocks.step[ax]), 0, nb[ax] - 1)
           for ax in range(3)]  # fmt: skip
    out = np.empty(data.shape, dtype=np.float32)
    _masked_copy(data, blocks.body.view(np.uint8), idx[2], idx[1], idx[0], np.float32(AIR_HU), out)
    return Volume(out, affine, label=volume.label, meta=volume.meta)


@numba.njit(parallel=True, cache=True)
def _masked_copy(data, body, bk, bj, bi, air_hu, out) -> None:  # noqa: ANN001
    """``out`` = ``data`` where its body block is set and the voxel is denser than ``air_hu``,
    else -1000 (air)."""
    nk, nj, ni = data.shape
    air = np.float32(-1000.0)
    for k in numba.prange(nk):
        for j in range(nj):
            for i in range(ni):
                v = np.float32(data[k, j, i])
                out[k, j, i] = v if body[bk[k], bj[j], bi[i]] and v > air_hu else air


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
