"""Plane A alone of the capture study's moments, registered with two sets of options in one
process (arms ``shipped`` and ``early``, flat keywords as JSON), each assessed as
``register --confidence``; one JSON line per moment.

    BASE='{"depth_far_start_mm": null}' VARIANT='{}' \\
        python scripts/capture_single_ab.py translation 30,40,50 0 > far-start-s0.jsonl

Arguments: the sweeps (comma-separated), the levels (mm or degrees), the study seed. Records in
docs/validation/capture/far-start/.
"""

import json
import os
import sys
import time

import numpy as np

from registration.core.assess import assess
from registration.core.preparation import Preparation
from registration.core.register import RegistrationOptions, register
from registration.studies.biplane import _offset_motion, case_views, study_volume
from registration.studies.capture import CaptureConfig, capture_tasks


def main() -> None:
    sweeps, levels = tuple(sys.argv[1].split(",")), {float(x) for x in sys.argv[2].split(",")}
    seed = int(sys.argv[3]) if len(sys.argv) > 3 else 0
    arms = {
        "shipped": RegistrationOptions(**json.loads(os.environ.get("BASE", "{}"))),
        "early": RegistrationOptions(**json.loads(os.environ.get("VARIANT", "{}"))),
    }
    for t in capture_tasks(CaptureConfig(sweeps=sweeps, seed=seed)):
        sweep = t.extra["sweep"]
        level = t.extra["level_translation_mm"] if sweep == "translation" else t.extra["level_rotation_deg"]
        if level not in levels:
            continue
        case = t.case
        volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
        motion = _offset_motion(case)
        views, _ = case_views(case, volume, motion)
        along = abs(float(np.asarray(case.translation_mm) @ views[0].geometry.direction))
        row = {"case_id": t.case_id, "level": level, "oop_off": along}
        for name, options in arms.items():
            prep = Preparation.of(volume, views[0], options=options)
            t0 = time.perf_counter()
            r = register(volume, views[0], truth=motion, seed=case.seed, options=options, renderer=prep.renderer)
            seconds = time.perf_counter() - t0
            a = assess(r, views[0], prep)
            row[name] = {"right": bool(r.residual.success), "inplane": r.residual.inplane_mm,
                         "oop": r.residual.outofplane_mm, "rot": r.residual.rotation_deg, "applied": a.applied,
                         "reason": a.reason, "drr": r.drr_count, "s": seconds, "tz": r.depth_tz_mm,
                         "at_bound": r.depth_at_bound, "start_shift_mm": r.start_shift_mm}  # fmt: skip
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
