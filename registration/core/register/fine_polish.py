"""A last polish at full resolution for two views' estimate found away from the machine-based pose.

The polish that ends every search compares 128-pixel images with the volume's level 1 (2.8 mm
voxels on a 128^3 3DRA of 1.4 mm). Near the machine-based pose its optimum lies within a few
tenths of a millimetre of the truth; when the patient moved further (the search started from the
image shift or walked) that optimum can drift by a millimetre and more at the iso-center: on the
capture study's 50 mm moments a search started at the true pose ends 1.1-1.35 mm off, and a
polish on the full images and the volume's own grid ends 0.6 mm off. This stage runs that
polish (COBYQA, the local search that needs the fewest of these dear level-0 DRRs), on a level-0
preparation made for it, only after such a search or when the estimate lies beyond the clinical
offsets (25 mm) from the machine-based pose although the search started there: registrations that
stay near the machine-based pose are untouched and cost nothing more. Decision record:
``docs/decisions/2026-12-04-fine-polish.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from registration.core.geometry import apply
from registration.core.metrics import residuals
from registration.core.prepare import Reach, prepare_volume
from registration.core.register.inputs import Inputs
from registration.core.register.monitor import Monitor
from registration.core.register.options import RegistrationOptions
from registration.core.register.plan import Plan, Run, State
from registration.core.register.result import Progress, RegistrationResult
from registration.core.register.stages import Polish, PolishBudget
from registration.core.search import SearchSpace


def started_away(result: RegistrationResult) -> bool:
    """Whether the kept estimate's search started away from the machine-based pose (the image
    shift, a walk of the box, or the second search's estimate kept)."""
    return bool(result.start_shift_mm or result.walk_hops)


def far_from_machine(result: RegistrationResult, machine_motion: np.ndarray, beyond_mm: float | None) -> bool:
    """Whether ``result``'s estimate moves the iso-center at least ``beyond_mm`` from where the
    machine-based pose puts it (None: never)."""
    if beyond_mm is None:
        return False
    iso = np.asarray(result.geometry.isocenter_mm, dtype=np.float64)
    moved = apply(np.asarray(result.patient_motion), iso) - apply(np.asarray(machine_motion), iso)
    return bool(np.linalg.norm(moved) >= beyond_mm)


def fine_polish_stage(options: RegistrationOptions) -> Polish:
    f = options.start
    budget = PolishBudget(f.fine_polish_evaluations, f.fine_polish_reach_mm, f.fine_polish_reach_deg,
                          f.fine_polish_xtol, options.polish.step_mm, options.polish.step_deg, "cobyqa")  # fmt: skip
    return Polish("fine polish", f.fine_polish_px, 0, options.margin_mm(len(options.levels)), budget)


def fine_polish(
    inputs: Inputs,
    result: RegistrationResult,
    options: RegistrationOptions,
    *,
    callback: Callable[[Progress], bool | None] | None,
    start_s: float,
    vessel_points_mm: ArrayLike | None = None,
) -> RegistrationResult:
    """``result`` polished on the views' full images and the volume's level 0 when it holds two or
    more views' six parameters, started away from the machine-based pose (or from landmarks:
    ``StartOptions.from_landmarks``) or ended ``StartOptions.fine_polish_beyond_mm`` or more from
    it, and was not stopped;
    otherwise ``result`` itself. The result keeps every cost, the polish's stage last."""
    if (
        len(inputs.views) < 2
        or "tz" not in result.parameters
        or not options.start.fine_polish_evaluations
        or result.stopped
        or not (
            started_away(result)
            or options.start.from_landmarks
            or far_from_machine(result, inputs.initial_motion, options.start.fine_polish_beyond_mm)
        )
    ):
        return result
    estimate = np.asarray(result.patient_motion, dtype=np.float64)
    iso = inputs.views[0].geometry.isocenter_mm
    reach = Reach.of_search(options.start.fine_polish_reach_mm, options.start.fine_polish_reach_deg,
                            initial_motion=estimate, isocenter_mm=iso)  # fmt: skip
    prepared = prepare_volume(inputs.volume, [v.geometry for v in inputs.views], reach=reach, levels=(0,))
    space = SearchSpace.for_views(inputs.views[0].geometry, estimate, optimize_tz=True,
                                  bound_mm=options.bound_mm, bound_deg=options.bound_deg)  # fmt: skip
    monitor = Monitor(space, callback, start_s)
    run = Run(replace(inputs, initial_motion=estimate, renderer=prepared.renderer), options, space,
              np.random.default_rng(0), monitor)  # fmt: skip
    state = Plan((fine_polish_stage(options),)).run(State(run, space.start(), space))
    if monitor.stopped or not monitor.stages:
        return result
    polished = state.motion
    offsets = result.offsets_of(polished)
    out = replace(
        result,
        patient_motion=polished,
        similarity=-state.f,
        similarity_trace=list(result.similarity_trace) + list(monitor.trace),
        drr_count=result.drr_count + monitor.drr_count,
        seconds=time.perf_counter() - start_s,
        offsets=offsets,
        stages=result.stages + tuple(monitor.stages),
        fine_polished=True,
    )
    if inputs.truth is not None:
        out.residual = residuals(polished, inputs.truth, result.geometry, vessel_points_mm, optimizes_tz=True)
    return out
