"""The depth-corrected single-plane registration against the five-parameter one, same process.

Run: ``python benchmarks/depth_correction_ab.py [--cases 20] [--phantom]`` (the real CT needs
../shared/data/real-ct/head-neck-ct; ``--phantom``: Table I's 16 cases instead, 512 px).

For each case of ``roadmap3d validate volume`` (seed 0: 384-px fluoro images of a 27 cm format
formed from the CT itself, trilinear, Beer-Lambert, noise, catheter: a best case) the volume is
prepared once and registered with ``RegistrationOptions.depth_correction`` off and on, the order
alternated per case (ABBA); it prints JSON with the per-case medians of the time and DRR ratios
(on / off), the DRR samples (the work, whatever the machine's load) and the residuals of each.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np

from registration.core.prepare import Reach, prepare_volume
from registration.core.register import RegistrationOptions, register


def _real_ct_cases(n: int):  # noqa: ANN202
    from registration.io import dicom
    from registration.studies.volume import (
        VolumeImager,
        VolumeStudyConfig,
        _views,
        case_motion,
        find_real_ct,
        volume_cases,
    )

    path = find_real_ct()
    if path is None:
        raise SystemExit("error: the real head CT is not here (../shared/data/real-ct/head-neck-ct)")
    volume = dicom.read_volume(path)
    iso = (247.5, -276.0, -90.0)
    config = VolumeStudyConfig(cases=n)
    imager = VolumeImager(volume, iso)
    for case in volume_cases(config):
        (g,) = _views(config, case, iso)
        truth = case_motion(case, iso)
        image = imager.image(g, truth, kind=config.kind, seed=case.seed)
        reach = Reach.of_search(30.0, 15.0, isocenter_mm=iso, translations=2)
        prepared = prepare_volume(volume, [g], reach=reach, levels=[1, 2])
        yield f"ct{case.number}", volume, image, truth, case.seed, prepared.renderer


def _phantom_cases():  # noqa: ANN202
    from registration.core.geometry import CArm, offsets_to_matrix
    from registration.core.preparation import Preparation
    from registration.sim.xray import simulate_xray
    from registration.studies.cases import _phantom, case_volume, offset_vector, table1_cases

    for case in table1_cases():
        g = CArm.for_format(case.image_format_cm, pixels=case.image_pixels, primary_deg=case.primary_deg,
                            secondary_deg=case.secondary_deg)  # fmt: skip
        truth = offsets_to_matrix(offset_vector(case.offset), g)
        volume = case_volume(case)
        xray = simulate_xray(_phantom(case.phantom_seed, False, case.facial), g, motion=truth, kind=case.image_kind,
                             seed=case.seed)  # fmt: skip
        yield f"{case.offset}-{case.image_kind}", volume, xray, truth, case.seed, Preparation.of(volume, xray).renderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--phantom", action="store_true")
    args = parser.parse_args()
    on, off = RegistrationOptions(), RegistrationOptions(depth_correction=False)
    rows = []
    cases = _phantom_cases() if args.phantom else _real_ct_cases(args.cases)
    for n, (name, volume, image, truth, seed, renderer) in enumerate(cases):
        out = {}
        for which in ("off", "on") if n % 2 == 0 else ("on", "off"):
            options = on if which == "on" else off
            samples0 = sum(renderer.samples_per_level)
            t0 = time.perf_counter()
            result = register(volume, image, truth=truth, seed=seed, options=replace(options), renderer=renderer)
            seconds = time.perf_counter() - t0
            r = result.residual
            out[which] = {
                "seconds": seconds,
                "drrs": result.drr_count,
                "samples": sum(renderer.samples_per_level) - samples0,
                "inplane_mm": r.inplane_mm,
                "outofplane_mm": r.outofplane_mm,
                "rotation_deg": r.rotation_deg,
                "success": bool(r.success),
                "depth_tz_mm": result.depth_tz_mm,
            }
        rows.append({"case": name, **out})
        print(json.dumps(rows[-1]), flush=True)

    def med(which: str, key: str) -> float:
        return float(np.median([r[which][key] for r in rows]))

    summary = {
        "cases": len(rows),
        "time_ratio_median": float(np.median([r["on"]["seconds"] / r["off"]["seconds"] for r in rows])),
        "drr_ratio_median": float(np.median([r["on"]["drrs"] / r["off"]["drrs"] for r in rows])),
        "samples_ratio_median": float(np.median([r["on"]["samples"] / r["off"]["samples"] for r in rows])),
        **{
            f"{w}_{k}": med(w, k)
            for w in ("off", "on")
            for k in ("seconds", "drrs", "inplane_mm", "outofplane_mm", "rotation_deg")
        },  # fmt: skip
        "off_success": int(sum(r["off"]["success"] for r in rows)),
        "on_success": int(sum(r["on"]["success"] for r in rows)),
        "off_inplane_max_mm": float(max(r["off"]["inplane_mm"] for r in rows)),
        "on_inplane_max_mm": float(max(r["on"]["inplane_mm"] for r in rows)),
    }
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
