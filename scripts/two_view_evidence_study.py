"""Two views far from the machine-based pose: each moment of the capture study registered with
both planes and assessed as ``register --confidence`` does, with the evidence of the assessment.

    PYTHONPATH=. python scripts/two_view_evidence_study.py --mm 50 --seeds 15,16,17
    PYTHONPATH=. python scripts/two_view_evidence_study.py --mm 40 --deg 20 --seeds 18,19

Prints one JSON line per moment: right (3-D criterion), the residual, applied, the confidence,
the withheld reason, the evidence, where the search started (``shift``: mm from the machine-based
pose, 0 when it started there), whether the translation-first candidate was kept, and seconds.
``--rescore`` reads such lines back and counts, per file, the applied estimates and the wrong
ones under the default rule and under the same rule without the ``beam`` term.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time


def run(mm: float, deg: float, seeds: list[int], moments: int) -> None:
    from registration.core.assess import assess
    from registration.core.register import RegistrationOptions, register
    from registration.studies.biplane import _offset_motion, case_preparations, case_views, study_volume
    from registration.studies.capture import CaptureConfig, capture_tasks
    from registration.studies.cases import assessment_fields

    sweep = "combined" if mm and deg else ("rotation" if deg else "translation")
    for seed in seeds:
        config = dataclasses.replace(CaptureConfig.quick_config(seed=seed), sweeps=(sweep,), translations_mm=(mm,),
                                     rotations_deg=(deg,), registrations_per_level=moments)  # fmt: skip
        for task in capture_tasks(config):
            case = task.case
            volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
            motion = _offset_motion(case)
            views, _ = case_views(case, volume, motion)
            options = RegistrationOptions()
            pair, _ = case_preparations(case, volume, views, options)
            start = time.perf_counter()
            result = register(
                volume, list(views), truth=motion, seed=case.seed, options=options, renderer=pair.renderer
            )
            decided = assessment_fields(assess(result, list(views), pair))
            evidence = {k: v for k, v in decided["confidence_evidence"].items() if v is not None}
            print(json.dumps({
                "case": task.case_id, "right": bool(result.residual.success_total),
                "translation_residual_mm": round(result.residual.translation_mm, 3),
                "rotation_residual_deg": round(result.residual.rotation_deg, 3),
                "applied": decided["applied"], "confidence": round(decided["confidence"], 4),
                "reason": decided["withheld_reason"], "evidence": evidence,
                "shift": round(result.start_shift_mm, 1), "translation_first": result.translation_first,
                "seconds": round(time.perf_counter() - start, 2),
            }), flush=True)  # fmt: skip


def rescore(paths: list[str]) -> None:
    from registration.core.confidence import DEFAULT_RULE, Evidence

    rules = {"without the beam term": dataclasses.replace(DEFAULT_RULE, beam_weight=0.0), "default": DEFAULT_RULE}
    for path in paths:
        records = [json.loads(line) for line in open(path)]
        counts = {}
        for name, rule in rules.items():
            applied = [
                r for r in records if "veto" not in r["evidence"] and rule.assess(Evidence(**r["evidence"])).applied
            ]
            counts[name] = {"applied": len(applied), "wrong": sum(not r["right"] for r in applied)}
        right = sum(r["right"] for r in records)
        print(json.dumps({"file": path, "moments": len(records), "right": right, **counts}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mm", type=float, default=50.0)
    parser.add_argument("--deg", type=float, default=0.0)
    parser.add_argument("--seeds", default="15")
    parser.add_argument("--moments", type=int, default=10)
    parser.add_argument("--rescore", nargs="+", metavar="JSONL")
    args = parser.parse_args()
    if args.rescore:
        rescore(args.rescore)
    else:
        run(args.mm, args.deg, [int(s) for s in args.seeds.split(",")], args.moments)


if __name__ == "__main__":
    main()
