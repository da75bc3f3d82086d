"""``roadmap3d validate volume``: how well registration holds on the user's own CT or 3DRA.

Views at random C-arm angles look at the volume moved by random offsets in the paper's
clinical range (translation length uniform in [0, ``max_mm``] in a random 3-D direction,
rotation uniform in [0, ``max_deg``] about a random axis through the iso-center); each view's
X-ray image is formed from the volume by the engine's image formation
(:mod:`registration.sim.volume_xray`: trilinear line integrals at half the finest voxel,
Beer-Lambert, Poisson noise, blur, collimation, a catheter the volume lacks), never by the DRR
renderer that scores it; the volume is registered back from the machine-based pose (the
identity) and scored against the offset (CONVENTIONS §4; biplane §6).

Honesty: the images come from the same volume that is registered, so the numbers are a best
case for that anatomy (``IMAGES_FROM_VOLUME``); a real X-ray of the patient differs from any
CT of them.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from registration import __version__
from registration.core.blas import with_one_blas_thread
from registration.core.geometry import CArm, rigid
from registration.core.images import XRayImage
from registration.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION_MM
from registration.core.preparation import Preparation
from registration.core.register import RegistrationOptions, register
from registration.core.roi import RegionOfInterest
from registration.core.volume import Volume
from registration.io.isocenter import head_isocenter_mm as head_isocenter_mm  # where the studies aim
from registration.sim.volume_xray import IMAGES_FROM_VOLUME, VolumeAttenuator, catheter_devices, default_catheter_path
from registration.sim.xray import simulate_xray
from registration.studies.runs import axis_angle_matrix, random_unit_vector
from registration.studies.volume_report import write_outputs

#: Summary keys of ``--json`` (the study's JSON contract), in order.
SUMMARY_KEYS = (
    "runs",
    "success_rate",
    "inplane_residual_mm_median",
    "rotation_residual_deg_median",
    "seconds_median",
    "prepare_seconds",
)
#: Plane B of a biplane system is lateral to plane A.
PLANE_B_OFFSET_DEG = 90.0


@dataclass(frozen=True)
class VolumeStudyConfig:
    """The draws and images of the study (every case depends only on ``seed`` and its number)."""

    cases: int = 20
    max_mm: float = 25.0
    max_deg: float = 10.0
    image_format_cm: float = 27.0
    pixels: int = 384
    kind: str = "fluoro"
    #: C-arm angles drawn uniformly in +-these (LAO/RAO, CRAN/CAUD) for plane A.
    max_primary_deg: float = 45.0
    max_secondary_deg: float = 25.0
    catheter: bool = True
    biplane: bool = False
    seed: int = 0
    #: The arms of the study (``--realism``): ``clean`` (the images above), ``clinical`` (every
    #: effect of :mod:`registration.sim.clinical`), ``each``, or effect names joined by ``+``,
    #: comma-separated; each arm registers the same cases.
    realism: str = "clean"
    #: Strengths of the effects (``at_strength``: 0 none, 1 typical, 2 severe); each arm runs at each.
    strengths: tuple[float, ...] = (1.0,)
    #: Assess each estimate's confidence (applied / withheld) as ``register --confidence`` does;
    #: always on (for every arm) when an arm has clinical effects.
    confidence: bool = False
    #: The part of the patient the registration follows (``register --roi``): "cranium" (the
    #: pixels that see mostly the neck below the skull base left out) or "none".
    roi: str = "cranium"

    def __post_init__(self) -> None:
        from registration.core.roi import REGIONS
        from registration.sim.clinical import parse_realism

        if self.roi not in REGIONS:
            raise ValueError(f"--roi must be one of {', '.join(REGIONS)}, got {self.roi!r}")

        parse_realism(self.realism)  # a bad word is refused here, by name
        if not self.strengths or any(not (math.isfinite(s) and 0 <= s <= 3) for s in self.strengths):
            raise ValueError(f"strengths must lie in [0, 3], got {self.strengths}")
        if int(self.cases) != self.cases or self.cases < 1:
            raise ValueError(f"--cases must be a positive integer, got {self.cases}")
        if not (math.isfinite(self.max_mm) and 0 <= self.max_mm <= 100):
            raise ValueError(f"--max-mm must lie in [0, 100] mm, got {self.max_mm}")
        if not (math.isfinite(self.max_deg) and 0 <= self.max_deg <= 45):
            raise ValueError(f"--max-deg must lie in [0, 45] degrees, got {self.max_deg}")
        if not (math.isfinite(self.image_format_cm) and 5 <= self.image_format_cm <= 60):
            raise ValueError(f"image format must lie in [5, 60] cm, got {self.image_format_cm}")
        if int(self.pixels) != self.pixels or not 32 <= self.pixels <= 2048:
            raise ValueError(f"pixels must be an integer in [32, 2048], got {self.pixels}")
        if self.kind not in ("fluoro", "exposure"):
            raise ValueError(f"kind must be 'fluoro' or 'exposure', got {self.kind!r}")


@dataclass(frozen=True)
class VolumeCase:
    """One registration: plane A's angles and the offset (world mm, rotation about the iso-center)."""

    number: int
    primary_deg: float
    secondary_deg: float
    translation_mm: tuple[float, float, float]
    rotation_axis: tuple[float, float, float]
    rotation_deg: float
    seed: int


