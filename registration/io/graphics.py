"""Burned-in graphics in an X-ray image: text, rulers and markers drawn at the largest value (full
white) in thin strokes that stand out from their surroundings, and lines of text at the smallest
(full black); masked with a margin (:func:`registration.io.field.find_field` runs it last)."""

from __future__ import annotations

from collections.abc import Sequence

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
        (vmin, _off_the_rim(field_mask) & (values <= vmin), True),
    ):
        if not candidates.any() or candidates.mean() > 0.5:
            continue
        other = (values >= vmax) if dark else (values <= vmin)  # the other extreme: not the surroundings
        out |= _strokes(values, field_mask & ~other, candidates, extreme, span, text_only=dark)
    if out.any():
        out = ndimage.binary_dilation(out, iterations=EDGE_MARGIN_PX)
    return out & field_mask


def _off_the_rim(field_mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The field without its 3 px rim (eroded three times, nothing beyond the image): for a
    whole-image field, the image without its 3 px frame."""
    if not field_mask.all():
        return ndimage.binary_erosion(field_mask, iterations=3, border_value=0)
    kept = np.zeros(field_mask.shape, dtype=bool)
    kept[3:-3, 3:-3] = True
    return kept


def _box(boxes: Sequence[tuple[slice, slice]], shape: tuple[int, ...], margin: int) -> tuple[slice, slice]:
    """The bounding box of ``boxes`` grown by ``margin`` px on every side, within ``shape``."""
    r0 = max(min(b[0].start for b in boxes) - margin, 0)
    r1 = min(max(b[0].stop for b in boxes) + margin, shape[0])
    c0 = max(min(b[1].start for b in boxes) - margin, 0)
    c1 = min(max(b[1].stop for b in boxes) + margin, shape[1])
    return slice(r0, r1), slice(c0, c1)


def _widest(labels: NDArray[np.integer], ids: Sequence[int], boxes: Sequence[tuple[slice, slice]]) -> dict[int, float]:
    """Each labelled component's (``ids``) largest distance (px) to the nearest pixel off it, as on
    the whole image: measured on the components' box grown by 1 px, the other components taken
    off (the nearest pixel off a component is never another's: an 8-connected path between two
    components crosses the background closer than either)."""
    box = _box([boxes[i - 1] for i in ids], labels.shape, 1)
    sub = labels[box]
    keep = np.zeros(int(labels.max()) + 1, dtype=bool)
    keep[np.asarray(ids)] = True
    mine = keep[sub]
    width = ndimage.distance_transform_edt(mine)
    widest = np.zeros(keep.size)
    np.maximum.at(widest, sub[mine], width[mine])
    return {i: float(widest[i]) for i in ids}


def _ring_means(
    values: NDArray[np.float64], field_mask: NDArray[np.bool_], candidates: NDArray[np.bool_],
    labels: NDArray[np.integer], ids: Sequence[int], boxes: Sequence[tuple[slice, slice]],
) -> dict[int, float]:  # fmt: skip
    """The mean of ``values`` over each component's (``ids``) ring: the field's pixels 2-3 px
    from the candidates, nearest that component (the larger label where rings meet), as on the
    whole image: measured on a box 3 px beyond the rings, so every dilation inside them is the
    whole image's."""
    box = _box([boxes[i - 1] for i in ids], labels.shape, 6)
    near = candidates[box]
    ring = ndimage.binary_dilation(near, iterations=3) & ~ndimage.binary_dilation(near) & field_mask[box]
    ring_labels = ndimage.grey_dilation(labels[box], size=(7, 7)) * ring
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.atleast_1d(ndimage.mean(values[box], ring_labels, np.asarray(ids)))
    return {i: float(m) for i, m in zip(ids, means, strict=True)}


def _strokes(
    values: NDArray[np.float64], field_mask: NDArray[np.bool_], candidates: NDArray[np.bool_], extreme: float,
    span: float, *, text_only: bool,
) -> NDArray[np.bool_]:  # fmt: skip
    """The components of ``candidates`` that are graphics (see :func:`find_graphics`). The cheap
    tests (size, a character's height) run first, the stroke width and the ring's contrast only
    around the components left."""
    labels, n = ndimage.label(candidates, structure=np.ones((3, 3), bool))
    if n == 0:
        return np.zeros(values.shape, dtype=bool)
    boxes = ndimage.find_objects(labels)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    left = [
        k for k in range(n)
        if boxes[k] is not None and sizes[k + 1] >= 3
        and not (text_only and boxes[k][0].stop - boxes[k][0].start > GRAPHICS_MAX_CHAR_PX)
    ]  # fmt: skip
    widest = _widest(labels, [k + 1 for k in left], boxes) if left else {}
    left = [k for k in left if 2.0 * widest[k + 1] <= GRAPHICS_MAX_STROKE_PX]
    if not left:
        return np.zeros(values.shape, dtype=bool)
    around = _ring_means(values, field_mask, candidates, labels, [k + 1 for k in left], boxes)
    thin = []
    for k in left:
        stroke = 2.0 * widest[k + 1]
        if not np.isfinite(around[k + 1]) or abs(extreme - around[k + 1]) < GRAPHICS_MIN_CONTRAST * span:
            continue
        height = boxes[k][0].stop - boxes[k][0].start
        extent = max(height, boxes[k][1].stop - boxes[k][1].start)
        if text_only:  # a word or a character: a line's height, with letters' holes or beside others
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
