"""Simulated annealing with scipy's optimizer contract.

``anneal(cost, x0, bounds, rng=..., schedule=..., callback=...)`` minimises ``cost(x) ->
float`` inside box bounds. Neighbours are Gaussian steps whose size (per parameter, in the
parameter's own unit) shrinks with the temperature; moves are accepted by the Metropolis
rule. The initial temperature is set from the cost changes of a few probe moves so that a
target share of uphill moves is accepted at first, whatever the scale of the cost. The
callback sees every iteration and may stop the run by returning True.

References
----------
Kirkpatrick, Gelatt, Vecchi, "Optimization by simulated annealing", Science 220 (1983).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Schedule:
    """The annealing schedule; every constant named.

    Attributes
    ----------
    step:
        Initial standard deviation of a neighbour step, per parameter (same unit as x).
    initial_acceptance:
        Target probability of accepting a typical uphill move at the start; sets T0.
    probes:
        Number of random moves used to measure typical cost changes for T0.
    cooling:
        Geometric cooling factor applied after each temperature stage.
    moves_per_stage:
        Neighbour evaluations per temperature stage.
    stages:
        Number of temperature stages (the run ends after them).
    step_floor:
        The step never shrinks below ``step * step_floor``.
    """

    step: tuple[float, ...] = (2.0, 2.0, 1.0, 1.0, 1.0)
    initial_acceptance: float = 0.5
    probes: int = 8
    cooling: float = 0.8
    moves_per_stage: int = 12
    stages: int = 15
    step_floor: float = 0.05

    def __post_init__(self) -> None:
        if not 0.0 < self.initial_acceptance < 1.0:
            raise ValueError(f"initial_acceptance must lie in (0, 1), got {self.initial_acceptance}")
        if not 0.0 < self.cooling < 1.0:
            raise ValueError(f"cooling must lie in (0, 1), got {self.cooling}")
        if self.moves_per_stage < 1 or self.stages < 1 or self.probes < 1:
            raise ValueError("moves_per_stage, stages and probes must be >= 1")
        if any(not math.isfinite(s) or s <= 0 for s in self.step):
            raise ValueError(f"step sizes must be positive, got {self.step}")
        if not 0.0 < self.step_floor <= 1.0:
            raise ValueError(f"step_floor must lie in (0, 1], got {self.step_floor}")

    @property
    def max_evaluations(self) -> int:
        """Cost evaluations of a full run: x0, the probes and every move."""
        return 1 + self.probes + self.stages * self.moves_per_stage


@dataclass(frozen=True)
class AnnealState:
    """What the callback sees after each iteration."""

    nit: int
    x: Array
    fun: float
    best_x: Array
    best_fun: float
    temperature: float
    nfev: int


@dataclass
class AnnealResult:
    """Result in scipy's vocabulary."""

    x: Array
    fun: float
    nit: int
    nfev: int
    success: bool
    message: str
    trace: list[float] = field(default_factory=list)


class _Counted:
    """The cost, its evaluations counted and a non-finite value taken as +inf."""

    def __init__(self, cost: Callable[[Array], float]) -> None:
        self.cost, self.nfev = cost, 0

    def evaluate(self, p: Array) -> float:
        self.nfev += 1
        value = float(self.cost(p))
        return value if math.isfinite(value) else math.inf


def _checked(x0: ArrayLike, bounds: ArrayLike, schedule: Schedule) -> tuple[Array, Array, Array]:
    """``x0`` as a float copy, the bounds as an (n, 2) array and the schedule's first steps, checked."""
    x = np.asarray(x0, dtype=np.float64).copy()
    b = np.asarray(bounds, dtype=np.float64)
    n = x.size
    if b.shape != (n, 2):
        raise ValueError(f"bounds must have shape ({n}, 2), got {b.shape}")
    if np.any(~np.isfinite(b)) or np.any(b[:, 0] >= b[:, 1]):
        raise ValueError(f"bounds must be finite with lower < upper, got {b.tolist()}")
    if np.any(x < b[:, 0]) or np.any(x > b[:, 1]):
        raise ValueError(f"x0 {x.tolist()} lies outside the bounds")
    step0 = np.asarray(schedule.step, dtype=np.float64)
    if step0.size != n:
        raise ValueError(f"schedule.step has {step0.size} entries for {n} parameters")
    return x, b, step0


