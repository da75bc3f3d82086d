"""Can a tracked patient leave the volume's prepared crop? (issue 13 follow-up; docs/validation/tracking-crop)

``roadmap3d track``, the app's Play run and ``listen`` prepare the volume once for the run's field
(:func:`registration.core.register.prepared_volume`: cropped to what rays through the field reach
while a capture searches +-30 mm / +-15 deg from the initial pose). This script measures how much
anatomy a DRR at a moved pose lacks when it is rendered from that crop instead of the whole body's
levels (same grids), and tracks runs that walk the pose far from the start:

``--part crops``: the shared real head CT (../shared/data/real-ct/head-neck-ct, iso-center
247.5,-276,-90) in the eight image formats x three C-arm angles; a tall CT of the analytic phantom
(head and neck to 330 mm below the iso-center, 2 x 2 x 3 mm) with the default and a narrow
(+-10 mm / +-4 deg) search: is the crop the whole body, and what a DRR 20..150 mm away misses.

``--part real-run``: a 60 s run of 64-px fluoro frames at 5 frames/s formed from the real CT (a
best case: images from the same volume), walking 1 mm/s headward for 30 s, then two sudden moves
(20 mm + 5 deg, 15 mm + 5 deg), about 65 mm / 10 deg from the start at the end; tracked frame by
frame; errors of the applied frames against the truth.

``--part tall-run``: the tall phantom CT with the narrow search, a 91 mm headward walk at 0.7 mm per
frame (15 frames/s: 10.5 mm/s, faster than a patient's drift, to keep the run short) tracked with
re-preparation on and off; frames formed from the analytic phantom (honest image model).

    .venv/bin/python scripts/crop_margin_study.py --part crops|real-run|tall-run [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np

from registration.core.drr import DRRRenderer
from registration.core.geometry import IMAGE_FORMATS_CM, CArm, rigid
from registration.core.images import XRayImage
from registration.core.metrics import residuals
from registration.core.prepare import Reach, prepare_volume
from registration.core.register import RegistrationOptions, prepared_volume
from registration.core.tracking import TrackingOptions, light_capture, track_run
from registration.core.volume import Volume

ISO = (247.5, -276.0, -90.0)


def tall_phantom_ct() -> tuple[Volume, object]:
    from registration.sim.phantom import make_head_phantom

    anatomy = make_head_phantom(seed=0, contrast=False)
    affine = np.diag([2.0, 2.0, 3.0, 1.0])
    affine[:3, 3] = (-100.0, -110.0, -330.0)
    hu = anatomy.voxelize((151, 111, 101), affine, supersample=1)
    return Volume(hu.astype(np.float32), affine, label="tall CT of the analytic phantom (2 x 2 x 3 mm)"), anatomy


def missing(prepared, geometry: CArm, motion: np.ndarray) -> dict:
    """What a DRR at ``motion`` from the crop lacks against the whole body's levels (same grids)."""
    crop = prepared.crop
    level = prepared.renderer.level_nearest(64)
    whole = DRRRenderer(prepared.volume, levels=[None] + [crop.base.levels[k] for k in (1, 2)])
    small = geometry.resized(64, 64)
    mask = small.field_mask()
    truth = whole.render(small, motion, level=level)[mask]
    diff = np.abs(truth - prepared.renderer.render(small, motion, level=level)[mask]) / max(truth.max(), 1e-12)
    return {"max_relative": float(diff.max()), "pixels_over_1pct": float((diff > 0.01).mean())}


def about(c: tuple[float, float, float], axis: tuple[float, float, float], deg: float) -> np.ndarray:
    from registration.studies.runs import axis_angle_matrix

    cc = np.asarray(c)
    return rigid(None, cc) @ axis_angle_matrix(axis, deg) @ rigid(None, -cc)


def part_crops() -> dict:
    from registration.io import dicom
    from registration.studies.volume import find_real_ct

    out: dict = {"real_ct": [], "tall_phantom": []}
    path = find_real_ct()
    if path is not None:
        volume = dicom.read_volume(path)
        for fmt in IMAGE_FORMATS_CM:
            for prim, sec in ((0.0, 0.0), (90.0, 0.0), (30.0, 20.0)):
                g = replace(CArm.for_format(fmt, pixels=128, primary_deg=prim, secondary_deg=sec), isocenter_mm=ISO)
                image = XRayImage(np.zeros((g.rows, g.cols), np.float32), g.field_mask(), g, "fluoro", {})
                p = prepared_volume(volume, (image,), np.eye(4), RegistrationOptions())
                far = rigid(None, (0.0, 0.0, 60.0)) @ about(ISO, (1.0, 0.0, 0.0), 10.0)
                out["real_ct"].append({"format_cm": fmt, "primary_deg": prim, "secondary_deg": sec,
                                       "complete": p.crop.complete, "box_lo": list(p.box_lo), "box_hi": list(p.box_hi),
                                       "voxels_per_level": p.voxels_per_level,
                                       "missing_at_60mm_10deg": missing(p, g, far)})  # fmt: skip
                print(out["real_ct"][-1], flush=True)
    volume, _ = tall_phantom_ct()
    for bound_mm, bound_deg in ((30.0, 15.0), (10.0, 4.0)):
        for fmt in (15.0, 27.0):
            g = CArm.for_format(fmt, pixels=128)
            reach = Reach.of_search(bound_mm, bound_deg, translations=2)
            p = prepare_volume(volume, [g], reach=reach, levels=[1, 2], cache=False)
            row = {"search": [bound_mm, bound_deg], "format_cm": fmt, "complete": p.crop.complete,
                   "box_lo": list(p.box_lo), "box_hi": list(p.box_hi), "missing_headward": {}}  # fmt: skip
            for d in (20, 40, 60, 80, 100, 150):
                row["missing_headward"][d] = missing(p, g, rigid(None, (0.0, 0.0, float(d))))
            out["tall_phantom"].append(row)
            print(row, flush=True)
    return out


