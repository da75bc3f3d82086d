"""The same draws registered with the capture level as it is and changed (a shorter annealing
schedule: fewer temperature stages or fewer moves per stage; or other images and volume level);
each estimate assessed as ``register --confidence``.

python scripts/capture_schedule_study.py runs --seed 50 --cases 10 --out tune-runs.jsonl
python scripts/capture_schedule_study.py volume --seed 80 --cases 20 --out tune-ct.jsonl
python scripts/capture_schedule_study.py table1 --seed 0 --out tune-t1.jsonl
python scripts/capture_schedule_study.py biplane --seed 3 --cases 12 --out fresh-biplane.jsonl
python scripts/capture_schedule_study.py capture --seed 9 --cases 10 --mm 50 --out fresh-50mm.jsonl

``runs``: the rotational-run study (``roadmap3d validate clinical --quick``, ``--cases``
registrations per patient); ``volume``: the shared real CT's clinical-looking images
(``roadmap3d validate volume --realism clinical``, single plane, ``--strength``); ``table1``:
Table I's four offsets on the phantom (27 cm, fluoro), ``--cases`` seeds from ``--seed``;
``biplane``: the biplane study's quick moments (``roadmap3d validate biplane --quick``: the
phantom, both planes and plane A alone, ``--cases`` moments); ``capture``: the capture-range
study's phantom moments at a translation of ``--mm`` (and a
rotation of ``--deg``), registered biplane and on plane A alone, ``--cases`` moments.
``--variants``: which schedules, as NAME=STAGESxMOVES (the default: 14x14, 11x14, 14x10, 10x12),
optionally at another image size and volume level, NAME=STAGESxMOVES@PIXELS/LEVEL (``c64=14x14@64/2``:
the default schedule on 64-pixel images of the volume's level 2); NAME=refine@PIXELS/LEVEL: the
capture as it is and the refinement level (the annealing after it) at other images and volume level.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from variant_draws import write_biplane, write_capture, write_runs, write_volume

from registration.core.register import RegistrationOptions

KEYS = ("inplane_residual_mm", "outofplane_residual_mm", "rotation_residual_deg", "success", "applied",
        "confidence", "drr_count", "seconds")  # fmt: skip


CAPTURE_KEYS = ("success", "applied", "translation_residual_mm", "single_success_inplane", "single_applied",
                "single_inplane_residual_mm", "drr_count", "seconds", "withheld_reason")  # fmt: skip


BIPLANE_KEYS = (*CAPTURE_KEYS, "rotation_residual_deg", "single_rotation_residual_deg")


def variants(spec: list[str]) -> dict[str, RegistrationOptions]:
    base = RegistrationOptions()
    out = {}
    for item in spec:
        name, _, spec_ = item.partition("=")
        shape, _, where = spec_.partition("@")
        if shape == "refine":  # the refinement level at other images and volume level
            px, level = (int(v) for v in where.split("/"))
            refine = replace(base.levels[1], image_px=px, volume_level=level)
            out[name] = replace(base, levels=(base.levels[0], refine, *base.levels[2:]))
            continue
        stages, moves = (int(v) for v in shape.split("x"))
        capture = base.levels[0]
        if where:
            px, level = (int(v) for v in where.split("/"))
            capture = replace(capture, image_px=px, volume_level=level)
        schedule = replace(capture.schedule, stages=stages, moves_per_stage=moves)
        out[name] = replace(base, levels=(replace(capture, schedule=schedule), *base.levels[1:]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("runs", "volume", "table1", "biplane", "capture"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=10)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--mm", type=float, default=50.0)
    ap.add_argument("--deg", type=float, default=0.0)
    ap.add_argument("--variants", nargs="+", default=["s14m14=14x14", "s11m14=11x14", "s14m10=14x10", "s10m12=10x12"])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    options = variants(args.variants)
    with args.out.open("a") as fh:
        if args.study == "runs":
            write_runs(fh, args.seed, args.cases, options, KEYS)
        elif args.study == "capture":
            write_capture(fh, args.seed, args.cases, args.mm, args.deg, options, CAPTURE_KEYS)
        elif args.study == "biplane":
            write_biplane(fh, args.seed, args.cases, options, BIPLANE_KEYS)
        elif args.study == "table1":
            from registration.core.geometry import TABLE_I
            from registration.studies.cases import Case, run_case

            for seed in range(args.seed, args.seed + args.cases):
                for n, offset in enumerate(TABLE_I):
                    case = Case(offset=offset, image_kind="fluoro", volume_format_cm=27.0, image_format_cm=27.0,
                                seed=seed)  # fmt: skip
                    line = {"study": "table1", "seed": seed, "case": n}
                    for name, o in options.items():
                        record = run_case(case, options=o)
                        line[name] = {k: record.get(k) for k in KEYS}
                    fh.write(json.dumps(line) + "\n")
                    fh.flush()
        else:
            write_volume(fh, args.seed, args.cases, args.strength, options, KEYS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
