"""DICOM in and out: 3DRA/CT volumes, XA/RF images, the project's ``.npz``, safe uploads.

Everything DICOM-specific (tag lookups, slice sorting, intensity relationships, shutters)
lives here; the rest of the engine sees a :class:`~registration.volume.Volume` and an
:class:`~registration.xray.XRayImage` that follow ``shared/CONVENTIONS.md``.

Volumes (CONVENTIONS §2)
    A folder of slices (CT Image Storage and the like) is sorted by position along the slice
    normal (never by file name); orientation, pixel spacing and size must agree across slices.
    Gantry tilt and uneven slice spacing are *rejected* (not resampled) with a message. An
    enhanced multi-frame file (Enhanced CT, X-Ray 3D Angiographic) is read through its
    functional groups. RescaleSlope/RescaleIntercept give HU. ``index_to_world`` maps
    (i, j, k) = (column, row, slice) to LPS mm exactly as DICOM defines it.

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

    The field mask (pixels that carry signal) is the intersection of the display shutters
    (ShutterShape CIRCULAR with CenterOfCircularShutter/RadiusOfCircularShutter, and/or
    RECTANGULAR with the four edges; 1-based pixel positions) and the complement of the
    constant-valued region connected to the image border (collimator blades). With neither,
    the whole image is used and a warning says so.

Errors are :class:`DicomError` (a ``ValueError``) naming the file and the tag.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import stat
import tempfile
import warnings
import zipfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

import numpy as np
import pydicom
from numpy.typing import ArrayLike, NDArray
from pydicom.datadict import tag_for_keyword
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.sequence import Sequence as DicomSequence
from pydicom.uid import (
    PYDICOM_IMPLEMENTATION_UID,
    UID,
    CTImageStorage,
    EnhancedCTImageStorage,
    EnhancedXAImageStorage,
    EnhancedXRFImageStorage,
    ExplicitVRLittleEndian,
    LegacyConvertedEnhancedCTImageStorage,
    MediaStorageDirectoryStorage,
    XRay3DAngiographicImageStorage,
    XRay3DCraniofacialImageStorage,
    XRayAngiographicImageStorage,
    XRayRadiofluoroscopicImageStorage,
    generate_uid,
)
from scipy import ndimage

from registration.geometry import CArm
from registration.volume import Volume

if TYPE_CHECKING:
    from registration.xray import XRayImage

#: Stored LOG pixel steps per unit of attenuation line integral (see the module docstring).
LOG_UNITS_PER_ATTENUATION = 1000.0
#: The LOG value (counted upward with attenuation) of zero attenuation: room for noise below zero.
LOG_ZERO_VALUE = 1000
#: The sign the project writes (+1: lower pixel values are less X-ray intensity).
WRITTEN_SIGN = 1
#: The stored value written outside the collimated field (sign +1: no X-ray intensity).
NO_SIGNAL_VALUE = 0

#: Slice positions may deviate this much (mm) from an even, untilted stack (scanners round
#: ImagePositionPatient, often to 0.01 mm) ...
POSITION_TOLERANCE_MM = 0.01
#: ... plus this fraction of the slice spacing along the normal (a missing slice is 100 %) ...
SPACING_TOLERANCE = 0.02
#: ... and this fraction of the pixel spacing within the slice plane (gantry tilt).
IN_PLANE_TOLERANCE = 0.05
#: Direction cosines of different slices may differ this much.
ORIENTATION_TOLERANCE = 1e-4
#: Refuse headers that claim more pixel data than this (bytes) before decoding.
MAX_PIXEL_BYTES = 4 * 1024**3
#: A folder holding more files than this is not scanned.
MAX_FOLDER_FILES = 20000

XRAY_CLASSES = {
    XRayAngiographicImageStorage: "XA",
    EnhancedXAImageStorage: "enhanced XA",
    XRayRadiofluoroscopicImageStorage: "RF",
    EnhancedXRFImageStorage: "enhanced RF",
}
ENHANCED_VOLUME_CLASSES = {
    EnhancedCTImageStorage: "enhanced CT",
    LegacyConvertedEnhancedCTImageStorage: "legacy converted enhanced CT",
    XRay3DAngiographicImageStorage: "X-ray 3D angiographic",
    XRay3DCraniofacialImageStorage: "X-ray 3D craniofacial",
}
#: Modalities whose values are Hounsfield units (3DRA is often stored as CT or XA slices).
VOLUME_MODALITIES = {"CT", "XA"}
IMPLEMENTATION_UID = PYDICOM_IMPLEMENTATION_UID

Array = NDArray[np.float64]


class DicomError(ValueError):
    """A file or folder the project cannot read, with the file and the tag at fault."""

    def __init__(self, path: str | os.PathLike[str], message: str) -> None:
        self.path = str(path)
        super().__init__(f"{path}: {message}")


class UploadError(ValueError):
    """An uploaded archive that is refused (size, unsafe names, links, not a zip)."""


def tag_name(keyword: str) -> str:
    """``'DistanceSourceToDetector (0018,1110)'`` for a DICOM keyword."""
    tag = tag_for_keyword(keyword)
    if tag is None:
        return keyword
    return f"{keyword} ({tag >> 16:04X},{tag & 0xFFFF:04X})"


# --------------------------------------------------------------------------------------
# Low-level reading helpers
# --------------------------------------------------------------------------------------
def read_dataset(path: str | os.PathLike[str], *, stop_before_pixels: bool = False) -> Dataset:
    """Read one DICOM file or raise :class:`DicomError` saying why it is not one."""
    path = Path(path)
    if not path.exists():
        raise DicomError(path, "no such file or folder")
    if path.is_dir():
        raise DicomError(path, "is a folder, expected a DICOM file")
    if not path.is_file():
        raise DicomError(path, "not a regular file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                ds = pydicom.dcmread(path, stop_before_pixels=stop_before_pixels)
            except InvalidDicomError:
                ds = pydicom.dcmread(path, stop_before_pixels=stop_before_pixels, force=True)
                if "SOPClassUID" not in ds or not ("PixelData" in ds or stop_before_pixels):
                    raise DicomError(path, "not a DICOM file (no 'DICM' preamble, no image)") from None
            # pydicom converts values lazily: convert them all now, so a corrupt value fails
            # here with a message instead of later in some attribute access.
            for _ in ds.iterall():
                pass
            return ds
    except DicomError:
        raise
    except PermissionError:
        raise DicomError(path, "permission denied") from None
    except IsADirectoryError:
        raise DicomError(path, "is a folder, expected a DICOM file") from None
    except Exception as exc:  # pydicom raises many types on corrupt input
        raise DicomError(path, f"not a readable DICOM file ({type(exc).__name__}: {_short(exc)})") from None


def _short(exc: BaseException, limit: int = 160) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _search_item(item: Dataset, keyword: str, depth: int) -> Any:
    if keyword in item:
        return item[keyword].value
    if depth <= 0:
        return None
    for elem in item:
        if elem.VR == "SQ" and elem.value:
            for sub in elem.value:
                found = _search_item(sub, keyword, depth - 1)
                if found is not None:
                    return found
    return None


def lookup(ds: Dataset, keyword: str, frame: int | None = None) -> Any:
    """A value from the frame's functional group, the shared groups or the top level."""
    items: list[Dataset] = []
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    if frame is not None and per_frame is not None and 0 <= frame < len(per_frame):
        items.append(per_frame[frame])
    shared = ds.get("SharedFunctionalGroupsSequence")
    if shared:
        items.append(shared[0])
    for item in items:
        found = _search_item(item, keyword, 2)
        if found is not None and found != "":
            return found
    if keyword in ds:
        value = ds[keyword].value
        if value is not None and value != "":
            return value
    return None


