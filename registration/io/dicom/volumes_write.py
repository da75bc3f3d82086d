"""Writing a volume as DICOM: a classic CT slice series or one Enhanced CT multi-frame file, int16
HU, written whole or not at all (read back by :mod:`registration.io.dicom.volumes`)."""

from __future__ import annotations

import os
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence as DicomSequence
from pydicom.uid import (
    UID,
    CTImageStorage,
    EnhancedCTImageStorage,
)

from registration.core.volume import Volume
from registration.io.dicom._common import (
    Array,
    _base,
    _ds_number,
    _save,
    make_uid,
)
from registration.io.dicom._files import (
    _atomic_path,
    atomic_folder,
)


def _volume_axes(volume: Volume) -> tuple[Array, Array, Array, tuple[float, float], float]:
    a = volume.index_to_world[:3, :3]
    spacing = np.linalg.norm(a, axis=0)
    row_dir, col_dir, k_axis = a[:, 0] / spacing[0], a[:, 1] / spacing[1], a[:, 2] / spacing[2]
    if abs(row_dir @ col_dir) > 1e-6:
        raise ValueError("the volume's i and j axes are not orthogonal: it cannot be written as DICOM slices")
    normal = np.cross(row_dir, col_dir)
    if abs(abs(k_axis @ normal) - 1.0) > 1e-6:
        raise ValueError("the volume's slice axis is not perpendicular to its slices (sheared/tilted affine)")
    return row_dir, col_dir, normal, (float(spacing[1]), float(spacing[0])), float(spacing[2])


def _hu_to_int16(data: NDArray[np.float32]) -> NDArray[np.int16]:
    return np.clip(np.rint(data), -32768, 32767).astype(np.int16)


def _slice_attributes(
    ds: Dataset, volume: Volume, k: int, position: Array, frame_of_reference: str, axes: tuple[Array, Array, Array],
    pixel_spacing: tuple[float, float], slice_mm: float,
) -> None:  # fmt: skip
    """Slice k's frame, position, orientation, spacing and pixel description (int16 HU)."""
    row_dir, col_dir, _normal = axes
    nk, nj, ni = volume.shape
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
    if volume.label:
        ds.DerivationDescription = volume.label[:1024]
    ds.FrameOfReferenceUID = frame_of_reference
    ds.PositionReferenceIndicator = ""
    ds.InstanceNumber = k + 1
    ds.ImagePositionPatient = [_ds_number(v) for v in position[:3]]
    ds.ImageOrientationPatient = [_ds_number(v) for v in (*row_dir, *col_dir)]
    ds.PixelSpacing = [_ds_number(pixel_spacing[0]), _ds_number(pixel_spacing[1])]
    ds.SliceThickness = _ds_number(slice_mm)
    ds.SpacingBetweenSlices = _ds_number(slice_mm)
    ds.SliceLocation = _ds_number(float(position[:3] @ _normal))
    ds.KVP = "90"
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = nj, ni
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 1
    ds.RescaleIntercept = "0"
    ds.RescaleSlope = "1"
    ds.RescaleType = "HU"
    ds.WindowCenter, ds.WindowWidth = "300", "1500"


def write_series(
    volume: Volume,
    folder: str | os.PathLike[str],
    *,
    modality: str = "CT",
    description: str | None = None,
    study_uid: str | None = None,
    uid_seed: str | None = None,
    patient_name: str = "roadmap3d^phantom",
    patient_id: str = "ROADMAP3D",
) -> list[Path]:
    """Write ``volume`` as a classic CT Image Storage slice series into ``folder`` (new or empty).

    Values are HU rounded to int16 (RescaleSlope 1, RescaleIntercept 0, RescaleType HU), so
    they read back within 0.5 HU. Slice k goes to ``slice_{k:04d}.dcm`` at
    ``index_to_world @ (0, 0, k, 1)``. The folder appears only when every slice is written.
    """
    row_dir, col_dir, _normal, pixel_spacing, slice_mm = _volume_axes(volume)
    study = UID(study_uid) if study_uid else make_uid(uid_seed, "study")
    series = make_uid(uid_seed, "series", volume.label)
    frame_of_reference = make_uid(uid_seed, "frame of reference")
    description = description or (volume.label or "roadmap3d volume")[:64]
    nk, nj, ni = volume.shape
    pixels = _hu_to_int16(volume.data)
    written: list[Path] = []
    with atomic_folder(folder) as tmp:
        for k in range(nk):
            position = volume.index_to_world @ np.array([0.0, 0.0, float(k), 1.0])
            ds = _base(
                CTImageStorage,
                modality,
                study_uid=study,
                series_uid=series,
                instance_uid=make_uid(uid_seed, "slice", k, volume.label),
                series_number=1,
                description=description[:64],
                patient_name=patient_name,
                patient_id=patient_id,
            )
            _slice_attributes(ds, volume, k, position, frame_of_reference, (row_dir, col_dir, _normal),
                              pixel_spacing, slice_mm)  # fmt: skip
            ds.PixelData = np.ascontiguousarray(pixels[k]).tobytes()
            name = f"slice_{k:04d}.dcm"
            _save(ds, tmp / name)
            written.append(Path(folder) / name)
    return written


