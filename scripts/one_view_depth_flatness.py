"""How flat one view's measure is along its beam far from the estimate, on chosen moments of the
full capture study (the same draws as ``validate capture --seed S --sweep translation``).

Each moment is registered on plane A alone as the study does, then the estimate is moved along
the beam by -84 to +84 mm in 4 mm steps (nothing else moves) and the high-passed measure of the
depth scan (:func:`registration.core.depth.depth_scan`, 128 px, the depth correction's level) is
evaluated at each. Printed per moment: the residuals, where the scan peaks, and
``far_minus_near``: the best value beyond ±24 mm less the best within it (near 0: the measure
does not tell the estimate's depth from one 24-84 mm away).

    PYTHONPATH=. python scripts/one_view_depth_flatness.py 50 /80mm-0deg/r2/,/20mm-0deg/r1/

``clinical SEED N`` instead: the first N registrations of each patient of the quick clinical
study (frames of a rotational run registered to its own FDK reconstruction, the study's
offsets), the same measure at each estimate.

    PYTHONPATH=. python scripts/one_view_depth_flatness.py clinical 3 10

``beam SEED N`` instead: moments whose offset lies mostly along plane A's beam (N per distance of
40-100 mm, either way, with up to 10 mm across the beam and 10 degrees about a random axis; plane A
drawn as the capture study draws it), registered and assessed on plane A alone as the capture
study does, then the same measure at each estimate: the offsets where one view is most likely to
end at a wrong depth.

    PYTHONPATH=. python scripts/one_view_depth_flatness.py beam 51 4
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np

from registration.core.blas import one_blas_thread
from registration.core.depth import depth_scan, scan_level
from registration.core.register import RegistrationOptions, register
from registration.studies.biplane import BiplaneCase, _offset_motion, case_preparations, case_views, study_volume
from registration.studies.capture import CaptureConfig, capture_tasks

OFFSETS_MM = tuple(float(v) for v in np.arange(-84.0, 84.1, 4.0))
NEAR_MM = 24.0


def _flatness(renderer, xray, motion) -> dict:  # noqa: ANN001
    """Where the depth scan peaks and its ``far_minus_near`` at ``motion``."""
    level = scan_level(renderer)
    scan = depth_scan(renderer, xray, motion, offsets_mm=OFFSETS_MM, image_px=128, volume_level=level)
    values, near = np.asarray(scan.similarity), np.abs(np.asarray(OFFSETS_MM)) <= NEAR_MM
    return {
        "volume_level": level,
        "peak_tz_mm": round(float(scan.tz_mm), 2),
        "far_minus_near": round(float(values[~near].max() - values[near].max()), 5),
        "values": [round(float(v), 6) for v in values],
    }


def clinical(seed: int, per_patient: int) -> None:
    from registration.core.assess import assess
    from registration.studies.cases import register_prepared
    from registration.studies.runs import ClinicalConfig, clinical_inputs, clinical_tasks

    config = dataclasses.replace(ClinicalConfig.quick_config(seed), registrations_per_patient=per_patient)
    with one_blas_thread():
        for task in clinical_tasks(config):
            case = task.case
            data, xray, offset = clinical_inputs(case)
            result, preparation = register_prepared(data.volume, xray, initial_motion=offset, truth=np.eye(4),
                                                    seed=case.seed)  # fmt: skip
            applied = assess(result, xray, preparation).applied
            record = {
                "case_id": task.case_id,
                "inplane_residual_mm": round(float(result.residual.inplane_mm), 3),
                "outofplane_residual_mm": round(float(result.residual.outofplane_mm), 2),
                "rotation_residual_deg": round(float(result.residual.rotation_deg), 2),
                "success": bool(result.residual.success),
                "applied": bool(applied),
                **_flatness(preparation.renderer, xray, result.patient_motion),
            }
            print(json.dumps(record), flush=True)


BEAM_DISTANCES_MM = (40.0, 50.0, 60.0, 70.0, 80.0, 90.0, 100.0)
ACROSS_MM = 10.0
TURN_DEG = 10.0


def beam_cases(seed: int, per_distance: int) -> list[tuple[str, BiplaneCase]]:
    """The moments of ``beam SEED N``: each depends only on the seed, distance and number."""
    from registration.sim.biplane import plane_a_spec
    from registration.studies.capture import PLANE_A_PRIMARY_DEG, PLANE_B_PRIMARY_DEG, SECONDARY_DEG
    from registration.studies.runs import random_unit_vector

    out = []
    for distance in BEAM_DISTANCES_MM:
        for number in range(per_distance):
            rng = np.random.default_rng([seed, 0xBE, int(distance), number])
            angles = (
                (float(rng.uniform(*PLANE_A_PRIMARY_DEG)), float(rng.uniform(*SECONDARY_DEG))),
                (float(rng.uniform(*PLANE_B_PRIMARY_DEG)), float(rng.uniform(*SECONDARY_DEG))),
            )
            beam = np.asarray(plane_a_spec().nominal(*angles[0]).direction, dtype=np.float64)
            across = random_unit_vector(rng)
            across -= (across @ beam) * beam
            across *= rng.uniform(0.0, ACROSS_MM) / np.linalg.norm(across)
            translation = (distance if rng.uniform() < 0.5 else -distance) * beam + across
            axis = random_unit_vector(rng)
            case = BiplaneCase(
                phantom_seed=0, volume_format_cm=27.0, volume_voxels=256, angles_deg=angles,
                translation_mm=tuple(float(v) for v in translation), rotation_axis=tuple(float(v) for v in axis),
                rotation_deg=float(rng.uniform(0.0, TURN_DEG)), pixels=(512, 384), kind="fluoro",
                seed=int(rng.integers(2**31)),
            )  # fmt: skip
            out.append((f"beam/{distance:g}mm/r{number}/s{seed}", case))
    return out


def beam(seed: int, per_distance: int) -> None:
    from registration.core.assess import assess
    from registration.core.confidence import DEFAULT_RULE
    from registration.studies.cases import assessment_fields

    with one_blas_thread():
        for case_id, case in beam_cases(seed, per_distance):
            volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
            motion = _offset_motion(case)
            views, _ = case_views(case, volume, motion)
            _, alone = case_preparations(case, volume, views, RegistrationOptions())
            single = register(volume, views[0], truth=motion, seed=case.seed, renderer=alone.renderer)
            assessment = assess(single, views[0], alone)
            judged = assessment_fields(assessment)
            # the same evidence without the far look's term: the decision before it
            before = dataclasses.replace(DEFAULT_RULE, far_weight=0.0).assess(assessment.evidence)
            t, d = np.asarray(case.translation_mm), np.asarray(views[0].geometry.direction)
            record = {
                "case_id": case_id,
                "offset_along_beam_mm": round(float(t @ d), 2),
                "offset_across_mm": round(float(np.linalg.norm(t - (t @ d) * d)), 2),
                "offset_rotation_deg": round(case.rotation_deg, 2),
                "inplane_residual_mm": round(float(single.residual.inplane_mm), 3),
                "outofplane_residual_mm": round(float(single.residual.outofplane_mm), 2),
                "rotation_residual_deg": round(float(single.residual.rotation_deg), 2),
                "success": bool(single.residual.success),
                "applied": bool(judged["applied"]),
                "confidence": round(float(judged["confidence"]), 4),
                "withheld_reason": judged["withheld_reason"],
                "applied_without_far": bool(before.applied),
                "confidence_without_far": round(float(before.confidence), 4),
                "evidence": {k: v for k, v in judged["confidence_evidence"].items() if v is not None},
                "depth_tz_mm": single.depth_tz_mm,
                **_flatness(alone.renderer, views[0], single.patient_motion),
            }
            print(json.dumps(record), flush=True)


def main() -> None:
    if sys.argv[1] == "clinical":
        clinical(int(sys.argv[2]), int(sys.argv[3]))
        return
    if sys.argv[1] == "beam":
        beam(int(sys.argv[2]), int(sys.argv[3]))
        return
    seed, wanted = int(sys.argv[1]), sys.argv[2].split(",")
    config = dataclasses.replace(CaptureConfig(seed=seed), sweeps=("translation",))
    with one_blas_thread():
        for task in capture_tasks(config):
            if not any(w in task.case_id for w in wanted):
                continue
            case = task.case
            volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
            motion = _offset_motion(case)
            views, _ = case_views(case, volume, motion)
            _, alone = case_preparations(case, volume, views, RegistrationOptions())
            single = register(volume, views[0], truth=motion, seed=case.seed, renderer=alone.renderer)
            record = {
                "case_id": task.case_id,
                "inplane_residual_mm": round(float(single.residual.inplane_mm), 3),
                "outofplane_residual_mm": round(float(single.residual.outofplane_mm), 2),
                **_flatness(alone.renderer, views[0], single.patient_motion),
            }
            print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
