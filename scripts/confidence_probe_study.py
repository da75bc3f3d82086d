"""The confidence as shipped against the one before (every single-plane estimate probed along the
beam, the depth scan at all 25 offsets), on the same registrations in one process.

python scripts/confidence_probe_study.py volume --seed 62 --cases 30 --out fresh-ct.jsonl
python scripts/confidence_probe_study.py volume --seed 63 --strength 2 --cases 30 --out fresh-ct.jsonl
python scripts/confidence_probe_study.py runs --seed 19 --cases 30 --out fresh-runs.jsonl

``volume``: the shared real CT's clinical-looking images (``roadmap3d validate volume --realism
clinical``, single plane); ``runs``: the rotational-run study (``roadmap3d validate clinical
--quick``, ``--cases`` registrations per patient). Appends one JSON line per registration: each
assessment's confidence, decision, seconds, DRRs and depth evidence, and whether the estimate
is right (in-plane < 1 mm, rotation < 3 degrees).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import registration.core.assess as assess_module
import registration.core.depth as depth_module

SHIPPED = assess_module.assess
SHIPPED_CORRECTED = assess_module.depth_corrected


def both(result, views, preparation, **kw) -> tuple[dict, object]:  # noqa: ANN001
    """``result`` assessed the earlier way and as shipped (the shipped assessment returned)."""
    preparation.probe_renderer()  # built once, before either is timed
    out, shipped = {}, None
    for name in ("before", "shipped"):
        if name == "before":
            depth_module.SCAN_STRIDE, assess_module.depth_corrected = 1, lambda _r: False
        renderer = preparation.probe_renderer()
        count, t0 = renderer.count, time.perf_counter()
        try:
            a = SHIPPED(result, views, preparation, **kw)
        finally:
            depth_module.SCAN_STRIDE, assess_module.depth_corrected = 3, SHIPPED_CORRECTED
        e = a.evidence
        out[name] = {"confidence": a.confidence, "applied": a.applied, "seconds": time.perf_counter() - t0,
                     "drrs": renderer.count - count, "depth_shift_mm": e.depth_shift_mm,
                     "depth_scan_tz_mm": e.depth_scan_tz_mm, "reason": a.reason}  # fmt: skip
        shipped = a
    res = result.residual
    out |= {"right": bool(res.inplane_mm < 1.0 and res.rotation_deg < 3.0), "inplane_mm": res.inplane_mm,
            "registration_seconds": result.seconds}  # fmt: skip
    return out, shipped


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("volume", "runs"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    tag = {"study": args.study, "seed": args.seed} | ({"strength": args.strength} if args.study == "volume" else {})

    def record(result, views, preparation, **kw):  # noqa: ANN001, ANN202
        out, shipped = both(result, views, preparation, **kw)
        with args.out.open("a") as fh:
            fh.write(json.dumps(tag | out) + "\n")
        return shipped

    assess_module.assess = record  # the studies import it at call time
    if args.study == "volume":
        import registration.studies.volume as study
        from registration.io import dicom

        volume = dicom.read_volume(study.find_real_ct())
        config = study.VolumeStudyConfig(cases=args.cases, seed=args.seed, realism="clinical",
                                         strengths=(args.strength,))  # fmt: skip
        study.run_volume_study(volume, study.head_isocenter_mm(volume), config, log=print)
    else:
        from registration.studies import runs

        config = replace(runs.ClinicalConfig.quick_config(args.seed), registrations_per_patient=args.cases)
        for task in runs.clinical_tasks(config):
            runs.run_clinical_case(task.case)
    return 0


if __name__ == "__main__":
    sys.exit(main())
