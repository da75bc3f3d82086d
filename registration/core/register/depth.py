"""The depth correction of a single-plane estimate."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from registration.core.drr import DRRRenderer
from registration.core.problem import iso_pixel_mm, level_factor, renderer_level
from registration.core.register.monitor import cost_function
from registration.core.register.options import DepthOptions, RegistrationOptions
from registration.core.register.plan import State
from registration.core.register.screen import rotation_margin
from registration.core.register.stages import PolishBudget, run_polish
from registration.core.search import SearchSpace

Array = NDArray[np.float64]


def depth_resolvable(renderer: DRRRenderer, depth: DepthOptions) -> bool:
    """Whether the depth correction's scan level (:func:`registration.core.depth.scan_level`)
    is fine enough to see a magnification (``depth.max_voxel_mm``)."""
    from registration.core.depth import scan_level

    level = scan_level(renderer, depth.voxel_mm)
    return float(renderer.level_volume(level).spacing_mm.max()) <= depth.max_voxel_mm


@dataclass(frozen=True)
class _AlongTheBeam:
    """What a stage that scans along the beam needs: the options and the polish's level."""

    depth: DepthOptions
    polish_image_px: int
    polish_volume_level: int
    margin_mm: float | None

    def stride_words(self) -> str:
        d = self.depth
        return f", every {d.scan_stride} then climbing to the peak" if d.scan_stride > 1 else ""


@dataclass(frozen=True)
class DepthCorrect(_AlongTheBeam):
    """One view: the depth correction of the polished five-parameter estimate
    (:class:`DepthOptions`): scan along the beam (:func:`registration.core.depth.depth_scan`,
    high-passed, the rest held), move tz to the peak (within +- ``bound_mm`` of the initial pose),
    polish the five parameters again at that tz (``budget``, at the polish's level), repeat while a
    scan moves tz by ``move_mm`` or more, ``rounds`` scans at most. The state's space then holds tz."""

    budget: PolishBudget

    def describe(self) -> str:
        d, stride = self.depth, self.stride_words()
        first = ""
        if d.first_polish and d.first_polish_skip_margin is not None:
            first = f" (the first only if tz moved or the rx, ry margin is below {d.first_polish_skip_margin:g})"
        widths = f"+-{d.rescan_mm:g} mm" if d.scan_first else f"+-{d.bound_mm:g} mm, then +-{d.rescan_mm:g} mm"
        small = (f"; a move below {d.move_mm:g} mm moves tz without a polish" if d.keep_small_moves
                 else "")  # fmt: skip
        within = f"+-{d.bound_mm:g} mm"
        if d.walk_mm > d.bound_mm:
            within = f"+-{d.walk_mm:g} mm, trusted within +-{d.bound_mm:g}"
        return (f"depth correction: up to {d.rounds} scans along the beam ({widths}, {d.scan_step_mm:g} mm "
                f"steps{stride}, tz within {within}), each followed by a polish{first} at "
                f"{self.polish_image_px} px: {self.budget.describe()}{small}")  # fmt: skip

    def runs(self, state: State) -> bool:
        return True

    def run(self, state: State) -> State:
        return depth_correct(state, self)


def depth_correct(state: State, stage: DepthCorrect) -> State:
    """:class:`DepthCorrect` from ``state`` (five parameters; tz held at its space's
    ``held_tz_mm``, the initial pose's at first). The scans' DRRs are counted in the run's
    monitor. Deterministic."""
    r, d = state.run, stage.depth
    view = r.inputs.views[0]
    bound = d.bound_mm
    space, tz, moves = state.space, state.space.held_tz_mm, []
    x, f = np.asarray(state.x, dtype=np.float64), state.f
    screened = None
    # after the scan before the polish (DepthPrescan), every scan here is a rescan
    prescanned = d.scan_first
    for n in range(d.rounds):
        if r.monitor.stopped:
            break
        move = _scan_move(state, stage, space, x, tz, bound if n == 0 and not prescanned else d.rescan_mm)
        if move is None:
            break
        moves.append(move)
        small = abs(move) < d.move_mm
        kept = small and d.keep_small_moves and move != 0.0
        if kept:
            # a small move is kept without a polish of its own (the first one's screen as below)
            tz, move = tz + move, 0.0
        if small and not (n == 0 and d.first_polish):
            if kept:
                f = _cost(state, stage, space.holding_tz(tz), x)
            break
        if small and d.first_polish_skip_margin is not None:
            # the first polish only where the estimate's rx / ry is in doubt
            measured = _screen(state, stage, space.holding_tz(tz), x)
            if measured[2] >= d.first_polish_skip_margin:
                screened = measured
                f = measured[1] if kept else f
                break
        tz += move
        held = space.holding_tz(tz)
        problem = r.problem(stage.polish_image_px, stage.polish_volume_level, stage.margin_mm, held.motion(x),
                            views=(view,))  # fmt: skip
        best = run_polish(problem, held, state.number, x, stage.budget, r.monitor)
        x, f = best.x, best.fun
    moved = (state.depth_moves_mm or ()) + tuple(moves)
    return replace(state, x=x, f=f, space=space.holding_tz(tz), depth_moves_mm=moved, screened=screened)


