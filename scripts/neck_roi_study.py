"""A bent neck and the cranium region: the shared real CT's images with the neck bent
(registration.sim.clinical's Neck: flexion at C1/C2, the spine following part of the motion),
registered to the whole CT and to its cranium (registration.core.roi), single plane; after the
cranium's registration the skull-and-spine check (registration.core.skull_spine) from its estimate.

python scripts/neck_roi_study.py --cases 6 --seed 23 --flexion 5
Prints one JSON line per registration and a summary per arm.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from variant_draws import shared_real_ct

from registration.core.register import RegistrationOptions, register
from registration.core.roi import cranium_region, roi_volume
from registration.core.skull_spine import skull_spine_check
from registration.sim.clinical import ClinicalEffects, ClinicalImager, Neck
from registration.studies.volume import VolumeStudyConfig, _views, case_motion, volume_cases


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=6)
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--flexion", type=float, default=5.0)
    ap.add_argument("--rotation", type=float, default=0.0)
    args = ap.parse_args()
    found = shared_real_ct()
    if found is None:
        return 2
    volume, iso = found
    roi = cranium_region(volume)
    arms = {"whole": volume, "cranium": roi_volume(volume, roi)}
    neck = Neck(flexion_deg=args.flexion, rotation_deg=args.rotation)
    imager = ClinicalImager(volume, iso, ClinicalEffects(neck=neck), catheter=True)
    config = VolumeStudyConfig(cases=args.cases, seed=args.seed)
    out: dict = {name: [] for name in arms}
    print(
        json.dumps({"roi": roi.summary(), "neck": vars(neck) if hasattr(neck, "__dict__") else str(neck)}), flush=True
    )
    for case in volume_cases(config):
        geometry = _views(config, case, iso)[0]
        truth = case_motion(case, iso)
        image = imager.image(geometry, truth, seed=case.seed).clean_xray()
        for name, vol in arms.items():
            r = register(vol, image, truth=truth, seed=case.seed, options=RegistrationOptions())
            res = r.residual
            ok = bool(res.inplane_mm < 1.0 and res.rotation_deg < 3.0)
            out[name].append((ok, res.inplane_mm))
            row = {"case": case.number, "arm": name, "inplane_mm": round(res.inplane_mm, 3),
                   "rotation_deg": round(res.rotation_deg, 3), "success": ok}  # fmt: skip
            if name == "cranium":
                check = skull_spine_check(volume, image, r.patient_motion, seed=case.seed)
                row["skull_spine"] = {k: v for k, v in check.to_dict().items() if k != "whole_volume_motion"}
            print(json.dumps(row), flush=True)
    for name, rows in out.items():
        inplane = [r[1] for r in rows]
        print(json.dumps({"arm": name, "success": f"{sum(r[0] for r in rows)}/{len(rows)}",
                          "median_inplane_mm": round(float(np.median(inplane)), 3),
                          "worst_inplane_mm": round(float(max(inplane)), 3)}))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
