"""XA/RF projection images: reading (geometry, intensities, field mask) and writing.

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

import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydicom.datadict import tag_for_keyword
from pydicom.dataset import Dataset
from pydicom.uid import (
    UID,
    ExplicitVRLittleEndian,
    JPEG2000Lossless,
    RLELossless,
    XRayAngiographicImageStorage,
)

from registration.core.geometry import CArm
from registration.io.dicom._common import (
    ENHANCED_VOLUME_CLASSES,
    LOG_UNITS_PER_ATTENUATION,
    LOG_ZERO_VALUE,
    NO_SIGNAL_VALUE,
    WRITTEN_SIGN,
    XRAY_CLASSES,
    DicomError,
    _base,
    _check_pixel_module,
    _ds_number,
    _float,
    _floats,
    _frames,
    _max_stored,
    _pixels,
    _save,
    _sop_class,
    _text,
    lookup,
    make_uid,
    pixel_decoder,
    read_dataset,
    tag_name,
)
from registration.io.dicom._files import (
    _atomic_path,
)
from registration.io.dicom.limits import check_dataset_pixels, check_frame_count
from registration.io.dicom.shutters import overlay_graphics, shutter_field, shutter_text

if TYPE_CHECKING:
    from registration.core.images import XRayImage


def _frame_angles(path: Path, ds: Dataset, frame: int, frames: int) -> tuple[float, float, str]:
    """Primary and secondary angle of ``frame`` and where they came from."""
    enhanced = "PerFrameFunctionalGroupsSequence" in ds or "SharedFunctionalGroupsSequence" in ds
    primary = _float(path, ds, "PositionerPrimaryAngle", frame if enhanced else None)
    secondary = _float(path, ds, "PositionerSecondaryAngle", frame if enhanced else None)
    source = "per-frame functional groups" if enhanced else "positioner angles"
    if not enhanced and frames > 1:
        for keyword, base, which in (
            ("PositionerPrimaryAngleIncrement", primary, 0),
            ("PositionerSecondaryAngleIncrement", secondary, 1),
        ):
            inc = _floats(path, ds, keyword, None, required=False)
            if not inc:
                continue
            if len(inc) == 1:
                angle = base + frame * inc[0]
            elif len(inc) == frames:
                angle = base + inc[frame]
            else:
                raise DicomError(
                    path,
                    f"{tag_name(keyword)} holds {len(inc)} values for {frames} frames (1 or {frames} expected)",
                )
            if which == 0:
                primary = angle
            else:
                secondary = angle
            source = "positioner angles + angle increments"
    return primary, secondary, source


def _distance(
    path: Path, ds: Dataset, frame: int, keywords: tuple[str, ...], given: float | None, option: str
) -> tuple[float, str]:
    """A distance (mm) from the first of ``keywords`` present, or the caller's ``given`` value.

    ``option`` names the parameter and the command-line flag that supply it (for the message).
    """
    found = None
    for keyword in keywords:
        values = _floats(path, ds, keyword, None, frame, required=False)
        if values:
            found = (values[0], keyword)
            break
    if given is not None:
        value = float(given)
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f"{option} must be a positive number of mm, got {given}")
        if found is not None and abs(found[0] - value) > 1e-6 * max(1.0, value):
            warnings.warn(
                f"{path}: {tag_name(found[1])} is {found[0]:g} mm; using the given {value:g} mm instead",
                stacklevel=4,
            )
        return value, option.split(" ")[0]
    if found is None:
        raise DicomError(path, f"missing {tag_name(keywords[0])}: supply it with {option}")
    return found


def _geometry(
    path: Path,
    ds: Dataset,
    frame: int,
    frames: int,
    rows: int,
    cols: int,
    isocenter_mm: tuple[float, float, float],
    *,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_mm: float | None = None,
) -> tuple[CArm, dict]:
    primary, secondary, angle_source = _frame_angles(path, ds, frame, frames)
    if abs(primary) > 180 or abs(secondary) > 90:  # legal for the C-arm, outside DICOM's defined range
        warnings.warn(
            f"{path}: positioner angles {primary:g}, {secondary:g} deg lie outside DICOM's ranges (primary "
            "-180..180, secondary -90..90); used as given",
            stacklevel=3,
        )
    sid, sid_from = _distance(path, ds, frame, ("DistanceSourceToDetector",), sid_mm, "sid_mm (--sid-mm)")
    sod, sod_from = _distance(
        path, ds, frame, ("DistanceSourceToPatient", "DistanceSourceToIsocenter"), sod_mm, "sod_mm (--sod-mm)"
    )
    spacing = _floats(path, ds, "ImagerPixelSpacing", 2, frame, required=False)
    spacing_tag = "ImagerPixelSpacing"
    if pixel_mm is not None:
        value = float(pixel_mm)
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f"pixel_mm (--pixel-mm) must be a positive number of mm, got {pixel_mm}")
        if spacing is not None and max(abs(v - value) for v in spacing) > 1e-6 * value:
            warnings.warn(f"{path}: {tag_name(spacing_tag)} is {spacing}; using the given {value:g} mm instead",
                          stacklevel=3)  # fmt: skip
        spacing, spacing_tag = [value, value], "pixel_mm"
    if spacing is None:
        spacing = _floats(path, ds, "PixelSpacing", 2, frame, required=False)
        spacing_tag = "PixelSpacing"
        if spacing is None:
            raise DicomError(
                path, f"missing {tag_name('ImagerPixelSpacing')} (and no PixelSpacing): supply it with --pixel-mm"
            )
        warnings.warn(
            f"{path}: no {tag_name('ImagerPixelSpacing')}; using {tag_name('PixelSpacing')} {spacing} as the "
            "spacing at the detector",
            stacklevel=3,
        )
    if _field_of_view(path, ds, frame)[0] in (90, 270):
        spacing = [spacing[1], spacing[0]]  # the spacing of the stored rows is that of physical columns
    try:
        geometry = CArm(
            primary_deg=primary,
            secondary_deg=secondary,
            sid_mm=sid,
            sod_mm=sod,
            rows=rows,
            cols=cols,
            pixel_mm=(spacing[0], spacing[1]),
            isocenter_mm=isocenter_mm,
        )
    except ValueError as exc:
        raise DicomError(
            path,
            f"inconsistent geometry ({tag_name('DistanceSourceToDetector')}, "
            f"{tag_name('DistanceSourceToPatient')}, {tag_name(spacing_tag)}, positioner angles): {exc}",
        ) from None
    info = {
        "angles_from": angle_source,
        "pixel_spacing_from": spacing_tag,
        "sid_from": sid_from,
        "sod_from": sod_from,
    }
    shift, note = _field_of_view_shift(path, ds, frame, geometry)
    if note:
        geometry = replace(geometry, detector_shift_mm=shift)
        info["field_of_view_origin"] = note
    return geometry, info


def _intensity_to_attenuation(
    path: Path,
    ds: Dataset,
    stored: NDArray[Any],
    frame: int,
    field: NDArray[np.bool_],
    inferred_sign: int | None = None,
) -> tuple[NDArray[np.float32], dict]:
    """Attenuation line integrals from the stored values (see the module docstring).

    ``inferred_sign``: the sign the collimated outside shows, used when the file states none.
    """
    relationship = _text(ds, "PixelIntensityRelationship").upper()
    if not relationship:
        found = lookup(ds, "PixelIntensityRelationship", frame)
        relationship = str(found).upper() if found else ""
    sign_value = lookup(ds, "PixelIntensityRelationshipSign", frame)
    info: dict[str, Any] = {}
    if relationship not in ("LOG", "LIN"):
        warnings.warn(
            f"{path}: {tag_name('PixelIntensityRelationship')} is {relationship or 'missing'}; reading the "
            "pixels as LOG (approximate attenuation)",
            stacklevel=3,
        )
        info["intensity_note"] = f"{relationship or 'missing'} read as LOG"
        relationship = "LOG"
    sign_from = "PixelIntensityRelationshipSign"
    if (sign_value is None or sign_value == "") and inferred_sign is not None:
        sign = inferred_sign
        sign_from = "no PixelIntensityRelationshipSign: read from the collimated outside (no X-rays)"
        warnings.warn(
            f"{path}: missing {tag_name('PixelIntensityRelationshipSign')}; the collimated outside says {sign:+d}",
            stacklevel=3,
        )
    elif sign_value is None or sign_value == "":
        sign = 1
        sign_from = "assumed (no PixelIntensityRelationshipSign)"
        warnings.warn(f"{path}: missing {tag_name('PixelIntensityRelationshipSign')}; assuming +1", stacklevel=3)
    else:
        try:
            sign = int(sign_value)
        except (TypeError, ValueError):
            raise DicomError(
                path,
                f"{tag_name('PixelIntensityRelationshipSign')} must be +1 or -1, got {str(sign_value)[:20]!r}",
            ) from None
        if sign not in (1, -1):
            raise DicomError(path, f"{tag_name('PixelIntensityRelationshipSign')} must be +1 or -1, got {sign}")
    slope = _float(path, ds, "RescaleSlope", frame, default=1.0)
    intercept = _float(path, ds, "RescaleIntercept", frame, default=0.0)
    m = stored.astype(np.float64) * slope + intercept
    m_max = _max_stored(ds) * slope + intercept
    upward = m if sign == -1 else m_max - m  # grows with attenuation
    if relationship == "LOG":
        att = (upward - LOG_ZERO_VALUE) / LOG_UNITS_PER_ATTENUATION
    else:
        intensity = m_max - upward
        inside = intensity[field] if field.any() else intensity
        ref = float(np.max(inside)) if inside.size else 1.0
        att = np.log(max(ref, 1.0) / np.maximum(intensity, 1.0))
    info.update(
        pixel_intensity_relationship=relationship,
        pixel_intensity_relationship_sign=sign,
        sign_from=sign_from,
        rescale_slope=slope,
        rescale_intercept=intercept,
        bits_stored=int(ds.get("BitsStored") or ds.get("BitsAllocated") or 0),
    )
    return att.astype(np.float32), info


def _field_of_view(path: Path, ds: Dataset, frame: int | None = None) -> tuple[int, bool]:
    """FieldOfViewRotation (degrees clockwise, 0/90/180/270) and FieldOfViewHorizontalFlip.

    Read from the frame's Field of View functional group (enhanced XA/RF) or the top level.
    """
    rotation_value = lookup(ds, "FieldOfViewRotation", frame)
    flip_text = str(lookup(ds, "FieldOfViewHorizontalFlip", frame) or "").strip().upper()
    if flip_text not in ("", "YES", "NO"):
        raise DicomError(path, f"{tag_name('FieldOfViewHorizontalFlip')} is {flip_text[:16]!r}: YES or NO expected")
    flip = flip_text == "YES"
    try:
        rotation = int(float(rotation_value)) % 360 if rotation_value not in (None, "") else 0
    except (TypeError, ValueError, OverflowError):  # OverflowError: inf
        raise DicomError(path, f"{tag_name('FieldOfViewRotation')} is not a finite number") from None
    if rotation % 90:
        raise DicomError(path, f"{tag_name('FieldOfViewRotation')} {rotation} is not a multiple of 90")
    return rotation, flip


def _field_rotation_shape(path: Path, ds: Dataset, rows: int, cols: int, frame: int | None = None) -> tuple[int, int]:
    """(rows, cols) of the image once the field-of-view rotation is undone."""
    rotation, _ = _field_of_view(path, ds, frame)
    return (cols, rows) if rotation in (90, 270) else (rows, cols)


def _undo_field_of_view(image: NDArray[Any], rotation: int, flip: bool) -> NDArray[Any]:
    """Physical detector axes from the stored ones: stored = flip(rotate_clockwise(physical)).

    DICOM: the field of view is rotated clockwise (as displayed: row 0 on top) relative to the
    physical detector, then flipped horizontally; undone in the reverse order.
    """
    if flip:
        image = image[..., ::-1]
    return np.ascontiguousarray(np.rot90(image, k=rotation // 90, axes=(-2, -1)))


def _field_rotation(
    path: Path, ds: Dataset, image: NDArray[Any], frame: int | None = None
) -> tuple[NDArray[Any], str | None]:
    rotation, flip = _field_of_view(path, ds, frame)
    if rotation == 0 and not flip:
        return image, None
    note = f"undid FieldOfViewRotation {rotation} deg" + (" and horizontal flip" if flip else "")
    warnings.warn(f"{path}: {note} to restore the CONVENTIONS §3 image axes", stacklevel=3)
    return _undo_field_of_view(image, rotation, flip), note


def _field_of_view_shift(
    path: Path, ds: Dataset, frame: int | None, geometry: CArm
) -> tuple[tuple[float, float, float], str | None]:
    """World shift of the image center from the central ray, from FieldOfViewOrigin.

    FieldOfViewOrigin (0018,7030) is the offset (row, column, in detector elements) of the
    field of view's top-left corner, before rotation and flipping, from the physical
    detector's; with DetectorElementSpacing, the field's size (FieldOfViewDimensionsInFloat or
    FieldOfViewDimensions, mm) and the active area (DetectorActiveOrigin, DetectorActiveDimensions,
    mm) it places the field's center relative to the active area's center, where the central
    ray meets the detector (CONVENTIONS §3). The shift, along u (columns) and v (rows) of the
    physical detector, becomes the geometry's ``detector_shift_mm``. Without the other tags the
    origin cannot be placed: it is ignored with a warning.
    """
    origin = _floats(path, ds, "FieldOfViewOrigin", 2, frame, required=False)
    if origin is None:
        return (0.0, 0.0, 0.0), None
    spacing = _floats(path, ds, "DetectorElementSpacing", 2, frame, required=False)
    size = _floats(path, ds, "FieldOfViewDimensionsInFloat", None, frame, required=False) or _floats(
        path, ds, "FieldOfViewDimensions", None, frame, required=False
    )
    active = _floats(path, ds, "DetectorActiveDimensions", None, frame, required=False)
    if spacing is None or size is None or active is None:
        missing = [
            tag_name(k)
            for k, v in (
                ("DetectorElementSpacing", spacing),
                ("FieldOfViewDimensions", size),
                ("DetectorActiveDimensions", active),
            )
            if v is None
        ]
        warnings.warn(
            f"{path}: {tag_name('FieldOfViewOrigin')} ignored (needs {', '.join(missing)}); the image center "
            "is taken as the central ray",
            stacklevel=4,
        )
        return (0.0, 0.0, 0.0), None
    active_origin = _floats(path, ds, "DetectorActiveOrigin", 2, frame, required=False) or [0.0, 0.0]
    if any(v <= 0 for v in (*spacing, *size, *active)):
        raise DicomError(path, "detector or field-of-view dimensions must be positive")
    size2 = size if len(size) == 2 else [size[0], size[0]]  # ROUND: one diameter
    active2 = active if len(active) == 2 else [active[0], active[0]]
    offset_row = origin[0] * spacing[0] + size2[0] / 2.0 - (active_origin[0] + active2[0] / 2.0)
    offset_col = origin[1] * spacing[1] + size2[1] / 2.0 - (active_origin[1] + active2[1] / 2.0)
    if max(abs(offset_row), abs(offset_col)) > max(active2):
        raise DicomError(
            path,
            f"{tag_name('FieldOfViewOrigin')} {origin} puts the field {offset_row:.0f}, {offset_col:.0f} mm "
            "from the detector center, outside the detector",
        )
    shift = offset_col * geometry.u + offset_row * geometry.v
    note = f"field of view {offset_row:+.2f} mm (rows), {offset_col:+.2f} mm (columns) from the central ray"
    return (float(shift[0]), float(shift[1]), float(shift[2])), note


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
        inferred = infer_signal_up(stored)
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
        if "angle_deg" in part:
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
def _encode_attenuation(image: NDArray[Any], mask: NDArray[np.bool_]) -> NDArray[np.uint16]:
    upward = np.rint(np.asarray(image, dtype=np.float64) * LOG_UNITS_PER_ATTENUATION) + LOG_ZERO_VALUE
    stored = np.where(mask, np.clip(65535 - upward, NO_SIGNAL_VALUE + 1, 65535), NO_SIGNAL_VALUE)
    return stored.astype(np.uint16)


#: Frame spacing (ms) of a run written without ``times_s`` (30 frames/s).
DEFAULT_FRAME_TIME_MS = 1000.0 / 30.0
#: Plane Identification (0018,9457) values (CONVENTIONS §6).
PLANES = ("MONOPLANE", "PLANE A", "PLANE B")
#: Lossless transfer syntaxes the writer can compress to (RLE needs no plugin; JPEG 2000 needs
#: pylibjpeg-openjpeg).
LOSSLESS_SYNTAXES = (RLELossless, JPEG2000Lossless)


def _check_times(times_s: ArrayLike | None, frames: int) -> NDArray[np.float64]:
    if times_s is None:
        return np.arange(frames, dtype=np.float64) * DEFAULT_FRAME_TIME_MS / 1000.0
    times = np.asarray(times_s, dtype=np.float64).reshape(-1)
    if times.shape != (frames,):
        raise ValueError(f"times_s must hold one time per frame ({frames}), got {times.size}")
    if not np.all(np.isfinite(times)):
        raise ValueError("times_s must be finite")
    if frames and abs(times[0]) > 1e-9:
        raise ValueError(f"times_s counts from the first frame: times_s[0] must be 0, got {times[0]}")
    if np.any(np.diff(times) < 0):
        raise ValueError("times_s must not decrease")
    return times


def _compress(ds: Dataset, stored: NDArray[Any], syntax: UID, path: Path) -> None:
    if syntax not in LOSSLESS_SYNTAXES:
        names = ", ".join(f"{s.name} ({s})" for s in LOSSLESS_SYNTAXES)
        raise ValueError(f"{path}: transfer_syntax {syntax} is not one the writer compresses to ({names})")
    try:
        ds.compress(syntax, np.ascontiguousarray(stored), generate_instance_uid=False)
    except Exception as exc:  # pydicom raises RuntimeError/ValueError when no encoder is installed
        raise ValueError(f"{path}: cannot compress to {syntax.name}: {exc}") from None
    ds.file_meta.TransferSyntaxUID = syntax


def write_xray(
    images: XRayImage | Sequence[XRayImage],
    path: str | os.PathLike[str],
    *,
    study_uid: str | None = None,
    uid_seed: str | None = None,
    description: str | None = None,
    patient_name: str = "roadmap3d^phantom",
    patient_id: str = "ROADMAP3D",
    times_s: ArrayLike | None = None,
    plane: str | None = None,
    transfer_syntax: str | None = None,
    acquired_at: datetime | None = None,
) -> Path:
    """Write one XA image, or a multi-frame XA run (per-frame angles), per the module docstring.

    Frames of a run share size, distances and pixel spacing; their angles are stored as the
    first frame's PositionerPrimary/SecondaryAngle plus a per-frame vector of offsets in the
    angle increment tags. The circular field goes into the shutter module and into the pixel
    values (NO_SIGNAL_VALUE outside the field). Only the nominal geometry is stored: DICOM
    has no place for the bending shifts of a true geometry.

    ``times_s`` (one per frame, seconds from the first frame, non-decreasing; default
    ``DEFAULT_FRAME_TIME_MS`` apart) become FrameTime (0018,1063) when evenly spaced, else
    FrameTimeVector (0018,1065) (CONVENTIONS §7). ``plane`` ("MONOPLANE", "PLANE A", "PLANE B")
    is written as PlaneIdentification (0018,9457) and ImageType (BIPLANE A / BIPLANE B);
    ``acquired_at`` (default: now, UTC) as AcquisitionDateTime, so the two planes of one
    moment can be written with the same time. ``transfer_syntax`` (a UID, e.g. RLE
    Lossless or JPEG 2000 Lossless; default Explicit VR Little Endian) compresses the pixels
    losslessly. :func:`registration.io.dicom.write_xray_run` is the run-facing entry point.
    """
    frames = [images] if not isinstance(images, Sequence) else list(images)
    if not frames:
        raise ValueError("no image to write")
    times = _check_times(times_s, len(frames))
    if plane is not None and plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}, got {plane!r}")
    first = frames[0]
    g0 = first.geometry
    for img in frames[1:]:
        g = img.geometry
        if (g.rows, g.cols, g.sid_mm, g.sod_mm, g.pixel_mm) != (
            g0.rows,
            g0.cols,
            g0.sid_mm,
            g0.sod_mm,
            g0.pixel_mm,
        ):
            raise ValueError("frames of one XA run must share size, SID, SOD and pixel spacing")
    kind = getattr(first, "kind", "exposure")
    study = UID(study_uid) if study_uid else make_uid(uid_seed, "study")
    ds = _base(
        XRayAngiographicImageStorage,
        "XA",
        study_uid=study,
        series_uid=make_uid(uid_seed, "xa series", kind, len(frames)),
        instance_uid=make_uid(uid_seed, "xa instance", kind, len(frames)),
        series_number=10,
        description=(description or f"roadmap3d {kind}")[:64],
        patient_name=patient_name,
        patient_id=patient_id,
    )
    biplane_type = {"PLANE A": "BIPLANE A", "PLANE B": "BIPLANE B"}
    ds.ImageType = ["ORIGINAL", "PRIMARY", biplane_type.get(plane or "", "SINGLE PLANE")]
    ds.InstanceNumber = 1
    ds.ImageComments = (
        f"roadmap3d {kind}: attenuation line integral = (65535 - {LOG_ZERO_VALUE} - stored value) / "
        f"{LOG_UNITS_PER_ATTENUATION:g} (LOG, sign +1); {NO_SIGNAL_VALUE} outside the field"
    )
    ds.AcquisitionDateTime = (acquired_at or datetime.now(UTC)).strftime("%Y%m%d%H%M%S.%f")
    ds.KVP = "80"
    ds.RadiationSetting = "SC" if kind == "fluoro" else "GR"
    ds.PositionerPrimaryAngle = _ds_number(g0.primary_deg)
    ds.PositionerSecondaryAngle = _ds_number(g0.secondary_deg)
    ds.DistanceSourceToDetector = _ds_number(g0.sid_mm)
    ds.DistanceSourceToPatient = _ds_number(g0.sod_mm)
    ds.EstimatedRadiographicMagnificationFactor = _ds_number(g0.sid_mm / g0.sod_mm)
    ds.ImagerPixelSpacing = [_ds_number(g0.pixel_mm[0]), _ds_number(g0.pixel_mm[1])]
    ds.IntensifierSize = _ds_number(g0.field_diameter_mm)
    if len(frames) == 1:
        ds.PositionerMotion = "STATIC"
    else:
        ds.PositionerMotion = "DYNAMIC"
        ds.NumberOfFrames = len(frames)
        steps_ms = np.diff(times) * 1000.0
        if np.allclose(steps_ms, steps_ms[0], rtol=0.0, atol=1e-6):
            ds.FrameTime = _ds_number(float(steps_ms[0]))
            ds.FrameIncrementPointer = tag_for_keyword("FrameTime")
        else:
            ds.FrameTimeVector = [_ds_number(0.0)] + [_ds_number(float(v)) for v in steps_ms]
            ds.FrameIncrementPointer = tag_for_keyword("FrameTimeVector")
        ds.FrameDimensionPointer = [
            tag_for_keyword("PositionerPrimaryAngleIncrement"),
            tag_for_keyword("PositionerSecondaryAngleIncrement"),
        ]
        ds.PositionerPrimaryAngleIncrement = [_ds_number(img.geometry.primary_deg - g0.primary_deg) for img in frames]
        ds.PositionerSecondaryAngleIncrement = [
            _ds_number(img.geometry.secondary_deg - g0.secondary_deg) for img in frames
        ]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = g0.rows, g0.cols
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 0
    ds.PixelIntensityRelationship = "LOG"
    ds.PixelIntensityRelationshipSign = WRITTEN_SIGN
    ds.LossyImageCompression = "00"
    # The shutter must contain the whole field: DICOM stores integers, the field center may
    # sit between pixels, so the circle is padded by one pixel (the pixel values give the edge).
    center_row, center_col = (g0.rows - 1) / 2.0 + 1.0, (g0.cols - 1) / 2.0 + 1.0
    radius_px = g0.field_diameter_mm / 2.0 / min(g0.pixel_mm)
    ds.ShutterShape = "CIRCULAR"
    ds.CenterOfCircularShutter = [int(round(center_row)), int(round(center_col))]
    ds.RadiusOfCircularShutter = int(math.ceil(radius_px + 1.0))
    stored = np.stack([_encode_attenuation(img.image, img.mask) for img in frames])
    low, high = np.percentile(stored[0][first.mask], [0.5, 99.5])
    ds.WindowCenter = _ds_number(round((low + high) / 2.0))
    ds.WindowWidth = _ds_number(max(1.0, round(1.1 * (high - low))))
    if plane is not None:
        ds.PlaneIdentification = plane
    path = Path(path)
    if transfer_syntax is None or UID(transfer_syntax) == ExplicitVRLittleEndian:
        ds.PixelData = stored.tobytes()
    else:
        _compress(ds, stored if len(frames) > 1 else stored[0], UID(transfer_syntax), path)
    with _atomic_path(path) as tmp:
        _save(ds, tmp)
    return path
