"""Similarity measures between a DRR and an X-ray image: higher is more similar.

All measures take two images of the same shape (attenuation line integrals, CONVENTIONS.md §5)
and an optional boolean field mask; pixels outside the mask never influence the value. The
gradient-based measures use 3x3 Sobel gradients and only pixels whose whole 3x3 footprint lies
inside the mask (the mask eroded by the Sobel footprint, and never the image border), so the
collimation edge cannot count.

:class:`GradientDifference` is the prepared, fast form of :func:`gradient_difference` that the
optimizer calls hundreds of times per registration against one X-ray image.
"""

from __future__ import annotations

import copy
import math

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

#: Candidate intensity scales of gradient difference, as multiples of the least-squares scale
#: <dX, dD> / <dD, dD>; the best one starts the Newton refinement (GD is not concave in s).
SCALE_GRID = np.array([0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0])

#: Safeguarded Newton iterations refining the scale, and their relative tolerance on s.
SCALE_NEWTON_ITERATIONS = 12
SCALE_TOLERANCE = 1e-7

#: The coarse search over SCALE_GRID uses every _GRID_STRIDE-th pixel (it only picks a bracket).
_GRID_STRIDE = 4

_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}  # no nnan/ninf: keep NaN semantics
#: numba's "python" error model checks every division for a zero divisor (to raise
#: ZeroDivisionError), and that branch keeps LLVM from vectorising the per-pixel loops: with
#: "numpy" (a zero divisor gives inf or nan, as in numpy) gradient difference takes about half
#: the time (0.47-0.54x on the real CT's 64 and 128 px levels, values equal to 1e-14). No
#: divisor here can be zero: A_v, A_h are at least the smallest positive double and the
#: scale's divisions are guarded.
_ERROR_MODEL = "numpy"


# --------------------------------------------------------------------------------------
# Input checks and masks
# --------------------------------------------------------------------------------------
def _as_image(name: str, image: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D image, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ValueError(f"{name} must be a real numeric image, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr.astype(np.float64, copy=False)


def _as_mask(mask: ArrayLike | None, shape: tuple[int, ...]) -> NDArray[np.bool_]:
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"mask shape {m.shape} does not match the image shape {shape}")
    if m.dtype != np.bool_:
        raise ValueError(f"mask must be boolean, got dtype {m.dtype}")
    if not m.any():
        raise ValueError("mask is empty: no pixel inside the field")
    return m


def _check_pair(drr: ArrayLike, xray: ArrayLike, mask: ArrayLike | None):
    d = _as_image("drr", drr)
    x = _as_image("xray", xray)
    if d.shape != x.shape:
        raise ValueError(f"drr shape {d.shape} does not match the xray shape {x.shape}")
    return d, x, _as_mask(mask, x.shape)


def gradient_mask(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Pixels whose whole 3x3 Sobel footprint lies inside ``mask`` (and not on the border)."""
    eroded = ndimage.binary_erosion(mask, structure=np.ones((3, 3), bool), border_value=0)
    if not eroded.any():
        raise ValueError("mask has no pixel whose 3x3 neighbourhood lies inside the field")
    return eroded


def sobel_gradients(image: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(vertical, horizontal) Sobel gradients: d/drow and d/dcol, unnormalised kernels."""
    img = np.asarray(image, dtype=np.float64)
    return ndimage.sobel(img, axis=0), ndimage.sobel(img, axis=1)


# --------------------------------------------------------------------------------------
# Gradient difference (Penney et al. 1998)
# --------------------------------------------------------------------------------------
@numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, error_model=_ERROR_MODEL)
def _gd_value(xv, xh, dv, dh, av, ah, s, stride=1):  # pragma: no cover - compiled
    """sum_p A_v / (A_v + (xv - s dv)^2) + A_h / (A_h + (xh - s dh)^2), every ``stride``-th pixel."""
    total = 0.0
    for n in range(0, xv.size, stride):
        ev = xv[n] - s * dv[n]
        eh = xh[n] - s * dh[n]
        total += av / (av + ev * ev) + ah / (ah + eh * eh)
    return total


@numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, error_model=_ERROR_MODEL)
def _gd_derivatives(xv, xh, dv, dh, av, ah, s):  # pragma: no cover - compiled
    """GD(s) and its first and second derivatives in s (one pass)."""
    f = 0.0
    g = 0.0
    h = 0.0
    for n in range(xv.size):
        ev = xv[n] - s * dv[n]
        iv = 1.0 / (av + ev * ev)
        tv = av * iv
        eh = xh[n] - s * dh[n]
        ih = 1.0 / (ah + eh * eh)
        th = ah * ih
        f += tv + th
        # d/ds A/(A + e^2) = 2 A e d / (A + e^2)^2, with e = x - s d
        g += 2.0 * (tv * iv * ev * dv[n] + th * ih * eh * dh[n])
        # d2/ds2 = 2 A d^2 (3 e^2 - A) / (A + e^2)^3
        h += 2.0 * (
            tv * iv * iv * dv[n] * dv[n] * (3.0 * ev * ev - av) + th * ih * ih * dh[n] * dh[n] * (3.0 * eh * eh - ah)
        )
    return f, g, h


@numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, error_model=_ERROR_MODEL)
def _gd_prepared(drr, spans, xv, xh, av, ah, grid, iters, tol, dv, dh):  # pragma: no cover
    """Sobel of ``drr`` at the listed pixels, then the maximum over the scale s of the GD sum.

    ``spans``: the pixels as runs of one row, (row, first column, length) each, in the order
    of ``xv``/``xh`` (row-major): each run's Sobel reads three contiguous rows (vectorised).
    Returns (GD sum, s). The scale: the best of ``grid`` x the least-squares scale, then a
    safeguarded Newton iteration on dGD/ds = 0 inside the bracket of the neighbouring grid
    points (bisection whenever Newton would leave it or the curvature is not negative).
    """
    sxd = 0.0
    sdd = 0.0
    n = 0
    for run in range(spans.shape[0]):
        r = spans[run, 0]
        c0 = spans[run, 1]
        up = drr[r - 1]
        mid = drr[r]
        dn = drr[r + 1]
        for j in range(spans[run, 2]):
            c = c0 + j
            a = up[c - 1]
            b = up[c]
            cc = up[c + 1]
            d = mid[c - 1]
            f = mid[c + 1]
            g = dn[c - 1]
            h = dn[c]
            k = dn[c + 1]
            dv[n + j] = (g + 2.0 * h + k) - (a + 2.0 * b + cc)
            dh[n + j] = (cc + 2.0 * f + k) - (a + 2.0 * d + g)
        n += spans[run, 2]
    # The sums in a loop of their own, which only reads: a loop that also stores runs its
    # vector code only where a run-time check finds the stores clear of the loads (the DRR's
    # rows), else a scalar copy, and the two group a reassociated sum differently: the
    # measure would then depend on where the buffers lie in memory (2e-16 between two
    # evaluators of the same DRR, enough for Powell to take another path).
    for m in range(n):
        gv = dv[m]
        gh = dh[m]
        sxd += xv[m] * gv + xh[m] * gh
        sdd += gv * gv + gh * gh
    if not sdd > 0.0:
        return _gd_value(xv, xh, dv, dh, av, ah, 0.0), 0.0
    s_ls = sxd / sdd
    if s_ls == 0.0:
        s_ls = 1e-300
    # coarse search on every GRID_STRIDE-th pixel: it only picks the bracket
    ng = grid.size
    best_i = 0
    best_coarse = -1.0
    for i in range(ng):
        fv = _gd_value(xv, xh, dv, dh, av, ah, grid[i] * s_ls, _GRID_STRIDE)
        if fv > best_coarse:
            best_coarse = fv
            best_i = i
    # bracket (in units of s_ls): two grid points either side of the best candidate, as the
    # subsampled values may rank neighbouring candidates of a flat maximum wrongly
    lo = grid[best_i - 2] if best_i > 1 else grid[0] - 2.0 * (grid[1] - grid[0])
    hi = grid[best_i + 2] if best_i < ng - 2 else grid[ng - 1] + 2.0 * (grid[ng - 1] - grid[ng - 2])
    u = grid[best_i]
    best_f = -1.0
    best_u = u
    for _ in range(iters):
        fv, g1, g2 = _gd_derivatives(xv, xh, dv, dh, av, ah, u * s_ls)
        if fv > best_f:
            best_f = fv
            best_u = u
        g1 *= s_ls  # derivatives in u = s / s_ls
        g2 *= s_ls * s_ls
        if g1 > 0.0:
            lo = u
        elif g1 < 0.0:
            hi = u
        else:
            break
        if g2 < 0.0:
            nxt = u - g1 / g2
            if not (lo < nxt < hi):
                nxt = 0.5 * (lo + hi)
        else:
            nxt = 0.5 * (lo + hi)
        if abs(nxt - u) <= tol * max(abs(u), 1.0):
            # converged: GD is flat here, the value at u is the maximum to ~tol^2
            break
        u = nxt
    return best_f, best_u * s_ls


