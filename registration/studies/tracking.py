"""``roadmap3d validate tracking``: live motion compensation over simulated fluoroscopy runs.

Each case is a run of the phantom (:mod:`registration.sim.fluoro`: still periods, drift,
sudden moves, breathing, a guidewire advancing; honest images) tracked against the FDK 3DRA by
:func:`registration.core.tracking.track_run` at the run's frame times (frames that arrive while
the engine is busy are skipped). Every processed frame is scored against the truth of its
frame: the residual of the pose the roadmap shows, and of the engine's estimate where there is
one (at the iso-center; in-plane for one plane, total for two). An estimate is "right" when
< 1 mm and < 3 degrees; applied precision = applied estimates that are right, recall = right
estimates that were applied.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from registration import __version__
from registration.core.geometry import CArm
from registration.core.metrics import residuals
from registration.core.tracking import TrackingOptions, TrackingRun, track_run
from registration.sim.fluoro import FluoroRun, RunScript, simulate_biplane_run
from registration.studies.cases import _phantom, load_volume, prepared_renderer


@dataclass(frozen=True)
class TrackingCase:
    """One tracked run: its script, views and volume."""

    name: str
    script: RunScript
    image_format_cm: float = 27.0
    volume_format_cm: float = 27.0
    pixels: int = 128
    volume_voxels: int = 128
    volume_source: str = "fdk"
    primary_deg: float = 0.0
    secondary_deg: float = 0.0
    #: Plane B's angles for a biplane run (None: one plane).
    plane_b_deg: tuple[float, float] | None = None


@dataclass(frozen=True)
class TrackingConfig:
    cases: tuple[TrackingCase, ...]
    realtime: bool = True
    seed: int = 0
    quick: bool = False
    options: TrackingOptions = field(default_factory=TrackingOptions)

    @classmethod
    def quick_config(cls, seed: int = 0) -> TrackingConfig:
        """About two minutes on 2 cores (the run is simulated once, then cached): one 20 s run
        at 128 px with two sudden moves, drift, breathing and an advancing guidewire."""
        return cls(
            cases=(TrackingCase("run20s", RunScript(duration_s=20.0, seed=seed, sudden_moves=2)),),
            seed=seed,
            quick=True,
        )

    @classmethod
    def full_config(cls, seed: int = 0) -> TrackingConfig:
        """Three 40 s runs at 256 px on 256^3: frontal, oblique, and a run of a still patient."""
        return cls(
            cases=(
                TrackingCase(
                    "frontal40s", RunScript(duration_s=40.0, seed=seed, sudden_moves=3), pixels=256, volume_voxels=256
                ),
                TrackingCase(
                    "oblique40s",
                    RunScript(duration_s=40.0, seed=seed + 1, sudden_moves=3),
                    pixels=256,
                    volume_voxels=256,
                    primary_deg=30.0,
                    secondary_deg=10.0,
                ),
                TrackingCase("still20s", RunScript.still(20.0, seed=seed + 2), pixels=256, volume_voxels=256),
            ),  # fmt: skip
            seed=seed,
        )


def case_runs(case: TrackingCase, progress: Callable[[int, int], None] | None = None) -> list[FluoroRun]:
    """The simulated run(s) of a case (cached on disk)."""
    geometries = [
        CArm.for_format(
            case.image_format_cm, pixels=case.pixels, primary_deg=case.primary_deg, secondary_deg=case.secondary_deg
        )
    ]
    if case.plane_b_deg is not None:
        geometries.append(
            CArm.for_format(
                case.image_format_cm, pixels=case.pixels, primary_deg=case.plane_b_deg[0],
                secondary_deg=case.plane_b_deg[1],
            )
        )  # fmt: skip
    anatomy = _phantom(0, False, True)  # no contrast in fluoro
    return simulate_biplane_run(anatomy, geometries, case.script, progress=progress)


def score_run(result: TrackingRun, runs: list[FluoroRun]) -> list[dict]:
    """One record per processed frame: status, decision, residuals against the truth."""
    geometry = runs[0].geometry
    biplane = len(runs) > 1
    records = []
    for est in result.frames:
        truth = runs[0].truth[est.frame]
        shown = residuals(est.patient_motion, truth, geometry)
        rec = {
            "frame": est.frame,
            "t_s": est.t_s,
            "phase": runs[0].phases[est.frame],
            "status": est.status,
            "path": est.path,
            "confidence": est.confidence,
            "reason": est.reason,
            "latency_ms": est.latency_ms,
            "drr_count": est.drr_count,
            "drop_sigmas": est.drop_sigmas,
            "shown_error_mm": shown.translation_mm if biplane else shown.inplane_mm,
            "shown_rotation_deg": shown.rotation_deg,
            "evidence": est.evidence,
        }
        if est.estimate is not None:
            r = residuals(est.estimate, truth, geometry)
            err = r.translation_mm if biplane else r.inplane_mm
            rec.update(
                estimate_error_mm=err,
                estimate_rotation_deg=r.rotation_deg,
                right=bool(err < 1.0 and r.rotation_deg < 3.0),
                applied=est.status == "applied",
            )
        records.append(rec)
    return records


def run_tracking_case(
    case: TrackingCase,
    *,
    options: TrackingOptions | None = None,
    realtime: bool = True,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
) -> dict:
    """Simulate (or load) the case's run, track it, and score every processed frame."""
    say = log or (lambda _m: None)
    say(f"{case.name}: simulating the run ({case.script.frames} frames of {case.pixels} px, cached)")
    runs = case_runs(case)
    volume = load_volume(0, True, case.volume_format_cm, case.volume_voxels, case.volume_source)
    renderer, prepare_s = prepared_renderer(volume)
    say(f"{case.name}: tracking")
    started = time.perf_counter()
    result = track_run(volume, runs, runs[0].times_s, options=options, renderer=renderer, seed=seed, realtime=realtime)
    wall = time.perf_counter() - started
    return {
        "case": case.name,
        "case_config": {**asdict(case), "script": case.script.to_dict()},
        "planes": len(runs),
        "frames": scored if (scored := score_run(result, runs)) else [],
        "skipped": result.skipped,
        "frame_count": result.frame_count,
        "summary": result.summary(),
        "wall_seconds": wall,
        "prepare_seconds": prepare_s,
        "volume_label": volume.label,
        "images": "simulated from the analytic phantom (honest image model), not from the 3DRA",
        "version": __version__,
    }


