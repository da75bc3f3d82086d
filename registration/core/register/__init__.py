"""The image-based registration pipeline (the paper's Fig. 2), for one or more views.

The machine-based pose (``initial_motion``, identity when the patient has not moved) is
refined by comparing DRRs of the volume with the X-ray images under gradient difference,
optimised by simulated annealing over offsets in the view frame of the first view
(:mod:`registration.core.search`). One view: the paper's five parameters (tx, ty, rx, ry, rz;
tz is kept, a view cannot see motion along its beam). Two views of the same moment (biplane,
CONVENTIONS.md §6): all six, in plane A's view frame, the measure being the mean of the
views' gradient differences (:mod:`registration.core.problem`).

The search runs coarse to fine: each :class:`Level` is prepared once
(:class:`~registration.core.problem.LevelProblem`) and annealed by one or several capture
runs side by side; a short local polish (:func:`~registration.core.anneal.polish`) ends it.

One view ends with the depth correction (:func:`depth_correct`,
``RegistrationOptions.depth_correction``, on by default since this revision; off reproduces the
five-parameter results before it, Table I's among them): the high-passed depth scan
(:func:`registration.core.depth.depth_scan`) estimates tz, the pose moves there and the five
parameters are polished again, up to three scans. The result's ``patient_motion`` then holds
that tz (``depth_tz_mm``); the in-plane residual and the rotation, hence single-view success
(CONVENTIONS §4), do not depend on it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.checks import check_information, parameters_at_bounds
from registration.core.drr import DRRRenderer
from registration.core.images import XRayImage
from registration.core.metrics import residuals
from registration.core.problem import LevelProblem, support_mask
from registration.core.register.biplane import (
    CROSS_START_MM,
    PLANE_CAPTURE_ROUNDS,
    PLANES_AGREE_DEG,
    PLANES_AGREE_MM,
    ROTATION_ACROSS_WEIGHT,
    _plane_captures,
    combine_plane_estimates,
    plane_disagreement,
)
from registration.core.register.depth import DepthCorrection, depth_correct, depth_resolvable
from registration.core.register.inputs import Inputs, check_inputs, prepared_renderer, prepared_volume
from registration.core.register.monitor import _Monitor
from registration.core.register.options import Level, RegistrationOptions
from registration.core.register.result import Progress, RegistrationResult
from registration.core.register.rotation_check import (
    RIVAL_DISTINCT_DEG,
    RotationCheck,
    _check_rotations,
    rotation_check,
)
from registration.core.register.stages import _anneal_level, _HeldTz, _plane_a_capture, _polish
from registration.core.search import FIVE_PARAMETERS, SIX_PARAMETERS, SearchSpace
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: Names of the five parameters of a single-view registration (mm, mm, deg, deg, deg).
PARAMETERS = FIVE_PARAMETERS

__all__ = [
    "CROSS_START_MM",
    "FIVE_PARAMETERS",
    "PARAMETERS",
    "PLANES_AGREE_DEG",
    "PLANES_AGREE_MM",
    "PLANE_CAPTURE_ROUNDS",
    "RIVAL_DISTINCT_DEG",
    "ROTATION_ACROSS_WEIGHT",
    "SIX_PARAMETERS",
    "DepthCorrection",
    "Inputs",
    "Level",
    "Progress",
    "RegistrationOptions",
    "RegistrationResult",
    "RotationCheck",
    "check_inputs",
    "combine_plane_estimates",
    "depth_correct",
    "depth_resolvable",
    "plane_disagreement",
    "prepared_renderer",
    "prepared_volume",
    "register",
    "rotation_check",
    "support_mask",
]


def register(
    volume: Volume,
    views: XRayImage | Sequence[XRayImage],
    *,
    initial_motion: ArrayLike | None = None,
    options: RegistrationOptions | None = None,
    seed: int = 0,
    callback: Callable[[Progress], bool | None] | None = None,
    truth: ArrayLike | None = None,
    vessel_points_mm: ArrayLike | None = None,
    renderer: DRRRenderer | None = None,
) -> RegistrationResult:
    """Estimate the patient motion that aligns ``volume`` with the X-ray view(s).

    Parameters
    ----------
    volume:
        The 3DRA or CT (HU). Its label is repeated in the result.
    views:
        One :class:`XRayImage` (image in attenuation line integrals, field mask, geometry),
        or several taken at the same moment (biplane: plane A first; offsets are in its
        view frame).
    initial_motion:
        The machine-based pose as a 4x4 patient motion (identity by default).
    options:
        Search configuration; see :class:`RegistrationOptions`.
    seed:
        Seed of the annealing's random generator (same seed, same result).
    callback:
        Called with a :class:`Progress` at every iteration; return True to stop.
    truth:
        The true patient motion; when given the result carries residuals and success.
    vessel_points_mm:
        Target points for the mTRE (e.g. the vessel centerline), in volume world mm.
    renderer:
        A :class:`DRRRenderer` of ``volume`` to use; by default the volume is prepared for the
        views and the search (:func:`prepared_renderer`, cached: later registrations of the same
        volume object and field reuse it) and ``seconds`` excludes that preparation.
    """
    options = options or RegistrationOptions()
    inputs = check_inputs(volume, views, initial_motion, truth, renderer, options)
    for view in inputs.views:
        check_information(inputs.volume, view)  # no edges, no registration (NoInformationError)
    start = time.perf_counter()
    space = SearchSpace.for_views(
        inputs.views[0].geometry,
        inputs.initial_motion,
        optimize_tz=options.optimizes_tz(len(inputs.views)),
        bound_mm=options.bound_mm,
        bound_deg=options.bound_deg,
    )
    monitor = _Monitor(space, callback, start)
    rng = np.random.default_rng(seed)
    x, f = space.start(), math.inf

    def prepare(image_px: int, volume_level: int, stage: int) -> LevelProblem:
        return LevelProblem.prepare(inputs.renderer, inputs.views, image_px=image_px, volume_level=volume_level,
                                    motion=space.motion(x), margin_mm=options.margin_mm(stage))  # fmt: skip

    # (index into the options' levels and support margins, level); Progress numbers them in order
    stages: list[tuple[int, Level]] = list(enumerate(options.levels))
    starts: list[Array] = [x]
    shown = 0  # the level number Progress shows for the first of ``stages``
    multi = len(inputs.views) > 1 and space.optimizes_tz
    if multi and options.plane_captures:
        starts, f = _plane_captures(inputs, space, options, rng, monitor)
        x = starts[0]
        if len(starts) == 1:
            # the planes agree: the capture level is done, the pair's levels follow
            if options.pair_levels is not None:
                last = len(options.levels) - 1
                stages = [(min(1 + n, last), lv) for n, lv in enumerate(options.pair_levels)]
            else:
                stages = stages[1:]
        else:
            # they do not: the pair's own capture level, one run from each start
            stages[0] = (0, replace(options.levels[0], restarts=len(starts)))
        shown = 1
    elif multi and options.plane_a_capture:
        x, f = _plane_a_capture(inputs, space, options, rng, monitor)
        shown = 1
    for n, (stage, level) in enumerate(stages):
        if monitor.stopped:
            break
        problem = prepare(level.image_px, level.volume_level, stage)
        begin: Array | list[Array] = x
        if n == 0 and len(starts) > 1:
            begin = starts
        else:
            level = replace(level, restarts=options.capture_runs(level, len(inputs.views)))
        best = _anneal_level(problem, space, level, shown + n, begin, rng, monitor, options.threads)
        x, f = best.x, best.fun
    pair = multi and options.plane_captures
    polish_shown = shown + len(stages)
    if options.polish and pair and options.pair_coarse_polish_evaluations and not monitor.stopped:
        first = options.levels[0]
        coarse = prepare(first.image_px, first.volume_level, len(options.levels) - 1)
        best = _polish(coarse, space, polish_shown, x, options, monitor, pair=True, coarse=True)
        x, f = best.x, best.fun
        polish_shown += 1
    if options.polish and not monitor.stopped:
        stage = len(options.levels)
        best = _polish(prepare(options.polish_image_px, options.polish_volume_level, stage), space,
                       polish_shown, x, options, monitor, pair=pair)  # fmt: skip
        x, f = best.x, best.fun
    depth: DepthCorrection | None = None
    if options.polish and options.depth_correction and len(inputs.views) == 1 and not space.optimizes_tz:
        if not monitor.stopped and depth_resolvable(inputs.renderer, options):
            depth = depth_correct(inputs.renderer, inputs.views[0], space, x, f, options, monitor, polish_shown + 1)
            x, f = depth.x, depth.fun
    check: RotationCheck | None = None
    if depth is not None and options.rotation_check and not monitor.stopped:
        x, f, depth, check = _check_rotations(inputs, space, x, f, depth, options, monitor, polish_shown + 2)
    return _result(inputs, space, x, f, monitor, vessel_points_mm, time.perf_counter() - start, depth, check)


def _result(inputs: Inputs, space: SearchSpace, x: Array, f: float, monitor: _Monitor,
            vessel_points_mm: ArrayLike | None, seconds: float, depth: DepthCorrection | None = None,
            check: RotationCheck | None = None) -> RegistrationResult:  # fmt: skip
    m_est = space.motion(x) if depth is None else _HeldTz(replace(space, names=SIX_PARAMETERS), depth.tz_mm).motion(x)
    res = None
    if inputs.truth is not None:
        res = residuals(m_est, inputs.truth, space.frame, vessel_points_mm, optimizes_tz=space.optimizes_tz)
    return RegistrationResult(
        patient_motion=m_est,
        similarity=-f,
        similarity_trace=monitor.trace,
        drr_count=monitor.drr_count,
        seconds=seconds,
        stopped=monitor.stopped,
        offsets=x,
        geometry=space.frame,
        volume_label=inputs.volume.label,
        residual=res,
        parameters=space.names,
        views=tuple(v.geometry for v in inputs.views),
        capture_motions=tuple(monitor.captures),
        at_bounds=tuple(space.names[i] for i in parameters_at_bounds(x, space.bounds)),
        depth_tz_mm=None if depth is None else depth.tz_mm,
        depth_moves_mm=() if depth is None else depth.moves_mm,
        rotation_check=check,
    )
