"""One view's search again from far along the beam: each draw registered with it off, then on
(the default), in one process, each estimate assessed as ``register --confidence`` does; one JSON
line per draw and arm (right by the in-plane criterion, applied, why withheld, DRRs, seconds,
``restart``: what :mod:`registration.core.register.beam_restart` did).

    PYTHONPATH=. python scripts/beam_restart_ab.py capture 62 20 /40mm-0deg/,/50mm-0deg/,/60mm-0deg/
    PYTHONPATH=. python scripts/beam_restart_ab.py clinical 21 50
    ROADMAP3D_REAL_CT=../shared/data/real-ct/head-neck-ct PYTHONPATH=. python scripts/beam_restart_ab.py ct 182 60

``capture SEED N PARTS``: plane A of the capture study's translation sweep at N moments per level
(the draws of ``validate capture --sweep translation --registrations N --seed SEED``), the moments
whose case id holds one of PARTS; ``clinical SEED N``: the quick clinical study's first N
registrations per patient (frames of a rotational run against its own FDK reconstruction); ``ct
SEED N``: the shared real CT's clinical-looking images (``validate volume --realism clinical``, the
iso-center in the head), one view.
Records in docs/validation/capture/beam-restart/. ``ARMS=on`` runs the default engine only;
``FLAT_FAR_LOOK=off`` assesses without the flat far look's veto (records in
docs/validation/capture/flat-far-look/, where the veto is replayed from them).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

import numpy as np

from registration.core.assess import assess
from registration.core.blas import one_blas_thread
from registration.core.register import DepthOptions, RegistrationOptions, register

ARMS = {"off": RegistrationOptions(depth=DepthOptions(restart_beyond_mm=None)), "on": RegistrationOptions()}
if os.environ.get("ARMS"):  # e.g. ARMS=on: the default engine only
    ARMS = {arm: ARMS[arm] for arm in os.environ["ARMS"].split(",")}
if os.environ.get("FLAT_FAR_LOOK") == "off":  # the assessment before its flat far-look rule (replayed from the records)
    import registration.core.assess as _assess

    _assess.FLAT_FAR_GAIN = float("inf")


def _line(case_id: str, arm: str, result, assessment) -> str:  # noqa: ANN001
    restart = result.beam_restart.to_dict() if result.beam_restart is not None else None
    return json.dumps({
        "case": case_id, "arm": arm, "right": bool(result.residual.success),
        "inplane": round(float(result.residual.inplane_mm), 3), "oop": round(float(result.residual.outofplane_mm), 1),
        "applied": bool(assessment.applied), "reason": assessment.reason[:90], "drrs": result.drr_count,
        "seconds": round(result.seconds, 3), "restart": restart,
    })  # fmt: skip


def capture(seed: int, per_level: int, parts: list[str]) -> None:
    from registration.studies.biplane import _offset_motion, case_preparations, case_views, study_volume
    from registration.studies.capture import CaptureConfig, capture_tasks

    config = dataclasses.replace(CaptureConfig(seed=seed), sweeps=("translation",), registrations_per_level=per_level)
    for task in capture_tasks(config):
        if not any(p in task.case_id for p in parts):
            continue
        case = task.case
        volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
        motion = _offset_motion(case)
        views, _ = case_views(case, volume, motion)
        _, alone = case_preparations(case, volume, views, RegistrationOptions())
        for arm, options in ARMS.items():
            result = register(volume, views[0], truth=motion, seed=case.seed, options=options, renderer=alone.renderer)
            print(_line(task.case_id, arm, result, assess(result, views[0], alone)), flush=True)


def clinical(seed: int, per_patient: int) -> None:
    from registration.studies.cases import register_prepared
    from registration.studies.runs import ClinicalConfig, clinical_inputs, clinical_tasks

    config = dataclasses.replace(ClinicalConfig.quick_config(seed), registrations_per_patient=per_patient)
    for task in clinical_tasks(config):
        case = task.case
        data, xray, offset = clinical_inputs(case)
        for arm, options in ARMS.items():
            result, preparation = register_prepared(data.volume, xray, initial_motion=offset, truth=np.eye(4),
                                                    seed=case.seed, options=options)  # fmt: skip
            print(_line(task.case_id, arm, result, assess(result, xray, preparation)), flush=True)


def ct(seed: int, cases: int) -> None:
    from registration.io import dicom
    from registration.studies.volume import VolumeStudyConfig, find_real_ct, head_isocenter_mm, run_volume_study

    path = find_real_ct()
    if path is None:
        raise SystemExit("no real CT: set ROADMAP3D_REAL_CT")
    volume = dicom.read_volume(path)
    config = VolumeStudyConfig(cases=cases, seed=seed, realism="clinical")
    for arm, options in ARMS.items():
        records, _ = run_volume_study(volume, head_isocenter_mm(volume), config, options=options)
        for r in records:
            print(json.dumps({"case": f"ct/s{seed}/{r.get('case')}", "arm": arm, "right": bool(r["success"]),
                              "inplane": round(float(r["inplane_residual_mm"]), 3),
                              "oop": round(float(r["outofplane_residual_mm"]), 1), "applied": bool(r.get("applied")),
                              "reason": str(r.get("withheld_reason", ""))[:90], "drrs": r["drr_count"],
                              "seconds": round(float(r["seconds"]), 3), "restart": r.get("beam_restart")}),
                  flush=True)  # fmt: skip


def main() -> None:
    with one_blas_thread():
        if sys.argv[1] == "capture":
            capture(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4].split(","))
        elif sys.argv[1] == "ct":
            ct(int(sys.argv[2]), int(sys.argv[3]))
        else:
            clinical(int(sys.argv[2]), int(sys.argv[3]))


if __name__ == "__main__":
    main()
