"""``roadmap3d validate geometry``: registration on files whose C-arm geometry is wrong, with and
without estimating it (:func:`registration.core.intrinsics.estimate_geometry`).

Each moment of the biplane study (the phantom, both planes, clinical offsets) is imaged with the
planes' own geometry: the analytic phantom's line integrals, with exactly the geometry a
calibrated system would put in its files. The files then say otherwise: each plane's
source-image distance ``sid_error`` short (the true one is ``1 + sid_error`` times the file's)
and, with ``shift_px``, its principal point moved by that many pixels in a random direction. Each
moment is registered three ways: with the images' own geometry (the best case), with the files'
geometry (what a user gets), and with the files' geometry and the source-image distances
estimated with the pose. The record keeps each one's residuals and success (3-D criterion,
CONVENTIONS §6) and how far the estimated distances lie from the images'.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from registration.core.register import RegistrationOptions
from registration.studies.biplane import BiplaneCase, BiplaneConfig, biplane_tasks

#: The errors a study draws when none are given: the files' distances 5 % short, no shift.
DEFAULT_SID_ERROR = 0.05


@dataclass(frozen=True)
class GeometryConfig:
    """What the geometry study registers: the biplane study's moments (``biplane``) with the
    files' geometry off by ``sid_error`` and ``shift_px``."""

    biplane: BiplaneConfig
    sid_error: float = DEFAULT_SID_ERROR
    shift_px: float = 0.0

    def __post_init__(self) -> None:
        if not -0.09 <= self.sid_error <= 0.09:
            raise ValueError(
                f"--sid-error must lie in [-0.09, 0.09] (the estimate's reach is 10 %), got {self.sid_error}"
            )
        if not 0.0 <= self.shift_px <= 20.0:
            raise ValueError(f"--shift-px must lie in [0, 20] pixels, got {self.shift_px}")


@dataclass(frozen=True)
class GeometryCase:
    """One moment of the biplane study with the files' geometry off (see the module)."""

    moment: BiplaneCase
    sid_error: float
    shift_px: float

    def prepare_key(self) -> tuple:
        return self.moment.prepare_key()

    def prepare(self) -> None:
        self.moment.prepare()

    def run(self, *, options: RegistrationOptions | None = None) -> dict:
        return run_geometry_case(self, options=options)


def geometry_tasks(config: GeometryConfig) -> list[Any]:
    """The biplane study's tasks, each with the files' geometry off by the config's errors."""
    tasks = []
    for task in biplane_tasks(config.biplane):
        tag = f"sid{config.sid_error:+g}-shift{config.shift_px:g}"
        case = GeometryCase(task.case, config.sid_error, config.shift_px)
        tasks.append(replace(task, case_id=f"geometry/{tag}/{task.case_id}", case=case))
    return tasks


def _files_views(case: GeometryCase, views: list) -> tuple[list, list[list[float]]]:
    """The views as their files describe them: each plane's distance short by the error, its
    principal point shifted in a direction drawn from the moment's seed."""
    from registration.core.intrinsics import with_intrinsics

    rng = np.random.default_rng([case.moment.seed, 0x6E0])
    out, shifts = [], []
    for view in views:
        direction = rng.normal(size=2)
        shift = case.shift_px * direction / np.linalg.norm(direction)
        out.append(replace(view, geometry=with_intrinsics(view.geometry, 1.0 / (1.0 + case.sid_error), shift)))
        shifts.append([float(s) for s in shift])
    return out, shifts


def _exact_views(case: BiplaneCase, motion: np.ndarray) -> list:
    """Both planes imaged with exactly the geometry their views carry (the machine-based one a
    calibrated system puts in its files: no bending left over), plane A then plane B."""
    from registration.sim.biplane import BiplaneSystem
    from registration.sim.xray import simulate_xray
    from registration.studies.cases import _phantom

    anatomy = _phantom(case.phantom_seed, False, True)
    system = BiplaneSystem()
    views = []
    for k, (plane, (primary, secondary), pixels) in enumerate(
        zip(system.planes(), case.angles_deg, case.pixels, strict=True)
    ):
        geometry = system.calibrated_geometry(plane, plane.nominal(primary, secondary, pixels=pixels))
        image = simulate_xray(anatomy, geometry, motion=motion, kind=case.kind, seed=case.seed + k)
        views.append(replace(image, meta={**image.meta, "plane": plane.name}))
    return views


def _scores(prefix: str, residual: Any) -> dict:
    return {
        f"{prefix}success": bool(residual.success_total),
        f"{prefix}translation_residual_mm": float(residual.translation_mm),
        f"{prefix}rotation_residual_deg": float(residual.rotation_deg),
    }


