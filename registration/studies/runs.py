"""The paper's validation studies at scale: Table II-III and Fig. 6 (phantom), Fig. 7 (clinical).

``roadmap3d validate phantom`` registers every volume format x image format of Table II, the
offsets T1-T4 of Table I, fluoro and exposure images (512 registrations), plus the 64 with the
alternative 22 cm 3DRA that contains the facial structures. ``roadmap3d validate clinical``
follows the paper's rotational-run method (section II.D / III.B): a random projection of a
virtual patient's rotational run is registered to that run's own FDK reconstruction after a
random offset; the ground truth is the run's calibrated geometry.

Execution: each registration is a :class:`StudyTask`; tasks run in joblib processes (default)
or on a Dask cluster (``scheduler="tcp://HOST:PORT"``). The parent process alone writes
``results.jsonl``: one JSON record per finished registration, appended, flushed and fsynced,
keyed by ``case_id``; a rerun skips every id already there, so a killed run loses nothing that
finished. The id names the case (study, formats, offset, image and volume resolution, seed), not
the engine: after changing the engine, write to a new output folder. The volumes (and
rotational runs) are built once in the parent before fanning out; the on-disk cache
(:mod:`registration.io.cache`) makes workers just load them. Dask workers on other machines should
share that cache (``ROADMAP3D_CACHE``) or they build what they need themselves.

Summaries and reports (plots, ``report.md``, ``report.html``) are in :mod:`registration.studies.report`.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from registration import __version__
from registration.core.geometry import IMAGE_FORMATS_CM, TABLE_I, CArm, axis_rotation, clinically_relevant, rigid
from registration.core.register import RegistrationOptions
from registration.studies.cases import Case, _translation, depth_correction_fields

if TYPE_CHECKING:
    from registration.core.images import XRayImage
    from registration.core.volume import Volume

#: Image and volume formats of Table II (cm): the system's eight.
STUDY_FORMATS_CM: tuple[float, ...] = IMAGE_FORMATS_CM
IMAGE_KINDS: tuple[str, ...] = ("exposure", "fluoro")

#: The alternative 22 cm 3DRA "which contained the facial structures" (paper III.A): the
#: rotational run was made with the table moved so that the reconstruction's center lies
#: 40 mm caudal and 20 mm anterior of the iso-center of the X-ray images (world mm, LPS).
#: The standard volumes are centered at the iso-center (the circle of Willis).
FACIAL_VOLUME_FORMAT_CM = 22.0
FACIAL_VOLUME_CENTER_MM: tuple[float, float, float] = (0.0, -20.0, -40.0)

#: Clinical study (paper III.B): 10 patients, 6 at 22 cm and 4 at 27 cm, 5 with contrast.
CLINICAL_PATIENTS: tuple[tuple[float, bool], ...] = (
    (22.0, True),
    (22.0, False),
    (22.0, True),
    (22.0, False),
    (22.0, True),
    (22.0, False),
    (27.0, True),
    (27.0, False),
    (27.0, True),
    (27.0, False),
)
#: Largest random offset of the clinical study: translation length (mm), rotation angle (deg).
CLINICAL_MAX_TRANSLATION_MM = 25.0
CLINICAL_MAX_ROTATION_DEG = 10.0
#: Phantom seeds of the virtual patients start here (seed 0 is the phantom study's head).
CLINICAL_FIRST_PHANTOM_SEED = 1


def _stable_seed(base: int, key: str) -> int:
    """A per-case seed that depends only on the study seed and the case's identity (not on the
    grid or its resolution: the quick study repeats the full study's draws at lower resolution)."""
    return int((int(base) * 1_000_003 + zlib.crc32(key.encode())) % (2**31 - 1))


