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

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from registration import __version__
from registration.core.geometry import CArm, matrix_to_offsets
from registration.core.metrics import residuals
from registration.core.preparation import Preparation
from registration.core.tracking import TrackingOptions, TrackingRun, track_run
from registration.sim.fluoro import FluoroRun, RunScript, simulate_biplane_run
from registration.studies.cases import _phantom, load_volume
from registration.studies.report_kit import fmt_pct


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
        at 128 px with two sudden moves, drift, breathing, an advancing guidewire and two
        frames that show no anatomy (read-out glitches, which must be withheld)."""
        return cls(
            cases=(
                TrackingCase(
                    "run20s", RunScript(duration_s=20.0, seed=seed, sudden_moves=2, glitch_times_s=(5.0, 15.0))
                ),
            ),
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
            "cpu_ms": est.cpu_ms,
            "drr_count": est.drr_count,
            "drop_sigmas": est.drop_sigmas,
            "reprepared": est.reprepared,
            "crop_margin_mm": est.crop_margin_mm,
            "shown_error_mm": shown.translation_mm if biplane else shown.inplane_mm,
            "true_offset_mm": matrix_to_offsets(truth, geometry)[:3].tolist(),
            "shown_offset_mm": matrix_to_offsets(est.patient_motion, geometry)[:3].tolist(),
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


def run_timeline(result: TrackingRun, runs: list[FluoroRun]) -> dict:
    """At every frame of the run (skipped ones too): the true and the shown in-plane position
    (tx, ty mm in the view frame) and the roadmap's error. The roadmap shows the pose of the
    last frame processed before it (the initial pose before the first)."""
    geometry = runs[0].geometry
    biplane = len(runs) > 1
    shown = np.eye(4)
    by_frame = {f.frame: f for f in result.frames}
    true_xy, shown_xy, error = [], [], []
    for n in range(len(runs[0])):
        if n in by_frame:
            shown = by_frame[n].patient_motion
        truth = runs[0].truth[n]
        r = residuals(shown, truth, geometry)
        true_xy.append(matrix_to_offsets(truth, geometry)[:2].tolist())
        shown_xy.append(matrix_to_offsets(shown, geometry)[:2].tolist())
        error.append(r.translation_mm if biplane else r.inplane_mm)
    return {"t_s": runs[0].times_s.tolist(), "true_mm": true_xy, "shown_mm": shown_xy, "error_mm": error}


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
    # the volume prepared as `roadmap3d track` prepares it: for the runs' first frames' fields
    preparation = Preparation.of(volume, [run[0] for run in runs])
    say(f"{case.name}: tracking")
    started = time.perf_counter()
    result = track_run(volume, runs, runs[0].times_s, options=options, renderer=preparation.renderer, seed=seed,
                       realtime=realtime)  # fmt: skip
    wall = time.perf_counter() - started
    timeline = run_timeline(result, runs)
    return {
        "case": case.name,
        "case_config": {**asdict(case), "script": case.script.to_dict()},
        "planes": len(runs),
        "frames": scored if (scored := score_run(result, runs)) else [],
        "skipped": result.skipped,
        "timeline": timeline,
        "frame_count": result.frame_count,
        "summary": result.summary(),
        "wall_seconds": wall,
        "realtime": realtime,
        "prepare_seconds": preparation.seconds,
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
    timeline_err = np.array([e for c in cases for e in c.get("timeline", {}).get("error_mm", [])])
    cpu = np.array([f.get("cpu_ms", 0.0) for f in frames])
    cpu_capture = np.array([f.get("cpu_ms", 0.0) for f in frames if f["path"] == "capture"])

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
        "reprepared": sum(bool(f.get("reprepared")) for f in frames),
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
        "roadmap_error_mm_median_all_frames": q(timeline_err, 50),
        "roadmap_error_mm_p95_all_frames": q(timeline_err, 95),
        "cpu_ms_per_frame_median": q(cpu, 50),
        "cpu_ms_per_frame_p95": q(cpu, 95),
        "capture_cpu_ms_median": q(cpu_capture, 50),
        "realtime": bool(cases[0].get("realtime", True)) if cases else True,
        "applied_precision": precision,
        "applied_recall": recall,
        "still_runs_reporting_motion": sum(any(f["status"] != "unchanged" for f in c["frames"]) for c in still),
    }


def _case_key(case: TrackingCase, config: TrackingConfig) -> dict:
    """What a saved case's outcome depends on (a rerun reuses it only when all of this matches)."""
    return {
        "case_config": json.loads(json.dumps({**asdict(case), "script": case.script.to_dict()}, default=float)),
        "seed": config.seed,
        "realtime": config.realtime,
        "options": _options_dict(config.options),
        "version": __version__,
    }