def _row_runs(rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.int64]:
    """Pixels listed row-major as runs of consecutive columns of one row: (row, first column,
    length) per run."""
    if rows.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    breaks = np.flatnonzero((np.diff(rows) != 0) | (np.diff(cols) != 1)) + 1
    starts = np.concatenate([[0], breaks])
    lengths = np.diff(np.concatenate([starts, [rows.size]]))
    return np.stack([rows[starts], cols[starts], lengths], axis=1).astype(np.int64)


class GradientDifference:
    """Gradient difference against one X-ray image, prepared for many DRRs.

    ``GradientDifference(xray, mask)(drr)`` equals ``gradient_difference(drr, xray, mask)``;
    the X-ray gradients, their variances and the pixel list are computed once.

    The value is normalised by the number of pixels used, so it lies in (0, 2] (2 = the
    scaled DRR gradients equal the X-ray gradients everywhere) and is comparable across
    image sizes (pyramid levels). The intensity scale s of the DRR is chosen to maximise the
    measure: the best of a grid of multiples of the least-squares scale (``SCALE_GRID``),
    refined by a safeguarded Newton iteration on dGD/ds = 0 within the neighbouring grid
    points (``SCALE_NEWTON_ITERATIONS``, ``SCALE_TOLERANCE``). The scale found by the last
    call is in ``last_scale``.

    References
    ----------
    G. P. Penney, J. Weese, J. A. Little, P. Desmedt, D. L. G. Hill, D. J. Hawkes,
    "A comparison of similarity measures for use in 2-D-3-D medical image registration",
    IEEE Transactions on Medical Imaging 17(4):586-595, 1998.
    """

    def __init__(self, xray_image: ArrayLike, mask: ArrayLike | None = None) -> None:
        x = _as_image("xray", xray_image)
        m = _as_mask(mask, x.shape)
        used = gradient_mask(m)
        self.shape: tuple[int, int] = x.shape  # type: ignore[assignment]
        self.mask = m
        self.gradient_mask = used
        rows_idx, cols_idx = np.nonzero(used)  # row-major
        self._spans = _row_runs(rows_idx, cols_idx)
        gv, gh = sobel_gradients(x)
        self._xv = np.ascontiguousarray(gv[used])
        self._xh = np.ascontiguousarray(gh[used])
        # Variances of the X-ray gradient images over the used pixels. A constant X-ray image
        # has zero variance: the smallest positive double keeps every term finite (then only
        # pixels with zero difference score, each 1).
        tiny = np.finfo(np.float64).tiny
        self.a_v = max(float(self._xv.var()), tiny)
        self.a_h = max(float(self._xh.var()), tiny)
        self.n_pixels = int(rows_idx.size)
        self._dv = np.empty(self.n_pixels)
        self._dh = np.empty(self.n_pixels)
        self.last_scale = float("nan")

    def with_scratch(self) -> GradientDifference:
        """The same prepared measure with its own scratch buffers, for another thread.

        The X-ray gradients and pixel lists are shared (read-only); only the DRR gradient
        buffers and ``last_scale`` are the copy's own.
        """
        other = copy.copy(self)
        other._dv = np.empty(self.n_pixels)
        other._dh = np.empty(self.n_pixels)
        other.last_scale = float("nan")
        return other

    def __call__(self, drr: ArrayLike) -> float:
        d = np.asarray(drr)
        if d.shape != self.shape:
            raise ValueError(f"drr shape {d.shape} does not match the xray shape {self.shape}")
        if d.dtype not in (np.float32, np.float64):
            d = _as_image("drr", d)
        elif not np.isfinite(d).all():
            raise ValueError("drr contains NaN or infinite values")
        value, scale = _gd_prepared(
            d, self._spans, self._xv, self._xh, self.a_v, self.a_h,
            SCALE_GRID, SCALE_NEWTON_ITERATIONS, SCALE_TOLERANCE, self._dv, self._dh,
        )  # fmt: skip
        self.last_scale = float(scale)
        return float(value) / self.n_pixels


