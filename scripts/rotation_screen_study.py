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
import sys
from pathlib import Path

from variant_draws import write_runs, write_volume

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
    variants = {"on": None, "off": OFF}
    with args.out.open("a") as fh:
        if args.study == "runs":
            write_runs(fh, args.seed, args.cases, variants, KEYS)
        else:
            write_volume(fh, args.seed, args.cases, args.strength, variants, KEYS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
