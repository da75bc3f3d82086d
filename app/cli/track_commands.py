"""The tracking commands: ``roadmap3d track`` and ``roadmap3d phantom-run``.

``track`` follows the patient over a fluoroscopy run (one multi-frame XA/RF, or two for a
biplane pair) at the run's frame times and writes the per-frame list of CONVENTIONS §7
(frame, t_s, patient_motion, status) with the latency, confidence and reason of each frame.
``phantom-run`` writes a simulated run of the phantom (with its per-frame truth) to try it on.
Bad input raises ``ValueError`` (a DicomError names the file and the tag): ``error: ...``, exit 2.
"""

from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from app.cli.configs import PhantomRun, Track
from app.cli.errors import UserError
from registration.io import dicom
from registration.io.isocenter import from_volume

#: Files written by ``roadmap3d phantom-run``.
RUN_FILE = "fluoro_run.dcm"
RUN_B_FILE = "fluoro_run_b.dcm"
RUN_TRUTH = "run_truth.json"
RUN_VOLUME_DIR = "volume"


def _say(text: str = "") -> None:
    print(text, flush=True)


def _err(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def read_run_truth(path: Path, frames: int) -> np.ndarray:
    """(frames, 4, 4) true motions from a ``run_truth.json`` (as ``phantom-run`` writes it)."""
    import json

    try:
        doc = json.loads(Path(path).read_text())
        motions = np.asarray([f["patient_motion"] for f in doc["frames"]], dtype=np.float64)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a run truth file (frames[].patient_motion): {exc}") from None
    if motions.shape != (frames, 4, 4) or not np.all(np.isfinite(motions)):
        raise ValueError(f"{path}: holds {motions.shape[0] if motions.ndim else 0} 4x4 motions for {frames} frames")
    return motions


def run_track(options: Track) -> int:
    """``roadmap3d track``: a run (or a biplane pair of runs) from files, or from a PACS."""
    if options.pacs is not None:
        if options.report is not None:
            raise UserError("--report works on files only (not with --pacs) for now")
        if options.pixel_mm is not None:
            raise UserError("--pixel-mm works on files only (not with --pacs) for now")
        from app.cli.net_commands import run_track_pacs

        return run_track_pacs(options, track_files)
    if options.study or options.ca_bundle:
        raise UserError("--study and --ca-bundle need --pacs URL")
    return track_files(options)


def _read_runs(options: Track) -> tuple[Any, list, Path, Path | None]:
    """The volume and the run(s), a biplane pair checked and ordered plane A, plane B; returns
    the volume, the runs and their paths in that order."""
    from app.cli.commands import parse_isocenter

    run, run_b, isocenter = options.run, options.run_b, options.isocenter
    given = {"sid_mm": options.sid_mm, "sod_mm": options.sod_mm, "frame_time_ms": options.frame_time_ms,
             "pixel_mm": options.pixel_mm}  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vol = dicom.read_volume(options.volume)
        iso = parse_isocenter(isocenter, vol)
        runs = [dicom.read_xray_run(run, isocenter_mm=iso, **given)]
        if run_b is not None:
            runs.append(dicom.read_xray_run(run_b, isocenter_mm=iso, **given))
    for w in caught:
        _err(f"warning: {w.message}")
    if len(runs) == 2:
        names = [run, run_b]
        planes = [r.planes[0] if r.planes else "" for r in runs]
        if planes[0] == planes[1] and planes[0] in ("PLANE A", "PLANE B"):
            raise ValueError(f"{run} and {run_b} are both {planes[0]} (0018,9457): a biplane pair needs plane A and B")
        if planes[0] == "PLANE B" or planes[1] == "PLANE A":  # given the other way round: plane A goes first
            _err(f"note: {run_b} is plane A by its Plane Identification (0018,9457): tracked as plane A, {run} as B")
            runs.reverse()
            names.reverse()
            run, run_b = names
        if len(runs[0]) != len(runs[1]):
            raise ValueError(f"{run} has {len(runs[0])} frames but {run_b} has {len(runs[1])}: not one biplane run")
        if not np.allclose(runs[0].times_s, runs[1].times_s, atol=1e-3):
            raise ValueError(f"{run} and {run_b}: frame times differ (not taken at the same moments)")
    if len(runs) == 1 and runs[0].planes and runs[0].planes[0] in ("PLANE A", "PLANE B"):
        _err(f"note: {run} is {runs[0].planes[0]} of a biplane run; --run-b with the other plane's run tracks both")
    return vol, runs, run, run_b


def _prepare(vol: Any, frames: list) -> tuple[Any, Any]:
    """The volume prepared as ``register`` prepares it (cropped to what the run's fields reach over
    a capture's search from the initial pose, levels in mm, cached on disk): the tracking level and
    the captures render these levels, not a pyramid of the whole volume."""
    from app.cli.commands import prepare_for_registration

    prep_start = time.perf_counter()
    prepared, store = prepare_for_registration(vol, [f[0] for f in frames])
    kept = [n for n in prepared.voxels_per_level if n is not None]
    _err(
        f"prepared the volume for the run's field{'s' if len(frames) == 2 else ''}: "
        f"{', '.join(f'{n / 1e6:.2g} M' for n in kept)} voxels per level (the volume: "
        f"{np.prod(vol.shape) / 1e6:.3g} M) in {time.perf_counter() - prep_start:.1f} s"
        + (" (from the cache)" if prepared.base_source == "disk" else "")
    )
    return prepared, store


def _frame_printer() -> Callable[[Any], None]:
    """What ``track`` says of a frame on stderr: every change, and every 30th frame."""
    shown = {"n": 0}

    def on_frame(est: Any) -> None:
        shown["n"] += 1
        if est.reprepared:  # the applied pose neared the crop's edge: prepared again around it
            c = est.crop
            _err(
                f"  frame {est.frame:4d} t={est.t_s:6.2f} s crop prepared again around the applied pose (started at "
                f"frame {c['started_frame']}, ready after {c['ready_after_ms']:.0f} ms): "
                f"{', '.join(f'{n / 1e6:.2g} M' for n in c['voxels_per_level'] if n is not None)} voxels per level"
            )
        if est.status != "unchanged" or shown["n"] % 30 == 0:
            conf = "" if est.confidence is None else f" confidence {est.confidence:.2f}"
            why = f" ({est.reason})" if est.reason else ""
            _err(
                f"  frame {est.frame:4d} t={est.t_s:6.2f} s {est.status:<9} {est.path:<7} "
                f"{est.latency_ms:7.1f} ms{conf}{why}"
            )

    return on_frame


def _score(result: Any, document: dict, summary: dict, m_true: np.ndarray, geom: Any, biplane: bool) -> None:
    """Each frame's error against the truth (shown pose and estimate) into ``document``, and the
    applied estimates' median and worst error, precision and recall into ``summary``."""
    from registration.core.confidence import precision_recall
    from registration.core.metrics import residuals

    errors, right, applied = [], [], []
    for f, rec in zip(result.frames, document["frames"], strict=True):
        r = residuals(f.patient_motion, m_true[f.frame], geom)
        rec["shown_error_mm"] = r.translation_mm if biplane else r.inplane_mm
        rec["shown_rotation_deg"] = r.rotation_deg
        if f.estimate is not None:
            e = residuals(f.estimate, m_true[f.frame], geom)
            err = e.translation_mm if biplane else e.inplane_mm
            rec["estimate_error_mm"] = err
            right.append(err < 1.0 and e.rotation_deg < 3.0)
            applied.append(f.status == "applied")
            if f.status == "applied":
                errors.append(err)
    p, rc = precision_recall(applied, right)
    summary.update(
        tracking_error_mm_median=float(np.median(errors)) if errors else None,
        max_error_applied_mm=float(np.max(errors)) if errors else None,
        applied_precision=p,
        applied_recall=rc,
    )
    document["summary"] = summary


def _say_summary(summary: dict, crop: Any, wall_s: float, scored: bool) -> None:
    _say(
        f"{summary['frames']} frames: {summary['processed']} processed, {summary['skipped']} skipped "
        f"(arrived while busy); {summary['applied']} applied, {summary['withheld']} withheld, "
        f"{summary['unchanged']} unchanged; {summary['captures']} full captures; "
        + (
            "the crop holds the whole body (never prepared again)"
            if crop is None or crop.complete
            else f"the crop prepared again {summary['reprepared']} time(s) around the applied pose"
        )
    )
    med, p95 = summary["ms_per_frame_median"], summary["ms_per_frame_p95"]
    _say(f"latency: median {med:.1f} ms, p95 {p95:.1f} ms per frame; {wall_s:.1f} s in all")
    if scored and summary.get("tracking_error_mm_median") is not None:
        prec, rec_ = summary["applied_precision"], summary["applied_recall"]
        _say(
            f"vs truth: applied estimates median {summary['tracking_error_mm_median']:.2f} mm, "
            f"max {summary['max_error_applied_mm']:.2f} mm; precision "
            f"{'-' if prec is None else f'{100 * prec:.1f} %'}, recall {'-' if rec_ is None else f'{100 * rec_:.1f} %'}"
        )


def track_files(options: Track) -> int:
    """Track a run (or a biplane pair of runs); print a summary; optionally write the JSON and,
    with ``report``, the report folder (:mod:`app.cli.report_commands`; ``report_identify``: with the
    patient's name, ID and the file paths).

    ``sid_mm``, ``sod_mm``, ``pixel_mm`` and ``frame_time_ms`` fill in what a run's files lack
    (:func:`registration.io.dicom.read_xray_run`)."""
    from app.cli.commands import parse_isocenter
    from app.cli.report_commands import check_report_folder
    from registration.core.tracking import track_run

    out, report, isocenter = options.out, options.report, options.isocenter
    if out is not None and Path(out).is_dir():
        raise ValueError(f"{out}: is a folder; --out takes a JSON file name")
    check_report_folder(report)
    if isocenter is not None and not from_volume(isocenter):
        parse_isocenter(isocenter)  # a bad value is refused before any file is read
    vol, runs, run, run_b = _read_runs(options)
    times = runs[0].times_s
    m_true = read_run_truth(options.truth, len(times)) if options.truth is not None else None
    _say(f"volume: {vol.label}  {vol.shape[2]}x{vol.shape[1]}x{vol.shape[0]} voxels")
    g = runs[0].geometries[0]
    span = float(times[-1] - times[0]) if len(times) > 1 else 0.0
    _say(
        f"run:    {run}: {len(times)} frames over {span:.1f} s (times from {runs[0].times_from}), "
        f"{g.cols}x{g.rows} px" + (f"; plane B {run_b}" if run_b else "")
    )
    # decode every frame first: in the clinic frames arrive decoded; decoding is not the engine's latency
    frames = [r.frames() for r in runs]
    prepared, store = _prepare(vol, frames)
    started = time.perf_counter()
    result = track_run(vol, frames, times, seed=options.seed, realtime=not options.every_frame,
                       on_frame=_frame_printer(), renderer=prepared.renderer)  # fmt: skip
    wall = time.perf_counter() - started
    if store is not None:
        store.flush()  # a first run writes the prepared volume while it tracks
    summary = result.summary()
    document = result.to_dict()
    document["volume"] = {"path": str(options.volume), "label": vol.label}
    document["runs"] = [str(run)] + ([str(run_b)] if run_b else [])
    document["conventions"] = (
        "shared/CONVENTIONS.md §7: per frame (frame, t_s, patient_motion, status); patient_motion is the pose the "
        "roadmap shows after the frame (the last applied estimate)"
    )
    if m_true is not None:
        _score(result, document, summary, m_true, g, biplane=len(runs) == 2)
    _say_summary(summary, prepared.crop, wall, scored=m_true is not None)
    if out is not None:
        dicom.write_text_atomic(out, dicom.json_dumps(document))
        _say(f"wrote {out}")
    if report is not None:
        from app.cli.report_commands import write_run_report

        last = result.frames[-1].frame if result.frames else len(times) - 1
        write_run_report(
            report, document=document, volume=vol, last_views=[f[last] for f in frames], renderer=prepared.renderer,
            truth=m_true, identify=options.report_identify,
        )  # fmt: skip
        _say(f"wrote {report}/ (open {Path(report) / 'report.html'})")
    return 0


def _write_run_export(out: Path, options: PhantomRun, volume: Any, description: str, runs: list, truth: dict) -> None:
    """The export folder, whole or not at all: the 3DRA series, each plane's run and the truth."""
    seed, seconds, pixels, image_format, biplane = (options.seed, options.seconds, options.pixels,
                                                   options.image_format, options.biplane)  # fmt: skip
    uid_seed = f"roadmap3d phantom run {seed} {seconds} {pixels} {image_format} {biplane}"
    study_uid = str(dicom.make_uid(uid_seed, "study"))
    with dicom.atomic_folder(out) as tmp:
        dicom.write_series(volume, tmp / RUN_VOLUME_DIR, description=description, study_uid=study_uid,
                           uid_seed=uid_seed)  # fmt: skip
        names = [RUN_FILE, RUN_B_FILE]
        for p, r in enumerate(runs):
            dicom.write_xray_run(
                list(r), tmp / names[p], times_s=r.times_s, plane=r.plane if biplane else None,
                study_uid=study_uid, uid_seed=f"{uid_seed} plane {p}",
                description=f"roadmap3d fluoro run{' ' + r.plane if biplane else ''}",
            )  # fmt: skip
        dicom.write_text_atomic(tmp / RUN_TRUTH, dicom.json_dumps(truth))


def run_phantom_run_export(options: PhantomRun) -> int:
    """Write a simulated fluoroscopy run of the phantom (multi-frame XA with its frame times),
    its per-frame truth, and the 3DRA series to track it with."""
    out, seconds, pixels, image_format = options.out, options.seconds, options.pixels, options.image_format
    primary_deg, secondary_deg, biplane = options.primary_deg, options.secondary_deg, options.biplane
    sudden_moves, seed, voxels = options.sudden_moves, options.seed, options.voxels
    volume_source = options.volume_source
    from app.cli.phantom_commands import _phantom_3dra
    from registration.core.geometry import CArm
    from registration.sim.fluoro import RunScript, simulate_biplane_run
    from registration.sim.phantom import make_head_phantom

    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not an empty folder; refusing to overwrite")
    if pixels < 32 or pixels > 1024:
        raise ValueError(f"--pixels must lie in 32..1024, got {pixels}")
    script = RunScript(duration_s=seconds, seed=seed, sudden_moves=sudden_moves)
    geometries = [CArm.for_format(image_format, pixels=pixels, primary_deg=primary_deg, secondary_deg=secondary_deg)]
    if biplane:
        geometries.append(CArm.for_format(image_format, pixels=pixels, primary_deg=primary_deg + 90.0))
    start = time.perf_counter()
    anatomy = make_head_phantom(seed=0, contrast=False)

    def progress(done: int, total: int) -> None:
        if done % 25 == 0 or done == total:
            _err(f"  frame {done}/{total} ({time.perf_counter() - start:.0f} s)")

    _err(f"simulating {script.frames} frames x {len(geometries)} plane(s) of {pixels} px (cached after the first time)")
    runs = simulate_biplane_run(anatomy, geometries, script, progress=progress)
    volume, description, made = _phantom_3dra(
        source=volume_source, seed=0, contrast=True, volume_format=image_format, voxels=voxels
    )
    truth = {
        "frames": [
            {"frame": n, "t_s": float(t), "patient_motion": runs[0].truth[n].tolist(), "phase": runs[0].phases[n]}
            for n, t in enumerate(runs[0].times_s)
        ],
        "script": script.to_dict(),
        "geometry": geometries[0].to_dict(),
        "volume_label": volume.label,
        **made,
        "images": "the analytic phantom moved by patient_motion (honest image model), not the 3DRA",
        "conventions": "shared/CONVENTIONS.md §4, §7: anatomy the volume shows at X is at M @ X in frame n",
    }
    _write_run_export(out, options, volume, description, runs, truth)
    _say(f"wrote {out}/ in {time.perf_counter() - start:.1f} s: {RUN_VOLUME_DIR}/ ({volume.label}), {RUN_FILE}"
         + (f", {RUN_B_FILE}" if biplane else "") + f", {RUN_TRUTH}")  # fmt: skip
    b = f" --run-b {out / RUN_B_FILE}" if biplane else ""
    _say(
        f"try: roadmap3d track --volume {out / RUN_VOLUME_DIR} --run {out / RUN_FILE}{b} --truth {out / RUN_TRUTH} "
        f"--out track.json"
    )
    return 0
