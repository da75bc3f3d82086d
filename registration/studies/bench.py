"""``roadmap3d bench``: speed measured as ratios against references in the same run.

DRRs beside the scipy reference renderer, gradient difference, registration over Table I
(27/27 cm, fluoro), biplane registration, the real CT and the real XA run when available, the
FDK reconstruction, and the peak resident memory.
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


#: The checks the registration's cost is compared without (same cases, same process, interleaved).
CHECKS_OFF = {"depth_correction": False, "rotation_check": False}


def _spread(values: list[float]) -> dict:
    return {"min": float(np.min(values)), "median": float(np.median(values))}


def stage_costs(runs: list[dict]) -> list[dict]:
    """Per stage of the plan (in the order they ran), the median DRRs, rays and seconds over
    ``runs`` (records with ``stages``) and how many runs ran it."""
    order: list[str] = []
    by_stage: dict[str, list[dict]] = {}
    for run in runs:
        for cost in run.get("stages", ()):
            if cost["stage"] not in by_stage:
                order.append(cost["stage"])
            by_stage.setdefault(cost["stage"], []).append(cost)
    return [
        {
            "stage": name,
            "runs": len(by_stage[name]),
            "drrs_median": float(np.median([c["drrs"] for c in by_stage[name]])),
            "rays_median": float(np.median([c["rays"] for c in by_stage[name]])),
            "seconds_median": float(np.median([c["seconds"] for c in by_stage[name]])),
        }
        for name in order
    ]


def bench_registration(*, seed: int = 0, rounds: int = 3) -> dict:
    """Registration time over T1-T4 on 27/27 cm fluoro images (phantom and volume cached first),
    each case registered with every check and, right after it in the same process, without the
    depth correction and the rotation check (the checks' price as a ratio both runs share the
    machine's load for); ``rounds`` repetitions of the four cases."""
    from registration.core.geometry import TABLE_I
    from registration.core.register import RegistrationOptions
    from registration.studies.cases import Case, run_case

    cases = [
        Case(offset=o, image_kind="fluoro", volume_format_cm=27.0, image_format_cm=27.0, seed=seed + r)
        for r in range(rounds)
        for o in TABLE_I
    ]
    off = RegistrationOptions(**CHECKS_OFF)
    run_case(cases[0])  # warm-up: compiles, builds the cached phantom and volume
    run_case(cases[0], options=off)
    runs, bare = [], []
    for case in cases:  # interleaved: each pair sees the same moment's load
        runs.append(run_case(case))
        bare.append(run_case(case, options=off))
    seconds = [r["seconds"] for r in runs]
    off_seconds = [r["seconds"] for r in bare]
    ratios = [a / b for a, b in zip(seconds, off_seconds, strict=True) if b > 0]
    return {
        "seconds_median": float(np.median(seconds)),
        "seconds_min": float(np.min(seconds)),
        "checks_off_seconds_median": float(np.median(off_seconds)),
        "checks_off_seconds_min": float(np.min(off_seconds)),
        "checks_ratio": {**_spread(ratios), "of_medians": float(np.median(seconds) / np.median(off_seconds))},
        "drr_count_median": float(np.median([r["drr_count"] for r in runs])),
        "checks_off_drr_count_median": float(np.median([r["drr_count"] for r in bare])),
        "success_rate": float(np.mean([r["success"] for r in runs])),
        "checks_off_success_rate": float(np.mean([r["success"] for r in bare])),
        "rounds": rounds,
        "stages": stage_costs(runs),
        "runs": [
            {
                "offset": r["offset"],
                "seconds": r["seconds"],
                "checks_off_seconds": b["seconds"],
                "drr_count": r["drr_count"],
                "inplane_residual_mm": r["inplane_residual_mm"],
                "rotation_residual_deg": r["rotation_residual_deg"],
                "success": r["success"],
            }
            for r, b in zip(runs, bare, strict=True)
        ],
    }


def bench_biplane(*, seed: int = 0, repeats: int = 4) -> dict:
    """Biplane registration time: the first moments of the biplane study (27 cm 3DRA, plane A
    512 px, plane B 384 px, clinical offsets), after a warm-up registration; per stage of the
    plan, the median DRRs, rays and seconds (:func:`stage_costs`)."""
    from registration.studies.biplane import BiplaneConfig, biplane_tasks, run_biplane_case

    tasks = biplane_tasks(BiplaneConfig(patients=((0, 27.0),), registrations_per_patient=repeats + 1, seed=seed))
    run_biplane_case(tasks[0].case)  # warm-up: compiles, builds the cached volume and plane B's calibration
    runs = [run_biplane_case(t.case) for t in tasks[1:]]
    return {
        "seconds_median": float(np.median([r["seconds"] for r in runs])),
        "success_rate": float(np.mean([r["success"] for r in runs])),
        "stages": stage_costs(runs),
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
    drr = bench_drr(sizes=sizes, repeats=4 if quick else 30, rounds=2 if quick else 5)
    say("gradient difference ...")
    gd_ms = bench_gradient_difference()
    say("registration over T1-T4 (27/27 cm, fluoro) ...")
    reg = bench_registration(seed=seed, rounds=1 if quick else 3)
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
    from registration.studies.volume_bench import bench_real_volume

    say("registration on the real head CT (../shared) ...")
    out["real_volume"] = bench_real_volume(
        seed=seed, cases=2 if quick else 4, log=say, phantom_seconds=reg["seconds_median"]
    )
    from registration.studies.run_bench import bench_real_run

    say("reading the real XA run frame by frame (../shared) ...")
    out["real_run"] = bench_real_run(frames=20 if quick else 40)
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