def volume_cases(config: VolumeStudyConfig) -> list[VolumeCase]:
    out = []
    for number in range(config.cases):
        rng = np.random.default_rng([config.seed, 11, number])
        primary = float(rng.uniform(-config.max_primary_deg, config.max_primary_deg))
        secondary = float(rng.uniform(-config.max_secondary_deg, config.max_secondary_deg))
        t = rng.uniform(0.0, config.max_mm) * random_unit_vector(rng)
        axis = random_unit_vector(rng)
        angle = float(rng.uniform(0.0, config.max_deg))
        out.append(
            VolumeCase(
                number=number,
                primary_deg=primary,
                secondary_deg=secondary,
                translation_mm=(float(t[0]), float(t[1]), float(t[2])),
                rotation_axis=(float(axis[0]), float(axis[1]), float(axis[2])),
                rotation_deg=angle,
                seed=int(rng.integers(2**31)),
            )
        )
    return out


def case_motion(case: VolumeCase, isocenter_mm: tuple[float, float, float]) -> np.ndarray:
    """The true patient motion: rotation about the iso-center, then the translation."""
    c = np.asarray(isocenter_mm, dtype=np.float64)
    about_iso = rigid(None, c) @ axis_angle_matrix(case.rotation_axis, case.rotation_deg) @ rigid(None, -c)
    return rigid(None, np.asarray(case.translation_mm)) @ about_iso


class VolumeImager:
    """Forms the study's X-ray images of one volume (its attenuator and catheter built once)."""

    def __init__(self, volume: Volume, isocenter_mm: tuple[float, float, float], *, catheter: bool = True) -> None:
        self.attenuator = VolumeAttenuator(_tissue_box(volume))
        self.devices = catheter_devices(default_catheter_path(isocenter_mm)) if catheter else None

    def image(self, geometry: CArm, motion: np.ndarray, *, kind: str, seed: int) -> XRayImage:
        return simulate_xray(
            self.attenuator, geometry, motion=motion, kind=kind, seed=seed,
            catheter=self.devices is not None, devices=self.devices,
        )  # fmt: skip


def _tissue_box(volume: Volume, tissue_hu: float = -900.0, margin_voxels: int = 3) -> Volume:
    """The volume cut to the box of its non-air voxels (plus a margin): the air around the
    patient attenuates nothing worth its rays' time."""
    inside = volume.data > tissue_hu
    spans = [np.flatnonzero(inside.any(axis=tuple(a for a in range(3) if a != axis))) for axis in range(3)]
    if any(s.size == 0 for s in spans):
        return volume
    lo = [max(int(s[0]) - margin_voxels, 0) for s in spans]
    hi = [min(int(s[-1]) + margin_voxels, n - 1) for s, n in zip(spans, volume.shape, strict=True)]
    data = volume.data[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1]
    affine = volume.index_to_world.copy()
    affine[:3, 3] = volume.index_to_world[:3, :3] @ np.array([lo[2], lo[1], lo[0]]) + volume.index_to_world[:3, 3]
    return Volume(np.ascontiguousarray(data), affine, label=volume.label)


