"""Where along the beam does the gradient difference peak at the true pose, and does matching
the images' resolution or removing their coarse scales move it? (docs/validation/clinical-s6/depth_scan.md)

For frames of the quick clinical study's two patients (the cached rotational runs and FDK
reconstructions, ``registration.studies.runs.patient_data``), at the true pose moved along the
beam only (tz from -20 to +20 mm in 2.5 mm steps, + toward the source), at the registration's
levels (``LevelProblem``, 4 mm support margin), the measure of

* the frame Gaussian-blurred by sigma px (normalised inside the field) against the DRR,
* the frame against the DRR blurred by sigma px,
* both high-passed (:func:`registration.core.depth.high_pass`) at sigma px,

and prints the best tz per sigma.

    .venv/bin/python scripts/depth_bias_scan.py [--frames 10,50,100,115]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from registration.core.depth import high_pass
from registration.core.drr import DRRRenderer
from registration.core.images import XRayImage
from registration.core.problem import LevelProblem
from registration.core.similarity import GradientDifference
from registration.studies.runs import patient_data

PATIENTS = ((1, 22.0, True), (2, 27.0, False))  # the quick study's (phantom seed, format, contrast)
LEVELS = ((256, 0), (128, 1), (64, 2))  # (image px, volume level)
TZ_MM = np.arange(-20.0, 20.01, 2.5)


def blur(image: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return np.asarray(image, np.float64)
    num = ndimage.gaussian_filter(np.where(mask, image, 0.0).astype(np.float64), sigma)
    den = ndimage.gaussian_filter(mask.astype(np.float64), sigma)
    return np.where(mask, num / np.maximum(den, 1e-6), 0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default="10,30,50,75,100,115")
    args = parser.parse_args()
    frames = [int(f) for f in args.frames.split(",")]
    variants = {
        "frame blurred": (0.0, 0.5, 1.0, 1.5, 2.0, 3.0),
        "DRR blurred": (0.0, 0.5, 1.0, 1.5, 2.0, 3.0),
        "both high-passed": (0.0, 2.0, 4.0, 8.0, 16.0),
    }
    for patient, (seed, fmt, contrast) in enumerate(PATIENTS):
        data = patient_data(seed, fmt, contrast, 120, 200.0, 256, 128)
        renderer = DRRRenderer(data.volume, levels=3)  # the index pyramid the recorded studies used
        for frame in frames:
            g = data.calibrated_geometries[frame]
            xray = XRayImage(data.images[frame], data.masks[frame], g, "exposure", {})
            for px, level in LEVELS:
                problem = LevelProblem.prepare(renderer, (xray,), image_px=px, volume_level=level, motion=np.eye(4),
                                               margin_mm=4.0)  # fmt: skip
                view = problem.views[0]
                factor = xray.shape[0] // view.geometry.rows
                image = (xray.downsample(factor) if factor > 1 else xray).image
                mask = view.mask
                drrs = []
                for tz in TZ_MM:
                    m = np.eye(4)
                    m[:3, 3] = -tz * np.asarray(g.direction)
                    drrs.append(renderer.render(view.geometry, m, level=problem.volume_level, mask=mask))
                for name, sigmas in variants.items():
                    best = []
                    for s in sigmas:
                        if name == "frame blurred":
                            gd = GradientDifference(blur(image, mask, s), mask)
                            vals = [gd(d) for d in drrs]
                        elif name == "DRR blurred":
                            gd = GradientDifference(image, mask)
                            vals = [gd(blur(d, mask, s)) for d in drrs]
                        else:
                            gd = GradientDifference(high_pass(image, mask, s) if s else image, mask)
                            vals = [gd(high_pass(d, mask, s) if s else d) for d in drrs]
                        best.append(float(TZ_MM[int(np.argmax(vals))]))
                    pairs = ", ".join(f"{s:g}: {b:+.1f}" for s, b in zip(sigmas, best, strict=True))
                    print(f"patient {patient} ({fmt:g} cm) frame {frame} (primary {g.primary_deg:.0f}) "
                          f"{px} px / level {level}, {name}: best tz per sigma {{{pairs}}}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
