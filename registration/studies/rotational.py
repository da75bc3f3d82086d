"""The paper's retrospective validation on a real rotational run (Homan et al., III.B).

A 3DRA is reconstructed from a rotational run, so every frame of that run is registered to the
3DRA by construction: its geometry (the run's per-frame angles, refined by the C-arm's
calibration when the user supplies it) is a nearly perfect ground truth, and any archived case
becomes a validation case. :func:`rotational_tasks` draws random frames and offsets in the
paper's range (translation length uniform in [0, 25] mm in a random direction, rotation uniform
in [0, 10] degrees about a random axis through the iso-center, as :func:`registration.studies.runs.
clinical_tasks`); :func:`run_rotational_case` registers one frame from its offset pose to the
volume and scores it against the identity; the records have the fields of the clinical study's,
so :mod:`registration.studies.report` summarises and reports them the same way.

Honest-simulation note: the frames and the volume come from the same acquisition; that is the
method (the frames are real projections, not DRRs of the volume), and the reports say so.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from registration import __version__
from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.core.register import RegistrationOptions
from registration.core.volume import Volume
from registration.studies.report_kit import source_revision
from registration.studies.runs import (
    CLINICAL_MAX_ROTATION_DEG,
    CLINICAL_MAX_TRANSLATION_MM,
    axis_angle_matrix,
    offset_record,
    random_unit_vector,
)

#: The report's title and method paragraph (registration.studies.report.write_clinical_report).
REPORT_TITLE = "Retrospective validation on a rotational run (Homan et al. III.B)"


@dataclass(frozen=True)
class RotationalCase:
    """One registration: frame ``frame`` of the run from a pose offset by (translation, rotation)."""

    frame: int
    translation_mm: tuple[float, float, float]
    rotation_axis: tuple[float, float, float]
    rotation_deg: float
    seed: int
    number: int


def rotational_tasks(
    frames: int,
    cases: int,
    *,
    seed: int = 0,
    max_translation_mm: float = CLINICAL_MAX_TRANSLATION_MM,
    max_rotation_deg: float = CLINICAL_MAX_ROTATION_DEG,
) -> list[RotationalCase]:
    """``cases`` random (frame, offset) draws; each depends only on ``seed`` and its number."""
    if frames < 1:
        raise ValueError(f"the run has no frame ({frames})")
    if cases < 1:
        raise ValueError(f"--cases must be >= 1, got {cases}")
    if not (0 <= max_translation_mm <= 100 and 0 <= max_rotation_deg <= 45):
        raise ValueError("offset range must be 0..100 mm and 0..45 deg")
    out = []
    for number in range(cases):
        rng = np.random.default_rng([seed, 14, number])
        frame = int(rng.integers(frames))
        translation = rng.uniform(0.0, max_translation_mm) * random_unit_vector(rng)
        axis = random_unit_vector(rng)
        angle = float(rng.uniform(0.0, max_rotation_deg))
        out.append(
            RotationalCase(
                frame=frame,
                translation_mm=(float(translation[0]), float(translation[1]), float(translation[2])),
                rotation_axis=(float(axis[0]), float(axis[1]), float(axis[2])),
                rotation_deg=angle,
                seed=int(rng.integers(2**31)),
                number=number,
            )
        )
    return out


def run_rotational_case(
    volume: Volume,
    image: XRayImage,
    geometry: CArm,
    case: RotationalCase,
    *,
    run_label: str = "",
    options: RegistrationOptions | None = None,
    revision: str = "",
) -> dict:
    """Register ``image`` (frame ``case.frame``, seen with ``geometry``) to ``volume`` from the
    case's offset pose; truth: the identity. A record with the clinical study's fields."""
    from registration.core.register import register

    xray = XRayImage(image.image, image.mask, geometry, image.kind, {**image.meta, "frame": case.frame})
    t = np.asarray(case.translation_mm, dtype=np.float64)
    offset = np.eye(4)
    offset[:3, 3] = t
    offset = offset @ axis_angle_matrix(case.rotation_axis, case.rotation_deg)
    result = register(volume, xray, initial_motion=offset, truth=np.eye(4), seed=case.seed, options=options)
    c = np.asarray(geometry.isocenter_mm, dtype=np.float64)
    # the offset's translation at the iso-center (the rotation is about the world origin)
    shift = offset[:3, :3] @ c + offset[:3, 3] - c
    return {
        "case_id": f"rotational-run/r{case.number}/f{case.frame}",
        "patient": 0,
        "phantom_seed": None,
        "volume_format_cm": round(float(geometry.field_diameter_mm) / 10.0, 1),
        "contrast": None,
        "frame": case.frame,
        "primary_deg": geometry.primary_deg,
        "secondary_deg": geometry.secondary_deg,
        **offset_record(result, geometry, shift, case.rotation_axis, case.rotation_deg, case.seed),
        # the offset as drawn (its translation at the world origin), beside its value at the iso-center
        "offset_vector_mm": [float(v) for v in t],
        "run": run_label,
        "image_pixels": int(geometry.cols),
        "volume_voxels": int(max(volume.shape)),
        "version": __version__,
        "revision": revision,
    }


def validate_rotational_run(
    volume: Volume,
    frames: Sequence[XRayImage],
    cases: Sequence[RotationalCase],
    *,
    geometry_of: Callable[[CArm], CArm] | None = None,
    run_label: str = "",
    options: RegistrationOptions | None = None,
    done: Callable[[dict], None] | None = None,
) -> list[dict]:
    """Every case's record. ``frames[n]`` is frame n of the run (decoded on access);
    ``geometry_of`` maps a frame's geometry from the file to the scoring geometry (the user's
    calibration; default: the file's own); ``done`` sees each record as it is made."""
    records = []
    revision = source_revision()
    for case in cases:
        image = frames[case.frame]
        geometry = geometry_of(image.geometry) if geometry_of is not None else image.geometry
        record = run_rotational_case(
            volume, image, geometry, case, run_label=run_label, options=options, revision=revision
        )
        records.append(record)
        if done is not None:
            done(record)
    return records


def method_lines(*, frames: int, calibrated: bool, run_label: str, volume_label: str) -> list[str]:
    """The report's method paragraph."""
    scored = (
        "the C-arm calibration the user supplied (per-frame source/detector deviations)"
        if calibrated
        else "the nominal geometry of the run's positioner tags (no calibration supplied)"
    )
    return [
        f"Run: {run_label} ({frames} frames). Volume: {volume_label}, reconstructed from that run.",
        "Random frames of the run are registered to the 3DRA reconstructed from the same run, from a pose",
        "offset by a random translation (length uniform in [0, 25] mm, random direction) and rotation (uniform",
        f"in [0, 10]° about a random axis through the iso-center). Truth: the frame's own geometry, from {scored};",
        "the frames are the run's real projections (not DRRs of the volume). Translation success: in-plane",
        "residual < 1 mm; rotation success: < 3°.",
    ]


def max_offset_ok(record: dict) -> bool:
    """The record's offset lies in the paper's range (used by the tests)."""
    return (
        record["offset_translation_mm"] <= CLINICAL_MAX_TRANSLATION_MM + 1e-6
        and record["offset_rotation_deg"] <= CLINICAL_MAX_ROTATION_DEG + 1e-9
        and math.isfinite(record["inplane_residual_mm"])
    )
