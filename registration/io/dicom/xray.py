"""XA/RF projection images: reading (the geometry in :mod:`.xray_geometry`, the intensities in
:mod:`.xray_intensity`, the field mask here); writing in :mod:`.xray_write`.

X-ray images (CONVENTIONS §3, §5)
    XA and RF, single or multi-frame, classic or enhanced. The C-arm comes from
    PositionerPrimaryAngle, PositionerSecondaryAngle, DistanceSourceToDetector,
    DistanceSourceToPatient and ImagerPixelSpacing (PixelSpacing as a fallback, with a
    warning). Per-frame angles of a classic multi-frame image follow DICOM C.8.7.5.1.3: a
    single increment value is the constant change per frame (angle_n = angle + n * inc); a
    vector is the offset of each frame from the (initial) angle (angle_n = angle + inc[n]).

    Intensities become attenuation line integrals (larger = more attenuation). With
    ``m = RescaleSlope * stored + RescaleIntercept`` (slope 1, intercept 0 when absent),
    ``m_max`` the largest representable ``m`` (from BitsStored), and ``a = m`` for sign -1
    (higher values = less X-ray intensity) or ``a = m_max - m`` for sign +1 (lower values =
    less intensity), so that ``a`` grows with attenuation:

    * LOG: ``attenuation = (a - LOG_ZERO_VALUE) / LOG_UNITS_PER_ATTENUATION``
    * LIN: intensity ``I = m_max - a``; ``attenuation = ln(I_ref / max(I, 1))`` with ``I_ref``
      the largest ``I`` in the field.

    (DISP, or a missing relationship, is read as LOG with a warning.) The project writes
    LOG, sign +1 (vessels and bone dark, as viewers show XA), 16-bit unsigned pixels
    ``65535 - LOG_ZERO_VALUE - round(LOG_UNITS_PER_ATTENUATION * attenuation)`` clipped to
    1..65535 (attenuation -1 .. 64.5: the quantum noise of air, slightly below zero,
    survives), and 0 outside the collimated field (no X-ray intensity behind the collimator),
    so its files read back within 0.5 / LOG_UNITS_PER_ATTENUATION.
    For other software's LOG images the scale of the logarithm is not stored in DICOM; the
    result is then attenuation in units of 1/1000 of a stored step, which the similarity
    measure (gradient difference fits an intensity scale) does not mind.

    The field mask (pixels that carry signal) is the intersection of the shutter and collimator
    tags (:mod:`registration.io.dicom.shutters`: rectangular, circular, polygonal, per frame),
    what :func:`registration.io.field.find_field` finds in the pixels (the collimated outside,
    collimator blades, burned-in text and rulers), the complement of the overlay planes'
    graphics and the user's own mask (``image_mask``). ``meta["field"]`` says what was found.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydicom.dataset import Dataset
from pydicom.uid import (
    UID,
)

from registration.io.dicom._common import (
    ENHANCED_VOLUME_CLASSES,
    XRAY_CLASSES,
    DicomError,
    _check_pixel_module,
    _frames,
    _pixels,
    _sop_class,
    _text,
    lookup,
    pixel_decoder,
    read_dataset,
    tag_name,
)
from registration.io.dicom.limits import check_dataset_pixels, check_frame_count
from registration.io.dicom.shutters import overlay_graphics, shutter_field, shutter_text
from registration.io.dicom.xray_geometry import (
    _field_of_view,
    _field_rotation,
    _frame_angles,
    _geometry,
    _undo_field_of_view,
)
from registration.io.dicom.xray_intensity import _intensity_to_attenuation

#: Plane Identification (0018,9457) values (CONVENTIONS §6).
PLANES = ("MONOPLANE", "PLANE A", "PLANE B")

if TYPE_CHECKING:
    from registration.core.images import XRayImage


def _xray_kind(ds: Dataset, kind: str | None) -> tuple[str, str]:
    """The XRayImage kind and the acquisition type guessed from the header."""
    from registration.core.images import IMAGE_KINDS

    if _text(ds, "Modality").upper() == "RF" or "FLUORO" in _text(ds, "ImageType").upper():
        acquisition = "fluoro"
    else:
        acquisition = "exposure"
    if kind is not None:
        if kind not in IMAGE_KINDS:
            raise ValueError(f"kind must be one of {IMAGE_KINDS}, got {kind!r}")
        return kind, acquisition
    comments = (_text(ds, "ImageComments") + " " + _text(ds, "SeriesDescription")).lower()
    for name in IMAGE_KINDS:
        if f"roadmap3d {name}" in comments:  # written by the project
            return name, name
    return "dicom", acquisition


def read_xray(
    path: str | os.PathLike[str],
    *,
    frame: int | None = None,
    isocenter_mm: ArrayLike = (0.0, 0.0, 0.0),
    kind: str | None = None,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    geometry: str | os.PathLike[str] | dict | None = None,
    image_mask: str | os.PathLike[str] | None = None,
    pixel_mm: float | None = None,
) -> XRayImage:
    """An XA/RF image (one frame) as attenuation line integrals with its field mask and C-arm.

    A TIFF or PNG file is read by :func:`registration.io.image_files.read_image_file` with its
    ``geometry`` side file (default ``<image>.json``); ``frame`` and ``kind`` do not apply.

    ``frame`` is 0-based; a multi-frame file read without it gives frame 0 and a warning.
    ``isocenter_mm`` places the iso-center (default: the world origin, CONVENTIONS §1).
    ``sid_mm`` / ``sod_mm`` supply the source-detector and source-iso-center distances for
    files that lack DistanceSourceToDetector / DistanceSourceToPatient; given for a file that
    has them, they replace the file's values (with a warning when they differ); ``pixel_mm`` does
    the same for ImagerPixelSpacing (square pixels at the detector).
    ``image_mask``: the user's own field mask, a PNG or TIFF of the image's stored size
    (nonzero = usable), intersected with the field the file and its pixels give.
    A whole run (all frames, their times) is read by :func:`registration.io.dicom.read_xray_run`.
    """
    path = Path(path)
    iso = _check_isocenter(isocenter_mm)
    from registration.io.image_files import is_image_file, read_image_file

    if is_image_file(path):
        if frame not in (None, 0):
            raise DicomError(path, f"frame {frame}: a TIFF/PNG image is one frame")
        image = read_image_file(path, geometry=geometry, isocenter_mm=iso, sid_mm=sid_mm, sod_mm=sod_mm)
        return image if image_mask is None else with_user_mask(image, image_mask)
    ds, frames, rows, cols = _open_xray(path)
    if frame is None:
        if frames > 1:
            warnings.warn(f"{path}: {frames} frames; using frame 0 (choose one with --frame)", stacklevel=2)
        frame = 0
    if not 0 <= int(frame) < frames:
        raise DicomError(path, f"frame {frame} out of range: {tag_name('NumberOfFrames')} is {frames}")
    return _xray_frame(
        path, ds, int(frame), frames, rows, cols, iso, kind=kind, sid_mm=sid_mm, sod_mm=sod_mm, image_mask=image_mask,
        pixel_mm=pixel_mm,
    )  # fmt: skip


def with_user_mask(image: XRayImage, image_mask: str | os.PathLike[str]) -> XRayImage:
    """``image`` with its field intersected with the user's mask file (nonzero = usable)."""
    from registration.core.images import XRayImage
    from registration.io.image_files import ImageFileError, read_image_mask

    user = read_image_mask(image_mask, image.shape)
    mask = image.mask & user
    if not mask.any():
        raise ImageFileError(image_mask, "the image mask and the image's field have no pixel in common")
    found_by = f"{image.meta.get('mask_from', 'whole image')}, user mask {Path(image_mask).name}"
    meta = {**image.meta, "mask_from": found_by}
    field = dict(meta.get("field") or {})
    field.update(user_mask=str(image_mask), usable_pixels=int(mask.sum()), usable_fraction=round(float(mask.mean()), 4))
    meta["field"] = field
    return XRayImage(np.where(mask, image.image, np.float32(0.0)), mask, image.geometry, image.kind, meta)


