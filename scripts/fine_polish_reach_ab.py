"""The two-view fine polish's reach: capture moments registered with a polish of +-3 mm / 2 deg
(the reach before 2026-12-07) and of the default reach, each estimate assessed as ``register
--confidence`` does; one JSON line per moment and arm.

    PYTHONPATH=. python scripts/fine_polish_reach_ab.py 64,65 /50mm-0deg/ old,new > ab.jsonl

Arguments: the capture study's seeds (the draws of ``validate capture --sweep translation
--registrations 20 --seed S``), parts of the case ids to register (comma-separated) and the arms.
Records in docs/validation/capture/fine-polish-reach/.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor

from registration.core.register import RegistrationOptions

DEFAULT = RegistrationOptions()
ARMS = {
    "old": dataclasses.replace(
        DEFAULT, start=dataclasses.replace(DEFAULT.start, fine_polish_reach_mm=3.0, fine_polish_reach_deg=2.0)
    ),
    "new": DEFAULT,
}


def _config(seed: int):  # noqa: ANN202
    from registration.studies.capture import CaptureConfig

    return dataclasses.replace(CaptureConfig(seed=seed), sweeps=("translation",), registrations_per_level=20)


def run(job: tuple[int, str, str]) -> str:
    from registration.core.assess import assess
    from registration.core.register import register
    from registration.studies.biplane import _offset_motion, case_preparations, case_views, study_volume
    from registration.studies.capture import capture_tasks

    seed, case_id, arm = job
    options = ARMS[arm]
    case = next(t for t in capture_tasks(_config(seed)) if t.case_id == case_id).case
    volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
    motion = _offset_motion(case)
    views, _ = case_views(case, volume, motion)
    pair, _ = case_preparations(case, volume, views, options)
    t0 = time.perf_counter()
    both = register(volume, list(views), truth=motion, seed=case.seed, options=options, renderer=pair.renderer)
    assessment = assess(both, list(views), pair)
    return json.dumps({
        "case": case_id, "arm": arm, "success": bool(both.residual.success_total),
        "res": round(both.residual.translation_mm, 2), "rot": round(both.residual.rotation_deg, 2),
        "applied": bool(assessment.applied), "conf": round(assessment.confidence, 3), "reason": assessment.reason[:70],
        "drrs": both.drr_count, "s": round(time.perf_counter() - t0, 1), "fine": bool(both.fine_polished),
    })  # fmt: skip


def main() -> None:
    from registration.studies.capture import capture_tasks

    seeds = [int(s) for s in sys.argv[1].split(",")]
    parts, arms = sys.argv[2].split(","), sys.argv[3].split(",")
    jobs = [(seed, t.case_id, arm) for seed in seeds for t in capture_tasks(_config(seed))
            if any(p in t.case_id for p in parts) for arm in arms]  # fmt: skip
    with ProcessPoolExecutor(2, max_tasks_per_child=1) as pool:  # a fresh process per moment
        for line in pool.map(run, jobs):
            print(line, flush=True)


if __name__ == "__main__":
    main()