def _score(result, truth: np.ndarray, g: CArm) -> dict:
    errors = [residuals(f.estimate, truth[f.frame], g).inplane_mm for f in result.frames if f.status == "applied"]
    shown = [residuals(f.patient_motion, truth[f.frame], g).inplane_mm for f in result.frames]
    s = result.summary()
    return {
        **{k: s[k] for k in ("frames", "applied", "withheld", "unchanged", "captures", "reprepared")},
        "applied_error_mm_median": float(np.median(errors)) if errors else None,
        "applied_error_mm_max": float(np.max(errors)) if errors else None,
        "applied_worse_than_1mm": int(np.sum(np.array(errors) >= 1.0)),
        "shown_error_mm_last": shown[-1],
        "shown_error_mm_max": float(np.max(shown)),
        "crop_margin_mm_last": result.frames[-1].crop_margin_mm,
    }


def part_real_run() -> dict:
    from registration.io import dicom
    from registration.studies.volume import VolumeImager, find_real_ct

    path = find_real_ct()
    if path is None:
        raise SystemExit("error: the real head CT is not here (../shared/data/real-ct/head-neck-ct)")
    volume = dicom.read_volume(path)
    imager = VolumeImager(volume, ISO)
    g = replace(CArm.for_format(27.0, pixels=64, primary_deg=20.0, secondary_deg=-10.0), isocenter_mm=ISO)
    fps, seconds = 5.0, 60.0
    times = np.arange(int(fps * seconds)) / fps
    truth = []
    for t in times:
        walk = min(max(t - 2.0, 0.0), 30.0) * 1.0  # 1 mm/s headward from 2 s to 32 s
        m = rigid(None, (0.0, 0.0, walk))
        if t >= 35.0:
            s = min((t - 35.0) / 0.5, 1.0)
            m = rigid(None, (0.0, 0.0, 20.0 * s)) @ about(ISO, (0.0, 0.0, 1.0), 5.0 * s) @ m
        if t >= 45.0:
            s = min((t - 45.0) / 0.5, 1.0)
            m = rigid(None, (10.0 * s, 0.0, 11.0 * s)) @ about(ISO, (1.0, 0.0, 0.0), 5.0 * s) @ m
        truth.append(m)
    truth_a = np.array(truth)
    t0 = time.perf_counter()
    frames = [imager.image(g, m, kind="fluoro", seed=n) for n, m in enumerate(truth_a)]
    print(f"formed {len(frames)} frames in {time.perf_counter() - t0:.0f} s", flush=True)
    image = frames[0]
    prepared = prepared_volume(volume, (image,), np.eye(4), RegistrationOptions())
    result = track_run(volume, [frames], times, renderer=prepared.renderer, realtime=False, seed=0)
    end = residuals(np.eye(4), truth_a[-1], g)
    out = {"crop_complete": prepared.crop.complete, "voxels_per_level": prepared.voxels_per_level,
           "moved_at_end_mm": end.translation_mm, "moved_at_end_deg": end.rotation_deg,
           **_score(result, truth_a, g)}  # fmt: skip
    print(out, flush=True)
    return out


def part_tall_run() -> dict:
    from registration.sim.xray import simulate_xray

    volume, anatomy = tall_phantom_ct()
    g = CArm.for_format(15.0, pixels=64)
    capture = light_capture(RegistrationOptions(bound_mm=10.0, bound_deg=4.0))
    options = TrackingOptions(image_px=64, volume_voxels=64, capture=capture)
    motions = [np.eye(4)] * 3 + [rigid(None, (0.0, 0.0, 0.7 * (k + 1))) for k in range(130)]
    motions += [motions[-1]] * 3
    frames = [simulate_xray(anatomy, g, motion=m, kind="fluoro", catheter=False, seed=100 + n)
              for n, m in enumerate(motions)]  # fmt: skip
    times = np.arange(len(frames)) / 15.0
    out = {}
    for on in (True, False):
        prepared = prepare_volume(volume, [g], reach=Reach.of_search(10.0, 4.0, translations=2), levels=[1, 2],
                                  cache=False)  # fmt: skip
        result = track_run(volume, [frames], times, options=replace(options, reprepare=on),
                           renderer=prepared.renderer, realtime=False, seed=1)  # fmt: skip
        truth = np.array(motions)
        score = _score(result, truth, g)
        late = [residuals(f.estimate, truth[f.frame], g).inplane_mm for f in result.frames
                if f.status == "applied" and truth[f.frame][2, 3] >= 60.0]  # fmt: skip
        score["applied_error_mm_median_beyond_60mm"] = float(np.median(late)) if late else None
        score["applied_error_mm_max_beyond_60mm"] = float(np.max(late)) if late else None
        out["reprepare_on" if on else "reprepare_off"] = score
        print(on, score, flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("crops", "real-run", "tall-run"), required=True)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    result = {"crops": part_crops, "real-run": part_real_run, "tall-run": part_tall_run}[args.part]()
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(result, fh, indent=1, default=float)


if __name__ == "__main__":
    main()