def _check_isocenter(isocenter_mm: ArrayLike) -> tuple[float, float, float]:
    iso = np.asarray(isocenter_mm, dtype=np.float64).reshape(-1)
    if iso.shape != (3,) or not np.all(np.isfinite(iso)):
        raise ValueError(f"isocenter_mm must be three finite numbers, got {isocenter_mm}")
    return (float(iso[0]), float(iso[1]), float(iso[2]))


def _open_xray(path: Path) -> tuple[Dataset, int, int, int]:
    """The dataset of an XA/RF file, its frame count, rows and columns (as stored)."""
    ds = read_dataset(path)
    sop = _sop_class(ds)
    modality = _text(ds, "Modality").upper()
    if sop not in XRAY_CLASSES and modality not in ("XA", "RF"):
        name = UID(sop).name if sop else "unknown class"
        raise DicomError(
            path,
            f"wrong modality: {tag_name('Modality')} is {modality or 'missing'} ({name}); an XA or RF "
            "projection image is expected",
        )
    if sop in ENHANCED_VOLUME_CLASSES:
        raise DicomError(path, f"is a {ENHANCED_VOLUME_CLASSES[sop]} volume, not a projection image")
    frames = _frames(path, ds)
    rows, cols = _check_pixel_module(path, ds, frames)
    check_dataset_pixels(path, ds, frames)  # declared sizes against the bytes present, before decoding
    return ds, frames, rows, cols


