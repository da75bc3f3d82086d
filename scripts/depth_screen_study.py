"""The same draws registered with the depth correction as it is and with its cheaper variants:
the first polish screened by the estimate's rotation margin (``first_polish_skip_margin``), the
scans strided (``scan_stride``), and both; each estimate assessed as ``register --confidence``.

python scripts/depth_screen_study.py runs --seed 40 --cases 20 --out tune-runs.jsonl
python scripts/depth_screen_study.py volume --seed 70 --cases 20 --out tune-ct.jsonl

``runs``: the rotational-run study (``roadmap3d validate clinical --quick``, ``--cases``
registrations per patient), one line per draw with every variant's registration; ``volume``:
the shared real CT's clinical-looking images (``roadmap3d validate volume --realism clinical``,
single plane, ``--strength``), written when every pass has ended. ``--margin``: the screen's
threshold; ``--stride``: the strided scans' step.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from variant_draws import write_runs, write_volume

from registration.core.register import RegistrationOptions

KEYS = ("inplane_residual_mm", "outofplane_residual_mm", "rotation_residual_deg", "success", "applied",
        "confidence", "drr_count", "seconds", "depth_tz_mm", "depth_moves_mm", "rotation_check")  # fmt: skip


def variants(margin: float, stride: int) -> dict[str, RegistrationOptions]:
    base = RegistrationOptions(depth_first_polish_skip_margin=None, depth_scan_stride=1)
    return {
        "base": base,
        "screen": replace(base, depth=replace(base.depth, first_polish_skip_margin=margin)),
        "stride": replace(base, depth=replace(base.depth, scan_stride=stride)),
        "both": replace(base, depth=replace(base.depth, first_polish_skip_margin=margin, scan_stride=stride)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("runs", "volume"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--margin", type=float, default=0.008)
    ap.add_argument("--stride", type=int, default=3)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    options = variants(args.margin, args.stride)
    with args.out.open("a") as fh:
        if args.study == "runs":
            write_runs(fh, args.seed, args.cases, options, KEYS)
        else:
            write_volume(fh, args.seed, args.cases, args.strength, options, KEYS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
