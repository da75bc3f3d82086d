"""The head phantom's compiled kernels: exact line integrals, point values and voxels of painted
quadric primitives, and the ray culling that keeps them fast.

A primitive is the intersection of up to ``MAX_QUADRICS`` quadrics (ellipsoids, cylinders) and
``MAX_PLANES`` half-spaces; later primitives are painted over earlier ones
(:class:`registration.sim.phantom.HeadPhantom` holds the arrays and is the only caller). Rays
are binned into tiles (gnomonic bins around the source) and each tile meets only the
primitives whose bounding spheres its rays can reach. numba-compiled (``cache=True``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

#: Air: the value outside every primitive, and what a voxel or a ray starts from.
HU_AIR = -1000.0

Float = NDArray[np.float64]


# --------------------------------------------------------------------------------------
# Compiled kernels
# --------------------------------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def _chord(p, ox, oy, oz, ex, ey, ez, nq, qcen, qmat, npl, planes, pre, qpre, ppre):  # pragma: no cover
    """Parameter interval [t0, t1] within [0, 1] of o + t e inside primitive p (t0 >= t1: miss).

    With ``pre``, every segment starts at the same point, whose local coordinates per quadric
    (``qpre[p, q] = (A (o - c), |A (o - c)|^2 - 1)``) and plane offsets
    (``ppre[p, k] = d - n . o``) were computed once.
    """
    t0 = 0.0
    t1 = 1.0
    for q in range(nq[p]):
        a = 0.0
        b = 0.0
        if pre:
            c = qpre[p, q, 3]
            for r in range(3):
                le = qmat[p, q, r, 0] * ex + qmat[p, q, r, 1] * ey + qmat[p, q, r, 2] * ez
                a += le * le
                b += qpre[p, q, r] * le
        else:
            px = ox - qcen[p, q, 0]
            py = oy - qcen[p, q, 1]
            pz = oz - qcen[p, q, 2]
            c = -1.0
            for r in range(3):
                m0 = qmat[p, q, r, 0]
                m1 = qmat[p, q, r, 1]
                m2 = qmat[p, q, r, 2]
                lp = m0 * px + m1 * py + m2 * pz
                le = m0 * ex + m1 * ey + m2 * ez
                a += le * le
                b += lp * le
                c += lp * lp
        if a < 1e-300:
            if c > 0.0:
                return 0.0, 0.0
            continue
        disc = b * b - a * c
        if disc <= 0.0:
            return 0.0, 0.0
        s = math.sqrt(disc)
        ta = (-b - s) / a
        tb = (-b + s) / a
        if ta > t0:
            t0 = ta
        if tb < t1:
            t1 = tb
        if t0 >= t1:
            return 0.0, 0.0
    for k in range(npl[p]):
        nx = planes[p, k, 0]
        ny = planes[p, k, 1]
        nz = planes[p, k, 2]
        nd = nx * ex + ny * ey + nz * ez
        if pre:
            rhs = ppre[p, k]
        else:
            rhs = planes[p, k, 3] - (nx * ox + ny * oy + nz * oz)
        if abs(nd) < 1e-300:
            if rhs < 0.0:
                return 0.0, 0.0
        elif nd > 0.0:
            tt = rhs / nd
            if tt < t1:
                t1 = tt
        else:
            tt = rhs / nd
            if tt > t0:
                t0 = tt
        if t0 >= t1:
            return 0.0, 0.0
    return t0, t1


@nb.njit(cache=True)
def source_terms(s, nq, qcen, qmat, npl, planes):  # pragma: no cover - jit
    """Per-primitive constants of segments that all start at ``s`` (see ``_chord``)."""
    n = nq.shape[0]
    qpre = np.zeros((n, qcen.shape[1], 4))
    ppre = np.zeros((n, planes.shape[1]))
    for p in range(n):
        for q in range(nq[p]):
            c = -1.0
            for r in range(3):
                lp = (
                    qmat[p, q, r, 0] * (s[0] - qcen[p, q, 0])
                    + qmat[p, q, r, 1] * (s[1] - qcen[p, q, 1])
                    + qmat[p, q, r, 2] * (s[2] - qcen[p, q, 2])
                )
                qpre[p, q, r] = lp
                c += lp * lp
            qpre[p, q, 3] = c
        for k in range(npl[p]):
            ppre[p, k] = planes[p, k, 3] - (planes[p, k, 0] * s[0] + planes[p, k, 1] * s[1] + planes[p, k, 2] * s[2])
    return qpre, ppre


@nb.njit(cache=True, inline="always")
def _segment_hits_sphere(ox, oy, oz, ex, ey, ez, ee, cx, cy, cz, r):  # pragma: no cover - jit
    wx = cx - ox
    wy = cy - oy
    wz = cz - oz
    t = (wx * ex + wy * ey + wz * ez) / ee
    if t < 0.0:
        t = 0.0
    elif t > 1.0:
        t = 1.0
    dx = ox + t * ex - cx
    dy = oy + t * ey - cy
    dz = oz + t * ez - cz
    return dx * dx + dy * dy + dz * dz <= r * r


@nb.njit(cache=True)
def _trace(
    ox,
    oy,
    oz,
    ex,
    ey,
    ez,
    cands,
    nq,
    qcen,
    qmat,
    npl,
    planes,
    bsph,
    pre,
    qpre,
    ppre,
    cov_s,
    cov_e,
    vis_p,
    vis_s,
    vis_e,
):  # pragma: no cover - jit
    """Painter's algorithm along one segment o + t e, t in [0, 1].

    ``cands`` lists the primitives that may meet the segment, oldest first; they are visited
    newest first and each contributes only where no newer primitive already covers the
    segment. Writes the visible pieces (primitive, t_start, t_end); returns their count.
    """
    ee = ex * ex + ey * ey + ez * ez
    nc = 0
    nv = 0
    cap = cov_s.shape[0]
    vcap = vis_p.shape[0]
    if ee <= 0.0:
        return 0
    for ci in range(cands.shape[0] - 1, -1, -1):
        p = cands[ci]
        if not _segment_hits_sphere(ox, oy, oz, ex, ey, ez, ee, bsph[p, 0], bsph[p, 1], bsph[p, 2], bsph[p, 3]):
            continue
        a, b = _chord(p, ox, oy, oz, ex, ey, ez, nq, qcen, qmat, npl, planes, pre, qpre, ppre)
        if b <= a:
            continue
        # visible gaps of [a, b] between the sorted, disjoint covered intervals
        cur = a
        for c in range(nc):
            if cov_e[c] <= cur:
                continue
            if cov_s[c] >= b:
                break
            if cov_s[c] > cur and nv < vcap:
                vis_p[nv] = p
                vis_s[nv] = cur
                vis_e[nv] = cov_s[c]
                nv += 1
            cur = max(cur, cov_e[c])
            if cur >= b:
                break
        if cur < b and nv < vcap:
            vis_p[nv] = p
            vis_s[nv] = cur
            vis_e[nv] = b
            nv += 1
        # insert [a, b] into the covered set, merging what it overlaps
        lo = 0
        while lo < nc and cov_e[lo] < a:
            lo += 1
        hi = lo
        na = a
        nb_ = b
        while hi < nc and cov_s[hi] <= b:
            na = min(na, cov_s[hi])
            nb_ = max(nb_, cov_e[hi])
            hi += 1
        removed = hi - lo
        if removed == 0:
            if nc < cap:
                for c in range(nc, lo, -1):
                    cov_s[c] = cov_s[c - 1]
                    cov_e[c] = cov_e[c - 1]
                cov_s[lo] = na
                cov_e[lo] = nb_
                nc += 1
        else:
            cov_s[lo] = na
            cov_e[lo] = nb_
            shift = removed - 1
            if shift > 0:
                for c in range(lo + 1, nc - shift):
                    cov_s[c] = cov_s[c + shift]
                    cov_e[c] = cov_e[c + shift]
                nc -= shift
        if nc == 1 and cov_s[0] <= 0.0 and cov_e[0] >= 1.0:
            return nv  # the whole segment is covered
    return nv


_SCRATCH = 256  # covered intervals / visible pieces per segment


@nb.njit(cache=True, parallel=True)
def line_integrals_kernel(
    src,
    dst,
    order,
    tile_ptr,
    tile_perm,
    cand_ptr,
    cand_idx,
    nq,
    qcen,
    qmat,
    npl,
    planes,
    mu,
    bsph,
    pre,
    qpre,
    ppre,
):  # pragma: no cover - jit
    """Line integrals of rays binned into tiles that share one candidate list each."""
    n = src.shape[0]
    out = np.zeros(n)
    for ti in nb.prange(tile_perm.shape[0]):
        t = tile_perm[ti]
        cands = cand_idx[cand_ptr[t] : cand_ptr[t + 1]]
        cov_s = np.empty(_SCRATCH)
        cov_e = np.empty(_SCRATCH)
        vis_p = np.empty(_SCRATCH, np.int64)
        vis_s = np.empty(_SCRATCH)
        vis_e = np.empty(_SCRATCH)
        for k in range(tile_ptr[t], tile_ptr[t + 1]):
            i = order[k]
            ox, oy, oz = src[i, 0], src[i, 1], src[i, 2]
            ex, ey, ez = dst[i, 0] - ox, dst[i, 1] - oy, dst[i, 2] - oz
            nv = _trace(
                ox,
                oy,
                oz,
                ex,
                ey,
                ez,
                cands,
                nq,
                qcen,
                qmat,
                npl,
                planes,
                bsph,
                pre,
                qpre,
                ppre,
                cov_s,
                cov_e,
                vis_p,
                vis_s,
                vis_e,
            )
            acc = 0.0
            for v in range(nv):
                acc += mu[vis_p[v]] * (vis_e[v] - vis_s[v])
            out[i] = acc * math.sqrt(ex * ex + ey * ey + ez * ez)
    return out


@nb.njit(cache=True)  # serial: cheap per point, and quicker to compile
def value_at_kernel(pts, nq, qcen, qmat, npl, planes, value, background, bsph, tol):  # pragma: no cover
    """``value`` of the newest primitive holding each point (closed, within ``tol`` mm), else
    ``background``."""
    n = pts.shape[0]
    out = np.empty(n)
    for i in range(n):
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        res = background
        for p in range(bsph.shape[0] - 1, -1, -1):
            dx, dy, dz = x - bsph[p, 0], y - bsph[p, 1], z - bsph[p, 2]
            if dx * dx + dy * dy + dz * dz > (bsph[p, 3] + tol) * (bsph[p, 3] + tol):
                continue
            inside = True
            for q in range(nq[p]):
                px = x - qcen[p, q, 0]
                py = y - qcen[p, q, 1]
                pz = z - qcen[p, q, 2]
                s = 0.0
                fro = 0.0
                for r in range(3):
                    lp = qmat[p, q, r, 0] * px + qmat[p, q, r, 1] * py + qmat[p, q, r, 2] * pz
                    s += lp * lp
                    fro += qmat[p, q, r, 0] ** 2 + qmat[p, q, r, 1] ** 2 + qmat[p, q, r, 2] ** 2
                # |A y|^2 grows by at most 2 |A| tol per mm of distance at the surface (|A| >= its
                # largest singular value), so this accepts points within ~tol mm of it.
                if s > 1.0 + 2.0 * math.sqrt(fro) * tol:
                    inside = False
                    break
            if inside:
                for k in range(npl[p]):
                    if planes[p, k, 0] * x + planes[p, k, 1] * y + planes[p, k, 2] * z > planes[p, k, 3] + tol:
                        inside = False
                        break
            if inside:
                res = value[p]
                break
        out[i] = res
    return out


@nb.njit(cache=True, parallel=True)
def voxelize_kernel(
    shape, aff, ss, tile, tile_perm, ntj, cand_ptr, cand_idx, nq, qcen, qmat, npl, planes, hu, bsph
):  # pragma: no cover - jit
    """Anti-aliased HU: exact box average along i, ss x ss supersampling in j and k.

    Lines along i are grouped in ``tile`` x ``tile`` blocks of (j, k) sharing a candidate list.
    """
    nk, nj, ni = shape[0], shape[1], shape[2]
    out = np.empty((nk, nj, ni), dtype=np.float32)
    ex = aff[0, 0] * ni
    ey = aff[1, 0] * ni
    ez = aff[2, 0] * ni
    scale = 1.0 / (ss * ss)
    qpre = np.zeros((1, 1, 4))
    ppre = np.zeros((1, 1))
    for ti in nb.prange(tile_perm.shape[0]):
        t = tile_perm[ti]
        tj = t % ntj
        tk = t // ntj
        cands = cand_idx[cand_ptr[t] : cand_ptr[t + 1]]
        row = np.empty(ni)
        cov_s = np.empty(_SCRATCH)
        cov_e = np.empty(_SCRATCH)
        vis_p = np.empty(_SCRATCH, np.int64)
        vis_s = np.empty(_SCRATCH)
        vis_e = np.empty(_SCRATCH)
        for k in range(tk * tile, min((tk + 1) * tile, nk)):
            for j in range(tj * tile, min((tj + 1) * tile, nj)):
                row[:] = 0.0
                for sk in range(ss):
                    kk = k + (sk + 0.5) / ss - 0.5
                    for sj in range(ss):
                        jj = j + (sj + 0.5) / ss - 0.5
                        ox = aff[0, 0] * -0.5 + aff[0, 1] * jj + aff[0, 2] * kk + aff[0, 3]
                        oy = aff[1, 0] * -0.5 + aff[1, 1] * jj + aff[1, 2] * kk + aff[1, 3]
                        oz = aff[2, 0] * -0.5 + aff[2, 1] * jj + aff[2, 2] * kk + aff[2, 3]
                        nv = _trace(
                            ox,
                            oy,
                            oz,
                            ex,
                            ey,
                            ez,
                            cands,
                            nq,
                            qcen,
                            qmat,
                            npl,
                            planes,
                            bsph,
                            False,
                            qpre,
                            ppre,
                            cov_s,
                            cov_e,
                            vis_p,
                            vis_s,
                            vis_e,
                        )
                        for v in range(nv):
                            d = (hu[vis_p[v]] - HU_AIR) * scale
                            x0 = vis_s[v] * ni
                            x1 = vis_e[v] * ni
                            i0 = max(int(math.floor(x0)), 0)
                            i1 = min(int(math.ceil(x1)), ni)
                            for i in range(i0, i1):
                                lo = x0 if x0 > i else float(i)
                                hi = x1 if x1 < i + 1.0 else i + 1.0
                                if hi > lo:
                                    row[i] += d * (hi - lo)
                for i in range(ni):
                    out[k, j, i] = HU_AIR + row[i]
    return out


# --------------------------------------------------------------------------------------
# Culling: which primitives may meet a bundle of rays
# --------------------------------------------------------------------------------------
def _csr(hits: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Row pointers and column indices (ascending) of a boolean (tiles, primitives) matrix."""
    rows, cols = np.nonzero(hits)
    ptr = np.zeros(hits.shape[0] + 1, np.int64)
    np.cumsum(np.bincount(rows, minlength=hits.shape[0]), out=ptr[1:])
    return ptr, cols.astype(np.int64)


