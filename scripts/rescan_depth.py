"""Re-scan the clinical study's recorded single-plane estimates along the beam
(docs/validation/clinical-s6/depth_scan.md).

For every record of the given results.jsonl files, :func:`registration.core.depth.depth_scan`
at the recorded estimate (``patient_motion``) against the record's frame of its patient's
cached rotational run and FDK reconstruction (``registration.studies.runs.patient_data``, the
quick study's 120 projections of 256 px, 128^3); no registration runs. One JSON line per record:
case, seed, patient, success, the recorded decision, the residuals, the estimate's signed
out-of-plane offset from the truth (``need_mm``: the move along the beam, + toward the source,
that would reach the truth) and where the scan peaks (``scan_tz_mm``), with the evidence the
record holds (``confidence_evidence``), so a rule can be re-scored with the scan as evidence.

    .venv/bin/python scripts/rescan_depth.py OUT.jsonl docs/validation/clinical-200/results.jsonl ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from registration.core.depth import depth_scan
from registration.core.drr import DRRRenderer
from registration.core.geometry import apply
from registration.core.images import XRayImage
from registration.studies.runs import patient_data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("results", type=Path, nargs="+")
    args = parser.parse_args()
    records = [json.loads(line) for p in args.results for line in p.read_text().splitlines() if line.strip()]
    with args.out.open("w") as out:
        for r in sorted(records, key=lambda r: (r["phantom_seed"], r["case_id"])):
            data = patient_data(r["phantom_seed"], r["volume_format_cm"], r["contrast"], r["projections"], 200.0,
                                r["image_pixels"], r["volume_voxels"])  # fmt: skip
            renderer = DRRRenderer(data.volume, levels=3)  # the index pyramid the recorded studies used
            g = data.calibrated_geometries[r["frame"]]
            xray = XRayImage(data.images[r["frame"]], data.masks[r["frame"]], g, "exposure", {})
            m = np.asarray(r["patient_motion"])
            iso = np.asarray(g.isocenter_mm)
            need = float((apply(m, iso) - iso) @ g.direction)  # the truth is the identity
            scan = depth_scan(renderer, xray, m)
            row = {
                "case_id": r["case_id"],
                "study_seed": r["study_seed"],
                "patient": r["patient"],
                "primary_deg": r["primary_deg"],
                "success": r["success"],
                "applied_recorded": r["applied"],
                "inplane_residual_mm": r["inplane_residual_mm"],
                "rotation_residual_deg": r["rotation_residual_deg"],
                "need_mm": need,
                "scan_tz_mm": scan.tz_mm,
                "scan_sigma_px": scan.sigma_px,
                "confidence_evidence": r["confidence_evidence"],
            }
            out.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