def _views(config: VolumeStudyConfig, case: VolumeCase, isocenter_mm: tuple[float, float, float]) -> list[CArm]:
    plane_a = CArm.for_format(config.image_format_cm, pixels=config.pixels, primary_deg=case.primary_deg,
                              secondary_deg=case.secondary_deg)  # fmt: skip
    views = [replace(plane_a, isocenter_mm=tuple(isocenter_mm))]
    if config.biplane:
        views.append(replace(views[0], primary_deg=case.primary_deg + PLANE_B_OFFSET_DEG, secondary_deg=0.0))
    return views


def study_arms(config: VolumeStudyConfig) -> list[tuple[str, tuple[str, ...], float]]:
    """(arm name, effect names, strength) of each arm: clean runs once, the others at each strength."""
    from registration.sim.clinical import parse_realism

    out = []
    for name, effects in parse_realism(config.realism):
        for strength in [1.0] if not effects else list(config.strengths):
            out.append((name, effects, float(strength)))
    return out


class ClinicalViews:
    """An arm's clinical-looking images, written as the XA files a system sends and read back by
    the project's reader (:func:`registration.io.dicom.read_xray`) as ``roadmap3d register`` reads
    them; plane B of a biplane pair carries the same acquisition time."""

    def __init__(self, volume: Volume, isocenter_mm, effects: tuple[str, ...], strength: float, *,
                 catheter: bool, base: Volume | None) -> None:  # fmt: skip
        from registration.sim.clinical import ClinicalEffects, ClinicalImager

        self.effects = ClinicalEffects.of(effects, strength)
        self.isocenter_mm = tuple(isocenter_mm)
        self.imager = ClinicalImager(volume, isocenter_mm, self.effects, catheter=catheter, base=base)

    def views(
        self, geometries: list[CArm], motion: np.ndarray, *, kind: str, seed: int
    ) -> tuple[list[XRayImage], dict]:
        import tempfile
        import warnings
        from datetime import UTC, datetime

        from registration.io import dicom

        when = datetime(2025, 1, 1, tzinfo=UTC)
        planes = ["PLANE A", "PLANE B"] if len(geometries) > 1 else [None]
        out, notes = [], {}
        with tempfile.TemporaryDirectory(prefix="roadmap3d-clinical-") as tmp:
            for n, (g, plane) in enumerate(zip(geometries, planes, strict=False)):
                image = self.imager.image(g, motion, kind=kind, seed=seed + n)
                path = image.write_dicom(Path(tmp) / f"plane{n}.dcm", acquired_at=when, plane=plane)
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    view = dicom.read_xray(path, isocenter_mm=self.isocenter_mm)
                out.append(view)
                if n == 0:
                    notes = {
                        "mask_from": view.meta.get("mask_from"),
                        "intensity_note": view.meta.get("intensity_note"),
                        "reader_warnings": sorted({str(w.message).split(": ", 1)[-1][:120] for w in caught}),
                        "field_px": int(image.field.sum()),
                        "mask_px": int(view.mask.sum()),
                        # pixels the reader uses that carry no anatomy (blades, text) / anatomy it drops
                        "mask_false_px": int((view.mask & ~image.field).sum()),
                        "mask_missed_px": int((image.field & ~view.mask).sum()),
                    }
        return out, notes


def _case_images(
    imager: VolumeImager | ClinicalViews, geometries: list[CArm], truth: np.ndarray, kind: str, seed: int
) -> tuple[list[XRayImage], dict]:
    """The case's image per view (clinical: written as XA files and read back, with the reader's notes)."""
    if isinstance(imager, ClinicalViews):
        return imager.views(geometries, truth, kind=kind, seed=seed)
    return [imager.image(g, truth, kind=kind, seed=seed + n) for n, g in enumerate(geometries)], {}


def _case_offsets(case: VolumeCase, geometries: list[CArm]) -> dict:
    """The case's view and offset, split into plane A's in-plane and out-of-plane parts."""
    g = geometries[0]
    t = np.asarray(case.translation_mm)
    t_out = float(t @ g.direction)
    return {
        "case": case.number,
        "primary_deg": case.primary_deg,
        "secondary_deg": case.secondary_deg,
        "views": len(geometries),
        "offset_translation_mm": float(np.linalg.norm(t)),
        "offset_inplane_mm": float(np.linalg.norm(t - t_out * g.direction)),
        "offset_outofplane_mm": abs(t_out),
        "offset_rotation_deg": case.rotation_deg,
        "seed": case.seed,
    }


