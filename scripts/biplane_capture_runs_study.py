"""Two views registered with each plane's capture as it is (two annealing runs per plane) and
with one run per plane, on the same draws; each estimate assessed as ``register --confidence``.

python scripts/biplane_capture_runs_study.py quick --seed 4 --cases 12 --out quick.jsonl
python scripts/biplane_capture_runs_study.py capture --seed 11 --cases 10 --mm 50 --out capture.jsonl
python scripts/biplane_capture_runs_study.py volume --seed 60 --cases 10 --strength 1 --out ct.jsonl

``quick``: the biplane study's quick moments (``roadmap3d validate biplane --quick``);
``capture``: the capture-range study's phantom moments at ``--mm`` and ``--deg``; ``volume``:
the shared real CT's clinical-looking images, both planes (``roadmap3d validate volume --realism
clinical --biplane``, ``--strength``).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from variant_draws import write_biplane, write_capture

from registration.core.register import RegistrationOptions

KEYS = ("success", "applied", "translation_residual_mm", "rotation_residual_deg", "drr_count", "seconds",
        "withheld_reason")  # fmt: skip


def variants() -> dict[str, RegistrationOptions]:
    base = RegistrationOptions()
    return {f"c64r{n}": replace(base, biplane=replace(base.biplane, plane_capture_runs=n)) for n in (2, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("quick", "capture", "volume"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=10)
    ap.add_argument("--mm", type=float, default=50.0)
    ap.add_argument("--deg", type=float, default=0.0)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    options = variants()
    with args.out.open("a") as fh:
        if args.study == "quick":
            write_biplane(fh, args.seed, args.cases, options, KEYS)
        elif args.study == "capture":
            write_capture(fh, args.seed, args.cases, args.mm, args.deg, options, KEYS)
        else:
            import registration.studies.volume as study
            from registration.io import dicom

            volume = dicom.read_volume(study.find_real_ct())
            iso = study.head_isocenter_mm(volume)
            config = study.VolumeStudyConfig(cases=args.cases, seed=args.seed, realism="clinical",
                                             strengths=(args.strength,), biplane=True)  # fmt: skip
            passes = {name: study.run_volume_study(volume, iso, config, options=o)[0] for name, o in options.items()}
            keys = ("success", "applied", "inplane_residual_mm", "rotation_residual_deg", "drr_count", "seconds",
                    "withheld_reason")  # fmt: skip
            for n in range(args.cases):
                line = {"seed": args.seed, "mode": f"volume biplane {args.strength:g}", "case": n}
                for name, records in passes.items():
                    line[name] = {k: records[n].get(k) for k in keys}
                fh.write(json.dumps(line) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
