"""Two views started from the image shift: a second candidate that first moves the patient only.

Far beyond the clinical offsets (40-60 mm, much of the head out of a plane's field) the planes'
captures on 32 px images turn the head 5-20 degrees where the patient only moved, and every
capture run can end in the same wrong basin. The image shift (:mod:`.shift_start`) found the
move across each beam but not its depth and left the rotation where the machine put it. This
stage searches from that start the three translations alone on 64 px images of the
quarter-resolution volume (the rotation held), polishes all six parameters on 128 px images of
the half-resolution volume, and keeps the candidate when the views' measure at 128 px is better
there than at the search's estimate (one comparison on the same images and support). It runs only
after a search from the image shift, so registrations that start at the machine-based pose are
untouched and cost nothing more. Decision record: ``docs/decisions/2026-12-06-translation-first.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from registration.core.anneal import PolishState, polish
from registration.core.metrics import residuals
from registration.core.register.inputs import Inputs
from registration.core.register.monitor import Monitor, cost_function
from registration.core.register.options import RegistrationOptions
from registration.core.register.plan import Plan, Run, State
from registration.core.register.result import Progress, RegistrationResult
from registration.core.register.stages import Polish, PolishBudget
from registration.core.search import SearchSpace

#: The translation search: image size, volume level, reach either side of the start (mm) and
#: first steps (mm); its evaluations are :attr:`StartOptions.translation_first_evaluations`.
TRANSLATION_IMAGE_PX = 64
TRANSLATION_VOLUME_LEVEL = 2
TRANSLATION_REACH_MM = 20.0
TRANSLATION_STEP_MM = 4.0
#: The six-parameter polish after it, and the comparison's level: image size, volume level,
#: evaluations, reach (mm, degrees).
POLISH_IMAGE_PX = 128
POLISH_VOLUME_LEVEL = 1
POLISH_EVALUATIONS = 60
POLISH_REACH = (4.0, 3.0)


@dataclass(frozen=True)
class TranslationSearch:
    """Powell over the three translations from the state's estimate, its rotation held."""

    image_px: int
    volume_level: int
    margin_mm: float | None
    evaluations: int

    def describe(self) -> str:
        return (f"translations alone at {self.image_px} px, volume level {self.volume_level}: "
                f"{self.evaluations} evaluations over +-{TRANSLATION_REACH_MM:g} mm")  # fmt: skip

    def runs(self, state: State) -> bool:
        return True

    def run(self, state: State) -> State:
        r, space, x0 = state.run, state.space, np.asarray(state.x, dtype=np.float64)
        problem = r.problem(self.image_px, self.volume_level, self.margin_mm, state.motion)
        cost6 = cost_function(problem, space, r.monitor, None)
        moves = np.asarray(space.is_translation())

        def full(t: np.ndarray) -> np.ndarray:
            x = x0.copy()
            x[moves] = t
            return x

        def on_evaluation(s: PolishState) -> bool:
            return r.monitor.report(state.number, 0.0, full(s.x), s.fun, full(s.best_x), s.best_fun, 0, space)

        t0 = x0[moves]
        reach = np.stack([t0 - TRANSLATION_REACH_MM, t0 + TRANSLATION_REACH_MM], axis=1)
        found = polish(lambda t: cost6(full(t)), t0, reach, step=[TRANSLATION_STEP_MM] * int(moves.sum()),
                       max_evaluations=self.evaluations, callback=on_evaluation)  # fmt: skip
        return replace(state, x=full(found.x), f=found.fun)


def translation_first(
    inputs: Inputs,
    result: RegistrationResult,
    options: RegistrationOptions,
    *,
    callback: Callable[[Progress], bool | None] | None,
    start_s: float,
    vessel_points_mm: ArrayLike | None = None,
) -> RegistrationResult:
    """``result``, or the translation-first candidate from ``inputs``' start (the image shift:
    :func:`registration.core.register.register` calls it only after a search started there) when
    its measure is better (see the module). Runs for two or more views whose estimate started from
    the image shift and was not stopped; the result keeps every cost."""
    evaluations = options.start.translation_first_evaluations
    if len(inputs.views) < 2 or not evaluations or not result.start_shift_mm or result.stopped:
        return result
    start = np.asarray(inputs.initial_motion, dtype=np.float64)
    geometry = inputs.views[0].geometry
    space = SearchSpace.for_views(geometry, start, optimize_tz=True, bound_mm=options.bound_mm,
                                  bound_deg=options.bound_deg)  # fmt: skip
    monitor = Monitor(space, callback, start_s)
    run = Run(inputs, options, space, np.random.default_rng(0), monitor)
    margin = options.margin_mm(len(options.levels))
    budget = PolishBudget(POLISH_EVALUATIONS, *POLISH_REACH, options.polish.xtol, options.polish.step_mm,
                          options.polish.step_deg)  # fmt: skip
    plan = Plan((TranslationSearch(TRANSLATION_IMAGE_PX, TRANSLATION_VOLUME_LEVEL, margin, evaluations),
                 Polish("candidate's polish", POLISH_IMAGE_PX, POLISH_VOLUME_LEVEL, margin, budget)))  # fmt: skip
    state = plan.run(State(run, space.start(), space))
    if monitor.stopped:
        return result
    candidate = state.motion
    if np.any(np.abs(space.from_motion(candidate)[:3]) >= TRANSLATION_REACH_MM - 0.5):
        return replace(result, drr_count=result.drr_count + monitor.drr_count)  # ended at its reach: no candidate
    # both estimates on the same images and support: the polish's level prepared at the start
    judge = run.problem(POLISH_IMAGE_PX, POLISH_VOLUME_LEVEL, margin, start).evaluator()
    monitor.charge(2 * judge.drrs_per_evaluation, 2 * judge.rays_per_evaluation)  # the two evaluations below
    estimate = np.asarray(result.patient_motion, dtype=np.float64)
    kept_candidate = judge.similarity(candidate) > judge.similarity(estimate)
    costs = dict(drr_count=result.drr_count + monitor.drr_count, seconds=time.perf_counter() - start_s,
                 similarity_trace=list(result.similarity_trace) + list(monitor.trace),
                 stages=result.stages + tuple(monitor.stages))  # fmt: skip
    if not kept_candidate:
        return replace(result, **costs)
    out = replace(result, patient_motion=candidate, similarity=-state.f, at_bounds=(), translation_first=True,
                  offsets=result.offsets_of(candidate), **costs)  # fmt: skip
    if inputs.truth is not None:
        out.residual = residuals(candidate, inputs.truth, result.geometry, vessel_points_mm, optimizes_tz=True)
    return out
