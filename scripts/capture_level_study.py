"""One level of the capture-range study with more moments: the phantom registered biplane and on
plane A alone from a translation of ``--mm`` in a random direction (the quick study's images,
volume and seeds otherwise), each estimate assessed as ``register --confidence`` does.

python scripts/capture_level_study.py --mm 50 --seed 2 --moments 10
Prints one JSON line per moment.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from registration.studies.capture import CaptureConfig, capture_tasks
from registration.studies.execution import execute

KEYS = ("case_id", "offset_translation_mm", "success", "applied", "translation_residual_mm", "single_success_inplane",
        "single_applied", "single_inplane_residual_mm", "withheld_reason")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mm", type=float, default=50.0)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--moments", type=int, default=10)
    args = ap.parse_args()
    config = dataclasses.replace(CaptureConfig.quick_config(seed=args.seed), sweeps=("translation",),
                                 translations_mm=(args.mm,), rotations_deg=(0.0,),
                                 registrations_per_level=args.moments)  # fmt: skip
    for task in capture_tasks(config):
        record = execute(task)
        print(json.dumps({k: record[k] for k in KEYS}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
