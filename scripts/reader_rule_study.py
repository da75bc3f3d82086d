"""One rule of the field reader, on and off, on the same clinical-looking images: the shared real
CT's draws of ``roadmap3d validate volume --realism clinical`` (single plane), each written as the
XA file a system sends and read back twice, with the reader as shipped and with the rule left
out; where the two masks differ both are registered and assessed as ``register --confidence``
does (where they agree, once). Per draw: the pixels each mask keeps behind the rectangular blades
(the simulation's truth) and each registration's residual and decision.

python scripts/reader_rule_study.py --seed 180 --cases 100 --strength 1 --out s180.jsonl
Rules: ``outside-edges`` (:func:`registration.io.field.find_outside_edges`).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from variant_draws import clinical_draws, shared_real_ct

import registration.io.field as field
from registration.core.assess import assess
from registration.core.preparation import Preparation
from registration.core.register import RegistrationOptions, register
from registration.io import dicom
from registration.sim.clinical.detector import blade_maps
from registration.studies.cases import assessment_fields
from registration.studies.volume import _views, case_motion, volume_cases

RULES = {"outside-edges": "find_outside_edges"}


def _read(path: Path, iso: tuple[float, float, float], without: str | None):  # noqa: ANN202
    """The XA file read back, with the reader's rule ``without`` (a function of the field module)
    replaced by one that finds nothing."""
    kept = getattr(field, without) if without else None
    try:
        if without:
            setattr(field, without, lambda *a, **k: [])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DISP read as LOG
            return dicom.read_xray(path, isocenter_mm=iso)
    finally:
        if without:
            setattr(field, without, kept)


def _registered(volume, view, truth: np.ndarray, seed: int, options: RegistrationOptions) -> dict:  # noqa: ANN001
    preparation = Preparation.of(volume, [view], options=options)
    r = register(volume, [view], truth=truth, seed=seed, options=options, renderer=preparation.prepared.renderer)
    found = assessment_fields(assess(r, [view], preparation))
    res = r.residual
    return {"success": bool(res.inplane_mm < 1.0 and res.rotation_deg < 3.0), "inplane_mm": round(res.inplane_mm, 3),
            "rotation_deg": round(res.rotation_deg, 3), "applied": found["applied"],
            "confidence": round(found["confidence"], 3), "mask_px": int(view.mask.sum())}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--rule", choices=sorted(RULES), default="outside-edges")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    found = shared_real_ct()
    if found is None:
        return 2
    volume, iso = found
    config, views = clinical_draws(volume, iso, args.seed, args.cases, args.strength)
    blades = views.effects.blades
    options = RegistrationOptions()
    with tempfile.TemporaryDirectory(prefix="roadmap3d-rule-") as tmp, args.out.open("w") as fh:
        for case in volume_cases(config):
            truth = case_motion(case, iso)
            geometry = _views(config, case, iso)[0]
            image = views.imager.image(geometry, truth, kind=config.kind, seed=case.seed)
            path = image.write_dicom(Path(tmp) / "xa.dcm")
            shipped, without = _read(path, iso, None), _read(path, iso, RULES[args.rule])
            behind = ~blade_maps(geometry, replace(blades, shapes=("rectangular",)))[1] if blades else None
            row: dict = {"seed": args.seed, "case": case.number, "strength": args.strength, "rule": args.rule,
                         "masks_differ_px": int((shipped.mask != without.mask).sum())}  # fmt: skip
            row["shipped"] = _registered(volume, shipped, truth, case.seed, options)
            row["without"] = (dict(row["shipped"]) if row["masks_differ_px"] == 0
                              else _registered(volume, without, truth, case.seed, options))  # fmt: skip
            for name, view in (("shipped", shipped), ("without", without)):
                row[name]["kept_behind_blades_px"] = None if behind is None else int((view.mask & behind).sum())
                row[name]["anatomy_px"] = int((view.mask & image.field).sum())
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            brief = {n: [row[n][k] for k in ("inplane_mm", "applied", "kept_behind_blades_px")]
                     for n in ("shipped", "without")}  # fmt: skip
            print(json.dumps({"case": row["case"], "masks_differ_px": row["masks_differ_px"]} | brief), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
