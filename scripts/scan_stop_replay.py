"""Replay the recorded full depth scans (docs/validation/scan-stride/*/*.scans.jsonl) through the
strided scan and the stopping scan (``below_mm``): the term ``depth_scan`` of each, and the
evaluations each needs.

python scripts/scan_stop_replay.py
"""

from __future__ import annotations

import glob
import json

from registration.core.depth import SCAN_STRIDE, SCAN_TZ_MM, _scanned, scan_peak_mm

THRESHOLDS_MM = (-11.0, -7.0, -5.0, 3.0)


def main() -> int:
    out = {str(t): {"scans": 0, "same_term": 0, "below": 0, "stopped": 0, "strided": 0, "stopping": 0}
           for t in THRESHOLDS_MM}  # fmt: skip
    for path in sorted(glob.glob("docs/validation/scan-stride/*/*.scans.jsonl")):
        for line in open(path):
            values = json.loads(line)["values"]
            if len(values) != len(SCAN_TZ_MM):
                continue
            for below in THRESHOLDS_MM:
                calls: list[float] = []

                def at(o: float, calls: list = calls, values: list = values) -> float:
                    calls.append(o)
                    return values[SCAN_TZ_MM.index(o)]

                strided = scan_peak_mm(*_scanned(SCAN_TZ_MM, at, SCAN_STRIDE))
                n_strided = len(calls)
                calls.clear()
                got, vals, stopped = _scanned(SCAN_TZ_MM, at, SCAN_STRIDE, below)
                tz = scan_peak_mm(got, vals, stopped)
                o = out[str(below)]
                o["scans"] += 1
                o["same_term"] += max(0.0, below - strided) == max(0.0, below - tz)
                o["below"] += strided < below
                o["stopped"] += stopped
                o["strided"] += n_strided
                o["stopping"] += len(calls)
    for o in out.values():
        o["evaluations_per_scan"] = [round(o["strided"] / o["scans"], 2), round(o["stopping"] / o["scans"], 2)]
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
