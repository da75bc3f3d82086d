"""The real CT's registration timed as the bench reports it: in this process on the shipped path,
and as ``roadmap3d register`` end to end.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from registration.core.volume import Volume
from registration.sim.volume_xray import IMAGES_FROM_VOLUME
from registration.studies.volume import (
    REAL_CT_RELATIVE,
    VolumeImager,
    VolumeStudyConfig,
    _views,
    case_motion,
    find_real_ct,
    head_isocenter_mm,
    run_volume_case,
    volume_cases,
)

#: Timed runs of ``register`` through a warm worker (after one that reads the CT into it).
WORKER_ROUNDS = 3


def bench_real_volume(
    *,
    seed: int = 0,
    cases: int = 3,
    log: Callable[[str], None] | None = None,
    phantom_seconds: float | None = None,
    command_line: bool = True,
) -> dict:
    """Registration on the real head CT: 384-px fluoro images of a 27 cm format at random angles
    and offsets <= 25 mm / 10 deg, the volume prepared per view (``prepare_seconds``), one
    registration end to end in this process (reading the DICOM series, preparing, registering)
    and (``command_line``) ``roadmap3d register --verbose`` in a new process on an XA formed from
    the CT (start-up, imports and numba's cache included). ``phantom_seconds``: the phantom's
    registration median of the same run, for the ratio. ``{"skipped": reason}`` when the CT is
    absent."""
    from registration.core.roi import followed_region
    from registration.io import dicom

    path = find_real_ct()
    if path is None:
        return {"skipped": f"no real CT at {REAL_CT_RELATIVE} (or ROADMAP3D_REAL_CT)"}
    say = log or (lambda _msg: None)
    t0 = time.perf_counter()
    volume = dicom.read_volume(path)
    read_s = time.perf_counter() - t0
    iso = head_isocenter_mm(volume)
    config = VolumeStudyConfig(cases=cases, seed=seed)
    imager = VolumeImager(volume, iso)
    # the region register follows by default (found once, as a study or a worker finds it)
    region = followed_region(volume, config.roi)
    records = []
    for case in volume_cases(config):
        say(f"real CT case {case.number + 1}/{cases} ...")
        records.append(run_volume_case(volume, imager, case, config, iso, confidence=True, region=region))
    end_to_end = read_s + records[0]["prepare_seconds"] + records[0]["seconds"]
    seconds = float(np.median([r["seconds"] for r in records]))
    cli = _command_line_register(volume, imager, config, iso, path, log=say) if command_line else None
    say("the same CT resampled to 0.5 x 0.5 x 2.5 mm ...")
    grid = finer_grid(volume, imager, config, iso)
    return {
        "seconds_median": seconds,
        "seconds_ratio_to_phantom": None if not phantom_seconds else seconds / phantom_seconds,
        "drr_samples_median": float(np.median([r["drr_samples"] for r in records])),
        "drr_samples_per_level": records[0]["drr_samples_per_level"],
        "drr_count_median": float(np.median([r["drr_count"] for r in records])),
        "prepare_seconds": float(np.median([r["prepare_seconds"] for r in records])),
        # the first case's preparation: the view-independent part built (later cases reuse it)
        "prepare_seconds_first": records[0]["prepare_seconds"],
        "voxels_per_level": records[0]["voxels_per_level"],
        "spacing_mm": records[0]["spacing_mm"],
        "source_voxels": int(np.prod(volume.shape)),
        "read_seconds": read_s,
        "register_end_to_end_seconds": end_to_end,
        "confidence": _confidence_cost(records),
        "command_line": cli,
        "finer_grid": grid,
        "success_rate": float(np.mean([r["success"] for r in records])),
        "runs": [
            {k: r[k] for k in ("seconds", "prepare_seconds", "inplane_residual_mm", "rotation_residual_deg", "success")}
            for r in records
        ],
        "volume": str(path),
        "region": None if region is None else region.describe(),
        "isocenter_mm": list(iso),
        "images": IMAGES_FROM_VOLUME,
    }


def _confidence_cost(records: list[dict]) -> dict:
    """What ``--confidence`` adds to each registration in this process: the assessment's seconds
    (the probe levels built once per preparation, before the first, not counted) against the
    registration's, per case."""
    ratios = [r["confidence_seconds"] / r["seconds"] for r in records]
    return {
        "seconds_median": float(np.median([r["confidence_seconds"] for r in records])),
        "ratio_to_registration_median": float(np.median(ratios)),
        "ratio_to_registration_min": float(min(ratios)),
        "applied": int(sum(bool(r["applied"]) for r in records)),
    }


#: The finer scanner grid the bench resamples the CT to (mm, x y z), and the rounds timed on each.
FINER_GRID_MM = (0.5, 0.5, 2.5)
FINER_GRID_ROUNDS = 3


def resampled(volume: Volume, spacing_mm: tuple[float, float, float]) -> Volume:
    """``volume`` resampled (linearly) to about ``spacing_mm`` over the same extent: its first and
    last voxels stay where they were, the spacing is the one that fits."""
    from scipy import ndimage

    nk, nj, ni = volume.shape
    sp = np.asarray(volume.spacing_mm, dtype=np.float64)  # x, y, z
    n_out = np.rint((np.array([ni, nj, nk]) - 1) * sp / np.asarray(spacing_mm)).astype(int) + 1
    data = ndimage.zoom(volume.data, n_out[::-1] / np.array([nk, nj, ni]), order=1, grid_mode=False)
    scale = (np.array([ni, nj, nk]) - 1) / (np.array(data.shape[::-1]) - 1)
    affine = volume.index_to_world.copy()
    affine[:3, :3] = volume.index_to_world[:3, :3] @ np.diag(scale)
    return Volume(data.astype(np.float32), affine, label=f"{volume.label} (resampled)", meta=volume.meta)


def finer_grid(
    volume: Volume, imager: VolumeImager, config: VolumeStudyConfig, isocenter_mm: tuple[float, float, float]
) -> dict:
    """Case 0 registered on ``volume`` and on it resampled to :data:`FINER_GRID_MM`, interleaved,
    :data:`FINER_GRID_ROUNDS` rounds each (the preparations built first): the seconds (min and
    median), their ratio, the DRR pixels of each (equal when the levels are), both residuals."""
    from registration.core.preparation import Preparation
    from registration.core.register import register

    fine = resampled(volume, FINER_GRID_MM)
    case = volume_cases(replace(config, cases=1))[0]
    geometry = _views(config, case, isocenter_mm)[0]
    truth = case_motion(case, isocenter_mm)
    image = imager.image(geometry, truth, kind=config.kind, seed=case.seed)
    preps = [Preparation.of(v, image) for v in (volume, fine)]
    seconds: list[list[float]] = [[], []]
    results = [None, None]
    for _ in range(FINER_GRID_ROUNDS):
        for k, (vol, prep) in enumerate(zip((volume, fine), preps, strict=True)):
            results[k] = register(vol, image, truth=truth, seed=case.seed, renderer=prep.renderer)
            seconds[k].append(results[k].seconds)
    pixels = [int(sum(c.rays for c in r.stages)) for r in results]
    return {
        "spacing_mm": [float(s) for s in fine.spacing_mm],
        "level_spacing_mm": [list(p.prepared.spacing_mm) for p in preps],
        "seconds_min": float(min(seconds[1])),
        "seconds_median": float(np.median(seconds[1])),
        "original_seconds_min": float(min(seconds[0])),
        "original_seconds_median": float(np.median(seconds[0])),
        "ratio_of_minima": float(min(seconds[1]) / min(seconds[0])),
        "drr_pixels": pixels[1],
        "original_drr_pixels": pixels[0],
        "inplane_residual_mm": float(results[1].residual.inplane_mm),
        "original_inplane_residual_mm": float(results[0].residual.inplane_mm),
        "rounds": FINER_GRID_ROUNDS,
    }


def _command_line_register(
    volume: Volume,
    imager: VolumeImager,
    config: VolumeStudyConfig,
    isocenter_mm: tuple[float, float, float],
    series: Path,
    *,
    log: Callable[[str], None],
) -> dict:
    """``roadmap3d register --verbose`` in a new process: the series against an XA of case 0
    formed from it (and its truth), wall seconds and the command's own breakdown."""
    import sys
    import tempfile

    from registration.io import dicom

    case = volume_cases(replace(config, cases=1))[0]
    geometry = _views(config, case, isocenter_mm)[0]
    truth = case_motion(case, isocenter_mm)
    image = imager.image(geometry, truth, kind=config.kind, seed=case.seed)
    with tempfile.TemporaryDirectory(prefix="roadmap3d-bench-") as tmp:
        xa, truth_json = Path(tmp) / "xa.dcm", Path(tmp) / "truth.json"
        dicom.write_xray(image, xa, description=f"fluoro formed from {volume.label or 'the CT'} (bench, case 0)")
        truth_json.write_text(json.dumps({"patient_motion": truth.tolist()}))
        iso = ",".join(f"{c:.6g}" for c in isocenter_mm)
        argv = [sys.executable, "-c", "from app.cli import main; main()", "register", "--volume", str(series),
                "--image", str(xa), "--truth", str(truth_json), "--isocenter", iso, "--verbose"]  # fmt: skip
        # a cache folder of its own: the first run prepares from scratch (cold), the second finds the
        # view-independent part of the preparation on disk (warm: a later registration on this CT)
        env = os.environ | {"ROADMAP3D_CACHE": str(Path(tmp) / "cache")}
        env.pop("ROADMAP3D_NO_CACHE", None)
        # the modules kept as bytecode, as an installed package has them, also where the
        # environment turns writing it off (the cold run writes what is missing)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        runs = []
        # cold, warm, then warm with --confidence (the estimate assessed on the prepared levels)
        for what, extra in (("cold", []), ("warm", []), ("warm, --confidence", ["--confidence"])):
            log(f"roadmap3d register on the real CT in a new process ({what} cache) ...")
            runs.append(_timed(argv + extra, env))
        worker = _on_worker(argv[3:], env, Path(tmp) / "worker", log=log)
        if "wall_seconds_median" in worker and runs[1]["wall_seconds"] > 0:
            worker["ratio_to_own_process_warm"] = worker["wall_seconds_median"] / runs[1]["wall_seconds"]
    # the cold run's keys as before, the warm runs beside them
    return runs[0] | {
        "warm": runs[1],
        "warm_confidence": runs[2],
        "worker": worker,
        "command": "roadmap3d register --volume CT --image XA --truth JSON --isocenter ISO --verbose",
        "bytecode": "kept (written by the cold run where missing), as an installed package has it",
    }


def _timed(argv: list[str], env: dict[str, str]) -> dict:
    """One ``register --verbose`` in a new process: its wall seconds, exit code, time line, success."""
    import subprocess

    start = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, timeout=600, check=False, env=env)
    wall = time.perf_counter() - start
    timing = next((line for line in done.stderr.splitlines() if line.startswith("time: ")), None)
    success = "-> success" in done.stdout
    return {"wall_seconds": wall, "exit_code": done.returncode, "timing": timing, "success": success}