def _assessed(result: object, images: list[XRayImage], preparation: Preparation) -> dict:
    """The estimate's confidence and decision as ``register --confidence`` gives them (at the
    search bounds: withheld)."""
    from registration.core.assess import assess
    from registration.studies.cases import assessment_fields

    found = assessment_fields(assess(result, images, preparation))  # type: ignore[arg-type]
    keys = ("confidence", "applied", "withheld_reason", "confidence_evidence", "confidence_seconds")
    return {k: found[k] for k in keys}


@with_one_blas_thread
def run_volume_case(
    volume: Volume,
    imager: VolumeImager,
    case: VolumeCase,
    config: VolumeStudyConfig,
    isocenter_mm: tuple[float, float, float],
    *,
    options: RegistrationOptions | None = None,
    confidence: bool = False,
    region: RegionOfInterest | None = None,
) -> dict:
    """Form the case's image(s), prepare the volume for its view(s), register and score.
    ``imager``: a :class:`VolumeImager` (clean images in memory) or :class:`ClinicalViews` (XA
    files written and read back); ``confidence``: assess the estimate as ``register --confidence``;
    ``region``: the part of the patient followed (:func:`registration.core.roi.region_views`, as
    ``register --roi`` narrows the fields)."""
    from registration.core.roi import region_views

    options = options or RegistrationOptions()
    geometries = _views(config, case, isocenter_mm)
    truth = case_motion(case, isocenter_mm)
    t0 = time.perf_counter()
    images, notes = _case_images(imager, geometries, truth, config.kind, case.seed)
    geometries = [im.geometry for im in images]
    narrowed, fields = region_views(volume, region, images)
    notes["region_left_out_px"] = [f.left_out_px for f in fields]
    image_s = time.perf_counter() - t0
    # the volume prepared as `roadmap3d register` prepares it (crop, body, mm levels; for the
    # whole fields, which the assessment sees), registered on the region's pixels
    preparation = Preparation.of(volume, images, options=options)
    prepared = preparation.prepared
    samples_before = list(prepared.renderer.samples_per_level)
    result = register(volume, narrowed, truth=truth, seed=case.seed, options=options, renderer=prepared.renderer)
    samples = [b - a for a, b in zip(samples_before, prepared.renderer.samples_per_level, strict=True)]
    res = result.residual
    assert res is not None
    inplane_ok = res.inplane_mm < SUCCESS_TRANSLATION_MM and res.rotation_deg < SUCCESS_ROTATION_DEG
    assessed = _assessed(result, images, preparation) if confidence else {}
    offsets = _case_offsets(case, geometries)
    return (
        assessed
        | notes
        | offsets
        | {
            "translation_residual_mm": res.translation_mm,
            "inplane_residual_mm": res.inplane_mm,
            "outofplane_residual_mm": res.outofplane_mm,
            "rotation_residual_deg": res.rotation_deg,
            # single plane: the paper's in-plane criterion (even when tz is searched too); biplane: 3-D
            "success": bool(res.success_total if len(geometries) > 1 else inplane_ok),
            "success_total": bool(res.success_total),
            "seconds": result.seconds,
            "prepare_seconds": prepared.seconds,
            # "built", or "memory" when an earlier case's view-independent part was reused
            "prepare_base": prepared.base_source,
            "image_seconds": image_s,
            "drr_count": result.drr_count,
            # the registration's work whatever the machine's load: bilinear samples of its DRRs
            "drr_samples": int(sum(samples)),
            "drr_samples_per_level": samples,
            "voxels_per_level": prepared.voxels_per_level,
            "spacing_mm": list(prepared.spacing_mm),
            "parameters": list(result.parameters),
            "offsets": np.asarray(result.offsets).tolist(),
            # where the search started (mm from the machine-based pose) and why it searched again
            "start_shift_mm": result.start_shift_mm,
            "second_search": result.second_search,
            # one view searched again from far along the beam (what it found; absent: it did not look)
            **({"beam_restart": result.beam_restart.to_dict()} if result.beam_restart is not None else {}),
            "version": __version__,
        }
    )


