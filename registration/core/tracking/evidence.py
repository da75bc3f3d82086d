"""What the engine can tell about one registration result without a run around it: the evidence
the confidence rule weighs (:mod:`registration.core.confidence`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.confidence import Evidence, edge_fraction
from registration.core.depth import DepthProbe
from registration.core.drr import DRRRenderer
from registration.core.geometry import check_rigid, offsets_to_matrix
from registration.core.images import XRayImage
from registration.core.register import support_mask
from registration.core.tracking.tracker import _Level, _level_factor
from registration.core.volume import Volume

Array = NDArray[np.float64]


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
    not estimate: :func:`registration.core.confidence.capture_agreement`).
    """
    from registration.core.confidence import PERTURB_DEG, PERTURB_MM, ROTATION_PROBE_DEG, capture_agreement

    m = check_rigid(motion, name="motion")
    if renderer is None:
        renderer = DRRRenderer(volume, levels=3)
    level = renderer.level_nearest(volume_voxels)
    factor = _level_factor(xray.geometry, image_px)
    small_geom = xray.geometry.resized(xray.geometry.rows // factor, xray.geometry.cols // factor)
    lv = _Level(xray, factor, support_mask(volume, small_geom, m, support_margin_mm), 1)
    geometry = xray.geometry

    def f(pose: Array) -> float:
        return lv.measures[0](renderer.render(lv.geometry, pose, level=level, mask=lv.mask))

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
