"""One view: the depth scan before the polish against after it, on the same draws.

Each draw is registered once per arm (``now``: the polish, then the depth correction's scans,
a move below 1.5 mm left out; ``prescan_keep``: the shipped options, a scan along the beam before
the polish, then rescans, every move kept), in one process, and
assessed as ``register --confidence`` does. One JSON line per draw with both arms' records.

    PYTHONPATH=. python scripts/depth_prescan_study.py runs --seed 23 --cases 20 > runs-s23.jsonl
    PYTHONPATH=. python scripts/depth_prescan_study.py volume --seed 66 --cases 20 > volume-s66.jsonl
    PYTHONPATH=. python scripts/depth_prescan_study.py table1 --seed 0 --cases 3 > table1-s0.jsonl
    PYTHONPATH=. python scripts/depth_prescan_study.py ct --seed 0 --cases 8 > real-ct-s0.jsonl

``runs``: the rotational-run study (``roadmap3d validate clinical --quick``'s patients, ``--cases``
registrations per patient); ``volume``: the shared real CT (ROADMAP3D_REAL_CT), clinical-looking
images of ``--strength``; ``table1``: the four Table I offsets on 27/27 cm fluoro images,
``--cases`` rounds (seeds ``seed`` onward); ``ct``: the shared real CT's clean images from the CT
itself, as ``roadmap3d bench`` registers them. ``--compare after-capture``: the arms ``shipped``
and ``after_capture`` (``DepthOptions.scan_after_capture``, and ``reach_mm`` from ``--reach-mm``)
instead; ``--variant JSON``: the arms ``shipped`` and ``variant`` (those flat keywords).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

from registration.core.register import RegistrationOptions

KEYS = ("inplane_residual_mm", "translation_residual_mm", "outofplane_residual_mm", "rotation_residual_deg",
        "success", "applied", "confidence", "drr_count", "drr_samples", "seconds")  # fmt: skip


COMPARE = "scan-first"
REACH_MM: float | None = None


VARIANT: dict | None = None


def arms() -> dict[str, RegistrationOptions]:
    base = RegistrationOptions()
    if VARIANT is not None:
        return {"shipped": base, "variant": RegistrationOptions(**VARIANT)}
    if COMPARE == "after-capture":
        variant = replace(base.depth, scan_after_capture=True, reach_mm=REACH_MM)
        return {"shipped": base, "after_capture": replace(base, depth=variant)}
    before = replace(base, depth=replace(base.depth, scan_first=False, keep_small_moves=False))
    return {"now": before, "prescan_keep": base}


def main() -> int:
    import variant_draws as draws

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("runs", "volume", "table1", "ct"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--compare", choices=("scan-first", "after-capture"), default="scan-first",
                    help="the arms compared (see the module's docstring)")  # fmt: skip
    ap.add_argument("--reach-mm", type=float, default=None, help="after-capture: the variant's DepthOptions.reach_mm")
    ap.add_argument("--variant", type=json.loads, default=None,
                    help="the shipped options against these flat keywords (JSON)")  # fmt: skip
    args = ap.parse_args()
    global COMPARE, REACH_MM, VARIANT
    COMPARE, REACH_MM, VARIANT = args.compare, args.reach_mm, args.variant
    if args.study == "runs":
        draws.write_runs(sys.stdout, args.seed, args.cases, arms(), KEYS)
    elif args.study == "volume":
        draws.write_volume(sys.stdout, args.seed, args.cases, args.strength, arms(), KEYS)
    elif args.study == "ct":
        from registration.core.roi import followed_region
        from registration.studies import volume as study

        shared = draws.shared_real_ct()
        if shared is None:
            return 2
        ct, iso = shared
        config = study.VolumeStudyConfig(cases=args.cases, seed=args.seed)
        imager, region = study.VolumeImager(ct, iso), followed_region(ct, config.roi)
        for case in study.volume_cases(config):
            line = {"study": "ct", "seed": args.seed, "case": case.number}
            for name, options in arms().items():
                record = study.run_volume_case(ct, imager, case, config, iso, options=options, confidence=True,
                                               region=region)  # fmt: skip
                line[name] = {k: record.get(k) for k in KEYS}
            print(json.dumps(line), flush=True)
    else:
        from registration.core.geometry import TABLE_I
        from registration.studies.cases import Case, run_case

        for r in range(args.cases):
            for offset in TABLE_I:
                case = Case(offset=offset, image_kind="fluoro", volume_format_cm=27.0, image_format_cm=27.0,
                            seed=args.seed + r)  # fmt: skip
                line = {"study": "table1", "seed": args.seed + r, "offset": str(offset)}
                for name, options in arms().items():
                    record = run_case(case, options=options)
                    line[name] = {k: record.get(k) for k in KEYS}
                print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
