"""One view: the depth correction's polishes with fewer evaluations, on the same draws.

Each draw is registered once per arm (``--budgets``, the depth correction's polish evaluations;
the shipped default first), in one process, interleaved, and assessed as ``register
--confidence`` does. Prints one JSON line per draw and arm: right (in-plane < 1 mm and rotation
< 3 degrees), applied, the residuals, the DRRs and the seconds.

    PYTHONPATH=. python scripts/depth_budget_study.py runs --seed 21 --cases 20 --budgets 60,40
    PYTHONPATH=. python scripts/depth_budget_study.py volume --seed 64 --cases 20 --budgets 60,40

``runs``: the rotational-run study (``roadmap3d validate clinical --quick``'s patients, ``--cases``
registrations per patient); ``volume``: the shared real CT (ROADMAP3D_REAL_CT), clinical-looking
images of ``--strength`` (``roadmap3d validate volume --realism clinical``).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

from registration.core.register import RegistrationOptions
from registration.core.register.options import DepthOptions


def _line(tag: dict, budget: int, record: dict) -> str:
    right = bool(record["inplane_residual_mm"] < 1.0 and record["rotation_residual_deg"] < 3.0)
    return json.dumps(tag | {
        "budget": budget, "right": right, "applied": bool(record.get("applied")),
        "inplane_mm": round(float(record["inplane_residual_mm"]), 3),
        "rotation_deg": round(float(record["rotation_residual_deg"]), 3),
        "drrs": record.get("drr_count"), "seconds": round(float(record["seconds"]), 3),
    })  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("runs", "volume"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--budgets", default="60,40")
    args = ap.parse_args()
    arms = {int(b): RegistrationOptions(depth=DepthOptions(polish_evaluations=int(b))) for b in args.budgets.split(",")}
    if args.study == "runs":
        from registration.studies import runs

        config = replace(runs.ClinicalConfig.quick_config(args.seed), registrations_per_patient=args.cases)
        for task in runs.clinical_tasks(config):
            for budget, options in arms.items():
                record = runs.run_clinical_case(task.case, options=options)
                print(_line({"study": "runs", "case": task.case_id}, budget, record), flush=True)
        return 0
    from registration.core.roi import followed_region
    from registration.io import dicom
    from registration.studies import volume as study

    ct = dicom.read_volume(study.find_real_ct())
    iso = study.head_isocenter_mm(ct)
    config = study.VolumeStudyConfig(cases=args.cases, seed=args.seed, realism="clinical", strengths=(args.strength,))
    region = followed_region(ct, config.roi)
    for arm, effects, strength in study.study_arms(config):
        if not effects:
            continue  # the clinical-looking images only
        base = None
        if "table" in effects:
            from registration.sim.clinical.anatomy import patient_only

            base = patient_only(ct)[0]
        imager = study.ClinicalViews(ct, iso, effects, strength, catheter=config.catheter, base=base)
        for case in study.volume_cases(config):
            for budget, options in arms.items():
                record = study.run_volume_case(ct, imager, case, config, iso, options=options, confidence=True,
                                               region=region)  # fmt: skip
                tag = {"study": "volume", "arm": arm, "strength": strength, "seed": args.seed, "case": case.number}
                print(_line(tag, budget, record), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
