"""Two views: the pair's polish on the half-resolution volume (volume level 1, the default) against
the quarter-resolution one (level 2), the same draws both ways in one process.

    PYTHONPATH=. python scripts/pair_polish_level_study.py --seed 3 --moments 10
    PYTHONPATH=. python scripts/pair_polish_level_study.py --seed 4 --moments 8 --ct ../shared/data/real-ct/head-neck-ct

Draws: the biplane study's moments (27 cm phantom 3DRA, or the CT with images formed from it).
Prints one JSON line per draw and arm (seconds, the polish's seconds, the 3-D residual, right and
applied as ``register --confidence`` decides), then each arm's medians.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from registration.core.register import RegistrationOptions
from registration.studies.biplane import BiplaneConfig, biplane_tasks, run_biplane_case


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--moments", type=int, default=10)
    parser.add_argument("--ct", default=None)
    args = parser.parse_args()
    config = BiplaneConfig(patients=((0, 27.0),), registrations_per_patient=args.moments, seed=args.seed,
                           ct_path=args.ct)  # fmt: skip
    base = RegistrationOptions()
    arms = {"level 1": base, "level 2": replace(base, polish=replace(base.polish, volume_level=2))}
    tasks = biplane_tasks(config)
    run_biplane_case(tasks[0].case)  # warm-up: compiled kernels, the cached volume
    rows: dict[str, list[dict]] = {arm: [] for arm in arms}
    for task in tasks:
        for arm, options in arms.items():
            r = run_biplane_case(task.case, options=options)
            polish = sum(s["seconds"] for s in r["stages"] if s["stage"].startswith("polish"))
            line = {"arm": arm, "case": task.case_id, "seconds": round(r["seconds"], 3),
                    "polish_seconds": round(polish, 3),
                    "translation_residual_mm": round(r["translation_residual_mm"], 3),
                    "rotation_residual_deg": round(r["rotation_residual_deg"], 3), "right": bool(r["success"]),
                    "applied": r.get("applied")}  # fmt: skip
            rows[arm].append(line)
            print(json.dumps(line), flush=True)
    for arm, lines in rows.items():

        def med(key: str, lines: list[dict] = lines) -> float:
            return round(float(np.median([x[key] for x in lines])), 3)

        print(json.dumps({"arm": arm, "draws": len(lines), "seconds_median": med("seconds"),
                          "polish_seconds_median": med("polish_seconds"),
                          "translation_residual_mm_median": med("translation_residual_mm"),
                          "translation_residual_mm_max": max(x["translation_residual_mm"] for x in lines),
                          "rotation_residual_deg_median": med("rotation_residual_deg"),
                          "right": sum(x["right"] for x in lines),
                          "applied": sum(bool(x["applied"]) for x in lines)}))  # fmt: skip


if __name__ == "__main__":
    main()
