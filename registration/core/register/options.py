"""How a registration searches: its levels and the options of every stage.

Each stage's options are one frozen dataclass (:class:`PolishOptions`, :class:`BiplaneOptions`,
:class:`DepthOptions`, :class:`RotationCheckOptions`), validated when made; units are in the
names (``_mm``, ``_deg``, ``_px``). Why a default is what it is: ``docs/decisions/``.

:class:`RegistrationOptions` also takes the flat keywords of earlier versions
(``polish_evaluations=40``, ``depth_correction=False``, ``rotation_check_reach=(2.0, 9.0)``, ...:
:data:`FLAT_NAMES`) and reads them back as attributes, so existing callers keep working.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import MISSING, dataclass, field, fields, replace
from typing import Any

from registration.core.anneal import Schedule
from registration.core.register.result import SINGLE_PLANE_MAX_TURN_DEG


@dataclass(frozen=True)
class Level:
    """One annealing level of the coarse-to-fine search.

    ``image_px``: the X-ray image is block-averaged to about this many pixels across (>= 16);
    ``volume_level``: the renderer's pyramid level (0 = full resolution, 1 = half, ...);
    ``restarts``: independent annealing runs from the level's start, the best continues (>= 1).
    """

    image_px: int
    volume_level: int
    schedule: Schedule
    restarts: int = 1


#: The capture's annealing schedule. Steps are for (tx, ty, rx, ry, rz); a six-parameter search
#: steps tz as tx.
CAPTURE_SCHEDULE = Schedule(step=(4.0, 4.0, 2.0, 2.0, 2.0), stages=14, moves_per_stage=14, cooling=0.75)

#: Four capture runs at 64 px on the quarter-resolution volume: each biplane plane's capture and
#: the pair's, and the tracker's re-capture (docs/decisions/2026-12-02-registration-levels.md).
CAPTURE_64 = Level(64, 2, CAPTURE_SCHEDULE, restarts=4)

#: The refinement's annealing schedule after a capture (one view's second level; shorter, each
#: biplane plane's capture runs).
REFINE_SCHEDULE = Schedule(step=(1.0, 1.0, 0.7, 0.7, 0.7), stages=8, moves_per_stage=10, cooling=0.7)

#: Each biplane plane's own capture: the one-view capture's 32 px images of the eighth-resolution
#: volume (docs/decisions/2026-12-05-plane-captures-at-32-px.md).
PLANE_CAPTURE_32 = Level(32, 3, CAPTURE_SCHEDULE, restarts=2)
#: Each of those runs then goes on briefly at 64 px of the quarter-resolution volume before the
#: planes are compared.
PLANE_REFINE_64 = Level(64, 2, replace(REFINE_SCHEDULE, stages=4))


def _default_levels() -> tuple[Level, ...]:
    # capture: four runs at 32 px on the eighth-resolution volume (one view;
    # docs/decisions/2026-12-05-capture-level.md); refine: about 64 px on the quarter-resolution
    # volume (docs/decisions/2026-12-05-refinement-images.md).
    return (
        Level(32, 3, CAPTURE_SCHEDULE, restarts=4),
        Level(64, 2, REFINE_SCHEDULE),
    )


def _positive(owner: str, **values: float | None) -> None:
    for name, value in values.items():
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{owner}.{name} must be a positive number, got {value}")


def _at_least(owner: str, low: int, **values: int | None) -> None:
    for name, value in values.items():
        if value is not None and value < low:
            raise ValueError(f"{owner}.{name} must be >= {low}, got {value}")


def _reach(owner: str, mm: float | None, deg: float | None, *, optional: bool) -> None:
    if (mm is None) != (deg is None) or (mm is None and not optional):
        raise ValueError(f"{owner} needs both reach_mm and reach_deg{' or neither' if optional else ''}")
    _positive(owner, reach_mm=mm, reach_deg=deg)


@dataclass(frozen=True)
class PolishOptions:
    """The local polish after the annealing: Powell's bounded line searches near the estimate
    (docs/decisions/2026-12-02-polish-reach.md)."""

    #: Whether the polish runs (default True; without it no depth correction or rotation check).
    enabled: bool = True
    #: Evaluation budget (default 40, >= 1).
    evaluations: int = 40
    #: Image size compared, in pixels across (default 128, >= 16).
    image_px: int = 128
    #: Renderer pyramid level (default 1, half resolution; >= 0).
    volume_level: int = 1
    #: Powell's first step for translations, mm (default 0.5, > 0).
    step_mm: float = 0.5
    #: Powell's first step for rotations, degrees (default 0.3, > 0).
    step_deg: float = 0.3
    #: Searched translation either side of the start, mm (default 2.0, > 0; None with
    #: ``reach_deg`` None: the whole search range).
    reach_mm: float | None = 2.0
    #: Searched rotation either side of the start, degrees (default 1.5, > 0; None: see above).
    reach_deg: float | None = 1.5
    #: Powell's tolerance on the parameters (default 0.1, > 0).
    xtol: float = 0.1

    def __post_init__(self) -> None:
        _at_least("PolishOptions", 1, evaluations=self.evaluations)
        _at_least("PolishOptions", 16, image_px=self.image_px)
        _at_least("PolishOptions", 0, volume_level=self.volume_level)
        _positive("PolishOptions", step_mm=self.step_mm, step_deg=self.step_deg, xtol=self.xtol)
        _reach("PolishOptions", self.reach_mm, self.reach_deg, optional=True)


@dataclass(frozen=True)
class BiplaneOptions:
    """Two or more views (six parameters): each plane's own capture, then the pair's search
    (docs/decisions/2026-12-02-biplane-captures-and-polishes.md)."""

    #: Start with plane A's own single-plane capture when ``plane_captures`` is off (default True).
    plane_a_capture: bool = True
    #: Each of the first two planes runs its own single-plane capture, side by side, combined
    #: geometrically into the pair's start (default True; replaces ``plane_a_capture``).
    plane_captures: bool = True
    #: The level of each plane's capture, of the pair's capture when the planes disagree and of
    #: the coarse polish (default :data:`CAPTURE_64`; None: the first of the registration's levels).
    capture: Level | None = CAPTURE_64
    #: Capture runs per plane and round (default 2, >= 1).
    plane_capture_runs: int = 2
    #: The level of each plane's own capture (default :data:`PLANE_CAPTURE_32`; None:
    #: :attr:`capture`; a volume too small for its volume level captures at :attr:`capture`).
    plane_capture: Level | None = PLANE_CAPTURE_32
    #: Each plane's capture runs go on at this level, one run from each end, before the planes
    #: are compared (default :data:`PLANE_REFINE_64`; None: none).
    plane_refine: Level | None = PLANE_REFINE_64
    #: At most this many capture runs per pair level (default 2, >= 1; None: as the level says).
    pair_capture_runs: int | None = 2
    #: The pair's annealing levels when the planes agree (default (): straight to the polishes;
    #: None: the levels after the capture).
    pair_levels: tuple[Level, ...] | None = ()
    #: The pair's polish budget (default 30, >= 1; None: the single-plane polish's).
    polish_evaluations: int | None = 30
    #: The pair's polish reach either side of its start, mm and degrees (default 2.0 and 1.5,
    #: > 0; both None: the search range).
    polish_reach_mm: float | None = 2.0
    polish_reach_deg: float | None = 1.5
    #: Powell's tolerance of the pair's polishes (default 0.1, > 0).
    polish_xtol: float = 0.1
    #: The coarse polish before the pair's polish, on the capture level's images (default 60
    #: evaluations, >= 0; 0: none).
    coarse_polish_evaluations: int = 60
    #: Its reach, mm and degrees (default 4.0 and 3.0, > 0; both None: the search range).
    coarse_polish_reach_mm: float | None = 4.0
    coarse_polish_reach_deg: float | None = 3.0
    #: The pair's measure weights each view's gradient difference by the share of its field that
    #: it compares (default True; False: the plain mean;
    #: docs/decisions/2026-12-06-planes-weighted-by-field-share.md).
    field_share_weights: bool = True

    def __post_init__(self) -> None:
        _at_least("BiplaneOptions", 1, plane_capture_runs=self.plane_capture_runs,
                  pair_capture_runs=self.pair_capture_runs, polish_evaluations=self.polish_evaluations)  # fmt: skip
        _at_least("BiplaneOptions", 0, coarse_polish_evaluations=self.coarse_polish_evaluations)
        _positive("BiplaneOptions", polish_xtol=self.polish_xtol)
        _reach("BiplaneOptions.polish", self.polish_reach_mm, self.polish_reach_deg, optional=True)
        _reach("BiplaneOptions.coarse_polish", self.coarse_polish_reach_mm, self.coarse_polish_reach_deg,
               optional=True)  # fmt: skip
        own = [lv for lv in (self.capture, self.plane_capture, self.plane_refine) if lv is not None]
        for level in (*(self.pair_levels or ()), *own):
            _check_level(level)


@dataclass(frozen=True)
class DepthOptions:
    """One view: the depth correction after the polish (scan along the beam, move tz, polish;
    docs/decisions/2026-12-02-depth-correction.md)."""

    #: Whether it runs (default True; False: the paper's five-parameter result).
    enabled: bool = True
    #: Scans at most (default 3, >= 1).
    rounds: int = 3
    #: Another scan follows while one moves tz by at least this, mm (default 1.5, > 0).
    move_mm: float = 1.5
    #: tz stays within this of the initial pose, mm; the first scan's half width (default 25, > 0).
    bound_mm: float = 25.0
    #: The scan's volume level: the prepared level whose voxel is nearest this, mm (default 1.0, > 0).
    voxel_mm: float = 1.0
    #: No correction when that level's voxel is coarser than this, mm (default 3.0, > 0).
    max_voxel_mm: float = 3.0
    #: The volume's own level 0 is prepared for the scan too when the volume has at most this many
    #: voxels (default 2**22: a 128^3 3DRA, not a 256^3 one or a CT; 0: never).
    level0_max_voxels: int = 2**22
    #: The scan's image size, pixels across (default 128, >= 16).
    image_px: int = 128
    #: The scan's step along the beam, mm (default 2.0, > 0).
    scan_step_mm: float = 2.0
    #: Half width of the scans after the first, mm (default 12, > 0).
    rescan_mm: float = 12.0
    #: The correction's polishes: reach either side, mm and degrees (default 2.0 and 5.0, > 0).
    polish_reach_mm: float = 2.0
    polish_reach_deg: float = 5.0
    #: Their budget (default 60, >= 1).
    polish_evaluations: int = 60
    #: Polish after the first scan even when it moved tz by less than ``move_mm`` (default True).
    first_polish: bool = True
    #: ... unless the estimate's out-of-plane rotation margin (rx, ry turned +-3 deg, relative)
    #: reaches this (default 0.008, the rotation check's): its rotation is not in doubt, and tz
    #: stays (None: always polish).
    first_polish_skip_margin: float | None = 0.008
    #: The scans evaluate every this-th offset, then climb offset by offset to the peak (default 6,
    #: docs/decisions/2026-12-05-scan-stride.md; 1: every offset).
    scan_stride: int = 6
    #: Scan once before the polish (+- ``bound_mm``), so that the polish runs at the corrected
    #: depth and the scans after it are rescans (default True;
    #: docs/decisions/2026-12-06-depth-scan-first.md).
    scan_first: bool = True
    #: A scan's move below ``move_mm`` still moves tz, without a polish of its own (default True;
    #: False: tz stays where it was).
    keep_small_moves: bool = True
    #: How far from the initial pose a rescan may still walk tz, mm (default 40; None: ``bound_mm``;
    #: never less than it; docs/decisions/2026-12-06-far-start-depth.md). An estimate that ends
    #: beyond ``bound_mm`` (within a step of it) is still withheld: the further reach finds the
    #: depth of a patient who lies there, it does not make it trusted.
    reach_mm: float | None = 40.0
    #: Scan once more right after the capture level, before the finer annealing (+- ``bound_mm``),
    #: so that the finer levels fit the plane at the corrected depth (default False).
    scan_after_capture: bool = False
    #: One view's search that starts from an image shift of at least this, mm, scans after the
    #: capture level (default 25, the shift beyond which the confidence withholds one view's
    #: estimate anyway; None: never).
    far_start_mm: float | None = 25.0
    #: One view's estimate this far or further from the machine-based pose (mm at the iso-center),
    #: whose capture runs disagreed, is searched again from far along the beam
    #: (:mod:`registration.core.register.beam_restart`; default 20; None: never).
    restart_beyond_mm: float | None = 20.0
    #: ... when the far look along the beam (``depth_far``) finds the measure this close to the
    #: estimate's or closer (its gain above this; default -0.1: a peak standing out more is not in
    #: doubt) ...
    restart_far_gain: float = -0.1
    #: ... and that search's estimate is kept when the depth scan's high-passed measure is higher
    #: by at least this (default 0.01, >= 0).
    restart_gain: float = 0.01

    def __post_init__(self) -> None:
        _at_least("DepthOptions", 1, rounds=self.rounds, polish_evaluations=self.polish_evaluations)
        _at_least("DepthOptions", 16, image_px=self.image_px)
        _at_least("DepthOptions", 0, level0_max_voxels=self.level0_max_voxels)
        _at_least("DepthOptions", 1, scan_stride=self.scan_stride)
        skip = self.first_polish_skip_margin
        if skip is not None and not (math.isfinite(skip) and skip >= 0):
            raise ValueError(f"DepthOptions.first_polish_skip_margin must be >= 0 or None, got {skip}")
        _positive("DepthOptions", move_mm=self.move_mm, bound_mm=self.bound_mm, voxel_mm=self.voxel_mm,
                  max_voxel_mm=self.max_voxel_mm, scan_step_mm=self.scan_step_mm, rescan_mm=self.rescan_mm)  # fmt: skip
        _reach("DepthOptions.polish", self.polish_reach_mm, self.polish_reach_deg, optional=False)
        if self.reach_mm is not None:
            _positive("DepthOptions", reach_mm=self.reach_mm)
        if self.far_start_mm is not None:
            _positive("DepthOptions", far_start_mm=self.far_start_mm)
        if self.restart_beyond_mm is not None:
            _positive("DepthOptions", restart_beyond_mm=self.restart_beyond_mm)
        if not math.isfinite(self.restart_far_gain):
            raise ValueError(f"DepthOptions.restart_far_gain must be a finite number, got {self.restart_far_gain}")
        if not (math.isfinite(self.restart_gain) and self.restart_gain >= 0):
            raise ValueError(f"DepthOptions.restart_gain must be >= 0, got {self.restart_gain}")

    @property
    def walk_mm(self) -> float:
        """How far from the initial pose tz may go (``reach_mm``, at least ``bound_mm``)."""
        return self.bound_mm if self.reach_mm is None else max(self.bound_mm, self.reach_mm)


@dataclass(frozen=True)
class RotationCheckOptions:
    """One view, after the depth correction: polishes from the estimate with rx or ry turned
    (docs/decisions/2026-12-02-rotation-check.md)."""

    #: Whether it runs (default True; needs the depth correction).
    enabled: bool = True
    #: The turn of rx or ry at each of the four starts, degrees (default 6.0, in (0, 15]).
    turn_deg: float = 6.0
    #: Each polish's reach either side of the estimate, mm and degrees (default 2.0 and 9.0, > 0).
    reach_mm: float = 2.0
    reach_deg: float = 9.0
    #: Each polish's budget (default 40, >= 1).
    evaluations: int = 40
    #: Checks at most (default 3, >= 1).
    rounds: int = 3
    #: No polish when the estimate's relative margin over rx and ry turned by 3 degrees reaches
    #: this (a sharp peak of its own; None: always check).
    skip_margin: float | None = 0.008

    def __post_init__(self) -> None:
        if self.skip_margin is not None and not (math.isfinite(self.skip_margin) and self.skip_margin >= 0):
            raise ValueError(f"RotationCheckOptions.skip_margin must be >= 0 or None, got {self.skip_margin}")
        if not (math.isfinite(self.turn_deg) and 0 < self.turn_deg <= 15):
            raise ValueError(f"RotationCheckOptions.turn_deg must lie in (0, 15], got {self.turn_deg}")
        _reach("RotationCheckOptions", self.reach_mm, self.reach_deg, optional=False)
        _at_least("RotationCheckOptions", 1, evaluations=self.evaluations, rounds=self.rounds)


@dataclass(frozen=True)
class StartOptions:
    """Where the search starts: the machine-based pose, or the image shift beyond the clinical
    offsets (:mod:`registration.core.register.shift_start`), and from there a search box that
    walks when the estimate ends on its bounds (:mod:`registration.core.register.walk`)."""

    #: Whether the box walks and the shifted start is tried (default True; the walk runs only
    #: when an estimate ends at the bounds).
    enabled: bool = True
    #: Restarts at most, each from the last estimate with the box centred there (default 3, >= 1).
    walk_hops: int = 3
    #: Start from the image shift found by phase correlation when it moves the start by at least
    #: this much, mm (default 25.0, > 0; None: never; :mod:`registration.core.register.shift_start`).
    shift_mm: float | None = 25.0
    #: Search again from the image shift when the first estimate leaves the anatomy at least this
    #: far from where the image shows it, mm, and keep the better measure (default 5.0, > 0;
    #: None: never; :func:`registration.core.register.shift_start.look_again`).
    recheck_mm: float | None = 5.0
    #: Two views' estimate whose search started away from the machine-based pose (image shift or
    #: walk) is polished once more on the views' full images and the volume's level 0
    #: (:mod:`registration.core.register.fine_polish`, COBYQA): evaluations at most, each
    #: time it runs (default 120, >= 0; 0: never).
    fine_polish_evaluations: int = 120
    #: The fine polish also runs when two views' estimate lies at least this far from the
    #: machine-based pose (mm at the iso-center) although its search started there (default
    #: 25.0, > 0; None: only after a start away from it).
    fine_polish_beyond_mm: float | None = 25.0
    #: Before it, the estimate is moved along each view's central ray within this reach (mm,
    #: 1.5 mm steps, at the fine polish's images and level) to where the views' measure is best
    #: (default 15.0, > 0; None: never): another view's depth that the search left off.
    beam_scan_mm: float | None = 15.0
    #: The scan's volume level; its images are the fine polish's halved once per level (default
    #: 0: the fine polish's images and level, >= 0).
    beam_scan_level: int = 0
    #: After the fine polish, the estimate is moved along each view's central ray within this
    #: reach (mm; a bounded line search to 0.1 mm at the fine polish's images and level 0) to
    #: where the views' measure is best (default 3.0, > 0; None: never).
    beam_line_mm: float | None = 3.0
    #: Its image size, pixels across (default 256, >= 16).
    fine_polish_px: int = 256
    #: Its reach either side of the estimate, mm and degrees (default 10.0 and 5.0, > 0).
    fine_polish_reach_mm: float = 10.0
    fine_polish_reach_deg: float = 5.0
    #: Its final trust-region radius, in first steps (0.5 mm, 0.3 deg) (default 0.05, > 0).
    fine_polish_xtol: float = 0.05
    #: Two views' estimate whose search started from the image shift is compared with a candidate
    #: searched from that start over the translations alone, then polished, and the better
    #: measure kept (:mod:`registration.core.register.translation_first`): the translation
    #: search's evaluations (default 80, >= 0; 0: never).
    translation_first_evaluations: int = 80
    #: The initial motion is a landmark start (:mod:`registration.core.landmarks`), not the
    #: machine-based pose: two views' estimate is then fine-polished as one from a start away
    #: from the machine-based pose (default False).
    from_landmarks: bool = False
    #: Two or more views from landmarks (``register(landmarks=...)``) whose estimate moves them
    #: further than their check allows (``LANDMARK_MOVE_MM``): a second search from their start
    #: (no image shift, no second search from it), where a pose beyond that costs this much more
    #: per mm squared beyond it, is kept instead and shown for a check by eye (default 0.05, > 0;
    #: None: never; :mod:`registration.core.register.landmark_hold`).
    landmark_wall: float | None = 0.05
    #: One view from landmarks: the depth correction may move tz this far from their start (mm;
    #: default 50.0, > 0; None: ``DepthOptions.bound_mm``): four picks on one image put the
    #: depth 15-50 mm off, beyond the correction's usual 25 mm.
    landmark_depth_mm: float | None = 50.0

    def __post_init__(self) -> None:
        _at_least("StartOptions", 1, walk_hops=self.walk_hops)
        _at_least("StartOptions", 0, fine_polish_evaluations=self.fine_polish_evaluations,
                  translation_first_evaluations=self.translation_first_evaluations)  # fmt: skip
        _at_least("StartOptions", 16, fine_polish_px=self.fine_polish_px)
        _at_least("StartOptions", 0, beam_scan_level=self.beam_scan_level)
        _positive("StartOptions", shift_mm=self.shift_mm, recheck_mm=self.recheck_mm,
                  fine_polish_beyond_mm=self.fine_polish_beyond_mm, beam_scan_mm=self.beam_scan_mm,
                  beam_line_mm=self.beam_line_mm,
                  fine_polish_reach_mm=self.fine_polish_reach_mm,
                  fine_polish_reach_deg=self.fine_polish_reach_deg,
                  fine_polish_xtol=self.fine_polish_xtol, landmark_wall=self.landmark_wall,
                  landmark_depth_mm=self.landmark_depth_mm)  # fmt: skip

    def describe(self) -> str:
        """One line per rule that moves the search's start (what ``register --explain`` prints
        after the plan)."""
        if not self.enabled:
            return "the search starts at the machine-based pose and stays in its box"
        lines = []
        if self.shift_mm is not None:
            lines.append(f"start from the image shift when it moves the patient {self.shift_mm:g} mm or more")
        lines.append(f"the box walks from an estimate on its bounds, up to {self.walk_hops} times")
        if self.recheck_mm is not None:
            lines.append(
                f"a second search from the image shift when the estimate leaves the anatomy {self.recheck_mm:g} mm "
                f"or more from where the image shows it, or one view's estimate turns the head more than "
                f"{SINGLE_PLANE_MAX_TURN_DEG:g} deg (the better fit kept)"
            )
        if self.shift_mm is not None and self.translation_first_evaluations:
            lines.append(
                f"two views from the image shift: a second candidate searched over the translations alone "
                f"({self.translation_first_evaluations} evaluations at 64 px), polished at 128 px, kept when it "
                "fits better there"
            )
        if self.fine_polish_evaluations:
            away = "landmarks" if self.from_landmarks else "a start away from the machine-based pose"
            if self.fine_polish_beyond_mm is not None and not self.from_landmarks:
                away += f" or {self.fine_polish_beyond_mm:g} mm or more from it"
            if self.beam_scan_mm is not None:
                lines.append(
                    f"two views' estimate from {away}: moved along each view's beam within +-{self.beam_scan_mm:g} mm "
                    f"to where the views fit best, at {max(16, self.fine_polish_px >> self.beam_scan_level)} px, "
                    f"volume level {self.beam_scan_level}"
                )
            lines.append(
                f"two views' estimate from {away}: a fine polish at "
                f"{self.fine_polish_px} px, volume level 0, {self.fine_polish_evaluations} evaluations over "
                f"+-{self.fine_polish_reach_mm:g} mm / {self.fine_polish_reach_deg:g} deg (COBYQA)"
            )
            if self.beam_line_mm is not None:
                lines.append(
                    f"after it, a line search along each view's beam within +-{self.beam_line_mm:g} mm at "
                    f"{self.fine_polish_px} px, volume level 0"
                )
        if self.from_landmarks and self.landmark_depth_mm is not None:
            reach = f"+-{self.landmark_depth_mm:g} mm"
            lines.append(f"one view from landmarks: the depth correction reaches {reach} from their start")
        if self.from_landmarks and self.landmark_wall is not None:
            lines.append(
                "two views from landmarks: when the estimate moves them more than their check allows, a second "
                f"search from their start, held near the poses they allow (a pose beyond costs {self.landmark_wall:g} "
                "per mm^2), kept instead and shown for a check by eye"
            )
        return "\n".join(lines)


def _check_level(level: Level) -> None:
    if not isinstance(level, Level):
        raise TypeError(f"levels must be Level(image_px, volume_level, schedule, restarts), got {type(level).__name__}")
    if level.image_px < 16:
        raise ValueError(f"image_px must be >= 16, got {level.image_px}")
    if level.volume_level < 0:
        raise ValueError(f"volume_level must be >= 0, got {level.volume_level}")
    if level.restarts < 1:
        raise ValueError(f"restarts must be >= 1, got {level.restarts}")


#: The flat keywords of earlier versions: name -> (group, field) or (group, (mm field, deg field)).
FLAT_NAMES: dict[str, tuple[str, str | tuple[str, str]]] = {
    "polish_evaluations": ("polish", "evaluations"),
    "polish_image_px": ("polish", "image_px"),
    "polish_volume_level": ("polish", "volume_level"),
    "polish_step_mm": ("polish", "step_mm"),
    "polish_step_deg": ("polish", "step_deg"),
    "polish_reach": ("polish", ("reach_mm", "reach_deg")),
    "polish_xtol": ("polish", "xtol"),
    "multi_view_restarts": ("biplane", "pair_capture_runs"),
    "plane_a_capture": ("biplane", "plane_a_capture"),
    "plane_captures": ("biplane", "plane_captures"),
    "plane_capture_runs": ("biplane", "plane_capture_runs"),
    "pair_levels": ("biplane", "pair_levels"),
    "pair_polish_evaluations": ("biplane", "polish_evaluations"),
    "pair_polish_reach": ("biplane", ("polish_reach_mm", "polish_reach_deg")),
    "pair_polish_xtol": ("biplane", "polish_xtol"),
    "pair_coarse_polish_evaluations": ("biplane", "coarse_polish_evaluations"),
    "pair_coarse_polish_reach": ("biplane", ("coarse_polish_reach_mm", "coarse_polish_reach_deg")),
    "depth_correction": ("depth", "enabled"),
    "depth_rounds": ("depth", "rounds"),
    "depth_move_mm": ("depth", "move_mm"),
    "depth_bound_mm": ("depth", "bound_mm"),
    "depth_voxel_mm": ("depth", "voxel_mm"),
    "depth_max_voxel_mm": ("depth", "max_voxel_mm"),
    "depth_level0_max_voxels": ("depth", "level0_max_voxels"),
    "depth_image_px": ("depth", "image_px"),
    "depth_scan_step_mm": ("depth", "scan_step_mm"),
    "depth_rescan_mm": ("depth", "rescan_mm"),
    "depth_polish_reach": ("depth", ("polish_reach_mm", "polish_reach_deg")),
    "depth_polish_evaluations": ("depth", "polish_evaluations"),
    "depth_first_polish": ("depth", "first_polish"),
    "depth_first_polish_skip_margin": ("depth", "first_polish_skip_margin"),
    "depth_scan_stride": ("depth", "scan_stride"),
    "depth_scan_first": ("depth", "scan_first"),
    "depth_keep_small_moves": ("depth", "keep_small_moves"),
    "depth_scan_after_capture": ("depth", "scan_after_capture"),
    "depth_reach_mm": ("depth", "reach_mm"),
    "depth_far_start_mm": ("depth", "far_start_mm"),
    "rotation_check_deg": ("rotation_check", "turn_deg"),
    "rotation_check_reach": ("rotation_check", ("reach_mm", "reach_deg")),
    "rotation_check_evaluations": ("rotation_check", "evaluations"),
    "rotation_check_rounds": ("rotation_check", "rounds"),
    "rotation_check_skip_margin": ("rotation_check", "skip_margin"),
}
_GROUPS = {"polish": PolishOptions, "biplane": BiplaneOptions, "depth": DepthOptions,
           "rotation_check": RotationCheckOptions, "start": StartOptions}  # fmt: skip


@dataclass(frozen=True, init=False)
class RegistrationOptions:
    """How a registration searches; the defaults are the benchmarked configuration.

    ``RegistrationOptions(bound_mm=20.0, depth=DepthOptions(rounds=2))``; the flat keywords of
    :data:`FLAT_NAMES` are taken too (``polish=False`` / ``depth_correction=False`` /
    ``rotation_check=False`` switch a stage off) and read back as attributes.
    """

    #: The annealing levels, coarse to fine (default: a 32 px capture, a 64 px refinement; two or
    #: more views capture at :attr:`BiplaneOptions.capture`).
    levels: tuple[Level, ...] = field(default_factory=_default_levels)
    #: Search range either side of the initial pose, mm (default 30, > 0).
    bound_mm: float = 30.0
    #: Search range either side of the initial pose, degrees (default 15, > 0).
    bound_deg: float = 15.0
    #: Threads for capture runs side by side (default None: one per core).
    threads: int | None = None
    #: Per level, then the polish: compare only pixels whose rays pass at least this far inside
    #: the volume's support, mm (default (15, 6, 4), >= 0; None: the whole field).
    support_margin_mm: tuple[float, ...] | None = (15.0, 6.0, 4.0)
    #: Optimise tz (six parameters); default None: only with two or more views.
    optimize_tz: bool | None = None
    polish: PolishOptions = field(default_factory=PolishOptions)
    biplane: BiplaneOptions = field(default_factory=BiplaneOptions)
    depth: DepthOptions = field(default_factory=DepthOptions)
    rotation_check: RotationCheckOptions = field(default_factory=RotationCheckOptions)
    start: StartOptions = field(default_factory=StartOptions)
    #: The image's intensities (:mod:`registration.core.intensity`; default "auto": matched to
    #: the DRR's when the reader could not know them to be line integrals, display-processed
    #: pixels or a missing relationship tag; "match": always; "as-read": never).
    intensity: str = "auto"

    def __init__(self, **kwargs: Any) -> None:
        own = {f.name: f for f in fields(self)}
        unknown = set(kwargs) - set(own) - set(FLAT_NAMES)
        if unknown:
            raise TypeError(f"RegistrationOptions got unexpected options {sorted(unknown)}")
        values: dict[str, Any] = {}
        for name, f in own.items():
            given = kwargs.get(name, MISSING)
            if given is MISSING or (name in _GROUPS and isinstance(given, bool)):
                given = f.default_factory() if f.default_factory is not MISSING else f.default
            values[name] = given
        for group in _GROUPS:  # polish=False, rotation_check=False: the stage switched off
            if isinstance(kwargs.get(group), bool):
                values[group] = replace(values[group], enabled=kwargs[group])
        flat = {k: v for k, v in kwargs.items() if k in FLAT_NAMES}
        for group in _GROUPS:
            changes: dict[str, Any] = {}
            for name, value in flat.items():
                target_group, target = FLAT_NAMES[name]
                if target_group != group:
                    continue
                if isinstance(target, tuple):
                    if value is not None and not isinstance(value, tuple | list):
                        raise ValueError(f"{name} must be two numbers (mm, deg), got {value!r}")
                    pair = (None, None) if value is None else tuple(value)
                    if len(pair) != 2:
                        raise ValueError(f"{name} must be two numbers (mm, deg), got {value}")
                    changes.update(zip(target, pair, strict=True))
                else:
                    changes[target] = value
            if changes:
                try:
                    values[group] = replace(values[group], **changes)
                except ValueError as e:
                    names = ", ".join(k for k in flat if FLAT_NAMES[k][0] == group)
                    raise ValueError(f"{names}: {e}") from None
        for name, value in values.items():
            object.__setattr__(self, name, value)
        self.__post_init__()

    def __post_init__(self) -> None:
        if self.intensity not in ("auto", "as-read", "match"):
            raise ValueError(f"intensity must be 'auto', 'as-read' or 'match', got {self.intensity!r}")
        if not self.levels:
            raise ValueError("at least one level is needed")
        bounds = (self.bound_mm, self.bound_deg)
        if not all(isinstance(b, numbers.Real) and math.isfinite(b) and b > 0 for b in bounds):
            raise ValueError(f"bound_mm and bound_deg must be positive finite numbers, got {bounds}")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int)
                                         or self.threads < 1):  # fmt: skip
            raise ValueError(f"threads must be None (one per core) or an integer >= 1, got {self.threads!r}")
        for level in self.levels:
            _check_level(level)
        for group, kind in _GROUPS.items():
            if not isinstance(getattr(self, group), kind):
                raise ValueError(f"{group} must be a {kind.__name__} or a bool, got {getattr(self, group)!r}")
        if self.support_margin_mm is not None:
            if len(self.support_margin_mm) != len(self.levels) + 1:
                raise ValueError("support_margin_mm needs one margin per level plus one for the polish")
            if any(not math.isfinite(m) or m < 0 for m in self.support_margin_mm):
                raise ValueError(f"support margins must be >= 0 mm, got {self.support_margin_mm}")

    def __getattr__(self, name: str) -> Any:
        """The flat names of earlier versions (:data:`FLAT_NAMES`), read from the groups."""
        if name not in FLAT_NAMES:
            raise AttributeError(f"'RegistrationOptions' object has no attribute {name!r}")
        group, target = FLAT_NAMES[name]
        options = object.__getattribute__(self, group)
        if isinstance(target, tuple):
            mm, deg = (getattr(options, t) for t in target)
            return None if mm is None else (mm, deg)
        return getattr(options, target)

    def margin_mm(self, stage: int) -> float | None:
        """The support margin of level ``stage`` (``len(levels)``: the polish)."""
        return None if self.support_margin_mm is None else self.support_margin_mm[stage]

    def capture_runs(self, level: Level, n_views: int) -> int:
        """The capture runs of ``level`` for ``n_views`` views."""
        if n_views > 1 and self.biplane.pair_capture_runs is not None:
            return min(level.restarts, self.biplane.pair_capture_runs)
        return level.restarts

    def optimizes_tz(self, n_views: int) -> bool:
        return n_views > 1 if self.optimize_tz is None else bool(self.optimize_tz)

    @property
    def pyramid_levels(self) -> int:
        """Volume pyramid levels the search uses (finest 0 to the coarsest level named)."""
        return max([*self.volume_levels(), self.polish.volume_level]) + 1

    def capture_level(self, n_views: int) -> Level:
        """The capture level of a registration on ``n_views`` views: the first of ``levels``, or
        for two or more the biplane's own (:attr:`BiplaneOptions.capture`)."""
        if n_views > 1 and self.biplane.capture is not None:
            return self.biplane.capture
        return self.levels[0]

    def volume_levels(self) -> list[int]:
        """The renderer's pyramid levels the search renders (the levels', the biplane capture's
        and the polish's)."""
        levels = {lv.volume_level for lv in self.levels}
        b = self.biplane
        levels |= {lv.volume_level for lv in (b.capture, b.plane_capture, b.plane_refine) if lv is not None}
        return sorted(levels | ({self.polish.volume_level} if self.polish.enabled else set()))