def _shared_groups(row_dir: Array, col_dir: Array, pixel_spacing: tuple[float, float], slice_mm: float) -> Dataset:
    """What every frame of the Enhanced CT shares: pixel measures, orientation, HU rescaling, frame type."""
    shared = Dataset()
    measures = Dataset()
    measures.PixelSpacing = [_ds_number(pixel_spacing[0]), _ds_number(pixel_spacing[1])]
    measures.SliceThickness = _ds_number(slice_mm)
    measures.SpacingBetweenSlices = _ds_number(slice_mm)
    shared.PixelMeasuresSequence = DicomSequence([measures])
    orientation = Dataset()
    orientation.ImageOrientationPatient = [_ds_number(v) for v in (*row_dir, *col_dir)]
    shared.PlaneOrientationSequence = DicomSequence([orientation])
    transform = Dataset()
    transform.RescaleIntercept = "0"
    transform.RescaleSlope = "1"
    transform.RescaleType = "HU"
    shared.PixelValueTransformationSequence = DicomSequence([transform])
    frame_type = Dataset()
    frame_type.FrameType = ["DERIVED", "SECONDARY", "VOLUME", "NONE"]
    shared.CTImageFrameTypeSequence = DicomSequence([frame_type])
    return shared


def _frame_group(volume: Volume, k: int) -> Dataset:
    """Frame k's own group: the slice's position and its place in the stack."""
    item = Dataset()
    position = Dataset()
    position.ImagePositionPatient = [
        _ds_number(v) for v in (volume.index_to_world @ np.array([0.0, 0.0, float(k), 1.0]))[:3]
    ]
    item.PlanePositionSequence = DicomSequence([position])
    content = Dataset()
    content.InStackPositionNumber = k + 1
    content.StackID = "1"
    content.DimensionIndexValues = [1, k + 1]
    item.FrameContentSequence = DicomSequence([content])
    return item


def write_enhanced(
    volume: Volume,
    path: str | os.PathLike[str],
    *,
    description: str | None = None,
    study_uid: str | None = None,
    uid_seed: str | None = None,
    patient_name: str = "roadmap3d^phantom",
    patient_id: str = "ROADMAP3D",
) -> Path:
    """Write ``volume`` as one Enhanced CT multi-frame file (frame k = slice k), int16 HU."""
    row_dir, col_dir, _normal, pixel_spacing, slice_mm = _volume_axes(volume)
    nk, nj, ni = volume.shape
    study = UID(study_uid) if study_uid else make_uid(uid_seed, "study")
    ds = _base(
        EnhancedCTImageStorage,
        "CT",
        study_uid=study,
        series_uid=make_uid(uid_seed, "enh series"),
        instance_uid=make_uid(uid_seed, "enh instance"),
        series_number=2,
        description=(description or volume.label or "roadmap3d volume")[:64],
        patient_name=patient_name,
        patient_id=patient_id,
    )
    ds.ImageType = ["DERIVED", "SECONDARY", "VOLUME", "NONE"]
    if volume.label:
        ds.DerivationDescription = volume.label[:1024]
    ds.FrameOfReferenceUID = make_uid(uid_seed, "frame of reference")
    ds.PositionReferenceIndicator = ""
    ds.InstanceNumber = 1
    ds.ContentQualification = "RESEARCH"
    ds.AcquisitionDateTime = datetime.now(UTC).strftime("%Y%m%d%H%M%S")
    ds.BurnedInAnnotation = "NO"
    ds.NumberOfFrames = nk
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = nj, ni
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 1
    ds.PresentationLUTShape = "IDENTITY"
    ds.LossyImageCompression = "00"
    ds.SharedFunctionalGroupsSequence = DicomSequence([_shared_groups(row_dir, col_dir, pixel_spacing, slice_mm)])
    ds.PerFrameFunctionalGroupsSequence = DicomSequence([_frame_group(volume, k) for k in range(nk)])
    ds.PixelData = _hu_to_int16(volume.data).tobytes()
    path = Path(path)
    with _atomic_path(path) as tmp:
        _save(ds, tmp)
    return path
