"""The whole CT against its cranium on the same clinical-looking images: the shared real CT's
images formed by the clinical image model with every effect (`validate volume --realism clinical`'s
draws, written as XA files and read back), each registered twice, to the whole volume and to the
cranium (registration.core.roi), each estimate assessed as `register --confidence` does.

python scripts/region_compare_study.py --seed 35 --strength 2 --cases 30 [--biplane] [--only 33,46]
Prints one JSON line per draw: {"case", "whole": {...}, "cranium": {...}}.
"""

from __future__ import annotations

import argparse
import json
import sys

from variant_draws import clinical_draws, shared_real_ct

from registration.core.assess import assess
from registration.core.preparation import Preparation
from registration.core.register import RegistrationOptions, register
from registration.core.roi import cranium_region, roi_volume
from registration.studies.cases import assessment_fields
from registration.studies.volume import _views, case_motion, volume_cases


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=35)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--biplane", action="store_true")
    ap.add_argument("--only", default="", help="comma-separated case numbers (default: every case)")
    args = ap.parse_args()
    found = shared_real_ct()
    if found is None:
        return 2
    volume, iso = found
    config, views = clinical_draws(volume, iso, args.seed, args.cases, args.strength, biplane=args.biplane)
    arms = {"whole": volume, "cranium": roi_volume(volume, cranium_region(volume))}
    only = {int(n) for n in args.only.split(",") if n}
    options = RegistrationOptions()
    for case in volume_cases(config):
        if only and case.number not in only:
            continue
        truth = case_motion(case, iso)
        images, _ = views.views(_views(config, case, iso), truth, kind=config.kind, seed=case.seed)
        row: dict = {"case": case.number}
        for name, vol in arms.items():
            preparation = Preparation.of(vol, images, options=options)
            r = register(vol, images, truth=truth, seed=case.seed, options=options,
                         renderer=preparation.prepared.renderer)  # fmt: skip
            res = r.residual
            found = assessment_fields(assess(r, images, preparation))
            ok = res.success_total if args.biplane else (res.inplane_mm < 1.0 and res.rotation_deg < 3.0)
            row[name] = {"ok": bool(ok), "t3": round(res.translation_mm, 3), "ip": round(res.inplane_mm, 3),
                         "rot": round(res.rotation_deg, 3), "applied": found["applied"],
                         "conf": round(found["confidence"], 3)}  # fmt: skip
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
