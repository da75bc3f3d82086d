"""The shifted start: a patient moved far across the image, found by phase correlation.

The annealing searches a box around the machine-based pose. A patient moved further than the
box across the beam (a table moved, the head repositioned) leaves the search in a wrong minimum
inside the box or walking the wrong way. The shift of the anatomy between the DRR at the
machine-based pose and the X-ray image is found at once by phase correlation of their gradient
magnitudes (scikit-image's :func:`~skimage.registration.phase_cross_correlation`, on ~128 px
images at the coarse level): one DRR per view.

Each view's shift gives the patient's translation across its beam at the iso-center (pixel
spacing over magnification); with two views, each plane's translation and the two combined
(least squares over the planes) are candidates. A candidate is taken only when it moves the
start by at least :attr:`StartOptions.shift_mm` (within the paper's clinical offsets the search
needs no help, so their registrations are unchanged) and the views' gradient difference (their
sum, the biplane measure) is better there than at the machine-based pose. The registration then
runs from it, its box centred there; when its estimate lies beyond the box around the
machine-based pose, :func:`registration.core.assess.veto` withholds it for a look.

The same shift checks an estimate afterwards (:func:`look_again`): at a right estimate the DRR
and the image line up (the shift left is under a coarse pixel); a search that settled in a wrong
minimum inside its box leaves the anatomy several mm away. Then, or when one view's estimate
turns the head more than one view can confirm (a tilted head can line up with the image's edges),
the search runs again from the shifted start (any shift of at least
:attr:`StartOptions.recheck_mm`) and the estimate with the better measure is kept. A
registration whose first estimate is right costs one DRR per view more.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from registration.core.drr import DRRRenderer
from registration.core.geometry import rigid
from registration.core.images import XRayImage
from registration.core.register.inputs import Inputs, coarse_level, prepared_renderer
from registration.core.register.options import RegistrationOptions
from registration.core.register.result import SINGLE_PLANE_MAX_TURN_DEG, RegistrationResult, single_plane_turn_deg
from registration.core.similarity import gradient_difference, sobel_gradients

#: The images compared are block-averaged to about this many pixels across.
SHIFT_IMAGE_PX = 128


def _coarse(view: XRayImage) -> XRayImage:
    rows, cols = view.shape
    for factor in range(max(1, min(rows, cols) // SHIFT_IMAGE_PX), 0, -1):
        if rows % factor == 0 and cols % factor == 0:
            try:
                return view.downsample(factor)
            except ValueError:  # no block wholly inside the field
                continue
    return view


def _edges(image: NDArray[np.floating], mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Gradient magnitude inside the field (its border eroded: the collimator's edge is no anatomy)."""
    g = np.hypot(*sobel_gradients(image))
    inside = ndimage.binary_erosion(mask, iterations=2)
    g = np.where(inside, g, 0.0)
    spread = float(g[inside].std()) if inside.any() else 0.0
    return g / spread if spread > 0 else g


def view_shift_mm(
    renderer: DRRRenderer, view: XRayImage, motion: NDArray[np.float64], level: int, *, coarse: XRayImage | None = None
) -> NDArray[np.float64]:
    """The patient's translation across ``view``'s beam at the iso-center (world mm) that moves
    the DRR at ``motion`` onto the image, by phase correlation of their gradient magnitudes
    (``coarse``: the view already block-averaged to ~128 px, by default done here)."""
    from skimage.registration import phase_cross_correlation

    coarse = _coarse(view) if coarse is None else coarse
    g = coarse.geometry
    drr = renderer.render(g, motion, level=level)
    image = _edges(coarse.image, coarse.mask)
    moving = _edges(drr, coarse.mask)
    shift, _, _ = phase_cross_correlation(image, moving, upsample_factor=4, normalization=None)
    u, v, _ = g.detector_axes()
    return (shift[1] * g.pixel_mm[1] * u + shift[0] * g.pixel_mm[0] * v) / g.magnification


