"""The image-based registration pipeline (the paper's Fig. 2), for one or more views.

The machine-based pose (``initial_motion``, identity when the patient has not moved) is
refined by comparing DRRs of the volume with the X-ray images under gradient difference,
optimised by simulated annealing over offsets in the view frame of the first view
(:mod:`registration.core.search`). One view: the paper's five parameters (tx, ty, rx, ry, rz;
tz is kept, a view cannot see motion along its beam). Two views of the same moment (biplane,
CONVENTIONS.md §6): all six, in plane A's view frame, the measure being the mean of the
views' gradient differences (:mod:`registration.core.problem`).

The search runs coarse to fine: each :class:`Level` is prepared once
(:class:`~registration.core.problem.LevelProblem`) and annealed by one or several capture
runs side by side; a short local polish (:func:`~registration.core.anneal.polish`) ends it.

One view ends with the depth correction (:func:`depth_correct`,
``RegistrationOptions.depth_correction``, on by default since this revision; off reproduces the
five-parameter results before it, Table I's among them): the high-passed depth scan
(:func:`registration.core.depth.depth_scan`) estimates tz, the pose moves there and the five
parameters are polished again, up to three scans. The result's ``patient_motion`` then holds
that tz (``depth_tz_mm``); the in-plane residual and the rotation, hence single-view success
(CONVENTIONS §4), do not depend on it.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.anneal import AnnealResult, AnnealState, PolishState, Schedule, anneal, polish
from registration.core.checks import check_information, parameters_at_bounds
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, check_rigid, invert_rigid, rigid, rotation_angle_deg
from registration.core.images import XRayImage
from registration.core.metrics import Residual, residuals
from registration.core.prepare import PreparationStore, PreparedVolume, Reach, prepare_volume
from registration.core.problem import LevelProblem, iso_pixel_mm, level_factor, renderer_level, support_mask
from registration.core.search import FIVE_PARAMETERS, SIX_PARAMETERS, SearchSpace
from registration.core.volume import Volume

Array = NDArray[np.float64]

#: Names of the five parameters of a single-view registration (mm, mm, deg, deg, deg).
PARAMETERS = FIVE_PARAMETERS

__all__ = [
    "FIVE_PARAMETERS",
    "PARAMETERS",
    "SIX_PARAMETERS",
    "Level",
    "Progress",
    "RegistrationOptions",
    "RegistrationResult",
    "register",
    "support_mask",
]


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
    # translation trades one run can fall into); refine: finer images, same volume level;
    # the polish then uses the half-resolution volume. Chosen on T1-T4 at 22/27/48 cm, oblique
    # views (12/12 with two runs vs 11/12 with one) and on the quick studies (four runs vs two:
    # clinical 38/40 vs 35/40 on translation, 40/40 vs 38/40 on rotation; phantom 22 cm volume
    # failures 4 -> 2), for 970 instead of 560 DRRs, the extra ones the cheapest.
    # Steps are given for (tx, ty, rx, ry, rz); a six-parameter search steps tz as tx.
    # The refine level asks for about 96 px (1.9 mm at the iso-center of a 27 cm field, between
    # the capture's 2.85 and the polish's 1.42 mm; its volume has 2.85-4 mm voxels): a 384 px
    # image is compared at 96 px (blocks of 4), 0.56x the pixels of 128; a 512 px image keeps
    # 128 px (blocks of 5.3 rounded to 5 do not divide it, level_factor takes 4), so Table I
    # and the bench's T1-T4 (512 px) are unchanged. Same-process A/B against 128,
    # seed 0: the real CT's 20 `validate volume` cases (384 px) 20/20 both, in-plane median
    # 0.133 / 0.132 mm, worst 0.66 / 0.69, rotation 0.160 / 0.163 deg, DRR samples 0.89x, time
    # 0.93x; the phantom's Table I cases on 384 px images (seeds 0 and 1, 32 cases) 32/32 both,
    # in-plane 0.025 / 0.023 mm (worst 0.12 / 0.12), rotation 0.131 / 0.110 deg (worst 0.30 /
    # 0.22), samples 0.94x.
    return (
        Level(64, 2, Schedule(step=(4.0, 4.0, 2.0, 2.0, 2.0), stages=14, moves_per_stage=14, cooling=0.75), restarts=4),
        Level(96, 2, Schedule(step=(1.0, 1.0, 0.7, 0.7, 0.7), stages=8, moves_per_stage=10, cooling=0.7)),
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
    polish_evaluations: int = 40
    polish_image_px: int = 128
    polish_volume_level: int = 1
    #: Powell's initial step for translations (mm) and rotations (deg).
    polish_step_mm: float = 0.5
    polish_step_deg: float = 0.3
    #: The polish searches its start +- this (mm, deg), not the whole search range (None: the
    #: search range), with Powell's tolerance ``polish_xtol`` (the pair's polishes have their
    #: own, below). As for the pair (``pair_polish_reach``): over the whole range each line
    #: search opens 7 mm / 3.5 deg out, far outside the basin the annealing left, and the 60
    #: evaluations were one pass over the parameters; over +- 2 mm / 1.5 deg with xtol 0.1, 40
    #: evaluations did as well (same-process A/B against 60 over the range, seed 0: Table I's
    #: 16 cases 16/16, in-plane median 0.048 mm against 0.052, worst 0.076 / 0.074, rotation
    #: 0.170 / 0.169 deg, worst 0.295 / 0.292; the real CT's first 12 `validate volume` cases
    #: 12/12, 0.138 mm / 0.202 deg against 0.150 / 0.203; DRR samples 0.91x, time 0.93-0.94x).
    #: 30 evaluations left the rotation worse (Table I median 0.229 deg).
    polish_reach: tuple[float, float] | None = (2.0, 1.5)
    polish_xtol: float = 0.1
    #: Compare only pixels whose rays pass at least this far inside the volume's support
    #: (its box and the reconstructable cylinder), judged at the current estimate at the
    #: start of each level: the support's outline is an edge the X-ray image does not
    #: have. One margin per level, then the polish's; None compares the whole field.
    support_margin_mm: tuple[float, ...] | None = (15.0, 6.0, 4.0)
    #: Optimise tz too (six parameters). None: only when there are two or more views.
    optimize_tz: bool | None = None
    #: With two or more views, at most this many capture runs per level (None: as the level
    #: says): after plane A's own capture (below) the pair's capture starts close, so two runs
    #: do (on the moment that needed it: 0.12 mm total with two, 0.31 mm with one).
    multi_view_restarts: int | None = 2
    #: With two or more views, start with the single-plane capture on plane A alone (the
    #: first level, five parameters, its capture runs): one view's capture finds the in-plane
    #: pose from large offsets, which the six-parameter capture of a pair missed on a 25 mm
    #: offset along plane B's beam (tx 24 mm off with two and with four capture runs).
    #: Progress then numbers that capture level 0 and the levels after it from 1.
    plane_a_capture: bool = True
    #: With two or more views (six parameters): each of the first two planes first runs its own
    #: single-plane capture (five parameters in its own view frame, the first level), both side
    #: by side on the cores; plane B's in-plane estimate holds plane A's tz and plane A's holds
    #: plane B's, so the two combine geometrically into a six-parameter start (each plane's
    #: estimate counts for what its image shows: translation across its beam, rotation about
    #: it; :func:`combine_plane_estimates`). ``plane_capture_runs`` capture runs per plane;
    #: each plane's best run (its own measure) counts and their combination starts the pair's
    #: levels (``pair_levels``). Where the two disagree on what both see
    #: (:data:`PLANES_AGREE_MM`, :data:`PLANES_AGREE_DEG`: a capture traded a rotation for a
    #: translation, e.g. plane A 12 deg and 35 mm off on a 25 mm moment, both its runs alike)
    #: another round of runs follows, each plane starting from the other's best estimate, spread
    #: +- :data:`CROSS_START_MM` along the other's beam (up to :data:`PLANE_CAPTURE_ROUNDS`);
    #: without agreement the pair's own capture level runs, then ``levels[1:]``. Replaces
    #: ``plane_a_capture`` when True: ~1,006 DRRs when the planes agree at once (1,940 before),
    #: ~1,830 after a second round, ~2,650 after a third (the polishes: 122 DRRs of 64 px, 62 of 128 px).
    plane_captures: bool = True
    plane_capture_runs: int = 2
    #: With ``plane_captures`` and agreeing planes: the pair's levels after the capture (None:
    #: ``levels[1:]``; each with the support margin of the level after the capture) and the
    #: pair's polish budget (None: ``polish_evaluations``). By default the combined start goes
    #: straight to the polish: it lies within about 1 mm and 1 deg (two planes, each across
    #: the other's beam), which the polish closes (the 27 cm study's moments 1-6 with 60
    #: evaluations over the whole range: 0.05-0.44 mm, 0.06-0.34 deg, as with the 128 px
    #: annealing level between, 178 DRRs more; 40-45 such evaluations left up to 0.6-1.1 deg).
    pair_levels: tuple[Level, ...] | None = ()
    pair_polish_evaluations: int | None = 30
    #: With ``plane_captures``: the pair's polish searches its start +- this (mm, deg), not the
    #: whole search range (None: the search range). Powell's bounded line search (scipy's
    #: fminbound) opens each line with two points 38 % into the interval from its ends: over
    #: +- 30 mm / 15 deg those lie 7 mm / 3.5 deg out (a third point at 16 mm / 8 deg), far
    #: outside the basin of a start within about 1 mm and 1 deg,
    #: and the rest of the line's budget converges from there: 60 evaluations were one pass over
    #: the six parameters. Over +- 4 mm / 3 deg the first points lie ~1 mm / 0.7 deg out, and
    #: with ``pair_polish_xtol`` 0.1 (each line ends at 0.05 mm / 0.03 deg, not 0.01 / 0.006)
    #: 45 evaluations did better than 60 (a4957a5: the full study's first 10 moments at 27 and
    #: 48 cm from the same captures, median 0.18 mm / 0.22 deg against 0.22 / 0.25, worst
    #: 0.44 mm / 0.54 deg against 0.45 / 0.77, 92 DRRs against 122). After the coarse polish
    #: (below) the start is closer still: +- 2 mm / 1.5 deg and 30 evaluations (25 left the
    #: rotation a little worse than the 45 without it on the quick study's 12 moments, whose
    #: capture level has 5.7 mm voxels: median 0.30 deg against 0.21; 30: 0.24 deg).
    pair_polish_reach: tuple[float, float] | None = (2.0, 1.5)
    #: Powell's tolerance of the pair's polishes (:func:`registration.core.anneal.polish`).
    pair_polish_xtol: float = 0.1
    #: With ``plane_captures``: before the pair's polish, a coarse one of this many evaluations
    #: (0: none) on the first level's images and volume level (64 px, quarter resolution: about
    #: a seventh of the polish's DRR samples per evaluation) over the start +-
    #: ``pair_coarse_polish_reach`` (mm, deg). Each plane's capture fitted five parameters to
    #: its own image; this fits the six to both images at once. From the same captures, 60
    #: coarse + 25 evaluations against the 45 of the polish alone: the full study's first 8
    #: moments at 27 and 48 cm, median 0.10 mm / 0.16 deg against 0.18 / 0.17, worst 0.29 mm /
    #: 0.47 deg against 0.44 / 0.54, DRR samples of the polishes 0.75x; on the real CT's first
    #: 11 moments (quick images) 60 + 30: 0.21 mm / 0.14 deg against 0.39 / 0.28 (docs/biplane.md).
    pair_coarse_polish_evaluations: int = 60
    pair_coarse_polish_reach: tuple[float, float] | None = (4.0, 3.0)
    #: One view (five parameters, with the polish): the depth correction
    #: (:func:`depth_correct`). After the polish the high-passed depth scan
    #: (:func:`registration.core.depth.depth_scan`, the estimate moved along the beam only) says
    #: where along the beam the measure peaks; tz moves there (within ``depth_bound_mm`` of the
    #: initial pose), the five parameters are polished again at that tz, and so on while the
    #: scan moves tz by at least ``depth_move_mm``, at most ``depth_rounds`` scans. A wrong tz is
    #: a wrong magnification which the in-plane fit absorbs at ~0.05 mm per mm (the clinical
    #: study's applied near misses, 1.0-1.4 mm in-plane at 12-22 mm along the beam). The
    #: result's ``patient_motion`` holds the tz so estimated (``depth_tz_mm``); the in-plane
    #: residual and the rotation, hence success, are the same as with tz put back to the
    #: initial pose's (CONVENTIONS §4: single-view success uses the in-plane part). False: the
    #: five-parameter registration as before (Table I's numbers up to 44953cb).
    depth_correction: bool = True
    depth_rounds: int = 3
    depth_move_mm: float = 1.5
    depth_bound_mm: float = 25.0
    #: The scan's volume level: the prepared level whose voxel is nearest this (mm,
    #: :func:`registration.core.depth.scan_level`), compared at the polish's pixel size at the
    #: iso-center (within ``depth_image_px``'s block size: the clinical study's 256 px frames
    #: at 128 px, the real CT's 384 px at 128, Table I's 512 px at 256); the first scan spans
    #: +- ``depth_bound_mm`` around the estimate, the later ones +- ``depth_rescan_mm``, in
    #: ``depth_scan_step_mm`` steps.
    depth_voxel_mm: float = 1.0
    #: No correction when that level's voxel is coarser than this (mm): a 20 mm offset along
    #: the beam is a 2.7 % magnification, ~1.6 mm at 60 mm from the central ray, below what
    #: voxels of 3 mm and more resolve (the app's 48^3 PACS export of a 27 cm field has 5.6 mm:
    #: its scan moved tz 4 mm off the truth).
    depth_max_voxel_mm: float = 3.0
    depth_image_px: int = 128
    depth_scan_step_mm: float = 2.0
    depth_rescan_mm: float = 12.0
    #: The correction's polishes (five parameters at the scan's tz): their reach around their
    #: start (mm, deg) and budget; ``depth_first_polish``: the first scan is followed by a polish
    #: even when it moves tz by less than ``depth_move_mm``. Chosen on the clinical study's seeds
    #: 6 and 7 (400 registrations, their recorded estimates corrected offline; calibration
    #: seeds): right estimates (< 1 mm in-plane, < 3 deg) 344 of 400 before; corrected with the
    #: main polish's (2 mm, 1.5 deg) and 40 evaluations 370; with (2 mm, 5 deg) and 60, 377;
    #: with the first polish too 381: the wider rotation reach lets an estimate caught 3.4-7 deg
    #: off in rx / ry (the five-parameter polish can move a rotation 1.5 deg) reach the right
    #: optimum once the magnification is right, as the six-parameter depth probe did.
    depth_polish_reach: tuple[float, float] = (2.0, 5.0)
    depth_polish_evaluations: int = 60
    depth_first_polish: bool = True
    #: One view, after the depth correction: the rotation check (:func:`rotation_check`). A
    #: view sees its out-of-plane rotations (about the view's x and y axes) least, and a
    #: single-plane estimate can end in a wrong optimum of them, 4-15 deg off (the clinical
    #: study's rotation failures). Four polishes (five parameters, tz held) start from the
    #: estimate with rx or ry turned by +- ``rotation_check_deg`` (reach
    #: ``rotation_check_reach`` mm / deg around the estimate, ``rotation_check_evaluations``
    #: each); when one ends with a better measure the estimate moves there (and the depth
    #: correction runs again from it when it moved by more than ``RIVAL_DISTINCT_DEG``) and is
    #: checked again, ``rotation_check_rounds`` checks at most. What the last check found is
    #: the result's ``rotation_check`` (the confidence's evidence ``rival_gain``). Chosen on the
    #: clinical study's seeds 9-11 (recorded estimates re-checked offline: of the 24 estimates
    #: that missed 1 mm / 3 deg, 20 had a better optimum within 1.5 deg of the truth at +- 6 deg
    #: with 40 evaluations; of 30 right ones none had a better optimum anywhere), ~165 DRRs of
    #: the polish's size per check.
    rotation_check: bool = True
    rotation_check_deg: float = 6.0
    rotation_check_reach: tuple[float, float] = (2.0, 9.0)
    rotation_check_evaluations: int = 40
    rotation_check_rounds: int = 3

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
        for name in ("polish_reach", "pair_polish_reach", "pair_coarse_polish_reach", "depth_polish_reach",
                     "rotation_check_reach"):  # fmt: skip
            reach = getattr(self, name)
            if reach is not None and not (len(reach) == 2 and all(r > 0 for r in reach)):
                raise ValueError(f"{name} must be two positive numbers (mm, deg), got {reach}")
        if self.pair_coarse_polish_evaluations < 0:
            raise ValueError(f"pair_coarse_polish_evaluations must be >= 0, got {self.pair_coarse_polish_evaluations}")
        if not self.polish_xtol > 0:
            raise ValueError(f"polish_xtol must be positive, got {self.polish_xtol}")
        if not self.pair_polish_xtol > 0:
            raise ValueError(f"pair_polish_xtol must be positive, got {self.pair_polish_xtol}")
        if self.plane_capture_runs < 1:
            raise ValueError(f"plane_capture_runs must be >= 1, got {self.plane_capture_runs}")
        if self.multi_view_restarts is not None and self.multi_view_restarts < 1:
            raise ValueError(f"multi_view_restarts must be >= 1, got {self.multi_view_restarts}")
        if not self.polish_step_mm > 0 or not self.polish_step_deg > 0:
            raise ValueError("polish_step_mm and polish_step_deg must be positive")
        if self.depth_rounds < 1:
            raise ValueError(f"depth_rounds must be >= 1, got {self.depth_rounds}")
        for name in (
            "depth_move_mm",
            "depth_bound_mm",
            "depth_voxel_mm",
            "depth_max_voxel_mm",
            "depth_scan_step_mm",
            "depth_rescan_mm",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value}")
        if self.depth_polish_evaluations < 1:
            raise ValueError(f"depth_polish_evaluations must be >= 1, got {self.depth_polish_evaluations}")
        if self.depth_image_px < 16:
            raise ValueError(f"depth_image_px must be >= 16, got {self.depth_image_px}")
        if not (math.isfinite(self.rotation_check_deg) and 0 < self.rotation_check_deg <= 15):
            raise ValueError(f"rotation_check_deg must lie in (0, 15], got {self.rotation_check_deg}")
        if self.rotation_check_evaluations < 1 or self.rotation_check_rounds < 1:
            raise ValueError("rotation_check_evaluations and rotation_check_rounds must be >= 1")

    def margin_mm(self, stage: int) -> float | None:
        """The support margin of level ``stage`` (``len(levels)``: the polish)."""
        return None if self.support_margin_mm is None else self.support_margin_mm[stage]

    def capture_runs(self, level: Level, n_views: int) -> int:
        """The capture runs of ``level`` for ``n_views`` views."""
        if n_views > 1 and self.multi_view_restarts is not None:
            return min(level.restarts, self.multi_view_restarts)
        return level.restarts

    def optimizes_tz(self, n_views: int) -> bool:
        return n_views > 1 if self.optimize_tz is None else bool(self.optimize_tz)

    @property
    def pyramid_levels(self) -> int:
        """Volume pyramid levels the search uses (finest 0 to the coarsest level named)."""
        return max([lv.volume_level for lv in self.levels] + [self.polish_volume_level]) + 1


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
    """The outcome of one registration (CONVENTIONS.md §4, §6).

    ``geometry`` is the first view's (plane A's): ``offsets`` and the residual's in-plane and
    out-of-plane parts are in its view frame; ``views`` lists every view's geometry.
    Fields added later must have defaults and appear in :meth:`to_dict` only when set, so
    the JSON of a single-view registration stays what it is.
    """

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
    parameters: tuple[str, ...] = FIVE_PARAMETERS
    views: tuple[CArm, ...] = ()
    #: Where the capture runs of the first level ended (4x4 motions; empty with one run).
    capture_motions: tuple[Array, ...] = ()
    #: Parameters whose estimate ended on the search bounds: such a result is not a registration
    #: (inputs without information drift there), whatever its similarity.
    at_bounds: tuple[str, ...] = ()
    #: The depth correction (:attr:`RegistrationOptions.depth_correction`, one view): tz, the
    #: offset along the beam (mm in the view frame, + toward the source) that ``patient_motion``
    #: holds beside the five ``offsets`` (``patient_motion = offsets_to_matrix((tx, ty,
    #: depth_tz_mm, rx, ry, rz), geometry) @ initial_motion``), and each scan's move (mm).
    #: None / (): no correction ran (two views, the option off, stopped).
    depth_tz_mm: float | None = None
    depth_moves_mm: tuple[float, ...] = ()
    #: The rotation check (:attr:`RegistrationOptions.rotation_check`, one view): how many
    #: checks ran, how many moved the estimate, and the last check's ``rival_gain``
    #: (:class:`RotationCheck`: the best other optimum against the kept estimate, relative,
    #: <= 0; > 0 only when the last check still moved the estimate; None: every polish came
    #: back). None: no check ran.
    rotation_check: RotationCheck | None = None

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
            "offsets": dict(zip(self.parameters, np.asarray(self.offsets).tolist(), strict=True)),
            "geometry": self.geometry.to_dict(),
            "volume_label": self.volume_label,
        }
        if len(self.views) > 1:
            out["views"] = [g.to_dict() for g in self.views]
        if self.residual is not None:
            out["residual"] = self.residual.to_dict()
            out["success"] = self.residual.success
        if self.at_bounds:
            out["at_bounds"] = list(self.at_bounds)
        if self.depth_tz_mm is not None:
            out["depth_tz_mm"] = self.depth_tz_mm
            out["depth_moves_mm"] = list(self.depth_moves_mm)
        if self.rotation_check is not None:
            out["rotation_check"] = self.rotation_check.to_dict()
        return out


# --------------------------------------------------------------------------------------
# Inputs, checked once here: nothing inside checks them again
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Inputs:
    """The checked inputs of one registration."""

    volume: Volume
    views: tuple[XRayImage, ...]
    initial_motion: Array
    truth: Array | None
    renderer: DRRRenderer


def check_inputs(
    volume: Volume,
    views: XRayImage | Sequence[XRayImage],
    initial_motion: ArrayLike | None,
    truth: ArrayLike | None,
    renderer: DRRRenderer | None,
    options: RegistrationOptions,
) -> Inputs:
    """Validate what the caller gave (ValueError saying what is wrong) and prepare the renderer."""
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a Volume, got {type(volume).__name__}")
    views = (views,) if isinstance(views, XRayImage) else tuple(views)
    if not views:
        raise ValueError("at least one X-ray view is needed")
    for n, view in enumerate(views):
        if not isinstance(view, XRayImage):
            raise ValueError(f"view {n} must be an XRayImage, got {type(view).__name__}")
    m_init = np.eye(4) if initial_motion is None else check_rigid(initial_motion, name="initial motion")
    truth_m = None if truth is None else check_rigid(truth, name="true motion")
    if renderer is None:
        renderer = prepared_renderer(volume, views, m_init, options)
    elif renderer.volume is not volume:
        raise ValueError("renderer was prepared for another volume")
    return Inputs(volume, views, m_init, truth_m, renderer)


def prepared_renderer(
    volume: Volume, views: tuple[XRayImage, ...], initial_motion: Array, options: RegistrationOptions
) -> DRRRenderer:
    """The renderer of the volume prepared for these views and this search (cropped to what the
    fields can reach, isotropic levels in mm; :func:`registration.core.prepare.prepare_volume`,
    cached per volume and field)."""
    return prepared_volume(volume, views, initial_motion, options).renderer


def prepared_volume(
    volume: Volume,
    views: tuple[XRayImage, ...],
    initial_motion: Array,
    options: RegistrationOptions,
    *,
    store: PreparationStore | None = None,
) -> PreparedVolume:
    """:func:`prepared_renderer`'s preparation itself; ``store``: where its view-independent part
    is looked up and kept across processes (:class:`registration.core.prepare.PreparationStore`)."""
    reach = Reach.of_search(
        options.bound_mm,
        options.bound_deg,
        initial_motion=initial_motion,
        isocenter_mm=views[0].geometry.isocenter_mm,
        translations=3 if options.optimizes_tz(len(views)) else 2,
    )
    levels = {lv.volume_level for lv in options.levels} | ({options.polish_volume_level} if options.polish else set())
    return prepare_volume(volume, [v.geometry for v in views], reach=reach, levels=sorted(levels), store=store)


# --------------------------------------------------------------------------------------
# Progress, stop and accounting shared by the capture runs
# --------------------------------------------------------------------------------------
class _Monitor:
    """Counts DRRs, keeps the similarity trace, calls the callback and holds the stop flag.

    Capture runs report from several threads; what the callback sees as "best" and
    "temperature" spans the current level's runs (so it never zigzags between them).
    """

    def __init__(self, space: SearchSpace, callback: Callable[[Progress], bool | None] | None, start_s: float):
        self.space, self.callback, self.start_s = space, callback, start_s
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.drr_count = 0
        self.iteration = 0
        self.trace: list[float] = []
        self._level = -1
        self._best: tuple[float, Array, SearchSpace] | None = None
        self._temperatures: dict[int, float] = {}
        #: Where the first level's capture runs ended (motions): the confidence's agreement.
        self.captures: list[Array] = []

    @property
    def stopped(self) -> bool:
        return self.stop.is_set()

    def charge(self, drrs: int) -> bool:
        """Count ``drrs`` DRRs about to be rendered; False (render nothing) once stopped."""
        with self.lock:
            if self.stop.is_set():
                return False
            self.drr_count += drrs
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
            if self.callback(progress):
                self.stop.set()
            return self.stop.is_set()


def _cost(problem: LevelProblem, space: SearchSpace, monitor: _Monitor, parallel: bool | None) -> Callable:
    """cost(x) = -similarity of the DRRs at the motion of x (inf once stopped)."""
    evaluator = problem.evaluator(parallel=parallel)

    def cost(x: Array) -> float:
        if not monitor.charge(evaluator.drrs_per_evaluation):
            return math.inf  # another capture run was stopped: render nothing more
        return -evaluator.similarity(space.motion(x))

    return cost


# --------------------------------------------------------------------------------------
# The stages
# --------------------------------------------------------------------------------------
def _anneal_level(
    problem: LevelProblem,
    space: SearchSpace,
    level: Level,
    stage: int,
    x_start: Array | list[Array],
    rng: np.random.Generator,
    monitor: _Monitor,
    threads: int | None,
) -> AnnealResult:
    """The level's capture runs from ``x_start`` (or run ``c`` from ``x_start[c % len]``); the
    best of them."""
    starts = x_start if isinstance(x_start, list) else [x_start]
    bounds = space.bounds
    schedule = replace(level.schedule, step=tuple(space.per_parameter(level.schedule.step)))

    def run(chain: int, chain_rng: np.random.Generator, parallel: bool | None) -> AnnealResult:
        def on_iteration(s: AnnealState) -> bool:
            return monitor.report(stage, s.temperature, s.x, s.fun, s.best_x, s.best_fun, chain)

        cost = _cost(problem, space, monitor, parallel)
        x0 = starts[chain % len(starts)]
        return anneal(cost, x0, bounds, rng=chain_rng, schedule=schedule, callback=on_iteration)

    if level.restarts == 1:
        return run(0, rng, None)
    # Independent runs, each with its own random stream (same seed, same result whatever
    # the threads), side by side on the cores with single-threaded DRRs.
    workers = max(1, min(level.restarts, threads or os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        results = list(pool.map(lambda c: run(c[0], c[1], False), enumerate(rng.spawn(level.restarts))))
    if not monitor.captures:
        monitor.captures = [space.motion(r.x) for r in results]
    return min(results, key=lambda r: r.fun)


def _polish(problem: LevelProblem, space: SearchSpace | _HeldTz, stage: int, x_start: Array,
            options: RegistrationOptions, monitor: _Monitor, *, pair: bool = False,
            coarse: bool = False) -> AnnealResult:  # fmt: skip
    """Powell from the annealed estimate, within the evaluation budget, over the estimate +-
    ``polish_reach`` (within the search range); ``pair``: the pair's polish after the plane
    captures (its budget, reach and tolerance), and with ``coarse`` the pair's coarse polish
    before it."""

    def on_evaluation(s: PolishState) -> bool:
        return monitor.report(stage, 0.0, s.x, s.fun, s.best_x, s.best_fun, 0, space)  # type: ignore[arg-type]

    step = np.where(space.is_translation(), options.polish_step_mm, options.polish_step_deg)
    bounds, evaluations = space.bounds, options.polish_evaluations
    xtol, reach = options.polish_xtol, options.polish_reach
    if pair:
        reach = options.pair_coarse_polish_reach if coarse else options.pair_polish_reach
        if coarse:
            evaluations = options.pair_coarse_polish_evaluations
        elif options.pair_polish_evaluations is not None:
            evaluations = options.pair_polish_evaluations
        xtol = options.pair_polish_xtol
    if reach is not None:
        half = np.where(space.is_translation(), *reach)
        x0 = np.clip(x_start, bounds[:, 0], bounds[:, 1])
        bounds = np.stack([np.maximum(bounds[:, 0], x0 - half), np.minimum(bounds[:, 1], x0 + half)], axis=1)
    cost = _cost(problem, space, monitor, None)
    return polish(cost, x_start, bounds, step=step, max_evaluations=evaluations, callback=on_evaluation, xtol=xtol)


def _plane_a_capture(
    inputs: Inputs, space: SearchSpace, options: RegistrationOptions, rng: np.random.Generator, monitor: _Monitor
) -> tuple[Array, float]:
    """The single-plane capture on plane A alone (five parameters, the first level as for one
    view), as the start of a multi-view search; its estimate with tz = 0 in ``space``."""
    five = replace(space, names=FIVE_PARAMETERS)
    level = options.levels[0]
    problem = LevelProblem.prepare(inputs.renderer, inputs.views[:1], image_px=level.image_px,
                                   volume_level=level.volume_level, motion=five.motion(five.start()),
                                   margin_mm=options.margin_mm(0))  # fmt: skip
    monitor.space = five
    try:
        best = _anneal_level(problem, five, level, 0, five.start(), rng, monitor, options.threads)
    finally:
        monitor.space = space
    return space.from_offsets(five.offsets(best.x)), math.inf


def _plane_captures(
    inputs: Inputs, space: SearchSpace, options: RegistrationOptions, rng: np.random.Generator, monitor: _Monitor
) -> tuple[list[Array], float]:
    """Each of the first two planes' own single-plane capture, side by side, combined into the
    start of the pair's six-parameter search (:attr:`RegistrationOptions.plane_captures`) and its
    cost. Each plane's best estimate (lowest cost of its own measure) counts; when the two
    disagree (:func:`plane_disagreement`) another round follows, cross-seeded; after
    :data:`PLANE_CAPTURE_ROUNDS` rounds without agreement, the starts of the pair's capture level
    instead (three: the bests' combination, each plane's best alone)."""
    level = options.levels[0]
    runs = options.plane_capture_runs
    planes = inputs.views[:2]
    spaces = [SearchSpace(v.geometry, inputs.initial_motion, FIVE_PARAMETERS, options.bound_mm, options.bound_deg)
              for v in planes]  # fmt: skip
    # plane B's capture compares its image at plane A's pixel size at the iso-center, as the pair does
    problems = [LevelProblem.prepare(inputs.renderer, planes[:1], image_px=level.image_px,
                                     volume_level=level.volume_level, motion=inputs.initial_motion,
                                     margin_mm=options.margin_mm(0))]  # fmt: skip
    pixel_mm = problems[0].views[0].pixel_at_iso_mm
    problems += [
        LevelProblem.prepare(
            inputs.renderer,
            (v,),
            image_px=level.image_px,
            volume_level=level.volume_level,
            motion=inputs.initial_motion,
            margin_mm=options.margin_mm(0),
            pixel_at_iso_mm=pixel_mm,
        )
        for v in planes[1:]
    ]
    geometries = (planes[0].geometry, planes[1].geometry)
    pair = LevelProblem.prepare(inputs.renderer, inputs.views, image_px=level.image_px,
                                volume_level=level.volume_level, motion=inputs.initial_motion,
                                margin_mm=options.margin_mm(0))  # fmt: skip
    cost = _cost(pair, space, monitor, None)
    per_plane: list[list[Array]] = [[] for _ in planes]
    single_costs: list[list[float]] = [[] for _ in planes]
    starts = [[sp.start()] * runs for sp in spaces]
    for _round in range(PLANE_CAPTURE_ROUNDS):
        for plane, motion, f_plane in _capture_planes(problems, spaces, level, starts, rng, monitor, options.threads):
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
        starts = []
        for p in range(2):
            other = best[1 - p]
            along = np.asarray(geometries[1 - p].direction, dtype=np.float64)
            along = along - (along @ geometries[p].direction) * np.asarray(geometries[p].direction)
            along /= max(float(np.linalg.norm(along)), 1e-12)
            shifts = np.linspace(-CROSS_START_MM, CROSS_START_MM, runs) if runs > 1 else np.zeros(1)
            starts.append([
                np.clip(spaces[p].from_motion(rigid(None, t * along) @ per_plane[1 - p][other]),
                        spaces[p].bounds[:, 0], spaces[p].bounds[:, 1])
                for t in shifts
            ])  # fmt: skip
    # Still none: the pair's capture runs start from the bests' combination and from each
    # plane's best estimate alone (the other plane's out-of-plane offset at the initial pose).
    alone = [np.clip(space.from_motion(m), space.bounds[:, 0], space.bounds[:, 1]) for m in ends]
    return [x, *alone], cost(x)


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
    monitor: _Monitor,
    threads: int | None,
) -> list[tuple[int, Array, float]]:
    """Single-plane capture runs, one per start of each plane (``starts[plane]``, parameter
    vectors in its space), all side by side: (plane, end motion, its cost) each."""
    jobs = [(p, c) for p in range(len(problems)) for c in range(len(starts[p]))]
    streams = rng.spawn(len(jobs))

    def run(job: int) -> AnnealResult:
        plane, chain = jobs[job]
        sp = spaces[plane]
        schedule = replace(level.schedule, step=tuple(sp.per_parameter(level.schedule.step)))

        def on_iteration(s: AnnealState) -> bool:
            return monitor.report(0, s.temperature, s.x, s.fun, s.best_x, s.best_fun, job, sp)

        cost = _cost(problems[plane], sp, monitor, False)
        x0 = starts[plane][chain]
        return anneal(cost, x0, sp.bounds, rng=streams[job], schedule=schedule, callback=on_iteration)

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
        rhs_r += weight @ _rotation_vector(delta[:3, :3])
    t = np.linalg.solve(lhs_t, rhs_t)
    rot = _rotation_matrix(np.linalg.solve(lhs_r, rhs_r))
    delta = np.eye(4)
    delta[:3, :3] = rot
    delta[:3, 3] = iso + t - rot @ iso
    return delta @ np.asarray(initial_motion, dtype=np.float64)


#: Weight of a single plane's rotations about axes across its beam (against 1 about it).
ROTATION_ACROSS_WEIGHT = 0.5


def _rotation_vector(r: Array) -> Array:
    """Axis times angle (radians) of a 3x3 rotation."""
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    if angle < 1e-12:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2.0 * math.sin(angle))
    return axis * angle


def _rotation_matrix(v: Array) -> Array:
    """Rodrigues: the rotation of axis-angle vector ``v`` (radians)."""
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    k = v / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * kx @ kx


def register(
    volume: Volume,
    views: XRayImage | Sequence[XRayImage],
    *,
    initial_motion: ArrayLike | None = None,
    options: RegistrationOptions | None = None,
    seed: int = 0,
    callback: Callable[[Progress], bool | None] | None = None,
    truth: ArrayLike | None = None,
    vessel_points_mm: ArrayLike | None = None,
    renderer: DRRRenderer | None = None,
) -> RegistrationResult:
    """Estimate the patient motion that aligns ``volume`` with the X-ray view(s).

    Parameters
    ----------
    volume:
        The 3DRA or CT (HU). Its label is repeated in the result.
    views:
        One :class:`XRayImage` (image in attenuation line integrals, field mask, geometry),
        or several taken at the same moment (biplane: plane A first; offsets are in its
        view frame).
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
        A :class:`DRRRenderer` of ``volume`` to use; by default the volume is prepared for the
        views and the search (:func:`prepared_renderer`, cached: later registrations of the same
        volume object and field reuse it) and ``seconds`` excludes that preparation.
    """
    options = options or RegistrationOptions()
    inputs = check_inputs(volume, views, initial_motion, truth, renderer, options)
    for view in inputs.views:
        check_information(inputs.volume, view)  # no edges, no registration (NoInformationError)
    start = time.perf_counter()
    space = SearchSpace.for_views(
        inputs.views[0].geometry,
        inputs.initial_motion,
        optimize_tz=options.optimizes_tz(len(inputs.views)),
        bound_mm=options.bound_mm,
        bound_deg=options.bound_deg,
    )
    monitor = _Monitor(space, callback, start)
    rng = np.random.default_rng(seed)
    x, f = space.start(), math.inf

    def prepare(image_px: int, volume_level: int, stage: int) -> LevelProblem:
        return LevelProblem.prepare(inputs.renderer, inputs.views, image_px=image_px, volume_level=volume_level,
                                    motion=space.motion(x), margin_mm=options.margin_mm(stage))  # fmt: skip

    # (index into the options' levels and support margins, level); Progress numbers them in order
    stages: list[tuple[int, Level]] = list(enumerate(options.levels))
    starts: list[Array] = [x]
    shown = 0  # the level number Progress shows for the first of ``stages``
    multi = len(inputs.views) > 1 and space.optimizes_tz
    if multi and options.plane_captures:
        starts, f = _plane_captures(inputs, space, options, rng, monitor)
        x = starts[0]
        if len(starts) == 1:
            # the planes agree: the capture level is done, the pair's levels follow
            if options.pair_levels is not None:
                last = len(options.levels) - 1
                stages = [(min(1 + n, last), lv) for n, lv in enumerate(options.pair_levels)]
            else:
                stages = stages[1:]
        else:
            # they do not: the pair's own capture level, one run from each start
            stages[0] = (0, replace(options.levels[0], restarts=len(starts)))
        shown = 1
    elif multi and options.plane_a_capture:
        x, f = _plane_a_capture(inputs, space, options, rng, monitor)
        shown = 1
    for n, (stage, level) in enumerate(stages):
        if monitor.stopped:
            break
        problem = prepare(level.image_px, level.volume_level, stage)
        begin: Array | list[Array] = x
        if n == 0 and len(starts) > 1:
            begin = starts
        else:
            level = replace(level, restarts=options.capture_runs(level, len(inputs.views)))
        best = _anneal_level(problem, space, level, shown + n, begin, rng, monitor, options.threads)
        x, f = best.x, best.fun
    pair = multi and options.plane_captures
    polish_shown = shown + len(stages)
    if options.polish and pair and options.pair_coarse_polish_evaluations and not monitor.stopped:
        first = options.levels[0]
        coarse = prepare(first.image_px, first.volume_level, len(options.levels) - 1)
        best = _polish(coarse, space, polish_shown, x, options, monitor, pair=True, coarse=True)
        x, f = best.x, best.fun
        polish_shown += 1
    if options.polish and not monitor.stopped:
        stage = len(options.levels)
        best = _polish(prepare(options.polish_image_px, options.polish_volume_level, stage), space,
                       polish_shown, x, options, monitor, pair=pair)  # fmt: skip
        x, f = best.x, best.fun
    depth: DepthCorrection | None = None
    if options.polish and options.depth_correction and len(inputs.views) == 1 and not space.optimizes_tz:
        if not monitor.stopped and depth_resolvable(inputs.renderer, options):
            depth = depth_correct(inputs.renderer, inputs.views[0], space, x, f, options, monitor, polish_shown + 1)
            x, f = depth.x, depth.fun
    check: RotationCheck | None = None
    if depth is not None and options.rotation_check and not monitor.stopped:
        x, f, depth, check = _check_rotations(inputs, space, x, f, depth, options, monitor, polish_shown + 2)
    return _result(inputs, space, x, f, monitor, vessel_points_mm, time.perf_counter() - start, depth, check)


def depth_resolvable(renderer: DRRRenderer, options: RegistrationOptions) -> bool:
    """Whether the depth correction's scan level (:func:`registration.core.depth.scan_level`)
    is fine enough to see a magnification (``depth_max_voxel_mm``)."""
    from registration.core.depth import scan_level

    level = scan_level(renderer, options.depth_voxel_mm)
    return float(renderer.level_volume(level).spacing_mm.max()) <= options.depth_max_voxel_mm


@dataclass(frozen=True)
class DepthCorrection:
    """The outcome of :func:`depth_correct`: the five parameters, the measure there, tz."""

    x: Array
    fun: float
    tz_mm: float
    moves_mm: tuple[float, ...]


def depth_correct(
    renderer: DRRRenderer,
    view: XRayImage,
    space: SearchSpace,
    x: Array,
    f: float,
    options: RegistrationOptions,
    monitor: _Monitor,
    stage: int,
    tz_mm: float = 0.0,
) -> DepthCorrection:
    """The depth correction of a five-parameter estimate ``x`` (``space``'s, cost ``f``): scan
    along the beam (:func:`registration.core.depth.depth_scan`, high-passed, the rest held),
    move tz to the peak (within +- ``depth_bound_mm`` of the initial pose), polish the five
    parameters again at that tz (the polish's level, budget and reach), repeat while a scan
    moves tz by ``depth_move_mm`` or more, ``depth_rounds`` scans at most
    (:attr:`RegistrationOptions.depth_correction`). The scans' DRRs are counted in
    ``monitor``; ``tz_mm``: the estimate's tz (the initial pose's by default). Deterministic."""
    from registration.core.depth import depth_scan, scan_level

    six = replace(space, names=SIX_PARAMETERS)
    level = scan_level(renderer, options.depth_voxel_mm)
    # the scan compares at the polish's pixel (at the iso-center), not finer
    polish_level = renderer_level(renderer, options.polish_volume_level)
    polish_voxel_mm = float(renderer.level_volume(polish_level).spacing_mm.max())
    pixel_mm = iso_pixel_mm(view.geometry, level_factor(view.geometry, options.polish_image_px, polish_voxel_mm))
    step, bound = options.depth_scan_step_mm, options.depth_bound_mm
    tz, moves = float(tz_mm), []
    x = np.asarray(x, dtype=np.float64)
    for n in range(options.depth_rounds):
        if monitor.stopped:
            break
        half = bound if n == 0 else options.depth_rescan_mm
        # the offsets that stay within the bound, from the estimate's tz
        lo, hi = max(-half, -bound - tz), min(half, bound - tz)
        offsets = tuple(float(o) for o in np.arange(math.ceil(lo / step) * step, hi + 1e-9, step))
        if len(offsets) < 3:
            break
        motion = six.motion(np.insert(x, 2, tz))
        scan = depth_scan(renderer, view, motion, offsets_mm=offsets, image_px=options.depth_image_px,
                          volume_level=level, margin_mm=options.margin_mm(len(options.levels)),
                          pixel_at_iso_mm=pixel_mm)  # fmt: skip
        with monitor.lock:
            monitor.drr_count += scan.drr_count
        move = float(np.clip(tz + scan.tz_mm, -bound, bound)) - tz
        moves.append(move)
        if abs(move) < options.depth_move_mm and not (n == 0 and options.depth_first_polish):
            break
        tz += move
        problem = LevelProblem.prepare(renderer, (view,), image_px=options.polish_image_px,
                                       volume_level=options.polish_volume_level, motion=six.motion(np.insert(x, 2, tz)),
                                       margin_mm=options.margin_mm(len(options.levels)))  # fmt: skip
        held = _HeldTz(six, tz)
        polish_options = replace(options, polish_reach=options.depth_polish_reach,
                                 polish_evaluations=options.depth_polish_evaluations)  # fmt: skip
        best = _polish(problem, held, stage, x, polish_options, monitor)
        x, f = best.x, best.fun
    return DepthCorrection(x, f, tz, tuple(moves))


#: A rotation check's polish that ends more than this far from the estimate (deg) found a
#: rival optimum, not the estimate's own peak.
RIVAL_DISTINCT_DEG = 2.0


@dataclass(frozen=True)
class RotationCheck:
    """What :func:`rotation_check` (and the rounds of :attr:`RegistrationOptions.rotation_check`)
    found. The check keeps the best of the estimate and its polishes (``x``, ``fun``;
    ``moved_deg`` from the estimate); ``rival_gain`` is the best measure among the other optima
    it reached (the polishes' ends and the estimate, those more than ``RIVAL_DISTINCT_DEG`` from
    the kept one) minus the kept one's, relative to it: <= 0, 0 a tie; None when every polish
    came back to the kept one. After the rounds (:func:`_check_rotations`) a ``rival_gain``
    > 0 says the last check moved the estimate to a rival no check has seen since (its gain
    over the estimate it left)."""

    rival_gain: float | None
    moved_deg: float
    x: Array
    fun: float
    f_estimate: float
    checks: int = 1
    moves: int = 0

    def to_dict(self) -> dict:
        return {
            "rival_gain": self.rival_gain,
            "moved_deg": self.moved_deg,
            "checks": self.checks,
            "moves": self.moves,
        }


def rotation_check(
    renderer: DRRRenderer,
    view: XRayImage,
    space: SearchSpace,
    x: Array,
    tz_mm: float,
    options: RegistrationOptions,
    monitor: _Monitor,
    stage: int,
) -> RotationCheck:
    """Polish the five parameters (tz held at ``tz_mm``) from the estimate ``x`` (``space``'s,
    five parameters) with the view's rx or ry turned by +- ``options.rotation_check_deg``, at
    the polish's level, and compare with the estimate's measure there (one support mask, the
    estimate's). Deterministic; the DRRs are counted in ``monitor``."""
    six = replace(space, names=SIX_PARAMETERS)
    held = _HeldTz(six, tz_mm)
    x = np.asarray(x, dtype=np.float64)
    m_est = held.motion(x)
    problem = LevelProblem.prepare(renderer, (view,), image_px=options.polish_image_px,
                                   volume_level=options.polish_volume_level, motion=m_est,
                                   margin_mm=options.margin_mm(len(options.levels)))  # fmt: skip
    f_est = _cost(problem, held, monitor, None)(x)
    check_options = replace(options, polish_reach=options.rotation_check_reach,
                            polish_evaluations=options.rotation_check_evaluations)  # fmt: skip
    d = options.rotation_check_deg
    ends: list[AnnealResult] = []
    for slot in (2, 3):  # rx, ry of the five parameters
        for sign in (1.0, -1.0):
            if monitor.stopped:
                break
            start = x.copy()
            start[slot] += sign * d
            start = np.clip(start, held.bounds[:, 0], held.bounds[:, 1])
            ends.append(_polish(problem, held, stage, start, check_options, monitor))
    best = min(ends, key=lambda r: r.fun) if ends else None
    if best is not None and best.fun < f_est:
        chosen_x, chosen_f = np.asarray(best.x, dtype=np.float64), float(best.fun)
    else:
        chosen_x, chosen_f = x, f_est
    m_chosen = held.motion(chosen_x)
    moved = rotation_angle_deg(m_chosen @ invert_rigid(m_est))
    scale = max(abs(chosen_f), 1e-12)
    # the other optima the polishes (and the estimate itself) reached, against the chosen one
    others = [(held.motion(r.x), r.fun) for r in ends] + [(m_est, f_est)]
    gains = [(chosen_f - fun) / scale for m, fun in others
             if rotation_angle_deg(m @ invert_rigid(m_chosen)) > RIVAL_DISTINCT_DEG]  # fmt: skip
    return RotationCheck(max(gains) if gains else None, moved, chosen_x, chosen_f, f_est)


def _check_rotations(
    inputs: Inputs, space: SearchSpace, x: Array, f: float, depth: DepthCorrection,
    options: RegistrationOptions, monitor: _Monitor, stage: int,
) -> tuple[Array, float, DepthCorrection, RotationCheck]:  # fmt: skip
    """The rounds of the rotation check (:attr:`RegistrationOptions.rotation_check`): move to a
    better polish when one is found (and correct the depth again from it when it is a rival,
    more than ``RIVAL_DISTINCT_DEG`` away), check again, ``rotation_check_rounds`` at most."""
    renderer, view = inputs.renderer, inputs.views[0]
    moves, check = 0, None
    for n in range(options.rotation_check_rounds):
        check = rotation_check(renderer, view, space, x, depth.tz_mm, options, monitor, stage)
        if not check.fun < check.f_estimate or monitor.stopped:
            break
        x, f, moves = check.x, check.fun, moves + 1
        if check.moved_deg <= RIVAL_DISTINCT_DEG:
            break  # the estimate's own peak, polished further: nothing else to correct
        again = depth_correct(renderer, view, space, x, f, options, monitor, stage, tz_mm=depth.tz_mm)
        depth = DepthCorrection(again.x, again.fun, again.tz_mm, depth.moves_mm + again.moves_mm)
        x, f = depth.x, depth.fun
        if n == options.rotation_check_rounds - 1:
            # the last check moved the estimate to a rival, which no check has seen since: its
            # gain over the estimate it left is the evidence (> 0)
            check = replace(check, rival_gain=(check.f_estimate - check.fun) / max(abs(check.fun), 1e-12))
    assert check is not None
    return x, f, depth, replace(check, checks=n + 1, moves=moves)


class _HeldTz:
    """The five-parameter view of a six-parameter space with tz held: what :func:`_polish` and
    :func:`_cost` need (``motion``, ``bounds``, ``is_translation``)."""

    def __init__(self, six: SearchSpace, tz: float) -> None:
        self.six, self.tz = six, float(tz)
        five = replace(six, names=FIVE_PARAMETERS)
        self.bounds = five.bounds
        self.is_translation = five.is_translation
        self.names = FIVE_PARAMETERS

    def motion(self, x: ArrayLike) -> Array:
        return self.six.motion(np.insert(np.asarray(x, dtype=np.float64), 2, self.tz))


def _result(inputs: Inputs, space: SearchSpace, x: Array, f: float, monitor: _Monitor,
            vessel_points_mm: ArrayLike | None, seconds: float, depth: DepthCorrection | None = None,
            check: RotationCheck | None = None) -> RegistrationResult:  # fmt: skip
    m_est = space.motion(x) if depth is None else _HeldTz(replace(space, names=SIX_PARAMETERS), depth.tz_mm).motion(x)
    res = None
    if inputs.truth is not None:
        res = residuals(m_est, inputs.truth, space.frame, vessel_points_mm, optimizes_tz=space.optimizes_tz)
    return RegistrationResult(
        patient_motion=m_est,
        similarity=-f,
        similarity_trace=monitor.trace,
        drr_count=monitor.drr_count,
        seconds=seconds,
        stopped=monitor.stopped,
        offsets=x,
        geometry=space.frame,
        volume_label=inputs.volume.label,
        residual=res,
        parameters=space.names,
        views=tuple(v.geometry for v in inputs.views),
        capture_motions=tuple(monitor.captures),
        at_bounds=tuple(space.names[i] for i in parameters_at_bounds(x, space.bounds)),
        depth_tz_mm=None if depth is None else depth.tz_mm,
        depth_moves_mm=() if depth is None else depth.moves_mm,
        rotation_check=check,
    )
