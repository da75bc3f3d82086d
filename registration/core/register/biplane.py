"""Biplane: each plane's own capture side by side, combined geometrically, checked for agreement."""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from registration.core.anneal import AnnealResult, AnnealState, anneal
from registration.core.geometry import CArm, invert_rigid, rigid, rotation_angle_deg, rotation_matrix, rotation_vector
from registration.core.problem import LevelProblem
from registration.core.register.monitor import Monitor, cost_function
from registration.core.register.options import Level
from registration.core.register.plan import Run, State
from registration.core.search import FIVE_PARAMETERS, SearchSpace

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PlaneCaptures:
    """Each of the first two planes' own single-plane capture (five parameters in its own view
    frame, the first level), side by side, combined into the pair's start
    (:attr:`BiplaneOptions.plane_captures`); up to :data:`PLANE_CAPTURE_ROUNDS` rounds, cross-seeded,
    until the planes agree. Sets the state's ``planes_agree`` (and its ``starts`` when they do not)."""

    level: Level
    runs_per_plane: int
    margin_mm: float | None
    #: Each run goes on at this level before the planes are compared (None: it does not).
    refine: Level | None = None
    refine_margin_mm: float | None = None

    def describe(self) -> str:
        lv, then = self.level, ""
        if self.refine is not None:
            then = f", each run then at {self.refine.image_px} px, volume level {self.refine.volume_level}"
        return (f"each plane's own capture at {lv.image_px} px, volume level {lv.volume_level}, "
                f"{self.runs_per_plane} runs per plane{then}, up to {PLANE_CAPTURE_ROUNDS} rounds until the "
                "planes agree")  # fmt: skip

    def runs(self, state: State) -> bool:
        return True

    def run(self, state: State) -> State:
        starts, f = plane_captures(state.run, self.level, self.runs_per_plane, self.margin_mm,
                                   refine=self.refine, refine_margin_mm=self.refine_margin_mm)  # fmt: skip
        agree = len(starts) == 1
        return replace(state, x=starts[0], f=f, starts=() if agree else tuple(starts), planes_agree=agree)


def plane_captures(
    run: Run,
    level: Level,
    runs: int,
    margin_mm: float | None,
    *,
    refine: Level | None = None,
    refine_margin_mm: float | None = None,
) -> tuple[list[Array], float]:
    """The rounds of :class:`PlaneCaptures`: the pair's start and its cost when the planes agree;
    after :data:`PLANE_CAPTURE_ROUNDS` rounds without agreement, the starts of the pair's capture
    level instead (three: the bests' combination, each plane's best alone). ``refine``: each
    capture run goes on at that level (one run from its end) before the planes are compared."""
    inputs, space, options, rng, monitor = run.inputs, run.space, run.options, run.rng, run.monitor
    planes = inputs.views[:2]
    spaces = [SearchSpace(v.geometry, inputs.initial_motion, FIVE_PARAMETERS, options.bound_mm, options.bound_deg,
                          wall=space.wall) for v in planes]  # fmt: skip
    problems = _plane_problems(run, level, margin_mm)
    refined = None if refine is None else (refine, _plane_problems(run, refine, refine_margin_mm))
    geometries = (planes[0].geometry, planes[1].geometry)
    pair = LevelProblem.prepare(inputs.renderer, inputs.views, image_px=level.image_px,
                                volume_level=level.volume_level, motion=inputs.initial_motion,
                                margin_mm=margin_mm,
                                field_share_weights=options.biplane.field_share_weights)  # fmt: skip
    cost = cost_function(pair, space, monitor, None)
    per_plane: list[list[Array]] = [[] for _ in planes]
    single_costs: list[list[float]] = [[] for _ in planes]
    starts = [[sp.start()] * runs for sp in spaces]
    for _round in range(PLANE_CAPTURE_ROUNDS):
        captured = _capture_planes(problems, spaces, level, starts, rng, monitor, options.threads, refined)
        for plane, motion, f_plane in captured:
            per_plane[plane].append(motion)
            single_costs[plane].append(f_plane)
        if monitor.stopped:
            return [space.start()], math.inf
        # Each plane's estimate of lowest cost (its own measure) so far: where those two agree,
        # their combination starts the pair.
        best = [int(np.argmin(c)) for c in single_costs]
        ends = (per_plane[0][best[0]], per_plane[1][best[1]])
        x = space.from_motion(combine_plane_estimates(inputs.initial_motion, ends, geometries))
        x = np.clip(x, space.bounds[:, 0], space.bounds[:, 1])
        monitor.captures = [combine_plane_estimates(inputs.initial_motion, (a, b), geometries)
                            for a in per_plane[0][-runs:] for b in per_plane[1][-runs:]]  # fmt: skip
        shared_mm, rotation_deg = plane_disagreement(ends, geometries)
        if shared_mm <= PLANES_AGREE_MM and rotation_deg <= PLANES_AGREE_DEG:
            return [x], cost(x)
        # They do not: a capture traded a rotation for a translation (both runs of a plane can
        # fall into the same wrong basin). Another round, each plane's runs now starting from
        # the other plane's best estimate (its rotation and the displacement both see): the
        # plane that failed starts near the right rotation.
        # What the other plane cannot see (the displacement along its beam) is spread over the
        # runs: +- CROSS_START_MM along it, the rest of the start from its estimate of lowest cost.
        starts = [_cross_starts(spaces[p], geometries[p], geometries[1 - p], per_plane[1 - p][best[1 - p]], runs)
                  for p in range(2)]  # fmt: skip
    # Still none: the pair's capture runs start from the bests' combination and from each
    # plane's best estimate alone (the other plane's out-of-plane offset at the initial pose).
    alone = [np.clip(space.from_motion(m), space.bounds[:, 0], space.bounds[:, 1]) for m in ends]
    return [x, *alone], cost(x)