# --------------------------------------------------------------------------------------
# Study configurations
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PhantomConfig:
    """What the phantom study registers."""

    volume_formats_cm: tuple[float, ...] = STUDY_FORMATS_CM
    image_formats_cm: tuple[float, ...] = STUDY_FORMATS_CM
    kinds: tuple[str, ...] = IMAGE_KINDS
    offsets: tuple[str, ...] = tuple(TABLE_I)
    #: Image formats registered against the alternative (facial) 22 cm volume; () for none.
    facial_image_formats_cm: tuple[float, ...] = STUDY_FORMATS_CM
    image_pixels: int = 512
    volume_voxels: int = 256
    volume_source: str = "fdk"
    seed: int = 0
    quick: bool = False

    @classmethod
    def quick_config(cls, seed: int = 0) -> PhantomConfig:
        """A few minutes on 2 cores: clinically relevant sample, one kind, 256 px, 128^3."""
        sample = (22.0, 27.0, 37.0, 48.0)
        return cls(
            volume_formats_cm=sample,
            image_formats_cm=sample,
            kinds=("exposure",),
            facial_image_formats_cm=(22.0, 27.0),
            image_pixels=256,
            volume_voxels=128,
            seed=seed,
            quick=True,
        )


@dataclass(frozen=True)
class ClinicalConfig:
    """What the clinical (rotational-run) study registers."""

    patients: tuple[tuple[float, bool], ...] = CLINICAL_PATIENTS
    registrations_per_patient: int = 100
    projections: int = 120
    arc_deg: float = 200.0
    #: Detector pixels of the run (2x2-binned rotational mode, as reconstruct_3dra).
    run_pixels: int = 256
    volume_voxels: int = 256
    max_translation_mm: float = CLINICAL_MAX_TRANSLATION_MM
    max_rotation_deg: float = CLINICAL_MAX_ROTATION_DEG
    seed: int = 0
    quick: bool = False

    @classmethod
    def quick_config(cls, seed: int = 0) -> ClinicalConfig:
        """A few minutes on 2 cores: 2 patients (22 cm with contrast, 27 cm without) x 20
        registrations; full runs (120 projections of 256 px), 128^3 reconstructions.

        Runs of 128 px frames (1.16 mm per pixel at the iso-center for 22 cm) were tried and
        bias the 22 cm registrations by ~0.5 mm even from the true pose: too coarse for a 1 mm
        criterion."""
        return cls(
            patients=((22.0, True), (27.0, False)),
            registrations_per_patient=20,
            projections=120,
            run_pixels=256,
            volume_voxels=128,
            seed=seed,
            quick=True,
        )


# --------------------------------------------------------------------------------------
# Tasks
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ClinicalCase:
    """One registration of the clinical study: a projection of a patient's own rotational run,
    offset by (translation, rotation about ``rotation_axis``) from its calibrated pose."""

    patient: int
    phantom_seed: int
    volume_format_cm: float
    contrast: bool
    frame: int
    translation_mm: tuple[float, float, float]
    rotation_axis: tuple[float, float, float]
    rotation_deg: float
    seed: int
    projections: int = 120
    arc_deg: float = 200.0
    run_pixels: int = 256
    volume_voxels: int = 256


@dataclass(frozen=True)
class StudyTask:
    """A unit of work: a phantom :class:`~registration.studies.cases.Case` or a
    :class:`ClinicalCase`, its id, and fields the record carries along."""

    case_id: str
    case: Case | ClinicalCase | Any
    extra: dict = field(default_factory=dict)
    options: RegistrationOptions | None = None


