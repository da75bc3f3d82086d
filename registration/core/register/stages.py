"""The annealing levels and the local polish."""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.anneal import AnnealResult, AnnealState, PolishState, anneal, polish
from registration.core.problem import LevelProblem
from registration.core.register.inputs import Inputs
from registration.core.register.monitor import _cost, _Monitor
from registration.core.register.options import Level, RegistrationOptions
from registration.core.search import FIVE_PARAMETERS, SearchSpace

Array = NDArray[np.float64]


# --------------------------------------------------------------------------------------
# The stages
# --------------------------------------------------------------------------------------
def _anneal_level(
    problem: LevelProblem,
    space: SearchSpace,
    level: Level,
    stage: int,
    x_start: Array | list[Array],
    rng: np.random.Generator,
    monitor: _Monitor,
    threads: int | None,
) -> AnnealResult:
    """The level's capture runs from ``x_start`` (or run ``c`` from ``x_start[c % len]``); the
    best of them."""
    starts = x_start if isinstance(x_start, list) else [x_start]
    bounds = space.bounds
    schedule = replace(level.schedule, step=tuple(space.per_parameter(level.schedule.step)))

    def run(chain: int, chain_rng: np.random.Generator, parallel: bool | None) -> AnnealResult:
        def on_iteration(s: AnnealState) -> bool:
            return monitor.report(stage, s.temperature, s.x, s.fun, s.best_x, s.best_fun, chain)

        cost = _cost(problem, space, monitor, parallel)
        x0 = starts[chain % len(starts)]
        return anneal(cost, x0, bounds, rng=chain_rng, schedule=schedule, callback=on_iteration)

    if level.restarts == 1:
        return run(0, rng, None)
    # Independent runs, each with its own random stream (same seed, same result whatever
    # the threads), side by side on the cores with single-threaded DRRs.
    workers = max(1, min(level.restarts, threads or os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        results = list(pool.map(lambda c: run(c[0], c[1], False), enumerate(rng.spawn(level.restarts))))
    if not monitor.captures:
        monitor.captures = [space.motion(r.x) for r in results]
    return min(results, key=lambda r: r.fun)


def _polish(problem: LevelProblem, space: SearchSpace | _HeldTz, stage: int, x_start: Array,
            options: RegistrationOptions, monitor: _Monitor, *, pair: bool = False,
            coarse: bool = False) -> AnnealResult:  # fmt: skip
    """Powell from the annealed estimate, within the evaluation budget, over the estimate +-
    ``polish_reach`` (within the search range); ``pair``: the pair's polish after the plane
    captures (its budget, reach and tolerance), and with ``coarse`` the pair's coarse polish
    before it."""

    def on_evaluation(s: PolishState) -> bool:
        return monitor.report(stage, 0.0, s.x, s.fun, s.best_x, s.best_fun, 0, space)  # type: ignore[arg-type]

    step = np.where(space.is_translation(), options.polish_step_mm, options.polish_step_deg)
    bounds, evaluations = space.bounds, options.polish_evaluations
    xtol, reach = options.polish_xtol, options.polish_reach
    if pair:
        reach = options.pair_coarse_polish_reach if coarse else options.pair_polish_reach
        if coarse:
            evaluations = options.pair_coarse_polish_evaluations
        elif options.pair_polish_evaluations is not None:
            evaluations = options.pair_polish_evaluations
        xtol = options.pair_polish_xtol
    if reach is not None:
        half = np.where(space.is_translation(), *reach)
        x0 = np.clip(x_start, bounds[:, 0], bounds[:, 1])
        bounds = np.stack([np.maximum(bounds[:, 0], x0 - half), np.minimum(bounds[:, 1], x0 + half)], axis=1)
    cost = _cost(problem, space, monitor, None)
    return polish(cost, x_start, bounds, step=step, max_evaluations=evaluations, callback=on_evaluation, xtol=xtol)


def _plane_a_capture(
    inputs: Inputs, space: SearchSpace, options: RegistrationOptions, rng: np.random.Generator, monitor: _Monitor
) -> tuple[Array, float]:
    """The single-plane capture on plane A alone (five parameters, the first level as for one
    view), as the start of a multi-view search; its estimate with tz = 0 in ``space``."""
    five = replace(space, names=FIVE_PARAMETERS)
    level = options.levels[0]
    problem = LevelProblem.prepare(inputs.renderer, inputs.views[:1], image_px=level.image_px,
                                   volume_level=level.volume_level, motion=five.motion(five.start()),
                                   margin_mm=options.margin_mm(0))  # fmt: skip
    monitor.space = five
    try:
        best = _anneal_level(problem, five, level, 0, five.start(), rng, monitor, options.threads)
    finally:
        monitor.space = space
    return space.from_offsets(five.offsets(best.x)), math.inf


class _HeldTz:
    """The five-parameter view of a six-parameter space with tz held: what :func:`_polish` and
    :func:`_cost` need (``motion``, ``bounds``, ``is_translation``)."""

    def __init__(self, six: SearchSpace, tz: float) -> None:
        self.six, self.tz = six, float(tz)
        five = replace(six, names=FIVE_PARAMETERS)
        self.bounds = five.bounds
        self.is_translation = five.is_translation
        self.names = FIVE_PARAMETERS

    def motion(self, x: ArrayLike) -> Array:
        return self.six.motion(np.insert(np.asarray(x, dtype=np.float64), 2, self.tz))
