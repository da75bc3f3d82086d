"""A tracked run's options and a frame's outcome (CONVENTIONS §7): the statuses and paths, the tracker's
options with its light capture, and what it decides for one frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from registration.core.anneal import POLISH_XTOL
from registration.core.confidence import DEFAULT_RULE, ConfidenceRule
from registration.core.register import RegistrationOptions
from registration.core.register.options import CAPTURE_64

Array = NDArray[np.float64]


#: Statuses of a frame (CONVENTIONS §7).
STATUSES = ("applied", "withheld", "unchanged")
#: How a frame was processed.
PATHS = ("check", "refine", "capture")


def light_capture(options: RegistrationOptions | None = None) -> RegistrationOptions:
    """``options`` (default: register's) with only the first (capture) level and the polish.

    Without register's second (refine) annealing level the polish starts from the capture's estimate,
    so it searches the whole range (60 evaluations, Powell's default tolerance) as it did when
    this was measured, not register's +- 2 mm / 1.5 deg around an annealed estimate."""
    from dataclasses import replace

    o = options or RegistrationOptions()
    margins = None if o.support_margin_mm is None else (o.support_margin_mm[0], o.support_margin_mm[-1])
    if options is None:
        o = replace(o, polish_reach=None, polish_evaluations=60, polish_xtol=POLISH_XTOL)
    # no depth correction: the tracker refines the capture's estimate at its own level, five
    # parameters (validate tracking was measured without it); no walk beyond the search box (a
    # frame at the bounds is withheld, the next frame tries again)
    # the tracker's capture as measured: 64 px on the quarter-resolution volume
    capture = CAPTURE_64 if options is None else o.levels[0]
    return replace(o, levels=(capture,), support_margin_mm=margins, depth_correction=False, start=False)


@dataclass(frozen=True)
class TrackingOptions:
    """How the tracker detects, refines and captures (defaults: the benchmarked configuration)."""

    #: The tracking level: frames block-averaged to about this many pixels across, and the
    #: volume's pyramid level with about this many voxels across.
    image_px: int = 64
    volume_voxels: int = 64
    #: Pixels compared: the field, shrunk to rays passing this far inside the volume's support.
    support_margin_mm: float = 6.0
    #: Motion is detected when the measure at the last applied pose drops below its level by
    #: more than ``detect_sigmas`` noise units and more than ``detect_relative`` of the level.
    detect_sigmas: float = 5.0
    detect_relative: float = 0.0006
    #: A smaller drop (or ``probe_every`` frames without a refinement) makes the tracker look:
    #: a refinement that finds no pose better than the last applied one by ``detect_sigmas``
    #: (and ``detect_relative``) means no motion (the image changed, e.g. a wire advanced).
    suspect_sigmas: float = 2.5
    probe_every: int = 4
    #: Floor of the learned noise, relative to the level, and its ceiling in floors (the
    #: learned deviations include slow image changes: a guidewire advancing, drift).
    noise_floor_relative: float = 0.0002
    noise_ceiling_floors: float = 2.0
    #: A refinement that moves the pose by less than this (iso-center mm, in-plane for one
    #: view; degrees) is the tracking level's jitter, not motion: the frame is unchanged.
    min_correction_mm: float = 0.15
    min_correction_deg: float = 0.15
    #: A drop beyond this fraction of the level goes straight to the full capture.
    capture_relative: float = 0.02
    #: A refinement whose measure stays more than this many noise units below the level
    #: (and more than ``detect_relative``) did not find the patient: full capture.
    recover_sigmas: float = 6.0
    #: After a full capture the level is expected back to within this fraction of itself.
    capture_tolerance: float = 0.004
    #: Newton iterations of the refinement, its probe steps and its smallest step.
    refine_iterations: int = 3
    refine_step_mm: float = 0.5
    refine_step_deg: float = 0.5
    refine_tolerance: float = 0.03
    #: The refinement stays within this range of the pose it starts from.
    refine_bound_mm: float = 8.0
    refine_bound_deg: float = 5.0
    #: Memory of the level and noise on unchanged frames (0: forget at once).
    level_memory: float = 0.9
    #: Run the full capture on the first frame (else the run starts registered: the first
    #: frame's pose is the initial pose, as after the roadmap's initial registration).
    register_first: bool = False
    #: Options of the full capture (None: the defaults of :func:`register`). The default
    #: keeps a capture level (four runs at 64 px, :data:`CAPTURE_64`) and register's polish but not its second
    #: (refine) annealing level: the tracker refines the result at its own level anyway. Measured on
    #: the quick run's two moves: 1.5-1.65 s CPU instead of 2.4-2.8 s, residuals 0.31/0.35 mm
    #: instead of 0.31/0.30 mm.
    capture: RegistrationOptions | None = field(default_factory=lambda: light_capture())
    #: Threads that render probes side by side (None: one per core, at most 2).
    threads: int | None = None
    rule: ConfidenceRule = DEFAULT_RULE
    #: A renderer of prepared levels (:mod:`registration.core.prepare`) holds the anatomy of a
    #: crop: what the field reaches while the patient stays within one capture's search of
    #: where the crop was prepared. When the applied pose leaves the next capture too little of
    #: that reach, the crop is prepared again around the applied pose (in a thread of its own,
    #: swapped in when ready), with this much slack (mm, deg) beyond the capture's search.
    #: A crop that holds the whole body never is. False: never re-prepare. The margin may fall
    #: ``reprepare_tolerance_mm`` / ``_deg`` short first: then only a capture's farthest poses
    #: could render that much of the anatomy the crop lacks, beyond the two coarsest voxels the
    #: crop keeps past its reach anyway (a still patient's applied pose never moves: its crop is
    #: never prepared again).
    reprepare: bool = True
    reprepare_slack_mm: float = 10.0
    reprepare_slack_deg: float = 5.0
    reprepare_tolerance_mm: float = 1.0
    reprepare_tolerance_deg: float = 0.5

    def __post_init__(self) -> None:
        if self.image_px < 16 or self.volume_voxels < 8:
            raise ValueError("image_px must be >= 16 and volume_voxels >= 8")
        for name in ("detect_sigmas", "recover_sigmas", "refine_step_mm", "refine_step_deg", "refine_tolerance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0.0 <= self.level_memory < 1.0:
            raise ValueError(f"level_memory must lie in [0, 1), got {self.level_memory}")
        if self.refine_iterations < 1:
            raise ValueError(f"refine_iterations must be >= 1, got {self.refine_iterations}")
        for name in ("reprepare_slack_mm", "reprepare_slack_deg", "reprepare_tolerance_mm", "reprepare_tolerance_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")


@dataclass
class FrameEstimate:
    """What the tracker decided for one frame (CONVENTIONS §7)."""

    frame: int
    t_s: float
    status: str
    #: The pose the roadmap shows after this frame (the last applied estimate).
    patient_motion: Array
    #: The engine's estimate for this frame (None when no motion was detected).
    estimate: Array | None
    path: str
    confidence: float | None
    reason: str
    latency_ms: float
    similarity: float
    drop_sigmas: float
    drr_count: int
    evidence: dict = field(default_factory=dict)
    #: CPU time of the process over the frame (ms, all threads): the work, whatever else
    #: shares the machine (on a busy machine ``latency_ms`` grows, this does not).
    cpu_ms: float = 0.0
    #: The volume's crop was prepared again (around the applied pose) and used from this frame
    #: on; ``crop`` then says what it holds and when it was started.
    reprepared: bool = False
    crop: dict | None = None
    #: What the crop leaves the next capture from the applied pose (mm at the iso-center, deg;
    #: None when nothing is cropped away: a whole volume's pyramid or a crop of the whole body).
    crop_margin_mm: float | None = None
    crop_margin_deg: float | None = None

    def __repr__(self) -> str:
        """A line a notebook shows: the frame, its time, what was decided and why."""
        confidence = "" if self.confidence is None else f", confidence {self.confidence:.2f}"
        reason = f", {self.reason}" if self.reason else ""
        return (f"{type(self).__name__}(frame {self.frame} at {self.t_s:.3f} s: {self.status} ({self.path}"
                f"{confidence}){reason}, {self.latency_ms:.0f} ms, {self.drr_count} DRRs)")  # fmt: skip

    def to_dict(self) -> dict:
        out = {
            "frame": self.frame,
            "t_s": self.t_s,
            "status": self.status,
            "patient_motion": np.asarray(self.patient_motion).tolist(),
            "estimate": None if self.estimate is None else np.asarray(self.estimate).tolist(),
            "path": self.path,
            "confidence": self.confidence,
            "reason": self.reason,
            "latency_ms": self.latency_ms,
            "cpu_ms": self.cpu_ms,
            "similarity": self.similarity,
            "drop_sigmas": self.drop_sigmas,
            "drr_count": self.drr_count,
            "evidence": self.evidence,
            "reprepared": self.reprepared,
            "crop_margin_mm": self.crop_margin_mm,
            "crop_margin_deg": self.crop_margin_deg,
        }
        if self.crop is not None:
            out["crop"] = self.crop
        return out
