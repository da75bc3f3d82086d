"""3DRA/CT volumes: DICOM slice series, enhanced multi-frame files, the project's ``.npz``.

Volumes (CONVENTIONS §2)
    A folder of slices (CT Image Storage and the like) is sorted by position along the slice
    normal (never by file name); orientation, pixel spacing and size must agree across slices.
    Gantry tilt and uneven slice spacing are *rejected* (not resampled) with a message. An
    enhanced multi-frame file (Enhanced CT, X-Ray 3D Angiographic) is read through its
    functional groups. RescaleSlope/RescaleIntercept give HU. ``index_to_world`` maps
    (i, j, k) = (column, row, slice) to LPS mm exactly as DICOM defines it.

Writing: a classic CT slice series, one Enhanced CT file, or the ``.npz``.
"""

from __future__ import annotations

import io
import math
import os
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import Dataset
from pydicom.uid import (
    UID,
    CTImageStorage,
    MediaStorageDirectoryStorage,
)

from registration.core.volume import Volume
from registration.io.dicom._common import (
    ENHANCED_VOLUME_CLASSES,
    IN_PLANE_TOLERANCE,
    ORIENTATION_TOLERANCE,
    POSITION_TOLERANCE_MM,
    SPACING_TOLERANCE,
    VOLUME_MODALITIES,
    XRAY_CLASSES,
    Array,
    DicomError,
    _candidate_files,
    _check_pixel_module,
    _float,
    _floats,
    _frames,
    _is_xray,
    _pixels,
    _short,
    _sop_class,
    _text,
    pixel_decoder,
    read_dataset,
    tag_name,
)
from registration.io.dicom._files import (
    _atomic_path,
)
from registration.io.dicom.limits import (
    check_affine,
    check_dataset_pixels,
    check_folder_bytes,
    check_npz_member,
    check_voxels,
)


# --------------------------------------------------------------------------------------
# Volumes
# --------------------------------------------------------------------------------------
@dataclass
class _Slice:
    source: str
    position: Array
    orientation: Array  # 6 direction cosines (row direction, column direction)
    spacing: tuple[float, float]  # PixelSpacing: (row spacing, column spacing)
    rows: int
    cols: int
    slope: float
    intercept: float
    load: Callable[[], NDArray[Any]]


def _orientation(path: Path, values: list[float]) -> Array:
    iop = np.asarray(values, dtype=np.float64)
    row, col = iop[:3], iop[3:]
    if abs(np.linalg.norm(row) - 1) > 1e-3 or abs(np.linalg.norm(col) - 1) > 1e-3 or abs(row @ col) > 1e-3:
        raise DicomError(path, f"{tag_name('ImageOrientationPatient')} is not two orthogonal unit vectors: {values}")
    row = row / np.linalg.norm(row)
    col = col - (col @ row) * row
    return np.concatenate([row, col / np.linalg.norm(col)])


def _check_alike(slices: list[_Slice]) -> None:
    """Every slice of a stack has the first's size, orientation and pixel spacing."""
    ref = slices[0]
    for s in slices[1:]:
        if (s.rows, s.cols) != (ref.rows, ref.cols):
            raise DicomError(
                s.source,
                f"{tag_name('Rows')}/{tag_name('Columns')} {s.rows}x{s.cols} differ from "
                f"{ref.rows}x{ref.cols} of {ref.source} (mixed series?)",
            )
        if np.max(np.abs(s.orientation - ref.orientation)) > ORIENTATION_TOLERANCE:
            raise DicomError(
                s.source,
                f"{tag_name('ImageOrientationPatient')} differs from {ref.source}: slices of one volume "
                "share one orientation (mixed series?)",
            )
        if np.max(np.abs(np.subtract(s.spacing, ref.spacing))) > 1e-4 * max(ref.spacing):
            raise DicomError(
                s.source, f"{tag_name('PixelSpacing')} {s.spacing} differs from {ref.spacing} of {ref.source}"
            )