def run_tracking_study(
    config: TrackingConfig, *, log: Callable[[str], None] | None = None, out: Path | None = None
) -> dict:
    """Every case of the config; returns {"summary", "cases", "config"}. With ``out``, each
    case's outcome is saved as it finishes (``out/cases/NAME.json``, written atomically) and a
    rerun with the same configuration reuses it: an interrupted study resumes at the case it
    was in."""
    from registration.io.dicom import write_text_atomic

    say = log or (lambda _m: None)
    cases = []
    for c in config.cases:
        saved = None if out is None else Path(out) / "cases" / f"{c.name}.json"
        key = _case_key(c, config)
        if saved is not None and saved.is_file():
            try:
                doc = json.loads(saved.read_text())
            except (OSError, ValueError):
                doc = None
            if isinstance(doc, dict) and doc.get("key") == key:
                say(f"{c.name}: reused from {saved}")
                cases.append(doc["case"])
                continue
        done = run_tracking_case(c, options=config.options, realtime=config.realtime, seed=config.seed, log=log)
        if saved is not None:
            saved.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomic(saved, json.dumps({"key": key, "case": done}, default=float))
        cases.append(done)
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
    """ms per frame over the quick tracking run (replayed at its frame times, frames arriving
    while busy skipped): wall and CPU time, the refine path apart from the full captures."""
    config = TrackingConfig.quick_config(seed)
    case = replace(config.cases[0])
    out = run_tracking_case(case, options=config.options, seed=seed)
    s = out["summary"]
    return {
        "ms_per_frame_median": s["ms_per_frame_median"],
        "ms_per_frame_p95": s["ms_per_frame_p95"],
        "refine_path_ms_median": s["refine_path_ms_median"],
        "refine_path_ms_p95": s["refine_path_ms_p95"],
        "capture_ms_median": s["capture_ms_median"],
        "cpu_ms_per_frame_median": s["cpu_ms_per_frame_median"],
        "cpu_ms_per_frame_p95": s["cpu_ms_per_frame_p95"],
        "capture_cpu_ms_median": s["capture_cpu_ms_median"],
        "note": "replayed at the frames' times: ms_per_frame_* include full captures; refine_path_* exclude them",
        "frames": s["frames"],
        "skipped": s["skipped"],
    }


# --------------------------------------------------------------------------------------
# Report: strip chart, latency, ROC
# --------------------------------------------------------------------------------------
def _case_from_dict(d: dict) -> TrackingCase:
    script = RunScript(**d["script"])
    fields = {k: v for k, v in d.items() if k != "script"}
    if fields.get("plane_b_deg") is not None:
        fields["plane_b_deg"] = tuple(fields["plane_b_deg"])
    return TrackingCase(script=script, **fields)


def strip_chart(case: dict, path: Path) -> Path:
    """Estimated (shown) vs true motion over the run, per-frame latency, and the decisions."""
    from registration.studies.report_kit import pyplot

    plt = pyplot()
    frames = case["frames"]
    timeline = case["timeline"]
    t_all = np.array(timeline["t_s"])
    true_mm = np.array(timeline["true_mm"])
    shown_mm = np.array(timeline["shown_mm"])
    t = np.array([f["t_s"] for f in frames])
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True, gridspec_kw={"height_ratios": [3, 1.3, 1.3]})
    ax = axes[0]
    for k, (name, color) in enumerate((("tx", "#1f77b4"), ("ty", "#d62728"))):
        ax.plot(t_all, true_mm[:, k], color=color, lw=1.0, alpha=0.5, label=f"true {name}")
        ax.step(t_all, shown_mm[:, k], where="post", color=color, lw=1.6, label=f"roadmap {name}")
    status_colors = {"applied": "#2ca02c", "withheld": "#ff7f0e"}
    for st, c in status_colors.items():
        ts = [f["t_s"] for f in frames if f["status"] == st]
        if ts:
            ax.plot(ts, [ax.get_ylim()[0]] * len(ts), "|", color=c, ms=10, label=st)
    ax.set_ylabel("in-plane position (mm, view frame)")
    ax.legend(ncol=3, fontsize=8, loc="best")
    ax.set_title(f"{case['case']}: roadmap vs true patient motion ({case['planes']} plane(s))")
    ax = axes[1]
    err = np.array(timeline["error_mm"])
    ax.plot(t_all, err, color="#444", lw=1.0)
    ax.axhline(1.0, color="#d62728", lw=0.8, ls="--")
    ax.set_ylabel("roadmap error (mm)\nat every frame")
    ax = axes[2]
    lat = np.array([f["latency_ms"] for f in frames])
    colors = [
        "#9467bd" if f["path"] == "capture" else ("#2ca02c" if f["path"] == "refine" else "#7f7f7f") for f in frames
    ]
    ax.scatter(t, lat, s=6, c=colors)
    ax.set_yscale("log")
    ax.axhline(66.0, color="#d62728", lw=0.8, ls="--")
    ax.set_ylabel("latency (ms)")
    ax.set_xlabel("time (s); grey: check, green: refine, purple: full capture; dashed: 66 ms")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fmt(v: object, unit: str = "", digits: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}{unit}"
    return f"{v}{unit}"


