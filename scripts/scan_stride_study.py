"""The confidence's depth scan at every offset, and where a strided scan (every ``s``-th offset,
then climbing from the best until it has both neighbours) would put its peak, for several
strides, on the same registrations.

python scripts/scan_stride_study.py runs --seed 60 --cases 15 --out runs.jsonl
python scripts/scan_stride_study.py volume --seed 95 --cases 20 --strength 1 --out ct.jsonl
python scripts/scan_stride_study.py table1 --seed 4 --cases 2 --out t1.jsonl

Each registration runs as shipped (its assessment scans with ``depth.SCAN_STRIDE``); the scan is
also run at every offset (``stride=1``) and written with the peak index each stride would find.
The values at each offset do not depend on the stride, so a stride whose peak index is the
shipped stride's gives the same scan result (the peak's parabola reads the same three offsets).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from variant_draws import write_runs, write_volume

import registration.core.depth as depth
from registration.core.register import RegistrationOptions

STRIDES = (1, 2, 3, 4, 5, 6, 8)


def peak_index(values: list[float], stride: int) -> tuple[int, int]:
    """The peak index a ``stride`` scan settles on (``depth._scanned``'s rule) and its evaluations."""
    seen: list[int] = []

    def at(i: float) -> float:
        seen.append(int(i))
        return values[int(i)]

    offsets, got = depth._scanned(tuple(float(i) for i in range(len(values))), at, stride)
    best = max(range(len(got)), key=lambda k: (got[k], -offsets[k]))
    return int(offsets[best]), len(seen)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("runs", "volume", "table1"))
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cases", type=int, default=10)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    scans = args.out.with_suffix(".scans.jsonl").open("a")
    shipped = depth.depth_scan

    def logged(renderer, xray, motion, **kw):  # noqa: ANN001, ANN003, ANN202
        full = shipped(renderer, xray, motion, **{**kw, "stride": 1})
        values = [float(v) for v in full.similarity]
        line = {"study": args.study, "seed": args.seed, "values": values, "tz_mm": float(full.tz_mm)}
        line["peaks"] = {str(s): peak_index(values, s) for s in STRIDES}
        scans.write(json.dumps(line) + "\n")
        scans.flush()
        return shipped(renderer, xray, motion, **kw)

    depth.depth_scan = logged  # the assessment imports it at call time: only its scans are logged
    keys = ("inplane_residual_mm", "success", "applied", "confidence")
    variants = {"shipped": RegistrationOptions()}
    with args.out.open("a") as fh:
        if args.study == "runs":
            write_runs(fh, args.seed, args.cases, variants, keys)
        elif args.study == "volume":
            write_volume(fh, args.seed, args.cases, args.strength, variants, keys)
        else:
            from registration.core.geometry import TABLE_I
            from registration.studies.cases import Case, run_case

            for seed in range(args.seed, args.seed + args.cases):
                for n, offset in enumerate(TABLE_I):
                    case = Case(offset=offset, image_kind="fluoro", volume_format_cm=27.0, image_format_cm=27.0,
                                seed=seed)  # fmt: skip
                    record = run_case(case, options=variants["shipped"])
                    fh.write(json.dumps({"study": "table1", "seed": seed, "case": n,
                                         "shipped": {k: record.get(k) for k in keys}}) + "\n")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