def _plane_problems(run: Run, level: Level, margin_mm: float | None) -> list[LevelProblem]:
    """Each plane's capture level alone; plane B's compares its image at plane A's pixel size at
    the iso-center, as the pair does."""
    inputs = run.inputs
    first = LevelProblem.prepare(inputs.renderer, inputs.views[:1], image_px=level.image_px,
                                 volume_level=level.volume_level, motion=inputs.initial_motion,
                                 margin_mm=margin_mm)  # fmt: skip
    pixel_mm = first.views[0].pixel_at_iso_mm
    return [first] + [
        LevelProblem.prepare(inputs.renderer, (v,), image_px=level.image_px, volume_level=level.volume_level,
                             motion=inputs.initial_motion, margin_mm=margin_mm, pixel_at_iso_mm=pixel_mm)
        for v in inputs.views[1:2]
    ]  # fmt: skip


def _cross_starts(space: SearchSpace, geometry: CArm, other: CArm, other_best: Array, runs: int) -> list[Array]:
    """A plane's next round's starts: the other plane's best estimate (its rotation and the
    displacement both see), spread +- :data:`CROSS_START_MM` along the other plane's beam (what
    it cannot see) over the runs."""
    along = np.asarray(other.direction, dtype=np.float64)
    along = along - (along @ geometry.direction) * np.asarray(geometry.direction)
    along /= max(float(np.linalg.norm(along)), 1e-12)
    shifts = np.linspace(-CROSS_START_MM, CROSS_START_MM, runs) if runs > 1 else np.zeros(1)
    return [np.clip(space.from_motion(rigid(None, t * along) @ other_best), space.bounds[:, 0], space.bounds[:, 1])
            for t in shifts]  # fmt: skip


#: Rounds of plane captures (each ``plane_capture_runs`` runs per plane) before the pair's own
#: capture level is run instead: a round whose pairings all disagree is followed by another.
PLANE_CAPTURE_ROUNDS = 3
#: The second round's runs start this far either side (mm) along the other plane's beam.
CROSS_START_MM = 12.0


