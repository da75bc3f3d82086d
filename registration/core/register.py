"""The image-based registration pipeline (the paper's Fig. 2).

The machine-based pose (``initial_motion``, identity when the patient has not moved) is
refined by comparing DRRs of the volume with the X-ray image under gradient difference,
optimised by simulated annealing over five parameters in the view frame of the X-ray image:
in-plane translations (tx, ty) and rotations (rx, ry, rz) about the iso-center; tz is kept.
The search runs coarse to fine over image/volume pyramids, and ends with a short local
polish (Powell) at the finest level.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from registration.core.anneal import AnnealResult, AnnealState, Schedule, anneal
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, check_rigid, offsets_to_matrix
from registration.core.images import XRayImage
from registration.core.metrics import Residual, residuals
from registration.core.similarity import GradientDifference
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: Names of the five optimised parameters, in order (mm, mm, deg, deg, deg).
PARAMETERS = ("tx", "ty", "rx", "ry", "rz")


@dataclass(frozen=True)
class Level:
    """One stage of the coarse-to-fine search.

    ``image_px``: the X-ray image is block-averaged to about this many pixels across;
    ``volume_level``: pyramid level of the volume (0 = full resolution, 1 = half, ...).
    """

    image_px: int
    volume_level: int
    schedule: Schedule
    #: Independent annealing runs from the level's start; the best one continues.
    restarts: int = 1


def _default_levels() -> tuple[Level, ...]:
    # Capture: four independent annealing runs on 64-px images from the quarter-resolution
    # volume (cheap, run side by side on the cores; several runs escape the rotation-for-
    # translation trades one run can fall into); refine: 128-px images, same volume level;
    # the polish then uses the half-resolution volume. Chosen on T1-T4 at 22/27/48 cm, oblique
    # views (12/12 with two runs vs 11/12 with one) and on the quick studies (four runs vs two:
    # clinical 38/40 vs 35/40 on translation, 40/40 vs 38/40 on rotation; phantom 22 cm volume
    # failures 4 -> 2), for 970 instead of 560 DRRs, the extra ones the cheapest.
    return (
        Level(64, 2, Schedule(step=(4.0, 4.0, 2.0, 2.0, 2.0), stages=14, moves_per_stage=14, cooling=0.75), restarts=4),
        Level(128, 2, Schedule(step=(1.0, 1.0, 0.7, 0.7, 0.7), stages=8, moves_per_stage=10, cooling=0.7)),
    )


@dataclass(frozen=True)
class RegistrationOptions:
    """How a registration searches; the defaults are the benchmarked configuration."""

    levels: tuple[Level, ...] = field(default_factory=_default_levels)
    #: Search range around the initial pose: +- translation (mm) and rotation (deg).
    bound_mm: float = 30.0
    bound_deg: float = 15.0
    #: Threads for independent capture runs (None: one per core).
    threads: int | None = None
    #: Final local polish at the last level (Powell), and its evaluation budget.
    polish: bool = True
    polish_evaluations: int = 60
    polish_image_px: int = 128
    polish_volume_level: int = 1
    #: Compare only pixels whose rays pass at least this far inside the volume's support
    #: (its box and the reconstructable cylinder), judged at the current estimate at the
    #: start of each level: the support's outline is an edge the X-ray image does not
    #: have. One margin per level, then the polish's; None compares the whole field.
    support_margin_mm: tuple[float, ...] | None = (15.0, 6.0, 4.0)

    def __post_init__(self) -> None:
        if not self.levels:
            raise ValueError("at least one level is needed")
        if self.bound_mm <= 0 or self.bound_deg <= 0:
            raise ValueError("bound_mm and bound_deg must be positive")
        for level in self.levels:
            if level.image_px < 16:
                raise ValueError(f"image_px must be >= 16, got {level.image_px}")
            if level.volume_level < 0:
                raise ValueError(f"volume_level must be >= 0, got {level.volume_level}")
            if level.restarts < 1:
                raise ValueError(f"restarts must be >= 1, got {level.restarts}")
        if self.support_margin_mm is not None:
            if len(self.support_margin_mm) != len(self.levels) + 1:
                raise ValueError("support_margin_mm needs one margin per level plus one for the polish")
            if any(not math.isfinite(m) or m < 0 for m in self.support_margin_mm):
                raise ValueError(f"support margins must be >= 0 mm, got {self.support_margin_mm}")


@dataclass(frozen=True)
class Progress:
    """What the registration callback sees at every iteration."""

    iteration: int
    level: int
    temperature: float
    current_motion: Array
    best_motion: Array
    current_similarity: float
    best_similarity: float
    drr_count: int
    elapsed_s: float


@dataclass
class RegistrationResult:
    """The outcome of one registration (CONVENTIONS.md §4)."""

    patient_motion: Array
    similarity: float
    similarity_trace: list[float]
    drr_count: int
    seconds: float
    stopped: bool
    offsets: Array
    geometry: CArm
    volume_label: str
    residual: Residual | None = None

    @property
    def success(self) -> bool | None:
        return None if self.residual is None else self.residual.success

    def to_dict(self) -> dict:
        out = {
            "patient_motion": np.asarray(self.patient_motion).tolist(),
            "similarity": self.similarity,
            "similarity_trace": list(self.similarity_trace),
            "drr_count": self.drr_count,
            "seconds": self.seconds,
            "stopped": self.stopped,
            "offsets": dict(zip(PARAMETERS, np.asarray(self.offsets).tolist(), strict=True)),
            "geometry": self.geometry.to_dict(),
            "volume_label": self.volume_label,
        }
        if self.residual is not None:
            out["residual"] = self.residual.to_dict()
            out["success"] = self.residual.success
        return out


class _Stop(Exception):
    pass


def support_mask(volume: Volume, geometry: CArm, motion: ArrayLike, margin_mm: float) -> NDArray[np.bool_]:
    """Pixels whose rays pass through the volume's support shrunk by ``margin_mm``.

    The support is the volume's box intersected with the cylinder (axis along the volume's
    k axis) inscribed in it: a cone-beam 3DRA reconstructs only that cylinder, and a CT box
    contains it. Rays that graze the support's outline see its truncation edge, which the
    X-ray image does not have; ``motion`` places the volume as in the DRR.
    """
    m = check_rigid(motion, name="motion")
    rows, cols = np.mgrid[0 : geometry.rows, 0 : geometry.cols]
    targets = geometry.pixel_to_world(cols, rows).reshape(-1, 3)
    to_index = volume.world_to_index @ np.linalg.inv(m)
    src = to_index[:3, :3] @ geometry.source_mm + to_index[:3, 3]
    dirs = targets @ to_index[:3, :3].T + to_index[:3, 3] - src
    spacing = volume.spacing_mm
    # Work in index units scaled to mm along each axis (the 3DRA grids are orthogonal).
    src_mm, dirs_mm = src * spacing, dirs * spacing
    n = np.array(volume.shape[::-1], dtype=np.float64)  # (ni, nj, nk)
    lo, hi = np.full(3, margin_mm) - 0.5 * spacing, (n - 0.5) * spacing - margin_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - src_mm) / dirs_mm, (hi - src_mm) / dirs_mm
    near = np.nanmax(np.where(np.isfinite(t1), np.minimum(t1, t2), -np.inf), axis=1)
    far = np.nanmin(np.where(np.isfinite(t1), np.maximum(t1, t2), np.inf), axis=1)
    # Rays parallel to a slab must start inside it.
    parallel = dirs_mm == 0
    outside = parallel & ((src_mm < lo) | (src_mm > hi))
    far[np.any(outside, axis=1)] = -np.inf
    # The inscribed cylinder about the k axis.
    center = (n[:2] - 1) / 2.0 * spacing[:2]
    radius = min(n[0] * spacing[0], n[1] * spacing[1]) / 2.0 - margin_mm
    p, d = src_mm[:2] - center, dirs_mm[:, :2]
    a = np.sum(d * d, axis=1)
    b = 2.0 * d @ p
    c = p @ p - radius * radius
    disc = b * b - 4 * a * c
    hit = (disc > 0) & (a > 0) & (radius > 0)
    root = np.sqrt(np.where(hit, disc, 0.0))
    safe_a = np.where(a > 0, a, 1.0)
    near = np.where(hit, np.maximum(near, (-b - root) / (2 * safe_a)), near)
    far = np.where(hit, np.minimum(far, (-b + root) / (2 * safe_a)), -np.inf)
    return (far > near).reshape(geometry.rows, geometry.cols)


def register(
    volume: Volume,
    xray: XRayImage,
    *,
    initial_motion: ArrayLike | None = None,
    options: RegistrationOptions | None = None,
    seed: int = 0,
    callback: Callable[[Progress], bool | None] | None = None,
    truth: ArrayLike | None = None,
    vessel_points_mm: ArrayLike | None = None,
    renderer: DRRRenderer | None = None,
) -> RegistrationResult:
    """Estimate the patient motion that aligns ``volume`` with ``xray``.

    Parameters
    ----------
    volume:
        The 3DRA (HU). Its label is repeated in the result.
    xray:
        The X-ray image (attenuation line integrals), its field mask and geometry.
    initial_motion:
        The machine-based pose as a 4x4 patient motion (identity by default).
    options:
        Search configuration; see :class:`RegistrationOptions`.
    seed:
        Seed of the annealing's random generator (same seed, same result).
    callback:
        Called with a :class:`Progress` at every iteration; return True to stop.
    truth:
        The true patient motion; when given the result carries residuals and success.
    vessel_points_mm:
        Target points for the mTRE (e.g. the vessel centerline), in volume world mm.
    renderer:
        A prepared :class:`DRRRenderer` of ``volume`` to reuse across registrations.
    """
    start = time.perf_counter()
    options = options or RegistrationOptions()
    geometry = xray.geometry
    m_init = np.eye(4) if initial_motion is None else check_rigid(initial_motion, name="initial motion")
    truth_m = None if truth is None else check_rigid(truth, name="true motion")
    n_levels = max([lv.volume_level for lv in options.levels] + [options.polish_volume_level]) + 1
    if renderer is None:
        renderer = DRRRenderer(volume, levels=n_levels)
    elif renderer.volume is not volume:
        raise ValueError("renderer was prepared for another volume")
    rng = np.random.default_rng(seed)
    tz0 = 0.0

    def motion_of(x: Array) -> Array:
        return offsets_to_matrix([x[0], x[1], tz0, x[2], x[3], x[4]], geometry) @ m_init

    bounds = np.array([[-options.bound_mm, options.bound_mm]] * 2 + [[-options.bound_deg, options.bound_deg]] * 3)
    x_best = np.zeros(5)
    f_best = math.inf
    trace: list[float] = []
    drr_count = 0
    stopped = False
    iteration = 0

    lock = threading.Lock()  # capture runs may report from several threads
    stop_event = threading.Event()

    # What the callback sees as "best" and "temperature" spans the level's capture runs.
    shown: dict = {"level": -1, "f": math.inf, "x": None, "temperatures": {}}

    def report(
        level: int, temperature: float, x_cur: Array, f_cur: float, x_b: Array, f_b: float, chain: int = 0
    ) -> bool:
        nonlocal iteration
        with lock:
            if shown["level"] != level:
                shown.update(level=level, f=math.inf, x=None, temperatures={})
            if f_b < shown["f"] or shown["x"] is None:
                shown["f"], shown["x"] = f_b, x_b
            shown["temperatures"][chain] = temperature
            f_b, x_b = shown["f"], shown["x"]
            temperature = max(shown["temperatures"].values())
            iteration += 1
            trace.append(-f_b)
            if stop_event.is_set():
                return True
            if callback is None:
                return False
            stop = bool(
                callback(
                    Progress(
                        iteration=iteration,
                        level=level,
                        temperature=temperature,
                        current_motion=motion_of(x_cur),
                        best_motion=motion_of(x_b),
                        current_similarity=-f_cur,
                        best_similarity=-f_b,
                        drr_count=drr_count,
                        elapsed_s=time.perf_counter() - start,
                    )
                )
            )
            if stop:
                stop_event.set()
            return stop

    def make_cost(
        image_px: int, volume_level: int, margin_mm: float | None, parallel: bool | None = None
    ) -> Callable[[Array], float]:
        vl = min(volume_level, renderer.n_levels - 1)
        # Pixels about as fine as ``image_px`` across the image, or as the volume level's
        # voxels seen at the iso-center, whichever is finer: a volume much smaller than the
        # image still gets enough pixels (the support mask keeps their number small).
        factor_image = max(1, round(geometry.cols / image_px))
        voxel_px = renderer.level_volume(vl).spacing_mm.max() * geometry.magnification / max(geometry.pixel_mm)
        factor = min(factor_image, 2 ** max(0, math.floor(math.log2(max(voxel_px, 1.0)))))
        while factor > 1 and (geometry.rows % factor or geometry.cols % factor):
            factor -= 1
        level_image = xray.downsample(factor) if factor > 1 else xray
        level_geom = level_image.geometry
        mask = level_image.mask
        if margin_mm is not None:
            inside = mask & support_mask(volume, level_geom, motion_of(x_best), margin_mm)
            # Keep the whole field when the support would leave too little to compare.
            if inside.sum() >= 0.25 * mask.sum():
                mask = inside
        measure = GradientDifference(level_image.image, mask)

        def cost(x: Array) -> float:
            nonlocal drr_count
            with lock:
                if stop_event.is_set():  # another capture run was stopped: render nothing more
                    return math.inf
                drr_count += 1
            drr = renderer.render(level_geom, motion_of(x), level=vl, mask=mask, parallel=parallel)
            return -measure(drr)

        return cost

    for li, level in enumerate(options.levels):
        margin = None if options.support_margin_mm is None else options.support_margin_mm[li]

        def on_iter(state: AnnealState, li: int = li, chain: int = 0) -> bool:
            return report(li, state.temperature, state.x, state.fun, state.best_x, state.best_fun, chain)

        if level.restarts == 1:
            cost = make_cost(level.image_px, level.volume_level, margin)
            results = [anneal(cost, x_best, bounds, rng=rng, schedule=level.schedule, callback=on_iter)]
        else:
            # Independent runs, each with its own random stream (same seed, same result
            # whatever the threads), side by side on the cores with single-threaded DRRs.
            def chain(
                numbered: tuple[int, np.random.Generator],
                level_: Level = level,
                x_start: Array = x_best,
                margin: float | None = margin,
            ) -> AnnealResult:
                number, chain_rng = numbered
                cost = make_cost(level_.image_px, level_.volume_level, margin, parallel=False)
                return anneal(
                    cost,
                    x_start,
                    bounds,
                    rng=chain_rng,
                    schedule=level_.schedule,
                    callback=lambda state: on_iter(state, chain=number),
                )

            workers = max(1, min(level.restarts, options.threads or os.cpu_count() or 1))
            with ThreadPoolExecutor(max_workers=workers) as pool:
                results = list(pool.map(chain, enumerate(rng.spawn(level.restarts))))
        best = min(results, key=lambda r: r.fun)
        x_best, f_best = best.x, best.fun
        if any(r.message == "stopped by the callback" for r in results) or stop_event.is_set():
            stopped = True
            break

    if options.polish and not stopped:
        margin = None if options.support_margin_mm is None else options.support_margin_mm[-1]
        cost = make_cost(options.polish_image_px, options.polish_volume_level, margin)
        f_start = cost(x_best)
        state = {"x": x_best.copy(), "f": f_start}

        def polish_cost(x: Array) -> float:
            f = cost(np.clip(x, bounds[:, 0], bounds[:, 1]))
            if f < state["f"]:
                state["x"], state["f"] = np.clip(x, bounds[:, 0], bounds[:, 1]), f
            if report(len(options.levels), 0.0, x, f, state["x"], state["f"]):
                raise _Stop
            return f

        try:
            optimize.minimize(
                polish_cost,
                x_best,
                method="Powell",
                bounds=bounds,
                options={
                    "maxfev": options.polish_evaluations,
                    "xtol": 0.02,
                    "ftol": 1e-6,
                    "direc": np.diag([0.5, 0.5, 0.3, 0.3, 0.3]),
                },
            )
        except _Stop:
            stopped = True
        x_best, f_best = state["x"], state["f"]

    m_est = motion_of(x_best)
    res = None
    if truth_m is not None:
        res = residuals(m_est, truth_m, geometry, vessel_points_mm)
    return RegistrationResult(
        patient_motion=m_est,
        similarity=-f_best,
        similarity_trace=trace,
        drr_count=drr_count,
        seconds=time.perf_counter() - start,
        stopped=stopped,
        offsets=x_best,
        geometry=geometry,
        volume_label=volume.label,
        residual=res,
    )