def frame_plane(path: Path, ds: Dataset, frame: int) -> str:
    """Plane Identification (0018,9457) of ``frame`` ("" when absent), checked against PLANES."""
    value = lookup(ds, "PlaneIdentification", frame)
    if value is None:
        return ""
    text = str(value).strip().upper()
    if text not in PLANES:
        raise DicomError(path, f"{tag_name('PlaneIdentification')} is {str(value)[:20]!r}; expected one of {PLANES}")
    return text


def frame_acquisition_datetime(ds: Dataset, frame: int) -> str:
    """When ``frame`` was taken, as DICOM DT text ("" when the file does not say):
    FrameAcquisitionDateTime (0018,9074), else AcquisitionDateTime (0008,002A), else
    AcquisitionDate + AcquisitionTime."""
    value = lookup(ds, "FrameAcquisitionDateTime", frame) or lookup(ds, "AcquisitionDateTime", frame)
    if not value and ds.get("AcquisitionDate") and ds.get("AcquisitionTime"):
        value = f"{ds.AcquisitionDate}{ds.AcquisitionTime}"
    return str(value or "").strip()


def _image_references(ds: Dataset) -> dict[str, str]:
    """The UIDs and patient of an X-ray image (for the Spatial Registration object)."""
    return {
        key: _text(ds, keyword)
        for key, keyword in (
            ("sop_class", "SOPClassUID"),
            ("sop_instance_uid", "SOPInstanceUID"),
            ("series_uid", "SeriesInstanceUID"),
            ("study_uid", "StudyInstanceUID"),
            ("frame_of_reference_uid", "FrameOfReferenceUID"),
            ("patient_name", "PatientName"),
            ("patient_id", "PatientID"),
        )
    }


def _signal_up(ds: Dataset, frame: int) -> bool:
    """Whether larger stored values mean more X-rays (PixelIntensityRelationshipSign, +1 when absent)."""
    try:
        return int(lookup(ds, "PixelIntensityRelationshipSign", frame) or 1) != -1
    except (TypeError, ValueError):
        return True


def _raw_words(ds: Dataset, frame: int, frames: int, rows: int, cols: int) -> NDArray[Any] | None:
    """The frame's stored 16-bit words with their high bits (uncompressed data only)."""
    ts = ds.file_meta.get("TransferSyntaxUID") if hasattr(ds, "file_meta") else None
    if ts is not None and UID(ts).is_compressed or int(ds.get("BitsAllocated") or 0) != 16:
        return None
    data = ds.get("PixelData")
    if not isinstance(data, (bytes, bytearray)) or len(data) < frames * rows * cols * 2:
        return None
    words = np.frombuffer(data, dtype="<u2", count=frames * rows * cols)
    return words.reshape(frames, rows, cols)[frame]