def _stacked_pixels(slices: list[_Slice], source: Path) -> NDArray[np.float32]:
    """The sorted slices' values (stored * slope + intercept) as one (slices, rows, cols) array."""
    ref = slices[0]
    check_voxels(source, (len(slices), ref.rows, ref.cols), what="slices x Rows x Columns")
    data = np.empty((len(slices), ref.rows, ref.cols), dtype=np.float32)
    for k, s in enumerate(slices):
        pixels = s.load()
        if pixels.shape != (ref.rows, ref.cols):
            raise DicomError(
                s.source, f"{tag_name('PixelData')} has shape {pixels.shape}, expected {ref.rows}x{ref.cols}"
            )
        # stored values * slope + intercept, written into the stack (no temporary arrays)
        np.multiply(pixels, np.float32(s.slope), out=data[k], dtype=np.float32, casting="unsafe")
        data[k] += np.float32(s.intercept)
    return data


def _stack(slices: list[_Slice], source: Path, *, label: str, meta: dict) -> Volume:
    """Sort slices along the slice normal, check the stack and build the volume."""
    if len(slices) < 2:
        s = slices[0]
        raise DicomError(
            source,
            f"holds a single 2-D image ({s.rows} x {s.cols}), not a volume: a volume needs at least "
            "2 slices (a folder of slices or a multi-frame file)",
        )
    ref = slices[0]
    _check_alike(slices)
    row_dir, col_dir = ref.orientation[:3], ref.orientation[3:]
    normal = np.cross(row_dir, col_dir)
    along = np.array([s.position @ normal for s in slices])
    order = np.argsort(along, kind="stable")
    slices = [slices[i] for i in order]
    along = along[order]
    steps = np.diff(along)
    if np.any(steps < POSITION_TOLERANCE_MM):
        i = int(np.argmin(steps))
        raise DicomError(
            source,
            f"two slices at the same {tag_name('ImagePositionPatient')} ({slices[i].source} and "
            f"{slices[i + 1].source}): several series, time points or echoes mixed?",
        )
    # Fit along = start + k * step; every slice must sit on that line.
    k = np.arange(len(slices), dtype=np.float64)
    step, start = (float(v) for v in np.polyfit(k, along, 1))
    if np.max(np.abs(along - (start + k * step))) > POSITION_TOLERANCE_MM + SPACING_TOLERANCE * step:
        raise DicomError(
            source,
            f"uneven slice spacing along the slice normal ({tag_name('ImagePositionPatient')}): steps from "
            f"{steps.min():.4g} to {steps.max():.4g} mm (a missing slice?); uneven stacks are rejected, "
            "not resampled",
        )
    first = slices[0].position
    lateral = np.array([s.position - first for s in slices]) - np.outer(along - along[0], normal)
    if np.max(np.linalg.norm(lateral, axis=1)) > POSITION_TOLERANCE_MM + IN_PLANE_TOLERANCE * min(ref.spacing):
        tilt = math.degrees(math.atan2(float(np.linalg.norm(lateral[-1])), float(along[-1] - along[0])))
        raise DicomError(
            source,
            f"slices are shifted within their plane along the stack ({tag_name('ImagePositionPatient')}, "
            f"gantry tilt of about {tilt:.2f} deg); tilted stacks are rejected, not resampled",
        )
    data = _stacked_pixels(slices, source)
    affine = np.eye(4)
    affine[:3, 0] = row_dir * ref.spacing[1]  # i: along a row (increasing column index)
    affine[:3, 1] = col_dir * ref.spacing[0]  # j: down a column (increasing row index)
    affine[:3, 2] = normal * step
    affine[:3, 3] = first + (start - along[0]) * normal
    meta = dict(meta, slices=len(slices), slice_spacing_mm=step, pixel_spacing_mm=list(ref.spacing))
    try:
        return Volume(data=data, index_to_world=affine, label=label, meta=meta)
    except ValueError as exc:
        raise DicomError(source, str(exc)) from None


def _check_volume_modality(path: Path, ds: Dataset) -> None:
    sop = _sop_class(ds)
    modality = _text(ds, "Modality").upper()
    if sop in XRAY_CLASSES:
        raise DicomError(
            path,
            f"is an {XRAY_CLASSES[sop]} projection image ({tag_name('SOPClassUID')}), not a volume: "
            "give it as the X-ray image (--image)",
        )
    if sop in ENHANCED_VOLUME_CLASSES or sop == CTImageStorage:
        return
    if modality not in VOLUME_MODALITIES:
        name = UID(sop).name if sop else "unknown class"
        raise DicomError(
            path,
            f"wrong modality: {tag_name('Modality')} is {modality or 'missing'} ({name}); the registration "
            "needs a volume in Hounsfield units (CT or 3DRA)",
        )


