"""``roadmap3d validate rotational-run`` and the phantom's rotational-run export.

The work is in :mod:`registration.studies.rotational`; this module finds the data (files, or a
study on a PACS), prints progress on stderr and the summary on stdout (``--json``: one object).
"""

from __future__ import annotations

import json
import shutil
import sys
import time
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.cli.options import RotationalRunStudy
from registration.io import dicom

if TYPE_CHECKING:
    from registration.core.volume import Volume

#: Files ``roadmap3d phantom`` adds when its 3DRA is an FDK reconstruction.
PHANTOM_RUN = "rotational_run.dcm"
PHANTOM_RUN_CALIBRATION = "rotational_run_calibration.json"
#: Frame rate written for the phantom's rotational run (a propeller run of 120 frames in ~4 s).
RUN_FRAMES_PER_S = 30.0


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------
# The phantom's run
# --------------------------------------------------------------------------------------
def export_phantom_run(
    folder: Path, volume: Volume, *, seed: int, contrast: bool, volume_format: float, study_uid: str, uid_seed: str
) -> dict[str, Any]:
    """Write the rotational run the FDK 3DRA ``volume`` was reconstructed from (one multi-frame
    XA, per-frame angles, CONVENTIONS §7) and its calibration (the deviations the dodecahedron
    calibration measured per frame, as a calibration table over the run's angles). Returns what
    the truth JSON says about them."""
    from registration.core.images import XRayImage
    from registration.sim.calibration import CalibrationTable, deviation_vector
    from registration.sim.reconstruct import rotational_run_3dra

    m = volume.meta
    run = rotational_run_3dra(
        seed,
        volume_format_cm=volume_format,
        contrast=contrast,
        pixels=int(m["pixels"]),
        projections=int(m["projections"]),
        arc_deg=float(m["arc_deg"]),
        kind=str(m.get("kind", "exposure")),
        seed=int(m.get("seed", 0)),
    )
    frames = [
        XRayImage(run.images[i], run.masks[i], g, run.kind, {"frame": i}) for i, g in enumerate(run.nominal_geometries)
    ]
    times = np.arange(len(frames)) / RUN_FRAMES_PER_S
    dicom.write_xray_run(
        frames,
        folder / PHANTOM_RUN,
        times_s=times,
        study_uid=study_uid,
        uid_seed=uid_seed + " rotational run",
        description=f"rotational run of the 3DRA, {len(frames)} frames",
    )
    deviations = np.stack([deviation_vector(g) for g in run.calibrated_geometries])
    # A propeller run has one secondary angle (0): the table repeats its row at +-1 degree.
    table = CalibrationTable(
        np.asarray(run.primary_deg, dtype=np.float64),
        np.array([-1.0, 1.0]),
        np.repeat(deviations[:, None, :], 2, axis=1),
        meta={"what": "dodecahedron calibration of the phantom's rotational-run protocol", "frames": len(frames)},
    )
    dicom.write_text_atomic(folder / PHANTOM_RUN_CALIBRATION, dicom.json_dumps(table.to_dict()))
    return {
        "rotational_run_file": PHANTOM_RUN,
        "rotational_run_calibration": PHANTOM_RUN_CALIBRATION,
        "rotational_run_images": "the 3DRA's own run: exposure images formed with the true (bent) geometry; "
        "the file holds the nominal angles, the calibration file the calibrated deviations",
    }


# --------------------------------------------------------------------------------------
# validate rotational-run
# --------------------------------------------------------------------------------------
def _from_pacs(args: RotationalRunStudy, work: Path) -> tuple[Path, Path, str]:
    """Retrieve the study's 3DRA and run into ``work``; (volume folder, run file, run label)."""
    from registration.io.pacs import Pacs, PacsSettings

    if not args.study:
        raise ValueError("--pacs needs --study UID (the study that holds the 3DRA and its rotational run)")
    pacs = Pacs(PacsSettings.resolve(args.pacs, ca_bundle=args.ca_bundle))
    series = pacs.series(args.study)
    if not series:
        raise ValueError(f"PACS {pacs.name}: study {args.study} not found or empty")
    by_uid = {s.series_uid: s for s in series}
    for given, what in ((args.volume, "--volume"), (args.run, "--run")):
        if given and given not in by_uid:
            raise ValueError(f"PACS {pacs.name}: study {args.study} has no series {given} ({what})")
    volume = by_uid[args.volume] if args.volume else next((s for s in series if s.role == "volume"), None)
    if volume is None:
        raise ValueError(f"PACS {pacs.name}: study {args.study} holds no CT/3DRA series; give --volume SERIES_UID")
    if args.run:
        run = by_uid[args.run]
    else:
        frames = {s.series_uid: pacs.frames(args.study, s.series_uid) for s in series if s.role == "xray"}
        runs = [s for s in series if frames.get(s.series_uid, 0) > 1]
        if not runs:
            raise ValueError(f"PACS {pacs.name}: study {args.study} holds no multi-frame XA/RF run; give --run")
        run = max(runs, key=lambda s: frames[s.series_uid])
    _stderr(f"retrieving {volume.label()} and {run.label()} from {pacs.name}")
    vfolder = pacs.retrieve_series(args.study, volume.series_uid, work / "volume")
    rfolder = pacs.retrieve_series(args.study, run.series_uid, work / "run")
    run_files = sorted(rfolder.iterdir())
    if len(run_files) != 1:
        raise ValueError(
            f"PACS {pacs.name}: series {run.series_uid} holds {len(run_files)} instances; expected one run"
        )
    return vfolder, run_files[0], f"{run.label()} (series {run.series_uid} on {pacs.name})"