def _floats(
    path: Path,
    ds: Dataset,
    keyword: str,
    count: int | None,
    frame: int | None = None,
    *,
    required: bool = True,
) -> list[float] | None:
    value = lookup(ds, keyword, frame)
    if value is None or (isinstance(value, (list, tuple)) and len(value) == 0):
        if required:
            raise DicomError(path, f"missing {tag_name(keyword)}")
        return None
    values = list(value) if isinstance(value, (list, tuple, pydicom.multival.MultiValue)) else [value]
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError):
        raise DicomError(path, f"{tag_name(keyword)} is not numeric: {str(value)[:80]!r}") from None
    if count is not None and len(out) != count:
        raise DicomError(path, f"{tag_name(keyword)} must hold {count} numbers, got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise DicomError(path, f"{tag_name(keyword)} holds a NaN or infinite value")
    return out


def _float(path: Path, ds: Dataset, keyword: str, frame: int | None = None, *, default: float | None = None) -> float:
    values = _floats(path, ds, keyword, None, frame, required=default is None)
    if values is None:
        assert default is not None
        return default
    return values[0]


def _int(path: Path, ds: Dataset, keyword: str, *, default: int | None = None, low: int = 1) -> int:
    value = ds.get(keyword)
    if value is None or value == "":
        if default is None:
            raise DicomError(path, f"missing {tag_name(keyword)}")
        return default
    try:
        out = int(value)
    except (TypeError, ValueError):
        raise DicomError(path, f"{tag_name(keyword)} is not an integer: {str(value)[:40]!r}") from None
    if out < low:
        raise DicomError(path, f"{tag_name(keyword)} must be >= {low}, got {out}")
    return out


def _text(ds: Dataset, keyword: str) -> str:
    try:
        value = ds.get(keyword)
    except Exception:
        return ""
    if value is None:
        return ""
    if isinstance(value, (list, tuple, pydicom.multival.MultiValue)):
        return "\\".join(str(v) for v in value)
    return str(value).strip()


def _sop_class(ds: Dataset) -> str:
    return _text(ds, "SOPClassUID") or _text(getattr(ds, "file_meta", Dataset()), "MediaStorageSOPClassUID")


def _frames(path: Path, ds: Dataset) -> int:
    return _int(path, ds, "NumberOfFrames", default=1)


def _check_pixel_module(path: Path, ds: Dataset, frames: int) -> tuple[int, int]:
    if "PixelData" not in ds:
        for keyword in ("FloatPixelData", "DoubleFloatPixelData"):
            if keyword in ds:
                raise DicomError(path, f"{tag_name(keyword)} is not supported (integer PixelData expected)")
        raise DicomError(path, f"no image: missing {tag_name('PixelData')}")
    rows = _int(path, ds, "Rows")
    cols = _int(path, ds, "Columns")
    samples = _int(path, ds, "SamplesPerPixel", default=1)
    if samples != 1:
        raise DicomError(path, f"{tag_name('SamplesPerPixel')} is {samples}: only grayscale images are read")
    photometric = _text(ds, "PhotometricInterpretation") or "MONOCHROME2"
    if photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise DicomError(path, f"{tag_name('PhotometricInterpretation')} {photometric}: grayscale expected")
    bits = _int(path, ds, "BitsAllocated")
    if bits not in (8, 16, 32):
        raise DicomError(path, f"{tag_name('BitsAllocated')} {bits} is not supported")
    if rows * cols * frames * bits // 8 > MAX_PIXEL_BYTES:
        raise DicomError(path, f"image too large: {frames} x {rows} x {cols} pixels of {bits} bits")
    return rows, cols


def _transfer_syntax(ds: Dataset) -> UID | None:
    meta = getattr(ds, "file_meta", None)
    ts = meta.get("TransferSyntaxUID") if meta is not None else None
    return UID(str(ts)) if ts else None


def _pixels(path: Path, ds: Dataset, index: int | None = None) -> NDArray[Any]:
    """Decoded stored values (all frames, or frame ``index``), as pydicom gives them."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arr = pydicom.pixels.pixel_array(ds, index=index) if index is not None else ds.pixel_array
    except Exception as exc:
        ts = _transfer_syntax(ds)
        what = f"transfer syntax {ts.name} ({ts})" if ts is not None else "an unknown transfer syntax"
        if ts is not None and ts.is_compressed:
            hint = "; compressed pixel data needs a decoder (pip install pylibjpeg pylibjpeg-libjpeg)"
        else:
            hint = ""
        raise DicomError(path, f"cannot decode {tag_name('PixelData')} in {what}: {_short(exc)}{hint}") from None
    return np.asarray(arr)


def _max_stored(ds: Dataset) -> float:
    try:
        bits = int(ds.get("BitsStored") or ds.get("BitsAllocated") or 16)
        signed = int(ds.get("PixelRepresentation") or 0) == 1
    except (TypeError, ValueError):
        bits, signed = 16, False
    bits = min(max(bits, 1), 32)
    return float(2 ** (bits - 1) - 1 if signed else 2**bits - 1)


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
    data = np.empty((len(slices), ref.rows, ref.cols), dtype=np.float32)
    for k, s in enumerate(slices):
        pixels = s.load()
        if pixels.shape != (ref.rows, ref.cols):
            raise DicomError(
                s.source, f"{tag_name('PixelData')} has shape {pixels.shape}, expected {ref.rows}x{ref.cols}"
            )
        data[k] = pixels.astype(np.float32) * np.float32(s.slope) + np.float32(s.intercept)
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


def _slice_from_dataset(path: Path, ds: Dataset) -> _Slice:
    rows, cols = _check_pixel_module(path, ds, 1)
    iop = _orientation(path, _floats(path, ds, "ImageOrientationPatient", 6) or [])
    ipp = np.asarray(_floats(path, ds, "ImagePositionPatient", 3), dtype=np.float64)
    spacing = _floats(path, ds, "PixelSpacing", 2) or []
    if min(spacing) <= 0:
        raise DicomError(path, f"{tag_name('PixelSpacing')} must be positive, got {spacing}")
    slope = _float(path, ds, "RescaleSlope", default=1.0)
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
                cache["all"] = pixels.reshape(frames, rows, cols) if frames > 1 else pixels[None]
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
                slope=_float(path, ds, "RescaleSlope", n, default=1.0),
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
        "source": str(path),
        "format": kind,
        "modality": _text(ds, "Modality"),
        "sop_class": _sop_class(ds),
        "series_uid": _text(ds, "SeriesInstanceUID"),
        "frame_of_reference_uid": _text(ds, "FrameOfReferenceUID"),
        "series_description": _text(ds, "SeriesDescription"),
    }


def _candidate_files(folder: Path) -> list[Path]:
    files: list[Path] = []
    for root, dirs, names in os.walk(folder, followlinks=False):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(names):
            if name.startswith(".") or name.upper() == "DICOMDIR":
                continue
            p = Path(root) / name
            if p.is_symlink() or not p.is_file():
                continue
            files.append(p)
            if len(files) > MAX_FOLDER_FILES:
                raise DicomError(folder, f"holds more than {MAX_FOLDER_FILES} files")
    return files


def read_series(folder: str | os.PathLike[str], *, label: str | None = None) -> Volume:
    """A volume from a folder of single-frame slices (or holding one multi-frame file)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DicomError(folder, "not a folder")
    datasets: list[tuple[Path, Dataset]] = []
    skipped: list[str] = []
    for p in _candidate_files(folder):
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
    if len(datasets) == 1 and _frames(*datasets[0]) > 1:
        return _enhanced_volume(datasets[0][0], datasets[0][1], label=label)
    for p, ds in datasets:
        if _frames(p, ds) > 1:
            raise DicomError(p, f"multi-frame file ({tag_name('NumberOfFrames')}) mixed with single slices")
    slices = [_slice_from_dataset(p, ds) for p, ds in datasets]
    first = datasets[0][1]
    meta = _volume_meta(folder, first, "slice series")
    meta["skipped_files"] = skipped[:20]
    return _stack(slices, folder, label=label or _volume_label(first, folder, "series"), meta=meta)


def read_npz(path: str | os.PathLike[str]) -> Volume:
    """The project's volume file: arrays ``data`` (k, j, i), ``index_to_world`` (4x4), ``label``."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in ("data", "index_to_world") if k not in npz.files]
            if missing:
                raise DicomError(path, f"missing array(s) {', '.join(missing)} in the .npz volume")
            data = np.asarray(npz["data"])
            affine = np.asarray(npz["index_to_world"], dtype=np.float64)
            label = str(npz["label"]) if "label" in npz.files else path.name
    except DicomError:
        raise
    except FileNotFoundError:
        raise DicomError(path, "no such file") from None
    except Exception as exc:
        raise DicomError(path, f"not a readable .npz volume ({type(exc).__name__}: {_short(exc)})") from None
    try:
        return Volume(data=data, index_to_world=affine, label=label, meta={"source": str(path), "format": "npz"})
    except ValueError as exc:
        raise DicomError(path, str(exc)) from None


def read_volume(path: str | os.PathLike[str], *, label: str | None = None) -> Volume:
    """A volume from a DICOM folder, an enhanced multi-frame file or the project's ``.npz``."""
    path = Path(path)
    if not path.exists():
        raise DicomError(path, "no such file or folder")
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
# X-ray images
# --------------------------------------------------------------------------------------
def _is_xray(ds: Dataset) -> bool:
    sop = _sop_class(ds)
    if sop in XRAY_CLASSES:
        return True
    if sop in ENHANCED_VOLUME_CLASSES or sop == CTImageStorage or "ImageOrientationPatient" in ds:
        return False
    return _text(ds, "Modality").upper() in ("XA", "RF")


def _frames_safe(ds: Dataset) -> int:
    try:
        return max(1, int(ds.get("NumberOfFrames") or 1))
    except (TypeError, ValueError):
        return 1


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


def _geometry(
    path: Path,
    ds: Dataset,
    frame: int,
    frames: int,
    rows: int,
    cols: int,
    isocenter_mm: tuple[float, float, float],
) -> tuple[CArm, dict]:
    primary, secondary, angle_source = _frame_angles(path, ds, frame, frames)
    sid = _float(path, ds, "DistanceSourceToDetector", frame)
    sod_values = _floats(path, ds, "DistanceSourceToPatient", None, frame, required=False)
    if sod_values is None:
        sod_values = _floats(path, ds, "DistanceSourceToIsocenter", None, frame, required=False)
    if sod_values is None:
        raise DicomError(path, f"missing {tag_name('DistanceSourceToPatient')}")
    spacing = _floats(path, ds, "ImagerPixelSpacing", 2, frame, required=False)
    spacing_tag = "ImagerPixelSpacing"
    if spacing is None:
        spacing = _floats(path, ds, "PixelSpacing", 2, frame, required=False)
        spacing_tag = "PixelSpacing"
        if spacing is None:
            raise DicomError(path, f"missing {tag_name('ImagerPixelSpacing')} (and no PixelSpacing)")
        warnings.warn(
            f"{path}: no {tag_name('ImagerPixelSpacing')}; using {tag_name('PixelSpacing')} {spacing} as the "
            "spacing at the detector",
            stacklevel=3,
        )
    try:
        geometry = CArm(
            primary_deg=primary,
            secondary_deg=secondary,
            sid_mm=sid,
            sod_mm=sod_values[0],
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
    return geometry, {"angles_from": angle_source, "pixel_spacing_from": spacing_tag}


def _intensity_to_attenuation(
    path: Path, ds: Dataset, stored: NDArray[Any], frame: int, field: NDArray[np.bool_]
) -> tuple[NDArray[np.float32], dict]:
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
    if sign_value is None or sign_value == "":
        sign = 1
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
        rescale_slope=slope,
        rescale_intercept=intercept,
    )
    return att.astype(np.float32), info


def _shutter_mask(path: Path, ds: Dataset, rows: int, cols: int) -> NDArray[np.bool_] | None:
    shape = _text(ds, "ShutterShape").upper()
    if not shape:
        return None
    mask = np.ones((rows, cols), dtype=bool)
    rr, cc = np.mgrid[0:rows, 0:cols]
    used = False
    if "CIRCULAR" in shape:
        center = _floats(path, ds, "CenterOfCircularShutter", 2)
        radius = _float(path, ds, "RadiusOfCircularShutter")
        assert center is not None
        mask &= (rr - (center[0] - 1)) ** 2 + (cc - (center[1] - 1)) ** 2 <= radius**2
        used = True
    if "RECTANGULAR" in shape:
        left = _float(path, ds, "ShutterLeftVerticalEdge") - 1
        right = _float(path, ds, "ShutterRightVerticalEdge") - 1
        upper = _float(path, ds, "ShutterUpperHorizontalEdge") - 1
        lower = _float(path, ds, "ShutterLowerHorizontalEdge") - 1
        mask &= (cc >= left) & (cc <= right) & (rr >= upper) & (rr <= lower)
        used = True
    return mask if used else None


def _border_mask(stored: NDArray[Any]) -> NDArray[np.bool_] | None:
    """False where the image holds the corners' constant value, connected to the border."""
    corners = {stored[0, 0].item(), stored[0, -1].item(), stored[-1, 0].item(), stored[-1, -1].item()}
    if len(corners) != 1:
        return None
    value = corners.pop()
    same = stored == value
    labels, _ = ndimage.label(same)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    border = border[border > 0]
    outside = np.isin(labels, border)
    if outside.all():
        return None
    return ~outside


def _field_rotation(path: Path, ds: Dataset, image: NDArray[Any]) -> tuple[NDArray[Any], str | None]:
    rotation_value = ds.get("FieldOfViewRotation")
    flip = _text(ds, "FieldOfViewHorizontalFlip").upper() == "YES"
    try:
        rotation = int(float(rotation_value)) % 360 if rotation_value not in (None, "") else 0
    except (TypeError, ValueError):
        raise DicomError(path, f"{tag_name('FieldOfViewRotation')} is not a number") from None
    if rotation % 90:
        raise DicomError(path, f"{tag_name('FieldOfViewRotation')} {rotation} is not a multiple of 90")
    if rotation == 0 and not flip:
        return image, None
    if flip:
        image = image[..., ::-1]
    image = np.rot90(image, k=rotation // 90, axes=(-2, -1))
    note = f"undid FieldOfViewRotation {rotation} deg" + (" and horizontal flip" if flip else "")
    warnings.warn(f"{path}: {note} to restore the CONVENTIONS §3 image axes", stacklevel=3)
    return np.ascontiguousarray(image), note


def _xray_kind(ds: Dataset, kind: str | None) -> tuple[str, str]:
    """The XRayImage kind and the acquisition type guessed from the header."""
    from registration.xray import IMAGE_KINDS

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
) -> XRayImage:
    """An XA/RF image (one frame) as attenuation line integrals with its field mask and C-arm.

    ``frame`` is 0-based; a multi-frame file read without it gives frame 0 and a warning.
    ``isocenter_mm`` places the iso-center (default: the world origin, CONVENTIONS §1).
    """
    from registration.xray import XRayImage

    path = Path(path)
    iso = np.asarray(isocenter_mm, dtype=np.float64).reshape(-1)
    if iso.shape != (3,) or not np.all(np.isfinite(iso)):
        raise ValueError(f"isocenter_mm must be three finite numbers, got {isocenter_mm}")
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
    if frame is None:
        if frames > 1:
            warnings.warn(f"{path}: {frames} frames; using frame 0 (choose one with --frame)", stacklevel=2)
        frame = 0
    if not 0 <= int(frame) < frames:
        raise DicomError(path, f"frame {frame} out of range: {tag_name('NumberOfFrames')} is {frames}")
    frame = int(frame)
    stored = _pixels(path, ds, index=frame if frames > 1 else None)
    if stored.ndim == 3 and stored.shape[0] == 1:
        stored = stored[0]
    if stored.shape != (rows, cols):
        raise DicomError(path, f"{tag_name('PixelData')} decodes to shape {stored.shape}, expected {rows}x{cols}")
    stored, rotation_note = _field_rotation(path, ds, stored)
    rows, cols = stored.shape
    geometry, geo_info = _geometry(path, ds, frame, frames, rows, cols, (float(iso[0]), float(iso[1]), float(iso[2])))
    shutter = None if rotation_note else _shutter_mask(path, ds, rows, cols)
    border = _border_mask(stored)
    if shutter is None and border is None:
        warnings.warn(
            f"{path}: no shutter ({tag_name('ShutterShape')}) and no constant collimator border; using the "
            "whole image as the field",
            stacklevel=2,
        )
        mask = np.ones((rows, cols), dtype=bool)
        mask_source = "whole image"
    else:
        mask = np.ones((rows, cols), dtype=bool)
        sources = []
        if shutter is not None:
            mask &= shutter
            sources.append("shutter")
        if border is not None:
            mask &= border
            sources.append("constant border")
        mask_source = " and ".join(sources)
    if not mask.any():
        raise DicomError(path, f"the field is empty (shutter {tag_name('ShutterShape')} or pixel values)")
    image, intensity = _intensity_to_attenuation(path, ds, stored, frame, mask)
    image = np.where(mask, image, np.float32(0.0)).astype(np.float32)
    meta: dict[str, Any] = {
        "source": str(path),
        "format": XRAY_CLASSES.get(sop, modality),
        "modality": modality,
        "frame": frame,
        "frames": frames,
        "mask_from": mask_source,
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
    return [_frame_angles(path, ds, n, frames)[:2] for n in range(frames)]


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
def _ds_number(value: float) -> str:
    """A DS string (at most 16 characters) holding ``value`` as exactly as DS allows."""
    for digits in range(15, 5, -1):
        text = f"{value:.{digits}g}"
        if len(text) <= 16:
            return text
    return f"{value:.6g}"


def make_uid(seed: str | None, *parts: object) -> UID:
    """A new UID, or a reproducible one derived from ``seed`` and ``parts``."""
    if seed is None:
        return generate_uid()
    return generate_uid(entropy_srcs=[seed, *(str(p) for p in parts)])


def _base(
    sop_class: UID,
    modality: str,
    *,
    study_uid: UID,
    series_uid: UID,
    instance_uid: UID,
    series_number: int,
    description: str,
    patient_name: str,
    patient_id: str,
) -> Dataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = instance_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = IMPLEMENTATION_UID
    meta.ImplementationVersionName = "ROADMAP3D"
    ds = Dataset()
    ds.file_meta = meta
    now = datetime.now(UTC)
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = instance_uid
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = now.strftime("%H%M%S")
    ds.AccessionNumber = ""
    ds.Modality = modality
    ds.Manufacturer = "roadmap3d"
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = "roadmap3d"
    ds.SeriesDescription = description
    ds.PatientName = patient_name
    ds.PatientID = patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = "O"
    ds.PatientPosition = "HFS"
    ds.StudyInstanceUID = study_uid
    ds.SeriesInstanceUID = series_uid
    ds.StudyID = "1"
    ds.SeriesNumber = series_number
    ds.PatientOrientation = ""
    return ds


def _save(ds: Dataset, path: Path) -> None:
    ds.save_as(path, enforce_file_format=True)


def _read_umask() -> int:
    mask = os.umask(0o022)  # the only portable way to read it: set and restore
    os.umask(mask)
    return mask


#: Read once at import (os.umask is process-wide; reading it later could race other threads).
_UMASK = _read_umask()


def _umask() -> int:
    return _UMASK


@contextmanager
def _atomic_path(path: Path) -> Iterator[Path]:
    """A temporary sibling of ``path`` renamed onto it when the block succeeds."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.chmod(0o666 & ~_umask())  # mkstemp makes it private; the result gets the usual mode
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_folder(folder: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary sibling folder renamed to ``folder`` (absent or empty) when the block succeeds."""
    folder = Path(folder)
    if folder.exists():
        if not folder.is_dir():
            raise ValueError(f"{folder}: exists and is not a folder")
        if any(folder.iterdir()):
            raise ValueError(f"{folder}: exists and is not empty; refusing to write into it")
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        if folder.exists():
            folder.rmdir()
        os.replace(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write a text file through a temporary file, never leaving a partial one."""
    with _atomic_path(Path(path)) as tmp:
        tmp.write_text(text)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write a binary file through a temporary file, never leaving a partial one."""
    with _atomic_path(Path(path)) as tmp:
        tmp.write_bytes(data)


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
            ds.PixelData = np.ascontiguousarray(pixels[k]).tobytes()
            name = f"slice_{k:04d}.dcm"
            _save(ds, tmp / name)
            written.append(Path(folder) / name)
    return written


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
    ds.SharedFunctionalGroupsSequence = DicomSequence([shared])
    per_frame = []
    for k in range(nk):
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
        per_frame.append(item)
    ds.PerFrameFunctionalGroupsSequence = DicomSequence(per_frame)
    ds.PixelData = _hu_to_int16(volume.data).tobytes()
    path = Path(path)
    with _atomic_path(path) as tmp:
        _save(ds, tmp)
    return path


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


def _encode_attenuation(image: NDArray[Any], mask: NDArray[np.bool_]) -> NDArray[np.uint16]:
    upward = np.rint(np.asarray(image, dtype=np.float64) * LOG_UNITS_PER_ATTENUATION) + LOG_ZERO_VALUE
    stored = np.where(mask, np.clip(65535 - upward, NO_SIGNAL_VALUE + 1, 65535), NO_SIGNAL_VALUE)
    return stored.astype(np.uint16)


def write_xray(
    images: XRayImage | Sequence[XRayImage],
    path: str | os.PathLike[str],
    *,
    study_uid: str | None = None,
    uid_seed: str | None = None,
    description: str | None = None,
    patient_name: str = "roadmap3d^phantom",
    patient_id: str = "ROADMAP3D",
) -> Path:
    """Write one XA image, or a multi-frame XA run (per-frame angles), per the module docstring.

    Frames of a run share size, distances and pixel spacing; their angles are stored as the
    first frame's PositionerPrimary/SecondaryAngle plus a per-frame vector of offsets in the
    angle increment tags. The circular field goes into the shutter module and into the pixel
    values (NO_SIGNAL_VALUE outside the field). Only the nominal geometry is stored: DICOM
    has no place for the bending shifts of a true geometry.
    """
    frames = [images] if not isinstance(images, Sequence) else list(images)
    if not frames:
        raise ValueError("no image to write")
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
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.InstanceNumber = 1
    ds.ImageComments = (
        f"roadmap3d {kind}: attenuation line integral = (65535 - {LOG_ZERO_VALUE} - stored value) / "
        f"{LOG_UNITS_PER_ATTENUATION:g} (LOG, sign +1); {NO_SIGNAL_VALUE} outside the field"
    )
    ds.AcquisitionDateTime = datetime.now(UTC).strftime("%Y%m%d%H%M%S")
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
        ds.FrameTime = "33.3"
        ds.FrameIncrementPointer = tag_for_keyword("FrameTime")
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
    ds.PixelData = stored.tobytes()
    path = Path(path)
    with _atomic_path(path) as tmp:
        _save(ds, tmp)
    return path


# --------------------------------------------------------------------------------------
# inspect (for `roadmap3d info`)
# --------------------------------------------------------------------------------------
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


def inspect(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What the project reads from ``path``: kind, geometry, shape, spacing, value range.

    Never raises for bad input: the result says ``accepted: False`` and gives the ``problem``;
    for a DICOM file the ``header`` entry lists the tags the readers look at.
    """
    path = Path(path)
    out: dict[str, Any] = {"path": str(path)}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if path.is_dir() or path.suffix.lower() == ".npz":
                out.update(_inspect_volume(read_volume(path)))
            else:
                ds = read_dataset(path, stop_before_pixels=True)
                out["sop_class"] = UID(_sop_class(ds)).name if _sop_class(ds) else ""
                out["modality"] = _text(ds, "Modality")
                ts = _transfer_syntax(ds)
                out["transfer_syntax"] = ts.name if ts is not None else ""
                out["header"] = {k: _text(ds, k) for k in HEADER_TAGS if _text(ds, k)}
                if _is_xray(ds):
                    out.update(_inspect_xray(path, ds))
                else:
                    out.update(_inspect_volume(read_volume(path)))
            out["accepted"] = True
        except (ValueError, OSError) as exc:
            out["accepted"] = False
            out["problem"] = str(exc)
    out["warnings"] = sorted({str(w.message) for w in caught})
    return out


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
    }


def _inspect_xray(path: Path, header: Dataset) -> dict[str, Any]:
    frames = _frames(path, header)
    image = read_xray(path, frame=0)
    sign = image.meta.get("pixel_intensity_relationship_sign")
    out: dict[str, Any] = {
        "kind": "xray",
        "format": image.meta.get("format", ""),
        "image_kind": image.kind,
        "frames": frames,
        "geometry": image.geometry.to_dict(),
        "field_pixels": int(image.mask.sum()),
        "mask_from": image.meta.get("mask_from"),
        "intensity": f"{image.meta.get('pixel_intensity_relationship')}, sign {sign:+d}",
        "attenuation_range": [round(v, 4) for v in _range(image.image[image.mask])],
    }
    if frames > 1:
        angles = read_xray_angles(path)
        out["angles_deg"] = [[round(a, 3), round(b, 3)] for a, b in angles[:12]] + (["..."] if frames > 12 else [])
    return out


# --------------------------------------------------------------------------------------
# Uploads (the web app): unpack a zip safely
# --------------------------------------------------------------------------------------
def _safe_member_name(name: str) -> PurePosixPath | None:
    if "\x00" in name:
        raise UploadError(f"refused archive member {name!r}: NUL character in the name")
    normalized = name.replace("\\", "/")
    if normalized.startswith("/") or (len(normalized) > 1 and normalized[1] == ":"):
        raise UploadError(f"refused archive member {name!r}: absolute path")
    parts = [p for p in normalized.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise UploadError(f"refused archive member {name!r}: '..' in the path")
    return PurePosixPath(*parts) if parts else None


def unpack_upload(
    zip_bytes: bytes,
    dest_dir: str | os.PathLike[str],
    *,
    max_bytes: int,
    max_files: int = 10000,
    max_ratio: float = 200.0,
) -> list[Path]:
    """Unpack an uploaded zip into ``dest_dir`` (created private, or empty) and list the files.

    Refused with :class:`UploadError` (nothing left behind): not a zip; more than
    ``max_bytes`` compressed or uncompressed (counted while inflating, so lying headers do not
    help a zip bomb); more than ``max_files`` members; a member compressed more than
    ``max_ratio`` times; absolute names, ``..``, links, encrypted or duplicate members.
    Directories in the archive are recreated; no path from the archive is trusted.
    """
    if max_bytes <= 0:
        raise ValueError(f"max_bytes must be positive, got {max_bytes}")
    if len(zip_bytes) > max_bytes:
        raise UploadError(f"upload of {len(zip_bytes)} bytes exceeds the limit of {max_bytes} bytes")
    dest = Path(dest_dir)
    if dest.exists():
        if not dest.is_dir() or dest.is_symlink():
            raise UploadError(f"{dest}: not a folder")
        if any(dest.iterdir()):
            raise UploadError(f"{dest}: not empty")
    else:
        dest.mkdir(mode=0o700, parents=True)
    try:
        archive = zipfile.ZipFile(io.BytesIO(zip_bytes))
        members = archive.infolist()
    except Exception as exc:  # zipfile raises many types on corrupt archives
        raise UploadError(f"not a readable zip archive ({type(exc).__name__}: {_short(exc)})") from None
    written: list[Path] = []
    try:
        if len(members) > max_files:
            raise UploadError(f"archive holds {len(members)} members, more than {max_files}")
        declared = sum(max(0, m.file_size) for m in members)
        if declared > max_bytes:
            raise UploadError(f"archive unpacks to {declared} bytes, more than the limit of {max_bytes}")
        seen: set[str] = set()
        total = 0
        root = dest.resolve()
        for member in members:
            relative = _safe_member_name(member.filename)
            if relative is None:  # "./" and the like: the upload folder itself
                continue
            mode = (member.external_attr >> 16) & 0o170000
            if mode == stat.S_IFLNK:
                raise UploadError(f"refused archive member {member.filename!r}: symbolic link")
            if mode not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise UploadError(f"refused archive member {member.filename!r}: not a regular file")
            if member.flag_bits & 0x1:
                raise UploadError(f"refused archive member {member.filename!r}: encrypted")
            key = str(relative).lower()
            if key in seen:
                raise UploadError(f"refused archive member {member.filename!r}: duplicate name")
            seen.add(key)
            target = dest.joinpath(*relative.parts)
            if not target.resolve().is_relative_to(root):
                raise UploadError(f"refused archive member {member.filename!r}: leaves the upload folder")
            if member.is_dir() or mode == stat.S_IFDIR:
                target.mkdir(mode=0o700, parents=True, exist_ok=True)
                continue
            if member.compress_size > 0 and member.file_size / member.compress_size > max_ratio:
                raise UploadError(f"refused archive member {member.filename!r}: compression ratio above {max_ratio:g}")
            target.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            if not target.parent.resolve().is_relative_to(root):
                raise UploadError(f"refused archive member {member.filename!r}: leaves the upload folder")
            flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
            fd = os.open(target, flags, 0o600)
            written.append(target)
            with os.fdopen(fd, "wb") as out, archive.open(member) as src:
                while True:
                    chunk = src.read(1 << 16)
                    if not chunk:
                        break
                    total += len(chunk)
                    if total > max_bytes:
                        raise UploadError(f"archive unpacks to more than the limit of {max_bytes} bytes")
                    out.write(chunk)
    except UploadError:
        _remove_tree_contents(dest)
        raise
    except Exception as exc:  # corrupt members: zlib.error, NotImplementedError, EOFError, ...
        _remove_tree_contents(dest)
        raise UploadError(f"cannot unpack the archive ({type(exc).__name__}: {_short(exc)})") from None
    finally:
        archive.close()
    return written


def _remove_tree_contents(folder: Path) -> None:
    for child in folder.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)


def classify_upload(folder: str | os.PathLike[str]) -> dict[str, Path | None]:
    """Find the volume (series folder or multi-frame/.npz file) and the XA/RF file in ``folder``."""
    folder = Path(folder)
    xray: Path | None = None
    volume_files: list[Path] = []
    npz: Path | None = None
    for p in _candidate_files(folder):
        if p.suffix.lower() == ".npz":
            npz = npz or p
            continue
        try:
            ds = read_dataset(p, stop_before_pixels=True)
        except DicomError:
            continue
        if _is_xray(ds):
            xray = xray or p
        else:
            volume_files.append(p)
    volume: Path | None = npz
    if volume is None and volume_files:
        parents = {p.parent for p in volume_files}
        volume = volume_files[0] if len(volume_files) == 1 else Path(os.path.commonpath(sorted(parents)))
    return {"volume": volume, "image": xray}


def json_dumps(data: Any) -> str:
    """Indented JSON with numpy values converted and each list of numbers on one line."""

    def plain(obj: Any) -> Any:
        if isinstance(obj, dict):
            return {str(k): plain(v) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            return [plain(v) for v in obj]
        if isinstance(obj, np.ndarray):
            return plain(obj.tolist())
        if isinstance(obj, (np.floating, np.integer, np.bool_)):
            return obj.item()
        if isinstance(obj, Path):
            return str(obj)
        return obj

    def flat(obj: Any) -> bool:
        return isinstance(obj, list) and all(
            isinstance(v, (int, float, bool, str)) or v is None or (isinstance(v, list) and flat(v) and len(v) <= 4)
            for v in obj
        )

    def dump(obj: Any, level: int) -> str:
        pad, inner = "  " * level, "  " * (level + 1)
        if isinstance(obj, dict) and obj:
            items = [f"{inner}{json.dumps(k)}: {dump(v, level + 1)}" for k, v in obj.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        if isinstance(obj, list) and obj and not flat(obj):
            return "[\n" + ",\n".join(inner + dump(v, level + 1) for v in obj) + "\n" + pad + "]"
        if isinstance(obj, list) and obj and isinstance(obj[0], list):
            rows = [json.dumps(v) for v in obj]
            return "[" + (",\n" + inner).join(rows) + "]"
        return json.dumps(obj)

    return dump(plain(data), 0) + "\n"
