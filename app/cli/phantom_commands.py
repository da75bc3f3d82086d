"""``roadmap3d phantom``: the built-in phantom exported as a user's files (a DICOM 3DRA series,
XA images with a known motion, the truth JSON), written whole or not at all."""

from __future__ import annotations

import time
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from app.cli.commands import _format_offsets, _progress, _say, parse_offset
from app.cli.configs import Phantom
from registration.core.geometry import OFFSET_NAMES, CArm, offsets_to_matrix
from registration.core.images import XRayImage
from registration.core.volume import Volume
from registration.io import dicom
from registration.sim.threedra import VOLUME_SOURCES, VolumeRecipe

#: Files written by ``roadmap3d phantom`` inside its output folder.
PHANTOM_VOLUME_DIR = "volume"
PHANTOM_FLUORO = "xa_fluoro.dcm"
PHANTOM_EXPOSURE = "xa_exposure.dcm"
PHANTOM_FLUORO_B = "xa_fluoro_plane_b.dcm"
#: Seconds between the phantom's fluoro frame and its exposure (two acquisitions, not one moment).
EXPOSURE_AFTER_FLUORO_S = 4.0
PHANTOM_TRUTH = "truth.json"


def _phantom_3dra(
    *,
    source: str,
    seed: int,
    contrast: bool,
    volume_format: float,
    voxels: int,
) -> tuple[Volume, str, dict[str, Any]]:
    """The 3DRA to export, its SeriesDescription (<= 64 characters) and how it was made (for the truth).

    The same phantom (seed, contrast) as the XA images; the run's own noise seed and protocol
    are the recipe's defaults, so the cache entry is shared with the validation and the app.
    """
    recipe = VolumeRecipe(
        phantom_seed=seed, volume_format_cm=volume_format, source=source, voxels=voxels, contrast=contrast,
        noise_seed=seed,
    )  # fmt: skip
    if not recipe.reconstructed:
        volume = recipe.build()
        return volume, "3DRA stand-in: phantom resampled to the 3DRA grid", {"volume_source": source}
    message = (
        f"3DRA: simulating the rotational run and reconstructing it (FDK, {voxels}^3 voxels, "
        f"{volume_format:g} cm format); this takes minutes the first time and is cached afterwards"
    )
    with _progress(message):
        volume = recipe.build()
    run = {k: volume.meta[k] for k in ("projections", "arc_deg", "pixels", "kind", "seed") if k in volume.meta}
    label = f"3DRA: {volume.label}, head phantom seed {seed} {'with' if contrast else 'without'} contrast"
    description = f"3DRA: FDK reconstruction, {run.get('projections', '?')} projections"
    return volume.with_data(volume.data, label=label), description, {"volume_source": source, "rotational_run": run}


