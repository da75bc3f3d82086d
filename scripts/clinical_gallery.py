"""The gallery of clinical-looking X-ray images (docs/clinical-images.md): each effect of
``registration.sim.clinical`` alone and all together, on a CT, frontal and lateral.

Run: ``python scripts/clinical_gallery.py [CT folder] [--out docs/clinical-images]`` (default: the
shared real head CT beside the project). Each PNG shows the stored pixels as a viewer shows them
(display-processed images as stored; the project's LOG images windowed to their field), the
overlay plane's graphics in yellow as a viewer draws them, and the outline of the field where the
pixels carry anatomy (red, 1 px).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from registration.core.geometry import CArm, rigid  # noqa: E402
from registration.io import dicom  # noqa: E402
from registration.sim.clinical import EFFECT_NAMES, ClinicalEffects, ClinicalImager  # noqa: E402
from registration.sim.clinical.anatomy import patient_only  # noqa: E402
from registration.studies.runs import axis_angle_matrix  # noqa: E402
from registration.studies.volume import find_real_ct, head_isocenter_mm  # noqa: E402

PIXELS = 384
#: The patient's motion in every image: 6 mm and 4 degrees (the neck then bends visibly less).
TRANSLATION_MM = (4.0, -3.0, 3.5)
ROTATION = ((0.3, 0.2, 1.0), 4.0)


def _view(image) -> np.ndarray:  # noqa: ANN001
    """8-bit picture of the stored pixels (display images as stored, LOG images windowed)."""
    stored = image.stored.astype(np.float64)
    if image.effects.display is not None:
        top = (1 << image.bits) - 1
        gray = stored / top * 255.0
    else:
        lo, hi = np.percentile(stored[image.field], [0.5, 99.5])
        gray = np.where(image.circle, (stored - lo) / max(hi - lo, 1.0) * 255.0, 0.0)
        gray[image.graphics] = 255.0  # burned in at full white, over the collimator too
    rgb = cv2.cvtColor(np.clip(gray, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    near_text = cv2.dilate(image.graphics.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    edge = image.field ^ cv2.erode(image.field.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    rgb[edge & ~near_text] = (0, 0, 255)
    if image.overlay is not None:  # a viewer draws the overlay plane over the pixels
        rgb[image.overlay] = (0, 255, 255)
    return rgb


def _label(panel: np.ndarray, text: str) -> np.ndarray:
    strip = np.full((26, panel.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([strip, panel])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ct", nargs="?", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "clinical-images")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--only", default="", help="comma-separated picture names (default: all)")
    args = parser.parse_args(argv)
    ct = args.ct or find_real_ct()
    if ct is None:
        print("error: no CT given and no shared real CT found", file=sys.stderr)
        return 2
    volume = dicom.read_volume(ct)
    iso = head_isocenter_mm(volume)
    base = patient_only(volume)[0]
    c = np.asarray(iso)
    motion = rigid(None, np.asarray(TRANSLATION_MM)) @ rigid(None, c) @ axis_angle_matrix(*ROTATION) @ rigid(None, -c)
    views = [
        ("frontal (PA)", replace(CArm.for_format(27.0, pixels=PIXELS), isocenter_mm=tuple(iso))),
        ("lateral (LAO 90)", replace(CArm.for_format(27.0, pixels=PIXELS, primary_deg=90.0), isocenter_mm=tuple(iso))),
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    arms = [("clean", ClinicalEffects())] + [(n, ClinicalEffects.of([n])) for n in EFFECT_NAMES]
    arms += [("clinical", ClinicalEffects.all()), ("clinical-strength-2", ClinicalEffects.of(EFFECT_NAMES, 2.0))]
    only = {n.strip() for n in args.only.split(",") if n.strip()}
    for name, effects in arms:
        if only and name not in only:
            continue
        imager = ClinicalImager(volume, iso, effects, base=base if effects.table is not None else None)
        panels = []
        for title, g in views:
            image = imager.image(g, motion, seed=args.seed)
            panels.append(_label(_view(image), f"{name}: {title}"))
        path = args.out / f"{name}.png"
        cv2.imwrite(str(path), np.hstack(panels), [cv2.IMWRITE_PNG_COMPRESSION, 9])
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
