"""The depth correction of a single-plane estimate."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from registration.core.drr import DRRRenderer
from registration.core.images import XRayImage
from registration.core.problem import LevelProblem, iso_pixel_mm, level_factor, renderer_level
from registration.core.register.monitor import _Monitor
from registration.core.register.options import RegistrationOptions
from registration.core.register.stages import _HeldTz, _polish
from registration.core.search import SIX_PARAMETERS, SearchSpace

Array = NDArray[np.float64]


def depth_resolvable(renderer: DRRRenderer, options: RegistrationOptions) -> bool:
    """Whether the depth correction's scan level (:func:`registration.core.depth.scan_level`)
    is fine enough to see a magnification (``depth_max_voxel_mm``)."""
    from registration.core.depth import scan_level

    level = scan_level(renderer, options.depth_voxel_mm)
    return float(renderer.level_volume(level).spacing_mm.max()) <= options.depth_max_voxel_mm


@dataclass(frozen=True)
class DepthCorrection:
    """The outcome of :func:`depth_correct`: the five parameters, the measure there, tz."""

    x: Array
    fun: float
    tz_mm: float
    moves_mm: tuple[float, ...]


def depth_correct(
    renderer: DRRRenderer,
    view: XRayImage,
    space: SearchSpace,
    x: Array,
    f: float,
    options: RegistrationOptions,
    monitor: _Monitor,
    stage: int,
    tz_mm: float = 0.0,
) -> DepthCorrection:
    """The depth correction of a five-parameter estimate ``x`` (``space``'s, cost ``f``): scan
    along the beam (:func:`registration.core.depth.depth_scan`, high-passed, the rest held),
    move tz to the peak (within +- ``depth_bound_mm`` of the initial pose), polish the five
    parameters again at that tz (the polish's level, budget and reach), repeat while a scan
    moves tz by ``depth_move_mm`` or more, ``depth_rounds`` scans at most
    (:attr:`RegistrationOptions.depth_correction`). The scans' DRRs are counted in
    ``monitor``; ``tz_mm``: the estimate's tz (the initial pose's by default). Deterministic."""
    from registration.core.depth import depth_scan, scan_level

    six = replace(space, names=SIX_PARAMETERS)
    level = scan_level(renderer, options.depth_voxel_mm)
    # the scan compares at the polish's pixel (at the iso-center), not finer
    polish_level = renderer_level(renderer, options.polish_volume_level)
    polish_voxel_mm = float(renderer.level_volume(polish_level).spacing_mm.max())
    pixel_mm = iso_pixel_mm(view.geometry, level_factor(view.geometry, options.polish_image_px, polish_voxel_mm))
    step, bound = options.depth_scan_step_mm, options.depth_bound_mm
    tz, moves = float(tz_mm), []
    x = np.asarray(x, dtype=np.float64)
    for n in range(options.depth_rounds):
        if monitor.stopped:
            break
        half = bound if n == 0 else options.depth_rescan_mm
        # the offsets that stay within the bound, from the estimate's tz
        lo, hi = max(-half, -bound - tz), min(half, bound - tz)
        offsets = tuple(float(o) for o in np.arange(math.ceil(lo / step) * step, hi + 1e-9, step))
        if len(offsets) < 3:
            break
        motion = six.motion(np.insert(x, 2, tz))
        scan = depth_scan(renderer, view, motion, offsets_mm=offsets, image_px=options.depth_image_px,
                          volume_level=level, margin_mm=options.margin_mm(len(options.levels)),
                          pixel_at_iso_mm=pixel_mm)  # fmt: skip
        with monitor.lock:
            monitor.drr_count += scan.drr_count
        move = float(np.clip(tz + scan.tz_mm, -bound, bound)) - tz
        moves.append(move)
        if abs(move) < options.depth_move_mm and not (n == 0 and options.depth_first_polish):
            break
        tz += move
        problem = LevelProblem.prepare(renderer, (view,), image_px=options.polish_image_px,
                                       volume_level=options.polish_volume_level, motion=six.motion(np.insert(x, 2, tz)),
                                       margin_mm=options.margin_mm(len(options.levels)))  # fmt: skip
        held = _HeldTz(six, tz)
        polish_options = replace(options, polish_reach=options.depth_polish_reach,
                                 polish_evaluations=options.depth_polish_evaluations)  # fmt: skip
        best = _polish(problem, held, stage, x, polish_options, monitor)
        x, f = best.x, best.fun
    return DepthCorrection(x, f, tz, tuple(moves))


#: A rotation check's polish that ends more than this far from the estimate (deg) found a
