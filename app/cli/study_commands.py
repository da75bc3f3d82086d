"""The printing runners of ``roadmap3d validate`` and ``roadmap3d bench``.

The studies live in :mod:`registration.studies` and return data; these functions turn the
command line's options into the studies' frozen configurations, print progress on stderr and
results on stdout (a table, or one JSON object with ``--json``).
"""

from __future__ import annotations

import json
import json as json_module
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from app.cli.configs import Bench
from app.cli.options import (
    BiplaneStudy,
    CalibrationStudy,
    ClinicalStudy,
    GeometryStudy,
    PhantomStudy,
    Table1,
    TrackingStudy,
    VolumeStudy,
)
from registration import __version__
from registration.sim.calibration import ERROR_REGION_RADIUS_MM, calibration_study
from registration.studies import bench, execution, runs
from registration.studies.cases import format_table, run_case, summarize, table1_cases
from registration.studies.runs import ClinicalConfig, PhantomConfig


def run_table1(args: Table1) -> int:
    """``roadmap3d validate table1``: 16 registrations, a table or one JSON object."""
    cases = table1_cases(args.seed)
    records = []
    started = time.perf_counter()
    for i, case in enumerate(cases, 1):
        if not args.json:
            print(
                f"[{i:2d}/{len(cases)}] {case.offset} {case.image_kind:<8} "
                f"{case.volume_format_cm:.0f}/{case.image_format_cm:.0f} cm ...",
                end="\r",
                file=sys.stderr,
                flush=True,
            )
        records.append(run_case(case))
    summary = summarize(records)
    summary["wall_seconds"] = time.perf_counter() - started
    summary["seed"] = args.seed
    summary["version"] = __version__
    summary["volume_label"] = records[0]["volume_label"] if records else ""
    if args.json:
        print(json.dumps({"records": records, "summary": summary}))
    else:
        print(" " * 60, end="\r", file=sys.stderr)
        print(f"Table I offsets on the simulated head phantom (volume: {summary['volume_label']})")
        print("Success: in-plane residual at the iso-center < 1 mm and rotation < 3 deg.\n")
        print(format_table(records))
        print(
            f"\n{summary['successes']}/{summary['runs']} successful; median {summary['seconds_median']:.2f} s, "
            f"{summary['drr_count_median']:.0f} DRRs per registration; seed {args.seed}, roadmap3d {__version__}"
        )
        print(
            f"Preparing the 3DRAs for rendering (once per volume, not per registration): "
            f"{summary['prepare_seconds_total']:.2f} s in all."
        )
    return 0


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _run_tasks(
    tasks: list, args: PhantomStudy | ClinicalStudy | BiplaneStudy | GeometryStudy
) -> tuple[list[dict], float]:
    """The study's tasks run (resumably) into ``args.out``, progress on stderr unless ``--json``."""
    log = None if args.json else _stderr
    return execution.run_study(tasks, args.out, n_jobs=_check_jobs(args.jobs), scheduler=args.scheduler, log=log)


def _check_jobs(jobs: int | None) -> int | None:
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    return jobs


def run_phantom_study(args: PhantomStudy) -> int:
    """``roadmap3d validate phantom``: Table II-III and Fig. 6, written to ``args.out``."""
    from registration.studies.phantom_report import phantom_summary, write_phantom_report

    config = PhantomConfig.quick_config(args.seed) if args.quick else PhantomConfig(seed=args.seed)
    if getattr(args, "volume_source", None):
        config = replace(config, volume_source=args.volume_source)
    tasks = runs.phantom_tasks(config)
    records, wall = _run_tasks(tasks, args)
    summary = phantom_summary(records, config=asdict(config), wall_seconds=wall)
    write_phantom_report(records, summary, Path(args.out))
    _print_summary(summary, args.json, Path(args.out))
    return 0


