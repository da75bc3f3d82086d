"""How often a landmark start leads to a right registration, at offsets far beyond the search box.

The moments of the capture study's quick run on the phantom (``validate capture --quick``'s
cases at its larger offsets: translation 40-80 mm, rotation 20-40 degrees, and both together),
four landmarks per plane picked with noise: each volume point 3 mm off (isotropic normal, per
axis 3 mm / sqrt(3)) and each image point off by the same 3 mm seen at the iso-center. The
volume points are the skull's outermost voxels in eight spread directions (orbit rims, vertex,
occiput, temples: where a user picks), on each plane the first four its field shows (``--picks
all``: the first four wherever they project). Biplane: each plane's picks; single plane: plane
A's. A view set where no plane shows four is counted as having no landmark start.
Each start registers as ``roadmap3d register --landmarks --confidence`` does (the volume prepared
from the start, the estimate assessed with the landmarks' check); success is the capture study's
criterion, and each line says whether the estimate was applied and how far it moved the landmarks.

python scripts/landmark_start_study.py --seed 0 [--pairs 4] [--noise-mm 3] [--only translation/80mm] [--without-wall]
    [--picks in-field|all]
Prints one JSON line per registration and a summary.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

import numpy as np

from registration.core.assess import assess
from registration.core.geometry import apply
from registration.core.landmarks import MIN_PAIRS, landmark_start
from registration.core.register import RegistrationOptions, StartOptions
from registration.studies.biplane import _offset_motion, case_views, study_volume
from registration.studies.capture import CaptureConfig, capture_tasks
from registration.studies.cases import register_prepared
from registration.studies.landmark_starts import picked_landmarks, picks_per_plane

FROM_LANDMARKS = RegistrationOptions(start=StartOptions(from_landmarks=True))
#: The same without the landmarks' wall (two views' search not held near the poses they allow).
WITHOUT_WALL = RegistrationOptions(start=StartOptions(from_landmarks=True, landmark_wall=None))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--noise-mm", type=float, default=3.0)
    ap.add_argument("--only", default="", help="register only the cases so named, comma-separated (picks for all)")
    ap.add_argument("--without-wall", action="store_true", help="two views' search not held by the landmarks")
    ap.add_argument("--planes", choices=("both", "biplane", "single_plane"), default="both")
    ap.add_argument("--aimed", action="store_true", help="both C-arms aimed at the moved head")
    ap.add_argument("--beam-line-mm", type=float, default=None, help="two views' last line search (0: off)")
    ap.add_argument("--fine-polish-evaluations", type=int, default=None, help="two views' fine polish budget")
    ap.add_argument("--depth-bound-mm", type=float, default=None, help="one view's depth correction bound")
    ap.add_argument("--picks", choices=("in-field", "all"), default="in-field",
                    help="pick where each plane's field shows the point, or wherever it projects")  # fmt: skip
    args = ap.parse_args()
    options = WITHOUT_WALL if args.without_wall else FROM_LANDMARKS
    if args.fine_polish_evaluations is not None:
        options = replace(options, start=replace(options.start, fine_polish_evaluations=args.fine_polish_evaluations))
    if args.beam_line_mm is not None:
        options = replace(options, start=replace(options.start, beam_line_mm=args.beam_line_mm or None))
    if args.depth_bound_mm is not None:
        options = replace(options, depth=replace(options.depth, bound_mm=args.depth_bound_mm))
    rng = np.random.default_rng([args.seed, 0x1A])
    config = replace(CaptureConfig.quick_config(seed=args.seed), aimed=args.aimed)
    tasks = [t for t in capture_tasks(config) if t.extra["level"] >= 2]
    rows: dict[str, list[tuple[bool, bool]]] = {"biplane": [], "single_plane": []}
    no_start: dict[str, int] = {"biplane": 0, "single_plane": 0}
    for task in tasks:
        case = task.case
        volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
        truth = _offset_motion(case)
        views, _ = case_views(case, volume, truth)
        landmarks = picked_landmarks(volume, views, truth, pairs=args.pairs, noise_mm=args.noise_mm, rng=rng,
                                     visible=args.picks == "in-field")  # fmt: skip
        if not any(part in task.case_id for part in args.only.split(",")):
            continue
        for name, vs, lms in (
            ("biplane", list(views), landmarks),
            ("single_plane", [views[0]], [lm for lm in landmarks if lm.plane == 0]),
        ):
            if args.planes not in ("both", name):
                continue
            counts = picks_per_plane(lms, len(vs))
            if max(counts) < MIN_PAIRS:  # too little of the skull in view: no landmark start to make
                no_start[name] += 1
                case_name = task.case_id.split("/a")[0]
                print(json.dumps({"case": case_name, "planes": name, "landmark_start": False, "picks": counts}))
                continue
            start = landmark_start([v.geometry for v in vs], lms)
            images = vs if len(vs) > 1 else vs[0]
            r, prepared = register_prepared(volume, images, initial_motion=start.patient_motion, truth=truth,
                                            seed=case.seed, landmarks=start,
                                            options=options)  # fmt: skip
            decided = assess(r, images, prepared, landmarks=start)
            ok = bool(r.residual.success_total if name == "biplane" else r.residual.success)
            rows[name].append((ok, bool(decided.applied)))
            iso = np.asarray(views[0].geometry.isocenter_mm)
            start_off = float(np.linalg.norm(apply(start.patient_motion, iso) - apply(truth, iso)))
            print(
                json.dumps(
                    {
                        "case": task.case_id.split("/a")[0],
                        "planes": name,
                        "wall": not args.without_wall,
                        "start_rms_px": round(start.rms_px, 2),
                        "start_off_mm": round(start_off, 2),
                        "start_shift_mm": round(r.start_shift_mm, 1),
                        "walk_hops": r.walk_hops,
                        "held": bool(r.held_by_landmarks),
                        "inplane_mm": round(r.residual.inplane_mm, 3),
                        "total_mm": round(r.residual.translation_mm, 3),
                        "rotation_deg": round(r.residual.rotation_deg, 3),
                        "success": ok,
                        "estimate_moved_mm": round(start.moved_mm(r.patient_motion), 3),
                        "start_offset_mm": round(start.start_offset_mm(), 2),
                        "applied": bool(decided.applied),
                        "withheld_reason": decided.reason,
                        "confidence": round(decided.confidence, 4),
                        "beam_margin": decided.evidence.beam_margin,
                        "fine_polish_evaluations": options.start.fine_polish_evaluations,
                        "beam_line_mm": options.start.beam_line_mm,
                        "depth_bound_mm": options.depth.bound_mm,
                        "aimed": args.aimed,
                        "picks": counts,
                        "pick_rule": args.picks,
                    }
                ),
                flush=True,
            )
    for name, got in rows.items():
        right = sum(ok for ok, _ in got)
        applied = sum(a for _, a in got)
        wrong = sum(a and not ok for ok, a in got)
        summary = {"planes": name, "success": f"{right}/{len(got)}", "applied": applied, "wrong_applied": wrong,
                   "without_landmark_start": no_start[name]}  # fmt: skip
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
