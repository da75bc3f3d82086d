"""The paper's validation experiments on the simulated head phantom.

``run_case`` is one registration experiment (phantom, formats, offset, image kind) with the
honest image model; the studies loop over it. ``validate table1`` reproduces Table I's four
offsets on two format pairs with fluoro and exposure images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration import __version__
from registration.core.assess import assess, assess_on
from registration.core.confidence import Assessment
from registration.core.drr import DRRRenderer
from registration.core.geometry import TABLE_I, CArm, offsets_to_matrix, rigid
from registration.core.images import XRayImage
from registration.core.landmarks import LandmarkStart
from registration.core.preparation import Preparation
from registration.core.register import RegistrationOptions, RegistrationResult, register
from registration.sim.threedra import VolumeRecipe

if TYPE_CHECKING:
    from registration.core.volume import Volume
    from registration.sim.phantom import HeadPhantom


@dataclass(frozen=True)
class Case:
    """One registration experiment."""

    offset: str
    image_kind: str
    volume_format_cm: float
    image_format_cm: float
    seed: int = 0
    primary_deg: float = 0.0
    secondary_deg: float = 0.0
    #: Phantom variant (anatomy) seed; the noise and annealing use ``seed``.
    phantom_seed: int = 0
    facial: bool = True
    image_pixels: int = 512
    volume_voxels: int = 256
    #: How the 3DRA is made (registration.sim.threedra.VOLUME_SOURCES): "fdk", reconstructed
    #: from a simulated rotational run; "resampled", the phantom resampled (a faster stand-in).
    volume_source: str = "fdk"
    #: Contrast in the rotational run of the 3DRA (the fluoro image never has contrast).
    volume_contrast: bool = True
    #: Center of the 3DRA grid (world mm); non-zero for a 3DRA made with the table moved, e.g.
    #: the alternative 22 cm volume containing the facial structures (registration.studies.runs).
    volume_center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)


@lru_cache(maxsize=4)
def _phantom(seed: int, contrast: bool, facial: bool) -> HeadPhantom:
    from registration.sim.phantom import make_head_phantom

    return make_head_phantom(seed=seed, contrast=contrast, facial=facial)


def volume_recipe(case: Case) -> VolumeRecipe:
    """Which 3DRA a case registers to (its phantom, format, grid, source, contrast, center)."""
    return VolumeRecipe(
        phantom_seed=case.phantom_seed,
        volume_format_cm=case.volume_format_cm,
        source=case.volume_source,
        voxels=case.volume_voxels,
        contrast=case.volume_contrast,
        facial=case.facial,
        center_mm=tuple(case.volume_center_mm),  # type: ignore[arg-type]
    )


@lru_cache(maxsize=4)
def recipe_volume(recipe: VolumeRecipe) -> Volume:
    """The registration volume of a recipe (cached on disk and, for the last few, in memory)."""
    return recipe.build()


def load_volume(
    phantom_seed: int,
    facial: bool,
    volume_format_cm: float,
    voxels: int,
    source: str = "fdk",
    contrast: bool = True,
) -> Volume:
    """The registration volume of a phantom variant centered at the iso-center (cached)."""
    recipe = VolumeRecipe(
        phantom_seed=phantom_seed, volume_format_cm=volume_format_cm, source=source, voxels=voxels,
        contrast=contrast, facial=facial,
    )  # fmt: skip
    return recipe_volume(recipe)


def offset_vector(offset: str) -> np.ndarray:
    """Table I id ("T1".."T4") or "tx,ty,tz,rx,ry,rz" to six numbers."""
    if offset in TABLE_I:
        return np.array(TABLE_I[offset], dtype=np.float64)
    try:
        values = np.array([float(v) for v in offset.split(",")])
    except ValueError:
        raise ValueError(f"offset must be T1..T4 or six comma-separated numbers, got {offset!r}") from None
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(f"offset must be six finite numbers tx,ty,tz,rx,ry,rz, got {offset!r}")
    return values


def case_volume(case: Case) -> Volume:
    """The registration volume of a case: the 3DRA of its phantom and format (cached)."""
    return recipe_volume(volume_recipe(case))


def assessment_fields(assessment: Assessment) -> dict:
    """A record's fields of an assessment (:func:`registration.core.assess.assess`):
    ``confidence``, ``applied`` (CONVENTIONS §7), ``withheld_reason``, the evidence, the seconds
    it took and, for one plane, the probes along the beam (``depth_probe``, ``depth_scan``,
    ``depth_far``) and on the head alone (``spine_pull``)."""
    probe, scan = assessment.depth_probe, assessment.depth_scan
    return {
        "confidence": assessment.confidence,
        "applied": assessment.applied,
        "withheld_reason": assessment.reason,
        "confidence_evidence": assessment.evidence.to_dict(),
        "confidence_seconds": assessment.seconds,
        **({"depth_probe": probe.to_dict()} if probe is not None else {}),
        **({"depth_scan": scan.to_dict()} if scan is not None else {}),
        **({"spine_pull": pull.to_dict()} if (pull := assessment.spine_pull) is not None else {}),
        **({"depth_far": far.to_dict()} if (far := assessment.depth_far) is not None else {}),
    }


def confidence_fields(
    volume: Volume,
    xray: XRayImage | Sequence[XRayImage],
    result: RegistrationResult,
    renderer: DRRRenderer | None = None,
    *,
    single_plane_motion: ArrayLike | None = None,
) -> dict:
    """:func:`assessment_fields` of :func:`registration.core.assess.assess_on` for a caller holding
    a renderer rather than a :class:`~registration.core.preparation.Preparation` (None: the
    whole volume's index pyramid, ``DRRRenderer(volume, levels=3)``)."""
    renderer = renderer if renderer is not None else DRRRenderer(volume, levels=3)
    return assessment_fields(assess_on(result, xray, volume, renderer, single_plane_motion=single_plane_motion))


def depth_correction_fields(result: object) -> dict:
    """A depth-corrected single-plane result's tz (``depth_tz_mm``: mm along the beam in the view
    frame, + toward the source, held in ``patient_motion``) and its scans' moves; nothing for a
    result without the correction (RegistrationOptions.depth_correction off, two views); and
    the rotation check's outcome (``rotation_check``) and the search again from far along the beam
    (``beam_restart``) when they ran."""
    tz = getattr(result, "depth_tz_mm", None)
    if tz is None:
        return {}
    out = {"depth_tz_mm": float(tz), "depth_moves_mm": [float(m) for m in result.depth_moves_mm]}
    check = getattr(result, "rotation_check", None)
    if check is not None:
        out["rotation_check"] = check.to_dict()
    restart = getattr(result, "beam_restart", None)
    if restart is not None:
        out["beam_restart"] = restart.to_dict()
    return out


def rival_gain(result: object) -> float | None:
    """The rotation check's ``rival_gain`` of a single-plane result (None: no check ran, or every
    polish came back): :attr:`registration.core.register.RegistrationResult.rotation_check`."""
    check = getattr(result, "rotation_check", None)
    return None if check is None or check.rival_gain is None else float(check.rival_gain)


def register_prepared(
    volume: Volume,
    views: XRayImage | Sequence[XRayImage],
    *,
    seed: int,
    initial_motion: ArrayLike | None = None,
    truth: ArrayLike | None = None,
    vessel_points_mm: ArrayLike | None = None,
    options: RegistrationOptions | None = None,
    landmarks: LandmarkStart | None = None,
) -> tuple[RegistrationResult, Preparation]:
    """Register as ``roadmap3d register`` does: the volume prepared for the views from the
    initial pose (:class:`registration.core.preparation.Preparation`: crop, body, mm levels),
    then :func:`registration.core.register.register` with its renderer. The studies' path."""
    preparation = Preparation.of(volume, views, initial_motion=initial_motion, options=options)
    result = register(volume, views, initial_motion=initial_motion, seed=seed, truth=truth,
                      vessel_points_mm=vessel_points_mm, options=options, renderer=preparation.renderer,
                      landmarks=landmarks)  # fmt: skip
    return result, preparation


def run_case(case: Case, *, options: RegistrationOptions | None = None) -> dict:
    """Simulate the X-ray image of the moved phantom and register the 3DRA to it."""
    from registration.sim.xray import simulate_xray

    geometry = CArm.for_format(
        case.image_format_cm,
        pixels=case.image_pixels,
        primary_deg=case.primary_deg,
        secondary_deg=case.secondary_deg,
    )
    truth = offsets_to_matrix(offset_vector(case.offset), geometry)
    volume = case_volume(case)
    anatomy = _phantom(case.phantom_seed, False, case.facial)  # no contrast in the fluoro image
    xray = simulate_xray(anatomy, geometry, motion=truth, kind=case.image_kind, seed=case.seed)
    result, preparation = register_prepared(
        volume, xray, seed=case.seed, truth=truth, vessel_points_mm=anatomy.vessel_centerline_mm(), options=options
    )
    res = result.residual
    assert res is not None
    return {
        "offset": case.offset,
        "image_kind": case.image_kind,
        "volume_format_cm": case.volume_format_cm,
        "image_format_cm": case.image_format_cm,
        "primary_deg": case.primary_deg,
        "secondary_deg": case.secondary_deg,
        "seed": case.seed,
        "phantom_seed": case.phantom_seed,
        "facial": case.facial,
        "translation_residual_mm": res.translation_mm,
        "inplane_residual_mm": res.inplane_mm,
        "outofplane_residual_mm": res.outofplane_mm,
        "rotation_residual_deg": res.rotation_deg,
        "mtre_mm": res.mtre_mm,
        "success": bool(res.success),
        "success_total": bool(res.success_total),
        "seconds": result.seconds,
        "prepare_seconds": preparation.seconds,
        "drr_count": result.drr_count,
        "stages": [c.to_dict() for c in result.stages],
        "similarity": result.similarity,
        "volume_label": result.volume_label,
        "version": __version__,
        **depth_correction_fields(result),
        **assessment_fields(assess(result, xray, preparation)),
    }


def table1_cases(seed: int = 0) -> list[Case]:
    return [
        Case(offset=o, image_kind=kind, volume_format_cm=f, image_format_cm=f, seed=seed)
        for f in (27.0, 48.0)
        for kind in ("fluoro", "exposure")
        for o in TABLE_I
    ]


def summarize(records: list[dict]) -> dict:
    """Success rate and residual statistics of a list of records."""
    if not records:
        return {"runs": 0, "success_rate": None}
    ok = [r for r in records if r["success"]]

    def stats(key: str, rows: list[dict]) -> dict | None:
        if not rows:
            return None
        v = np.array([r[key] for r in rows], dtype=float)
        return {"mean": float(v.mean()), "std": float(v.std()), "min": float(v.min()), "max": float(v.max())}

    return {
        "runs": len(records),
        "successes": len(ok),
        "success_rate": len(ok) / len(records),
        "inplane_residual_mm": stats("inplane_residual_mm", records),
        "translation_residual_mm": stats("translation_residual_mm", records),
        "rotation_residual_deg": stats("rotation_residual_deg", records),
        "inplane_residual_mm_successful": stats("inplane_residual_mm", ok),
        "rotation_residual_deg_successful": stats("rotation_residual_deg", ok),
        "seconds_median": float(np.median([r["seconds"] for r in records])),
        "drr_count_median": float(np.median([r["drr_count"] for r in records])),
        # The preparation's view-independent part is built once per volume, its levels per view.
        "prepare_seconds_total": float(sum(r.get("prepare_seconds", 0.0) for r in records)),
    }


def format_table(records: list[dict]) -> str:
    head = (
        f"{'T':<3} {'kind':<8} {'vol':>4} {'img':>4}  {'in-plane':>9} {'total':>8} {'rot':>7} "
        f"{'mTRE':>7} {'DRRs':>5} {'s':>6}  ok"
    )
    lines = [head, "-" * len(head)]
    for r in records:
        mtre = f"{r['mtre_mm']:7.2f}" if r.get("mtre_mm") is not None else "      -"
        lines.append(
            f"{r['offset']:<3} {r['image_kind']:<8} {r['volume_format_cm']:>4.0f} {r['image_format_cm']:>4.0f}"
            f"  {r['inplane_residual_mm']:>6.2f} mm {r['translation_residual_mm']:>5.2f} mm"
            f" {r['rotation_residual_deg']:>5.2f}° {mtre} {r['drr_count']:>5d} {r['seconds']:>6.2f}"
            f"  {'yes' if r['success'] else 'NO'}"
        )
    return "\n".join(lines)


def _translation(t_mm: Sequence[float]) -> NDArray[np.float64]:
    return rigid(None, np.asarray(t_mm, dtype=np.float64))
