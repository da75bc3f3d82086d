"""The rotation check of a single-plane estimate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from registration.core.anneal import AnnealResult
from registration.core.drr import DRRRenderer
from registration.core.geometry import invert_rigid, rotation_angle_deg
from registration.core.images import XRayImage
from registration.core.problem import LevelProblem
from registration.core.register.depth import DepthCorrection, depth_correct
from registration.core.register.inputs import Inputs
from registration.core.register.monitor import _cost, _Monitor
from registration.core.register.options import RegistrationOptions
from registration.core.register.result import RotationCheck
from registration.core.register.stages import _HeldTz, _polish
from registration.core.search import SIX_PARAMETERS, SearchSpace

Array = NDArray[np.float64]


RIVAL_DISTINCT_DEG = 2.0


def rotation_check(
    renderer: DRRRenderer,
    view: XRayImage,
    space: SearchSpace,
    x: Array,
    tz_mm: float,
    options: RegistrationOptions,
    monitor: _Monitor,
    stage: int,
) -> RotationCheck:
    """Polish the five parameters (tz held at ``tz_mm``) from the estimate ``x`` (``space``'s,
    five parameters) with the view's rx or ry turned by +- ``options.rotation_check_deg``, at
    the polish's level, and compare with the estimate's measure there (one support mask, the
    estimate's). Deterministic; the DRRs are counted in ``monitor``."""
    six = replace(space, names=SIX_PARAMETERS)
    held = _HeldTz(six, tz_mm)
    x = np.asarray(x, dtype=np.float64)
    m_est = held.motion(x)
    problem = LevelProblem.prepare(renderer, (view,), image_px=options.polish_image_px,
                                   volume_level=options.polish_volume_level, motion=m_est,
                                   margin_mm=options.margin_mm(len(options.levels)))  # fmt: skip
    f_est = _cost(problem, held, monitor, None)(x)
    check_options = replace(options, polish_reach=options.rotation_check_reach,
                            polish_evaluations=options.rotation_check_evaluations)  # fmt: skip
    d = options.rotation_check_deg
    ends: list[AnnealResult] = []
    for slot in (2, 3):  # rx, ry of the five parameters
        for sign in (1.0, -1.0):
            if monitor.stopped:
                break
            start = x.copy()
            start[slot] += sign * d
            start = np.clip(start, held.bounds[:, 0], held.bounds[:, 1])
            ends.append(_polish(problem, held, stage, start, check_options, monitor))
    best = min(ends, key=lambda r: r.fun) if ends else None
    if best is not None and best.fun < f_est:
        chosen_x, chosen_f = np.asarray(best.x, dtype=np.float64), float(best.fun)
    else:
        chosen_x, chosen_f = x, f_est
    m_chosen = held.motion(chosen_x)
    moved = rotation_angle_deg(m_chosen @ invert_rigid(m_est))
    scale = max(abs(chosen_f), 1e-12)
    # the other optima the polishes (and the estimate itself) reached, against the chosen one
    others = [(held.motion(r.x), r.fun) for r in ends] + [(m_est, f_est)]
    gains = [(chosen_f - fun) / scale for m, fun in others
             if rotation_angle_deg(m @ invert_rigid(m_chosen)) > RIVAL_DISTINCT_DEG]  # fmt: skip
    return RotationCheck(max(gains) if gains else None, moved, chosen_x, chosen_f, f_est)


def _check_rotations(
    inputs: Inputs, space: SearchSpace, x: Array, f: float, depth: DepthCorrection,
    options: RegistrationOptions, monitor: _Monitor, stage: int,
) -> tuple[Array, float, DepthCorrection, RotationCheck]:  # fmt: skip
    """The rounds of the rotation check (:attr:`RegistrationOptions.rotation_check`): move to a
    better polish when one is found (and correct the depth again from it when it is a rival,
    more than ``RIVAL_DISTINCT_DEG`` away), check again, ``rotation_check_rounds`` at most."""
    renderer, view = inputs.renderer, inputs.views[0]
    moves, check = 0, None
    for n in range(options.rotation_check_rounds):
        check = rotation_check(renderer, view, space, x, depth.tz_mm, options, monitor, stage)
        if not check.fun < check.f_estimate or monitor.stopped:
            break
        x, f, moves = check.x, check.fun, moves + 1
        if check.moved_deg <= RIVAL_DISTINCT_DEG:
            break  # the estimate's own peak, polished further: nothing else to correct
        again = depth_correct(renderer, view, space, x, f, options, monitor, stage, tz_mm=depth.tz_mm)
        depth = DepthCorrection(again.x, again.fun, again.tz_mm, depth.moves_mm + again.moves_mm)
        x, f = depth.x, depth.fun
        if n == options.rotation_check_rounds - 1:
            # the last check moved the estimate to a rival, which no check has seen since: its
            # gain over the estimate it left is the evidence (> 0)
            check = replace(check, rival_gain=(check.f_estimate - check.fun) / max(abs(check.fun), 1e-12))
    assert check is not None
    return x, f, depth, replace(check, checks=n + 1, moves=moves)