def summarize_tracking(cases: list[dict]) -> dict:
    """The summary of ``validate tracking`` over every case's frames."""
    from registration.core.confidence import precision_recall

    frames = [f for c in cases for f in c["frames"]]
    est = [f for f in frames if "right" in f]
    applied = [f for f in est if f["applied"]]
    lat = np.array([f["latency_ms"] for f in frames]) if frames else np.zeros(0)
    refine_lat = np.array([f["latency_ms"] for f in frames if f["path"] != "capture"])
    capture_lat = np.array([f["latency_ms"] for f in frames if f["path"] == "capture"])
    precision, recall = precision_recall([f["applied"] for f in est], [f["right"] for f in est])
    applied_err = np.array([f["estimate_error_mm"] for f in applied])
    shown = np.array([f["shown_error_mm"] for f in frames])

    def q(a: np.ndarray, p: float) -> float | None:
        return float(np.percentile(a, p)) if len(a) else None

    still = [
        c for c in cases if c["case_config"]["script"]["sudden_moves"] == 0 and not c["case_config"]["script"]["drift"]
    ]
    return {
        "runs": len(cases),
        "frames": int(sum(c["frame_count"] for c in cases)),
        "processed": len(frames),
        "skipped": int(sum(len(c["skipped"]) for c in cases)),
        "estimates": len(est),
        "applied": len(applied),
        "withheld": sum(f["status"] == "withheld" for f in frames),
        "unchanged": sum(f["status"] == "unchanged" for f in frames),
        "captures": sum(f["path"] == "capture" for f in frames),
        "ms_per_frame_median": q(lat, 50),
        "ms_per_frame_p95": q(lat, 95),
        "refine_path_ms_median": q(refine_lat, 50),
        "refine_path_ms_p95": q(refine_lat, 95),
        "capture_ms_median": q(capture_lat, 50),
        "tracking_error_mm_median": q(applied_err, 50),
        "max_error_applied_mm": float(applied_err.max()) if len(applied_err) else None,
        "applied_worse_than_2mm": int((applied_err >= 2.0).sum()),
        "shown_error_mm_median": q(shown, 50),
        "shown_error_mm_p95": q(shown, 95),
        "applied_precision": precision,
        "applied_recall": recall,
        "still_runs_reporting_motion": sum(any(f["status"] != "unchanged" for f in c["frames"]) for c in still),
    }


def run_tracking_study(config: TrackingConfig, *, log: Callable[[str], None] | None = None) -> dict:
    """Every case of the config; returns {"summary", "cases", "config"}."""
    cases = [
        run_tracking_case(c, options=config.options, realtime=config.realtime, seed=config.seed, log=log)
        for c in config.cases
    ]
    return {
        "summary": summarize_tracking(cases),
        "cases": cases,
        "config": {"quick": config.quick, "seed": config.seed, "realtime": config.realtime,
                   "options": _options_dict(config.options)},
    }  # fmt: skip


def _options_dict(options: TrackingOptions) -> dict:
    out = {}
    for k, v in asdict(options).items():
        out[k] = v if isinstance(v, (int, float, bool, str, type(None))) else str(v)
    return out


def bench_tracking(*, seed: int = 0) -> dict:
    """ms per frame over the quick tracking run (realtime replay)."""
    config = TrackingConfig.quick_config(seed)
    case = replace(config.cases[0])
    out = run_tracking_case(case, options=config.options, seed=seed)
    s = out["summary"]
    return {
        "ms_per_frame_median": s["ms_per_frame_median"],
        "ms_per_frame_p95": s["ms_per_frame_p95"],
        "refine_path_ms_median": s["refine_path_ms_median"],
        "capture_ms_median": s["capture_ms_median"],
        "frames": s["frames"],
        "skipped": s["skipped"],
    }
