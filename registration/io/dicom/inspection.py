"""What the project reads from a file or folder, for ``roadmap3d info``."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import Dataset
from pydicom.uid import (
    UID,
)

from registration.core.volume import Volume
from registration.io.dicom._common import (
    DicomError,
    _frames,
    _is_xray,
    _sop_class,
    _text,
    _transfer_syntax,
    pixel_decoder,
    read_dataset,
)
from registration.io.dicom.runs import frame_times
from registration.io.dicom.volumes import read_volume
from registration.io.dicom.xray import field_summary, intensity_assumed, read_xray, read_xray_angles, xray_field


def _range(values: NDArray[Any]) -> list[float]:
    return [float(np.min(values)), float(np.max(values))] if values.size else []


#: Header tags that ``inspect`` shows when present (what the readers look at).
HEADER_TAGS = (
    "Rows",
    "Columns",
    "NumberOfFrames",
    "PixelSpacing",
    "ImagerPixelSpacing",
    "ImagePositionPatient",
    "ImageOrientationPatient",
    "RescaleSlope",
    "RescaleIntercept",
    "PositionerPrimaryAngle",
    "PositionerSecondaryAngle",
    "DistanceSourceToDetector",
    "DistanceSourceToPatient",
    "PixelIntensityRelationship",
    "PixelIntensityRelationshipSign",
    "ShutterShape",
)


def inspect(
    path: str | os.PathLike[str],
    *,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    image_mask: str | os.PathLike[str] | None = None,
    pixel_mm: float | None = None,
) -> dict[str, Any]:
    """What the project reads from ``path``: kind, geometry, shape, spacing, value range.

    ``sid_mm`` / ``sod_mm`` supply the distances of X-ray images that lack them (as for
    :func:`registration.io.dicom.read_xray`); ``image_mask`` is the user's field mask of an
    X-ray image.

    Never raises for bad input: the result says ``accepted: False`` and gives the ``problem``;
    for a DICOM file the ``header`` entry lists the tags the readers look at.
    """
    path = Path(path)
    out: dict[str, Any] = {"path": str(path)}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            from registration.io.image_files import is_image_file
            from registration.io.volume_files import volume_format

            if path.is_dir() or path.suffix.lower() == ".npz" or volume_format(path) is not None:
                out.update(_inspect_volume(read_volume(path)))
            elif is_image_file(path):
                out.update(_inspect_image_file(path, sid_mm=sid_mm, sod_mm=sod_mm))
            else:
                ds = read_dataset(path, stop_before_pixels=True)
                out["sop_class"] = UID(_sop_class(ds)).name if _sop_class(ds) else ""
                out["modality"] = _text(ds, "Modality")
                ts = _transfer_syntax(ds)
                out["transfer_syntax"] = ts.name if ts is not None else ""
                out["decoder"] = pixel_decoder(ds)[1]
                out["header"] = {k: _text(ds, k) for k in HEADER_TAGS if _text(ds, k)}
                if _is_xray(ds):
                    out.update(
                        _inspect_xray(path, ds, sid_mm=sid_mm, sod_mm=sod_mm, image_mask=image_mask, pixel_mm=pixel_mm)
                    )
                else:
                    out.update(_inspect_volume(read_volume(path)))
            out["accepted"] = True
        except (ValueError, OSError) as exc:
            out["accepted"] = False
            out["problem"] = str(exc)
            if out.get("header") is not None and "kind" not in out and _xray_header(path):
                out.update(_inspect_xray_without_geometry(path, str(exc), image_mask))
    out["warnings"] = sorted({str(w.message) for w in caught})
    return out


def _xray_header(path: Path) -> bool:
    try:
        return _is_xray(read_dataset(path, stop_before_pixels=True))
    except (ValueError, OSError):
        return False


def _inspect_volume(volume: Volume) -> dict[str, Any]:
    nk, nj, ni = volume.shape
    return {
        "kind": "volume",
        "format": volume.meta.get("format", ""),
        "label": volume.label,
        "shape_kji": [nk, nj, ni],
        "spacing_mm_ijk": [round(float(s), 6) for s in volume.spacing_mm],
        "index_to_world": np.round(volume.index_to_world, 6).tolist(),
        "center_mm": [round(float(c), 3) for c in volume.center_mm],
        "value_range_hu": [round(v, 1) for v in _range(volume.data)],
        **({"decoder": volume.meta["decoder"]} if volume.meta.get("decoder") else {}),
        **({"orientation_from": volume.meta["orientation_from"]} if volume.meta.get("orientation_from") else {}),
    }


def _inspect_image_file(path: Path, *, sid_mm: float | None = None, sod_mm: float | None = None) -> dict[str, Any]:
    """A TIFF/PNG X-ray image with its geometry side file (registration.io.image_files)."""
    image = read_xray(path, sid_mm=sid_mm, sod_mm=sod_mm)
    return {
        "kind": "xray",
        "format": image.meta.get("format", ""),
        "geometry_from": image.meta.get("geometry_from"),
        "pixel_values": image.meta.get("pixel_values"),
        "geometry": image.geometry.to_dict(),
        "field_pixels": int(image.mask.sum()),
        "mask_from": image.meta.get("mask_from"),
        "attenuation_range": [round(v, 4) for v in _range(image.image[image.mask])],
    }


#: Where an X-ray image's geometry came from, shown by ``info``.
_GEOMETRY_SOURCES = ("sid_from", "sod_from", "field_rotation", "field_of_view_origin")


def _field_report(field: dict[str, Any]) -> dict[str, Any]:
    """The field's entries of the report: how it was found, what was masked, how much is usable."""
    if not field:
        return {}
    out: dict[str, Any] = {
        "field": f"{field.get('found_by', '')}; {field.get('usable_pixels', 0)} pixels usable "
        f"({100.0 * field.get('usable_fraction', 0.0):.1f} % of the image)"
    }
    lines = field_summary(field)
    if lines:
        out["field_masked"] = "; ".join(lines)
    return out


