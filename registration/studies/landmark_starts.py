"""Starts from picked landmarks, measured: each moment of the capture study registered from the
pose that landmarks picked with error give, instead of from the machine-based pose
(``roadmap3d validate capture --from-landmarks``).

The picks are where a user picks: the skull's outermost bone points in spread directions (orbit
rims, vertex, occiput, temples), on each plane the first ``pairs`` of them that the plane's field
shows (a point outside the image, or behind a blade, cannot be picked on it). Each volume point
is picked ``noise_mm`` off (isotropic normal, ``noise_mm / sqrt(3)`` per axis) and each image
point off by the same ``noise_mm`` seen at the iso-center. Two views: each plane's own picks;
one view: plane A's. A view set where no plane shows :data:`~registration.core.landmarks.MIN_PAIRS`
of the points has no landmark start: it registers from the machine-based pose, as a user would,
and its record says so (``landmark_start`` False, ``landmark_picks`` per plane). Each start
registers as ``roadmap3d register --landmarks --confidence`` does (the volume prepared from the
start, :func:`registration.core.register.register` with the landmarks, the estimate assessed
with the landmarks' check). The records carry the capture study's fields (``success``,
``applied``, ``single_success_inplane``, ``single_applied``), so its summary, curves and report
read them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.core.assess import assess
from registration.core.geometry import apply
from registration.core.images import XRayImage
from registration.core.landmarks import MIN_PAIRS, Landmark, LandmarkStart, landmark_start
from registration.core.register import RegistrationOptions
from registration.core.volume import Volume
from registration.studies.biplane import BiplaneCase, _offset_motion, case_views, study_volume
from registration.studies.cases import register_prepared

#: Where the picks lie: the skull's outermost bone point along each direction (world axes of the
#: volume; spread first: left, right, vertex, front, then the others).
PICK_DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, -1, 0.3], [0, 1, 0.3], [0.7, -0.7, 0.3],
                            [-0.7, -0.7, 0.3], [0, -0.6, -0.8]], dtype=float)  # fmt: skip
#: Bone for the picks: voxels above this value (HU).
BONE_HU = 400.0


def outer_bone_points(volume: Volume, count: int) -> NDArray[np.float64]:
    """The skull's outermost bone voxels (world mm) along the first ``count`` pick directions."""
    if not 1 <= count <= len(PICK_DIRECTIONS):
        raise ValueError(f"landmark pairs must lie in 1..{len(PICK_DIRECTIONS)}, got {count}")
    kk, jj, ii = np.nonzero(volume.data > BONE_HU)
    if ii.size == 0:
        raise ValueError(f"{volume.label}: no bone above {BONE_HU:g} HU to pick landmarks on")
    pts = (volume.index_to_world @ np.stack([ii, jj, kk, np.ones_like(ii)]).astype(float))[:3].T
    centre = pts.mean(axis=0)
    dirs = PICK_DIRECTIONS[:count] / np.linalg.norm(PICK_DIRECTIONS[:count], axis=1, keepdims=True)
    return np.array([pts[int(np.argmax((pts - centre) @ d))] for d in dirs])


def in_field(view: XRayImage, image_px: NDArray[np.float64]) -> bool:
    """Whether the pixel (column, row) lies on the image inside its usable field."""
    col, row = (int(round(float(v))) for v in image_px)
    rows, cols = view.shape
    return 0 <= row < rows and 0 <= col < cols and bool(view.mask[row, col])


def picked_landmarks(
    volume: Volume,
    views: Any,
    truth: NDArray[np.float64],
    *,
    pairs: int,
    noise_mm: float,
    rng: np.random.Generator,
    visible: bool = True,
) -> list[Landmark]:
    """Up to ``pairs`` landmarks per view, picked with ``noise_mm`` error: on each plane the first
    of the skull's outline points (:data:`PICK_DIRECTIONS`) that its field shows (``visible``),
    or the first ``pairs`` wherever they project (``visible=False``: the same anatomy on every
    plane, some of it perhaps off the image)."""
    anatomy = outer_bone_points(volume, len(PICK_DIRECTIONS) if visible else pairs)
    sigma = noise_mm / np.sqrt(3.0)
    out = []
    for plane, view in enumerate(views):
        g = view.geometry
        px_per_mm = g.magnification / float(np.mean(g.pixel_mm))
        taken = 0
        for p in anatomy:
            seen = g.project(apply(truth, p))
            if taken == pairs or (visible and not in_field(view, seen)):
                continue
            image_px = seen + rng.normal(0.0, sigma, 2) * px_per_mm
            volume_mm = p + rng.normal(0.0, sigma, 3)
            out.append(Landmark(tuple(float(v) for v in image_px), tuple(float(v) for v in volume_mm), plane))
            taken += 1
    return out


