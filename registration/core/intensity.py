"""An X-ray image's intensities brought onto the DRR's, whatever display chain stored them.

Clinical systems often store display-processed pixels: a window, a non-linear look-up table and
a gamma, either polarity, 8 to 16 bits (PixelIntensityRelationship DISP, or no tag at all). Read
as LOG they are a monotone but non-linear function of the attenuation line integrals
(CONVENTIONS.md §5), which gradient difference, fitting one global scale, cannot undo.

:func:`match_intensities` estimates the inverse look-up table from the DRR at the machine-based
pose: the image's values inside the field are replaced by the DRR's values of the same rank
(histogram matching: every pixel's rank among the field's pixels mapped onto the DRR's quantile
function). Any strictly increasing look-up table of the stored values gives the same ranks, so
every such variant of one image becomes the same image (up to the ties a coarser bit depth
makes). The polarity (dense structures bright or dark) is the one whose matched image, smoothed,
correlates better with the smoothed DRR; the margin between the two is reported.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm
from registration.core.images import XRayImage

#: How a registration treats the image's intensities: "as-read" (line integrals as the reader
#: converted them), "match" (the inverse look-up table estimated from the DRR, see the module),
#: "auto" (matched when the image's intensities are not known to be line integrals: its reader
#: noted an assumption, ``meta["intensity_note"]``, as for DISP or a missing relationship tag).
INTENSITY_MODES = ("auto", "as-read", "match")

#: Pixels across the reference DRR's field (the histogram needs no finer DRR).
REFERENCE_PX = 128

#: Gaussian smoothing (mm at the detector) of both images before the polarity's correlation:
#: coarse enough that an offset of the machine-based pose still overlaps the same structures.
POLARITY_SMOOTHING_MM = 6.0


@dataclass(frozen=True)
class IntensityMatch:
    """What :func:`match_intensities` assumed of one image.

    ``polarity``: +1 the stored pixels grew with attenuation as read, -1 they were inverted;
    ``polarity_margin``: correlation of the chosen polarity minus the other's (small: unsure);
    ``levels``: distinct stored values in the field (256 for an 8-bit image);
    ``correlation``: the smoothed images' correlation at the chosen polarity.
    """

    polarity: int
    polarity_margin: float
    correlation: float
    levels: int

    def note(self) -> str:
        side = "as read" if self.polarity > 0 else "inverted"
        return (
            f"intensities matched to the DRR's (inverse look-up table from {self.levels} levels, "
            f"polarity {side}, margin {self.polarity_margin:.2f})"
        )

    def to_dict(self) -> dict:
        return {
            "polarity": self.polarity,
            "polarity_margin": self.polarity_margin,
            "correlation": self.correlation,
            "levels": self.levels,
        }


def _ranks(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """Mid-ranks in (0, 1) (ties share their mean rank)."""
    order = np.argsort(values, kind="stable")
    sorted_v = values[order]
    n = values.size
    # the first and last index of each run of equal values
    starts = np.concatenate([[0], np.flatnonzero(np.diff(sorted_v) != 0) + 1])
    ends = np.concatenate([starts[1:], [n]])
    mid = (starts + ends - 1) / 2.0
    ranks = np.empty(n)
    ranks[order] = np.repeat(mid, ends - starts)
    return (ranks + 0.5) / n


def _quantile_map(values: NDArray[np.float64], reference: NDArray[np.float64]) -> NDArray[np.float64]:
    """``values`` replaced by the ``reference`` values of the same rank."""
    ref = np.sort(reference)
    q = (np.arange(ref.size) + 0.5) / ref.size
    return np.interp(_ranks(values), q, ref)


def _smoothed_ncc(a: NDArray[np.float64], b: NDArray[np.float64], mask: NDArray[np.bool_], sigma_px: float) -> float:
    w = ndimage.gaussian_filter(mask.astype(np.float64), sigma_px)
    inside = mask & (w > 0.5)
    if inside.sum() < 16:
        inside = mask
    sa = ndimage.gaussian_filter(np.where(mask, a, 0.0), sigma_px) / np.maximum(w, 1e-6)
    sb = ndimage.gaussian_filter(np.where(mask, b, 0.0), sigma_px) / np.maximum(w, 1e-6)
    x = sa[inside] - sa[inside].mean()
    y = sb[inside] - sb[inside].mean()
    den = float(np.sqrt((x @ x) * (y @ y)))
    return float(x @ y) / den if den > 0 else 0.0


def match_intensities(
    image: ArrayLike,
    mask: ArrayLike,
    reference: ArrayLike,
    reference_mask: ArrayLike,
    *,
    sigma_px: float = 3.0,
) -> tuple[NDArray[np.float32], IntensityMatch]:
    """``image`` (any monotone function of the attenuation, either polarity) mapped onto the
    distribution of ``reference`` (the DRR) inside the masks; outside ``mask`` the matched
    image's smallest value. The polarity is chosen by the correlation of the two images smoothed
    by ``sigma_px`` on ``reference``'s grid (``image`` is resampled to it by block means when
    larger). Raises ValueError on empty masks or shapes that do not divide."""
    img = np.asarray(image, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    ref = np.asarray(reference, dtype=np.float64)
    rm = np.asarray(reference_mask, dtype=bool)
    if img.shape != m.shape or ref.shape != rm.shape:
        raise ValueError("image and reference must each have a mask of their shape")
    if not m.any() or not rm.any():
        raise ValueError("an empty field: nothing to match the intensities on")
    ref_values = ref[rm]
    values = img[m]
    levels = int(np.unique(values).size)
    best: tuple[float, int, NDArray[np.float64]] | None = None
    scores = {}
    for polarity in (1, -1):
        mapped = np.full(img.shape, 0.0)
        matched_values = _quantile_map(polarity * values, ref_values)
        mapped[m] = matched_values
        mapped[~m] = matched_values.min()
        small, small_mask = _on_grid(mapped, m, ref.shape)
        score = _smoothed_ncc(small, ref, small_mask & rm, sigma_px)
        scores[polarity] = score
        if best is None or score > best[0]:
            best = (score, polarity, mapped)
    assert best is not None
    score, polarity, mapped = best
    info = IntensityMatch(polarity=polarity, polarity_margin=float(score - scores[-polarity]),
                          correlation=float(score), levels=levels)  # fmt: skip
    return mapped.astype(np.float32), info


def _on_grid(image: NDArray[np.float64], mask: NDArray[np.bool_], shape: tuple[int, ...]):
    """Block means of ``image`` onto ``shape`` (an integer factor smaller), the mask's blocks
    kept where wholly inside."""
    if image.shape == shape:
        return image, mask
    fr, fc = image.shape[0] // shape[0], image.shape[1] // shape[1]
    if fr < 1 or fc < 1 or fr * shape[0] != image.shape[0] or fc * shape[1] != image.shape[1]:
        raise ValueError(f"image shape {image.shape} is not a whole multiple of the reference's {shape}")
    small = image.reshape(shape[0], fr, shape[1], fc).mean(axis=(1, 3))
    small_mask = mask.reshape(shape[0], fr, shape[1], fc).all(axis=(1, 3))
    return small, small_mask


def reference_geometry(geometry: CArm, px: int = REFERENCE_PX) -> CArm:
    """The view at about ``px`` pixels across, an integer factor coarser than the image."""
    factor = max(1, min(geometry.rows, geometry.cols) // px)
    while factor > 1 and (geometry.rows % factor or geometry.cols % factor):
        factor -= 1
    return geometry.resized(geometry.rows // factor, geometry.cols // factor)


def matched_view(view: XRayImage, drr: ArrayLike, drr_mask: ArrayLike) -> tuple[XRayImage, IntensityMatch]:
    """``view`` with its intensities matched to ``drr`` (rendered at the machine-based pose on
    :func:`reference_geometry`'s grid; ``drr_mask``: its pixels the volume reaches)."""
    shape = np.asarray(drr).shape
    small_mask = _on_grid(np.zeros(view.shape), view.mask, shape)[1]
    sigma_px = POLARITY_SMOOTHING_MM / (float(min(view.geometry.pixel_mm)) * view.shape[0] / shape[0])
    matched, info = match_intensities(
        view.image, view.mask, drr, np.asarray(drr_mask, dtype=bool) & small_mask, sigma_px=sigma_px
    )
    meta = dict(view.meta)
    meta["intensity_match"] = info.to_dict()
    return replace(view, image=matched, meta=meta), info


def needs_matching(view: XRayImage, mode: str) -> bool:
    """Whether ``mode`` (one of ``INTENSITY_MODES``) matches this view's intensities."""
    if mode not in INTENSITY_MODES:
        raise ValueError(f"intensity mode must be one of {INTENSITY_MODES}, got {mode!r}")
    if mode == "auto":
        return bool(view.meta.get("intensity_note"))
    return mode == "match"


def match_views(
    renderer: DRRRenderer,
    views: tuple[XRayImage, ...],
    motion: ArrayLike,
    mode: str,
    *,
    level: int,
    support: Callable[[CArm], NDArray[np.bool_]],
) -> tuple[tuple[XRayImage, ...], tuple[IntensityMatch | None, ...]]:
    """Each view matched (:func:`matched_view`) when ``mode`` asks for it, against a DRR of the
    renderer's ``level`` at ``motion`` (the machine-based pose) on :func:`reference_geometry`;
    ``support(geometry)``: the pixels whose rays the volume reaches. None for a view left as read."""
    out, infos = [], []
    for view in views:
        if not needs_matching(view, mode):
            out.append(view)
            infos.append(None)
            continue
        g = reference_geometry(view.geometry)
        drr = renderer.render(g, motion, level=level)
        matched, info = matched_view(view, drr, support(g))
        out.append(matched)
        infos.append(info)
    return tuple(out), tuple(infos)