def _calibration(args: RotationalRunStudy) -> tuple[Path | None, Any]:
    """The C-arm calibration table to refine each frame's geometry with: ``--calibration``, or the
    one an export put beside its run; (None, None) with a warning when there is none."""
    from registration.sim.calibration import CalibrationTable

    table = None
    calibration = args.calibration
    if calibration is None and args.run and not args.pacs:
        beside = Path(args.run).parent / PHANTOM_RUN_CALIBRATION
        if beside.is_file():  # the calibration an export put beside its run
            calibration = beside
            _stderr(f"calibration: {beside} (found beside the run; --calibration names another)")
    if calibration is not None:
        try:
            table = CalibrationTable.from_dict(json.loads(Path(calibration).read_text()))
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{calibration}: not a calibration table JSON ({exc})") from None
    else:
        _stderr(
            "warning: no C-arm calibration (--calibration): the frames are registered on the run's nominal "
            "geometry (its positioner tags); a bent, uncalibrated C-arm makes many of them fail"
        )
    return calibration, table


def _summary(args: RotationalRunStudy, records: list[dict], calibration: Path | None, calibrated: bool, frames: int,
             run_label: str, wall: float) -> dict:  # fmt: skip
    """The study's summary, as ``validate clinical`` summarises, with the run and its geometry."""
    from registration.studies.clinical_report import clinical_summary

    config = {**asdict(args), "calibration": calibration, "frames": frames, "calibrated": calibrated,
              "seed": args.seed}  # fmt: skip
    config = {k: (str(v) if isinstance(v, Path) else v) for k, v in config.items()}
    for record in records:
        record["contrast"] = args.contrast
    summary = clinical_summary(records, config=config, wall_seconds=wall)
    if args.contrast is None:  # neither group: the report's contrast rows stay empty
        empty = clinical_summary([], config={}, wall_seconds=0.0)
        summary["contrast"], summary["no_contrast"] = empty["contrast"], empty["no_contrast"]
    summary.update({"study": "rotational-run", "run": run_label, "frames": frames, "calibrated": calibrated,
                    "geometry": "calibrated" if calibrated else "nominal"})  # fmt: skip
    return summary


def _write_and_say(args: RotationalRunStudy, records: list[dict], summary: dict, frames: int, calibrated: bool,
                   run_label: str, volume_label: str) -> None:  # fmt: skip
    """results.jsonl and the report in ``--out``; the summary on stdout (``--json``: as one object)."""
    from registration.studies.clinical_report import write_clinical_report
    from registration.studies.report import summary_lines
    from registration.studies.rotational import REPORT_TITLE, method_lines

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "results.jsonl", "w") as fh:
        for r in records:
            fh.write(json.dumps(r) + "\n")
    method = method_lines(frames=frames, calibrated=calibrated, run_label=run_label, volume_label=volume_label)
    write_clinical_report(records, summary, out, title=REPORT_TITLE, method=method)
    if args.json:
        print(json.dumps(summary))
    else:
        lines = summary_lines(summary)
        print("\n".join([lines[0], lines[1], lines[-1]]))
        print(f"success (both criteria): {100.0 * (summary['success_rate'] or 0.0):.1f} %"
              + ("" if calibrated else " (nominal geometry: no C-arm calibration)"))  # fmt: skip
        print(f"\nwritten: {out / 'results.jsonl'}, {out / 'report.md'}, {out / 'report.html'} and the plots")


def run_rotational_validation(args: RotationalRunStudy) -> int:
    """Register random frames of a rotational run to its own 3DRA; report as ``validate clinical``."""
    from registration.studies.rotational import rotational_tasks, validate_rotational_run

    if args.cases < 1:
        raise ValueError(f"--cases must be >= 1, got {args.cases}")
    calibration, table = _calibration(args)
    work = None
    try:
        if args.pacs:
            import tempfile

            work = Path(tempfile.mkdtemp(prefix="roadmap3d-rotational-"))
            volume_path, run_path, run_label = _from_pacs(args, work)
        else:
            if args.study:
                raise ValueError("--study applies to --pacs only")
            if not args.volume or not args.run:
                raise ValueError("give --volume (3DRA) and --run (its rotational run), or --pacs URL --study UID")
            volume_path, run_path, run_label = Path(args.volume), Path(args.run), str(args.run)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            volume = dicom.read_volume(volume_path)
            run = dicom.read_xray_run(run_path, sid_mm=args.sid_mm, sod_mm=args.sod_mm)
        if len(run) < 2:
            raise ValueError(f"{run_path}: a rotational run has many frames; this file holds {len(run)}")
        geometry_of = table.geometry if table is not None else None
        if table is not None:
            for n, g in enumerate(run.geometries):  # every frame must lie in the calibrated range
                try:
                    table.geometry(g)
                except ValueError as exc:
                    raise ValueError(f"{calibration}: frame {n}: {exc}") from None
        cases = rotational_tasks(len(run), args.cases, seed=args.seed)
        start = time.perf_counter()
        progress = None if args.json else _stderr

        def done(record: dict) -> None:
            if progress is not None:
                verdict = "ok" if record["success"] else "FAILED"
                progress(
                    f"  {record['case_id']}: {record['inplane_residual_mm']:.2f} mm in-plane, "
                    f"{record['rotation_residual_deg']:.2f} deg -> {verdict}"
                )

        if progress is not None:
            progress(f"registering {len(cases)} random frames of {run_label} to {volume.label}")
        records = validate_rotational_run(volume, run, cases, geometry_of=geometry_of, run_label=run_label, done=done)
        wall = time.perf_counter() - start
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    calibrated = table is not None
    summary = _summary(args, records, calibration, calibrated, len(run), run_label, wall)
    _write_and_say(args, records, summary, len(run), calibrated, run_label, volume.label)
    return 0
