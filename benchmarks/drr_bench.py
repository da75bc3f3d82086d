"""DRR and gradient-difference timings, printed as JSON.

Run: ``/work/venv/bin/python benchmarks/drr_bench.py [--repeats N] [--sizes 64 128 256]``

For each paired size (image 64^2 from volume 64^3, 128^2 from 128^3, 256^2 from 256^3) it
prints the milliseconds of the fast numba renderer and of the map_coordinates reference in the
same run, in interleaved rounds, their ratio (median and least of the rounds) and the largest
difference, plus the median time of one prepared
gradient-difference evaluation at 128^2. The functions live in ``registration.studies.perf`` so that
``roadmap3d bench`` can use them from the installed package.
"""

from __future__ import annotations

import argparse
import json

from registration.studies.perf import bench_drr, bench_gradient_difference


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50, help="fast-renderer repetitions per size")
    parser.add_argument("--rounds", type=int, default=5, help="rounds per size, each one reference call")
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256], help="edge lengths")
    args = parser.parse_args()
    drr = bench_drr([(s, s) for s in args.sizes], args.repeats, rounds=args.rounds)
    result = {"drr": drr, "gradient_difference_ms_median": round(bench_gradient_difference(), 4)}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
