"""A registration as a plan of stages, built from the views and the options, run in order.

Each stage is a small object with ``describe()`` (one line for ``register --explain``),
``runs(state)`` (whether it runs on the state it is given; a stage that depends on an earlier
outcome, such as the biplane planes' agreement, says so in its description) and
``run(state) -> state`` with its own budget. Progress numbers the stages that run, in the
plan's order, from 0 (:attr:`registration.core.register.Progress.level`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from registration.core.images import XRayImage
from registration.core.problem import LevelProblem
from registration.core.register.inputs import Inputs
from registration.core.register.monitor import Monitor
from registration.core.register.options import RegistrationOptions
from registration.core.register.result import RotationCheck, StageCost
from registration.core.search import SearchSpace

Array = NDArray[np.float64]


@dataclass
class Run:
    """What every stage of one registration shares: the checked inputs, the options, the
    registration's search space (plane A's view frame), the random stream and the monitor."""

    inputs: Inputs
    options: RegistrationOptions
    space: SearchSpace
    rng: np.random.Generator
    monitor: Monitor

    def problem(
        self, image_px: int, volume_level: int, margin_mm: float | None, motion: Array,
        views: tuple[XRayImage, ...] | None = None, pixel_at_iso_mm: float | None = None,
    ) -> LevelProblem:  # fmt: skip
        """One level of the views (all by default) prepared at ``motion``."""
        return LevelProblem.prepare(self.inputs.renderer, self.inputs.views if views is None else views,
                                    image_px=image_px, volume_level=volume_level, motion=motion,
                                    margin_mm=margin_mm, pixel_at_iso_mm=pixel_at_iso_mm,
                                    field_share_weights=self.options.biplane.field_share_weights)  # fmt: skip


@dataclass(frozen=True)
class State:
    """Where a registration stands between stages.

    ``x``: the estimate in ``space`` (the run's, or its five parameters with tz held once the
    depth correction ran), ``f`` its cost (-similarity; inf: not evaluated at the level that
    follows); ``number``: Progress's number of the stage running; ``starts``: several starts
    for the next annealing level (planes that disagreed); ``planes_agree``: the biplane
    captures' outcome (None: none ran); ``depth_moves_mm``: each depth scan's move of tz;
    ``check``: what the last rotation check found; ``screened``: see below.
    """

    run: Run
    x: Array
    space: SearchSpace
    f: float = math.inf
    number: int = 0
    starts: tuple[Array, ...] = ()
    planes_agree: bool | None = None
    depth_moves_mm: tuple[float, ...] | None = None
    check: RotationCheck | None = None
    #: The depth correction's rotation screen: the estimate it measured, its cost and its margin
    #: (at the polish's level; the rotation check's screen of the same estimate).
    screened: tuple[Array, float, float] | None = None

    @property
    def motion(self) -> Array:
        return self.space.motion(self.x)

    @property
    def tz_mm(self) -> float | None:
        """The depth-corrected tz (None: no depth correction ran)."""
        return None if self.depth_moves_mm is None else self.space.held_tz_mm


class Stage(Protocol):
    def describe(self) -> str: ...

    def runs(self, state: State) -> bool: ...

    def run(self, state: State) -> State: ...


#: A stage's condition on an earlier outcome: its description and its test.
Condition = tuple[str, Callable[[State], bool]]
PLANES_AGREE: Condition = ("when the planes agree", lambda s: s.planes_agree is not False)
PLANES_DISAGREE: Condition = ("when the planes disagree", lambda s: s.planes_agree is False)


@dataclass(frozen=True)
class Plan:
    """The stages of one registration, in order."""

    stages: tuple[Stage, ...] = field(default_factory=tuple)

    def describe(self) -> str:
        """One numbered line per stage (what ``register --explain`` prints)."""
        return "\n".join(f"{n + 1}. {stage.describe()}" for n, stage in enumerate(self.stages))

    def run(self, state: State) -> State:
        """Run the stages in order until the monitor stops; Progress numbers those that run, and
        the monitor keeps each one's cost (:class:`StageCost`)."""
        number = 0
        monitor = state.run.monitor
        for stage in self.stages:
            if monitor.stopped:
                break
            if not stage.runs(state):
                continue
            drrs, rays, began = monitor.drr_count, monitor.ray_count, time.perf_counter()
            state = stage.run(replace(state, number=number))
            cost = StageCost(stage.describe(), monitor.drr_count - drrs, monitor.ray_count - rays,
                             time.perf_counter() - began)  # fmt: skip
            monitor.stages.append(cost)
            number += 1
        return state
