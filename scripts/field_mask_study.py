"""How well the reader finds the usable field of clinical-looking images: the shared real CT's
images from the clinical image model (every effect, single plane, the views and offsets of
``roadmap3d validate volume``), written as the XA files a system sends and read back as
``roadmap3d register`` reads them; per image the pixels the reader keeps that the simulation
says carry no anatomy (behind blades, a wedge, under text) and the open field's pixels it drops.

python scripts/field_mask_study.py --seed 110 --cases 30 --strength 2 --out field-s110.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

import registration.studies.volume as study
from registration.io import dicom
from registration.sim.clinical import ClinicalEffects
from registration.sim.clinical.anatomy import patient_only


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--strength", type=float, default=2.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    volume = dicom.read_volume(study.find_real_ct())
    iso = study.head_isocenter_mm(volume)
    config = study.VolumeStudyConfig(cases=args.cases, seed=args.seed, realism="clinical", strengths=(args.strength,))
    effects = tuple(ClinicalEffects.all().names)
    imager = study.ClinicalViews(volume, iso, effects, args.strength, catheter=True, base=patient_only(volume)[0])
    rows = []
    with tempfile.TemporaryDirectory(prefix="roadmap3d-field-") as tmp:
        for case in study.volume_cases(config):
            geometry = study._views(config, case, iso)[0]
            image = imager.imager.image(geometry, study.case_motion(case, iso), kind=config.kind, seed=case.seed)
            path = image.write_dicom(Path(tmp) / "xa.dcm")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # DISP read as LOG
                view = dicom.read_xray(path, isocenter_mm=iso)
            row = {
                "case": case.number,
                "field_px": int(image.field.sum()),
                "kept_without_anatomy_px": int((view.mask & ~image.field).sum()),
                "field_dropped_px": int((image.field & ~view.mask).sum()),
                "mask_from": view.meta.get("mask_from"),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    args.out.write_text("".join(json.dumps(r) + "\n" for r in rows))
    kept = np.array([r["kept_without_anatomy_px"] for r in rows])
    dropped = np.array([r["field_dropped_px"] for r in rows])
    print(f"kept without anatomy: median {np.median(kept):.0f}, mean {kept.mean():.0f}, max {kept.max()}; "
          f"field dropped: median {np.median(dropped):.0f}, max {dropped.max()} (open field median "
          f"{np.median([r['field_px'] for r in rows]):.0f} px)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
