"""How much of the severe clinical images' low recall the field detection costs: the shared real
CT's clinical-looking images (``roadmap3d validate volume --realism clinical``, single plane)
registered and assessed as ``register --confidence`` does, once with the mask the reader finds
and once with that mask cut to the true open field (the simulation's, an oracle no user has).

python scripts/field_oracle_study.py --seed 80 --cases 20 --strength 2 --mask found --out found.jsonl
python scripts/field_oracle_study.py --seed 80 --cases 20 --strength 2 --mask true --out true.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import registration.studies.volume as study
from registration.io import dicom


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--strength", type=float, default=2.0)
    ap.add_argument("--mask", choices=("found", "true"), required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.mask == "true":
        found_views = study.ClinicalViews.views

        def true_field_views(self, geometries, motion, *, kind, seed):  # noqa: ANN001, ANN202
            images, notes = found_views(self, geometries, motion, kind=kind, seed=seed)
            fields = [self.imager.image(g, motion, kind=kind, seed=seed + n).field for n, g in enumerate(geometries)]
            return [dataclasses.replace(v, mask=v.mask & f) for v, f in zip(images, fields, strict=True)], notes

        study.ClinicalViews.views = true_field_views
    volume = dicom.read_volume(study.find_real_ct())
    iso = study.head_isocenter_mm(volume)
    config = study.VolumeStudyConfig(cases=args.cases, seed=args.seed, realism="clinical", strengths=(args.strength,))
    records = study.run_volume_study(volume, iso, config)[0]
    with args.out.open("w") as fh:
        for r in records:
            fh.write(json.dumps({"mask": args.mask, **r}, default=str) + "\n")
    right = sum(r["success"] for r in records)
    applied = sum(r["applied"] for r in records)
    wrong = sum(r["applied"] and not r["success"] for r in records)
    print(f"{args.mask} mask: {right}/{len(records)} right, {applied} applied, {wrong} applied wrong")
    return 0


if __name__ == "__main__":
    sys.exit(main())
