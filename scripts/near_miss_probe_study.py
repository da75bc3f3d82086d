"""Candidate probes for applied near misses on clinical-looking single-plane images.

The shared real CT's images formed by the clinical image model (`validate volume --realism clinical`'s
draws, written as XA files and read back), registered and assessed as `register --confidence` does;
then, at the estimate, each candidate probe:

``restart``: short local searches (``skull_spine.check_options``) started from the estimate moved by
a fixed pattern of in-plane shifts and rotations; how far their ends lie from the estimate (in-plane
at the iso-center, mm) and from each other.
``cranium``: the same local search from the estimate on the cranium alone (the spine left out).

python scripts/near_miss_probe_study.py --seed 130 --strength 1 --cases 100 [--only 52] --out probes.jsonl
Appends one JSON line per draw.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
from variant_draws import clinical_draws, shared_real_ct

from registration.core.assess import assess
from registration.core.geometry import apply, invert_rigid, offsets_to_matrix, rotation_angle_deg
from registration.core.preparation import Preparation
from registration.core.register import RegistrationOptions, register
from registration.core.roi import cranium_region, roi_volume
from registration.core.skull_spine import check_options, spine_pull
from registration.studies.cases import assessment_fields
from registration.studies.volume import _views, case_motion, volume_cases

#: (tx, ty, tz mm, rx, ry, rz deg) in the view frame: where the restarts begin, relative to the estimate.
PATTERN = (
    (2.5, 2.5, 0.0, 0.0, 0.0, 2.5),
    (-2.5, -2.5, 0.0, 0.0, 0.0, -2.5),
    (2.5, -2.5, 0.0, 2.5, -2.5, 0.0),
    (-2.5, 2.5, 0.0, -2.5, 2.5, 0.0),
)


def _variants() -> dict:
    """Cheaper searches for the head-alone probe: the annealing at 64 px and a 30-evaluation
    polish at 96 px; the annealing at 96 px without the polish."""
    from dataclasses import replace

    from registration.core.register.options import PolishOptions

    base = check_options()
    lv = base.levels[0]
    return {
        "a64p96": replace(base, levels=(replace(lv, image_px=64),), polish=PolishOptions(image_px=96, evaluations=30)),
        "a96np": replace(base, polish=PolishOptions(enabled=False)),
    }


VARIANTS = _variants()


def inplane(a: np.ndarray, b: np.ndarray, geometry) -> tuple[float, float]:  # noqa: ANN001
    """In-plane distance at the iso-center (mm) and rotation (deg) between two motions."""
    iso = np.asarray(geometry.isocenter_mm, dtype=np.float64)
    d = apply(a, iso) - apply(b, iso)
    d = d - (d @ geometry.direction) * geometry.direction
    return float(np.linalg.norm(d)), float(rotation_angle_deg(a @ invert_rigid(b)))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=130)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--only", default="", help="comma-separated case numbers (default: every case)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--pull-only", action="store_true", help="only the shipped probe (skull_spine.spine_pull)")
    ap.add_argument("--variants", action="store_true", help="also the probe with cheaper searches (VARIANTS)")
    args = ap.parse_args()
    found = shared_real_ct()
    if found is None:
        return 2
    volume, iso = found
    config, views = clinical_draws(volume, iso, args.seed, args.cases, args.strength)
    cranium = roi_volume(volume, cranium_region(volume))
    only = {int(n) for n in args.only.split(",") if n}
    options = RegistrationOptions()
    local = check_options()
    for case in volume_cases(config):
        if only and case.number not in only:
            continue
        truth = case_motion(case, iso)
        images, _ = views.views(_views(config, case, iso), truth, kind=config.kind, seed=case.seed)
        g = images[0].geometry
        preparation = Preparation.of(volume, images, options=options)
        r = register(volume, images, truth=truth, seed=case.seed, options=options,
                     renderer=preparation.prepared.renderer)  # fmt: skip
        res = r.residual
        found = assessment_fields(assess(r, images, preparation))
        est = np.asarray(r.patient_motion, dtype=np.float64)
        row: dict = {"case": case.number, "seed": args.seed, "strength": args.strength,
                     "ok": bool(res.inplane_mm < 1.0 and res.rotation_deg < 3.0),
                     "ip": round(res.inplane_mm, 3), "rot": round(res.rotation_deg, 3),
                     "applied": found["applied"], "conf": round(found["confidence"], 3),
                     "evidence": found.get("confidence_evidence")}  # fmt: skip
        pull = spine_pull(preparation.prepared, images[0], est)
        row["pull_mm"] = None if pull is None else round(pull.shift_mm, 3)
        row["pull_s"] = None if pull is None else round(pull.seconds, 3)
        row["pull_drrs"] = None if pull is None else pull.drr_count
        row["pull_moves_mm"] = None if pull is None else [round(m, 3) for m in pull.moves_mm]
        for name, variant in VARIANTS.items() if args.variants else ():
            found = spine_pull(preparation.prepared, images[0], est, options=variant)
            row[f"pull_{name}_mm"] = round(found.shift_mm, 3)
            row[f"pull_{name}_moves_mm"] = [round(m, 3) for m in found.moves_mm]
            row[f"pull_{name}_s"] = round(found.seconds, 3)
            row[f"pull_{name}_drrs"] = found.drr_count
        if args.pull_only:
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps({k: row[k] for k in ("case", "ok", "ip", "applied", "pull_mm", "pull_s")}), flush=True)
            continue
        t0 = time.perf_counter()
        ends = []
        for k, p in enumerate(PATTERN):
            start = offsets_to_matrix(p, g) @ est
            e = register(volume, images, initial_motion=start, options=local, seed=case.seed + k,
                         renderer=preparation.prepared.renderer)  # fmt: skip
            ends.append(np.asarray(e.patient_motion, dtype=np.float64))
        row["restart_mm"] = [round(inplane(e, est, g)[0], 3) for e in ends]
        row["restart_deg"] = [round(inplane(e, est, g)[1], 3) for e in ends]
        row["restart_truth_mm"] = [round(inplane(e, truth, g)[0], 3) for e in ends]
        row["restart_spread_mm"] = round(max(inplane(a, b, g)[0] for a in ends for b in ends), 3)
        row["restart_s"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        cprep = Preparation.of(cranium, images, options=options)
        c = register(cranium, images, initial_motion=est, options=local, seed=case.seed,
                     renderer=cprep.prepared.renderer)  # fmt: skip
        cm = np.asarray(c.patient_motion, dtype=np.float64)
        row["cranium_mm"], row["cranium_deg"] = (round(v, 3) for v in inplane(cm, est, g))
        row["cranium_truth_mm"] = round(inplane(cm, truth, g)[0], 3)
        row["cranium_s"] = round(time.perf_counter() - t0, 3)
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps({k: row[k] for k in ("case", "ok", "ip", "applied", "restart_mm", "restart_spread_mm",
                                              "cranium_mm")}), flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