def summarize(records: list[dict], config: VolumeStudyConfig, *, volume: Volume, isocenter_mm, revision: str) -> dict:
    """The ``--json`` summary (``SUMMARY_KEYS`` first), with what the numbers rest on."""

    def median(key: str) -> float | None:
        return float(np.median([r[key] for r in records])) if records else None

    out = {
        "runs": len(records),
        "success_rate": float(np.mean([r["success"] for r in records])) if records else None,
        "inplane_residual_mm_median": median("inplane_residual_mm"),
        "rotation_residual_deg_median": median("rotation_residual_deg"),
        "seconds_median": median("seconds"),
        # each case has its own C-arm angles, so the volume is prepared for each (once per view)
        "prepare_seconds": median("prepare_seconds"),
        "success_criterion": (
            "3-D translational residual at the iso-center < 1 mm and rotation < 3 deg (biplane, six parameters)"
            if config.biplane
            else "in-plane translational residual at the iso-center < 1 mm and rotation < 3 deg (single plane)"
        ),
        "translation_residual_mm_median": median("translation_residual_mm"),
        "outofplane_residual_mm_median": median("outofplane_residual_mm"),
        "success_rate_3d": float(np.mean([r["success_total"] for r in records])) if records else None,
        "images": IMAGES_FROM_VOLUME,
        "arms": arm_summaries(records, biplane=config.biplane),
        "volume": volume.label,
        "volume_shape": list(volume.shape[::-1]),
        "volume_spacing_mm": [float(s) for s in volume.spacing_mm],
        "isocenter_mm": [float(c) for c in isocenter_mm],
        "config": asdict(config),
        "version": __version__,
        "revision": revision,
    }
    return out


def arm_summaries(records: list[dict], *, biplane: bool) -> list[dict]:
    """Per arm and strength: success, applied precision (applied estimates right) and recall
    (right estimates applied), the worst applied error (3-D for biplane, in-plane for one plane)."""
    groups: dict[tuple[str, float], list[dict]] = {}
    for r in records:
        groups.setdefault((r.get("arm", "clean"), float(r.get("strength", 1.0))), []).append(r)
    key = "translation_residual_mm" if biplane else "inplane_residual_mm"
    out = []
    for (arm, strength), rs in groups.items():
        decided = [r for r in rs if "applied" in r]
        applied = [r for r in decided if r["applied"]]
        right = [r for r in decided if r["success"]]
        both = [r for r in applied if r["success"]]
        errors = [r[key] for r in applied]
        out.append({
            "arm": arm,
            "effects": rs[0].get("effects", []),
            "strength": strength,
            "runs": len(rs),
            "success_rate": float(np.mean([r["success"] for r in rs])),
            "applied": len(applied) if decided else None,
            "withheld": len(decided) - len(applied) if decided else None,
            "applied_precision": len(both) / len(applied) if applied else None,
            "applied_recall": len(both) / len(right) if right else None,
            "applied_wrong": [r["case"] for r in applied if not r["success"]],
            "max_applied_error_mm": float(max(errors)) if errors else None,
            "applied_worse_than_2mm": sum(e >= 2.0 for e in errors),
            "residual_mm_median": float(np.median([r[key] for r in rs])),
            "worst_residual_mm": float(max(r[key] for r in rs)),
            "rotation_residual_deg_median": float(np.median([r["rotation_residual_deg"] for r in rs])),
            "mask_from": sorted({str(r.get("mask_from")) for r in rs if r.get("mask_from")}),
            "mask_parts": mask_parts([r.get("mask_from") for r in rs]),
            "intensity_note": sorted({str(r.get("intensity_note")) for r in rs if r.get("intensity_note")}),
            "mask_false_px_median": (
                float(np.median([r["mask_false_px"] for r in rs])) if "mask_false_px" in rs[0] else None
            ),
            "seconds_median": float(np.median([r["seconds"] for r in rs])),
        })  # fmt: skip
    return out


def mask_parts(found: list[str | None]) -> dict[str, int]:
    """On how many images each part of the field was found, from the reader's ``mask_from``
    texts ("dark outside, collimator blade x2, ..."), in the order the reader lists them."""
    counts: dict[str, int] = {}
    places: dict[str, list[int]] = {}
    for text in found:
        parts = [re.sub(r" x\d+$", "", p.strip()) for p in (text or "").split(", ") if p.strip()]
        for place, part in enumerate(dict.fromkeys(parts)):
            counts[part] = counts.get(part, 0) + 1
            places.setdefault(part, []).append(place)
    return {part: counts[part] for part in sorted(counts, key=lambda p: float(np.mean(places[p])))}