def _hu_slope(path: Path, slope: float) -> float:
    """A volume's RescaleSlope: HU grow with the stored values, so it must be positive."""
    if slope <= 0:
        raise DicomError(
            path,
            f"{tag_name('RescaleSlope')} is {slope:g}: a volume in Hounsfield units needs a positive slope "
            "(0 makes every voxel equal, a negative one inverts bone and air)",
        )
    return slope


def _slice_from_dataset(path: Path, ds: Dataset) -> _Slice:
    rows, cols = _check_pixel_module(path, ds, 1)
    check_dataset_pixels(path, ds, 1)
    iop = _orientation(path, _floats(path, ds, "ImageOrientationPatient", 6) or [])
    ipp = np.asarray(_floats(path, ds, "ImagePositionPatient", 3), dtype=np.float64)
    spacing = _floats(path, ds, "PixelSpacing", 2) or []
    if min(spacing) <= 0:
        raise DicomError(path, f"{tag_name('PixelSpacing')} must be positive, got {spacing}")
    slope = _hu_slope(path, _float(path, ds, "RescaleSlope", default=1.0))
    intercept = _float(path, ds, "RescaleIntercept", default=0.0)
    return _Slice(
        source=str(path),
        position=ipp,
        orientation=iop,
        spacing=(spacing[0], spacing[1]),
        rows=rows,
        cols=cols,
        slope=slope,
        intercept=intercept,
        load=lambda: _pixels(path, ds),
    )


def _enhanced_volume(path: Path, ds: Dataset, *, label: str | None) -> Volume:
    frames = _frames(path, ds)
    rows, cols = _check_pixel_module(path, ds, frames)
    check_dataset_pixels(path, ds, frames)  # before the loop over the frames
    if "PerFrameFunctionalGroupsSequence" not in ds and "SharedFunctionalGroupsSequence" not in ds:
        raise DicomError(
            path,
            f"multi-frame file without {tag_name('PerFrameFunctionalGroupsSequence')}: the slice positions are unknown",
        )
    per_frame = ds.get("PerFrameFunctionalGroupsSequence") or []
    if len(per_frame) not in (0, frames):
        raise DicomError(
            path,
            f"{tag_name('PerFrameFunctionalGroupsSequence')} has {len(per_frame)} items for {frames} frames",
        )
    cache: dict[str, NDArray[Any]] = {}

    def frame_loader(n: int) -> Callable[[], NDArray[Any]]:
        def load() -> NDArray[Any]:
            if "all" not in cache:
                pixels = _pixels(path, ds)
                if pixels.size != frames * rows * cols:
                    raise DicomError(
                        path,
                        f"{tag_name('PixelData')} decodes to {pixels.size:,} values ({pixels.shape}), but "
                        f"{tag_name('NumberOfFrames')} x {tag_name('Rows')} x {tag_name('Columns')} is "
                        f"{frames} x {rows} x {cols}",
                    )
                cache["all"] = pixels.reshape(frames, rows, cols)
            return cache["all"][n]

        return load

    slices = []
    for n in range(frames):
        where = f"{path} frame {n}"
        iop = _orientation(Path(where), _floats(Path(where), ds, "ImageOrientationPatient", 6, n) or [])
        ipp = np.asarray(_floats(Path(where), ds, "ImagePositionPatient", 3, n), dtype=np.float64)
        spacing = _floats(Path(where), ds, "PixelSpacing", 2, n) or []
        if min(spacing) <= 0:
            raise DicomError(where, f"{tag_name('PixelSpacing')} must be positive, got {spacing}")
        slices.append(
            _Slice(
                source=where,
                position=ipp,
                orientation=iop,
                spacing=(spacing[0], spacing[1]),
                rows=rows,
                cols=cols,
                slope=_hu_slope(Path(where), _float(path, ds, "RescaleSlope", n, default=1.0)),
                intercept=_float(path, ds, "RescaleIntercept", n, default=0.0),
                load=frame_loader(n),
            )
        )
    kind = ENHANCED_VOLUME_CLASSES.get(_sop_class(ds), "multi-frame")
    meta = _volume_meta(path, ds, kind)
    return _stack(slices, path, label=label or _volume_label(ds, path, kind), meta=meta)


