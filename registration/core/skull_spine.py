"""Whether the skull and the spine agree: the whole volume's fit near the cranium's estimate.

A registration on the cranium (:func:`registration.core.roi.cranium_region`) follows the head and
ignores the cervical spine. When the neck is bent (flexion or rotation at C1/C2), the spine in
the image lies elsewhere than the rigid head says, and a fit of the whole volume is pulled
toward it. :func:`skull_spine_check` measures that pull: it searches the whole volume (spine
included) near the cranium's estimate, within ``reach_mm`` and ``reach_deg``, and reports how
far the whole volume's fit lies from it at the iso-center (in the image plane for one view, in
3-D for two). Beyond ``agree_mm`` or ``agree_deg`` the skull and the spine disagree: the neck
moved relative to the head, and the head's estimate (the cranium's) is the one to use.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.anneal import Schedule
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, apply, check_rigid, invert_rigid, rotation_angle_deg
from registration.core.images import XRayImage
from registration.core.prepare import PreparedVolume
from registration.core.register import Level, RegistrationOptions, StartOptions, register
from registration.core.roi import RegionOfInterest, followed_region, region_on_grid, soft_outside
from registration.core.volume import Volume

#: Beyond this shift at the iso-center (mm) the whole volume's fit and the cranium's disagree.
AGREE_MM = 1.0
#: Beyond this rotation (degrees) they disagree.
AGREE_DEG = 1.5


@dataclass(frozen=True)
class SkullSpineCheck:
    """How far the whole volume's fit (``whole_motion``) lies from the cranium's estimate:
    ``shift_mm`` at the iso-center (in plane A's image plane for one view, 3-D for two),
    ``rotation_deg``; ``agree`` when both are within the thresholds; ``drr_count``, ``seconds``:
    what the check cost."""

    shift_mm: float
    rotation_deg: float
    agree: bool
    whole_motion: NDArray[np.float64]
    drr_count: int
    seconds: float
    criterion: str

    def to_dict(self) -> dict:
        return {
            "agree": self.agree,
            "shift_mm": round(self.shift_mm, 3),
            "rotation_deg": round(self.rotation_deg, 3),
            "criterion": self.criterion,
            "whole_volume_motion": np.round(self.whole_motion, 6).tolist(),
            "drr_count": self.drr_count,
            "seconds": round(self.seconds, 3),
        }

    def message(self) -> str:
        where = f"{self.shift_mm:.2f} mm {self.criterion}, {self.rotation_deg:.2f} deg"
        if self.agree:
            return f"skull and spine agree: with the spine the fit moves {where} from the cranium's estimate"
        return (f"skull and spine DISAGREE: with the spine the fit moves {where} from the cranium's estimate "
                "(the neck moved relative to the head); the cranium's estimate is the head's")  # fmt: skip


def check_options(*, reach_mm: float = 6.0, reach_deg: float = 6.0) -> RegistrationOptions:
    """A short local search within ``reach_mm`` / ``reach_deg`` of the start: one annealing level
    at half resolution with small steps, then the polish; no depth correction, rotation check or
    walk (the start is already a registration's estimate)."""
    level = Level(96, 1, Schedule(step=(1.0, 1.0, 0.7, 0.7, 0.7), stages=6, moves_per_stage=10, cooling=0.7))
    return RegistrationOptions(
        levels=(level,), bound_mm=reach_mm, bound_deg=reach_deg, support_margin_mm=(6.0, 4.0),
        depth_correction=False, rotation_check=False, start=StartOptions(enabled=False),
    )  # fmt: skip


def skull_spine_check(
    whole: Volume,
    views: XRayImage | Sequence[XRayImage],
    cranium_motion: ArrayLike,
    *,
    renderer: DRRRenderer | None = None,
    seed: int = 0,
    agree_mm: float = AGREE_MM,
    agree_deg: float = AGREE_DEG,
    options: RegistrationOptions | None = None,
) -> SkullSpineCheck:
    """Search ``whole`` (the volume with its spine) near ``cranium_motion`` (a registration's
    estimate on the cranium) against ``views`` and say whether the two agree (see the module).
    ``renderer``: ``whole`` prepared for the views (:func:`registration.core.register.prepared_renderer`),
    by default prepared here around ``cranium_motion``."""
    views = (views,) if isinstance(views, XRayImage) else tuple(views)
    start = check_rigid(cranium_motion, name="cranium motion")
    began = time.perf_counter()
    result = register(whole, views, initial_motion=start, options=options or check_options(), seed=seed,
                      renderer=renderer)  # fmt: skip
    motion = np.asarray(result.patient_motion, dtype=np.float64)
    shift_mm, rotation = _moved(motion, start, views[0].geometry, in_plane=len(views) == 1)
    criterion = "in-plane" if len(views) == 1 else "3-D"
    agree = shift_mm <= agree_mm and rotation <= agree_deg
    return SkullSpineCheck(shift_mm, rotation, agree, motion, result.drr_count, time.perf_counter() - began,
                           criterion)  # fmt: skip


def _moved(
    end: NDArray[np.float64], start: NDArray[np.float64], geometry: CArm, *, in_plane: bool = True
) -> tuple[float, float]:
    """How far ``end`` lies from ``start`` at ``geometry``'s iso-center (mm; across its beam when
    ``in_plane``) and how far it turns (deg)."""
    iso = np.asarray(geometry.isocenter_mm, dtype=np.float64)
    shift = apply(end, iso) - apply(start, iso)
    if in_plane:
        shift = shift - (shift @ geometry.direction) * geometry.direction
    return float(np.linalg.norm(shift)), rotation_angle_deg(end @ invert_rigid(start))


@dataclass(frozen=True)
class SpinePull:
    """How far one view's estimate of the whole volume moves when the spine is left out: short
    local searches on the cranium (``check_options``) from the estimate end at least
    ``shift_mm`` from it in the image plane at the iso-center (that search ``rotation_deg``
    turned); ``drr_count``, ``seconds``: what the probe cost."""

    shift_mm: float
    rotation_deg: float
    drr_count: int
    seconds: float
    #: Each search's move (mm, in-plane at the iso-center).
    moves_mm: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        return {
            "shift_mm": round(self.shift_mm, 3),
            "moves_mm": [round(m, 3) for m in self.moves_mm],
            "rotation_deg": round(self.rotation_deg, 3),
            "drr_count": self.drr_count,
            "seconds": round(self.seconds, 3),
        }


def _cranium_of(volume: Volume) -> RegionOfInterest | None:
    """The volume's cranium region (found once per volume), None when the volume has no spine
    to leave out or is not axial."""
    region = followed_region(volume, "cranium")
    return None if region is None or region.skull_base_z_mm is None else region


def cranium_renderer(prepared: PreparedVolume) -> DRRRenderer | None:
    """The prepared levels with the cervical spine below the skull base turned into soft tissue
    (:func:`registration.core.roi.cranium_region`, :func:`~registration.core.roi.soft_outside`),
    sharing nothing else; built once per preparation. None when the volume has no spine to leave
    out."""
    key = ("cranium renderer",)
    if key not in prepared.derived:
        region = _cranium_of(prepared.volume)
        renderer = None
        if region is not None:
            base = prepared.renderer
            levels = {}
            for k in range(base.n_levels):
                if base.has_level(k):
                    grid = base.level_volume(k)
                    mask = region_on_grid(region, prepared.volume, grid)
                    levels[k] = Volume(soft_outside(grid.data, mask), grid.index_to_world, label=grid.label)
            renderer = base.with_levels(levels, lazy=True)  # written as the searches' rays read them
        prepared.derived[key] = renderer
    return prepared.derived[key]


#: The head-alone probe's short searches: their seeds (the probe's shift is the smallest of theirs).
PULL_SEEDS = (0, 1)


def spine_pull(
    prepared: PreparedVolume,
    view: XRayImage,
    motion: ArrayLike,
    *,
    enough_mm: float | None = None,
    options: RegistrationOptions | None = None,
) -> SpinePull | None:
    """Whether one view's estimate (``motion``, a registration of ``prepared``'s whole volume)
    holds for the head alone (:class:`SpinePull`); None when the volume has no spine to leave
    out. A neck that bent relative to the head pulls a rigid fit of the whole volume toward the
    spine's place in the image; on the head alone the fit moves back. Two short searches
    (``check_options``, seeds ``PULL_SEEDS``) start from the estimate; the pull is the smaller
    of their moves: a flat measure lets one search wander, both move only when the head's fit
    lies elsewhere. ``enough_mm``: no further search once one moved no more than this (the
    smallest move cannot be larger); ``options``: the searches' (``check_options()`` by default)."""
    began = time.perf_counter()
    renderer = cranium_renderer(prepared)
    if renderer is None:
        return None
    start = check_rigid(motion, name="motion")
    count0 = renderer.count
    moves = []
    options = options or check_options()
    for seed in PULL_SEEDS:
        result = register(prepared.volume, view, initial_motion=start, options=options, seed=seed,
                          renderer=renderer)  # fmt: skip
        moves.append(_moved(np.asarray(result.patient_motion, dtype=np.float64), start, view.geometry))
        if enough_mm is not None and moves[-1][0] <= enough_mm:
            break
    shift_mm, rotation = min(moves)
    return SpinePull(shift_mm, rotation, renderer.count - count0, time.perf_counter() - began,
                     tuple(m for m, _ in moves))  # fmt: skip