def run_geometry_case(case: GeometryCase, *, options: RegistrationOptions | None = None) -> dict:
    """Register the moment with the images' geometry, the files', and the files' with the
    distances estimated (see the module)."""
    from registration.core.intrinsics import refine_geometry, refine_on_own_grid
    from registration.core.metrics import residuals
    from registration.core.preparation import Preparation
    from registration.core.register import register
    from registration.studies.biplane import _offset_motion, study_volume

    moment = case.moment
    volume = study_volume(None, moment.phantom_seed, moment.volume_format_cm, moment.volume_voxels)
    truth = _offset_motion(moment)
    exact = _exact_views(moment, truth)
    files, shifts = _files_views(case, exact)
    options = options or RegistrationOptions()
    record: dict[str, Any] = {
        "sid_error": case.sid_error,
        "shift_px": case.shift_px,
        "principal_point_shifts_px": shifts,
        "plane_a_deg": list(moment.angles_deg[0]),
        "plane_b_deg": list(moment.angles_deg[1]),
        "offset_translation_mm": float(np.linalg.norm(moment.translation_mm)),
        "offset_rotation_deg": moment.rotation_deg,
        "seed": moment.seed,
    }
    pair = Preparation.of(volume, tuple(exact), options=options)
    best = register(volume, list(exact), truth=truth, seed=moment.seed, options=options, renderer=pair.renderer)
    record.update(_scores("images_geometry_", best.residual))
    pair = Preparation.of(volume, tuple(files), options=options)
    plain = register(volume, list(files), truth=truth, seed=moment.seed, options=options, renderer=pair.renderer)
    record.update(_scores("files_geometry_", plain.residual))
    frame = files[0].geometry
    coarse = refine_geometry(pair.renderer, files, plain.patient_motion, estimate=("sid",))
    record.update(_scores("first_pass_", residuals(coarse.patient_motion, truth, frame, None, optimizes_tz=True)))
    found = refine_on_own_grid(volume, files, coarse, estimate=("sid",))  # the estimate's second pass
    record.update(_scores("", residuals(found.patient_motion, truth, frame, None, optimizes_tz=True)))
    for prefix, estimate in (("first_pass_", coarse), ("", found)):
        record[f"{prefix}sid_error_percent"] = [
            100.0 * (v.sid_mm / image.geometry.sid_mm - 1.0)
            for v, image in zip(estimate.intrinsics, exact, strict=True)
        ]
    record["estimate_seconds"] = found.seconds
    record["estimate_evaluations"] = found.evaluations
    record["files_sid_error_percent"] = 100.0 * (1.0 / (1.0 + case.sid_error) - 1.0)
    return record


def _rate(records: list[dict], key: str) -> float | None:
    return sum(bool(r[key]) for r in records) / len(records) if records else None


def _abs_errors(records: list[dict], key: str) -> list[float]:
    return [abs(e) for r in records for e in r[key]]


def geometry_summary(records: list[dict], *, config: dict, wall_seconds: float) -> dict:
    """The study's numbers (the ``--json`` object): success with each geometry, and the estimated
    distances' error (per plane, |%|, median and largest)."""
    out: dict[str, Any] = {"study": "geometry", "runs": len(records)}
    for name, prefix in (("images_geometry", "images_geometry_"), ("files_geometry", "files_geometry_"),
                         ("first_pass", "first_pass_"), ("estimated", "")):  # fmt: skip
        values = [r[f"{prefix}translation_residual_mm"] for r in records]
        out[name] = {
            "success_rate": _rate(records, f"{prefix}success"),
            "translation_residual_mm_median": float(np.median(values)) if values else None,
        }
    for name, key in (("first_pass", "first_pass_sid_error_percent"), ("estimated", "sid_error_percent")):
        errors = _abs_errors(records, key)
        out[name]["sid_error_percent_median"] = float(np.median(errors)) if errors else None
        out[name]["sid_error_percent_max"] = float(np.max(errors)) if errors else None
        out[name]["planes_within_0_5_percent"] = sum(e <= 0.5 for e in errors)
        out[name]["planes"] = len(errors)
    seconds = [r["estimate_seconds"] for r in records]
    out["estimate_seconds_median"] = float(np.median(seconds)) if seconds else None
    out["criterion"] = "translation at the iso-center < 1 mm (3-D) and rotation < 3 deg (CONVENTIONS §6)"
    out["images"] = "the phantom's analytic line integrals with each plane's exact geometry"
    out["wall_seconds"] = wall_seconds
    out["config"] = config
    return out


def _percent(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def write_geometry_report(records: list[dict], summary: dict, out: Path) -> Path:
    """``report.md`` in ``out``: the table of the three geometries and the distances' error."""
    c = summary["config"]
    lines = [
        "# Registration on files with the wrong C-arm geometry",
        "",
        f"The biplane study's moments ({summary['runs']}, seed {c['biplane']['seed']}); the files' source-image "
        f"distances {100 * c['sid_error']:g} % short of the images'"
        + (f", principal points moved by {c['shift_px']:g} px" if c["shift_px"] else "")
        + f". Images: {summary['images']}. Success: {summary['criterion']}.",
        "",
        "| geometry | success | median translation residual | source-image distance error, median / largest |",
        "| --- | ---: | ---: | --- |",
    ]
    for name, label in (("images_geometry", "the images' own"), ("files_geometry", "the files'"),
                        ("first_pass", "the files', distances estimated (first pass, 128 px)"),
                        ("estimated", "the files', distances estimated (both passes)")):  # fmt: skip
        s = summary[name]
        err = "-"
        if s.get("sid_error_percent_median") is not None:
            err = (f"{s['sid_error_percent_median']:.2f} % / {s['sid_error_percent_max']:.2f} % "
                   f"({s['planes_within_0_5_percent']} of {s['planes']} planes within 0.5 %)")  # fmt: skip
        lines.append(
            f"| {label} | {_percent(s['success_rate'])} | {s['translation_residual_mm_median']:.2f} mm | {err} |"
        )
    lines += ["", f"The estimate took {summary['estimate_seconds_median']:.1f} s per moment (median).", ""]
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.md"
    path.write_text("\n".join(lines))
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return path
