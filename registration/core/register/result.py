"""What a registration returns and what its callback sees."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.core.geometry import (
    OFFSET_NAMES,
    CArm,
    invert_rigid,
    matrix_to_offsets,
    offsets_to_matrix,
    rotation_angle_deg,
)
from registration.core.metrics import Residual
from registration.core.search import FIVE_PARAMETERS

Array = NDArray[np.float64]


#: A single view's estimate that turns the head more than this (degrees) from where its search
#: started is not applied automatically: the clinical offsets reach 10 deg, a right estimate
#: there is within 3 deg of the truth, and one view sees out-of-plane turns poorly
#: (docs/decisions/2026-12-04-single-plane-turn.md).
SINGLE_PLANE_MAX_TURN_DEG = 13.0


def single_plane_turn_deg(result: RegistrationResult) -> float | None:
    """How far a single view's estimate turns the head from where the search started (degrees);
    None for an estimate of all six parameters (two views)."""
    parameters = tuple(getattr(result, "parameters", ()))
    offsets = getattr(result, "offsets", None)
    if "tz" in parameters or offsets is None or len(offsets) != len(parameters) or not parameters:
        return None
    found = dict(zip(parameters, np.asarray(offsets, dtype=np.float64), strict=True))
    full = np.array([found.get(name, 0.0) for name in OFFSET_NAMES])
    return rotation_angle_deg(offsets_to_matrix(full, result.geometry))


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


@dataclass(frozen=True)
class StageCost:
    """What one stage of the plan cost: its description, the DRRs and DRR pixels (rays) it
    rendered and its wall time."""

    stage: str
    drrs: int
    rays: int
    seconds: float

    def to_dict(self) -> dict:
        return {"stage": self.stage, "drrs": self.drrs, "rays": self.rays, "seconds": self.seconds}


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
    #: Whether the depth correction's tz ended within a scan step of its bound (the depth may lie
    #: beyond it, and one view cannot tell).
    depth_at_bound: bool = False
    #: The rotation check (:attr:`RegistrationOptions.rotation_check`, one view): how many
    #: checks ran, how many moved the estimate, and the last check's ``rival_gain``
    #: (:class:`RotationCheck`: the best other optimum against the kept estimate, relative,
    #: <= 0; > 0 only when the last check still moved the estimate; None: every polish came
    #: back). None: no check ran.
    rotation_check: RotationCheck | None = None
    #: Per view, what the intensity matching assumed (:mod:`registration.core.intensity`: the
    #: polarity, its margin, the stored levels, a note), None for a view used as read; () when
    #: every view was used as read.
    intensity: tuple[dict | None, ...] = ()
    #: Restarts of the whole search from an estimate that ended at the search bounds, each with
    #: the box centred there (:mod:`registration.core.register.walk`); 0: none was needed.
    walk_hops: int = 0
    #: How far the search's start was moved from the machine-based pose by the image shift
    #: (:mod:`registration.core.register.shift_start`), mm; 0.0: not moved.
    start_shift_mm: float = 0.0
    #: The image shift left at the first estimate when the search ran again from the image shift
    #: (:func:`registration.core.register.shift_start.look_again`), mm; 0.0: it did not.
    recheck_shift_mm: float = 0.0
    #: Why the search ran again from the image shift ("": it did not).
    second_search: str = ""
    #: Why the estimate is a second search held near the landmarks' poses
    #: (:mod:`registration.core.register.landmark_hold`; "": it is not).
    held_by_landmarks: str = ""
    #: Whether the estimate lies beyond the search box around the machine-based pose (its
    #: offsets from that pose exceed ``bound_mm`` / ``bound_deg``).
    beyond_box: bool = False
    #: Whether two views' estimate from a start away from the machine-based pose was polished on
    #: the full images and the volume's level 0 (:mod:`registration.core.register.fine_polish`).
    fine_polished: bool = False
    #: Two views from the image shift: the estimate is the translation-first candidate
    #: (:mod:`registration.core.register.translation_first`), which fit better than the search's.
    translation_first: bool = False
    #: Each stage that ran, in order, with its cost (a walk's restarts follow the first search's).
    stages: tuple[StageCost, ...] = ()
    #: Two views: whether the planes' own captures still disagreed after their rounds in some
    #: search of this registration (its pair's capture then ran from several starts).
    planes_disagreed: bool = False
    #: One view far from the machine-based pose: the search ran again from far along the beam
    #: (:class:`~registration.core.register.beam_restart.BeamRestart`: from where, both measures,
    #: whether its estimate was kept); None: it did not.
    beam_restart: Any = None

    @property
    def success(self) -> bool | None:
        return None if self.residual is None else self.residual.success

    def __repr__(self) -> str:
        """A line a notebook shows: the offsets, the similarity, the cost and, with a truth, the
        residual (:meth:`to_dict` holds everything)."""
        units = {"tx": " mm", "ty": " mm", "tz": " mm", "rx": " deg", "ry": " deg", "rz": " deg"}
        values = np.asarray(self.offsets, dtype=np.float64)
        offsets = [f"{n} {v:+.2f}{units.get(n, '')}" for n, v in zip(self.parameters, values, strict=True)]
        if self.depth_tz_mm is not None and "tz" not in self.parameters:
            offsets.insert(2, f"tz {self.depth_tz_mm:+.2f} mm")
        views = f"{len(self.views)} views, " if len(self.views) > 1 else ""
        stopped = ", stopped" if self.stopped else ""
        residual = ""
        if self.residual is not None:
            r = self.residual
            residual = (f"; residual {r.inplane_mm:.2f} mm in-plane, {r.translation_mm:.2f} mm total, "
                        f"{r.rotation_deg:.2f} deg: {'success' if r.success else 'failure'}")  # fmt: skip
        return (f"{type(self).__name__}({views}{', '.join(offsets)}; similarity {self.similarity:.4g}, "
                f"{self.drr_count:,} DRRs in {self.seconds:.2f} s{stopped}{residual})")  # fmt: skip

    def offsets_of(self, motion: Array) -> Array:
        """``motion``'s offsets (in :attr:`parameters`) from where this estimate's search started: a
        later stage that replaces the estimate keeps the offsets relative to that start."""
        old = dict(zip(self.parameters, np.asarray(self.offsets, dtype=np.float64), strict=True))
        start = offsets_to_matrix([old.get(n, 0.0) for n in OFFSET_NAMES], self.geometry)
        began_at = invert_rigid(start) @ np.asarray(self.patient_motion, dtype=np.float64)
        full = matrix_to_offsets(np.asarray(motion, dtype=np.float64) @ invert_rigid(began_at), self.geometry)
        return np.array([full[OFFSET_NAMES.index(n)] for n in self.parameters])

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
            if self.depth_at_bound:
                out["depth_at_bound"] = True
        if self.rotation_check is not None:
            out["rotation_check"] = self.rotation_check.to_dict()
        if self.intensity:
            out["intensity"] = list(self.intensity)
        if self.walk_hops:
            out["walk_hops"] = self.walk_hops
        if self.start_shift_mm:
            out["start_shift_mm"] = self.start_shift_mm
        if self.second_search:
            out["second_search"] = self.second_search
            out["recheck_shift_mm"] = self.recheck_shift_mm
        if self.held_by_landmarks:
            out["held_by_landmarks"] = self.held_by_landmarks
        if self.beyond_box:
            out["beyond_box"] = True
        if self.fine_polished:
            out["fine_polished"] = True
        if self.translation_first:
            out["translation_first"] = True
        if self.planes_disagreed:
            out["planes_disagreed"] = True
        if self.beam_restart is not None:
            out["beam_restart"] = self.beam_restart.to_dict()
        if self.stages:
            out["stages"] = [c.to_dict() for c in self.stages]
        return out


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
    #: The estimate's out-of-plane rotation margin measured before the first check
    #: (:func:`~registration.core.register.screen.rotation_margin`), and whether it was
    #: sharp enough that no polish ran (``checks`` 0).
    margin: float | None = None
    skipped: bool = False

    def to_dict(self) -> dict:
        return {
            "rival_gain": self.rival_gain,
            "moved_deg": self.moved_deg,
            "checks": self.checks,
            "moves": self.moves,
            "margin": self.margin,
            "skipped": self.skipped,
        }