def _unit(v: Float) -> Float:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def bin_rays(src: Float, dst: Float, bsph: Float) -> tuple:
    """Bin segments into tiles of similar direction with per-tile candidate primitives.

    Rays from one common source (an X-ray image) are binned by direction (gnomonic
    coordinates about their mean direction) and a primitive is a candidate of a tile when its
    bounding sphere's cone from the source meets the tile's cone. Other ray sets fall back to a
    single tile holding every primitive (still exact, only slower).
    """
    n = len(src)
    everything = (
        np.arange(n, dtype=np.int64),
        np.array([0, n], np.int64),
        np.zeros(1, np.int64),
        np.array([0, len(bsph)], np.int64),
        np.arange(len(bsph), dtype=np.int64),
    )
    if n < 64 or not np.all(src == src[0]):
        return _split_single_tile(everything, n)
    s = src[0]
    w = dst - s
    norm = np.linalg.norm(w, axis=1)
    if np.any(norm <= 0):
        return _split_single_tile(everything, n)
    w = w / norm[:, None]
    d0 = _unit(w.mean(axis=0))
    helper = np.array([1.0, 0.0, 0.0]) if abs(d0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = _unit(np.cross(helper, d0))
    v = np.cross(d0, u)
    wd = w @ d0
    if np.any(wd < 0.2):  # too wide a fan for gnomonic binning
        return _split_single_tile(everything, n)
    order, tile_ptr, cand_ptr, cand_idx = _gnomonic_bins(s, dst, d0, u, v, bsph, 200.0)
    perm = np.random.default_rng(0).permutation(len(tile_ptr) - 1).astype(np.int64)  # balance threads
    return order, tile_ptr, perm, cand_ptr, cand_idx


@nb.njit(cache=True)
def _gnomonic_bins(s, dst, d0, u, v, bsph, target_per_tile):  # pragma: no cover - jit
    """Counting-sort rays from source ``s`` into direction tiles; candidates per tile."""
    n = dst.shape[0]
    gx = np.empty(n)
    gy = np.empty(n)
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    for i in range(n):
        wx, wy, wz = dst[i, 0] - s[0], dst[i, 1] - s[1], dst[i, 2] - s[2]
        wd = wx * d0[0] + wy * d0[1] + wz * d0[2]
        gx[i] = (wx * u[0] + wy * u[1] + wz * u[2]) / wd
        gy[i] = (wx * v[0] + wy * v[1] + wz * v[2]) / wd
        x0 = min(x0, gx[i])
        x1 = max(x1, gx[i])
        y0 = min(y0, gy[i])
        y1 = max(y1, gy[i])
    nt = int(round(math.sqrt(n / target_per_tile)))
    nt = min(max(nt, 1), 48)
    sx = (x1 - x0) / nt + 1e-12
    sy = (y1 - y0) / nt + 1e-12
    ntt = nt * nt
    tid = np.empty(n, np.int64)
    tile_ptr = np.zeros(ntt + 1, np.int64)
    for i in range(n):
        ix = min(int((gx[i] - x0) / sx), nt - 1)
        iy = min(int((gy[i] - y0) / sy), nt - 1)
        tid[i] = iy * nt + ix
        tile_ptr[tid[i] + 1] += 1
    for t in range(ntt):
        tile_ptr[t + 1] += tile_ptr[t]
    fill = tile_ptr[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[tid[i]]] = i
        fill[tid[i]] += 1
    # primitive cones seen from the source
    npr = bsph.shape[0]
    qhat = np.empty((npr, 3))
    alpha = np.empty(npr)
    for p in range(npr):
        qx, qy, qz = bsph[p, 0] - s[0], bsph[p, 1] - s[1], bsph[p, 2] - s[2]
        dist = math.sqrt(qx * qx + qy * qy + qz * qz)
        if dist <= bsph[p, 3]:
            alpha[p] = np.pi
            qhat[p, 0] = 1.0
            qhat[p, 1] = 0.0
            qhat[p, 2] = 0.0
        else:
            alpha[p] = math.asin(bsph[p, 3] / dist)
            qhat[p, 0] = qx / dist
            qhat[p, 1] = qy / dist
            qhat[p, 2] = qz / dist
    counts = np.zeros(ntt + 1, np.int64)
    hits = np.zeros((ntt, npr), np.bool_)
    corner = np.empty(3)
    for t in range(ntt):
        cxg = x0 + (t % nt + 0.5) * sx
        cyg = y0 + (t // nt + 0.5) * sy
        c = d0 + cxg * u + cyg * v
        c /= math.sqrt(c[0] ** 2 + c[1] ** 2 + c[2] ** 2)
        half = 0.0
        for ox_ in (-0.5, 0.5):
            for oy_ in (-0.5, 0.5):
                corner[:] = d0 + (cxg + ox_ * sx) * u + (cyg + oy_ * sy) * v
                corner /= math.sqrt(corner[0] ** 2 + corner[1] ** 2 + corner[2] ** 2)
                cosang = min(1.0, max(-1.0, corner[0] * c[0] + corner[1] * c[1] + corner[2] * c[2]))
                half = max(half, math.acos(cosang))
        for p in range(npr):
            lim = alpha[p] + half + 1e-9
            if lim >= np.pi or c[0] * qhat[p, 0] + c[1] * qhat[p, 1] + c[2] * qhat[p, 2] >= math.cos(lim):
                hits[t, p] = True
                counts[t + 1] += 1
    for t in range(ntt):
        counts[t + 1] += counts[t]
    cand_idx = np.empty(counts[ntt], np.int64)
    for t in range(ntt):
        k = counts[t]
        for p in range(npr):
            if hits[t, p]:
                cand_idx[k] = p
                k += 1
    return order, tile_ptr, counts, cand_idx


def _split_single_tile(everything: tuple, n: int) -> tuple:
    """Everything in chunks of 256 rays (so threads share the work), all candidates each."""
    order, _, _, cand_ptr_all, cand_idx_all = everything
    chunks = max(1, (n + 255) // 256)
    tile_ptr = np.minimum(np.arange(chunks + 1, dtype=np.int64) * 256, n)
    cand_ptr = np.arange(chunks + 1, dtype=np.int64) * cand_ptr_all[1]
    cand_idx = np.tile(cand_idx_all, chunks)
    return order, tile_ptr, np.arange(chunks, dtype=np.int64), cand_ptr, cand_idx


def bin_lines(shape: tuple[int, int, int], aff: Float, bsph: Float, tile: int) -> tuple:
    """Candidate primitives per (tile x tile) block of voxelisation lines along i."""
    nk, nj, ni = shape
    ntj = (nj + tile - 1) // tile
    ntk = (nk + tile - 1) // tile
    e = _unit(aff[:3, 0])
    tj = (np.arange(ntj) + 0.5) * tile - 0.5
    tk = (np.arange(ntk) + 0.5) * tile - 0.5
    gk, gj = np.meshgrid(tk, tj, indexing="ij")  # tile index t = tk * ntj + tj
    origin = aff[:3, 1] * gj.reshape(-1, 1) + aff[:3, 2] * gk.reshape(-1, 1) + aff[:3, 3] - 0.5 * aff[:3, 0]
    # half extent of a tile across the lines (corner offset, perpendicular part)
    corner = aff[:3, 1] * (tile / 2.0 + 0.5) + aff[:3, 2] * (tile / 2.0 + 0.5)
    corner2 = aff[:3, 1] * (tile / 2.0 + 0.5) - aff[:3, 2] * (tile / 2.0 + 0.5)
    reach = max(np.linalg.norm(c - (c @ e) * e) for c in (corner, corner2))
    rel = bsph[None, :, :3] - origin[:, None, :]
    perp = rel - (rel @ e)[..., None] * e
    dist = np.linalg.norm(perp, axis=2)
    hits = dist <= bsph[None, :, 3] + reach + 1e-9
    cand_ptr, cand_idx = _csr(hits)
    perm = np.random.default_rng(0).permutation(ntj * ntk).astype(np.int64)
    return ntj, perm, cand_ptr, cand_idx
