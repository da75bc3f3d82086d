"""The usable field of an X-ray image found from its pixels, the way a reader of the image would.

Works on the stored pixel values of one frame (any bit depth, any look-up table), oriented so
that larger means more X-rays reached the detector (``signal``). Three things leave a pixel
unusable for registration:

* **the collimated outside**: no X-rays, so the lowest signal of the image, flat apart from
  noise, and connected to the image border (a circular field, an octagon of blades with cut
  corners, rectangular blades closed to the border). Found as the border-connected region
  within a noise tolerance of the level in the image's corners; a digitally blanked outside
  (one exact value) is taken as it is, a real one (noisy, lossy, a penumbra) with a margin.
* **collimator blades inside the image**: a straight edge across the field with a step to less
  signal on the side away from the image center that holds along the whole edge (anatomy
  never keeps one step along a straight line across the field). Found on Canny edges by a
  Hough transform and checked along the line; the whole side behind the edge is masked, up
  to where the step ends (the penumbra). Behind an opaque blade there is only noise (or the
  display window's black). A weaker step (less than ``BLADE_MEDIAN_STEP`` of the field's
  range) along a sharp straight edge is a semi-transparent wedge filter: the anatomy goes on
  behind it, so only the edge is masked (all of the side behind it when nothing of the anatomy
  shows there). A display chain can flatten a blade's shadow into the toe of its look-up table
  and ring along its edge: a line that, moved by a few pixels across itself, shows a step to
  less signal on nearly all of its profiles, however small against the field's range, with
  hardly any structure behind it, is such a blade too. A long straight stretch of the collimated
  outside's boundary is a blade's edge as well (its shadow over the head fell into the window's
  black), and the field beyond its line (air or thin tissue behind the blade) is masked.
* **burned-in graphics**: text, rulers and markers drawn at the largest value (full white) in
  thin strokes that stand out from their surroundings, and lines of text at the smallest (full
  black); masked with a margin.

:func:`find_field` runs them in that order and says what it found.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from registration.io.graphics import EDGE_MARGIN_PX, _members, find_graphics

#: The collimated outside ends at a step of at least this fraction of the image's signal range.
OUTSIDE_MIN_STEP = 0.1
#: Images smaller than this (px, either side) are searched for a constant border only.
MIN_SEARCH_SIZE = 64
#: A blade's edge must show its step on this fraction of its length (gaps of 3 samples bridged) ...
BLADE_STEP_FRACTION = 0.9
#: ... along one stretch of at least this fraction of the line's chord through the field (the
#: rest of the chord lies behind the other blades).
BLADE_RUN_FRACTION = 0.4
#: ... a step of at least this fraction of the field's signal range (1st..99th percentile).
BLADE_MIN_STEP = 0.08
#: ... and a median step of at least this fraction (blades remove most of the X-rays).
BLADE_MEDIAN_STEP = 0.25
#: ... and either a shadow that persists 10-40 px behind the edge, or an edge this sharp (px from
#: 10 % to 90 % of its step): anatomy's long straight edges are neither.
BLADE_SHARP_PX = 4.0
#: ... along at least this fraction of the image's smaller side.
BLADE_MIN_LENGTH = 0.25
#: A blade never leaves less than this fraction of the field.
BLADE_MAX_CLOSED = 0.6
#: A blade whose shadow a display window flattened (a weak step on dark anatomy): the step keeps
#: its sign, at least this fraction of the field's range, on this fraction of the line's profiles ...
BAND_MIN_STEP = 0.02
BAND_SIGN_FRACTION = 0.75
#: ... and behind the edge at most this share of the structure in front of it (anatomy goes on
#: behind a filter or an anatomical edge; behind an opaque blade only noise).
BAND_MAX_STRUCTURE = 0.3
#: ... looked for up to this many px either side of the Hough line.
BAND_SHIFT_PX = 8
#: A blade along the collimated outside (a straight stretch of the outside's boundary at least
#: ``BLADE_MIN_LENGTH`` long): where its line crosses the field (on at least this many profiles,
#: 2 px apart) ...
OUTSIDE_EDGE_MIN_CROSSING = 5
#: ... the step is to less signal behind it on at least this fraction of them.
OUTSIDE_EDGE_STEP_FRACTION = 0.8
#: A line turned less than this from a blade already found and within this many px of its edge
#: in the field is that edge again.
SAME_EDGE_DEG = 10.0
SAME_EDGE_PX = 20.0


@dataclass
class FieldFound:
    """What :func:`find_field` found: the usable mask and one entry per part that was masked."""

    mask: NDArray[np.bool_]
    parts: list[dict[str, Any]] = field(default_factory=list)

    @property
    def how(self) -> str:
        return ", ".join(p["what"] for p in self.parts) if self.parts else "whole image"


def _robust_range(values: NDArray[np.float64], where: NDArray[np.bool_]) -> float:
    inside = values[where] if where.any() else values.reshape(-1)
    lo, hi = np.percentile(inside, [1.0, 99.0])
    return float(max(hi - lo, 1e-9))


def _median5(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """5 x 5 median (OpenCV's, float32)."""
    import cv2

    return cv2.medianBlur(np.ascontiguousarray(values, dtype=np.float32), 5).astype(np.float64)


def _with_small_holes(outside: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The outside with its small enclosed pieces (text or marks drawn on it) added."""
    holes = ndimage.binary_fill_holes(outside) & ~outside
    labels, n = ndimage.label(holes)
    if n == 0:
        return outside
    sizes = ndimage.sum(holes, labels, np.arange(1, n + 1))
    small = np.flatnonzero(sizes < 0.02 * outside.size) + 1
    return outside | _members(labels, n, small)


def exact_outside(values: NDArray[Any]) -> NDArray[np.bool_] | None:
    """Border-connected pixels holding the corners' one exact value (a digitally blanked outside)."""
    corners = {values[0, 0].item(), values[0, -1].item(), values[-1, 0].item(), values[-1, -1].item()}
    if len(corners) != 1:
        return None
    same = values == corners.pop()
    labels, _ = ndimage.label(same)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    outside = _members(labels, int(labels.max()), border[border > 0])
    if not outside.any():
        return None
    outside = _with_small_holes(outside)
    if outside.mean() > 0.98:  # one value nearly everywhere: no collimated field to speak of
        return None
    return outside


def dark_outside(signal: NDArray[np.float64]) -> NDArray[np.bool_] | None:
    """The collimated outside of a real image: the border-connected low, flat signal of the corners.

    At least two corners (8 x 8 px) must sit at the image's lowest signal, flat; the region is
    every border-connected pixel whose median-smoothed signal lies within a noise tolerance of
    that level (components of fewer than 0.05 % of the image are ignored).
    """
    rows, cols = signal.shape
    k = max(4, min(rows, cols) // 64)
    smooth = _median5(signal)
    lo, hi = np.percentile(signal, [0.5, 99.5])
    span = float(max(hi - lo, 1e-9))
    patches = [smooth[:k, :k], smooth[:k, -k:], smooth[-k:, :k], smooth[-k:, -k:]]
    raw = [signal[:k, :k], signal[:k, -k:], signal[-k:, :k], signal[-k:, -k:]]
    levels = [float(np.median(p)) for p in patches]
    dark = [
        (lv, float(np.std(r)))
        for lv, r in zip(levels, raw, strict=True)
        if lv <= lo + 0.05 * span and np.std(r) <= 0.05 * span
    ]
    if len(dark) < 2:
        return None
    level = float(np.median([d[0] for d in dark]))
    sigma = float(np.median([d[1] for d in dark]))
    tol = max(4.0 * sigma, 0.03 * span)
    low = (smooth <= level + tol) & (signal <= level + tol + 3.0 * sigma)
    labels, n = ndimage.label(low)
    if n == 0:
        return None
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    border = border[border > 0]
    sizes = ndimage.sum(np.ones_like(labels), labels, border)
    keep = border[sizes >= 0.0005 * rows * cols]
    outside = _members(labels, n, keep)
    if not outside.any() or outside.mean() > 0.9:
        return None
    # A collimator's shadow ends at an edge: just inside it the signal is well above the shadow.
    ring = ndimage.binary_dilation(outside, iterations=8) & ~ndimage.binary_dilation(outside, iterations=4)
    if not ring.any() or float(np.median(smooth[ring])) - level < OUTSIDE_MIN_STEP * span:
        return None
    return _with_small_holes(outside)


def infer_signal_up(values: NDArray[Any]) -> bool | None:
    """Whether larger stored values mean more X-rays, read from the collimated outside (which
    has none): True when the outside is the image's darkest, False when it is the brightest,
    None when there is no such outside or only a digitally blanked (constant) one."""
    values = np.asarray(values)
    if min(values.shape) < MIN_SEARCH_SIZE:
        return None
    if exact_outside(values) is not None:
        return None  # a digitally blanked outside is often black whatever the polarity
    v = values.astype(np.float64)
    dark, bright = dark_outside(v) is not None, dark_outside(-v) is not None
    if dark != bright:
        return dark
    return None


def _line_points(
    inside: NDArray[np.bool_], theta: float, rho: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Points every 2 px along the line x cos(theta) + y sin(theta) = rho that lie inside; its normal."""
    rows, cols = inside.shape
    normal = np.array([math.cos(theta), math.sin(theta)])  # (x = col, y = row)
    direction = np.array([-normal[1], normal[0]])
    extent = math.hypot(rows, cols)
    t = np.arange(-extent, extent, 2.0)
    px = normal[0] * rho + t * direction[0]
    py = normal[1] * rho + t * direction[1]
    ok = (px >= 0) & (px <= cols - 1) & (py >= 0) & (py <= rows - 1)
    px, py = px[ok], py[ok]
    on = inside[np.rint(py).astype(int), np.rint(px).astype(int)]
    return px[on], py[on], normal


def _profiles(
    smooth: NDArray[np.float64],
    field_mask: NDArray[np.bool_],
    px: NDArray[np.float64],
    py: NDArray[np.float64],
    normal: NDArray[np.float64],
    offsets: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Signal at ``offsets`` along the normal from each point, and whether each sample is in the field."""
    xs, ys = _samples(px, py, normal, offsets)
    values = ndimage.map_coordinates(smooth, [ys.ravel(), xs.ravel()], order=1, mode="nearest").reshape(xs.shape)
    return values, _in_mask(field_mask, xs, ys)


def _samples(
    px: NDArray[np.float64], py: NDArray[np.float64], normal: NDArray[np.float64], offsets: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The columns and rows of the samples ``offsets`` along the normal from each point."""
    return px[:, None] + offsets[None, :] * normal[0], py[:, None] + offsets[None, :] * normal[1]


def _in_mask(mask: NDArray[np.bool_], xs: NDArray[np.float64], ys: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether each sample (columns ``xs``, rows ``ys``, as :func:`_samples` gives them) lies in
    the image and in ``mask``."""
    rows, cols = mask.shape
    inb = (xs >= 0) & (xs <= cols - 1) & (ys >= 0) & (ys <= rows - 1)
    xi = np.clip(np.rint(xs).astype(int), 0, cols - 1)
    yi = np.clip(np.rint(ys).astype(int), 0, rows - 1)
    return inb & mask[yi, xi]


def line_peaks(
    hspace: NDArray[np.integer], angles: NDArray[np.float64], dists: NDArray[np.float64], *, min_distance: int,
    min_angle: int, threshold: float, num_peaks: int,
) -> tuple[NDArray[Any], NDArray[np.float64], NDArray[np.float64]]:  # fmt: skip
    """The peaks :func:`skimage.transform.hough_line_peaks` finds, looked for only where the
    accumulator passes ``threshold``.

    A peak is a connected group of cells above ``threshold`` that hold the largest count within
    ``min_distance`` distances and ``min_angle`` angles (beyond the accumulator: none); groups
    are taken strongest first, each at its rounded centroid, where the largest count around it
    must still pass ``threshold`` once the neighbourhoods of the peaks taken before are cleared
    (across the angle's wrap-around, the distance mirrored). The strongest ``num_peaks`` are
    returned: counts, angles, distances.
    """
    rows, cols = hspace.shape
    min_angle = min(min_angle, cols)
    dy = np.arange(-min_distance, min_distance + 1)
    dx = np.arange(-min_angle, min_angle + 1)

    def window_max(ys: NDArray[np.intp], xs: NDArray[np.intp]) -> NDArray[Any]:
        wy, wx = ys[:, None, None] + dy[None, :, None], xs[:, None, None] + dx[None, None, :]
        inside = (wy >= 0) & (wy < rows) & (wx >= 0) & (wx < cols)
        got = hspace[np.clip(wy, 0, rows - 1), np.clip(wx, 0, cols - 1)]
        return np.where(inside, got, 0).max(axis=(1, 2))

    ys, xs = np.nonzero(hspace > threshold)
    none = (hspace[:0, 0], angles[:0], dists[:0])
    if ys.size == 0:
        return none
    top = hspace[ys, xs] == window_max(ys, xs)
    ys, xs = ys[top], xs[top]
    if ys.size == 0:
        return none
    r0, c0 = int(ys.min()), int(xs.min())
    grid = np.zeros((int(ys.max()) - r0 + 1, int(xs.max()) - c0 + 1), dtype=bool)
    grid[ys - r0, xs - c0] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3), bool))
    group = labels[ys - r0, xs - c0]
    count = hspace[ys, xs]
    strongest = np.zeros(n + 1, dtype=count.dtype)
    np.maximum.at(strongest, group, count)
    cells = np.bincount(group, minlength=n + 1)[1:].astype(np.float64)
    # each group's centroid, rounded (half to even); integer sums are exact, as in a mean
    mean_y = np.round(np.bincount(group, weights=ys.astype(np.float64), minlength=n + 1)[1:] / cells)
    mean_x = np.round(np.bincount(group, weights=xs.astype(np.float64), minlength=n + 1)[1:] / cells)
    # strongest first; equal counts in the reverse order of their groups (as a stable sort reversed)
    order = np.argsort(strongest[1:], kind="stable")[::-1]
    cy, cx = mean_y[order].astype(np.intp), mean_x[order].astype(np.intp)
    left = window_max(cy, cx)
    ny, nx = np.meshgrid(dy, dx, indexing="ij")
    ny, nx = ny.ravel(), nx.ravel()
    cleared = np.zeros((rows, cols), dtype=bool)
    peaks: list[tuple[Any, int, int]] = []
    for i in range(len(order)):
        value = hspace.dtype.type(0) if cleared[cy[i], cx[i]] else left[i]
        if not value > threshold:
            continue
        peaks.append((value, int(cy[i]), int(cx[i])))
        # clear the neighbourhood: distances within the accumulator (the first row never), the
        # angle wrapped around with the distance mirrored
        y, x = cy[i] + ny, cx[i] + nx
        keep = (y > 0) & (y < rows)
        y, x = y[keep], x[keep]
        wrap = (x < 0) | (x >= cols)
        cleared[np.where(wrap, rows - y, y), np.where(x < 0, x + cols, np.where(x >= cols, x - cols, x))] = True
    if not peaks:
        return none
    counts = np.array([p[0] for p in peaks])
    py = np.array([p[1] for p in peaks])
    px = np.array([p[2] for p in peaks])
    if num_peaks < len(peaks):
        best = np.argsort(counts)[::-1][:num_peaks]
        counts, py, px = counts[best], py[best], px[best]
    return counts, angles[px], dists[py]


def find_blades(
    signal: NDArray[np.float64], field_mask: NDArray[np.bool_], *, max_lines: int = 12
) -> list[dict[str, Any]]:
    """Straight collimator edges across the field (see the module docstring), strongest first.

    Each entry: ``theta``, ``rho`` (the line x cos(theta) + y sin(theta) = rho, x the column,
    y the row), ``distance`` (signed px from the line, positive toward the field's center),
    ``edge`` (the offsets, px, where the mean step across the line starts and ends),
    ``structure_behind`` (the smoothed gradient 6..30 px behind the edge over that in front of
    it: about 1 behind a semi-transparent filter, near 0 behind a blade on anatomy), ``step``
    (the median step as a fraction of the field's range) and ``length_px``.
    """
    from skimage.feature import canny
    from skimage.transform import hough_line

    rows, cols = signal.shape
    inside = ndimage.binary_erosion(field_mask, iterations=4)
    if inside.sum() < 100:
        return []
    span = _robust_range(signal, inside)
    smooth = ndimage.gaussian_filter(signal, 1.0)
    edges = canny(signal, sigma=2.0, low_threshold=0.02 * span, high_threshold=0.05 * span, mask=inside)
    if edges.sum() < 20:
        return []
    angles = np.deg2rad(np.arange(-90.0, 90.0, 0.5))
    hspace, thetas, dists = hough_line(edges, theta=angles)
    min_length = BLADE_MIN_LENGTH * min(rows, cols)
    peaks = line_peaks(
        hspace, thetas, dists, num_peaks=max_lines, threshold=int(0.5 * min_length), min_distance=7, min_angle=6
    )
    grad = ndimage.gaussian_gradient_magnitude(signal, 2.0)
    center = ndimage.center_of_mass(field_mask)
    found: list[dict[str, Any]] = []
    for _, theta, rho in zip(*peaks, strict=True):
        if any(_same_edge(inside, float(theta), float(rho), b) for b in found):
            continue  # a weaker line through an edge already found, turned a little
        blade = _blade(signal, smooth, grad, field_mask, inside, center, span, float(theta), float(rho), min_length)
        if blade is not None:
            found.append(blade)
    return found


def find_outside_edges(
    signal: NDArray[np.float64], outside: NDArray[np.bool_], field_mask: NDArray[np.bool_],
    found: list[dict[str, Any]] | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """Blades whose edge runs along the collimated ``outside``: a straight stretch of the
    outside's boundary with the field, at least ``BLADE_MIN_LENGTH`` of the image's smaller side,
    is a blade's edge, and the field beyond its line (where X-rays came through the blade onto
    thin tissue or air and left more signal than the outside's level) lies behind that blade
    too. Kept when beyond the line there is field to mask, no more than ``BLADE_MAX_CLOSED`` of
    it, and where the line crosses the field the step is to less signal behind it
    (``OUTSIDE_EDGE_STEP_FRACTION`` of the profiles along the stretch of the line, with field in
    front of it, that holds the outside's straight run). Entries as
    :func:`find_blades` lists them (never filters); lines through a blade in ``found`` are skipped."""
    from skimage.transform import hough_line

    rows, cols = signal.shape
    boundary = outside & ndimage.binary_dilation(field_mask)
    min_length = BLADE_MIN_LENGTH * min(rows, cols)
    if boundary.sum() < min_length or field_mask.sum() < 100:
        return []
    angles = np.deg2rad(np.arange(-90.0, 90.0, 0.5))
    hspace, thetas, dists = hough_line(boundary, theta=angles)
    peaks = line_peaks(hspace, thetas, dists, num_peaks=8, threshold=int(0.5 * min_length), min_distance=7,
                       min_angle=6)  # fmt: skip
    inside = ndimage.binary_erosion(field_mask, iterations=4)
    span = _robust_range(signal, inside if inside.sum() >= 100 else field_mask)
    smooth = ndimage.gaussian_filter(signal, 1.0)
    cy, cx = ndimage.center_of_mass(field_mask)
    everywhere = np.ones_like(field_mask)
    offsets = np.arange(-12.0, 13.0)
    near_cols, far_cols = (offsets >= 3) & (offsets <= 8), (offsets <= -3) & (offsets >= -8)
    out: list[dict[str, Any]] = []
    for _, theta, rho in zip(*peaks, strict=True):
        theta, rho = float(theta), float(rho)
        if any(_same_edge(inside, theta, rho, b) for b in [*(found or []), *out]):
            continue
        center_side = cx * math.cos(theta) + cy * math.sin(theta) - rho
        if abs(center_side) < 5:
            continue
        near_sign = 1.0 if center_side > 0 else -1.0
        px, py, normal = _line_points(everywhere, theta, rho)
        prof, in_field = _profiles(smooth, field_mask, px, py, near_sign * normal, offsets)
        in_outside = _in_mask(outside, *_samples(px, py, near_sign * normal, offsets))
        near = in_field[:, near_cols].all(axis=1)
        bounded = near & in_outside[:, far_cols].all(axis=1)
        crossing = near & in_field[:, far_cols].all(axis=1)
        step = (prof[:, near_cols].mean(axis=1) - prof[:, far_cols].mean(axis=1)) / span
        run = _longest_run(bounded)
        if 2 * (run.stop - run.start) < min_length:
            continue  # the outside's boundary is not straight along this line for long enough
        distance = _signed_distance((rows, cols), theta, rho, near_sign)
        beyond = field_mask & (distance < 0)
        if not beyond.any() or beyond.sum() > BLADE_MAX_CLOSED * field_mask.sum():
            continue
        # the blade's own edge: the stretch of the line with field in front of it around that run
        edge = np.zeros_like(near)
        edge[_stretch(near, run)] = True
        crossing &= edge
        steps = step[crossing]
        if steps.size >= OUTSIDE_EDGE_MIN_CROSSING and np.mean(steps > BLADE_MIN_STEP) < OUTSIDE_EDGE_STEP_FRACTION:
            continue  # where the edge crosses the field, anatomy goes on across it
        out.append({"theta": theta, "rho": rho, "distance": distance, "edge": (-0.5, 0.5), "filter": False,
                    "structure_behind": 0.0, "step": round(float(np.median(steps)) if steps.size else 0.0, 3),
                    "length_px": int(2 * (run.stop - run.start)), "along_outside": True})  # fmt: skip
    return out


def _same_edge(inside: NDArray[np.bool_], theta: float, rho: float, blade: dict[str, Any]) -> bool:
    """Whether the line x cos(theta) + y sin(theta) = rho runs within ``SAME_EDGE_PX`` of a found
    blade's edge somewhere in the field at an angle under ``SAME_EDGE_DEG``."""
    turn = abs((math.degrees(theta - blade["theta"]) + 90.0) % 180.0 - 90.0)
    if turn >= SAME_EDGE_DEG:
        return False
    px, py, _ = _line_points(inside, theta, rho)
    if px.size == 0:
        return False
    t = blade["theta"]
    return bool(np.min(np.abs(px * math.cos(t) + py * math.sin(t) - blade["rho"])) < SAME_EDGE_PX)


def _blade(
    signal: NDArray[np.float64],
    smooth: NDArray[np.float64],
    grad: NDArray[np.float64],
    field_mask: NDArray[np.bool_],
    inside: NDArray[np.bool_],
    center: tuple[float, float],
    span: float,
    theta: float,
    rho: float,
    min_length: float,
) -> dict[str, Any] | None:
    """The blade (or filter edge) along one Hough line, as :func:`find_blades` lists it; None when
    the line is not one: too short, no step along most of its chord, neither a persisting shadow
    nor a sharp edge, or closing too much of the field."""
    rows, cols = signal.shape
    cy, cx = center  # the field's centre of mass (row, column)
    offsets = np.arange(-40.0, 41.0)
    center_side = cx * math.cos(theta) + cy * math.sin(theta) - rho
    if abs(center_side) < 5:
        return None
    near_sign = 1.0 if center_side > 0 else -1.0
    px, py, normal = _line_points(inside, theta, rho)
    if px.size * 2 < min_length:
        return None
    prof, ok = _profiles(smooth, field_mask, px, py, near_sign * normal, offsets)
    found = _step_along(prof, ok, offsets, span, min_length)
    accepted = False
    if found is not None:
        piece, step = found
        filter_edge = bool(np.median(step) < BLADE_MEDIAN_STEP)
        if filter_edge:
            # a weak step: only a sharp straight edge counts (a semi-transparent filter's)
            accepted = _sharp_step(prof[piece], ok[piece], offsets)
        else:
            # a persisting shadow or a sharp edge (a display window can hide the shadow)
            accepted = _shadow_persists(prof[piece], ok[piece], offsets, span) or _sharp_step(
                prof[piece], ok[piece], offsets
            )
    if not accepted:
        # a shadow the display window flattened into a dark band: opaque, whatever its step's size
        band = _dark_band(prof, ok, offsets, span, min_length, grad, field_mask, theta, rho, near_sign)
        if band is None:
            return None
        filter_edge, step = False, np.array([band[0]])
        rho += near_sign * band[1]  # onto the step; not refined: a halo's half-step points turn the line
    else:
        theta, rho = _refine(prof[piece], ok[piece], offsets, px[piece], py[piece], near_sign * normal, theta, rho)
    near_sign = 1.0 if cx * math.cos(theta) + cy * math.sin(theta) - rho > 0 else -1.0
    px, py, normal = _line_points(inside, theta, rho)
    prof, ok = _profiles(smooth, field_mask, px, py, near_sign * normal, offsets)
    edge = _edge_extent(prof, ok, offsets)
    distance = _signed_distance((rows, cols), theta, rho, near_sign)
    far_side = (distance < edge[1]) & field_mask
    if far_side.sum() > BLADE_MAX_CLOSED * field_mask.sum() or not far_side.any():
        return None
    ratio = _structure_behind(grad, field_mask, distance, edge)
    return {
        "theta": theta,
        "rho": rho,
        "distance": distance,
        "edge": edge,
        "filter": filter_edge,
        "structure_behind": round(ratio, 3),
        "step": round(float(np.median(step)), 3),
        "length_px": int(step.size * 2),
    }


def _signed_distance(shape: tuple[int, ...], theta: float, rho: float, near_sign: float) -> NDArray[np.float64]:
    """Every pixel's signed distance (px) from the line x cos(theta) + y sin(theta) = rho,
    positive on the side ``near_sign`` points to (the field's center)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (xx * math.cos(theta) + yy * math.sin(theta) - rho) * near_sign


def _steps(
    prof: NDArray[np.float64], ok: NDArray[np.bool_], offsets: NDArray[np.float64], span: float, shift: int = 0
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """The profiles with both sides in the field, and their steps (fractions of the field's
    range) from 3-8 px behind the line to 3-8 px in front of it, the line moved ``shift`` px."""
    near_cols = (offsets >= 3 + shift) & (offsets <= 8 + shift)
    far_cols = (offsets <= -3 + shift) & (offsets >= -8 + shift)
    valid = ok[:, near_cols].all(axis=1) & ok[:, far_cols].all(axis=1)
    step = (prof[valid][:, near_cols].mean(axis=1) - prof[valid][:, far_cols].mean(axis=1)) / span
    return valid, step


def _step_along(
    prof: NDArray[np.float64], ok: NDArray[np.bool_], offsets: NDArray[np.float64], span: float, min_length: float
) -> tuple[NDArray[np.intp], NDArray[np.float64]] | None:
    """The profiles (their indices) where one step to less signal runs along most of the line's
    chord through the field, and the steps there (fractions of the field's range); None when it
    does not."""
    valid, step = _steps(prof, ok, offsets, span)
    if valid.sum() * 2 < min_length:
        return None
    run = _longest_run(step > BLADE_MIN_STEP)
    if run.stop - run.start < max(0.5 * min_length, BLADE_RUN_FRACTION * valid.sum()):
        return None  # the edge must run along most of the line's chord through the field
    step = step[run]
    if np.mean(step > BLADE_MIN_STEP) < BLADE_STEP_FRACTION:
        return None
    return np.flatnonzero(valid)[run], step


def _dark_band(
    prof: NDArray[np.float64],
    ok: NDArray[np.bool_],
    offsets: NDArray[np.float64],
    span: float,
    min_length: float,
    grad: NDArray[np.float64],
    field_mask: NDArray[np.bool_],
    theta: float,
    rho: float,
    near_sign: float,
) -> tuple[float, float] | None:
    """(the median step as a fraction of the field's range, the edge's offset from the line in
    px) when the line, moved by up to ``BAND_SHIFT_PX`` across itself (an edge enhancement's halo
    moves the Hough line off the edge), bounds a blade's flat dark band: a step to less signal on
    nearly every profile along the line's chord (however small against the field's range), and
    behind the edge hardly any of the structure in front of it; None when it does not."""
    best: tuple[float, int, NDArray[np.float64]] | None = None
    for shift in range(-BAND_SHIFT_PX, BAND_SHIFT_PX + 1):
        valid, step = _steps(prof, ok, offsets, span, shift)
        if valid.sum() * 2 < min_length:
            continue
        share = float(np.mean(step > BAND_MIN_STEP))
        if best is None or share > best[0]:
            best = (share, shift, step)
    if best is None or best[0] < BAND_SIGN_FRACTION:
        return None
    _, shift, step = best
    distance = _signed_distance(field_mask.shape, theta, rho, near_sign) - shift
    ratio = _structure_behind(grad, field_mask, distance, (-1.0, 1.0))
    if not 0.0 < ratio <= BAND_MAX_STRUCTURE:
        return None
    return float(np.median(step)), float(shift)


def _structure_behind(
    grad: NDArray[np.float64], field_mask: NDArray[np.bool_], distance: NDArray[np.float64], edge: tuple
) -> float:
    """Structure behind the edge against structure in front of it, in bands 6..30 px away (0: a
    sliver behind the edge, masked whole)."""
    behind = field_mask & (distance < edge[0] - 6) & (distance > edge[0] - 30)
    front = field_mask & (distance > edge[1] + 6) & (distance < edge[1] + 30)
    if behind.sum() > 50 and front.sum() > 50:
        return float(np.median(grad[behind]) / (np.median(grad[front]) + 1e-9))
    return 0.0


def _shadow_persists(
    prof: NDArray[np.float64], ok: NDArray[np.bool_], offsets: NDArray[np.float64], span: float
) -> bool:
    """A blade's shadow persists away from its edge (10..40 px on both sides); an anatomical
    edge's step does not. True when too few profiles reach that far to tell."""
    wide = np.where(ok, prof, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        far_wide = np.nanmedian(wide[:, (offsets <= -10) & (offsets >= -40)], axis=1)
        near_wide = np.nanmedian(wide[:, (offsets >= 10) & (offsets <= 40)], axis=1)
    persists = (near_wide - far_wide) / span > BLADE_MIN_STEP
    known = np.isfinite(far_wide) & np.isfinite(near_wide)
    return bool(known.sum() < 10 or np.mean(persists[known]) >= BLADE_STEP_FRACTION)


def _refine(
    prof: NDArray[np.float64],
    ok: NDArray[np.bool_],
    offsets: NDArray[np.float64],
    px: NDArray[np.float64],
    py: NDArray[np.float64],
    normal: NDArray[np.float64],
    theta: float,
    rho: float,
) -> tuple[float, float]:
    """The line through the edge's half-step points along it (least squares), sub-pixel."""
    points = []
    for k in range(prof.shape[0]):
        row = prof[k]
        far, near = np.median(row[(offsets <= -4) & (offsets >= -10)]), np.median(row[(offsets >= 4) & (offsets <= 10)])
        if near - far <= 0:
            continue
        rel = (row - far) / (near - far)
        window = np.flatnonzero((np.abs(offsets) <= 4) & ok[k])
        for i in window[:-1]:
            if rel[i] < 0.5 <= rel[i + 1]:
                o = offsets[i] + (0.5 - rel[i]) / max(rel[i + 1] - rel[i], 1e-9)
                points.append((px[k] + o * normal[0], py[k] + o * normal[1]))
                break
    if len(points) < 10:
        return theta, rho
    pts = np.asarray(points)
    center = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - center, full_matrices=False)
    n = vt[1]  # the normal of the best-fitting line
    new_theta = math.atan2(n[1], n[0])
    if math.cos(new_theta - theta) < 0:
        new_theta += math.pi
    new_theta = (new_theta + math.pi) % (2 * math.pi) - math.pi
    return new_theta, float(center[0] * math.cos(new_theta) + center[1] * math.sin(new_theta))


def _sharp_step(prof: NDArray[np.float64], ok: NDArray[np.bool_], offsets: NDArray[np.float64]) -> bool:
    """Whether the mean profile across the line is a sharp step between two flat levels: at most
    ``BLADE_SHARP_PX`` from 10 % to 90 %, each side 4..12 px away flat within a quarter of the step."""
    lo, hi = _edge_extent(prof, ok, offsets)
    if hi - lo > BLADE_SHARP_PX:
        return False
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(np.where(ok, prof, np.nan), axis=0)
    far, near = mean[(offsets <= -4) & (offsets >= -12)], mean[(offsets >= 4) & (offsets <= 12)]
    step = float(np.nanmedian(near) - np.nanmedian(far))
    if not np.isfinite(step) or step <= 0:
        return False
    return bool(np.nanstd(far) <= 0.25 * step and np.nanstd(near) <= 0.25 * step)


def _stretch(flags: NDArray[np.bool_], run: slice, gap: int = 3) -> slice:
    """The stretch of ``flags`` (gaps of up to ``gap`` samples bridged) that holds ``run``."""
    start, stop = run.start, run.stop
    while True:
        before = np.flatnonzero(flags[max(0, start - gap - 1) : start])
        if before.size == 0:
            break
        start = max(0, start - gap - 1) + int(before[0])
    while True:
        after = np.flatnonzero(flags[stop : stop + gap + 1])
        if after.size == 0:
            break
        stop = stop + int(after[-1]) + 1
    return slice(start, stop)


def _longest_run(flags: NDArray[np.bool_], gap: int = 3) -> slice:
    """The longest stretch of ``flags`` that is True, bridging gaps of up to ``gap`` samples."""
    best, start, last = slice(0, 0), None, -(10**9)
    for k, flag in enumerate(flags):
        if not flag:
            continue
        if start is None or k - last > gap + 1:
            start = k
        last = k
        if last + 1 - start > best.stop - best.start:
            best = slice(start, last + 1)
    return best


def _edge_extent(
    profiles: NDArray[np.float64], ok: NDArray[np.bool_], offsets: NDArray[np.float64]
) -> tuple[float, float]:
    """Offsets (px, + toward the field) where the mean profile leaves its far level (10 % of the
    step) and reaches its near level (90 %): the blade's penumbra, blur included."""
    mean = np.array([profiles[ok[:, k], k].mean() if ok[:, k].any() else np.nan for k in range(offsets.size)])
    center = int(np.argmin(np.abs(offsets)))
    far_level = np.nanmedian(mean[max(0, center - 12) : center - 3])
    near_level = np.nanmedian(mean[center + 4 : center + 13])
    step = near_level - far_level
    if not np.isfinite(step) or step <= 0:
        return (-1.0, 1.0)
    rel = (mean - far_level) / step
    lo, hi = -1.0, 1.0
    k = center
    while k > 0 and np.isfinite(rel[k - 1]) and rel[k - 1] > 0.1 and offsets[k - 1] > -12:
        k -= 1
    lo = float(offsets[k]) - 0.5
    k = center
    while k < offsets.size - 1 and np.isfinite(rel[k + 1]) and rel[k + 1] < 0.9 and offsets[k + 1] < 12:
        k += 1
    hi = float(offsets[k])
    return (min(lo, -0.5), max(hi, 0.5))


def find_field(
    values: NDArray[Any],
    *,
    signal_up: bool = True,
    start: NDArray[np.bool_] | None = None,
    blades: bool = True,
    graphics: bool = True,
    cache: dict[str, Any] | None = None,
) -> FieldFound:
    """The usable field of one frame's stored ``values`` (see the module docstring).

    ``signal_up``: larger stored values mean more X-rays (as the file's intensity tags say);
    ``start``: a field already known (shutter tags), intersected with what is found.
    ``cache``: a dict kept across the frames of one run: the outside and the blades found on
    the first frame are reused (the collimation of a run rarely changes; burned-in text, such
    as a frame counter, does, and is looked for on every frame).
    """
    values = np.asarray(values)
    rows, cols = values.shape
    mask = np.ones((rows, cols), dtype=bool) if start is None else start.copy()
    v = values.astype(np.float64)
    if min(rows, cols) < MIN_SEARCH_SIZE:
        exact = exact_outside(values)
        if exact is None:
            return FieldFound(mask=mask)
        return FieldFound(mask=mask & ~exact, parts=[{"what": "constant border", "pixels": int(exact.sum())}])
    strokes = find_graphics(v, mask) if graphics else np.zeros((rows, cols), dtype=bool)
    if cache is not None and cache.get("shape") == (rows, cols):
        collimation = cache["collimation"]
        parts = [dict(p) for p in cache["parts"]]
    else:
        collimation, parts = _collimation(v, values, signal_up, mask & ~strokes, blades)
        if cache is not None:
            cache.update(shape=(rows, cols), collimation=collimation, parts=[dict(p) for p in parts])
    mask &= collimation
    strokes &= mask
    if strokes.any():
        mask &= ~strokes
        parts.append({"what": "burned-in graphics", "pixels": int(strokes.sum())})
    return FieldFound(mask=mask, parts=parts)


def _collimation(
    v: NDArray[np.float64], values: NDArray[Any], signal_up: bool, start: NDArray[np.bool_], blades: bool
) -> tuple[NDArray[np.bool_], list[dict[str, Any]]]:
    """The pixels the collimator leaves (outside and blades removed) and what was found."""
    rows, cols = v.shape
    mask = np.ones((rows, cols), dtype=bool)
    parts: list[dict[str, Any]] = []
    signal = v if signal_up else -v
    exact = exact_outside(values)
    outside = dark_outside(signal)
    if exact is not None and (outside is None or (outside & ~exact).sum() <= 0.001 * rows * cols):
        mask &= ~exact
        parts.append({"what": "constant border", "pixels": int(exact.sum())})
    elif outside is not None:
        grown = ndimage.binary_dilation(outside, iterations=EDGE_MARGIN_PX)
        if exact is not None:
            grown |= exact
        mask &= ~grown
        parts.append({"what": "dark outside", "pixels": int(grown.sum())})
    if blades and (mask & start).any():
        found = find_blades(signal, mask & start)
        if outside is not None:
            found += find_outside_edges(signal, ~mask, mask & start, found)
        for blade in found:
            lo, hi = blade["edge"]
            if blade["filter"] and blade["structure_behind"] > BAND_MAX_STRUCTURE:
                # the anatomy continues behind a semi-transparent filter: its edge only
                cut = mask & (blade["distance"] > lo - EDGE_MARGIN_PX) & (blade["distance"] < hi + EDGE_MARGIN_PX)
            else:
                cut = mask & (blade["distance"] < hi - 0.5)
            if not cut.any():
                continue
            mask &= ~cut
            parts.append(
                {
                    "what": "filter edge" if blade["filter"] else "collimator blade",
                    "pixels": int((cut & start).sum()),
                    "angle_deg": round(math.degrees(blade["theta"]), 1),
                    "step": blade["step"],
                    "structure_behind": blade["structure_behind"],
                }
                | ({"along_outside": True} if blade.get("along_outside") else {})
            )
    return mask, parts