def run_volume_study(
    volume: Volume,
    isocenter_mm: tuple[float, float, float],
    config: VolumeStudyConfig,
    *,
    options: RegistrationOptions | None = None,
    out: Path | None = None,
    log: Callable[[str], None] | None = None,
) -> tuple[list[dict], dict]:
    """Every case of the study in this process; ``out``: results.jsonl, summary.json, report.md."""
    from registration.core.roi import followed_region
    from registration.studies.report_kit import source_revision

    say = log or (lambda _msg: None)
    records = []
    cases = volume_cases(config)
    arms = study_arms(config)
    region = followed_region(volume, config.roi)
    if region is not None:
        say(f"region: {region.describe()}")
    base = None
    # decisions for every arm (the clean one too, as the baseline) once any arm is clinical
    confidence = config.confidence or any(effects for _, effects, _ in arms)
    for arm, effects, strength in arms:
        if not effects:
            imager: VolumeImager | ClinicalViews = VolumeImager(volume, isocenter_mm, catheter=config.catheter)
        else:
            if base is None and "table" in effects:
                from registration.sim.clinical.anatomy import patient_only

                base = patient_only(volume)[0]  # the CT's couch cut off once for every arm with the table
            imager = ClinicalViews(volume, isocenter_mm, effects, strength, catheter=config.catheter,
                                   base=base if "table" in effects else None)  # fmt: skip
        label = arm if len(arms) == 1 or not effects else f"{arm} @ {strength:g}"
        for case in cases:
            record = run_volume_case(volume, imager, case, config, isocenter_mm, options=options, confidence=confidence,
                                     region=region)  # fmt: skip
            record.update(arm=arm, effects=list(effects), strength=strength)
            records.append(record)
            decision = ""
            if "applied" in record:
                decision = " applied" if record["applied"] else f" withheld ({record.get('withheld_reason')})"
            say(
                f"{label} [{case.number + 1}/{len(cases)}] LAO/RAO {case.primary_deg:+5.1f} CRAN/CAUD "
                f"{case.secondary_deg:+5.1f}: in-plane {record['inplane_residual_mm']:.2f} mm, 3-D "
                f"{record['translation_residual_mm']:.2f} mm, {record['rotation_residual_deg']:.2f} deg, "
                f"{record['seconds']:.2f} s (+{record['prepare_seconds']:.2f} s preparing) "
                f"{'ok' if record['success'] else 'MISS'}{decision}"
            )
            if out is not None:  # the records so far, so that a long study can be read while it runs
                Path(out).mkdir(parents=True, exist_ok=True)
                (Path(out) / "results.partial.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    summary = summarize(records, config, volume=volume, isocenter_mm=isocenter_mm, revision=source_revision())
    if any(effects for _, effects, _ in arms):
        from registration.sim.clinical import CLINICAL_IMAGES_FROM_VOLUME

        summary["images"] = CLINICAL_IMAGES_FROM_VOLUME + "; the arm 'clean': " + IMAGES_FROM_VOLUME
    if out is not None:
        write_outputs(Path(out), records, summary)
        (Path(out) / "results.partial.jsonl").unlink(missing_ok=True)
    return records, summary


#: Where the project finds the shared real head CT (outside the repository, see its README).
REAL_CT_RELATIVE = Path("..") / "shared" / "data" / "real-ct" / "head-neck-ct"


def find_real_ct() -> Path | None:
    """The shared real head CT folder (``../shared/data/real-ct/head-neck-ct`` beside the project,
    or ``ROADMAP3D_REAL_CT``), None when absent (a user's fresh clone has no ``../shared``)."""

    env = os.environ.get("ROADMAP3D_REAL_CT")
    root = Path(__file__).resolve().parents[2]
    for candidate in ([Path(env)] if env else []) + [root / REAL_CT_RELATIVE]:
        if candidate.is_dir() and any(candidate.glob("*.dcm")):
            return candidate
    return None
