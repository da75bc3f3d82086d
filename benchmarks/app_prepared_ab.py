"""The app's file data and ``roadmap3d track`` on the real CT: whole-volume pyramid against the prepared levels.

Run: ``python benchmarks/app_prepared_ab.py [--repeats 5]`` (needs ../shared/data/real-ct/head-neck-ct).

A same-process A/B, the two paths alternated (ABBA) and repeated; it prints JSON with the median
seconds of each path and the median of the per-repeat ratios (new / old), plus DRR samples (the
work, whatever the machine's load) and the residuals against the truth the images were formed with:

- ``old``: what ``FileData.renderer`` and the tracker built before: ``DRRRenderer(volume, levels=3)``
  (the index pyramid of the whole 23.5 M-voxel CT, couch and shoulders included).
- ``new``: :func:`app.cli.commands.prepare_for_registration` (``register``'s preparation: cropped to
  what the field reaches over the search, isotropic 2 / 4 mm levels, the body only), made afresh
  each repeat (memory cleared, no disk cache: a first session's cost; later ones read the cache).

Measured per path: the renderer's making (``prepare_s``), one registration of a 384-px fluoro
formed from the CT (12 / -8 / 5 mm, 6 deg; ``register_s``) and a 12-frame 128-px run tracked every
frame (registered start, then a 2.5 mm / 1 deg move; ``track_s`` and the tracker's median latency).
Images formed from the CT itself (trilinear, Beer-Lambert, noise, catheter): a best case.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np

from app.cli.commands import prepare_for_registration
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, rigid
from registration.core.metrics import residuals
from registration.core.prepare import clear_cache
from registration.core.register import register
from registration.core.tracking import track_run
from registration.io import dicom
from registration.studies.runs import axis_angle_matrix
from registration.studies.volume import VolumeImager, find_real_ct

ISO = (247.5, -276.0, -90.0)


def _moved(t_mm: list[float], axis: list[float], deg: float) -> np.ndarray:
    c = np.asarray(ISO)
    a = np.asarray(axis, dtype=np.float64)
    return (
        rigid(None, np.asarray(t_mm, dtype=np.float64))
        @ rigid(None, c)
        @ axis_angle_matrix(a / np.linalg.norm(a), deg)
        @ rigid(None, -c)
    )


def _ratios(v: dict[str, list[float]]) -> dict[str, float]:
    """The old and new medians and the median of their per-round ratio."""
    return {
        "old_median": float(np.median(v["old"])),
        "new_median": float(np.median(v["new"])),
        "new_over_old_median": float(np.median(np.asarray(v["new"]) / np.asarray(v["old"]))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    path = find_real_ct()
    if path is None:
        raise SystemExit("error: the real head CT is not here (../shared/data/real-ct/head-neck-ct)")
    volume = dicom.read_volume(path)
    imager = VolumeImager(volume, ISO)
    g384 = replace(CArm.for_format(27.0, pixels=384, primary_deg=20.0, secondary_deg=-10.0), isocenter_mm=ISO)
    g128 = g384.resized(128, 128)
    m_reg = _moved([12.0, -8.0, 5.0], [1.0, 2.0, 0.5], 6.0)
    image = imager.image(g384, m_reg, kind="fluoro", seed=3)
    m_run = [np.eye(4)] * 6 + [_moved([2.5, -1.5, 0.0], [0.0, 0.0, 1.0], 1.0)] * 6
    run = [imager.image(g128, m, kind="fluoro", seed=10 + n) for n, m in enumerate(m_run)]
    times = np.arange(len(run)) / 15.0

    def make(which: str, views: list) -> DRRRenderer:
        if which == "old":
            return DRRRenderer(volume, levels=3)
        clear_cache()
        return prepare_for_registration(volume, views, cache=False)[0].renderer

    keys = ("prepare_s", "register_s", "track_s", "track_ms_median")
    rows: dict[str, dict[str, list[float]]] = {k: {"old": [], "new": []} for k in keys}
    last: dict[str, dict] = {}
    for rep in range(args.repeats):
        for which in ("old", "new") if rep % 2 == 0 else ("new", "old"):
            t = time.perf_counter()
            renderer = make(which, [image])
            rows["prepare_s"][which].append(time.perf_counter() - t)
            t = time.perf_counter()
            result = register(volume, image, renderer=renderer, truth=m_reg, seed=0)
            rows["register_s"][which].append(time.perf_counter() - t)
            tracker_renderer = make(which, [run[0]])
            t = time.perf_counter()
            tracked = track_run(volume, [run], times, renderer=tracker_renderer, seed=0, realtime=False)
            rows["track_s"][which].append(time.perf_counter() - t)
            rows["track_ms_median"][which].append(tracked.summary()["ms_per_frame_median"])
            shown = residuals(tracked.frames[-1].patient_motion, m_run[-1], g128)
            last[which] = {
                "voxels_per_level": [
                    int(np.prod(renderer.level_volume(k).shape)) if renderer.has_level(k) else None
                    for k in range(renderer.n_levels)
                ],
                "register_drr_samples": int(sum(renderer.samples_per_level)),
                "register_inplane_mm": result.residual.inplane_mm,
                "register_rotation_deg": result.residual.rotation_deg,
                "track_statuses": [f.status for f in tracked.frames],
                "track_last_shown_inplane_mm": shown.inplane_mm,
            }
    out = {k: _ratios(v) for k, v in rows.items()}
    print(json.dumps({"repeats": args.repeats, "volume_voxels": int(np.prod(volume.shape)), **out, "last": last},
                     indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
