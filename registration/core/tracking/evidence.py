"""What the engine can tell about one registration result without a run around it: the evidence
the confidence rule weighs (:mod:`registration.core.confidence`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.confidence import Evidence, edge_fraction
from registration.core.depth import DepthProbe
from registration.core.drr import DRRRenderer
from registration.core.geometry import check_rigid, offsets_to_matrix, rigid
from registration.core.images import XRayImage
from registration.core.register import support_mask
from registration.core.tracking.tracker import _Level, _level_factor
from registration.core.volume import Volume

Array = NDArray[np.float64]


def probe_measure(
    volume: Volume,
    xray: XRayImage,
    motion: Array,
    renderer: DRRRenderer,
    *,
    image_px: int = 128,
    volume_voxels: int = 128,
    support_margin_mm: float = 4.0,
) -> tuple[_Level, Callable[[Array], float]]:
    """``xray`` at about ``image_px`` pixels with its support at ``motion``, and its gradient
    difference against the DRR at a pose (the renderer's level of about ``volume_voxels``
    voxels); a pose asked for again is not rendered again."""
    level = renderer.level_nearest(volume_voxels)
    factor = _level_factor(xray.geometry, image_px)
    small_geom = xray.geometry.resized(xray.geometry.rows // factor, xray.geometry.cols // factor)
    lv = _Level(xray, factor, support_mask(volume, small_geom, motion, support_margin_mm), 1)
    seen: dict[bytes, float] = {}

    def f(pose: Array) -> float:
        key = np.asarray(pose, dtype=np.float64).tobytes()
        if key not in seen:
            seen[key] = lv.measures[0](renderer.render(lv.geometry, pose, level=level, mask=lv.mask))
        return seen[key]

    return lv, f


def registration_evidence(
    volume: Volume,
    xray: XRayImage,
    motion: ArrayLike,
    *,
    renderer: DRRRenderer | None = None,
    capture_motions: Sequence[ArrayLike] | None = None,
    image_px: int = 128,
    volume_voxels: int = 128,
    support_margin_mm: float = 4.0,
    depth: DepthProbe | None = None,
    agreement_in_plane: bool = False,
    probe: tuple[_Level, Callable[[Array], float]] | None = None,
) -> Evidence:
    """What the engine can tell about one registration result without a run around it.

    ``margin``: the measure's mean margin at ``motion`` over poses perturbed by PERTURB_MM /
    PERTURB_DEG along each of the five parameters (10 DRRs at about ``image_px`` pixels),
    relative to the measure; ``rotation_margin``: the smaller margin over the out-of-plane
    rotations (rx, ry) perturbed by ROTATION_PROBE_DEG (4 DRRs); ``edges``: the field's edge
    fraction; ``agreement``: the capture runs' agreement with the result (when
    ``capture_motions`` are given); ``depth``: a
    :class:`~registration.core.depth.DepthProbe` of the result (its ``shift_mm`` and ``tz_mm``
    become the evidence ``depth_shift_mm`` and ``depth_tz_mm``); ``agreement_in_plane``: the
    capture runs compared across the beam only (a single-plane result, whose tz the captures do
    not estimate: :func:`registration.core.confidence.capture_agreement`); ``probe``: the view's
    :func:`probe_measure` at ``motion`` when the caller has it already.
    """
    from registration.core.confidence import PERTURB_DEG, PERTURB_MM, ROTATION_PROBE_DEG, capture_agreement

    m = check_rigid(motion, name="motion")
    if renderer is None:
        renderer = DRRRenderer(volume, levels=3)
    lv, f = probe or probe_measure(volume, xray, m, renderer, image_px=image_px, volume_voxels=volume_voxels,
                                   support_margin_mm=support_margin_mm)  # fmt: skip
    geometry = xray.geometry
    f_est = f(m)
    steps = [PERTURB_MM, PERTURB_MM, PERTURB_DEG, PERTURB_DEG, PERTURB_DEG]
    slots = [0, 1, 3, 4, 5]  # tx, ty, rx, ry, rz of the six offsets

    def margin(slot: int, step: float) -> float:
        # the measure's margin over the better of the two poses moved by +-step along one offset
        worst = -math.inf
        for sign in (1.0, -1.0):
            o = np.zeros(6)
            o[slot] = sign * step
            worst = max(worst, f(offsets_to_matrix(o, geometry) @ m))
        return f_est - worst

    margins = [margin(slot, step) for slot, step in zip(slots, steps, strict=True)]
    # the out-of-plane rotations (about the view's x and y axes), which one view sees least,
    # at ROTATION_PROBE_DEG: a wrong local optimum of rx / ry is flat there
    rotation_margins = [margin(slot, ROTATION_PROBE_DEG) for slot in (3, 4)]
    agreement = None
    if capture_motions:
        along = geometry.direction if agreement_in_plane else None
        agreement = capture_agreement([np.asarray(c) for c in capture_motions], m, geometry.isocenter_mm, along)
    return Evidence(
        margin=float(np.mean(margins)) / max(abs(f_est), 1e-12),
        rotation_margin=float(min(rotation_margins)) / max(abs(f_est), 1e-12),
        agreement=agreement,
        edges=edge_fraction(lv.image, lv.mask),
        depth_shift_mm=None if depth is None else float(depth.shift_mm),
        depth_tz_mm=None if depth is None else float(depth.tz_mm),
    )


def beam_margin(
    volume: Volume,
    views: Sequence[XRayImage],
    motion: ArrayLike,
    *,
    renderer: DRRRenderer,
    probes: Sequence[tuple[_Level, Callable[[Array], float]]] | None = None,
) -> float | None:
    """Two or more views: whether each view's depth is confirmed by another view. The estimate is
    moved BEAM_PROBE_MM either way along each view's central ray, which that view barely sees and
    the others see across their beams; the smallest margin of another view's measure at
    ``motion`` over those poses, relative to it (4 DRRs of about 128 px for two views, and one
    per view at ``motion`` unless ``probes``, each view's :func:`probe_measure` at ``motion``,
    has it already). None for one view."""
    from registration.core.confidence import BEAM_PROBE_MM

    if len(views) < 2:
        return None
    m = check_rigid(motion, name="motion")
    measures = [f for _, f in (probes or [probe_measure(volume, v, m, renderer) for v in views])]
    at_estimate = [f(m) for f in measures]
    worst = math.inf
    for i, view in enumerate(views):
        for sign in (1.0, -1.0):
            moved = rigid(None, sign * BEAM_PROBE_MM * np.asarray(view.geometry.direction)) @ m
            for j, f in enumerate(measures):
                if j != i:
                    worst = min(worst, (at_estimate[j] - f(moved)) / max(abs(at_estimate[j]), 1e-12))
    return float(worst)