def _initial_temperature(ups: list[float], fx: float, schedule: Schedule) -> float:
    """The temperature at which the typical uphill change of random moves (``ups``) is accepted
    with the schedule's ``initial_acceptance``."""
    typical_up = float(np.median(ups)) if ups else max(abs(fx), 1.0) * 1e-3
    return typical_up / -math.log(schedule.initial_acceptance)


def _accept(delta: float, temperature: float, rng: np.random.Generator) -> bool:
    """Metropolis: downhill always, uphill with probability exp(-delta / temperature)."""
    return delta <= 0 or rng.random() < math.exp(-delta / max(temperature, 1e-300))


def anneal(
    cost: Callable[[Array], float],
    x0: ArrayLike,
    bounds: ArrayLike,
    *,
    rng: np.random.Generator,
    schedule: Schedule | None = None,
    callback: Callable[[AnnealState], bool | None] | None = None,
) -> AnnealResult:
    """Minimise ``cost`` by simulated annealing from ``x0`` inside ``bounds`` ((n, 2) array).

    ``trace`` holds the best cost after each iteration. ``success`` is False only when the
    cost returned a non-finite value at x0; a run stopped by the callback is a success with
    the message saying so.
    """
    schedule = schedule or Schedule()
    x, b, step0 = _checked(x0, bounds, schedule)
    n = x.size
    counted = _Counted(cost)
    evaluate = counted.evaluate

    def neighbour(center: Array, step: Array) -> Array:
        return np.clip(center + rng.normal(0.0, 1.0, n) * step, b[:, 0], b[:, 1])

    fx = evaluate(x)
    if not math.isfinite(fx):
        return AnnealResult(x, fx, 0, counted.nfev, False, "cost is not finite at x0")
    best_x, best_f = x.copy(), fx

    # Initial temperature from the typical uphill change of random moves.
    probes = [(xp, evaluate(xp)) for xp in (neighbour(x, step0) for _ in range(schedule.probes))]
    for xp, fp in probes:
        if fp < best_f:
            best_x, best_f = xp.copy(), fp
    ups = [fp - fx for _, fp in probes if math.isfinite(fp) and fp > fx]
    temperature = t0 = _initial_temperature(ups, fx, schedule)

    trace: list[float] = []
    nit = 0
    message = "schedule completed"
    stopped = False
    for _stage in range(schedule.stages):
        # Steps shrink with the square root of the temperature ratio.
        step = step0 * max(schedule.step_floor, math.sqrt(temperature / t0))
        for _move in range(schedule.moves_per_stage):
            xp = neighbour(x, step)
            fp = evaluate(xp)
            if _accept(fp - fx, temperature, rng):
                x, fx = xp, fp
                if fx < best_f:
                    best_x, best_f = x.copy(), fx
            nit += 1
            trace.append(best_f)
            if callback is not None and callback(
                AnnealState(nit, x.copy(), fx, best_x.copy(), best_f, temperature, counted.nfev)
            ):
                message, stopped = "stopped by the callback", True
                break
        if stopped:
            break
        temperature *= schedule.cooling
        # Restart each stage from the best point seen: keeps the walk near the basin.
        x, fx = best_x.copy(), best_f
    return AnnealResult(best_x, best_f, nit, counted.nfev, True, message, trace)


# --------------------------------------------------------------------------------------
# The local polish
# --------------------------------------------------------------------------------------
#: Powell's tolerance on the parameters (same unit as x: mm or degrees) and on the cost.
POLISH_XTOL = 0.02
POLISH_FTOL = 1e-6


@dataclass(frozen=True)
class PolishState:
    """What the polish's callback sees after each cost evaluation."""

    nfev: int
    x: Array
    fun: float
    best_x: Array
    best_fun: float