def run_clinical_study(args: ClinicalStudy) -> int:
    """``roadmap3d validate clinical``: the rotational-run study and Fig. 7, written to ``args.out``."""
    from registration.studies.clinical_report import clinical_summary, write_clinical_report

    config = ClinicalConfig.quick_config(args.seed) if args.quick else ClinicalConfig(seed=args.seed)
    if args.registrations is not None:
        if args.registrations < 1:
            raise ValueError(f"--registrations must be >= 1, got {args.registrations}")
        config = replace(config, registrations_per_patient=int(args.registrations))
    tasks = runs.clinical_tasks(config)
    records, wall = _run_tasks(tasks, args)
    summary = clinical_summary(records, config=asdict(config), wall_seconds=wall)
    write_clinical_report(records, summary, Path(args.out))
    _print_summary(summary, args.json, Path(args.out))
    return 0


def ct_folder(ct: Path | None) -> str | None:
    """``--ct``: the CT folder's absolute path (ValueError when it is no folder)."""
    if ct is None:
        return None
    if not Path(ct).is_dir():
        raise ValueError(f"--ct {ct}: not a folder of DICOM CT slices")
    return str(Path(ct).resolve())


def registrations_flag(value: int | None) -> int | None:
    """``--registrations``: None (the study's default) or a count >= 1 (ValueError otherwise)."""
    if value is not None and value < 1:
        raise ValueError(f"--registrations must be >= 1, got {value}")
    return value


def run_biplane_study(args: BiplaneStudy) -> int:
    """``roadmap3d validate biplane``: biplane beside single-plane, written to ``args.out``."""
    from registration.studies import biplane

    ct = ct_folder(args.ct)
    config = (
        biplane.BiplaneConfig.quick_config(args.seed, ct)
        if args.quick
        else biplane.BiplaneConfig(seed=args.seed, ct_path=ct)
    )
    if registrations_flag(args.registrations) is not None:
        config = replace(config, registrations_per_patient=args.registrations)
    tasks = biplane.biplane_tasks(config)
    records, wall = _run_tasks(tasks, args)
    summary = biplane.biplane_summary(records, config=asdict(config), wall_seconds=wall)
    biplane.write_biplane_report(records, summary, Path(args.out))
    if args.json:
        print(json.dumps(summary))
        return 0
    pct = lambda x: "-" if x is None else f"{100 * x:.1f} %"  # noqa: E731
    print(f"biplane: {summary['runs']} moments, success (3-D) {pct(summary['success_rate'])}; single plane A: "
          f"{pct(summary['single_plane_success_rate_3d'])} (3-D), {pct(summary['single_plane_success_rate_inplane'])} "
          "(in-plane)")  # fmt: skip
    for name, label in (("", "biplane"), ("single_plane_", "single plane")):
        print(
            f"  {label:<13} median total {summary[name + 'translation_residual_mm_median']:.3f} mm, out-of-plane "
            f"{summary[name + 'out_of_plane_residual_mm_median']:.3f} mm, rotation "
            f"{summary[name + 'rotation_residual_deg_median']:.3f} deg, {summary[name + 'seconds_median']:.2f} s"
        )
    print(f"\nwritten: {Path(args.out) / 'results.jsonl'}, {Path(args.out) / 'report.md'} and the histograms")
    return 0


def _print_summary(summary: dict, as_json: bool, out: Path) -> None:
    if as_json:
        print(json.dumps(summary))
        return
    from registration.studies.report import summary_lines

    print("\n".join(summary_lines(summary)))
    print(f"\nwritten: {out / 'results.jsonl'}, {out / 'report.md'}, {out / 'report.html'} and the plots")