def _scan_move(
    state: State, stage: _AlongTheBeam, space: SearchSpace, x: Array, tz: float, half: float
) -> float | None:
    """One scan along the beam +- ``half`` mm from ``x`` at ``tz`` (within the depth bound): the
    move of tz to its peak (None: fewer than three offsets fit). Its DRRs are charged."""
    from registration.core.depth import depth_scan, scan_level

    r, d = state.run, stage.depth
    renderer, view = r.inputs.renderer, r.inputs.views[0]
    level = scan_level(renderer, d.voxel_mm)
    # the scan compares at the polish's pixel (at the iso-center), not finer
    polish_level = renderer_level(renderer, stage.polish_volume_level)
    polish_voxel_mm = float(renderer.level_volume(polish_level).spacing_mm.max())
    pixel_mm = iso_pixel_mm(view.geometry, level_factor(view.geometry, stage.polish_image_px, polish_voxel_mm))
    step, bound = d.scan_step_mm, d.walk_mm
    # the offsets that stay within the reach, from the estimate's tz
    lo, hi = max(-half, -bound - tz), min(half, bound - tz)
    offsets = tuple(float(o) for o in np.arange(math.ceil(lo / step) * step, hi + 1e-9, step))
    if len(offsets) < 3:
        return None
    scan = depth_scan(renderer, view, space.holding_tz(tz).motion(x), offsets_mm=offsets, image_px=d.image_px,
                      volume_level=level, margin_mm=stage.margin_mm, pixel_at_iso_mm=pixel_mm,
                      stride=d.scan_stride)  # fmt: skip
    r.monitor.charge(scan.drr_count, scan.drr_count * d.image_px * d.image_px)  # the scan's square images
    return float(np.clip(tz + scan.tz_mm, -bound, bound)) - tz


@dataclass(frozen=True)
class DepthPrescan(_AlongTheBeam):
    """One view, before the polish: a scan along the beam from the annealed estimate (+-
    ``bound_mm`` of the initial pose), tz moved to its peak and held, so that the polish runs at
    the corrected depth; the depth correction after the polish then only rescans. ``after``: the
    stage it follows when not the annealing (``DepthOptions.scan_after_capture``: the capture
    level, so that the finer levels fit at the corrected depth)."""

    after: str | None = None

    def describe(self) -> str:
        d, stride = self.depth, self.stride_words()
        small = "" if d.keep_small_moves else f" when it lies {d.move_mm:g} mm or more away"
        where = "before the polish" if self.after is None else f"after {self.after}"
        return (f"scan along the beam {where} (+-{d.bound_mm:g} mm, {d.scan_step_mm:g} mm steps{stride}): "
                f"tz to its peak{small}")  # fmt: skip

    def runs(self, state: State) -> bool:
        return True

    def run(self, state: State) -> State:
        d, tz = self.depth, state.space.held_tz_mm
        move = _scan_move(state, self, state.space, np.asarray(state.x, dtype=np.float64), tz, d.bound_mm)
        moves = () if move is None else (move,)
        # a move below move_mm leaves tz where it was, as the depth correction's scans do
        kept = move if move is not None and (abs(move) >= d.move_mm or d.keep_small_moves) else 0.0
        moved = (state.depth_moves_mm or ()) + moves
        return replace(state, space=state.space.holding_tz(tz + kept), depth_moves_mm=moved)


def _polish_cost(state: State, stage: _AlongTheBeam, space: SearchSpace, x: Array) -> Callable[[Array], float]:
    """The cost at the polish's level of images and volume, prepared at ``x``."""
    r = state.run
    problem = r.problem(stage.polish_image_px, stage.polish_volume_level, stage.margin_mm, space.motion(x),
                        views=r.inputs.views[:1])  # fmt: skip
    return cost_function(problem, space, r.monitor, None)


def _cost(state: State, stage: DepthCorrect, space: SearchSpace, x: Array) -> float:
    """The cost of ``x`` at the polish's level."""
    return float(_polish_cost(state, stage, space, x)(x))


def _screen(state: State, stage: DepthCorrect, space: SearchSpace, x: Array) -> tuple[Array, float, float]:
    """The estimate ``x``, its cost and its out-of-plane rotation margin
    (:func:`registration.core.register.screen.rotation_margin`) at the polish's level."""
    cost = _polish_cost(state, stage, space, x)
    f_est = cost(x)
    return np.array(x, dtype=np.float64), float(f_est), rotation_margin(cost, space, x, f_est)


def depth_stage(options: RegistrationOptions, margin_index: int) -> DepthCorrect:
    """The depth correction stage of ``options`` (its polishes at the polish's level)."""
    p, d = options.polish, options.depth
    budget = PolishBudget(d.polish_evaluations, d.polish_reach_mm, d.polish_reach_deg, p.xtol, p.step_mm, p.step_deg)
    return DepthCorrect(d, p.image_px, p.volume_level, options.margin_mm(margin_index), budget)


def depth_prescan_stage(options: RegistrationOptions, margin_index: int, after: str | None = None) -> DepthPrescan:
    """The scan before the polish of ``options`` (at the polish's level; ``after``: see :class:`DepthPrescan`)."""
    p = options.polish
    return DepthPrescan(options.depth, p.image_px, p.volume_level, options.margin_mm(margin_index), after)
