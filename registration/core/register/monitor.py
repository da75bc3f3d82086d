"""Progress, stop and accounting shared by a registration's stages and capture runs."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from registration.core.problem import LevelProblem
from registration.core.register.result import Progress
from registration.core.search import SearchSpace

Array = NDArray[np.float64]


class Monitor:
    """Counts DRRs, keeps the similarity trace, calls the callback and holds the stop flag.

    Capture runs report from several threads; what the callback sees as "best" and
    "temperature" spans the current level's runs (so it never zigzags between them).
    """

    def __init__(self, space: SearchSpace, callback: Callable[[Progress], bool | None] | None, start_s: float):
        self.space, self.callback, self.start_s = space, callback, start_s
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.drr_count = 0
        #: DRR pixels (rays) rendered, all stages together.
        self.ray_count = 0
        self.iteration = 0
        self.trace: list[float] = []
        self._level = -1
        self._best: tuple[float, Array, SearchSpace] | None = None
        self._temperatures: dict[int, float] = {}
        #: Where the first level's capture runs ended (motions): the confidence's agreement.
        self.captures: list[Array] = []
        #: The cost of each stage that ran (:class:`registration.core.register.result.StageCost`).
        self.stages: list = []

    @property
    def stopped(self) -> bool:
        return self.stop.is_set()

    def charge(self, drrs: int, rays: int = 0) -> bool:
        """Count ``drrs`` DRRs (``rays`` pixels) about to be rendered; False (render nothing) once
        stopped."""
        with self.lock:
            if self.stop.is_set():
                return False
            self.drr_count += drrs
            self.ray_count += rays
            return True

    def report(
        self, level: int, temperature: float, x: Array, f: float, best_x: Array, best_f: float, chain: int,
        space: SearchSpace | None = None,
    ) -> bool:  # fmt: skip
        """One iteration of one run (in ``space``, the monitor's by default); True to stop."""
        run_space = space or self.space  # a plane's own capture runs in its own frame
        with self.lock:
            if self._level != level:
                self._level, self._best, self._temperatures = level, None, {}
            if self._best is None or best_f < self._best[0]:
                self._best = (best_f, best_x, run_space)
            self._temperatures[chain] = temperature
            best_f, best_x, best_space = self._best
            self.iteration += 1
            self.trace.append(-best_f)
            if self.stop.is_set():
                return True
            if self.callback is None:
                return False
            progress = Progress(
                iteration=self.iteration,
                level=level,
                temperature=max(self._temperatures.values()),
                current_motion=run_space.motion(x),
                best_motion=best_space.motion(best_x),
                current_similarity=-f,
                best_similarity=-best_f,
                drr_count=self.drr_count,
                elapsed_s=time.perf_counter() - self.start_s,
            )
            try:
                if self.callback(progress):
                    self.stop.set()
            except BaseException:
                self.stop.set()  # the other capture runs stop too, and the exception reaches the caller
                raise
            return self.stop.is_set()


def cost_function(problem: LevelProblem, space: SearchSpace, monitor: Monitor, parallel: bool | None) -> Callable:
    """cost(x) = -similarity of the DRRs at the motion of x, plus the space's wall there (inf once
    stopped)."""
    evaluator = problem.evaluator(parallel=parallel)
    drrs, rays = evaluator.drrs_per_evaluation, getattr(evaluator, "rays_per_evaluation", 0)  # 0: a stand-in
    wall = space.wall

    def cost(x: Array) -> float:
        if not monitor.charge(drrs, rays):
            return math.inf  # another capture run was stopped: render nothing more
        motion = space.motion(x)
        return -evaluator.similarity(motion) + (wall(motion) if wall is not None else 0.0)

    return cost
