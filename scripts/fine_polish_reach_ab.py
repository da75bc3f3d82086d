"""The two-view fine polish's reach: capture moments registered with a polish of +-3 mm / 2 deg
(the reach before 2026-12-07) and of the default reach, each estimate assessed as ``register
--confidence`` does; one JSON line per moment and arm.

    PYTHONPATH=. python scripts/fine_polish_reach_ab.py capture 64,65 /50mm-0deg/ old,new > ab.jsonl
    PYTHONPATH=. python scripts/fine_polish_reach_ab.py landmarks 46,47 combined old,new > lm.jsonl

``capture``: the capture study's seeds (the draws of ``validate capture --sweep translation
--registrations 20 --seed S``), parts of the case ids to register (comma-separated) and the arms;
``landmarks``: the quick capture run from four landmarks per plane picked 3 mm off (the draws of
``validate capture --quick --from-landmarks 4 --seed S``), the same arguments; ``ct``: the quick
capture run on the shared real head CT (``validate capture --quick --ct DIR --seed S``, the CT from
``ROADMAP3D_REAL_CT``), the same arguments.
Records in docs/validation/capture/fine-polish-reach/.
"""

from __future__ import annotations

import dataclasses
import json
import os
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


def _config(mode: str, seed: int):  # noqa: ANN202
    from registration.studies.capture import CaptureConfig

    if mode == "landmarks":
        return dataclasses.replace(CaptureConfig.quick_config(seed), landmark_pairs=4)
    if mode == "ct":
        return CaptureConfig.quick_config(seed, ct_path=os.environ["ROADMAP3D_REAL_CT"])
    return dataclasses.replace(CaptureConfig(seed=seed), sweeps=("translation",), registrations_per_level=20)


def run_study(job: tuple[str, int, str, str]) -> str:
    """One moment of a quick capture run, registered and assessed as the study does."""
    from registration.studies.capture import capture_tasks
    from registration.studies.execution import execute

    _, seed, case_id, arm = job
    task = next(t for t in capture_tasks(_config(job[0], seed), ARMS[arm]) if t.case_id == case_id)
    r = execute(task)
    return json.dumps({
        "case": case_id, "arm": arm, "success": bool(r.get("success")), "res": round(r["translation_residual_mm"], 2),
        "rot": round(r["rotation_residual_deg"], 2), "applied": bool(r.get("applied")),
        "reason": r.get("withheld_reason", "")[:70],
        "drrs": r["drr_count"], "s": round(r["seconds"], 1), "single_success_inplane": r.get("single_success_inplane"),
        "single_applied": r.get("single_applied"),
    })  # fmt: skip


def run(job: tuple[str, int, str, str]) -> str:
    if job[0] in ("landmarks", "ct"):
        return run_study(job)
    from registration.core.assess import assess
    from registration.core.register import register
    from registration.studies.biplane import _offset_motion, case_preparations, case_views, study_volume
    from registration.studies.capture import capture_tasks

    _, seed, case_id, arm = job
    options = ARMS[arm]
    case = next(t for t in capture_tasks(_config("capture", seed)) if t.case_id == case_id).case
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

    mode, seeds = sys.argv[1], [int(s) for s in sys.argv[2].split(",")]
    parts, arms = sys.argv[3].split(","), sys.argv[4].split(",")
    jobs = [(mode, seed, t.case_id, arm) for seed in seeds for t in capture_tasks(_config(mode, seed))
            if any(p in t.case_id for p in parts) for arm in arms]  # fmt: skip
    with ProcessPoolExecutor(2, max_tasks_per_child=1) as pool:  # a fresh process per moment
        for line in pool.map(run, jobs):
            print(line, flush=True)


if __name__ == "__main__":
    main()