def _on_worker(args: list[str], env: dict[str, str], folder: Path, *, log: Callable[[str], None]) -> dict:
    """The same command through the console script to a warm worker (``roadmap3d serve``): the
    first run reads the CT into the worker's memory, the next ``WORKER_ROUNDS`` are timed (wall
    seconds of the client process, start-up included; min and median)."""
    import subprocess
    import sys

    script = [sys.executable, "-c", "import sys; sys.argv[0] = 'roadmap3d'; from app.launch import main; main()"]
    env = env | {"ROADMAP3D_WORKER_SOCKET": str(folder / "worker.sock")}
    env.pop("ROADMAP3D_WORKER", None)
    log("roadmap3d register on the real CT through a warm worker (roadmap3d serve) ...")
    server = subprocess.Popen([*script, "serve", "--socket", env["ROADMAP3D_WORKER_SOCKET"]], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        assert server.stdout is not None
        ready = ""
        for line in server.stdout:
            if "ready in" in line or "error" in line:
                ready = line
                break
        if "ready in" not in ready:
            return {"skipped": f"the worker did not start: {ready.strip() or 'no output'}"}
        runs = []
        for _ in range(1 + WORKER_ROUNDS):
            runs.append(_timed(script + args, env))
    finally:
        server.terminate()
        server.wait(timeout=60)
    timed = [r["wall_seconds"] for r in runs[1:]]
    return {
        "first": runs[0],
        "wall_seconds_min": float(np.min(timed)),
        "wall_seconds_median": float(np.median(timed)),
        "rounds": WORKER_ROUNDS,
        "runs": runs[1:],
    }
