"""The tracker's crop watch: does it cost the refine path anything? (issue 13 follow-up)

Run: ``python benchmarks/tracking_crop_ab.py [--repeats 3]``

A same-process A/B on the bench's tracking run (``validate tracking --quick``'s 20 s case, the
phantom's 3DRA, every frame replayed: deterministic): ``watch``, the tracker as it is (after each
frame the crop's margin for a capture from the applied pose; the phantom's renderer is a
whole-volume pyramid, so there is no crop and nothing is prepared again), against ``none``, the
watch's two calls replaced by no-ops (what the tracker did before it had one). The paths are
alternated (AB, BA, ...); it prints JSON with each path's refine-path (check + refine) latency
median and p95 per repeat and the median of the per-repeat ratios (watch / none), and checks that
both paths make the same decisions.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

import registration.core.tracking as tracking
from registration.core.drr import DRRRenderer
from registration.studies.cases import load_volume
from registration.studies.tracking import TrackingConfig, case_runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    config = TrackingConfig.quick_config(0)
    case = config.cases[0]
    runs = case_runs(case)
    volume = load_volume(0, True, case.volume_format_cm, case.volume_voxels, case.volume_source)
    renderer = DRRRenderer(volume, levels=3)
    watch_check, watch_take = tracking._CropWatch.check, tracking._CropWatch.take

    def run(watch: bool) -> tuple[float, float, list]:
        if watch:
            tracking._CropWatch.check, tracking._CropWatch.take = watch_check, watch_take
        else:
            tracking._CropWatch.check = lambda self, *a, **k: None  # type: ignore[method-assign]
            tracking._CropWatch.take = lambda self: None  # type: ignore[method-assign]
        try:
            r = tracking.track_run(volume, runs, runs[0].times_s, options=config.options, renderer=renderer, seed=0,
                                   realtime=False)  # fmt: skip
        finally:
            tracking._CropWatch.check, tracking._CropWatch.take = watch_check, watch_take
        lat = [f.latency_ms for f in r.frames if f.path != "capture"]
        return float(np.median(lat)), float(np.percentile(lat, 95)), [(f.status, f.path) for f in r.frames]

    out: dict[str, list] = {"watch": [], "none": []}
    reference = None
    for rep in range(args.repeats):
        for watch in (True, False) if rep % 2 == 0 else (False, True):
            median, p95, decisions = run(watch)
            reference = reference or decisions
            if decisions != reference:
                raise SystemExit("error: the two paths made different decisions")
            out["watch" if watch else "none"].append({"refine_path_ms_median": median, "refine_path_ms_p95": p95})
    ratios = [a["refine_path_ms_median"] / b["refine_path_ms_median"] for a, b in zip(out["watch"], out["none"],
                                                                                      strict=True)]  # fmt: skip
    print(json.dumps({**out, "ratio_watch_over_none_median": float(np.median(ratios)), "ratios": ratios,
                      "frames": len(reference or []), "same_decisions": True}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
