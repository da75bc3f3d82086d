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
stay near the machine-based pose are untouched and cost nothing more. Before the polish the
estimate is scanned along each view's beam (:class:`BeamScan`), after it searched along each beam
once more (:class:`BeamLine`). Decision record: ``docs/decisions/2026-12-04-fine-polish.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from registration.core.drr import DRRRenderer
from registration.core.geometry import apply, rigid
from registration.core.metrics import residuals
from registration.core.prepare import Reach, prepare_volume
from registration.core.register.inputs import Inputs
from registration.core.register.monitor import Monitor, cost_function
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


#: The beam scan's step along each central ray (mm), and how many times the scan and the polish
#: run (the second time only when the first scan moved the estimate).
BEAM_SCAN_STEP_MM = 1.5
BEAM_SCAN_ROUNDS = 2


class _Walk:
    """The cost ``t`` mm along one ray from ``base`` (called with ``t``), keeping the best pose
    seen and whether the monitor stopped the registration (then it evaluates no more)."""

    def __init__(self, state: State, cost: Callable[[np.ndarray], float], base: np.ndarray,
                 direction: np.ndarray, x: np.ndarray, f: float) -> None:  # fmt: skip
        self.state, self.cost, self.base, self.direction = state, cost, base, direction
        self.best_x, self.best_f, self.stopped = x, f, False

    def __call__(self, t: float) -> float:
        if self.stopped:
            return self.best_f
        space = self.state.space
        xt = space.from_motion(rigid(None, t * self.direction) @ self.base)
        ft = float(self.cost(xt))
        if ft < self.best_f:
            self.best_x, self.best_f = xt, ft
        monitor = self.state.run.monitor
        self.stopped = bool(monitor.report(self.state.number, 0.0, xt, ft, self.best_x, self.best_f, 0, space))
        return ft


@dataclass(frozen=True)
class AlongEachBeam:
    """Two or more views: the estimate moved along each view's central ray in turn, within
    ``reach_mm``, to where the views' measure at this level is best (how: :meth:`along`)."""

    image_px: int
    volume_level: int
    margin_mm: float | None
    reach_mm: float

    def runs(self, state: State) -> bool:
        return len(state.run.inputs.views) > 1

    def run(self, state: State) -> State:
        r, space = state.run, state.space
        problem = r.problem(self.image_px, self.volume_level, self.margin_mm, state.motion)
        cost = cost_function(problem, space, r.monitor, None)
        x = np.asarray(state.x, dtype=np.float64)
        f = float(cost(x))
        for view in r.inputs.views:
            walk = _Walk(state, cost, space.motion(x), np.asarray(view.geometry.direction, dtype=np.float64), x, f)
            self.along(walk)
            x, f = walk.best_x, walk.best_f
            if walk.stopped:
                break
        return replace(state, x=x, f=f)

    def along(self, at: Callable[[float], float]) -> None:
        raise NotImplementedError


@dataclass(frozen=True)
class BeamScan(AlongEachBeam):
    """The ray scanned in ``BEAM_SCAN_STEP_MM`` steps either side. One view barely sees a move
    along its own beam; far from the machine-based pose another view may see too little of the
    head to hold it, and the search leaves the depth along that beam several millimetres off,
    where the full images still tell it."""

    def describe(self) -> str:
        return (f"beam scan at {self.image_px} px, volume level {self.volume_level}: each view's central ray "
                f"+-{self.reach_mm:g} mm in {BEAM_SCAN_STEP_MM:g} mm steps")  # fmt: skip

    def along(self, at: Callable[[float], float]) -> None:
        steps = np.arange(1, int(self.reach_mm / BEAM_SCAN_STEP_MM) + 1) * BEAM_SCAN_STEP_MM
        for t in np.concatenate([steps, -steps]):
            at(float(t))


#: The final line search's tolerance along each beam (mm) and its evaluations at most per view.
BEAM_LINE_XTOL_MM = 0.1
BEAM_LINE_EVALUATIONS = 16


@dataclass(frozen=True)
class BeamLine(AlongEachBeam):
    """After the fine polish, a bounded 1-D search (Brent) along each ray. The polish's trust
    region can shrink before it has climbed a flat direction, and the flattest is along a beam
    that the other view sees little of."""

    def describe(self) -> str:
        return (f"line search at {self.image_px} px, volume level {self.volume_level}: each view's central ray "
                f"+-{self.reach_mm:g} mm to {BEAM_LINE_XTOL_MM:g} mm")  # fmt: skip

    def along(self, at: Callable[[float], float]) -> None:
        from scipy.optimize import minimize_scalar

        minimize_scalar(at, bounds=(-self.reach_mm, self.reach_mm), method="bounded",
                        options={"xatol": BEAM_LINE_XTOL_MM, "maxiter": BEAM_LINE_EVALUATIONS})  # fmt: skip


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
    wall: Callable[[np.ndarray], float] | None = None,
) -> RegistrationResult:
    """``result`` polished on the views' full images and the volume's level 0 when it holds two or
    more views' six parameters, started away from the machine-based pose (or from landmarks:
    ``StartOptions.from_landmarks``) or ended ``StartOptions.fine_polish_beyond_mm`` or more from
    it, and was not stopped;
    otherwise ``result`` itself (``wall``: the search space's, see
    :class:`~registration.core.search.SearchSpace`). The result keeps every cost, the polish's
    stage last."""
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
    scan_mm = options.start.beam_scan_mm

    def prepared_at(motion: np.ndarray) -> DRRRenderer:
        """Level 0 prepared for the scan and the polish from ``motion``."""
        reach_mm = options.start.fine_polish_reach_mm + (scan_mm or 0.0) + (options.start.beam_line_mm or 0.0)
        reach = Reach.of_search(reach_mm, options.start.fine_polish_reach_deg, initial_motion=motion, isocenter_mm=iso)
        levels = tuple(sorted({0, options.start.beam_scan_level}))
        return prepare_volume(inputs.volume, [v.geometry for v in inputs.views], reach=reach, levels=levels).renderer

    space = SearchSpace.for_views(inputs.views[0].geometry, estimate, optimize_tz=True, bound_mm=options.bound_mm,
                                  bound_deg=options.bound_deg, wall=wall)  # fmt: skip
    monitor = Monitor(space, callback, start_s)
    run = Run(replace(inputs, initial_motion=estimate, renderer=prepared_at(estimate)), options, space,
              np.random.default_rng(0), monitor)  # fmt: skip
    polish = fine_polish_stage(options)
    state = State(run, space.start(), space)
    if scan_mm is None:
        state = Plan((polish,)).run(state)
    else:  # scan and polish; once more when the scan moved the estimate
        level = options.start.beam_scan_level
        scan = BeamScan(max(16, polish.image_px >> level), level, polish.margin_mm, scan_mm)
        for round_ in range(BEAM_SCAN_ROUNDS):
            if round_:  # the second round reaches from where the first ended: prepared around it
                r = state.run
                state = replace(state, run=replace(r, inputs=replace(r.inputs, renderer=prepared_at(state.motion))))
            before = apply(state.motion, iso)
            state = Plan((scan,)).run(state)
            moved = np.linalg.norm(apply(state.motion, iso) - before) >= BEAM_SCAN_STEP_MM - 1e-6
            state = Plan((polish,)).run(state)
            if not moved:
                break
    if options.start.beam_line_mm is not None and not monitor.stopped:
        line = BeamLine(polish.image_px, polish.volume_level, polish.margin_mm, options.start.beam_line_mm)
        state = Plan((line,)).run(state)
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