def phantom_tasks(config: PhantomConfig, options: RegistrationOptions | None = None) -> list[StudyTask]:
    """Every registration of the phantom study, grouped by volume (workers reuse it)."""
    tag = f"p{config.image_pixels}-v{config.volume_voxels}-{config.volume_source}"
    tasks = []
    grid: list[tuple[str, float, tuple[float, ...]]] = [
        ("standard", v, config.image_formats_cm) for v in config.volume_formats_cm
    ]
    if config.facial_image_formats_cm:
        grid.append(("facial", FACIAL_VOLUME_FORMAT_CM, config.facial_image_formats_cm))
    for variant, vol, images in grid:
        for kind in config.kinds:
            for img in images:
                for offset in config.offsets:
                    ident = f"phantom/{variant}/{kind}/v{vol:g}/i{img:g}/{offset}"
                    case_id = f"{ident}/{tag}/s{config.seed}"
                    case = Case(
                        offset=offset,
                        image_kind=kind,
                        volume_format_cm=vol,
                        image_format_cm=img,
                        seed=_stable_seed(config.seed, ident),
                        image_pixels=config.image_pixels,
                        volume_voxels=config.volume_voxels,
                        volume_source=config.volume_source,
                        volume_center_mm=FACIAL_VOLUME_CENTER_MM if variant == "facial" else (0.0, 0.0, 0.0),
                    )
                    extra = {
                        "variant": variant,
                        "clinically_relevant": clinically_relevant(vol, img),
                        "study_seed": config.seed,
                        "image_pixels": config.image_pixels,
                        "volume_voxels": config.volume_voxels,
                        "volume_source": config.volume_source,
                        "volume_center_mm": list(case.volume_center_mm),
                    }
                    tasks.append(StudyTask(case_id, case, extra, options))
    return tasks


def random_unit_vector(rng: np.random.Generator) -> NDArray[np.float64]:
    """A direction uniform on the sphere."""
    while True:
        v = rng.normal(size=3)
        n = float(np.linalg.norm(v))
        if n > 1e-9:
            return v / n


def clinical_tasks(config: ClinicalConfig, options: RegistrationOptions | None = None) -> list[StudyTask]:
    """Every registration of the clinical study. Each draw (frame, offset, seed) depends only on
    the study seed, the patient and the registration number."""
    tag = f"n{config.projections}-p{config.run_pixels}-v{config.volume_voxels}"
    tasks = []
    for patient, (fmt, contrast) in enumerate(config.patients):
        phantom_seed = CLINICAL_FIRST_PHANTOM_SEED + patient
        for number in range(config.registrations_per_patient):
            rng = np.random.default_rng([config.seed, patient, number])
            frame = int(rng.integers(config.projections))
            length = rng.uniform(0.0, config.max_translation_mm)
            translation = length * random_unit_vector(rng)
            axis = random_unit_vector(rng)
            angle = rng.uniform(0.0, config.max_rotation_deg)
            ident = f"clinical/patient{patient}/r{number}"
            case_id = f"{ident}/{tag}/s{config.seed}"
            case = ClinicalCase(
                patient=patient,
                phantom_seed=phantom_seed,
                volume_format_cm=fmt,
                contrast=contrast,
                frame=frame,
                translation_mm=tuple(float(t) for t in translation),  # type: ignore[arg-type]
                rotation_axis=tuple(float(a) for a in axis),  # type: ignore[arg-type]
                rotation_deg=float(angle),
                seed=_stable_seed(config.seed, ident),
                projections=config.projections,
                arc_deg=config.arc_deg,
                run_pixels=config.run_pixels,
                volume_voxels=config.volume_voxels,
            )
            extra = {"study_seed": config.seed, "registration": number}
            tasks.append(StudyTask(case_id, case, extra, options))
    return tasks


# --------------------------------------------------------------------------------------
# Volumes the studies need beyond validation.load_volume
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PatientData:
    """A virtual patient: the rotational run (images, masks, true and calibrated geometries)
    and the FDK reconstruction of exactly those images."""

    images: NDArray[np.float32]
    masks: NDArray[np.bool_]
    true_geometries: tuple[CArm, ...]
    calibrated_geometries: tuple[CArm, ...]
    volume: Volume


def patient_params(case: ClinicalCase) -> dict:
    return {
        "phantom_seed": case.phantom_seed,
        "volume_format_cm": case.volume_format_cm,
        "contrast": case.contrast,
        "projections": case.projections,
        "arc_deg": case.arc_deg,
        "pixels": case.run_pixels,
        "voxels": case.volume_voxels,
    }