def _combined(views: tuple[XRayImage, ...], shifts: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The 3-D translation whose part across each view's beam is nearest that view's shift."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for view, s in zip(views, shifts, strict=True):
        d = view.geometry.direction
        p = np.eye(3) - np.outer(d, d)  # across the beam
        a += p
        b += p @ s
    return np.linalg.lstsq(a, b, rcond=None)[0]


def _score(
    renderer: DRRRenderer, coarse_views: tuple[XRayImage, ...], motion: NDArray[np.float64], level: int
) -> list[float]:
    scores = []
    for coarse in coarse_views:
        scores.append(gradient_difference(renderer.render(coarse.geometry, motion, level=level), coarse.image,
                                          coarse.mask))  # fmt: skip
    return scores


def shifted_start(
    inputs: Inputs, options: RegistrationOptions, *, threshold_mm: float | None = None
) -> tuple[Inputs, float]:
    """``inputs`` started from the shifted start when one is taken (see the module), with its
    renderer prepared around it, and the shift's length (mm; 0.0 when none is taken);
    ``threshold_mm``: the least shift taken (default :attr:`StartOptions.shift_mm`)."""
    threshold = options.start.shift_mm if threshold_mm is None else threshold_mm
    if threshold is None:
        return inputs, 0.0
    renderer, views = inputs.renderer, tuple(inputs.views)
    start = np.asarray(inputs.initial_motion, dtype=np.float64)
    level = coarse_level(renderer, options, len(views))
    coarse = tuple(_coarse(v) for v in views)
    shifts = [view_shift_mm(renderer, v, start, level, coarse=c) for v, c in zip(views, coarse, strict=True)]
    candidates = shifts + ([_combined(views, shifts)] if len(views) > 1 else [])
    candidates = [t for t in candidates if float(np.linalg.norm(t)) >= threshold]
    if not candidates:
        return inputs, 0.0
    here = _score(renderer, coarse, start, level)
    best, best_score = None, None
    for t in candidates:
        moved = rigid(None, t) @ start
        scores = _score(renderer, coarse, moved, level)
        if sum(scores) > sum(here) and (best_score is None or sum(scores) > best_score):
            best, best_score = moved, sum(scores)
    if best is None:
        return inputs, 0.0
    shifted = replace(inputs, initial_motion=best, renderer=prepared_renderer(inputs.volume, views, best, options))
    return shifted, float(np.linalg.norm(best[:3, 3] - start[:3, 3]))


def shift_left_mm(inputs: Inputs, result: RegistrationResult, options: RegistrationOptions) -> float:
    """How far the image shift still moves the anatomy at ``result``'s estimate (mm at the
    iso-center; one DRR per view): about 0 when the estimate is right (within 0.4 mm on the
    shared real CT's draws), several mm when the search settled in a wrong minimum."""
    renderer, views = inputs.renderer, tuple(inputs.views)
    level = coarse_level(renderer, options, len(views))
    motion = np.asarray(result.patient_motion, dtype=np.float64)
    shifts = [view_shift_mm(renderer, v, motion, level) for v in views]
    left = shifts[0] if len(views) == 1 else _combined(views, shifts)
    return float(np.linalg.norm(left))


def look_again(
    register_once: Callable[[Inputs], RegistrationResult],
    inputs: Inputs,
    result: RegistrationResult,
    options: RegistrationOptions,
) -> RegistrationResult:
    """A second search from the image shift when the first estimate leaves the anatomy at least
    :attr:`StartOptions.recheck_mm` from where the image shows it, or when one view's estimate
    turns the head more than ``SINGLE_PLANE_MAX_TURN_DEG`` (it would be withheld); the estimate
    with the better measure is kept. Runs only after a search that started from the machine-based
    pose (walked or not); the result carries why (``second_search``), the shift left
    (``recheck_shift_mm``) and both searches' costs."""
    threshold = options.start.recheck_mm
    if threshold is None or result.stopped or result.start_shift_mm:
        return result
    left = shift_left_mm(inputs, result, options)
    turn = single_plane_turn_deg(result)
    if left >= threshold:
        why = f"the first estimate left the anatomy {left:.0f} mm from where the image shows it"
    elif turn is not None and turn > SINGLE_PLANE_MAX_TURN_DEG:
        why = f"the first estimate turned the head {turn:.0f} deg, more than one view can confirm"
    else:
        return result
    shifted, shift_mm = shifted_start(inputs, options, threshold_mm=threshold)
    if not shift_mm:  # no shift of the anatomy to start from
        return result
    second = register_once(shifted)
    second.start_shift_mm = shift_mm
    kept = second if second.similarity > result.similarity else result
    kept.recheck_shift_mm, kept.second_search = left, why
    kept.drr_count = result.drr_count + second.drr_count
    kept.seconds = max(result.seconds, second.seconds)  # both timed from the registration's start
    kept.similarity_trace = list(result.similarity_trace) + list(second.similarity_trace)
    kept.stages = result.stages + tuple(replace(c, stage=f"second search: {c.stage}") for c in second.stages)
    return kept
