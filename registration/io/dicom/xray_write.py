"""Writing XA images and runs: the project's own XA files (16-bit LOG attenuation, sign +1, a
circular shutter around the field), read back by :func:`registration.io.dicom.read_xray`."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
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

from registration.io.dicom._common import (
    LOG_UNITS_PER_ATTENUATION,
    LOG_ZERO_VALUE,
    NO_SIGNAL_VALUE,
    WRITTEN_SIGN,
    _base,
    _ds_number,
    _save,
    make_uid,
)
from registration.io.dicom._files import (
    _atomic_path,
)
from registration.io.dicom.xray import PLANES

if TYPE_CHECKING:
    from registration.core.images import XRayImage


def _encode_attenuation(image: NDArray[Any], mask: NDArray[np.bool_]) -> NDArray[np.uint16]:
    upward = np.rint(np.asarray(image, dtype=np.float64) * LOG_UNITS_PER_ATTENUATION) + LOG_ZERO_VALUE
    stored = np.where(mask, np.clip(65535 - upward, NO_SIGNAL_VALUE + 1, 65535), NO_SIGNAL_VALUE)
    return stored.astype(np.uint16)


#: Frame spacing (ms) of a run written without ``times_s`` (30 frames/s).
DEFAULT_FRAME_TIME_MS = 1000.0 / 30.0
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
    g0 = frames[0].geometry
    for img in frames[1:]:
        g = img.geometry
        if (g.rows, g.cols, g.sid_mm, g.sod_mm, g.pixel_mm) != (g0.rows, g0.cols, g0.sid_mm, g0.sod_mm, g0.pixel_mm):
            raise ValueError("frames of one XA run must share size, SID, SOD and pixel spacing")
    kind = getattr(frames[0], "kind", "exposure")
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
    _acquisition(ds, kind, plane, acquired_at)
    _positioner(ds, frames, times)
    stored = _pixel_module(ds, frames)
    path = Path(path)
    if transfer_syntax is None or UID(transfer_syntax) == ExplicitVRLittleEndian:
        ds.PixelData = stored.tobytes()
    else:
        _compress(ds, stored if len(frames) > 1 else stored[0], UID(transfer_syntax), path)
    with _atomic_path(path) as tmp:
        _save(ds, tmp)
    return path


def _acquisition(ds: Dataset, kind: str, plane: str | None, acquired_at: datetime | None) -> None:
    """The image type (single plane or which plane of a biplane pair), how to read the values,
    when it was taken and the exposure's kind."""
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
    if plane is not None:
        ds.PlaneIdentification = plane


def _positioner(ds: Dataset, frames: list[XRayImage], times: NDArray[np.float64]) -> None:
    """The C-arm's angles and distances (CONVENTIONS §3); a run's frame times (§7) and its
    per-frame angles as increments on the first frame's."""
    g0 = frames[0].geometry
    ds.PositionerPrimaryAngle = _ds_number(g0.primary_deg)
    ds.PositionerSecondaryAngle = _ds_number(g0.secondary_deg)
    ds.DistanceSourceToDetector = _ds_number(g0.sid_mm)
    ds.DistanceSourceToPatient = _ds_number(g0.sod_mm)
    ds.EstimatedRadiographicMagnificationFactor = _ds_number(g0.sid_mm / g0.sod_mm)
    ds.ImagerPixelSpacing = [_ds_number(g0.pixel_mm[0]), _ds_number(g0.pixel_mm[1])]
    ds.IntensifierSize = _ds_number(g0.field_diameter_mm)
    if len(frames) == 1:
        ds.PositionerMotion = "STATIC"
        return
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
    ds.PositionerSecondaryAngleIncrement = [_ds_number(img.geometry.secondary_deg - g0.secondary_deg) for img in frames]


def _pixel_module(ds: Dataset, frames: list[XRayImage]) -> NDArray[np.uint16]:
    """The pixel description (16-bit LOG, sign +1), the circular shutter around the field and a
    window; returns the stored values (frames, rows, cols)."""
    first = frames[0]
    g0 = first.geometry
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
    return stored
