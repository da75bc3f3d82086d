"""How a registration searches: its levels and the options of every stage."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from registration.core.anneal import Schedule

Array = NDArray[np.float64]


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