def _field_mask(
    path: Path,
    ds: Dataset,
    stored: NDArray[Any],
    frame: int,
    *,
    image_mask: str | os.PathLike[str] | None = None,
    cache: dict[str, Any] | None = None,
) -> tuple[NDArray[np.bool_], dict[str, Any]]:
    """The usable field in stored pixel positions and how it was found (CONVENTIONS §5).

    The intersection of: the shutter and collimator tags, what :func:`registration.io.field.find_field`
    finds in the pixels (the collimated outside, blades, burned-in graphics), the complement of
    the overlay planes' graphics, and the user's mask.
    """
    from registration.io.field import find_field, infer_signal_up

    rows, cols = stored.shape
    frames = _frames(path, ds)
    shutter, shutter_info = shutter_field(path, ds, rows, cols, frame)
    signal_up = _signal_up(ds, frame)
    info: dict[str, Any] = {**shutter_info}
    if lookup(ds, "PixelIntensityRelationshipSign", frame) in (None, ""):
        # read from the first frame of a run: its collimated outside keeps its polarity
        if cache is not None and cache.get("sign_shape") == (rows, cols):
            inferred = cache["sign_inferred"]
        else:
            inferred = infer_signal_up(stored)
            if cache is not None:
                cache.update(sign_shape=(rows, cols), sign_inferred=inferred)
        if inferred is not None:
            signal_up = inferred
            info["sign_inferred"] = 1 if inferred else -1
    found = find_field(stored, signal_up=signal_up, start=shutter, cache=cache)
    mask = found.mask
    found_by: list[str] = []
    if shutter is not None:
        found_by.append(shutter_text(shutter_info))
    pixel_parts = [p["what"] for p in found.parts]
    for what in dict.fromkeys(pixel_parts):
        n = pixel_parts.count(what)
        found_by.append(what + (f" x{n}" if n > 1 else ""))
    if found.parts:
        info["found_in_pixels"] = found.parts
    overlay, notes = overlay_graphics(path, ds, rows, cols, frame, _raw_words(ds, frame, frames, rows, cols))
    if notes:
        info["overlays"] = notes
    if overlay is not None:
        mask = mask & ~overlay
        found_by.append("overlay graphics")
    if image_mask is not None:
        from registration.io.image_files import read_image_mask

        user = read_image_mask(image_mask, (rows, cols))
        mask = mask & user
        found_by.append(f"user mask {Path(image_mask).name}")
        info["user_mask"] = str(image_mask)
    if not found_by:
        warnings.warn(
            f"{path}: no shutter ({tag_name('ShutterShape')}), no collimator edge and no graphics found; using the "
            "whole image as the field",
            stacklevel=4,
        )
        found_by.append("whole image")
    if not mask.any():
        raise DicomError(path, "the field is empty (shutter, collimation found in the pixels, overlays or mask)")
    info["found_by"] = ", ".join(found_by)
    info["usable_pixels"] = int(mask.sum())
    info["usable_fraction"] = round(float(mask.mean()), 4)
    return mask, info


def intensity_assumed(meta: dict[str, Any]) -> str:
    """What the reader assumed about the stored values, in a sentence (for ``info``)."""
    relationship = meta.get("pixel_intensity_relationship", "?")
    sign = int(meta.get("pixel_intensity_relationship_sign", 1))
    note = meta.get("intensity_note")
    text = f"{note}" if note else f"{relationship} (from PixelIntensityRelationship)"
    polarity = "lower stored values = more attenuation" if sign == 1 else "higher stored values = more attenuation"
    text += f", sign {sign:+d} ({polarity}; {meta.get('sign_from', 'PixelIntensityRelationshipSign')})"
    if meta.get("bits_stored"):
        text += f", {meta['bits_stored']} bits stored"
    slope, intercept = meta.get("rescale_slope", 1.0), meta.get("rescale_intercept", 0.0)
    if (slope, intercept) != (1.0, 0.0):
        text += f", rescale {slope:g} x + {intercept:g}"
    if relationship == "LIN":
        text += "; attenuation = ln(brightest field pixel / value)"
    return text


def field_summary(field: dict[str, Any]) -> list[str]:
    """One line per part of the image that was masked (for ``info``)."""
    lines = []
    for key in ("shutter", "collimator"):
        if key in field:
            lines.append(f"{key} tags: {field[key]}")
    if "shutter_presentation_value" in field:
        lines.append(f"shutter presentation value {field['shutter_presentation_value']} (display only)")
    for part in field.get("found_in_pixels", []):
        text = f"{part['what']}: {part['pixels']} px"
        if part.get("along_outside"):
            step = f", step {part['step']:.2f} of the field's range" if part["step"] else ""
            text += f" (edge at {part['angle_deg']:+.1f} deg along the collimated outside{step})"
        elif "angle_deg" in part:
            text += f" (edge at {part['angle_deg']:+.1f} deg, step {part['step']:.2f} of the field's range)"
        lines.append(text)
    for note in field.get("overlays", []):
        lines.append(f"{note['plane']} ({note['type']}, {note.get('from', '')}): {note['pixels']} px drawn, masked")
    if "user_mask" in field:
        lines.append(f"user mask {field['user_mask']}")
    return lines