def _summary_lines(study: dict) -> list[str]:
    """The report's opening: how the runs were made and replayed, and the numbers beside the targets."""
    s = study["summary"]
    return [
        "# Live motion compensation: `roadmap3d validate tracking`",
        "",
        f"{'Quick' if study['config']['quick'] else 'Full'} study, seed {study['config']['seed']}, "
        f"roadmap3d {__version__}. Frames are simulated from the analytic phantom (honest image model: exact line "
        "integrals, Poisson noise at fluoroscopy dose, detector blur, collimation, a guidewire advancing), never "
        "by the renderer that scores them; the registration volume is the FDK 3DRA. Times are measured on a "
        "shared 2-core machine: other work ran beside it (the CPU time per frame does not grow with that load). "
        + (
            "Replayed at the frames' times: frames that arrived while the engine was busy were skipped."
            if s["realtime"]
            else "Replayed frame by frame (--every-frame): no frame skipped, latencies as measured."
        ),
        "",
        "| what | measured | target |",
        "| --- | --- | --- |",
        f"| frames (processed / skipped) | {s['frames']} ({s['processed']} / {s['skipped']}) | - |",
        f"| latency per frame, median / p95 | {_fmt(s['ms_per_frame_median'], ' ms', 1)} / "
        f"{_fmt(s['ms_per_frame_p95'], ' ms', 1)} | <= 66 / <= 150 ms |",
        f"| refine path (check + refine), median / p95 | {_fmt(s['refine_path_ms_median'], ' ms', 1)} / "
        f"{_fmt(s['refine_path_ms_p95'], ' ms', 1)} | <= 66 / <= 150 ms |",
        f"| full capture, median | {_fmt(s['capture_ms_median'], ' ms', 0)} ({s['captures']} captures) | <= 1000 ms |",
        "| CPU time per frame (all threads), median / p95; capture median | "
        f"{_fmt(s['cpu_ms_per_frame_median'], ' ms', 1)}"
        f" / {_fmt(s['cpu_ms_per_frame_p95'], ' ms', 1)}; {_fmt(s['capture_cpu_ms_median'], ' ms', 0)} | - |",
        f"| roadmap error at every frame (skipped ones too), median / p95 | "
        f"{_fmt(s['roadmap_error_mm_median_all_frames'], ' mm')} / "
        f"{_fmt(s['roadmap_error_mm_p95_all_frames'], ' mm')} | - |",
        f"| tracking error of applied frames, median | {_fmt(s['tracking_error_mm_median'], ' mm')} | <= 0.5 mm |",
        f"| worst applied estimate | {_fmt(s['max_error_applied_mm'], ' mm')} | < 2 mm |",
        f"| applied precision / recall | {fmt_pct(s['applied_precision'])} / {fmt_pct(s['applied_recall'])} | "
        ">= 99 % / >= 90 % |",
        f"| estimates applied / withheld / frames unchanged | {s['applied']} / {s['withheld']} / "
        f"{s['unchanged']} | - |",
        f"| roadmap error over all processed frames, median / p95 | {_fmt(s['shown_error_mm_median'], ' mm')} / "
        f"{_fmt(s['shown_error_mm_p95'], ' mm')} | - |",
        "",
        "Errors are residuals at the iso-center against each frame's truth (in-plane for one plane, total for "
        "two); an estimate is right when < 1 mm and < 3 degrees. Precision: applied estimates that are right; "
        "recall: right estimates that were applied.",
        "",
    ]


def write_tracking_report(study: dict, out: Path) -> dict[str, str]:
    """results.json, one strip chart per case, the ROC curve, report.md and report.html."""
    from registration.io.dicom import write_text_atomic
    from registration.studies.report_kit import write_report

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "results.json", json.dumps(study, default=float))
    images: dict[str, str] = {}
    for case in study["cases"]:
        name = f"strip_{case['case']}.png"
        strip_chart(case, out / name)
        images[case["case"]] = name
    from registration.studies.report_kit import roc_plot

    est = [f for c in study["cases"] for f in c["frames"] if "right" in f]
    rule_threshold = TrackingOptions().rule.threshold
    if est:
        roc_plot([f["confidence"] for f in est], [f["right"] for f in est], rule_threshold, out / "roc.png",
                 title="validate tracking: confidence of the estimates")  # fmt: skip
        images["roc"] = "roc.png"
    lines = _summary_lines(study)
    for case in study["cases"]:
        cs = case["summary"]
        lines += [
            f"## {case['case']}",
            "",
            f"{case['frame_count']} frames at {case['case_config']['script']['fps']:g} frames/s, "
            f"{case['case_config']['pixels']} px, {case['planes']} plane(s); volume: {case['volume_label']}. "
            f"{cs['processed']} processed, {cs['skipped']} skipped, {cs['captures']} full captures.",
            "",
            f"![strip chart]({images[case['case']]})",
            "",
        ]
    if "roc" in images:
        lines += ["## Confidence", "", "![ROC](roc.png)", ""]
    md = "\n".join(lines)
    write_report(out, md, "roadmap3d: live motion compensation")
    return images