def polish(
    cost: Callable[[Array], float],
    x0: ArrayLike,
    bounds: ArrayLike,
    *,
    step: ArrayLike,
    max_evaluations: int,
    callback: Callable[[PolishState], bool | None] | None = None,
    xtol: float = POLISH_XTOL,
    method: str = "powell",
) -> AnnealResult:
    """A short local refinement of ``x0`` by Powell's method (or COBYQA) inside ``bounds``.

    ``step`` is the initial search direction length per parameter (Powell's ``direc`` is its
    diagonal); the run spends at most ``max_evaluations`` cost evaluations after evaluating
    ``x0`` (its evaluation budget). Points are clipped to the bounds before ``cost`` sees
    them. The callback sees every evaluation and may stop the run by returning True: from
    then on ``cost`` is no longer called and Powell sees a flat function, so it ends at once.
    The result is the best point evaluated (``x0`` if nothing improved on it). ``xtol``:
    Powell's tolerance; with bounds each line search ends when it knows its minimum to
    ``xtol`` times the line's step (``step``), in the parameters' unit.

    ``method="cobyqa"``: scipy's COBYQA (quadratic models in a trust region) in the parameters
    divided by ``step``, its trust region from 1 step down to ``xtol`` steps. On the polish
    level it reaches with about 40 evaluations the measure Powell reaches with 80
    (docs/validation/speed.md), at a few milliseconds of its own arithmetic per evaluation.
    """
    b = np.asarray(bounds, dtype=np.float64)
    x_start = np.asarray(x0, dtype=np.float64).copy()
    direc = np.diag(np.asarray(step, dtype=np.float64))
    if b.shape != (x_start.size, 2) or direc.shape != (x_start.size, x_start.size):
        raise ValueError(f"bounds and step must match the {x_start.size} parameters")
    if int(max_evaluations) != max_evaluations or max_evaluations < 1:
        raise ValueError(f"max_evaluations must be a positive integer, got {max_evaluations}")
    if method not in ("powell", "cobyqa"):
        raise ValueError(f"method must be 'powell' or 'cobyqa', got {method!r}")
    run = _BudgetedCost(cost, x_start, b, max_evaluations, callback)
    if method == "cobyqa":
        scale = np.diag(direc)
        if np.any(scale <= 0):
            raise ValueError("step must be positive for COBYQA")
        x_in = np.clip(x_start, b[:, 0], b[:, 1])
        z_bounds = (b - x_in[:, None]) / scale[:, None]
        optimize.minimize(
            lambda z: run(x_in + z * scale),
            np.zeros_like(x_start),
            method="COBYQA",
            bounds=z_bounds,
            options={"maxfev": int(max_evaluations), "initial_tr_radius": 1.0, "final_tr_radius": float(xtol)},
        )
    else:
        optimize.minimize(
            run,
            x_start,
            method="Powell",
            bounds=b,
            options={"maxfev": int(max_evaluations), "xtol": float(xtol), "ftol": POLISH_FTOL, "direc": direc},
        )
    message = "stopped by the callback" if run.stopped else "polish completed"
    return AnnealResult(run.best_x, run.best_fun, run.spent, run.spent + 1, True, message)


class _BudgetedCost:
    """``cost`` as Powell sees it: clipped to the bounds, counted, best point kept, and flat
    (the best value, nothing evaluated) once the budget is spent or the callback said stop."""

    def __init__(
        self,
        cost: Callable[[Array], float],
        x0: Array,
        bounds: Array,
        budget: int,
        callback: Callable[[PolishState], bool | None] | None,
    ) -> None:
        self.cost, self.bounds, self.budget, self.callback = cost, bounds, int(budget), callback
        self.best_x, self.best_fun = x0.copy(), float(cost(x0))
        self.spent = 0
        self.stopped = False

    def __call__(self, x: Array) -> float:
        if self.stopped or self.spent >= self.budget:
            return self.best_fun
        x_in = np.clip(x, self.bounds[:, 0], self.bounds[:, 1])
        f = float(self.cost(x_in))
        self.spent += 1
        if f < self.best_fun:
            self.best_x, self.best_fun = x_in, f
        if self.callback is not None:
            state = PolishState(self.spent + 1, np.asarray(x, dtype=np.float64), f, self.best_x, self.best_fun)
            self.stopped = bool(self.callback(state))
        return f
