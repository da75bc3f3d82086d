"""No success without information: refuse inputs that carry no usable edges, flag estimates at the bounds.

Gradient-based similarity (gradient difference, Penney et al. 1998) scores edges. A constant
image (RescaleSlope 0, a blank frame), an empty or constant volume (all zeros, all air) or
an image whose field holds too few pixels with gradient gives the same score at every pose:
the optimizer then wanders to wherever its schedule ends, often a corner of the search box,
and that estimate must not be reported as a registration. :func:`check_information` is
called before the search (``register`` raises :class:`NoInformationError`, a ``ValueError``
whose message starts with "cannot register: "); :func:`parameters_at_bounds` tells which
parameters of an estimate ended on the search bounds, so a result there is never a success.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from registration.core.images import XRayImage
from registration.core.volume import Volume

#: A field pixel "has gradient" when its gradient magnitude exceeds this fraction of the
#: field's robust value range (1st to 99th percentile): noise-free constant regions have none,
#: a real fluoroscopy frame has edges on 5-40 % of its pixels.
EDGE_FRACTION_OF_RANGE = 0.01
#: At least this many field pixels with gradient ...
MIN_EDGE_PIXELS = 50
#: ... and at least this fraction of the field.
MIN_EDGE_FIELD_FRACTION = 0.002
#: A volume voxel is "structure" when it differs from the volume's median by more than this
#: (HU): soft tissue against air is ~1000 HU, bone against tissue ~500 HU, noise ~10-30 HU.
STRUCTURE_HU = 50.0
#: At least this many structure voxels (counted on a subsample of at most SAMPLE_VOXELS).
MIN_STRUCTURE_VOXELS = 100
SAMPLE_VOXELS = 262_144
#: A parameter within this fraction of its search span from a bound is "at the bound".
BOUND_FRACTION = 0.01


class NoInformationError(ValueError):
    """The inputs carry no edges to register on; the message starts with "cannot register: "."""

    def __init__(self, message: str) -> None:
        super().__init__(f"cannot register: {message}")


def image_edge_pixels(image: XRayImage) -> tuple[int, int]:
    """(field pixels with gradient, field pixels) of ``image`` (see EDGE_FRACTION_OF_RANGE)."""
    values = np.asarray(image.image, dtype=np.float64)
    mask = np.asarray(image.mask, dtype=bool)
    field = int(mask.sum())
    if field == 0:
        return 0, 0
    inside = values[mask]
    low, high = np.percentile(inside, [1.0, 99.0])
    value_range = float(high - low)
    if not np.isfinite(value_range) or value_range <= 0:
        return 0, field
    gy, gx = np.gradient(np.where(mask, values, np.median(inside)))
    magnitude = np.hypot(gx, gy)
    return int(np.count_nonzero(magnitude[mask] > EDGE_FRACTION_OF_RANGE * value_range)), field


def volume_structure_voxels(volume: Volume) -> tuple[int, int]:
    """(voxels differing from the median by more than STRUCTURE_HU, voxels counted) on a subsample."""
    data = np.asarray(volume.data)
    step = max(1, int(np.ceil((data.size / SAMPLE_VOXELS) ** (1.0 / 3.0))))
    sample = data[::step, ::step, ::step]
    median = float(np.median(sample))
    return int(np.count_nonzero(np.abs(sample - median) > STRUCTURE_HU)), int(sample.size)


def check_information(volume: Volume, image: XRayImage) -> None:
    """Raise :class:`NoInformationError` when ``volume`` or ``image`` carries no usable edges."""
    structure, counted = volume_structure_voxels(volume)
    if structure < MIN_STRUCTURE_VOXELS:
        low, high = float(np.min(volume.data)), float(np.max(volume.data))
        what = "constant" if high - low <= 0 else f"nearly uniform ({low:.4g} .. {high:.4g} HU)"
        raise NoInformationError(
            f"the volume {volume.label!r} is {what}: {structure} of {counted} sampled voxels differ from its median "
            f"by more than {STRUCTURE_HU:g} HU (at least {MIN_STRUCTURE_VOXELS} needed); an empty or constant "
            "volume has no structure to align"
        )
    edges, field = image_edge_pixels(image)
    needed = max(MIN_EDGE_PIXELS, int(np.ceil(MIN_EDGE_FIELD_FRACTION * field)))
    if edges < needed:
        source = image.meta.get("source") if isinstance(image.meta, dict) else None
        name = f" {source}" if source else ""
        raise NoInformationError(
            f"the X-ray image{name} has {edges} of {field} field pixels with gradient (at least {needed} needed): "
            "a constant or blank image (RescaleSlope 0?) has no edges to align"
        )


def check_in_field(volume: Volume, image: XRayImage, motion: np.ndarray, reach_mm: float) -> None:
    """Raise :class:`NoInformationError` when no ray of ``image``'s detector can meet ``volume``
    moved by ``motion`` (the start), even moved ``reach_mm`` further (the search's range): seen
    from the source, its bounding sphere grown by the reach lies beside the detector's corners by
    more than twice its angular radius, or wholly behind the source. Only a gross misplacement
    (a wrong iso-center, a volume or an initial motion metres off) is refused."""
    g = image.geometry
    n = np.asarray(volume.shape[::-1], dtype=np.float64) - 1.0  # (i, j, k)
    corners = np.array([[i, j, k, 1.0] for i in (0.0, n[0]) for j in (0.0, n[1]) for k in (0.0, n[2])])
    world = (motion @ volume.index_to_world @ corners.T).T[:, :3]
    center = world.mean(axis=0)
    radius = float(np.linalg.norm(world - center, axis=1).max()) + float(reach_mm)
    source = g.source_mm
    u, v, w = g.detector_axes()
    w = w if float(w @ (g.detector_center_mm - source)) > 0 else -w  # from the source toward the detector
    rel = center - source
    distance = float(np.linalg.norm(rel))
    if distance <= radius:
        return  # the source inside the sphere: rays meet it
    spread = 2.0 * math.asin(radius / distance)
    if float(rel @ w) / distance < -math.sin(spread):
        outside = True  # wholly behind the source
    else:
        edges = g.detector_corners_mm - source
        lo_u, hi_u = (f(np.arctan2(edges @ u, edges @ w)) for f in (np.min, np.max))
        lo_v, hi_v = (f(np.arctan2(edges @ v, edges @ w)) for f in (np.min, np.max))
        a_u, a_v = math.atan2(float(rel @ u), float(rel @ w)), math.atan2(float(rel @ v), float(rel @ w))
        outside = a_u + spread < lo_u or a_u - spread > hi_u or a_v + spread < lo_v or a_v - spread > hi_v
    if outside:
        name = f" {volume.label!r}" if volume.label else ""
        off = float(np.linalg.norm(center - np.asarray(g.isocenter_mm)))
        raise NoInformationError(
            f"the volume{name} does not project into the X-ray image's detector at the start, even moved "
            f"{reach_mm:g} mm (its center lies {off:.0f} mm from the iso-center): check the volume's position, "
            "the iso-center and the initial motion"
        )


def parameters_at_bounds(
    x: Sequence[float], bounds: Sequence[tuple[float, float]], *, fraction: float = BOUND_FRACTION
) -> list[int]:
    """Indices of the parameters of ``x`` within ``fraction`` of their span from a bound."""
    out = []
    for i, (value, (low, high)) in enumerate(zip(x, bounds, strict=True)):
        span = float(high) - float(low)
        if span <= 0:
            continue
        if float(value) - float(low) <= fraction * span or float(high) - float(value) <= fraction * span:
            out.append(i)
    return out