@lru_cache(maxsize=2)
def patient_data(
    phantom_seed: int,
    volume_format_cm: float,
    contrast: bool,
    projections: int = 120,
    arc_deg: float = 200.0,
    pixels: int = 256,
    voxels: int = 256,
) -> PatientData:
    """Simulate (or load from the cache) a patient's rotational run and its FDK 3DRA.

    The run is an exposure-dose propeller run of the phantom variant ``phantom_seed`` (iodine in
    the vessels when ``contrast``) at image format = ``volume_format_cm``; images are formed with
    the true (bent) geometry; the reconstruction uses the calibrated geometry
    (:func:`registration.sim.rotational_run.rotational_run`, :func:`~registration.sim.reconstruct.reconstruct_run`).
    """
    from registration.core.volume import Volume
    from registration.io.cache import cached_arrays
    from registration.sim.phantom import PHANTOM_MODEL_VERSION, make_head_phantom
    from registration.sim.reconstruct import RECONSTRUCTION_LABEL, reconstruct_run
    from registration.sim.rotational_run import rotational_run

    params = {"phantom_model": PHANTOM_MODEL_VERSION, "phantom_seed": int(phantom_seed),
              "volume_format_cm": float(volume_format_cm), "contrast": bool(contrast), "projections": int(projections),
              "arc_deg": float(arc_deg), "pixels": int(pixels), "voxels": int(voxels), "kind": "exposure"}  # fmt: skip

    def run_with(imager: Any = None) -> Any:
        return rotational_run(
            make_head_phantom(seed=phantom_seed, contrast=contrast),
            image_format_cm=volume_format_cm,
            projections=projections,
            arc_deg=arc_deg,
            kind="exposure",
            pixels=pixels,
            seed=phantom_seed,
            imager=imager,
        )

    def build() -> dict[str, np.ndarray]:
        run = run_with()
        vol = reconstruct_run(run, volume_format_cm=volume_format_cm, voxels=voxels)
        return {"images": run.images, "masks": run.masks, "volume": vol.data, "index_to_world": vol.index_to_world}

    arrays = cached_arrays("clinical-patient", params, build)

    # the geometries are cheap: the same run with a blank imager (calibration is cached)
    def blank(ph: object, geom: CArm, index: int) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((geom.rows, geom.cols), np.float32), np.ones((geom.rows, geom.cols), bool)

    geoms = run_with(blank)
    volume = Volume(
        arrays["volume"],
        arrays["index_to_world"],
        label=RECONSTRUCTION_LABEL.format(n=projections) + ", the patient's own run",
        meta=params,
    )
    return PatientData(
        images=arrays["images"],
        masks=arrays["masks"].astype(bool),
        true_geometries=geoms.true_geometries,
        calibrated_geometries=geoms.calibrated_geometries,
        volume=volume,
    )


def patient_of(case: ClinicalCase) -> PatientData:
    return patient_data(
        case.phantom_seed,
        case.volume_format_cm,
        case.contrast,
        case.projections,
        case.arc_deg,
        case.run_pixels,
        case.volume_voxels,
    )


def axis_angle_matrix(axis: Sequence[float], angle_deg: float) -> NDArray[np.float64]:
    """4x4 rotation by ``angle_deg`` about ``axis`` through the world origin (the iso-center)."""
    return rigid(axis_rotation(axis, math.radians(angle_deg)), None)