def xray_field(
    path: str | os.PathLike[str], *, frame: int = 0, image_mask: str | os.PathLike[str] | None = None
) -> tuple[NDArray[np.bool_], dict[str, Any], dict[str, Any]]:
    """The field mask (CONVENTIONS axes), how it was found and the intensity reading of one frame,
    without the C-arm geometry (for files that lack it, as ``info`` shows them)."""
    path = Path(path)
    ds, frames, rows, cols = _open_xray(path)
    if not 0 <= int(frame) < frames:
        raise DicomError(path, f"frame {frame} out of range: {tag_name('NumberOfFrames')} is {frames}")
    stored = _pixels(path, ds, index=frame if frames > 1 else None)
    if stored.ndim == 3 and stored.shape[0] == 1:
        stored = stored[0]
    mask, info = _field_mask(path, ds, stored, int(frame), image_mask=image_mask)
    _, intensity = _intensity_to_attenuation(path, ds, stored, int(frame), mask, info.get("sign_inferred"))
    rotation, flip = _field_of_view(path, ds, frame)
    if rotation or flip:
        mask = _undo_field_of_view(mask, rotation, flip)
    return mask, info, intensity


def _xray_frame(
    path: Path,
    ds: Dataset,
    frame: int,
    frames: int,
    rows: int,
    cols: int,
    iso: tuple[float, float, float],
    *,
    kind: str | None = None,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    image_mask: str | os.PathLike[str] | None = None,
    field_cache: dict[str, Any] | None = None,
    pixel_mm: float | None = None,
) -> XRayImage:
    """Frame ``frame`` of an opened XA/RF dataset as an :class:`XRayImage`.

    ``image_mask``: the user's mask (see :func:`read_xray`); ``field_cache``: a dict kept across
    the frames of one run (:func:`registration.io.field.find_field`).
    """
    from registration.core.images import XRayImage

    sop = _sop_class(ds)
    modality = _text(ds, "Modality").upper()
    stored = _pixels(path, ds, index=frame if frames > 1 else None)
    if stored.ndim == 3 and stored.shape[0] == 1:
        stored = stored[0]
    if stored.shape != (rows, cols):
        raise DicomError(path, f"{tag_name('PixelData')} decodes to shape {stored.shape}, expected {rows}x{cols}")
    mask, field_info = _field_mask(path, ds, stored, frame, image_mask=image_mask, cache=field_cache)
    stored, rotation_note = _field_rotation(path, ds, stored, frame)
    if rotation_note:
        mask = _undo_field_of_view(mask, *_field_of_view(path, ds, frame))
    rows, cols = stored.shape
    geometry, geo_info = _geometry(
        path, ds, frame, frames, rows, cols, iso, sid_mm=sid_mm, sod_mm=sod_mm, pixel_mm=pixel_mm
    )
    image, intensity = _intensity_to_attenuation(path, ds, stored, frame, mask, field_info.get("sign_inferred"))
    image = np.where(mask, image, np.float32(0.0)).astype(np.float32)
    meta: dict[str, Any] = {
        "source": str(path),
        "format": XRAY_CLASSES.get(sop, modality),
        "modality": modality,
        "frame": frame,
        "frames": frames,
        "mask_from": field_info["found_by"],
        "field": field_info,
        "decoder": pixel_decoder(ds)[1],
        "plane": frame_plane(path, ds, frame),
        "acquisition_datetime": frame_acquisition_datetime(ds, frame),
        **_image_references(ds),
        **geo_info,
        **intensity,
    }
    if rotation_note:
        meta["field_rotation"] = rotation_note
    try:
        image_kind, meta["acquisition"] = _xray_kind(ds, kind)
        return XRayImage(image=image, mask=mask, geometry=geometry, kind=image_kind, meta=meta)
    except ValueError as exc:
        raise DicomError(path, str(exc)) from None


def read_xray_angles(path: str | os.PathLike[str]) -> list[tuple[float, float]]:
    """(primary_deg, secondary_deg) of every frame, without decoding the pixels."""
    path = Path(path)
    ds = read_dataset(path, stop_before_pixels=True)
    frames = _frames(path, ds)
    check_frame_count(path, frames)
    return [_frame_angles(path, ds, n, frames)[:2] for n in range(frames)]


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