def run_calibration_study(args: CalibrationStudy) -> int:
    """``roadmap3d validate calibration``: print a table, or one JSON object with ``--json``."""
    result = calibration_study(samples=args.samples, seed=args.seed)
    if args.json:
        out = {k: result[k] for k in ("errors_mm", "median_mm", "max_mm")}
        out.update({k: result[k] for k in ("uncorrected_median_mm", "region_radius_mm", "target_mm")})
        out["samples"] = args.samples
        out["seed"] = args.seed
        print(json.dumps(out))
        return 0
    print(
        f"Machine-based registration error: max displacement within {ERROR_REGION_RADIUS_MM:.0f} mm "
        "of the iso-center, at the iso-center plane (mm)"
    )
    print(f"{'primary':>9} {'secondary':>10} {'error mm':>9} {'uncorrected mm':>15}")
    for r in result["records"]:
        print(f"{r['primary_deg']:9.1f} {r['secondary_deg']:10.1f} {r['error_mm']:9.3f} {r['uncorrected_mm']:15.3f}")
    print(
        f"median {result['median_mm']:.3f} mm, max {result['max_mm']:.3f} mm "
        f"(target < 0.2 mm; without calibration median {result['uncorrected_median_mm']:.2f} mm)"
    )
    return 0


def run_bench(options: Bench) -> int:
    """``roadmap3d bench``: a table, or one JSON object with ``--json``."""
    json, quick, seed = options.json, options.quick, options.seed
    out = bench.collect(quick=quick, seed=seed, log=None if json else _stderr)
    if json:
        print(_json_dumps(out))
        return 0
    drr, gd_ms, reg = out["drr"], out["gradient_difference_ms_median"], out["registration"]
    print("DRR (median ms)        fast    reference   speed-up: median (least) of rounds")
    for row in drr:
        print(
            f"  {row['image_px']:>3}^2 from {row['volume_px']:>3}^3  {row['ms_median']:7.2f}  "
            f"{row['reference_ms_median']:10.1f}   {row['speedup']:6.0f}x ({row['speedup_min']:.0f}x) "
            f"over {row['rounds']} rounds"
        )
    print(f"gradient difference     {gd_ms:.3f} ms median")
    print(
        f"registration            {reg['seconds_median']:.2f} s median over T1-T4, "
        f"{100 * reg['success_rate']:.0f} % successful"
    )
    ratio = reg["checks_ratio"]
    print(
        f"  without the checks    {reg['checks_off_seconds_median']:.2f} s median, "
        f"{100 * reg['checks_off_success_rate']:.0f} % successful; with / without: {ratio['median']:.2f}x median "
        f"({ratio['min']:.2f}x min) of the same cases, interleaved"
    )
    for stage in reg["stages"]:
        print(f"  {stage['drrs_median']:6.0f} DRRs {stage['seconds_median']:6.2f} s  {stage['stage'][:80]}")
    bi = out["biplane"]
    print(
        f"biplane registration    {bi['seconds_median']:.2f} s median over {len(bi['runs'])} moments, "
        f"{100 * bi['success_rate']:.0f} % successful (3-D criterion)"
    )
    real = out.get("real_volume", {})
    if "skipped" in real:
        print(f"real CT                 skipped: {real['skipped']}")
    elif real:
        print(
            f"real CT                 {real['seconds_median']:.2f} s median a registration (volume prepared), "
            f"{real['prepare_seconds']:.2f} s preparing, {real['register_end_to_end_seconds']:.2f} s end to end, "
            f"{100 * real['success_rate']:.0f} % successful (images formed from the CT: a best case)"
        )
        conf = real.get("confidence")
        if conf:
            print(
                f"real CT, --confidence   +{conf['seconds_median']:.2f} s median a registration "
                f"({100 * conf['ratio_to_registration_median']:.0f} % of it, "
                f"{100 * conf['ratio_to_registration_min']:.0f} % at least), {conf['applied']} applied"
            )
        cli = real.get("command_line") or {}
        if "wall_seconds" in cli:
            warm = cli.get("warm", {}).get("wall_seconds")
            assessed = cli.get("warm_confidence", {}).get("wall_seconds")
            print(
                f"real CT, new process    roadmap3d register {cli['wall_seconds']:.2f} s (preparation not cached)"
                + ("" if warm is None else f", {warm:.2f} s (its view-independent part cached on disk)")
                + ("" if assessed is None else f", {assessed:.2f} s with --confidence")
            )
    if "reconstruction" in out:
        rec = out["reconstruction"]
        print(
            f"reconstruction          {rec['seconds']:.1f} s ({rec['projections']} projections -> {rec['volume_px']}^3)"
        )
    print(f"peak memory             {out['peak_rss_mb']:.0f} MB")
    return 0


