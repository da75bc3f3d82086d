"""Burned-in graphics in an X-ray image: text, rulers and markers drawn at the largest value (full
white) in thin strokes that stand out from their surroundings, and lines of text at the smallest
(full black); masked with a margin (:func:`registration.io.field.find_field` runs it last)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

#: Masks found from the pixels grow by this margin (px): the collimator's penumbra, the
#: detector's blur and lossy-compression ringing around an edge or a stroke.
EDGE_MARGIN_PX = 2
#: Burned-in strokes are at most this wide (px); larger extreme regions are saturated anatomy.
GRAPHICS_MAX_STROKE_PX = 7.0
#: ... and stand out from their surroundings by this fraction of the field's signal range.
GRAPHICS_MIN_CONTRAST = 0.2
#: Black strokes: the largest character (px across) taken for text.
GRAPHICS_MAX_CHAR_PX = 30


def _members(labels: NDArray[np.integer], n: int, ids: NDArray[np.integer]) -> NDArray[np.bool_]:
    """Pixels whose label is one of ``ids`` (a look-up table: no sort of the image)."""
    table = np.zeros(n + 1, dtype=bool)
    table[np.asarray(ids, dtype=np.int64)] = True
    table[0] = False
    return table[labels]


def find_graphics(values: NDArray[np.float64], field_mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Burned-in text, rulers and markers: thin strokes at the field's largest value (full white),
    and lines of text at its smallest (full black).

    A stroke component (8-connected, at least 3 pixels) is at most ``GRAPHICS_MAX_STROKE_PX``
    wide, and its surroundings (a 3 px ring) differ from it by ``GRAPHICS_MIN_CONTRAST`` of the
    field's range. White: it is at least three times longer than wide (a ruler, a line), or one
    of at least three such pieces within a few character heights (a line of text). Black: only
    text, at most ``GRAPHICS_MAX_CHAR_PX`` high, with closed letters or among at least three
    pieces on one baseline, since contrast-filled vessels clipped by a display window are thin,
    dark, long and at the lowest value too. Returned grown by ``EDGE_MARGIN_PX``.
    """
    inside = values[field_mask]
    if inside.size == 0:
        return np.zeros(values.shape, dtype=bool)
    vmin, vmax = float(inside.min()), float(inside.max())
    lo, hi = np.percentile(inside, [1.0, 99.0])
    span = float(max(hi - lo, 1e-9))
    # near full white: within 4 % of the range below it (without the pixels at full black, so
    # that black text does not widen it)
    rest = inside[inside > vmin]
    full = float(max(vmax - (float(rest.min()) if rest.size else vmin), 1e-9))
    out = np.zeros(values.shape, dtype=bool)
    for extreme, candidates, dark in (
        (vmax, field_mask & (values >= vmax - 0.04 * full), False),
        # black text inside the field, off its rim (where the field's own edge reaches black)
        (vmin, ndimage.binary_erosion(field_mask, iterations=3, border_value=0) & (values <= vmin), True),
    ):
        if not candidates.any() or candidates.mean() > 0.5:
            continue
        other = (values >= vmax) if dark else (values <= vmin)  # the other extreme: not the surroundings
        out |= _strokes(values, field_mask & ~other, candidates, extreme, span, text_only=dark)
    if out.any():
        out = ndimage.binary_dilation(out, iterations=EDGE_MARGIN_PX)
    return out & field_mask


def _strokes(
    values: NDArray[np.float64], field_mask: NDArray[np.bool_], candidates: NDArray[np.bool_], extreme: float,
    span: float, *, text_only: bool,
) -> NDArray[np.bool_]:  # fmt: skip
    """The components of ``candidates`` that are graphics (see :func:`find_graphics`)."""
    labels, n = ndimage.label(candidates, structure=np.ones((3, 3), bool))
    if n == 0:
        return np.zeros(values.shape, dtype=bool)
    index = np.arange(1, n + 1)
    rs, cs = np.nonzero(candidates)
    r0, r1, c0, c1 = max(rs.min() - 1, 0), rs.max() + 2, max(cs.min() - 1, 0), cs.max() + 2
    width = np.zeros(values.shape)
    width[r0:r1, c0:c1] = ndimage.distance_transform_edt(candidates[r0:r1, c0:c1])
    widest = np.zeros(n + 1)
    np.maximum.at(widest, labels[rs, cs], width[rs, cs])
    widest = widest[1:]
    sizes = np.bincount(labels[rs, cs], minlength=n + 1)[1:]
    ring = ndimage.binary_dilation(candidates, iterations=3) & ~ndimage.binary_dilation(candidates) & field_mask
    ring_labels = ndimage.grey_dilation(labels, size=(7, 7)) * ring
    with np.errstate(invalid="ignore", divide="ignore"):
        around = ndimage.mean(values, ring_labels, index)
    boxes = ndimage.find_objects(labels)
    thin = []
    for k in range(n):
        stroke = 2.0 * widest[k]
        if sizes[k] < 3 or stroke > GRAPHICS_MAX_STROKE_PX or boxes[k] is None:
            continue
        if not np.isfinite(around[k]) or abs(extreme - float(around[k])) < GRAPHICS_MIN_CONTRAST * span:
            continue
        height = boxes[k][0].stop - boxes[k][0].start
        extent = max(height, boxes[k][1].stop - boxes[k][1].start)
        if text_only:  # a word or a character: a line's height, with letters' holes or beside others
            if height > GRAPHICS_MAX_CHAR_PX:
                continue
            extent = height
        thin.append((k, extent, extent >= 3.0 * max(stroke, 1.0), boxes[k]))
    centers = np.array([((b[0].start + b[0].stop) / 2, (b[1].start + b[1].stop) / 2) for _, _, _, b in thin])
    bottoms = np.array([float(b[0].stop) for _, _, _, b in thin])
    accepted = []
    for i, (k, extent, elongated, box) in enumerate(thin):
        if text_only and _holes(labels[box] == k + 1) > 0:
            accepted.append(k + 1)  # a word with closed letters (a vessel tree encloses nothing)
            continue
        if text_only or not elongated:
            reach = 3.0 * max(extent, 4)
            near = np.hypot(*(centers - centers[i]).T) <= reach
            if text_only:  # pieces of one line: their bottoms within a third of its height
                near &= np.abs(bottoms - bottoms[i]) <= max(2.0, extent / 3.0)
            if near.sum() < 3:
                continue
        accepted.append(k + 1)
    if not accepted:
        return np.zeros(values.shape, dtype=bool)
    return _members(labels, n, np.asarray(accepted))


def _holes(piece: NDArray[np.bool_]) -> int:
    """How many enclosed background regions a stroke component has."""
    _, n = ndimage.label(ndimage.binary_fill_holes(piece) & ~piece)
    return int(n)
