"""Two views: the same draws registered under two sets of options (the arms), each estimate
assessed as ``register --confidence`` does.

``--arms plane-capture`` (the default): each plane's capture at 64 px of the quarter-resolution
volume (before) against 32 px of the eighth-resolution volume with each run going on briefly at
64 px (now). ``--arms field-share``: the pair's measure as the plain mean of the planes' gradient
differences (before) against each weighted by the share of its field it compares (now).
``--arms translation-first``: a search from the image shift alone (before) against the same
with the translation-first candidate (:mod:`registration.core.register.translation_first`).
``--arms far-polish``: two views' fine polish only after a start away from the machine-based pose
(before) against also for an estimate 25 mm or more from it (now). ``--arms beam-scan``: the fine
polish alone (before) against the beam scan before it (now). ``--arms beam-scan-level``: the beam
scan on the fine polish's images and level 0 (now) against half those images on level 1.
``--arms beam-line``: the fine polish last (before) against a line search along each beam after it
(now). ``--arms beam-scan-reach``: the beam scan's +-15 mm (now) against +-30 mm. ``--arms pair-budgets``:
the coarse polish's and the pair's polish's evaluations (60 and 30 now) against fewer.

    PYTHONPATH=. python scripts/plane_capture_study.py phantom --seed 4 --moments 12
    PYTHONPATH=. python scripts/plane_capture_study.py ct --seed 62 --moments 10 --strength 1
    PYTHONPATH=. python scripts/plane_capture_study.py capture --seed 10 --moments 10 --mm 50 --arms field-share

``phantom``: the biplane study's quick moments; ``ct``: the shared real CT (ROADMAP3D_REAL_CT),
both planes, clinical images at ``--strength``, as ``validate volume --biplane --realism clinical``;
``capture``: the capture study's moments at ``--mm`` and ``--deg`` (its translation, rotation or
combined sweep; quick: 256/192 px and a 128³ 3DRA, ``--full``: the full study's 512/384 px and
256³). Prints one JSON line per draw and arm: right (3-D criterion), applied, the 3-D residual,
DRRs and seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from registration.core.register import RegistrationOptions
from registration.core.register.options import BiplaneOptions, StartOptions

#: The arms of each comparison: before, then the default now.
ARM_SETS = {
    "plane-capture": {
        "64 px captures": RegistrationOptions(biplane=BiplaneOptions(plane_capture=None, plane_refine=None)),
        "32 px captures, then 64 px": RegistrationOptions(),
    },
    "field-share": {
        "plain mean": RegistrationOptions(biplane=BiplaneOptions(field_share_weights=False)),
        "field-share weights": RegistrationOptions(),
    },
    "far-polish": {
        "fine polish after a far start": RegistrationOptions(start=StartOptions(fine_polish_beyond_mm=None)),
        "also 25 mm or more from the machine": RegistrationOptions(),
    },
    "beam-scan": {
        "fine polish alone": RegistrationOptions(start=StartOptions(beam_scan_mm=None)),
        "beam scan, then the fine polish": RegistrationOptions(),
    },
    "beam-scan-level": {
        "beam scan on level 0": RegistrationOptions(),
        "beam scan on level 1": RegistrationOptions(start=StartOptions(beam_scan_level=1)),
    },
    "beam-line": {
        "fine polish last": RegistrationOptions(start=StartOptions(beam_line_mm=None)),
        "a line search along each beam last": RegistrationOptions(),
    },
    "beam-scan-reach": {
        "beam scan +-15 mm": RegistrationOptions(),
        "beam scan +-30 mm": RegistrationOptions(start=StartOptions(beam_scan_mm=30.0)),
    },
    "pair-budgets": {
        "coarse 60, pair 30": RegistrationOptions(),
        "coarse 30, pair 30": RegistrationOptions(biplane=BiplaneOptions(coarse_polish_evaluations=30)),
        "coarse 60, pair 20": RegistrationOptions(biplane=BiplaneOptions(polish_evaluations=20)),
        "coarse 30, pair 20": RegistrationOptions(
            biplane=BiplaneOptions(coarse_polish_evaluations=30, polish_evaluations=20)
        ),
    },
    "translation-first": {
        "search only": RegistrationOptions(start=StartOptions(translation_first_evaluations=0)),
        "translation-first candidate": RegistrationOptions(),
    },
}


def _line(arm: str, case: str, record: dict) -> str:
    return json.dumps({
        "arm": arm, "case": case, "right": bool(record["success"]), "applied": record.get("applied"),
        "translation_residual_mm": round(float(record["translation_residual_mm"]), 3),
        "drrs": record.get("drr_count"), "seconds": round(float(record.get("seconds", 0.0)), 3),
    })  # fmt: skip


def phantom(arms: dict, seed: int, moments: int) -> None:
    from registration.studies.biplane import BiplaneConfig, biplane_tasks, run_biplane_case

    config = dataclasses.replace(BiplaneConfig.quick_config(seed=seed), registrations_per_patient=moments)
    for task in biplane_tasks(config):
        for arm, options in arms.items():
            print(_line(arm, task.case_id, run_biplane_case(task.case, options=options)), flush=True)


def ct(arms: dict, seed: int, moments: int, strength: float) -> None:
    from registration.io import dicom
    from registration.studies.volume import VolumeStudyConfig, find_real_ct, head_isocenter_mm, run_volume_study

    path = find_real_ct()
    if path is None:
        raise SystemExit("no real CT: set ROADMAP3D_REAL_CT")
    volume = dicom.read_volume(path)
    config = VolumeStudyConfig(cases=moments, seed=seed, biplane=True, realism="clinical", strengths=(strength,))
    for arm, options in arms.items():
        records, _ = run_volume_study(volume, head_isocenter_mm(volume), config, options=options)
        for record in records:
            print(_line(arm, f"ct/s{seed}/{record.get('case')}", record), flush=True)


def capture(arms: dict, seed: int, moments: int, mm: float, deg: float, full: bool = False) -> None:
    from registration.studies.capture import CaptureConfig, capture_tasks
    from registration.studies.execution import execute

    sweep = "combined" if mm and deg else ("rotation" if deg else "translation")
    base = CaptureConfig(seed=seed) if full else CaptureConfig.quick_config(seed=seed)
    config = dataclasses.replace(base, sweeps=(sweep,), translations_mm=(mm,),
                                 rotations_deg=(deg,), registrations_per_level=moments)  # fmt: skip
    for arm, options in arms.items():
        for task in capture_tasks(config, options):
            print(_line(arm, task.case_id, execute(task)), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("draws", choices=("phantom", "ct", "capture"))
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--moments", type=int, default=12)
    parser.add_argument("--strength", type=float, default=1.0)
    parser.add_argument("--mm", type=float, default=50.0)
    parser.add_argument("--deg", type=float, default=0.0)
    parser.add_argument("--arms", choices=tuple(ARM_SETS), default="plane-capture")
    parser.add_argument("--full", action="store_true", help="capture: the full study's images and 3DRA")
    args = parser.parse_args()
    arms = ARM_SETS[args.arms]
    if args.draws == "phantom":
        phantom(arms, args.seed, args.moments)
    elif args.draws == "ct":
        ct(arms, args.seed, args.moments, args.strength)
    else:
        capture(arms, args.seed, args.moments, args.mm, args.deg, args.full)


if __name__ == "__main__":
    main()
