"""Two views: the beam scan before the fine polish on level 0 (the fine polish's images) against
level 1 (half those images), on the nine quick capture moments the scan brought right (records
``docs/validation/capture/beam-scan/``), both ways at this revision.

    PYTHONPATH=. python scripts/beam_scan_level_study.py > fixed-by-the-scan-quick.jsonl

One JSON line per moment and arm: right (3-D criterion), applied, the 3-D residual, DRRs, seconds,
and the scan's rays and seconds.
"""

import dataclasses
import json

from registration.core.register import RegistrationOptions
from registration.core.register.options import StartOptions
from registration.studies.capture import CaptureConfig, capture_tasks
from registration.studies.execution import execute

MOMENTS = [
    ("translation", 40, 0, 28, 3),
    ("translation", 50, 0, 27, 8),
    ("translation", 50, 0, 28, 0),
    ("translation", 50, 0, 28, 3),
    ("translation", 50, 0, 29, 9),
    ("translation", 50, 0, 31, 1),
    ("translation", 50, 0, 32, 0),
    ("translation", 50, 0, 32, 8),
    ("combined", 40, 20, 27, 5),
]
arms = {
    "beam scan on level 0": RegistrationOptions(),
    "beam scan on level 1": RegistrationOptions(start=StartOptions(beam_scan_level=1)),
}
for sweep, mm, deg, seed, r in MOMENTS:
    config = dataclasses.replace(
        CaptureConfig.quick_config(seed=seed),
        sweeps=(sweep,),
        translations_mm=(mm,),
        rotations_deg=(deg,),
        registrations_per_level=r + 1,
    )
    for arm, options in arms.items():
        task = capture_tasks(config, options)[r]
        rec = execute(task)
        scan = [s for s in rec["stages"] if s["stage"].startswith("beam scan")]
        print(
            json.dumps(
                {
                    "arm": arm,
                    "case": task.case_id,
                    "right": bool(rec["success"]),
                    "applied": rec.get("applied"),
                    "translation_residual_mm": round(rec["translation_residual_mm"], 3),
                    "drrs": rec["drr_count"],
                    "seconds": round(rec["seconds"], 3),
                    "scan_rays": sum(s["rays"] for s in scan),
                    "scan_seconds": round(sum(s["seconds"] for s in scan), 3),
                }
            ),
            flush=True,
        )