def _capture_planes(
    problems: list[LevelProblem],
    spaces: list[SearchSpace],
    level: Level,
    starts: list[list[Array]],
    rng: np.random.Generator,
    monitor: Monitor,
    threads: int | None,
    refined: tuple[Level, list[LevelProblem]] | None = None,
) -> list[tuple[int, Array, float]]:
    """Single-plane capture runs, one per start of each plane (``starts[plane]``, parameter
    vectors in its space), all side by side: (plane, end motion, its cost) each. ``refined``: a
    level and its per-plane problems where each run goes on from its end (the cost is that level's)."""
    jobs = [(p, c) for p in range(len(problems)) for c in range(len(starts[p]))]
    streams = rng.spawn(len(jobs))

    stages = [(level, problems), *([refined] if refined is not None else [])]

    def run(job: int) -> AnnealResult:
        plane, chain = jobs[job]
        sp = spaces[plane]

        def on_iteration(s: AnnealState) -> bool:
            return monitor.report(0, s.temperature, s.x, s.fun, s.best_x, s.best_fun, job, sp)

        x = starts[plane][chain]
        for lv, level_problems in stages:  # the capture, then (refined) on from its end
            schedule = replace(lv.schedule, step=tuple(sp.per_parameter(lv.schedule.step)))
            cost = cost_function(level_problems[plane], sp, monitor, False)
            found = anneal(cost, x, sp.bounds, rng=streams[job], schedule=schedule, callback=on_iteration)
            if monitor.stopped:
                break
            x = found.x
        return found

    workers = max(1, min(len(jobs), threads or os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        results = list(pool.map(run, range(len(jobs))))
    return [(plane, spaces[plane].motion(r.x), r.fun) for (plane, _), r in zip(jobs, results, strict=True)]


#: The two planes' captures agree when their estimates of the displacement both images show
#: (across both beams) differ by at most this (mm) and their rotations by at most this (deg);
#: otherwise one capture failed and the pair's own capture level runs.
PLANES_AGREE_MM = 3.0
PLANES_AGREE_DEG = 4.0


def plane_disagreement(motions: tuple[Array, Array], geometries: tuple[CArm, CArm]) -> tuple[float, float]:
    """How far two planes' single-plane estimates of one moment disagree on what both can see:
    the iso-center's displacement across both beams (mm) and the rotation between them (deg)."""
    iso = np.asarray(geometries[0].isocenter_mm, dtype=np.float64)
    a, b = (np.asarray(m, dtype=np.float64) for m in motions)
    shared = np.cross(geometries[0].direction, geometries[1].direction)
    norm = float(np.linalg.norm(shared))
    diff = (a[:3, :3] @ iso + a[:3, 3]) - (b[:3, :3] @ iso + b[:3, 3])
    shared_mm = abs(float(diff @ shared)) / norm if norm > 1e-9 else float(np.linalg.norm(diff))
    return shared_mm, rotation_angle_deg(a @ invert_rigid(b))


def combine_plane_estimates(
    initial_motion: Array, motions: tuple[Array, Array], geometries: tuple[CArm, CArm]
) -> Array:
    """One patient motion from two single-plane (five-parameter) estimates of one moment.

    Each plane's estimate is trusted for what its image shows: the iso-center's displacement
    across its beam (along the beam it kept the initial pose), the rotation about its beam
    fully and the rotations about axes across it at half weight (a view sees those only as
    perspective changes). The iso-center's displacement solves
    ``(P_a + P_b) t = P_a e_a + P_b e_b`` (``P`` the projection across a beam, ``e`` a plane's
    displacement): exact when the beams are not parallel. The rotation vectors combine by the
    same weighted least squares. Rotation is about the iso-center (both planes share it).
    """
    iso = np.asarray(geometries[0].isocenter_mm, dtype=np.float64)
    inv0 = invert_rigid(initial_motion)
    lhs_t, rhs_t, lhs_r, rhs_r = np.zeros((3, 3)), np.zeros(3), np.zeros((3, 3)), np.zeros(3)
    for motion, geometry in zip(motions, geometries, strict=True):
        delta = np.asarray(motion, dtype=np.float64) @ inv0
        d = np.asarray(geometry.direction, dtype=np.float64)
        across = np.eye(3) - np.outer(d, d)
        e = delta[:3, :3] @ iso + delta[:3, 3] - iso
        lhs_t += across
        rhs_t += across @ e
        weight = np.outer(d, d) + ROTATION_ACROSS_WEIGHT * across
        lhs_r += weight
        rhs_r += weight @ rotation_vector(delta[:3, :3])
    t = np.linalg.solve(lhs_t, rhs_t)
    rot = rotation_matrix(np.linalg.solve(lhs_r, rhs_r))
    delta = np.eye(4)
    delta[:3, :3] = rot
    delta[:3, 3] = iso + t - rot @ iso
    return delta @ np.asarray(initial_motion, dtype=np.float64)


#: Weight of a single plane's rotations about axes across its beam (against 1 about it).
ROTATION_ACROSS_WEIGHT = 0.5
