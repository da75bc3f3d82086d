"""``roadmap3d bench``: speed measured as ratios against references in the same run.

DRRs beside the scipy reference renderer, gradient difference, registration over Table I
(27/27 cm, fluoro), biplane registration, the FDK reconstruction when available, and the peak resident memory.
"""

from __future__ import annotations

import os
import platform
import resource
from collections.abc import Callable

import numpy as np

from registration import __version__


def _peak_rss_mb() -> float:
    # ru_maxrss is in kilobytes on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_registration(*, seed: int = 0, repeats: int = 1) -> dict:
    """Registration time over T1-T4 on 27/27 cm fluoro images (phantom and volume cached first)."""
    from registration.core.geometry import TABLE_I
    from registration.studies.cases import Case, run_case

    cases = [
        Case(offset=o, image_kind="fluoro", volume_format_cm=27.0, image_format_cm=27.0, seed=seed + r)
        for r in range(repeats)
        for o in TABLE_I
    ]
    run_case(cases[0])  # warm-up: compiles, builds the cached phantom and volume
    runs = [run_case(c) for c in cases]
    return {
        "seconds_median": float(np.median([r["seconds"] for r in runs])),
        "success_rate": float(np.mean([r["success"] for r in runs])),
        "runs": [
            {
                "offset": r["offset"],
                "seconds": r["seconds"],
                "drr_count": r["drr_count"],
                "inplane_residual_mm": r["inplane_residual_mm"],
                "rotation_residual_deg": r["rotation_residual_deg"],
                "success": r["success"],
            }
            for r in runs
        ],
    }


def bench_biplane(*, seed: int = 0, repeats: int = 4) -> dict:
    """Biplane registration time: the first moments of the biplane study (27 cm 3DRA, plane A
    512 px, plane B 384 px, clinical offsets), after a warm-up registration."""
    from registration.studies.biplane import BiplaneConfig, biplane_tasks, run_biplane_case

    tasks = biplane_tasks(BiplaneConfig(patients=((0, 27.0),), registrations_per_patient=repeats + 1, seed=seed))
    run_biplane_case(tasks[0].case)  # warm-up: compiles, builds the cached volume and plane B's calibration
    runs = [run_biplane_case(t.case) for t in tasks[1:]]
    return {
        "seconds_median": float(np.median([r["seconds"] for r in runs])),
        "success_rate": float(np.mean([r["success"] for r in runs])),
        "runs": [
            {
                "seconds": r["seconds"],
                "drr_count": r["drr_count"],
                "translation_residual_mm": r["translation_residual_mm"],
                "outofplane_residual_mm": r["outofplane_residual_mm"],
                "rotation_residual_deg": r["rotation_residual_deg"],
                "success": r["success"],
            }
            for r in runs
        ],
    }


def collect(*, quick: bool = False, seed: int = 0, log: Callable[[str], None] | None = None) -> dict:
    """Every measurement of ``roadmap3d bench`` as one JSON-ready dict; ``log`` hears progress."""
    from registration.studies.perf import bench_drr, bench_gradient_difference

    say = log or (lambda _msg: None)
    sizes = ((64, 64), (128, 128)) if quick else ((64, 64), (128, 128), (256, 256))
    say("DRR renderer vs scipy reference ...")
    drr = bench_drr(sizes=sizes, repeats=5 if quick else 30)
    say("gradient difference ...")
    gd_ms = bench_gradient_difference()
    say("registration over T1-T4 (27/27 cm, fluoro) ...")
    reg = bench_registration(seed=seed)
    say("biplane registration (27 cm 3DRA, two planes, clinical offsets) ...")
    biplane = bench_biplane(seed=seed, repeats=2 if quick else 4)
    from registration.studies.tracking import bench_tracking

    say("tracking a 20 s fluoro run at its frame times ...")
    out: dict = {
        "drr": drr,
        "gradient_difference_ms_median": gd_ms,
        "registration": reg,
        "biplane": biplane,
        "tracking": bench_tracking(seed=seed),
    }
    from registration.studies.volume import bench_real_volume

    say("registration on the real head CT (../shared) ...")
    out["real_volume"] = bench_real_volume(
        seed=seed, cases=2 if quick else 4, log=say, phantom_seconds=reg["seconds_median"]
    )
    if not quick:
        from registration.sim.reconstruct import bench_reconstruction

        say("FDK reconstruction (120 x 512^2 -> 256^3) ...")
        out["reconstruction"] = bench_reconstruction()
    out["peak_rss_mb"] = _peak_rss_mb()
    out["machine"] = {
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "numba_threads": int(os.environ.get("NUMBA_NUM_THREADS", os.cpu_count() or 1)),
    }
    out["version"] = __version__
    return out