def _check(options: Phantom) -> None:
    out = Path(options.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not an empty folder; refusing to overwrite")
    if options.voxels < 8 or options.pixels < 16:
        raise ValueError(f"voxels must be >= 8 and pixels >= 16, got {options.voxels} and {options.pixels}")
    if options.volume_source not in VOLUME_SOURCES:
        raise ValueError(f"--volume-source must be one of {', '.join(VOLUME_SOURCES)}, got {options.volume_source!r}")


@dataclass
class _Export:
    """What ``roadmap3d phantom`` writes: the 3DRA, the images and the truth document."""

    volume: Volume
    description: str
    geometry: CArm
    geometry_b: CArm
    motion: np.ndarray
    images: dict[str, XRayImage]
    truth: dict[str, Any]


def _simulate(options: Phantom, offset_name: str, offsets: np.ndarray) -> _Export:
    """The 3DRA, the fluoro and exposure images of plane A and plane B's fluoro, and the truth."""
    from registration.sim.biplane import plane_b_spec
    from registration.sim.phantom import make_head_phantom
    from registration.sim.xray import simulate_xray

    seed, contrast = options.seed, options.contrast
    geometry = CArm.for_format(options.image_format, pixels=options.pixels, primary_deg=options.primary_deg,
                               secondary_deg=options.secondary_deg)  # fmt: skip
    motion = offsets_to_matrix(offsets, geometry)
    phantom = make_head_phantom(seed=seed, contrast=contrast)
    volume, description, made = _phantom_3dra(source=options.volume_source, seed=seed, contrast=contrast,
                                              volume_format=options.volume_format, voxels=options.voxels)  # fmt: skip
    # Plane B of the biplane system (CONVENTIONS §6): lateral, its own distances and detector,
    # the same moment as the plane A fluoro frame (same motion, own noise).
    geometry_b = plane_b_spec().nominal(90.0 + options.primary_deg, options.secondary_deg,
                                        pixels=max(16, 2 * round(0.375 * options.pixels)))  # fmt: skip
    images = {
        PHANTOM_FLUORO: simulate_xray(phantom, geometry, motion=motion, kind="fluoro", seed=seed),
        PHANTOM_EXPOSURE: simulate_xray(phantom, geometry, motion=motion, kind="exposure", seed=seed + 1),
        PHANTOM_FLUORO_B: simulate_xray(phantom, geometry_b, motion=motion, kind="fluoro", seed=seed + 2),
    }
    vessels = phantom.vessel_centerline_mm()
    truth = {
        "patient_motion": motion.tolist(),
        "offset": {"name": offset_name, **dict(zip(OFFSET_NAMES, offsets.tolist(), strict=True))},
        "geometry": geometry.to_dict(),
        "geometry_plane_b": geometry_b.to_dict(),
        "volume_format_cm": options.volume_format,
        "image_format_cm": options.image_format,
        "phantom": {"seed": seed, "contrast": contrast},
        "volume_label": volume.label,
        **made,
        "images": "the analytic phantom moved by patient_motion, projected with the nominal geometry of the "
        "XA positioner tags",
        "files": {
            "volume": PHANTOM_VOLUME_DIR,
            "fluoro": PHANTOM_FLUORO,
            "exposure": PHANTOM_EXPOSURE,
            "fluoro_plane_b": PHANTOM_FLUORO_B,
        },
        "vessel_points_mm": np.round(vessels[:: max(1, len(vessels) // 200)], 3).tolist(),
        "conventions": "shared/CONVENTIONS.md §4: anatomy the volume shows at X is at M @ X in the images",
    }
    return _Export(volume, description, geometry, geometry_b, motion, images, truth)


def _write(options: Phantom, export: _Export) -> None:
    """The export folder, whole or not at all: the 3DRA series, the XA files, the rotational run
    (FDK source) and the truth."""
    o = options
    uid_seed = (f"roadmap3d phantom {o.seed} {o.volume_format} {o.image_format} {o.voxels} {o.pixels} {o.contrast} "
                f"{o.volume_source}")  # fmt: skip
    study_uid = str(dicom.make_uid(uid_seed, "study"))
    moment = datetime.now(UTC)
    images, volume = export.images, export.volume
    with dicom.atomic_folder(Path(o.out)) as tmp:
        dicom.write_series(volume, tmp / PHANTOM_VOLUME_DIR, description=export.description, study_uid=study_uid,
                           uid_seed=uid_seed)  # fmt: skip
        dicom.write_xray(images[PHANTOM_FLUORO], tmp / PHANTOM_FLUORO, study_uid=study_uid, uid_seed=uid_seed,
                         plane="PLANE A", acquired_at=moment)  # fmt: skip
        dicom.write_xray(images[PHANTOM_FLUORO_B], tmp / PHANTOM_FLUORO_B, study_uid=study_uid,
                         uid_seed=f"{uid_seed} plane B", plane="PLANE B", acquired_at=moment,
                         description="roadmap3d fluoro, plane B")  # fmt: skip
        # The exposure is its own acquisition, a few seconds after the fluoro frame: never one moment
        # with it, however fast this machine writes the files (biplane pairing refuses it).
        dicom.write_xray(images[PHANTOM_EXPOSURE], tmp / PHANTOM_EXPOSURE, study_uid=study_uid, uid_seed=uid_seed,
                         acquired_at=moment + timedelta(seconds=EXPOSURE_AFTER_FLUORO_S))  # fmt: skip
        if o.volume_source == "fdk":  # the run the 3DRA was reconstructed from (validate rotational-run)
            from app.cli.rotational_commands import export_phantom_run

            export.truth["files"].update(
                export_phantom_run(tmp, volume, seed=o.seed, contrast=o.contrast, volume_format=o.volume_format,
                                   study_uid=study_uid, uid_seed=uid_seed)
            )  # fmt: skip
        dicom.write_text_atomic(tmp / PHANTOM_TRUTH, dicom.json_dumps(export.truth))


def _say_written(options: Phantom, export: _Export, offset_name: str, seconds: float) -> None:
    out, volume, pixels = Path(options.out), export.volume, options.pixels
    _say(f"wrote {out}/ in {seconds:.1f} s:")
    _say(
        f"  {PHANTOM_VOLUME_DIR}/       {volume.shape[0]} CT slices of {volume.shape[2]}x{volume.shape[1]} "
        f"({volume.label})"
    )
    _say(f"  {PHANTOM_FLUORO}    XA fluoroscopy, {pixels}x{pixels} px, {options.image_format:g} cm format")
    _say(f"  {PHANTOM_EXPOSURE}  XA exposure")
    _say(
        f"  {PHANTOM_FLUORO_B}  XA fluoroscopy of plane B (lateral, same moment as {PHANTOM_FLUORO}), "
        f"{export.geometry_b.cols}x{export.geometry_b.rows} px"
    )
    if "rotational_run_file" in export.truth["files"]:
        _say("  rotational_run.dcm  the 3DRA's rotational run (multi-frame XA, per-frame angles) + its calibration")
    _say(f"  {PHANTOM_TRUTH}      patient motion {offset_name}: {_format_offsets(export.motion, export.geometry)}")
    _say(
        f"try: roadmap3d register --volume {out / PHANTOM_VOLUME_DIR} --image {out / PHANTOM_FLUORO} "
        f"--truth {out / PHANTOM_TRUTH}"
    )
    _say(f"biplane: add --image {out / PHANTOM_FLUORO_B}")


def run_phantom_export(options: Phantom) -> int:
    """Export the phantom: DICOM 3DRA series, XA fluoro and exposure with known motion, truth JSON.

    The 3DRA series is ``volume_source`` (one of :data:`registration.sim.threedra.VOLUME_SOURCES`).
    The XA images are the analytic phantom moved by the known motion and projected with the nominal geometry that
    their positioner tags state; the FDK volume is reconstructed in the same world frame (from
    the calibrated geometry of its run), so the truth holds for either source.
    """
    _check(options)
    offset_name, offsets = parse_offset(options.offset)
    start = time.perf_counter()
    export = _simulate(options, offset_name, offsets)
    _write(options, export)
    _say_written(options, export, offset_name, time.perf_counter() - start)
    return 0
