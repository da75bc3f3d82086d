"""One rule of the field reader, on and off, on the same clinical-looking images: the shared real
CT's draws of ``roadmap3d validate volume --realism clinical`` (single plane), each written as the
XA file a system sends and read back twice, with the reader as shipped and with the rule left
out; where the two masks differ both are registered and assessed as ``register --confidence``
does (where they agree, once). Per draw: the pixels each mask keeps behind the rectangular blades
(the simulation's truth) and each registration's residual and decision (success: in-plane
< 1 mm with one plane, 3-D < 1 mm with two (``--biplane``), and rotation < 3 deg).

python scripts/reader_rule_study.py --seed 180 --cases 100 --strength 1 --out s180.jsonl
python scripts/reader_rule_study.py --seed 170 --strength 1 --figure 1,11,23,39 --out masks.png
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


def _registered(volume, views: list, truth: np.ndarray, seed: int, options: RegistrationOptions) -> dict:  # noqa: ANN001
    preparation = Preparation.of(volume, views, options=options)
    r = register(volume, views, truth=truth, seed=seed, options=options, renderer=preparation.prepared.renderer)
    found = assessment_fields(assess(r, views, preparation))
    res = r.residual
    error = res.inplane_mm if len(views) == 1 else res.translation_mm  # the study's criterion
    return {"success": bool(error < 1.0 and res.rotation_deg < 3.0), "inplane_mm": round(res.inplane_mm, 3),
            "translation_mm": round(res.translation_mm, 3), "rotation_deg": round(res.rotation_deg, 3),
            "applied": found["applied"], "confidence": round(found["confidence"], 3),
            "mask_px": int(sum(v.mask.sum() for v in views))}  # fmt: skip


def _tile(view, behind: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """The image as read (gray), what the mask leaves out dimmed, what it keeps behind the
    rectangular blades red."""
    a = view.image.astype(np.float64)
    lo, hi = np.percentile(a[view.mask], [1, 99])
    gray = np.clip((a - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    rgb = np.repeat(gray[..., None], 3, axis=2)
    rgb[~view.mask] *= 0.3
    red = view.mask & behind
    rgb[red] = 0.5 * rgb[red] + np.array([0.5, 0.0, 0.0])
    return rgb


def figure(seed: int, strength: float, cases: list[int], rule: str, out: Path) -> int:
    """The masks of the draws ``cases`` with the rule left out (top) and as shipped (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    found = shared_real_ct()
    if found is None:
        return 2
    volume, iso = found
    config, views = clinical_draws(volume, iso, seed, max(cases) + 1, strength)
    fig, axes = plt.subplots(2, len(cases), figsize=(3.2 * len(cases), 7.3), squeeze=False)
    with tempfile.TemporaryDirectory(prefix="roadmap3d-rule-") as tmp:
        for k, case in enumerate(c for c in volume_cases(config) if c.number in cases):
            truth = case_motion(case, iso)
            geometry = _views(config, case, iso)[0]
            image = views.imager.image(geometry, truth, kind=config.kind, seed=case.seed)
            path = image.write_dicom(Path(tmp) / "xa.dcm")
            behind = ~blade_maps(geometry, replace(views.effects.blades, shapes=("rectangular",)))[1]
            for row, name in enumerate((RULES[rule], None)):
                view = _read(path, iso, name)
                ax = axes[row, k]
                ax.imshow(_tile(view, behind))
                ax.set_xticks([]), ax.set_yticks([])
                ax.set_title(f"draw {case.number}: {int((view.mask & behind).sum())} px behind blades", fontsize=9)
            axes[0, k].set_ylabel("without the rule" if k == 0 else "")
            axes[1, k].set_ylabel("as shipped" if k == 0 else "")
    fig.suptitle(f"Masks on clinical images (seed {seed}, strength {strength:g}); red: kept behind the blades",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--biplane", action="store_true", help="two planes (plane B lateral to plane A)")
    ap.add_argument("--rule", choices=sorted(RULES), default="outside-edges")
    ap.add_argument("--figure", default="", help="comma-separated draws: draw their masks to --out (a PNG)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.figure:
        return figure(args.seed, args.strength, [int(n) for n in args.figure.split(",")], args.rule, args.out)
    found = shared_real_ct()
    if found is None:
        return 2
    volume, iso = found
    config, views = clinical_draws(volume, iso, args.seed, args.cases, args.strength, biplane=args.biplane)
    blades = views.effects.blades
    options = RegistrationOptions()
    with tempfile.TemporaryDirectory(prefix="roadmap3d-rule-") as tmp, args.out.open("w") as fh:
        for case in volume_cases(config):
            truth = case_motion(case, iso)
            shipped, without, images, behind = [], [], [], []
            for n, geometry in enumerate(_views(config, case, iso)):
                images.append(views.imager.image(geometry, truth, kind=config.kind, seed=case.seed + n))
                path = images[-1].write_dicom(Path(tmp) / f"plane{n}.dcm")
                shipped.append(_read(path, iso, None))
                without.append(_read(path, iso, RULES[args.rule]))
                behind.append(~blade_maps(geometry, replace(blades, shapes=("rectangular",)))[1] if blades else None)
            differ = sum(int((a.mask != b.mask).sum()) for a, b in zip(shipped, without, strict=True))
            row: dict = {"seed": args.seed, "case": case.number, "strength": args.strength, "rule": args.rule,
                         "views": len(images), "masks_differ_px": differ}  # fmt: skip
            row["shipped"] = _registered(volume, shipped, truth, case.seed, options)
            row["without"] = (
                dict(row["shipped"]) if differ == 0 else _registered(volume, without, truth, case.seed, options)
            )
            for name, read in (("shipped", shipped), ("without", without)):
                pairs = zip(read, behind, strict=True)
                kept = None if behind[0] is None else sum(int((v.mask & b).sum()) for v, b in pairs)
                row[name]["kept_behind_blades_px"] = kept
                row[name]["anatomy_px"] = sum(int((v.mask & i.field).sum()) for v, i in zip(read, images, strict=True))
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            brief = {n: [row[n][k] for k in ("inplane_mm", "translation_mm", "applied", "kept_behind_blades_px")]
                     for n in ("shipped", "without")}  # fmt: skip
            print(json.dumps({"case": row["case"], "masks_differ_px": differ} | brief), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
