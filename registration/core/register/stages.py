"""The annealing levels and the local polishes: the stages every registration's plan holds."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from registration.core.anneal import AnnealResult, AnnealState, PolishState, anneal, polish
from registration.core.problem import LevelProblem
from registration.core.register.monitor import Monitor, cost_function
from registration.core.register.options import Level
from registration.core.register.plan import Condition, State
from registration.core.search import FIVE_PARAMETERS, SearchSpace

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PolishBudget:
    """One polish's budget: evaluations, reach either side of its start (mm, deg; None: the
    search range), the tolerance and first steps (mm, deg), and the method (``"powell"`` or
    ``"cobyqa"``, :func:`registration.core.anneal.polish`)."""

    evaluations: int
    reach_mm: float | None
    reach_deg: float | None
    xtol: float
    step_mm: float
    step_deg: float
    method: str = "powell"

    def describe(self) -> str:
        reach = "the search range" if self.reach_mm is None else f"+-{self.reach_mm:g} mm / {self.reach_deg:g} deg"
        how = " (COBYQA)" if self.method == "cobyqa" else ""
        return f"{self.evaluations} evaluations over {reach}{how}"


def anneal_level(
    problem: LevelProblem,
    space: SearchSpace,
    level: Level,
    number: int,
    starts: list[Array],
    rng: np.random.Generator,
    monitor: Monitor,
    threads: int | None,
) -> AnnealResult:
    """The level's ``level.restarts`` capture runs, run ``c`` from ``starts[c % len]``; the best."""

    def run(chain: int, chain_rng: np.random.Generator, parallel: bool | None) -> AnnealResult:
        def on_iteration(s: AnnealState) -> bool:
            return monitor.report(number, s.temperature, s.x, s.fun, s.best_x, s.best_fun, chain, space)

        cost = cost_function(problem, space, monitor, parallel)
        return anneal(cost, starts[chain % len(starts)], space.bounds, rng=chain_rng, schedule=schedule,
                      callback=on_iteration)  # fmt: skip

    schedule = replace(level.schedule, step=tuple(space.per_parameter(level.schedule.step)))
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


def run_polish(
    problem: LevelProblem, space: SearchSpace, number: int, x_start: Array, budget: PolishBudget, monitor: Monitor
) -> AnnealResult:
    """Powell from ``x_start`` within ``budget`` (its evaluations, over the start +- its reach
    within the search range)."""

    def on_evaluation(s: PolishState) -> bool:
        return monitor.report(number, 0.0, s.x, s.fun, s.best_x, s.best_fun, 0, space)

    step = np.where(space.is_translation(), budget.step_mm, budget.step_deg)
    bounds = space.bounds
    if budget.reach_mm is not None:
        half = np.where(space.is_translation(), budget.reach_mm, budget.reach_deg)
        x0 = np.clip(x_start, bounds[:, 0], bounds[:, 1])
        bounds = np.stack([np.maximum(bounds[:, 0], x0 - half), np.minimum(bounds[:, 1], x0 + half)], axis=1)
    cost = cost_function(problem, space, monitor, None)
    return polish(cost, x_start, bounds, step=step, max_evaluations=budget.evaluations, callback=on_evaluation,
                  xtol=budget.xtol, method=budget.method)  # fmt: skip


@dataclass(frozen=True)
class AnnealLevel:
    """One annealing level: ``level.restarts`` capture runs from the estimate (``restarts``
    None: one run from each of the state's several starts, the planes' when they disagreed)."""

    level: Level
    margin_mm: float | None
    restarts: int | None
    when: Condition | None = None

    def describe(self) -> str:
        lv = self.level
        runs = "one run per start" if self.restarts is None else f"{self.restarts} run{'s' * (self.restarts > 1)}"
        when = f" ({self.when[0]})" if self.when else ""
        return f"anneal at {lv.image_px} px, volume level {lv.volume_level}, {runs}{when}"

    def runs(self, state: State) -> bool:
        return self.when is None or self.when[1](state)

    def run(self, state: State) -> State:
        r = state.run
        problem = r.problem(self.level.image_px, self.level.volume_level, self.margin_mm, state.motion)
        starts = list(state.starts) if self.restarts is None else [state.x]
        level = replace(self.level, restarts=len(starts) if self.restarts is None else self.restarts)
        best = anneal_level(problem, state.space, level, state.number, starts, r.rng, r.monitor, r.options.threads)
        return replace(state, x=best.x, f=best.fun, starts=())


@dataclass(frozen=True)
class Polish:
    """A local polish at one level of images and volume, with its own budget."""

    name: str
    image_px: int
    volume_level: int
    margin_mm: float | None
    budget: PolishBudget

    def describe(self) -> str:
        return f"{self.name} at {self.image_px} px, volume level {self.volume_level}: {self.budget.describe()}"

    def runs(self, state: State) -> bool:
        return True

    def run(self, state: State) -> State:
        r = state.run
        problem = r.problem(self.image_px, self.volume_level, self.margin_mm, state.motion)
        best = run_polish(problem, state.space, state.number, state.x, self.budget, r.monitor)
        return replace(state, x=best.x, f=best.fun)


@dataclass(frozen=True)
class PlaneACapture:
    """Two or more views: the single-plane capture on plane A alone (five parameters, the first
    level), whose estimate (tz = 0) starts the six-parameter search."""

    level: Level
    margin_mm: float | None

    def describe(self) -> str:
        lv = self.level
        return f"plane A's own capture at {lv.image_px} px, volume level {lv.volume_level}, {lv.restarts} runs"

    def runs(self, state: State) -> bool:
        return True

    def run(self, state: State) -> State:
        r = state.run
        five = replace(state.space, names=FIVE_PARAMETERS)
        problem = r.problem(self.level.image_px, self.level.volume_level, self.margin_mm, five.motion(five.start()),
                            views=r.inputs.views[:1])  # fmt: skip
        best = anneal_level(problem, five, self.level, state.number, [five.start()], r.rng, r.monitor,
                            r.options.threads)  # fmt: skip
        return replace(state, x=state.space.from_offsets(five.offsets(best.x)), f=float("inf"))
