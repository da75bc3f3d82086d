"""The confidence's cost on the real CT: the stopping depth scan against the strided one,
interleaved on each registration (same process, same estimate), with the registration's seconds.

ROADMAP3D_REAL_CT=DIR python scripts/confidence_cost_ab.py CASES SEED > out.jsonl
"""

import json
import sys
import time

import numpy as np

import registration.core.depth as depth
import registration.studies.volume as vol
from registration.core.assess import assess
from registration.core.roi import followed_region
from registration.io import dicom
from registration.studies.volume import VolumeImager, VolumeStudyConfig, run_volume_case, volume_cases
from registration.studies.volume_bench import find_real_ct, head_isocenter_mm

cases, seed, rounds = int(sys.argv[1]), int(sys.argv[2]), 3
volume = dicom.read_volume(find_real_ct())
iso = head_isocenter_mm(volume)
config = VolumeStudyConfig(cases=cases, seed=seed)
imager = VolumeImager(volume, iso)
region = followed_region(volume, config.roi)
shipped = depth.depth_scan
rows = []


def timed_assess(result, images, preparation):
    out = {}
    for r in range(rounds):
        for name in ("new", "old") if r % 2 == 0 else ("old", "new"):
            depth.depth_scan = shipped if name == "new" else (lambda *a, **k: shipped(*a, **{**k, "below_mm": None}))
            t = time.perf_counter()
            a = assess(result, images, preparation)
            dt = time.perf_counter() - t
            o = out.setdefault(
                name,
                {
                    "s": [],
                    "decision": (a.applied, round(a.confidence, 6)),
                    "drr": a.depth_scan.drr_count if a.depth_scan else None,
                },
            )
            o["s"].append(dt)
    depth.depth_scan = shipped
    rows.append(out)
    return {
        "confidence": 0,
        "applied": out["new"]["decision"][0],
        "withheld_reason": None,
        "confidence_evidence": {},
        "confidence_seconds": 0,
    }


vol._assessed = timed_assess
for case in volume_cases(config):
    rec = run_volume_case(volume, imager, case, config, iso, confidence=True, region=region)
    o = rows[-1]
    line = {
        "case": case.number,
        "reg_s": rec["seconds"],
        "new_min": min(o["new"]["s"]),
        "old_min": min(o["old"]["s"]),
        "new_med": float(np.median(o["new"]["s"])),
        "old_med": float(np.median(o["old"]["s"])),
        "same": o["new"]["decision"] == o["old"]["decision"],
        "decision": o["new"]["decision"],
        "scan_drr": (o["new"]["drr"], o["old"]["drr"]),
    }
    print(json.dumps(line), flush=True)