def _volume_label(ds: Dataset, path: Path, kind: str) -> str:
    derivation = _text(ds, "DerivationDescription")
    if derivation:
        return derivation
    description = _text(ds, "SeriesDescription")
    modality = _text(ds, "Modality") or "?"
    return f"{modality} {kind} '{description}' ({path.name})"


def _volume_meta(path: Path, ds: Dataset, kind: str) -> dict:
    return {
        **_isocenter_meta(path, ds),
        "source": str(path),
        "format": kind,
        "modality": _text(ds, "Modality"),
        "sop_class": _sop_class(ds),
        "series_uid": _text(ds, "SeriesInstanceUID"),
        "frame_of_reference_uid": _text(ds, "FrameOfReferenceUID"),
        "series_description": _text(ds, "SeriesDescription"),
        "decoder": pixel_decoder(ds)[1],
        **_reference_meta(ds),
    }


def _isocenter_meta(path: Path, ds: Dataset) -> dict:
    """IsocenterPosition (300A,012C), in patient coordinates (mm), where the files carry it.

    Radiotherapy exports carry it; angiography 3DRA volumes do not (their systems place the
    iso-center at the patient-coordinate origin, the project's default, CONVENTIONS §1).
    """
    iso = _floats(path, ds, "IsocenterPosition", 3, required=False)
    if iso is None:
        return {}
    return {"isocenter_mm": iso, "isocenter_from": f"{tag_name('IsocenterPosition')} of the volume"}


def _reference_meta(ds: Dataset) -> dict:
    """What a Spatial Registration object needs to reference this data (patient, study, instance)."""
    return {
        "study_uid": _text(ds, "StudyInstanceUID"),
        "patient_name": _text(ds, "PatientName"),
        "patient_id": _text(ds, "PatientID"),
        "instances": [[_sop_class(ds), _text(ds, "SOPInstanceUID")]] if _text(ds, "SOPInstanceUID") else [],
    }


