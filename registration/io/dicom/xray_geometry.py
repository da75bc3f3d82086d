"""An XA/RF image's C-arm from its tags (CONVENTIONS §3): positioner angles per frame, distances,
pixel spacing, and the field-of-view rotation, flip and origin the detector stored it with."""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import Dataset

from registration.core.geometry import CArm
from registration.io.dicom._common import (
    DicomError,
    _float,
    _floats,
    lookup,
    tag_name,
)

if TYPE_CHECKING:
    pass


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


def _pixel_spacing(path: Path, ds: Dataset, frame: int, pixel_mm: float | None) -> tuple[list[float], str]:
    """The detector's pixel spacing (mm, rows then columns) and where it came from: the given
    ``pixel_mm``, ImagerPixelSpacing, or PixelSpacing (with a warning)."""
    spacing = _floats(path, ds, "ImagerPixelSpacing", 2, frame, required=False)
    spacing_tag = "ImagerPixelSpacing"
    if pixel_mm is not None:
        value = float(pixel_mm)
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f"pixel_mm (--pixel-mm) must be a positive number of mm, got {pixel_mm}")
        if spacing is not None and max(abs(v - value) for v in spacing) > 1e-6 * value:
            warnings.warn(f"{path}: {tag_name(spacing_tag)} is {spacing}; using the given {value:g} mm instead",
                          stacklevel=4)  # fmt: skip
        spacing, spacing_tag = [value, value], "pixel_mm"
    if spacing is None:
        spacing = _floats(path, ds, "PixelSpacing", 2, frame, required=False)
        spacing_tag = "PixelSpacing"
        if spacing is None:
            raise DicomError(
                path,
                f"missing {tag_name('ImagerPixelSpacing')} (and no PixelSpacing): supply it with pixel_mm (--pixel-mm)",
            )
        warnings.warn(
            f"{path}: no {tag_name('ImagerPixelSpacing')}; using {tag_name('PixelSpacing')} {spacing} as the "
            "spacing at the detector",
            stacklevel=4,
        )
    return spacing, spacing_tag


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
    spacing, spacing_tag = _pixel_spacing(path, ds, frame, pixel_mm)
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
