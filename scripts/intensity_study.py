"""Intensity robustness A/B: clinical display chains (registration.sim.clinical, written as XA
files and read back) registered as read and with the intensities matched to the DRR.

python scripts/intensity_study.py --cases 8 --seed 0 --arms display,contrast,scatter
Prints one JSON line per registration and a summary per arm and mode.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from registration.core.prepare import Reach, prepare_volume
from registration.core.register import RegistrationOptions, register
from registration.io import dicom
from registration.studies.volume import (
    ClinicalViews,
    VolumeStudyConfig,
    _views,
    case_motion,
    find_real_ct,
    head_isocenter_mm,
    volume_cases,
)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arms", default="display")
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--modes", default="as-read,match")
    args = ap.parse_args()
    path = find_real_ct()
    volume = dicom.read_volume(path)
    iso = head_isocenter_mm(volume)
    config = VolumeStudyConfig(cases=args.cases, seed=args.seed)
    options = RegistrationOptions()
    per_mode = {m: RegistrationOptions(intensity=m) for m in ("as-read", "match")}
    summary: dict = {}
    for arm in args.arms.split(","):
        effects = tuple(arm.split("+"))
        views_maker = ClinicalViews(volume, iso, effects, args.strength, catheter=True, base=None)
        for case in volume_cases(config):
            geoms = _views(config, case, iso)
            truth = case_motion(case, iso)
            images, notes = views_maker.views(geoms, truth, kind="fluoro", seed=case.seed)
            geoms = [im.geometry for im in images]
            reach = Reach.of_search(options.bound_mm, options.bound_deg, isocenter_mm=iso, translations=2)
            prepared = prepare_volume(volume, geoms, reach=reach, levels=[1, 2])
            for mode in args.modes.split(","):
                t0 = time.perf_counter()
                r = register(volume, images, truth=truth, seed=case.seed, options=per_mode[mode],
                             renderer=prepared.renderer)  # fmt: skip
                info = r.intensity[0] if r.intensity else None
                res = r.residual
                ok = res.inplane_mm < 1 and res.rotation_deg < 3
                rec = {
                    "arm": arm,
                    "mode": mode,
                    "case": case.number,
                    "inplane_mm": round(res.inplane_mm, 3),
                    "rot_deg": round(res.rotation_deg, 3),
                    "success": ok,
                    "s": round(time.perf_counter() - t0, 2),
                    "match": info,
                    "note": notes.get("intensity_note"),
                }
                print(json.dumps(rec), flush=True)
                s = summary.setdefault(f"{arm}/{mode}", {"n": 0, "ok": 0, "inplane": []})
                s["n"] += 1
                s["ok"] += ok
                s["inplane"].append(res.inplane_mm)
    for k, s in summary.items():
        print(
            json.dumps(
                {
                    "arm": k,
                    "success": f"{s['ok']}/{s['n']}",
                    "median_inplane_mm": round(float(np.median(s["inplane"])), 3),
                    "worst_inplane_mm": round(max(s["inplane"]), 3),
                }
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
