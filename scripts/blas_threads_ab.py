"""The engine with BLAS on one thread against BLAS on the process's threads, in one process.

Each round runs the bench's measurements once per arm, alternating (``one``: as shipped, the
engine keeps BLAS to one thread while it works; ``process``: the limit replaced by nothing, BLAS
on as many threads as the process has): Table I with and without the checks, the two views'
moments, and the 128-pixel DRR against its reference. Prints one JSON line per round and arm,
then the medians per arm.

    PYTHONPATH=. python scripts/blas_threads_ab.py --rounds 3 > ab.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

import registration.core.blas as blas
from registration.studies.bench import bench_biplane, bench_registration
from registration.studies.perf import bench_drr


class _NoLimit:
    """Stands in for threadpoolctl's limiter: sets and restores nothing."""

    def __init__(self, **_: object) -> None:
        pass

    def restore_original_limits(self) -> None:
        pass


def _round(arm: str, seed: int) -> dict:
    table = bench_registration(seed=seed, rounds=1)
    pair = bench_biplane(seed=seed, repeats=4)
    drr = bench_drr(sizes=[(128, 128)], repeats=30, rounds=5)[0]
    return {
        "arm": arm,
        "table1_s": round(table["seconds_median"], 4),
        "table1_checks_off_s": round(table["checks_off_seconds_median"], 4),
        "table1_success": table["success_rate"],
        "two_views_s": round(pair["seconds_median"], 4),
        "two_views_success": pair["success_rate"],
        "two_views_stages_s": {s["stage"].split(" at ")[0]: round(s["seconds_median"], 4) for s in pair["stages"]},
        "drr_ms_median": drr["ms_median"],
        "drr_ms_min": drr["ms_min"],
        "drr_speedup": drr["speedup"],
        "drr_speedup_of_minima": drr["speedup_of_minima"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    limiter = blas.threadpool_limits
    rows = []
    for _ in range(args.rounds):
        for arm in ("process", "one"):
            blas.threadpool_limits = limiter if arm == "one" else _NoLimit
            rows.append(_round(arm, args.seed))
            print(json.dumps(rows[-1]), flush=True)
    blas.threadpool_limits = limiter
    keys = ("table1_s", "table1_checks_off_s", "two_views_s", "drr_ms_median", "drr_speedup", "drr_speedup_of_minima")
    for arm in ("process", "one"):
        mine = [r for r in rows if r["arm"] == arm]
        print(json.dumps({"arm": arm, "median_of_rounds": {k: float(np.median([r[k] for r in mine])) for k in keys}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
