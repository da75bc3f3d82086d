"""The capture study's sweeps as shipped, every single-plane assessment that holds a depth scan
logged with its decision with and without the scan's term (one JSON line per moment).

    python scripts/capture_scan_term.py translation OUT.jsonl

Records: docs/validation/confidence-scan/capture-translation-s0.jsonl (revision ba14a55, the
assessment then still scanning every one-view estimate).
"""

import json
import sys
from dataclasses import replace

import registration.core.confidence as C
from registration.studies.capture import CaptureConfig, capture_tasks

log = []
shipped = C.ConfidenceRule.assess


def spy(self, e):
    a = shipped(self, e)
    if e.depth_scan_tz_mm is not None:
        b = shipped(self, replace(e, depth_scan_tz_mm=None))
        log.append(
            {
                "with": a.applied,
                "without": b.applied,
                "conf_with": a.confidence,
                "conf_without": b.confidence,
                "scan_tz": e.depth_scan_tz_mm,
            }
        )
    return a


C.ConfidenceRule.assess = spy
sweeps = tuple(sys.argv[1].split(","))
config = CaptureConfig(sweeps=sweeps)
out = open(sys.argv[2], "a")
for t in capture_tasks(config):
    log.clear()
    rec = t.case.run(options=t.options)
    row = {
        "case_id": t.case_id,
        "single_applied": rec.get("single_applied"),
        "right": rec.get("single_success_inplane"),
        "inplane": rec.get("single_inplane_residual_mm"),
        "oop_off": rec.get("offset_outofplane_mm"),
        "logged": list(log),
    }
    out.write(json.dumps(row) + "\n")
    out.flush()
