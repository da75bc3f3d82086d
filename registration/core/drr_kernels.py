"""The DRR renderer's compiled kernels (numba): the rays' set-up and clipping, Joseph's marcher
with its empty-space leaps, the trilinear marcher, and the distance map the leaps read.
:class:`registration.core.drr.DRRRenderer` is their only caller; the method is described there."""

from __future__ import annotations

import math
import types

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.geometry import CArm, check_rigid

#: Image rows per work item of the parallel loop (small: balances threads when the machine
#: is shared and the mask or the clipped volume makes some rows cheaper than others).
_ROW_CHUNK = 4

#: Below this many samples (pixels x largest volume dimension) the serial kernel is used.
_SERIAL_SAMPLES = 100_000

#: Zero voxels padded on every side of the volume copies the kernels read (see _render_joseph).
_PAD = 2

#: Edge (voxels) of the blocks whose distance to attenuation lets rays leap over empty space.
_BLOCK_SHIFT = 1
_BLOCK = 1 << _BLOCK_SHIFT
#: Rays leap only from blocks at least this far (in blocks) from attenuation.
_LEAP_MIN = 3


# --------------------------------------------------------------------------------------
# Ray set-up shared by both renderers
# --------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _ray_setup(p: np.ndarray, index_from_world: np.ndarray, motion: np.ndarray, out_source, out_a) -> int:
    """Source and ray directions in voxel indices; returns 0, or 1 if ``motion`` is not rigid.

    ``P = K [I | -S]``: S = -inv(K) p4 and the ray through (c, r) runs along inv(K) (c, r, 1).
    The volume moved by M is seen through P @ M, so source and rays are moved by inv(M).
    """
    # rigidity of the motion: finite, last row (0, 0, 0, 1), orthonormal block, det > 0
    for i in range(4):
        for j in range(4):
            if not np.isfinite(motion[i, j]):
                return 1
    if abs(motion[3, 0]) > 1e-9 or abs(motion[3, 1]) > 1e-9 or abs(motion[3, 2]) > 1e-9:
        return 1
    if abs(motion[3, 3] - 1.0) > 1e-9:
        return 1
    for i in range(3):
        for j in range(3):
            dot = motion[0, i] * motion[0, j] + motion[1, i] * motion[1, j] + motion[2, i] * motion[2, j]
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-6:
                return 1
    det = (
        motion[0, 0] * (motion[1, 1] * motion[2, 2] - motion[1, 2] * motion[2, 1])
        - motion[0, 1] * (motion[1, 0] * motion[2, 2] - motion[1, 2] * motion[2, 0])
        + motion[0, 2] * (motion[1, 0] * motion[2, 1] - motion[1, 1] * motion[2, 0])
    )
    if det <= 0:
        return 1
    k_inv = np.ascontiguousarray(np.linalg.inv(np.ascontiguousarray(p[:, :3])))
    source_world = -(k_inv @ np.ascontiguousarray(p[:, 3]))
    # volume_from_world = inv(M) = [R^T | -R^T t]
    rt = motion[:3, :3].T.copy()
    t = motion[:3, 3].copy()
    src_vol = rt @ (source_world - t)
    lin = index_from_world[:3, :3].copy()
    out_source[:] = lin @ src_vol + index_from_world[:3, 3]
    out_a[:, :] = lin @ (rt @ k_inv)
    return 0


_IDENTITY = np.eye(4)