def offset_record(
    result: Any,
    geometry: CArm,
    shift_mm: NDArray[np.float64],
    rotation_axis: Sequence[float],
    rotation_deg: float,
    seed: int,
) -> dict:
    """The fields every random-offset record shares (clinical study, rotational-run validation):
    the offset (``shift_mm``: its translation at the iso-center; its in-plane and out-of-plane
    parts along ``geometry``'s beam), the residuals and successes of ``result`` (a
    :class:`~registration.core.register.RegistrationResult` with a truth), its cost."""
    res = result.residual
    if res is None:
        raise ValueError("the result has no residual: register with a truth")
    t = np.asarray(shift_mm, dtype=np.float64)
    t_out = float(t @ geometry.direction)
    return {
        "offset_translation_mm": float(np.linalg.norm(t)),
        "offset_inplane_mm": float(np.linalg.norm(t - t_out * geometry.direction)),
        "offset_outofplane_mm": abs(t_out),
        "offset_rotation_deg": rotation_deg,
        "offset_vector_mm": [float(v) for v in t],
        "offset_axis": list(rotation_axis),
        "seed": seed,
        "translation_residual_mm": res.translation_mm,
        "inplane_residual_mm": res.inplane_mm,
        "outofplane_residual_mm": res.outofplane_mm,
        "rotation_residual_deg": res.rotation_deg,
        "translation_success": bool(res.inplane_mm < 1.0),
        "rotation_success": bool(res.rotation_deg < 3.0),
        "success": bool(res.success),
        "success_total": bool(res.success_total),
        "seconds": result.seconds,
        "drr_count": result.drr_count,
        "similarity": result.similarity,
        "volume_label": result.volume_label,
        **depth_correction_fields(result),
    }


def clinical_inputs(case: ClinicalCase) -> tuple[PatientData, XRayImage, NDArray[np.float64]]:
    """The case's patient data, its frame as an exposure in the frame's calibrated geometry, and
    the initial offset (the case's translation after its rotation)."""
    from registration.core.images import XRayImage

    data = patient_of(case)
    xray = XRayImage(
        data.images[case.frame],
        data.masks[case.frame],
        data.calibrated_geometries[case.frame],
        "exposure",
        {"frame": case.frame, "source": "rotational run"},
    )
    offset = _translation(case.translation_mm) @ axis_angle_matrix(case.rotation_axis, case.rotation_deg)
    return data, xray, offset


def run_clinical_case(case: ClinicalCase, *, options: RegistrationOptions | None = None) -> dict:
    """Register one projection of the patient's run to the run's reconstruction, from a pose
    offset by the case's translation and rotation. Truth: the identity in the calibrated
    geometry of that frame (the projection itself was formed with the true, bent geometry)."""
    data, xray, offset = clinical_inputs(case)
    geometry = xray.geometry
    from registration.core.assess import assess
    from registration.studies.cases import assessment_fields, register_prepared

    result, preparation = register_prepared(data.volume, xray, initial_motion=offset, truth=np.eye(4),
                                            seed=case.seed, options=options)  # fmt: skip
    confidence = assessment_fields(assess(result, xray, preparation))
    return {
        "patient": case.patient,
        "phantom_seed": case.phantom_seed,
        "volume_format_cm": case.volume_format_cm,
        "contrast": case.contrast,
        "frame": case.frame,
        "primary_deg": geometry.primary_deg,
        **offset_record(
            result, geometry, np.asarray(case.translation_mm), case.rotation_axis, case.rotation_deg, case.seed
        ),
        "image_pixels": case.run_pixels,
        "volume_voxels": case.volume_voxels,
        "projections": case.projections,
        "version": __version__,
        "patient_motion": np.asarray(result.patient_motion).tolist(),
        **confidence,
        **depth_fields(confidence, np.eye(4), geometry),
    }


def depth_fields(confidence: dict, truth: NDArray[np.float64], geometry: CArm) -> dict:
    """The depth probe's pose (six parameters, from the five-parameter result) scored against the
    truth like the result: what a single-plane registration that ends by letting tz move would
    give (``depth_*`` residuals; the record's own success stays the result's)."""
    from registration.core.metrics import residuals

    probe = confidence.get("depth_probe")
    if probe is None:
        return {}
    r = residuals(np.asarray(probe["motion"]), truth, geometry)
    return {
        "depth_inplane_residual_mm": r.inplane_mm,
        "depth_outofplane_residual_mm": r.outofplane_mm,
        "depth_rotation_residual_deg": r.rotation_deg,
        "depth_success": bool(r.inplane_mm < 1.0 and r.rotation_deg < 3.0),
    }
