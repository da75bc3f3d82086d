"""Shared by the DICOM readers and writers: errors, constants, tag lookups, dataset basics.

Errors are :class:`DicomError` (a ``ValueError``) naming the file and the tag.
"""

from __future__ import annotations

import math
import os
import warnings
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
from numpy.typing import NDArray
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import (
    PYDICOM_IMPLEMENTATION_UID,
    UID,
    CTImageStorage,
    EnhancedCTImageStorage,
    EnhancedXAImageStorage,
    EnhancedXRFImageStorage,
    ExplicitVRLittleEndian,
    LegacyConvertedEnhancedCTImageStorage,
    XRay3DAngiographicImageStorage,
    XRay3DCraniofacialImageStorage,
    XRayAngiographicImageStorage,
    XRayRadiofluoroscopicImageStorage,
    generate_uid,
)

from registration.io.dicom._errors import DicomError, UploadError, tag_name  # noqa: F401 - re-exported
from registration.io.dicom.limits import capped_file, check_dataset_file, check_values

#: Stored LOG pixel steps per unit of attenuation line integral (see :mod:`registration.io.dicom.xray`).
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
    check_dataset_file(path)  # size, and a deflated data set's inflated size, before reading it whole
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                with capped_file(path) as fh:
                    ds = pydicom.dcmread(fh, stop_before_pixels=stop_before_pixels)
            except InvalidDicomError:
                with capped_file(path) as fh:
                    ds = pydicom.dcmread(fh, stop_before_pixels=stop_before_pixels, force=True)
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
    check_values(path, keyword, out)  # plausible ranges of geometry and rescale tags
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


#: pydicom decoding plugins in order of preference, by family of transfer syntax. All are
#: permissively licensed: GDCM (python-gdcm) for JPEG and JPEG-LS, pylibjpeg's openjpeg and rle
#: plugins for JPEG 2000 and RLE. pylibjpeg-libjpeg (GPL-3.0) is an optional extra
#: (``roadmap3d[gpl-jpeg]``), used only where GDCM cannot decode: 12-bit JPEG extended.
_PREFERENCE = {
    "JPEG 2000": ("pylibjpeg", "gdcm", "pillow"),
    "RLE": ("pylibjpeg", "pydicom"),
    "": ("gdcm", "pylibjpeg", "pillow"),
}
#: The distribution behind each plugin, by family (for the description users see).
_PACKAGES = {"gdcm": "python-gdcm", "pillow": "pillow", "pydicom": "pydicom"}
_PYLIBJPEG_PLUGINS = {"JPEG 2000": "pylibjpeg-openjpeg", "RLE": "pylibjpeg-rle", "": "pylibjpeg-libjpeg"}
_GPL_HINT = "pip install 'roadmap3d[gpl-jpeg]' adds pylibjpeg-libjpeg (GPL-3.0), which decodes it"


def _family(ts: UID) -> str:
    return next((k for k in ("JPEG 2000", "RLE") if ts.name.startswith(k)), "")


def pixel_decoder(ds: Dataset) -> tuple[str, str]:
    """The pydicom decoding plugin that reads ``ds``'s pixel data and a description for users.

    ``("", "native (uncompressed)")`` for uncompressed data; ``("", "none installed ...")``
    when no plugin can decode the transfer syntax. 12-bit JPEG extended, which GDCM does not
    decode, goes to pylibjpeg-libjpeg when that optional plugin is installed.
    """
    ts = _transfer_syntax(ds)
    if ts is None or not ts.is_transfer_syntax or not ts.is_compressed:  # is_compressed raises on other UIDs
        return "", "native (uncompressed)"
    try:
        from pydicom.pixels import get_decoder

        decoder = get_decoder(ts)
    except (NotImplementedError, ValueError):
        return "", f"none: pydicom has no decoder for {ts.name}"
    plugins = tuple(decoder.available_plugins)
    if not plugins:
        return "", f"none installed for {ts.name} (pip install python-gdcm pylibjpeg pylibjpeg-openjpeg)"
    family = _family(ts)
    order = _PREFERENCE[family]
    if ts.name.startswith("JPEG Extended") and _int_or(ds, "BitsStored", 8) > 8:
        order = ("pylibjpeg", *order)
    plugin = next((p for p in order if p in plugins), plugins[0])
    from importlib.metadata import PackageNotFoundError, version

    package = _PYLIBJPEG_PLUGINS[family] if plugin == "pylibjpeg" else _PACKAGES.get(plugin, plugin)
    try:
        if plugin == "pylibjpeg":
            return plugin, f"pylibjpeg {version('pylibjpeg')} with {package} {version(package)}"
        return plugin, f"{plugin} ({package} {version(package)})"
    except PackageNotFoundError:
        return plugin, plugin


def _int_or(ds: Dataset, keyword: str, default: int) -> int:
    try:
        return int(ds.get(keyword) or default)
    except (TypeError, ValueError):
        return default


def _pixels(path: Path, ds: Dataset, index: int | None = None) -> NDArray[Any]:
    """Decoded stored values (all frames, or frame ``index``), as pydicom gives them.

    Compressed data is decoded by :func:`pixel_decoder`'s plugin.
    """
    plugin, _ = pixel_decoder(ds)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arr = pydicom.pixels.pixel_array(ds, index=index, decoding_plugin=plugin)
    except Exception as exc:
        ts = _transfer_syntax(ds)
        what = f"transfer syntax {ts.name} ({ts})" if ts is not None else "an unknown transfer syntax"
        if ts is not None and not ts.is_transfer_syntax:
            what = f"{tag_name('TransferSyntaxUID')} {str(ts)[:64]!r}, which is not a transfer syntax"
        if ts is not None and ts.is_transfer_syntax and ts.is_compressed and not plugin:
            hint = "; compressed pixel data needs a decoder (pip install python-gdcm pylibjpeg pylibjpeg-openjpeg)"
        elif ts is not None and ts.name.startswith("JPEG Extended") and plugin != "pylibjpeg":
            hint = f"; GDCM does not decode 12-bit JPEG extended: {_GPL_HINT}"
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


def _is_xray(ds: Dataset) -> bool:
    sop = _sop_class(ds)
    if sop in XRAY_CLASSES:
        return True
    if sop in ENHANCED_VOLUME_CLASSES or sop == CTImageStorage or "ImageOrientationPatient" in ds:
        return False
    return _text(ds, "Modality").upper() in ("XA", "RF")


# --------------------------------------------------------------------------------------
# Writing: UIDs and the common header
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
