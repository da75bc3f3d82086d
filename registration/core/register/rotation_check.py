"""The rotation check of a single-plane estimate: polishes from its out-of-plane rotations turned."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from registration.core.anneal import AnnealResult
from registration.core.drr import DRRRenderer
from registration.core.geometry import invert_rigid, rotation_angle_deg
from registration.core.images import XRayImage
from registration.core.problem import LevelProblem
from registration.core.register.depth import DepthCorrect, depth_correct, depth_stage
from registration.core.register.monitor import Monitor, cost_function
from registration.core.register.options import RegistrationOptions, RotationCheckOptions
from registration.core.register.plan import State
from registration.core.register.result import RotationCheck
from registration.core.register.screen import SCREEN_TURN_DEG, rotation_margin, turned_starts
from registration.core.register.stages import PolishBudget, run_polish
from registration.core.search import SearchSpace

Array = NDArray[np.float64]

#: A rotation check's polish that ends more than this far from the estimate (deg) found a
#: rival optimum, not the estimate's own peak.
RIVAL_DISTINCT_DEG = 2.0


@dataclass(frozen=True)
class CheckRotations:
    """One view, after the depth correction (:class:`RotationCheckOptions`): four polishes
    (five parameters, tz held) from the estimate with rx or ry turned by +- ``turn_deg``; the
    estimate moves to a better one (and the depth is corrected again when it is a rival, more
    than :data:`RIVAL_DISTINCT_DEG` away) and is checked again, ``rounds`` checks at most."""

    check: RotationCheckOptions
    budget: PolishBudget
    polish_image_px: int
    polish_volume_level: int
    margin_mm: float | None
    depth: DepthCorrect

    def describe(self) -> str:
        c = self.check
        screen = ""
        if c.skip_margin is not None:
            turn = f"+-{SCREEN_TURN_DEG:g} deg"
            screen = f"unless the estimate's margin over rx, ry turned {turn} reaches {c.skip_margin:g}, "
        return (f"rotation check: {screen}4 polishes from rx, ry turned +-{c.turn_deg:g} deg at "
                f"{self.polish_image_px} px ({self.budget.describe()} each), up to {c.rounds} checks")  # fmt: skip

    def runs(self, state: State) -> bool:
        return True

    def run(self, state: State) -> State:
        r = state.run
        renderer, view = r.inputs.renderer, r.inputs.views[0]
        moves, check, margin = 0, None, None
        for n in range(self.check.rounds):
            known = state.screened if n == 0 and state.screened is not None else None
            if known is not None and not np.array_equal(known[0], state.x):
                known = None  # the depth correction screened another estimate
            check = check_estimate(renderer, view, state.space, state.x, self, r.monitor, state.number,
                                   screen=n == 0, screened=known)  # fmt: skip
            if check.skipped:
                return replace(state, check=replace(check, checks=0))
            if n == 0:
                margin = check.margin
            if not check.fun < check.f_estimate or r.monitor.stopped:
                break
            state, moves = replace(state, x=check.x, f=check.fun), moves + 1
            if check.moved_deg <= RIVAL_DISTINCT_DEG:
                break  # the estimate's own peak, polished further: nothing else to correct
            state = depth_correct(state, self.depth)
            if n == self.check.rounds - 1:
                # the last check moved the estimate to a rival, which no check has seen since: its
                # gain over the estimate it left is the evidence (> 0)
                check = replace(check, rival_gain=(check.f_estimate - check.fun) / max(abs(check.fun), 1e-12))
        assert check is not None
        return replace(state, check=replace(check, checks=n + 1, moves=moves, margin=margin))


def check_estimate(
    renderer: DRRRenderer, view: XRayImage, space: SearchSpace, x: Array, stage: CheckRotations, monitor: Monitor,
    number: int, *, screen: bool = False, screened: tuple[Array, float, float] | None = None,
) -> RotationCheck:  # fmt: skip
    """Polish the five parameters of ``space`` (tz held) from the estimate ``x`` with the view's
    rx or ry turned by +- ``turn_deg``, at the polish's level, and compare with the estimate's
    measure there (one support mask, the estimate's). ``screen``: first measure the estimate's
    out-of-plane rotation margin (:func:`rotation_margin`) and, when it reaches the options'
    ``skip_margin``, polish nothing (``skipped``); ``screened``: the estimate's cost and margin
    measured already (by the depth correction, at the same level). Deterministic; DRRs counted in
    ``monitor``."""
    x = np.asarray(x, dtype=np.float64)
    m_est = space.motion(x)
    if screen and screened is not None:
        problem, f_est, margin = None, screened[1], screened[2]
    else:
        problem = _polish_problem(renderer, view, stage, m_est)
        cost = cost_function(problem, space, monitor, None)
        f_est = cost(x)
        margin = rotation_margin(cost, space, x, f_est) if screen else None
    if margin is not None and not math.isfinite(margin):
        margin = None  # the run was stopped: nothing was measured
    skip = stage.check.skip_margin
    if margin is not None and skip is not None and margin >= skip:
        return RotationCheck(None, 0.0, x, f_est, f_est, margin=margin, skipped=True)
    if problem is None:
        problem = _polish_problem(renderer, view, stage, m_est)
    ends: list[AnnealResult] = []
    for start in turned_starts(x, space, stage.check.turn_deg):
        if monitor.stopped:
            break
        ends.append(run_polish(problem, space, number, start, stage.budget, monitor))
    best = min(ends, key=lambda r: r.fun) if ends else None
    if best is not None and best.fun < f_est:
        chosen_x, chosen_f = np.asarray(best.x, dtype=np.float64), float(best.fun)
    else:
        chosen_x, chosen_f = x, f_est
    m_chosen = space.motion(chosen_x)
    moved = rotation_angle_deg(m_chosen @ invert_rigid(m_est))
    scale = max(abs(chosen_f), 1e-12)
    # the other optima the polishes (and the estimate itself) reached, against the chosen one
    others = [(space.motion(r.x), r.fun) for r in ends] + [(m_est, f_est)]
    gains = [(chosen_f - fun) / scale for m, fun in others
             if rotation_angle_deg(m @ invert_rigid(m_chosen)) > RIVAL_DISTINCT_DEG]  # fmt: skip
    return RotationCheck(max(gains) if gains else None, moved, chosen_x, chosen_f, f_est, margin=margin)


def _polish_problem(renderer: DRRRenderer, view: XRayImage, stage: CheckRotations, motion: Array) -> LevelProblem:
    """The view at the polish's level, prepared at ``motion`` (its support mask)."""
    return LevelProblem.prepare(renderer, (view,), image_px=stage.polish_image_px,
                                volume_level=stage.polish_volume_level, motion=motion,
                                margin_mm=stage.margin_mm)  # fmt: skip


def rotation_check(
    renderer: DRRRenderer,
    view: XRayImage,
    space: SearchSpace,
    x: Array,
    tz_mm: float,
    options: RegistrationOptions,
    monitor: Monitor,
    number: int,
) -> RotationCheck:
    """One check (:func:`check_estimate`) of the five-parameter estimate ``x`` of ``space`` with
    tz held at ``tz_mm``, with the options' rotation check and polish level."""
    stage = rotation_check_stage(options, len(options.levels))
    return check_estimate(renderer, view, space.holding_tz(tz_mm), x, stage, monitor, number)


def rotation_check_stage(options: RegistrationOptions, margin_index: int) -> CheckRotations:
    """The rotation check stage of ``options`` (its polishes at the polish's level)."""
    p, c = options.polish, options.rotation_check
    budget = PolishBudget(c.evaluations, c.reach_mm, c.reach_deg, p.xtol, p.step_mm, p.step_deg)
    return CheckRotations(c, budget, p.image_px, p.volume_level, options.margin_mm(margin_index),
                          depth_stage(options, margin_index))  # fmt: skip