def _rays_in_index_space(
    index_from_world: NDArray[np.float64], geometry: CArm, motion: ArrayLike | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Source (3,) and the 3x3 ``A`` with direction(col, row) = A @ (col, row, 1), in voxel indices.

    The ray parameter t runs from the source (t = 0): X(t) = S + t * A @ (c, r, 1).
    """
    if not isinstance(geometry, CArm):
        raise ValueError(f"geometry must be a CArm, got {type(geometry).__name__}")
    if motion is None:
        m = _IDENTITY
    else:
        m = np.asarray(motion, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"motion must be a 4x4 matrix, got shape {m.shape}")
    source = np.empty(3)
    a_mat = np.empty((3, 3))
    if _ray_setup(geometry.projection_matrix, index_from_world, m, source, a_mat) != 0:
        check_rigid(m, name="motion")  # raises with the reason
        raise ValueError("motion is not a rigid transform")
    return source, a_mat


# --------------------------------------------------------------------------------------
# The compiled kernels
# --------------------------------------------------------------------------------------
@numba.njit(cache=True, fastmath=True, inline="always")
def _clip(
    s0: float, s1: float, s2: float, d0: float, d1: float, d2: float, lo: np.ndarray, hi: np.ndarray
) -> tuple[float, float]:
    """Slab clip of X(t) = S + t D to the box [lo, hi] (index space), t >= 0."""
    tmin = 0.0
    tmax = 1e30
    s = (s0, s1, s2)
    d = (d0, d1, d2)
    for a in range(3):
        if abs(d[a]) < 1e-12:
            if s[a] < lo[a] or s[a] > hi[a]:
                return 1.0, 0.0
        else:
            inv = 1.0 / d[a]
            t0 = (lo[a] - s[a]) * inv
            t1 = (hi[a] - s[a]) * inv
            if t0 > t1:
                t0, t1 = t1, t0
            if t0 > tmin:
                tmin = t0
            if t1 < tmax:
                tmax = t1
    return tmin, tmax


#: Fixed-point unit of the marching positions (32 fraction bits).
_FIX_SHIFT = 32
_FIX_ONE = float(1 << _FIX_SHIFT)
_FIX_MASK = (1 << _FIX_SHIFT) - 1
_FIX_INV = np.float32(1.0 / _FIX_ONE)


@numba.njit(cache=True, fastmath=True, inline="always")
def _bilinear(arr: np.ndarray, xfx: np.int64, qfx: np.int64, usq: np.uint64) -> np.float32:
    """Bilinear sample at fixed point (x, q) = (xfx, qfx) / 2^32 of the flat ``arr``, whose
    q axis has stride ``usq``: x is the flat index of the slice's start plus the contiguous
    index p (an integer offset added to p keeps its fraction, the bilinear weight along p).

    x, q >= 0 (padded indices: the padding keeps them so), so the integer parts are shifts and
    the weights the low words.
    """
    fp = np.float32(xfx & _FIX_MASK) * _FIX_INV
    fq = np.float32(qfx & _FIX_MASK) * _FIX_INV
    base = np.uint64(qfx >> _FIX_SHIFT) * usq + np.uint64(xfx >> _FIX_SHIFT)
    v00 = arr[base]
    v10 = arr[base + np.uint64(1)]
    v01 = arr[base + usq]
    v11 = arr[base + usq + np.uint64(1)]
    a0 = v00 + fp * (v10 - v00)
    a1 = v01 + fp * (v11 - v01)
    return a0 + fq * (a1 - a0)


@numba.njit(cache=True, inline="always")
def _no_ray():  # noqa: ANN202 - the tuple of _ray_start
    return (False, False, np.int64(0), np.int64(0), np.int64(0), np.int64(0), np.int64(0), np.int64(0), 0.0, 0.0,
            np.int64(0), np.int64(0), 0.0)  # fmt: skip


@numba.njit(cache=True, inline="always")
def _ray_start(c, r, a_mat, s0, s1, s2, lo, hi, ni, nj, nk, ni_p, nj_p, ebi, ebj, ebk, empty, use_empty, i2w):  # noqa: ANN001, ANN202
    """The ray through pixel (c, r), ready to march: (hit, transposed, x, q, x step, q step, q stride,
    inner slices, e0, e1, first slice, last slice, mm per slice), positions in fixed point (see
    :func:`_bilinear`); ``hit`` False for a ray that misses the attenuation or crosses only zeros."""
    d0 = a_mat[0, 0] * c + a_mat[0, 1] * r + a_mat[0, 2]
    d1 = a_mat[1, 0] * c + a_mat[1, 1] * r + a_mat[1, 2]
    d2 = a_mat[2, 0] * c + a_mat[2, 1] * r + a_mat[2, 2]
    tmin, tmax = _clip(s0, s1, s2, d0, d1, d2, lo, hi)
    if not tmin < tmax:
        return _no_ray()
    # dominant axis m; minor axes p (contiguous in memory) and q
    ad0, ad1, ad2 = abs(d0), abs(d1), abs(d2)
    if ad0 >= ad1 and ad0 >= ad2:  # m = i: mu_t, p = j, q = k
        transposed = True
        nm, np_, nq = ni, nj, nk
        dm, dp, dq, sm, sp, sq = d0, d1, d2, s0, s1, s2
        str_m = nj_p
        str_q = nj_p * ni_p
        ebm, ebp, ebq = ebi, ebj, ebk
    elif ad1 >= ad2:  # m = j: p = i, q = k
        transposed = False
        nm, np_, nq = nj, ni, nk
        dm, dp, dq, sm, sp, sq = d1, d0, d2, s1, s0, s2
        str_m = ni_p
        str_q = ni_p * nj_p
        ebm, ebp, ebq = ebj, ebi, ebk
    else:  # m = k: p = i, q = j
        transposed = False
        nm, np_, nq = nk, ni, nj
        dm, dp, dq, sm, sp, sq = d2, d0, d1, s2, s0, s1
        str_m = ni_p * nj_p
        str_q = ni_p
        ebm, ebp, ebq = ebk, ebi, ebj
    e0 = sm + tmin * dm
    e1 = sm + tmax * dm
    if e0 > e1:
        e0, e1 = e1, e0
    e0 = max(e0, 0.0)
    e1 = min(e1, nm - 1.0)
    if not e0 < e1:
        return _no_ray()
    m_first = int(math.ceil(e0))
    m_last = int(math.floor(e1))
    n_inner = max(m_last - m_first, 0)  # m_last = m_first - 1: within one slice interval
    rp = dp / dm
    rq = dq / dm
    # p, q one slice before the first sample and one after the last
    p_before = sp + (m_first - 1 - sm) * rp
    q_before = sq + (m_first - 1 - sm) * rq
    p_after = p_before + (n_inner + 2) * rp
    q_after = q_before + (n_inner + 2) * rq
    # Guard the memory footprint against any numerical surprise (never taken for rays
    # clipped to the box: the samples lie within one voxel of it).
    if (
        min(p_before, p_after) < -1.5
        or max(p_before, p_after) > np_ + 0.5
        or min(q_before, q_after) < -1.5
        or max(q_before, q_after) > nq + 0.5
    ):
        return _no_ray()
    if use_empty:
        # leap from both ends (slices m_first - 1 and m_last + 1) inwards over proven zeros:
        # at a block whose distance is db >= 2 the next 2 db - 3 slices' bilinear footprints
        # (p, q within one voxel, moving at most one voxel per slice) stay in empty blocks with
        # a voxel to spare for rounding. The two leaps are independent chains of loads, taken
        # step for step together; positions in fixed point (the block index is a shift).
        m_f = m_first - 1
        m_b = m_last + 1
        p_f = np.int64((p_before + _PAD) * _FIX_ONE)
        q_f = np.int64((q_before + _PAD) * _FIX_ONE)
        rp_x = np.int64(round(rp * _FIX_ONE))
        rq_x = np.int64(round(rq * _FIX_ONE))
        p_b = p_f + (m_b - m_f) * rp_x
        q_b = q_f + (m_b - m_f) * rq_x
        shift = _FIX_SHIFT + _BLOCK_SHIFT
        forward = True
        backward = True
        while forward or backward:
            if forward:
                db = np.int64(empty[((m_f + _PAD) >> _BLOCK_SHIFT) * ebm + (p_f >> shift) * ebp + (q_f >> shift) * ebq])
                if db < _LEAP_MIN:
                    forward = False
                else:
                    m_f += 2 * db - 3
                    p_f += (2 * db - 3) * rp_x
                    q_f += (2 * db - 3) * rq_x
            if backward:
                db = np.int64(empty[((m_b + _PAD) >> _BLOCK_SHIFT) * ebm + (p_b >> shift) * ebp + (q_b >> shift) * ebq])
                if db < _LEAP_MIN:
                    backward = False
                else:
                    m_b -= 2 * db - 3
                    p_b -= (2 * db - 3) * rp_x
                    q_b -= (2 * db - 3) * rq_x
            if m_f > m_b:
                return _no_ray()  # the slices before m_f and after m_b, that is all, are zero
        m_start = m_f
        m = m_b
        # the samples before m_start and after m are zero: integrate from the zero
        # slice before the first possibly non-zero one to the zero slice after the last
        e0 = max(e0, m_start - 1.0)
        e1 = min(e1, m + 1.0)
        if not e0 < e1:
            return _no_ray()
        m_first = int(math.ceil(e0))
        m_last = int(math.floor(e1))
        n_inner = max(m_last - m_first, 0)
        p_before = sp + (m_first - 1 - sm) * rp
        q_before = sq + (m_first - 1 - sm) * rq
    w0 = i2w[0, 0] * d0 + i2w[0, 1] * d1 + i2w[0, 2] * d2
    w1 = i2w[1, 0] * d0 + i2w[1, 1] * d1 + i2w[1, 2] * d2
    w2 = i2w[2, 0] * d0 + i2w[2, 1] * d1 + i2w[2, 2] * d2
    step_mm = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) / abs(dm)
    xfx = (np.int64((m_first - 1 + _PAD) * str_m) << _FIX_SHIFT) + np.int64((p_before + _PAD) * _FIX_ONE)
    qfx = np.int64((q_before + _PAD) * _FIX_ONE)
    rxx = (np.int64(str_m) << _FIX_SHIFT) + np.int64(round(rp * _FIX_ONE))
    rqx = np.int64(round(rq * _FIX_ONE))
    return (True, transposed, xfx, qfx, rxx, rqx, np.int64(str_q), np.int64(n_inner), e0, e1,
            np.int64(m_first), np.int64(m_last), step_mm)  # fmt: skip


@numba.njit(cache=True, fastmath=True, inline="always")
def _ends(v_before, v_first, v_last, v_after, acc, e0, e1, m_first, m_last):  # noqa: ANN001, ANN202
    """The ray's integral (in slices) from its samples: the trapezoid over [m_first, m_last]
    (``acc`` = the sum of the samples there) and the exact areas over the partial end slices."""
    if e1 < m_first:  # inside one slice interval [m_first - 1, m_first]
        f = np.float32(0.5 * (e0 + e1) - (m_first - 1))
        return np.float32(e1 - e0) * (v_before + f * (v_first - v_before))
    f0 = np.float32(m_first - e0)
    f1 = np.float32(e1 - m_last)
    v_e0 = v_first + f0 * (v_before - v_first)
    v_e1 = v_last + f1 * (v_after - v_last)
    total = acc - np.float32(0.5) * (v_first + v_last)
    total += np.float32(0.5) * (f0 * (v_e0 + v_first) + f1 * (v_e1 + v_last))
    return total


@numba.njit(cache=True, fastmath=True, inline="always")
def _march_one(arr, ray):  # noqa: ANN001, ANN202
    """Joseph's sum along one started ray (in slices: times ``ray[12]`` for mm)."""
    xfx, qfx, rxx, rqx, usq, n_inner = ray[2], ray[3], ray[4], ray[5], np.uint64(ray[6]), ray[7]
    v_before = _bilinear(arr, xfx, qfx, usq)
    xfx += rxx
    qfx += rqx
    v_first = _bilinear(arr, xfx, qfx, usq)
    v_last = v_first
    acc = v_first
    for _ in range(n_inner):
        xfx += rxx
        qfx += rqx
        v_last = _bilinear(arr, xfx, qfx, usq)
        acc += v_last
    xfx += rxx
    qfx += rqx
    v_after = _bilinear(arr, xfx, qfx, usq)
    return _ends(v_before, v_first, v_last, v_after, acc, ray[8], ray[9], ray[10], ray[11])


@numba.njit(cache=True, fastmath=True, inline="always")
def _march_two(arr_a, a, arr_b, b):  # noqa: ANN001, ANN202
    """:func:`_march_one` of two rays at once (the same operations on each, interleaved: twice
    the independent loads in flight, one loop's overhead for the slices both have)."""
    xa, qa, rxa, rqa, usqa, na = a[2], a[3], a[4], a[5], np.uint64(a[6]), a[7]
    xb, qb, rxb, rqb, usqb, nb = b[2], b[3], b[4], b[5], np.uint64(b[6]), b[7]
    vba = _bilinear(arr_a, xa, qa, usqa)
    vbb = _bilinear(arr_b, xb, qb, usqb)
    xa += rxa
    qa += rqa
    xb += rxb
    qb += rqb
    vfa = _bilinear(arr_a, xa, qa, usqa)
    vfb = _bilinear(arr_b, xb, qb, usqb)
    vla = vfa
    vlb = vfb
    acca = vfa
    accb = vfb
    n_both = min(na, nb)
    for _ in range(n_both):
        xa += rxa
        qa += rqa
        xb += rxb
        qb += rqb
        vla = _bilinear(arr_a, xa, qa, usqa)
        vlb = _bilinear(arr_b, xb, qb, usqb)
        acca += vla
        accb += vlb
    for _ in range(na - n_both):
        xa += rxa
        qa += rqa
        vla = _bilinear(arr_a, xa, qa, usqa)
        acca += vla
    for _ in range(nb - n_both):
        xb += rxb
        qb += rqb
        vlb = _bilinear(arr_b, xb, qb, usqb)
        accb += vlb
    vaa = _bilinear(arr_a, xa + rxa, qa + rqa, usqa)
    vab = _bilinear(arr_b, xb + rxb, qb + rqb, usqb)
    return (_ends(vba, vfa, vla, vaa, acca, a[8], a[9], a[10], a[11]),
            _ends(vbb, vfb, vlb, vab, accb, b[8], b[9], b[10], b[11]))  # fmt: skip


@numba.njit(cache=True, inline="always")
def _stored_ray(ints, reals, n):  # noqa: ANN001, ANN202
    """The tuple of :func:`_ray_start` from row ``n`` of the set-up arrays."""
    return (True, ints[n, 0] != 0, ints[n, 1], ints[n, 2], ints[n, 3], ints[n, 4], ints[n, 5], ints[n, 6],
            reals[n, 0], reals[n, 1], ints[n, 7], ints[n, 8], reals[n, 2])  # fmt: skip


@numba.njit(cache=True, inline="always")
def _set_up_row(r, a_mat, source, lo, hi, shape_ijk, i2w, mask, use_mask, empty, empty_strides, use_empty, out, ints,
                reals, where):  # noqa: ANN001, ANN202  # fmt: skip
    """Zero row ``r`` of ``out`` and set up its rays that hit (:func:`_ray_start`) into ``ints``,
    ``reals`` (:func:`_stored_ray`'s rows) and ``where`` (their columns); returns their count."""
    cols = out.shape[1]
    ni, nj, nk = shape_ijk[0], shape_ijk[1], shape_ijk[2]
    ni_p, nj_p = ni + 2 * _PAD, nj + 2 * _PAD
    n_rays = 0
    for c in range(cols):
        out[r, c] = 0.0
        if use_mask and mask[r, c] == 0:
            continue
        ray = _ray_start(c, r, a_mat, source[0], source[1], source[2], lo, hi, ni, nj, nk, ni_p, nj_p,
                         empty_strides[0], empty_strides[1], empty_strides[2], empty, use_empty, i2w)  # fmt: skip
        if not ray[0]:
            continue
        ints[n_rays, 0] = 1 if ray[1] else 0
        ints[n_rays, 1] = ray[2]
        ints[n_rays, 2] = ray[3]
        ints[n_rays, 3] = ray[4]
        ints[n_rays, 4] = ray[5]
        ints[n_rays, 5] = ray[6]
        ints[n_rays, 6] = ray[7]
        ints[n_rays, 7] = ray[10]
        ints[n_rays, 8] = ray[11]
        reals[n_rays, 0] = ray[8]
        reals[n_rays, 1] = ray[9]
        reals[n_rays, 2] = ray[12]
        where[n_rays] = c
        n_rays += 1
    return n_rays


def _joseph(
    mu: np.ndarray,  # float32, flat, C order of the padded (nk + 2 PAD, nj + 2 PAD, ni + 2 PAD) volume
    mu_t: np.ndarray,  # float32, flat, C order of the padded (nk + 2 PAD, ni + 2 PAD, nj + 2 PAD) volume
    shape_ijk: np.ndarray,  # int64 (ni, nj, nk), unpadded
    lo: np.ndarray,  # float64 (3,) clip box in (unpadded) index space
    hi: np.ndarray,
    source: np.ndarray,  # float64 (3,) source in (unpadded) index space
    a_mat: np.ndarray,  # float64 (3, 3): direction = A @ (c, r, 1)
    i2w: np.ndarray,  # float64 (3, 3): index -> world linear part (lengths in mm)
    mask: np.ndarray,  # uint8 (rows, cols); ignored when use_mask is False
    use_mask: bool,
    empty: np.ndarray,  # uint8, flat, C order of the (padded) blocks: see _empty_distance
    empty_strides: np.ndarray,  # int64 (3,): block strides along i, j, k (padded voxels // _BLOCK)
    use_empty: bool,
    out: np.ndarray,  # float32 (rows, cols)
    work: np.ndarray,  # int64 (rows,): the bilinear samples each row's rays took
) -> None:
    """Joseph's method: bilinear samples on the slices of each ray's dominant axis m.

    The samples at the integer slices inside the clipped ray [e0, e1], plus one beyond each
    end, are integrated as a function linear between slices: the trapezoid rule inside, and
    the exact area of the interpolated ends over the partial slices. So a ray leaving through
    a cut (non-air) face of the volume, or ending a hair before a slice by rounding, is
    integrated correctly, and the result is continuous in the pose (no slice-count jumps).

    The volume is padded by PAD = 2 zero voxels on every side, so every sample (including
    the two beyond the ends) has its bilinear footprint in memory without clamping; indices
    are unsigned (no negative-index wraparound code in the inner loop). Rays dominated by the
    i axis read ``mu_t``, the copy whose fastest axis is j, so the two samples of a bilinear
    pair are always adjacent in memory.

    Empty space (``use_empty``): before sampling, each ray leaps from both ends of its clipped
    span over the slices whose samples are provably zero (``empty``: per block of _BLOCK^3
    voxels, the chessboard distance in blocks to the nearest block with attenuation) and its
    span is narrowed to the slices in between, plus the zero slice at each end: the integral
    is the same (the samples left out are exact zeros), rays cross no air around the anatomy.

    Speed: the rays of a row are all set up first (:func:`_ray_start`), then marched two at a
    time (:func:`_march_two`: twice the independent loads in flight); positions march in 32.32
    fixed point (exact steps, no float-to-int conversions) and the kernels compile without
    reassociation, so the sample loop stays scalar and each ray's sum keeps its order.
    """
    rows, cols = out.shape
    for r in numba.prange(rows):
        # the row's rays are all set up first, then marched in pairs: a march starts with
        # loads of its state, not behind another ray's clip and leaps
        ints = np.empty((cols, 9), dtype=np.int64)
        reals = np.empty((cols, 3), dtype=np.float64)
        where = np.empty(cols, dtype=np.int64)
        n_rays = _set_up_row(r, a_mat, source, lo, hi, shape_ijk, i2w, mask, use_mask, empty, empty_strides, use_empty,
                             out, ints, reals, where)  # fmt: skip
        samples = 0
        for n in range(0, n_rays - 1, 2):
            ray_a = _stored_ray(ints, reals, n)
            ray_b = _stored_ray(ints, reals, n + 1)
            total_a, total_b = _march_two(mu_t if ray_a[1] else mu, ray_a, mu_t if ray_b[1] else mu, ray_b)
            out[r, where[n]] = total_a * np.float32(ray_a[12])
            out[r, where[n + 1]] = total_b * np.float32(ray_b[12])
            samples += ray_a[7] + ray_b[7] + 6
        if n_rays % 2 == 1:
            ray_a = _stored_ray(ints, reals, n_rays - 1)
            out[r, where[n_rays - 1]] = _march_one(mu_t if ray_a[1] else mu, ray_a) * np.float32(ray_a[12])
            samples += ray_a[7] + 3
        work[r] = samples


def _renamed(fn: types.FunctionType, name: str) -> types.FunctionType:
    """A copy of ``fn`` under another name. numba's on-disk cache keys compiled code by the
    function's name and line, so two dispatchers of one function (parallel and serial) would
    share a cache entry and one would silently load the other's code."""
    copy = types.FunctionType(fn.__code__.replace(co_name=name), fn.__globals__, name, fn.__defaults__)
    copy.__qualname__ = name
    copy.__doc__ = fn.__doc__
    return copy


#: fastmath without reassociation: LLVM then keeps the sample loop scalar (vectorised, its
#: emulated gathers and register spills cost ~3x the scalar loop) and the sums in order.
_KERNEL_FASTMATH = {"nnan", "ninf", "nsz", "arcp", "contract", "afn"}

_render_joseph = numba.njit(parallel=True, fastmath=_KERNEL_FASTMATH, cache=True, nogil=True)(
    _renamed(_joseph, "_joseph_parallel")
)
_render_joseph_serial = numba.njit(parallel=False, fastmath=_KERNEL_FASTMATH, cache=True, nogil=True)(
    _renamed(_joseph, "_joseph_serial")
)


@numba.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def _render_trilinear(
    mu: np.ndarray,  # float32, flat, padded (nk + 2 PAD, nj + 2 PAD, ni + 2 PAD)
    shape_ijk: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    source: np.ndarray,
    a_mat: np.ndarray,
    i2w: np.ndarray,
    mask: np.ndarray,
    use_mask: bool,
    step_voxels: float,
    out: np.ndarray,
) -> None:
    """Trilinear marcher, ``step_voxels`` along the dominant axis (midpoint rule)."""
    rows, cols = out.shape
    ni, nj = shape_ijk[0] + 2 * _PAD, shape_ijk[1] + 2 * _PAD
    s0, s1, s2 = source[0] + _PAD, source[1] + _PAD, source[2] + _PAD  # padded indices
    imax, jmax, kmax = ni - 2, nj - 2, shape_ijk[2] + 2 * _PAD - 2
    lo_p = lo + _PAD
    hi_p = hi + _PAD
    for r in numba.prange(rows):
        for c in range(cols):
            out[r, c] = 0.0
            if use_mask and mask[r, c] == 0:
                continue
            d0 = a_mat[0, 0] * c + a_mat[0, 1] * r + a_mat[0, 2]
            d1 = a_mat[1, 0] * c + a_mat[1, 1] * r + a_mat[1, 2]
            d2 = a_mat[2, 0] * c + a_mat[2, 1] * r + a_mat[2, 2]
            tmin, tmax = _clip(s0, s1, s2, d0, d1, d2, lo_p, hi_p)
            if not tmin < tmax:
                continue
            dmax = max(abs(d0), abs(d1), abs(d2))
            nsteps = max(int(math.ceil((tmax - tmin) * dmax / step_voxels)), 1)
            dt = (tmax - tmin) / nsteps
            w0 = i2w[0, 0] * d0 + i2w[0, 1] * d1 + i2w[0, 2] * d2
            w1 = i2w[1, 0] * d0 + i2w[1, 1] * d1 + i2w[1, 2] * d2
            w2 = i2w[2, 0] * d0 + i2w[2, 1] * d1 + i2w[2, 2] * d2
            step_mm = dt * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            t = tmin + 0.5 * dt
            x = s0 + t * d0
            y = s1 + t * d1
            z = s2 + t * d2
            dx, dy, dz = dt * d0, dt * d1, dt * d2
            acc = 0.0
            for _ in range(nsteps):
                ii = min(max(int(x), 0), imax)
                jj = min(max(int(y), 0), jmax)
                kk = min(max(int(z), 0), kmax)
                fx = x - ii
                fy = y - jj
                fz = z - kk
                base = (kk * nj + jj) * ni + ii
                c00 = mu[base] + fx * (mu[base + 1] - mu[base])
                c10 = mu[base + ni] + fx * (mu[base + ni + 1] - mu[base + ni])
                b2 = base + ni * nj
                c01 = mu[b2] + fx * (mu[b2 + 1] - mu[b2])
                c11 = mu[b2 + ni] + fx * (mu[b2 + ni + 1] - mu[b2 + ni])
                c0 = c00 + fy * (c10 - c00)
                c1 = c01 + fy * (c11 - c01)
                acc += c0 + fz * (c1 - c0)
                x += dx
                y += dy
                z += dz
            out[r, c] = acc * step_mm


@numba.njit(cache=True)
def _chessboard_distance(occupied: np.ndarray, out: np.ndarray) -> None:
    """out = chessboard distance (in cells, at most 255) from each cell to the nearest
    ``occupied`` one, by the two raster passes of the 3x3x3 unit mask (exact for this metric)."""
    nk, nj, ni = occupied.shape
    for k in range(nk):
        for j in range(nj):
            for i in range(ni):
                if occupied[k, j, i]:
                    out[k, j, i] = 0
                    continue
                best = 255
                for dk in range(-1, 1):
                    for dj in range(-1, 2):
                        for di in range(-1, 2):
                            if dk == 0 and (dj > 0 or (dj == 0 and di >= 0)):
                                continue
                            kk, jj, ii = k + dk, j + dj, i + di
                            if 0 <= kk and 0 <= jj < nj and 0 <= ii < ni:
                                best = min(best, np.int64(out[kk, jj, ii]) + 1)
                out[k, j, i] = best
    for k in range(nk - 1, -1, -1):
        for j in range(nj - 1, -1, -1):
            for i in range(ni - 1, -1, -1):
                best = np.int64(out[k, j, i])
                if best == 0:
                    continue
                for dk in range(0, 2):
                    for dj in range(-1, 2):
                        for di in range(-1, 2):
                            if dk == 0 and (dj < 0 or (dj == 0 and di <= 0)):
                                continue
                            kk, jj, ii = k + dk, j + dj, i + di
                            if kk < nk and 0 <= jj < nj and 0 <= ii < ni:
                                best = min(best, np.int64(out[kk, jj, ii]) + 1)
                out[k, j, i] = best


@numba.njit(parallel=True, cache=True)
def _fill_level(hu, mu_water_per_mm, padded, padded_t, any_kj, any_ki, want, want_t) -> None:  # noqa: ANN001
    """One pass over a level's HU: attenuation per mm (``hu_to_mu_per_mm``'s operations, in the
    same order and precision) into the interior of ``padded`` (k, j, i; if ``want``) and of its
    (k, i, j) copy ``padded_t`` (if ``want_t``); ``any_kj``/``any_ki`` mark the rows and columns
    holding attenuation."""
    nk, nj, ni = hu.shape
    p = _PAD
    thousand, one, zero = np.float32(1000.0), np.float32(1.0), np.float32(0.0)
    water = np.float32(mu_water_per_mm)
    for k in numba.prange(nk):
        for j in range(nj):
            for i in range(ni):
                x = np.float32(hu[k, j, i]) / thousand
                x = x + one
                x = x * water
                if x < zero:
                    x = zero
                if want:
                    padded[k + p, j + p, i + p] = x
                if want_t:
                    padded_t[k + p, i + p, j + p] = x
                if x > zero:
                    any_kj[k, j] = True
                    any_ki[k, i] = True


@numba.njit(parallel=True, cache=True)
def _occupied_blocks(padded_mu, b, out) -> None:  # noqa: ANN001
    """``out[bk, bj, bi]``: some voxel of the ``b``^3 block of ``padded_mu`` holds attenuation."""
    nk, nj, ni = padded_mu.shape
    for bk in numba.prange(out.shape[0]):
        for k in range(bk * b, min(bk * b + b, nk)):
            for j in range(nj):
                row = out[bk, j // b]
                for i in range(ni):
                    if padded_mu[k, j, i] > 0:
                        row[i // b] = 1


def _empty_distance(padded_mu: NDArray[np.float32], *, transposed: bool = False) -> NDArray[np.uint8] | None:
    """Per block of ``_BLOCK``^3 padded voxels (k, j, i), the chessboard distance in blocks to
    the nearest block holding attenuation (0 there); None when no block is far enough from
    attenuation (``_LEAP_MIN``) for a ray to leap from it: the leaps' look-ups would then find
    nothing, at about 4 % of a render. ``transposed``: ``padded_mu`` is the (k, i, j) copy (the
    blocks are the same, their order transposed back)."""
    b = _BLOCK
    shape = tuple(-(-n // b) for n in padded_mu.shape)
    occupied = np.zeros(shape, dtype=np.uint8)
    _occupied_blocks(padded_mu, b, occupied)
    if transposed:
        occupied = np.ascontiguousarray(occupied.transpose(0, 2, 1))
        shape = occupied.shape
    if occupied.all() or not occupied.any():
        return None
    distance = np.empty(shape, dtype=np.uint8)
    _chessboard_distance(occupied, distance)
    return distance if (distance >= _LEAP_MIN).any() else None
