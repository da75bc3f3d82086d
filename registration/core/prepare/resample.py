"""Isotropic level grids in millimetres: block averages or trilinear resampling."""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from registration.core.prepare.params import (
    SNAP_TOLERANCE,
)
from registration.core.prepare.reach import _axes_and_spacing
from registration.core.volume import Volume

Array = NDArray[np.float64]


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