def read_series(folder: str | os.PathLike[str], *, label: str | None = None) -> Volume:
    """A volume from a folder of single-frame slices (or holding one multi-frame file)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DicomError(folder, "not a folder")
    datasets: list[tuple[Path, Dataset]] = []
    skipped: list[str] = []
    candidates = _candidate_files(folder)
    check_folder_bytes(folder, candidates)  # before any file is read into memory
    for p in candidates:
        try:
            ds = read_dataset(p)
        except DicomError as exc:
            skipped.append(str(exc))
            continue
        if _sop_class(ds) == MediaStorageDirectoryStorage:
            continue
        datasets.append((p, ds))
    if not datasets:
        why = f" ({skipped[0]})" if skipped else ""
        raise DicomError(folder, f"no DICOM files in the folder{why}")
    projections = [(p, ds) for p, ds in datasets if _is_xray(ds)]
    if len(projections) == len(datasets):
        _check_volume_modality(*projections[0])  # raises: a projection image is not a volume
    if projections:  # an XA/RF file beside the slices (an upload holding both): not a slice
        datasets = [(p, ds) for p, ds in datasets if not _is_xray(ds)]
        skipped += [f"{p}: {XRAY_CLASSES.get(_sop_class(ds), 'X-ray')} projection image" for p, ds in projections]
    by_series: dict[str, list[tuple[Path, Dataset]]] = {}
    for p, ds in datasets:
        by_series.setdefault(_text(ds, "SeriesInstanceUID") or "(no SeriesInstanceUID)", []).append((p, ds))
    if len(by_series) > 1:
        parts = ", ".join(
            f"{len(v)} file(s) of {_text(v[0][1], 'Modality') or '?'} '{_text(v[0][1], 'SeriesDescription')}'"
            for v in by_series.values()
        )
        raise DicomError(
            folder,
            f"mixed series: {len(by_series)} different {tag_name('SeriesInstanceUID')} values ({parts}); "
            "give the folder of one series",
        )
    for p, ds in datasets:
        _check_volume_modality(p, ds)
    modalities = sorted({_text(ds, "Modality").upper() or "?" for _p, ds in datasets})
    if len(modalities) > 1:  # e.g. Modality XA slices inside a CT series
        raise DicomError(
            folder,
            f"one series with several {tag_name('Modality')} values ({', '.join(modalities)}): slices of one "
            "volume share one modality",
        )
    if len(datasets) == 1 and _frames(*datasets[0]) > 1:
        return _enhanced_volume(datasets[0][0], datasets[0][1], label=label)
    for p, ds in datasets:
        if _frames(p, ds) > 1:
            raise DicomError(p, f"multi-frame file ({tag_name('NumberOfFrames')}) mixed with single slices")
    slices = [_slice_from_dataset(p, ds) for p, ds in datasets]
    first = datasets[0][1]
    meta = _volume_meta(folder, first, "slice series")
    meta["skipped_files"] = skipped[:20]
    meta["instances"] = [[_sop_class(ds), _text(ds, "SOPInstanceUID")] for _, ds in datasets if "SOPInstanceUID" in ds]
    return _stack(slices, folder, label=label or _volume_label(first, folder, "series"), meta=meta)


def read_npz(path: str | os.PathLike[str]) -> Volume:
    """The project's volume file: arrays ``data`` (k, j, i), ``index_to_world`` (4x4), ``label``.

    Shapes and dtypes come from the members' ``.npy`` headers and are checked against the
    ceilings of :mod:`registration.io.dicom.limits` before anything is inflated.
    """
    path = Path(path)
    if not path.exists():
        raise DicomError(path, "no such file")
    if not path.is_file():
        raise DicomError(path, "not a regular file")
    try:
        with zipfile.ZipFile(path) as archive:
            names = set(archive.namelist())
            missing = [k for k in ("data", "index_to_world") if f"{k}.npy" not in names]
            if missing:
                raise DicomError(path, f"missing array(s) {', '.join(missing)} in the .npz volume")
            shape, _dtype = check_npz_member(path, archive, "data")
            if len(shape) != 3:
                raise DicomError(path, f"array 'data' has shape {shape}: a volume has 3 axes (k, j, i)")
            affine_shape, _ = check_npz_member(path, archive, "index_to_world")
            if affine_shape != (4, 4):
                raise DicomError(path, f"array 'index_to_world' has shape {affine_shape}, expected (4, 4)")
            if "label.npy" in names:
                label_shape, label_dtype = check_npz_member(path, archive, "label")
                if label_shape != () or label_dtype.itemsize > 4 * 4096:
                    raise DicomError(path, f"array 'label' must be one short string, got {label_shape} {label_dtype}")
        with np.load(path, allow_pickle=False) as npz:
            data = np.asarray(npz["data"])
            affine = np.asarray(npz["index_to_world"], dtype=np.float64)
            label = str(npz["label"]) if "label" in npz.files else path.name
        check_affine(path, affine)
    except DicomError:
        raise
    except FileNotFoundError:
        raise DicomError(path, "no such file") from None
    except Exception as exc:
        raise DicomError(path, f"not a readable .npz volume ({type(exc).__name__}: {_short(exc)})") from None
    try:
        return Volume(data=data, index_to_world=affine, label=label, meta={"source": str(path), "format": "npz"})
    except (ValueError, TypeError, ArithmeticError) as exc:
        raise DicomError(path, f"not a usable volume: {_short(exc)}") from None


def read_volume(path: str | os.PathLike[str], *, label: str | None = None) -> Volume:
    """A volume from a DICOM folder, an enhanced multi-frame file, the project's ``.npz``, or a
    NIfTI, NRRD or MetaImage file (:mod:`registration.io.volume_files`, CONVENTIONS §8)."""
    path = Path(path)
    if not path.exists():
        raise DicomError(path, "no such file or folder")
    from registration.io.volume_files import read_volume_file, volume_format

    if path.is_file() and volume_format(path) is not None:
        return read_volume_file(path, label=label)
    if path.is_dir():
        return read_series(path, label=label)
    if path.suffix.lower() == ".npz":
        volume = read_npz(path)
        return volume if label is None else volume.with_data(volume.data, label=label)
    ds = read_dataset(path)
    _check_volume_modality(path, ds)
    if _frames(path, ds) > 1:
        return _enhanced_volume(path, ds, label=label)
    return _stack([_slice_from_dataset(path, ds)], path, label="", meta={})


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
def write_npz(volume: Volume, path: str | os.PathLike[str]) -> Path:
    """The project's volume file (``data``, ``index_to_world``, ``label``), written atomically."""
    path = Path(path)
    buffer = io.BytesIO()
    np.savez_compressed(
        buffer,
        data=volume.data.astype(np.float32),
        index_to_world=volume.index_to_world,
        label=np.array(volume.label),
    )
    with _atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getvalue())
    return path
