"""The printing runner of ``roadmap3d validate capture`` (the study is
:mod:`registration.studies.capture`)."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, replace
from pathlib import Path

from app.cli.options import CaptureStudy
from app.cli.study_commands import ct_folder, registrations_flag
from registration.studies import capture, execution


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def capture_config(args: CaptureStudy) -> capture.CaptureConfig:
    """The study's frozen configuration from the command line's options (ValueError on bad ones)."""
    ct = ct_folder(args.ct)
    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {args.jobs}")
    config = (
        capture.CaptureConfig.quick_config(args.seed, ct)
        if args.quick
        else capture.CaptureConfig(seed=args.seed, ct_path=ct)
    )
    if registrations_flag(args.registrations) is not None:
        config = replace(config, registrations_per_level=args.registrations)
    if not args.sweep:
        raise ValueError("--sweep needs at least one of translation, rotation, combined")
    if args.from_landmarks is not None and not 4 <= args.from_landmarks <= 8:
        raise ValueError(f"--from-landmarks takes 4 to 8 landmarks per plane, got {args.from_landmarks}")
    if not args.landmark_error_mm >= 0:
        raise ValueError(f"--landmark-error-mm must be >= 0, got {args.landmark_error_mm}")
    return replace(config, sweeps=tuple(dict.fromkeys(args.sweep)), landmark_pairs=args.from_landmarks,
                   landmark_noise_mm=float(args.landmark_error_mm), aimed=bool(args.aimed))  # fmt: skip


def _pooled(args: CaptureStudy) -> tuple[list[dict], dict]:
    """``--pool``: the earlier runs' moments and the summary's configuration (ValueError on bad ones)."""
    out = Path(args.out).resolve()
    for given in args.pool:
        folder = Path(given) if Path(given).is_dir() else Path(given).parent
        if folder.resolve() == out:
            raise ValueError(f"--out {args.out} is a pooled run's own folder: name another one for the pooled report")
    records = capture.pooled_records(args.pool)
    return records, capture.pooled_config(records, args.pool)


def run_capture_study(args: CaptureStudy) -> int:
    """``roadmap3d validate capture``: the capture range, written to ``args.out``; with ``--pool``
    the summary of earlier runs' moments together."""
    if args.pool:
        records, config = _pooled(args)
        Path(args.out).mkdir(parents=True, exist_ok=True)
        summary = capture.capture_summary(records, config=config, wall_seconds=0.0)
    else:
        run = capture_config(args)
        tasks = capture.capture_tasks(run)
        log = None if args.json else _stderr
        records, wall = execution.run_study(tasks, args.out, n_jobs=args.jobs, scheduler=args.scheduler, log=log)
        summary = capture.capture_summary(records, config=asdict(run), wall_seconds=wall)
    capture.write_capture_report(records, summary, Path(args.out))
    if args.json:
        print(json.dumps(summary))
        return 0
    for plane, name in (("biplane", "biplane"), ("single_plane", "single plane A")):
        s = summary[plane]
        ran = set(s["sweeps"])
        translation = capture.radius_words(s["capture_radius_mm_95"], "mm", "translation" in ran)
        rotation = capture.radius_words(s["capture_radius_deg_95"], "deg", "rotation" in ran)
        precision = "-" if s["applied_precision"] is None else f"{100 * s['applied_precision']:.1f} %"
        print(
            f"{name:<15} capture radius (95 %): translation {translation}, rotation {rotation}; applied "
            f"precision {precision} ({s['applied']} applied of {s['runs']})"
        )
    written = "" if args.pool else f"{Path(args.out) / 'results.jsonl'}, "
    print(f"\nwritten: {written}{Path(args.out) / 'report.md'} and capture_curves.png")
    return 0
