"""The neck's pixels left out of the measure, or not: the shared real CT's clinical-looking images
(`validate volume --realism clinical`'s draws, written as XA files and read back), each registered
to the whole CT with every pixel of the field ("none"), without the pixels that see mostly the
slab below the skull base ("slab", `register`'s default), and without those that see mostly what
lies below it and behind a coronal plane FRONT mm in front of the spine's centre ("posterior");
each estimate assessed as `register --confidence` does.

python scripts/head_pixels_study.py --seed 200 --strength 1 --cases 40 [--only 18] [--front 20]
Prints one JSON line per draw: {"case", "none": {...}, "slab": {...}, "posterior": {...}}.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from variant_draws import clinical_draws, shared_real_ct

import registration.core.roi as roi
import registration.studies.volume as study
from registration.core.assess import assess
from registration.core.preparation import Preparation
from registration.core.register import register
from registration.studies.cases import assessment_fields


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=200)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--only", default="", help="comma-separated case numbers (default: every case)")
    ap.add_argument("--front", type=float, default=20.0, help="the posterior arm's plane, mm in front of the spine")
    args = ap.parse_args()
    found = shared_real_ct()
    if found is None:
        return 2
    volume, iso = found
    only = {int(n) for n in args.only.split(",") if n}
    config, views = clinical_draws(volume, iso, args.seed, max(only | {args.cases - 1}) + 1, args.strength)
    region = roi.followed_region(volume, "cranium")
    slab = roi.outside_voxels

    def posterior(vol, reg):  # noqa: ANN001, ANN202 - roi.outside_voxels's signature
        out = slab(vol, reg)
        if not out.any():
            return out
        a = vol.index_to_world
        y_spine = a[1, 1] * np.nonzero(~reg.mask)[1].mean() + a[1, 3]
        y = a[1, 1] * np.arange(vol.shape[1]) + a[1, 3]
        return out & (y > y_spine - args.front)[None, :, None]

    for case in study.volume_cases(config):
        if (only and case.number not in only) or (not only and case.number >= args.cases):
            continue
        truth = study.case_motion(case, iso)
        images, _ = views.views(study._views(config, case, iso), truth, kind=config.kind, seed=case.seed)
        row: dict = {"case": case.number}
        for name in ("none", "slab", "posterior"):
            roi.outside_voxels = posterior if name == "posterior" else slab
            roi._PARTS.clear()  # noqa: SLF001 - the coarse parts depend on the arm's outside
            narrowed, fields = roi.region_views(volume, None if name == "none" else region, images)
            preparation = Preparation.of(volume, narrowed)
            r = register(volume, narrowed, truth=truth, seed=case.seed, renderer=preparation.renderer)
            decided = assessment_fields(assess(r, narrowed, preparation))
            res = r.residual
            row[name] = {"ok": bool(res.inplane_mm < 1.0 and res.rotation_deg < 3.0), "ip": round(res.inplane_mm, 3),
                         "rot": round(res.rotation_deg, 3), "applied": decided["applied"],
                         "left_out_px": [f.left_out_px for f in fields]}  # fmt: skip
        roi.outside_voxels = slab
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
