"""The same draws registered with the rotation check's screen (the default) and without it
(``skip_margin=None``: every estimate checked), each estimate assessed as ``register --confidence``.

python scripts/rotation_screen_study.py runs --seed 21 --cases 30 --out fresh-runs.jsonl
python scripts/rotation_screen_study.py volume --seed 64 --cases 30 --out fresh-ct.jsonl

``runs``: the rotational-run study (``roadmap3d validate clinical --quick``, ``--cases``
registrations per patient), one line per draw with both registrations (``on``, ``off``);
``volume``: the shared real CT's clinical-looking images (``roadmap3d validate volume --realism
clinical``, single plane, ``--strength``), written when both passes have ended.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from registration.core.register import RegistrationOptions

#: Every estimate checked, as before the screen.
OFF = RegistrationOptions(rotation_check_skip_margin=None)
KEYS = ("rotation_check", "inplane_residual_mm", "rotation_residual_deg", "success", "applied", "confidence",
        "drr_count", "seconds")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("runs", "volume"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    with args.out.open("a") as fh:
        if args.study == "runs":
            from registration.studies import runs

            config = replace(runs.ClinicalConfig.quick_config(args.seed), registrations_per_patient=args.cases)
            for task in runs.clinical_tasks(config):
                line = {"case_id": task.case_id, "study": "runs", "seed": args.seed}
                for name, options in (("on", None), ("off", OFF)):
                    record = runs.run_clinical_case(task.case, options=options)
                    line[name] = {k: record.get(k) for k in KEYS}
                fh.write(json.dumps(line) + "\n")
                fh.flush()
        else:
            import registration.studies.volume as study
            from registration.io import dicom

            volume = dicom.read_volume(study.find_real_ct())
            iso = study.head_isocenter_mm(volume)
            config = study.VolumeStudyConfig(cases=args.cases, seed=args.seed, realism="clinical",
                                             strengths=(args.strength,))  # fmt: skip
            on = study.run_volume_study(volume, iso, config)[0]
            off = study.run_volume_study(volume, iso, config, options=OFF)[0]
            for a, b in zip(on, off, strict=True):
                both = {"on": {k: a.get(k) for k in KEYS}, "off": {k: b.get(k) for k in KEYS}}
                fh.write(json.dumps({"study": f"volume:{args.strength:g}", "seed": args.seed} | both) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
