"""The X-ray image as the engine sees it: attenuation line integrals, a field mask, a geometry.

CONVENTIONS.md §5: larger values mean more attenuation; pixels outside the collimated field
carry no signal and never drive the similarity.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from registration.core.geometry import CArm

#: Kinds of image an :class:`XRayImage` may carry.
IMAGE_KINDS = ("fluoro", "exposure", "drr", "dicom")

#: Block averages kept for reuse (the most recent, any image): a registration's levels ask for
#: the same few again; the bound keeps a long run's frames from each holding theirs.
KEPT_AVERAGES = 16
_averages: OrderedDict[tuple[int, int], tuple[weakref.ref, XRayImage]] = OrderedDict()
_averages_lock = threading.Lock()


@dataclass(frozen=True)
class XRayImage:
    """An X-ray image as the engine uses it.

    Attributes
    ----------
    image
        (rows, cols) float32 attenuation line integrals (CONVENTIONS §5: larger = more
        attenuation); zero outside the field.
    mask
        (rows, cols) bool, True inside the collimated field (the only usable pixels).
    geometry
        The C-arm view the image was taken with (rows and cols match the image).
    kind
        One of ``IMAGE_KINDS``: "fluoro", "exposure", "drr" or "dicom".
    meta
        Free-form provenance (dose, seed, devices, ...).
    """

    image: NDArray[np.float32]
    mask: NDArray[np.bool_]
    geometry: CArm
    kind: str = "fluoro"
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        image = np.asarray(self.image)
        mask = np.asarray(self.mask)
        if not isinstance(self.geometry, CArm):
            raise ValueError(f"geometry must be a CArm, got {type(self.geometry).__name__}")
        if image.ndim != 2:
            raise ValueError(f"image must be 2-D (rows, cols), got shape {image.shape}")
        if not np.issubdtype(image.dtype, np.number):
            raise ValueError(f"image must be numeric, got dtype {image.dtype}")
        expected = (self.geometry.rows, self.geometry.cols)
        if image.shape != expected:
            raise ValueError(f"image shape {image.shape} does not match the geometry's rows x cols {expected}")
        if mask.shape != image.shape:
            raise ValueError(f"mask shape {mask.shape} does not match image shape {image.shape}")
        if mask.dtype != np.bool_:
            raise ValueError(f"mask must be boolean, got dtype {mask.dtype}")
        if not mask.any():
            raise ValueError("mask is empty: no pixel of the image lies inside the field")
        image = np.ascontiguousarray(image, dtype=np.float32)
        bad = ~np.isfinite(image) & mask
        if bad.any():
            raise ValueError(f"image has {int(bad.sum())} NaN or infinite pixels inside the mask")
        if self.kind not in IMAGE_KINDS:
            raise ValueError(f"kind must be one of {IMAGE_KINDS}, got {self.kind!r}")
        object.__setattr__(self, "image", image)
        object.__setattr__(self, "mask", np.ascontiguousarray(mask))

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.image.shape[0]), int(self.image.shape[1]))

    def __repr__(self) -> str:
        """A line a notebook shows: the kind, the size, the field and the C-arm (not the pixels)."""
        rows, cols = self.shape
        g = self.geometry
        source = self.meta.get("source")
        field = 100 * float(self.mask.mean())
        return (f"{type(self).__name__}({self.kind}, {cols}x{rows} px, field {field:.0f} % of the pixels, "
                f"primary {g.primary_deg:+.1f} deg, secondary {g.secondary_deg:+.1f} deg, SID {g.sid_mm:.0f} mm, "
                f"SOD {g.sod_mm:.0f} mm" + (f", source {str(source)!r}" if source else "") + ")")  # fmt: skip

    def downsample(self, factor: int) -> XRayImage:
        """Average ``factor`` x ``factor`` pixel blocks; the mask keeps blocks wholly inside.

        The geometry is resized to the same detector area (pixel centers stay exact), so
        ``rows`` and ``cols`` must be multiples of ``factor``.
        """
        if int(factor) != factor or factor < 1:
            raise ValueError(f"factor must be a positive integer, got {factor}")
        factor = int(factor)
        if factor == 1:
            return self
        # each level of a registration asks again for the same blocks: the recent ones are kept
        key = (id(self), factor)
        with _averages_lock:
            kept = _averages.get(key)
            if kept is not None and kept[0]() is self:
                _averages.move_to_end(key)
                return kept[1]
        made = self._block_averaged(factor)
        with _averages_lock:
            _averages[key] = (weakref.ref(self), made)
            while len(_averages) > KEPT_AVERAGES:
                _averages.popitem(last=False)
        return made

    def _block_averaged(self, factor: int) -> XRayImage:
        rows, cols = self.shape
        if rows % factor or cols % factor:
            raise ValueError(f"image {rows}x{cols} is not a multiple of the factor {factor}")
        if rows // factor < 2 or cols // factor < 2:
            raise ValueError(f"image {rows}x{cols} too small to downsample by {factor}")
        r, c = rows // factor, cols // factor
        img = np.where(self.mask, self.image, 0.0).reshape(r, factor, c, factor).mean(axis=(1, 3))
        mask = self.mask.reshape(r, factor, c, factor).all(axis=(1, 3))
        if not mask.any():
            raise ValueError(f"the image's field ({int(self.mask.sum())} pixels of {rows}x{cols}) holds no "
                             f"{factor}x{factor} block wholly inside it: too small or thin to register")  # fmt: skip
        img = np.where(mask, img, 0.0).astype(np.float32)
        meta = {**self.meta, "downsampled_by": factor * int(self.meta.get("downsampled_by", 1))}
        made = XRayImage(img, mask, self.geometry.resized(r, c), self.kind, meta)
        made.image.flags.writeable = made.mask.flags.writeable = False  # shared by every caller
        return made


def line_integrals(
    intensity: NDArray[np.floating] | NDArray[np.integer],
    *,
    mask: NDArray[np.bool_] | None = None,
    i0: float | None = None,
) -> NDArray[np.float32]:
    """Attenuation line integrals ``-log(I / I0)`` from linear detector intensities (CONVENTIONS §5).

    ``intensity`` grows with the X-rays that reach the detector (air bright). ``i0`` is the
    unattenuated intensity; by default the largest intensity inside ``mask`` (the whole image
    without one), so the brightest pixel of the field has line integral 0. Intensities are
    floored at ``i0 * 1e-6`` (a line integral of at most 13.8), so a zero pixel stays finite.

    Examples
    --------
    >>> line_integrals(np.array([[100.0, 50.0], [25.0, 100.0]])).astype(float).round(3).tolist()
    [[0.0, 0.693], [1.386, 0.0]]
    """
    values = np.asarray(intensity, dtype=np.float64)
    if values.ndim != 2:
        raise ValueError(f"intensity must be 2-D (rows, cols), got shape {values.shape}")
    inside = values[mask] if mask is not None else values.reshape(-1)
    if inside.size == 0:
        raise ValueError("mask is empty: no pixel of the image lies inside the field")
    if not np.all(np.isfinite(inside)):
        raise ValueError("intensity has NaN or infinite pixels inside the field")
    reference = float(np.max(inside)) if i0 is None else float(i0)
    if not (math.isfinite(reference) and reference > 0):
        raise ValueError(f"the unattenuated intensity i0 must be positive, got {reference}")
    out = np.log(reference / np.maximum(values, reference * 1e-6))
    return np.where(np.isfinite(out), out, 0.0).astype(np.float32)
