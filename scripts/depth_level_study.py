"""Where one view's depth correction scans on the rotational-run study's FDK volumes: the prepared
level 1 against the volume's level 0 (``DepthOptions.level0_max_voxels``).

python scripts/depth_level_study.py truth --seed 17 --voxels 128 --out truth-128.jsonl
python scripts/depth_level_study.py pair --seed 31 --cases 6 --out pair.jsonl

``truth``: the high-passed scan along the beam at the true pose (the study's frames, 5-8 per
patient), on the index pyramid of the whole volume (``idx``), the preparation of levels 1 and 2
(``level1``) and the preparation with level 0 (``level0``): where each peaks (mm, + toward the
source; 0 is right). ``pair``: the same draws registered both ways, interleaved twice, the
seconds, DRR samples and residuals of each.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from registration.core.depth import depth_scan, scan_level
from registration.core.drr import DRRRenderer
from registration.core.images import XRayImage
from registration.core.preparation import Preparation
from registration.core.problem import iso_pixel_mm, level_factor, renderer_level
from registration.core.register import RegistrationOptions, register
from registration.studies import runs as R

ON = RegistrationOptions()
OFF = replace(ON, depth=replace(ON.depth, level0_max_voxels=0))


def _frame(case: R.ClinicalCase) -> tuple[R.PatientData, XRayImage]:
    data = R.patient_of(case)
    g = data.calibrated_geometries[case.frame]
    return data, XRayImage(data.images[case.frame], data.masks[case.frame], g, "exposure", {"frame": case.frame})


def truth(seed: int, voxels: int, per_patient: int, out) -> None:  # noqa: ANN001
    config = replace(R.ClinicalConfig.quick_config(seed), registrations_per_patient=100, volume_voxels=voxels)
    seen: set[tuple[int, int]] = set()
    for task in R.clinical_tasks(config):
        case = task.case
        if (case.patient, case.frame) in seen or sum(p == case.patient for p, _ in seen) >= per_patient:
            continue
        seen.add((case.patient, case.frame))
        data, xray = _frame(case)
        g = xray.geometry
        row: dict = {"patient": case.patient, "frame": case.frame, "voxels": voxels, "seed": seed}
        renderers = {
            "idx": DRRRenderer(data.volume, levels=3),
            "level1": Preparation.of(data.volume, xray, options=OFF).renderer,
            "level0": Preparation.of(data.volume, xray, options=ON).renderer,
        }
        for name, r in renderers.items():
            level = scan_level(r)
            polish_mm = float(r.level_volume(renderer_level(r, 1)).spacing_mm.max())
            pixel = iso_pixel_mm(g, level_factor(g, 128, polish_mm))
            scan = depth_scan(r, xray, np.eye(4), offsets_mm=tuple(np.arange(-24.0, 24.1, 2.0)), image_px=128,
                              volume_level=level, pixel_at_iso_mm=pixel)  # fmt: skip
            row[name] = {"peak_mm": scan.tz_mm, "level": level,
                         "voxel_mm": float(r.level_volume(level).spacing_mm.max())}  # fmt: skip
        print(json.dumps(row), file=out, flush=True)


def pair(seed: int, cases: int, out) -> None:  # noqa: ANN001
    config = replace(R.ClinicalConfig.quick_config(seed), registrations_per_patient=cases)
    for task in R.clinical_tasks(config):
        case = task.case
        data, xray = _frame(case)
        offset = R._translation(case.translation_mm) @ R.axis_angle_matrix(case.rotation_axis, case.rotation_deg)
        row: dict = {"case": task.case_id}
        for order in ((("level0", ON), ("level1", OFF)), (("level1", OFF), ("level0", ON))):
            for name, options in order:
                prepared = Preparation.of(data.volume, xray, initial_motion=offset, options=options)
                before = sum(prepared.renderer.samples_per_level)
                t0 = time.perf_counter()
                result = register(data.volume, xray, initial_motion=offset, truth=np.eye(4), seed=case.seed,
                                  options=options, renderer=prepared.renderer)  # fmt: skip
                row.setdefault(name, {"seconds": []})["seconds"].append(time.perf_counter() - t0)
                res = result.residual
                row[name].update(samples=int(sum(prepared.renderer.samples_per_level) - before),
                                 inplane_mm=res.inplane_mm, rotation_deg=res.rotation_deg,
                                 depth_tz_mm=result.depth_tz_mm)  # fmt: skip
        print(json.dumps(row), file=out, flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("truth", "pair"))
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--voxels", type=int, default=128)
    ap.add_argument("--cases", type=int, default=6, help="truth: frames per patient; pair: draws per patient")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    with a.out.open("w") if a.out else sys.stdout as out:
        if a.what == "truth":
            truth(a.seed, a.voxels, a.cases, out)
        else:
            pair(a.seed, a.cases, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
