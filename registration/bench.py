"""``roadmap3d bench``: speed measured as ratios against references in the same run.

DRRs beside the scipy reference renderer, gradient difference, registration over Table I
(27/27 cm, fluoro), the FDK reconstruction when available, and the peak resident memory.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import sys

import numpy as np

from registration import __version__


def _peak_rss_mb() -> float:
    # ru_maxrss is in kilobytes on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_registration(*, seed: int = 0, repeats: int = 1) -> dict:
    """Registration time over T1-T4 on 27/27 cm fluoro images (phantom and volume cached first)."""
    from registration.geometry import TABLE_I
    from registration.validation import Case, run_case

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


def run_bench(*, json: bool = False, quick: bool = False, seed: int = 0) -> int:
    from registration.perf import bench_drr, bench_gradient_difference

    def say(msg: str) -> None:
        if not json:
            print(msg, file=sys.stderr, flush=True)

    sizes = ((64, 64), (128, 128)) if quick else ((64, 64), (128, 128), (256, 256))
    say("DRR renderer vs scipy reference ...")
    drr = bench_drr(sizes=sizes, repeats=5 if quick else 30)
    say("gradient difference ...")
    gd_ms = bench_gradient_difference()
    say("registration over T1-T4 (27/27 cm, fluoro) ...")
    reg = bench_registration(seed=seed)
    out: dict = {
        "drr": drr,
        "gradient_difference_ms_median": gd_ms,
        "registration": reg,
    }
    if not quick:
        try:
            from registration.reconstruct import bench_reconstruction
        except ImportError:
            pass
        else:
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
    if json:
        print(_json_dumps(out))
        return 0
    print("DRR (median ms)        fast    reference   speed-up")
    for row in drr:
        ratio = row["reference_ms_median"] / row["ms_median"]
        print(
            f"  {row['image_px']:>3}^2 from {row['volume_px']:>3}^3  {row['ms_median']:7.2f}  "
            f"{row['reference_ms_median']:10.1f}   {ratio:8.0f}x"
        )
    print(f"gradient difference     {gd_ms:.3f} ms median")
    print(
        f"registration            {reg['seconds_median']:.2f} s median over T1-T4, "
        f"{100 * reg['success_rate']:.0f} % successful"
    )
    if "reconstruction" in out:
        rec = out["reconstruction"]
        print(
            f"reconstruction          {rec['seconds']:.1f} s ({rec['projections']} projections -> {rec['volume_px']}^3)"
        )
    print(f"peak memory             {out['peak_rss_mb']:.0f} MB")
    return 0


def _json_dumps(obj: dict) -> str:
    return json.dumps(obj, default=float)