def _json_dumps(obj: dict) -> str:
    return json_module.dumps(obj, default=float)


def run_tracking_study(args: TrackingStudy) -> int:
    """``roadmap3d validate tracking``: simulated runs tracked at their frame times; report in ``args.out``."""
    from registration.studies.tracking import TrackingConfig, write_tracking_report
    from registration.studies.tracking import run_tracking_study as study_run

    config = TrackingConfig.quick_config(args.seed) if args.quick else TrackingConfig.full_config(args.seed)
    config = replace(config, realtime=not args.every_frame)
    study = study_run(config, log=_stderr, out=Path(args.out))
    write_tracking_report(study, Path(args.out))
    s = study["summary"]
    if args.json:
        print(json.dumps(s))
        return 0

    def pct(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"

    def num(v: float | None, unit: str, digits: int = 2) -> str:
        return "-" if v is None else f"{v:.{digits}f} {unit}"

    print(f"tracking: {s['frames']} frames in {s['runs']} run(s): {s['processed']} processed, {s['skipped']} skipped")
    print(
        f"latency per frame: median {num(s['ms_per_frame_median'], 'ms', 1)}, p95 {num(s['ms_per_frame_p95'], 'ms', 1)}"
        f" (targets 66 / 150 ms); full capture median {num(s['capture_ms_median'], 'ms', 0)} (target 1000 ms)"
    )
    print(
        f"applied {s['applied']}, withheld {s['withheld']}, unchanged {s['unchanged']}; "
        f"tracking error of applied frames median {num(s['tracking_error_mm_median'], 'mm')} (target 0.5 mm), "
        f"worst {num(s['max_error_applied_mm'], 'mm')}"
    )
    print(
        f"applied precision {pct(s['applied_precision'])} (target 99 %), "
        f"recall {pct(s['applied_recall'])} (target 90 %)"
    )
    print(f"\nwritten: {Path(args.out) / 'results.json'}, {Path(args.out) / 'report.md'}, report.html and the plots")
    return 0


def _read_study_volume(args: VolumeStudy) -> Any:
    """The volume from its file or folder, or with --pacs retrieved (WADO-RS) into a private temporary folder."""
    from registration.io import dicom

    if not args.pacs:
        if args.study:
            raise ValueError("--study applies to --pacs only")
        return dicom.read_volume(args.volume)
    import shutil
    import tempfile

    from app.cli.net_commands import retrieve_volume
    from registration.io.pacs import Pacs, PacsSettings

    client = Pacs(PacsSettings.resolve(args.pacs, ca_bundle=args.ca_bundle))
    work = Path(tempfile.mkdtemp(prefix="roadmap3d-validate-volume-"))
    try:
        return dicom.read_volume(retrieve_volume(client, args.study, str(args.volume), work))
    finally:
        shutil.rmtree(work, ignore_errors=True)


#: Cases per arm of ``validate volume --quick``.
QUICK_VOLUME_CASES = 8


def run_volume_validation(args: VolumeStudy) -> int:
    """``roadmap3d validate volume``: random views and offsets on the user's volume, a table or
    one JSON object with ``--json``; ``--out`` keeps results.jsonl, summary.json and report.md."""
    import warnings

    from registration.io.isocenter import resolve_isocenter
    from registration.studies.volume import SUMMARY_KEYS, VolumeStudyConfig, run_volume_study
    from registration.studies.volume_report import report_markdown

    try:
        strengths = tuple(float(x) for x in str(args.strengths).split(",") if x.strip())
    except ValueError:
        raise ValueError(f"--strengths takes numbers separated by commas, got {args.strengths!r}") from None
    cases = QUICK_VOLUME_CASES if args.quick and args.cases == VolumeStudy.cases else args.cases
    config = VolumeStudyConfig(cases=cases, max_mm=args.max_mm, max_deg=args.max_deg, biplane=args.biplane,
                               seed=args.seed, realism=args.realism, strengths=strengths, roi=args.roi)  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        volume = _read_study_volume(args)
    for message in dict.fromkeys(str(w.message) for w in caught):
        _stderr(f"warning: {message}")
    iso, iso_from = resolve_isocenter(args.isocenter, volume)
    corners = volume.world_corners_mm()
    if np.any(np.asarray(iso) < corners.min(axis=0)) or np.any(np.asarray(iso) > corners.max(axis=0)):
        raise ValueError(
            f"the iso-center ({', '.join(f'{c:.1f}' for c in iso)}) mm ({iso_from}) lies outside the volume "
            f"{args.volume}; give --isocenter x,y,z inside the anatomy or --isocenter head (the middle of the head)"
        )
    _stderr(f"iso-center ({', '.join(f'{c:.1f}' for c in iso)}) mm: {iso_from}")
    _stderr("Best case: the X-ray images are formed from the same volume (not real X-rays).")
    if config.realism != "clean":
        _stderr(
            f"realism {config.realism} at strength(s) {', '.join(f'{x:g}' for x in strengths)}: clinical-looking "
            "images written as XA files and read back as register reads them; decisions as register --confidence"
        )
    log = _stderr
    records, summary = run_volume_study(volume, iso, config, out=args.out, log=log)
    if args.json:
        ordered = {k: summary[k] for k in SUMMARY_KEYS}
        ordered.update({k: v for k, v in summary.items() if k not in ordered})
        print(_json_dumps(ordered))
        return 0
    print(report_markdown(records, summary))
    if args.out is not None:
        print(f"written: {args.out / 'results.jsonl'}, {args.out / 'summary.json'}, {args.out / 'report.md'}")
    return 0


def run_geometry_study(args: GeometryStudy) -> int:
    """``roadmap3d validate geometry``: the files' geometry wrong, estimated or not, written to ``args.out``."""
    from registration.studies import biplane, geometry

    moments = biplane.BiplaneConfig.quick_config(args.seed) if args.quick else biplane.BiplaneConfig(seed=args.seed)
    moments = replace(moments, patients=moments.patients[:1])
    if registrations_flag(args.registrations) is not None:
        moments = replace(moments, registrations_per_patient=args.registrations)
    config = geometry.GeometryConfig(moments, sid_error=args.sid_error, shift_px=args.shift_px)
    records, wall = _run_tasks(geometry.geometry_tasks(config), args)
    summary = geometry.geometry_summary(records, config=asdict(config), wall_seconds=wall)
    geometry.write_geometry_report(records, summary, Path(args.out))
    if args.json:
        print(json.dumps(summary))
        return 0
    pct = lambda x: "-" if x is None else f"{100 * x:.0f} %"  # noqa: E731
    for name, label in (("images_geometry", "the images' own geometry"), ("files_geometry", "the files' geometry"),
                        ("estimated", "the files', distances estimated")):  # fmt: skip
        s = summary[name]
        line = f"{label:<32} success {pct(s['success_rate'])}, median {s['translation_residual_mm_median']:.2f} mm"
        if name == "estimated":
            line += (f"; distances off by {s['sid_error_percent_median']:.2f} % (median), at most "
                     f"{s['sid_error_percent_max']:.2f} %")  # fmt: skip
        print(line)
    print(f"\nwritten: {Path(args.out) / 'results.jsonl'} and {Path(args.out) / 'report.md'}")
    return 0