def picks_per_plane(landmarks: list[Landmark], planes: int) -> list[int]:
    """How many of ``landmarks`` lie on each of the first ``planes`` planes."""
    return [sum(lm.plane == p for lm in landmarks) for p in range(planes)]


@dataclass(frozen=True)
class LandmarkCase:
    """One capture moment, registered from landmarks picked with error."""

    case: BiplaneCase
    pairs: int = 4
    noise_mm: float = 3.0
    pick_seed: int = 0

    def prepare_key(self) -> tuple:
        return self.case.prepare_key()

    def prepare(self) -> None:
        self.case.prepare()

    def run(self, *, options: RegistrationOptions | None = None) -> dict:
        return run_landmark_case(self, options=options)


def _outcome(prefix: str, result: Any, decided: Any) -> dict:
    """The registration's residuals, cost and decision under the record's ``prefix``."""
    res = result.residual
    return {
        f"{prefix}translation_residual_mm": res.translation_mm,
        f"{prefix}inplane_residual_mm": res.inplane_mm,
        f"{prefix}rotation_residual_deg": res.rotation_deg,
        f"{prefix}seconds": result.seconds,
        f"{prefix}drr_count": result.drr_count,
        f"{prefix}applied": bool(decided.applied),
        f"{prefix}confidence": float(decided.confidence),
        f"{prefix}withheld_reason": decided.reason,
    }


def _start_outcome(prefix: str, start: LandmarkStart, result: Any, truth: NDArray[np.float64]) -> dict:
    """How far the landmark start lay from the truth and how far the estimate moved its landmarks."""
    iso = np.asarray(result.views[0].isocenter_mm)
    return {
        f"{prefix}start_rms_px": start.rms_px,
        f"{prefix}start_off_mm": float(np.linalg.norm(apply(start.patient_motion, iso) - apply(truth, iso))),
        f"{prefix}estimate_moved_mm": start.moved_mm(result.patient_motion),
        f"{prefix}held_by_landmarks": bool(result.held_by_landmarks),
    }


def run_landmark_case(lc: LandmarkCase, *, options: RegistrationOptions | None = None) -> dict:
    """Register the moment from landmarks on both planes, and on plane A alone from its own."""
    case = lc.case
    volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
    truth = _offset_motion(case)
    views, image_source = case_views(case, volume, truth)
    picks = picked_landmarks(volume, views, truth, pairs=lc.pairs, noise_mm=lc.noise_mm,
                             rng=np.random.default_rng(lc.pick_seed))  # fmt: skip
    record: dict = {
        "phantom_seed": case.phantom_seed,
        "volume_format_cm": case.volume_format_cm,
        "offset_translation_mm": float(np.linalg.norm(case.translation_mm)),
        "offset_rotation_deg": case.rotation_deg,
        "seed": case.seed,
        "landmark_pairs": lc.pairs,
        "landmark_noise_mm": lc.noise_mm,
        "image_source": image_source,
        "volume_label": volume.label,
        "pixels": list(case.pixels),
    }
    for prefix, vs in (("", list(views)), ("single_", [views[0]])):
        lms = [lm for lm in picks if lm.plane < len(vs)]
        counts = picks_per_plane(lms, len(vs))
        images = vs if len(vs) > 1 else vs[0]
        record[f"{prefix}landmark_picks"] = counts
        record[f"{prefix}landmark_start"] = max(counts) >= MIN_PAIRS
        if max(counts) < MIN_PAIRS:  # too little of the skull in view to pick: the machine-based pose
            result, prepared = register_prepared(volume, images, truth=truth, seed=case.seed, options=options)
            decided = assess(result, images, prepared)
            record.update(_outcome(prefix, result, decided))
        else:
            start = landmark_start([v.geometry for v in vs], lms)
            result, prepared = register_prepared(volume, images, initial_motion=start.patient_motion, truth=truth,
                                                 seed=case.seed, options=options, landmarks=start)  # fmt: skip
            decided = assess(result, images, prepared, landmarks=start)
            record.update(_outcome(prefix, result, decided) | _start_outcome(prefix, start, result, truth))
        if prefix:  # one view: the in-plane criterion (its depth is seen only through magnification)
            record["single_success_inplane"] = bool(result.residual.success)
        else:
            record["success"] = bool(result.residual.success_total)
    return record