def gradient_difference(drr: ArrayLike, xray: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Gradient difference of Penney et al. (1998), higher is more similar, in (0, 2].

    With Sobel gradients dX (X-ray) and dD (DRR), vertical and horizontal, and A_v, A_h the
    variances of the X-ray gradient images over the used pixels::

        GD(s) = 1/N sum_p [ A_v / (A_v + (dX_v - s dD_v)^2) + A_h / (A_h + (dX_h - s dD_h)^2) ]

    over the N pixels whose 3x3 footprint lies inside ``mask``, maximised over the intensity
    scale s (see :class:`GradientDifference`). Invariant to ``xray * a + b`` (a != 0) and to
    the DRR's intensity scale.

    Raises ValueError on shape mismatch, non-finite values or an empty mask.

    References
    ----------
    G. P. Penney, J. Weese, J. A. Little, P. Desmedt, D. L. G. Hill, D. J. Hawkes,
    "A comparison of similarity measures for use in 2-D-3-D medical image registration",
    IEEE Transactions on Medical Imaging 17(4):586-595, 1998.
    """
    d, x, m = _check_pair(drr, xray, mask)
    return GradientDifference(x, m)(d)


# --------------------------------------------------------------------------------------
# Gradient correlation and NCC
# --------------------------------------------------------------------------------------
def _ncc_values(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    a = a - a.mean()
    b = b - b.mean()
    denom = math.sqrt(float(a @ a) * float(b @ b))
    if denom == 0.0 or not math.isfinite(denom):
        return 0.0  # a constant image correlates with nothing
    return float(a @ b) / denom


def ncc(drr: ArrayLike, xray: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Normalised cross-correlation over the pixels inside ``mask``, in [-1, 1].

    Higher is more similar; 0 when either image is constant inside the mask.

    References
    ----------
    G. P. Penney et al., IEEE Transactions on Medical Imaging 17(4):586-595, 1998
    (cross-correlation, section II).
    """
    d, x, m = _check_pair(drr, xray, mask)
    return _ncc_values(d[m], x[m])


def gradient_correlation(drr: ArrayLike, xray: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Gradient correlation: mean of the NCCs of the vertical and horizontal Sobel gradients.

    Uses the pixels whose 3x3 footprint lies inside ``mask``; in [-1, 1], higher is more
    similar.

    References
    ----------
    G. P. Penney, J. Weese, J. A. Little, P. Desmedt, D. L. G. Hill, D. J. Hawkes,
    "A comparison of similarity measures for use in 2-D-3-D medical image registration",
    IEEE Transactions on Medical Imaging 17(4):586-595, 1998.
    """
    d, x, m = _check_pair(drr, xray, mask)
    used = gradient_mask(m)
    dv, dh = sobel_gradients(d)
    xv, xh = sobel_gradients(x)
    return 0.5 * (_ncc_values(dv[used], xv[used]) + _ncc_values(dh[used], xh[used]))