def _inspect_xray_without_geometry(
    path: Path, problem: str, image_mask: str | os.PathLike[str] | None = None
) -> dict[str, Any]:
    """What can be said of an X-ray image whose geometry is missing: its field and intensities."""
    try:
        mask, field, intensity = xray_field(path, image_mask=image_mask)
    except (ValueError, OSError):
        return {}
    return {
        "kind": "xray",
        "field_pixels": int(mask.sum()),
        **_field_report(field),
        "intensity_assumed": intensity_assumed(intensity),
        "geometry": f"not usable: {problem}",
    }


def _inspect_xray(
    path: Path,
    header: Dataset,
    *,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_mm: float | None = None,
    image_mask: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    frames = _frames(path, header)
    image = read_xray(path, frame=0, sid_mm=sid_mm, sod_mm=sod_mm, image_mask=image_mask, pixel_mm=pixel_mm)
    sign = image.meta.get("pixel_intensity_relationship_sign")
    out: dict[str, Any] = {
        "kind": "xray",
        "format": image.meta.get("format", ""),
        "image_kind": image.kind,
        "frames": frames,
        "geometry": image.geometry.to_dict(),
        "field_pixels": int(image.mask.sum()),
        "mask_from": image.meta.get("mask_from"),
        **_field_report(image.meta.get("field") or {}),
        "intensity": f"{image.meta.get('pixel_intensity_relationship')}, sign {sign:+d}",
        "intensity_assumed": intensity_assumed(image.meta),
        "attenuation_range": [round(v, 4) for v in _range(image.image[image.mask])],
        "decoder": image.meta.get("decoder", ""),
        "plane": image.meta.get("plane") or "not stated (PlaneIdentification 0018,9457 absent)",
        "acquired": image.meta.get("acquisition_datetime") or "not stated",
        **{k: image.meta[k] for k in _GEOMETRY_SOURCES if k in image.meta},
    }
    if frames > 1:
        angles = read_xray_angles(path)
        out["angles_deg"] = [[round(a, 3), round(b, 3)] for a, b in angles[:12]] + (["..."] if frames > 12 else [])
        try:
            times, source = frame_times(path, header, frames)
            out["frame_times"] = f"{times[-1]:.3f} s over {frames} frames, from {source}"
        except DicomError as exc:
            out["frame_times"] = f"not stated ({exc})"
    return out
