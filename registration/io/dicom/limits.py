"""Ceilings on what a file may declare, checked before any allocation or loop.

A reader trusts nothing a header says about sizes: before it allocates an array or loops
over frames it calls :func:`check_declared_pixels` (DICOM) or :func:`check_npz_member`
(the project's ``.npz``), which compare the declared size with the bytes really present
and with the ceilings below. A file that declares more is refused in milliseconds with a
:class:`~registration.io.dicom._common.DicomError` naming the tag and the numbers.

The ceilings are generous for clinical data (a 3DRA is 512^3 voxels, a CT a few hundred
512 x 512 slices, an XA run a few hundred 1024^2 frames) and can be raised through the
environment (read at every call, so a running server picks up nothing by surprise: set them
before starting it):

``ROADMAP3D_MAX_VOXELS``
    voxels (rows x columns x frames, summed over the slices of a series); default 2^29
    (536,870,912: 2 GiB as float32).
``ROADMAP3D_MAX_PIXEL_MB``
    megabytes of stored pixel data (declared, or inflated from a compressed member);
    default 2048.
``ROADMAP3D_MAX_FRAMES``
    frames of one multi-frame file, slices of one series; default 20,000.
``ROADMAP3D_MAX_FILE_MB``
    size of one file read whole (a DICOM file, a deflated data set once inflated);
    default 2100.
``ROADMAP3D_MAX_NPZ_RATIO``
    how many times a ``.npz`` member may be compressed (compressed zeros pass every size
    check, then fill the memory); default 100 (the project's own volumes compress 1.2-10x).
"""

from __future__ import annotations

import io
import math
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset
from pydicom.encaps import parse_fragments
from pydicom.uid import DeflatedExplicitVRLittleEndian

from registration.io.dicom._errors import DicomError, tag_name

__all__ = [
    "ReadLimits",
    "capped_file",
    "check_affine",
    "check_dataset_file",
    "check_dataset_pixels",
    "check_declared_pixels",
    "check_file_size",
    "check_folder_bytes",
    "check_frame_count",
    "check_npz_member",
    "check_voxels",
    "check_values",
    "current_limits",
    "VALUE_RANGES",
]

ENV_MAX_VOXELS = "ROADMAP3D_MAX_VOXELS"
ENV_MAX_PIXEL_MB = "ROADMAP3D_MAX_PIXEL_MB"
ENV_MAX_FRAMES = "ROADMAP3D_MAX_FRAMES"
ENV_MAX_FILE_MB = "ROADMAP3D_MAX_FILE_MB"
ENV_MAX_NPZ_RATIO = "ROADMAP3D_MAX_NPZ_RATIO"

#: How to raise a ceiling, appended to every refusal.
RAISE_HINT = "(raise the limit with {env} if the file is genuine)"


@dataclass(frozen=True)
class ReadLimits:
    """The ceilings (see the module docstring); :func:`current_limits` reads the environment."""

    max_voxels: int = 2**29
    max_pixel_bytes: int = 2048 * 1024**2
    max_frames: int = 20000
    max_file_bytes: int = 2100 * 1024**2
    max_npz_ratio: float = 100.0

    def __post_init__(self) -> None:
        for name in ("max_voxels", "max_pixel_bytes", "max_frames", "max_file_bytes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.max_npz_ratio) and self.max_npz_ratio >= 1.0):
            raise ValueError(f"max_npz_ratio must be a finite number >= 1, got {self.max_npz_ratio}")


def _env_number(name: str, default: float) -> float:
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name} must be a number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive number, got {text!r}")
    return value


def current_limits() -> ReadLimits:
    """The default ceilings, overridden by the ``ROADMAP3D_MAX_*`` environment variables."""
    d = ReadLimits()
    return ReadLimits(
        max_voxels=int(_env_number(ENV_MAX_VOXELS, d.max_voxels)),
        max_pixel_bytes=int(_env_number(ENV_MAX_PIXEL_MB, d.max_pixel_bytes / 1024**2) * 1024**2),
        max_frames=int(_env_number(ENV_MAX_FRAMES, d.max_frames)),
        max_file_bytes=int(_env_number(ENV_MAX_FILE_MB, d.max_file_bytes / 1024**2) * 1024**2),
        max_npz_ratio=_env_number(ENV_MAX_NPZ_RATIO, d.max_npz_ratio),
    )


def _mb(n: int) -> str:
    return f"{n / 1024**2:,.1f} MB" if n >= 1024**2 else f"{n:,} bytes"


def check_voxels(
    path: str | os.PathLike[str], shape: tuple[int, ...], *, what: str, limits: ReadLimits | None = None
) -> int:
    """Refuse a volume/image whose ``shape`` (declared) exceeds the voxel ceiling; the voxel count."""
    limits = limits or current_limits()
    if any(int(n) < 1 for n in shape):
        raise DicomError(path, f"{what} {' x '.join(str(int(n)) for n in shape)}: every size must be >= 1")
    voxels = math.prod(int(n) for n in shape)
    if voxels > limits.max_voxels:
        raise DicomError(
            path,
            f"{what} {' x '.join(f'{int(n):,}' for n in shape)} = {voxels:,} voxels is over the limit of "
            f"{limits.max_voxels:,} {RAISE_HINT.format(env=ENV_MAX_VOXELS)}",
        )
    return voxels


def check_file_size(path: str | os.PathLike[str], size: int, *, limits: ReadLimits | None = None) -> None:
    """Refuse a file (or an inflated data set) larger than the file ceiling before reading it whole."""
    limits = limits or current_limits()
    if size > limits.max_file_bytes:
        raise DicomError(
            path,
            f"{_mb(size)} is over the limit of {_mb(limits.max_file_bytes)} for one file "
            f"{RAISE_HINT.format(env=ENV_MAX_FILE_MB)}",
        )


def check_folder_bytes(folder: str | os.PathLike[str], files: list[Path], *, limits: ReadLimits | None = None) -> None:
    """Refuse a series folder whose files together exceed the pixel ceiling plus headers, before
    any is read (every slice is held in memory until the stack is checked)."""
    limits = limits or current_limits()
    total = sum(file_size(p) for p in files)
    allowed = limits.max_pixel_bytes + 64 * 1024 * max(1, len(files))  # pixels plus generous headers
    if total > allowed:
        raise DicomError(
            folder,
            f"its {len(files):,} files hold {_mb(total)}, more than a volume within the limit of "
            f"{_mb(limits.max_pixel_bytes)} of pixels {RAISE_HINT.format(env=ENV_MAX_PIXEL_MB)}",
        )


def check_declared_pixels(
    path: str | os.PathLike[str],
    *,
    rows: int,
    cols: int,
    frames: int,
    samples: int,
    bits_allocated: int,
    pixel_data_bytes: int | None,
    encapsulated_fragments: int | None = None,
    limits: ReadLimits | None = None,
) -> None:
    """Refuse a DICOM image whose declared pixels cannot be in the file or exceed the ceilings.

    ``pixel_data_bytes``: the length of the native (uncompressed) PixelData value, or None if
    encapsulated; then ``encapsulated_fragments`` (the number of fragments) bounds the frames:
    a fragment holds at most one frame (PS3.5 A.4). Python integers: no overflow whatever the
    header says.
    """
    limits = limits or current_limits()
    frames_tag = tag_name("NumberOfFrames")
    check_frame_count(path, frames, limits=limits)
    size = f"{tag_name('Rows')} x {tag_name('Columns')} x {frames_tag}"
    check_voxels(path, (rows, cols, frames), what=size, limits=limits)
    declared_bits = rows * cols * frames * samples * bits_allocated
    declared = (declared_bits + 7) // 8
    if declared > limits.max_pixel_bytes:
        raise DicomError(
            path,
            f"{size} x {tag_name('SamplesPerPixel')} x {tag_name('BitsAllocated')} = {rows} x {cols} x {frames} x "
            f"{samples} x {bits_allocated} bits = {_mb(declared)} is over the limit of {_mb(limits.max_pixel_bytes)} "
            f"{RAISE_HINT.format(env=ENV_MAX_PIXEL_MB)}",
        )
    if pixel_data_bytes is not None and pixel_data_bytes < declared:
        raise DicomError(
            path,
            f"{tag_name('PixelData')} holds {pixel_data_bytes:,} bytes, but {size} x {tag_name('BitsAllocated')} "
            f"({rows} x {cols} x {frames:,} x {bits_allocated} bits) declare {declared:,}: truncated file or "
            "wrong sizes",
        )
    if encapsulated_fragments is not None and frames > max(encapsulated_fragments, 1):
        raise DicomError(
            path,
            f"{frames_tag} is {frames:,} but the compressed {tag_name('PixelData')} holds "
            f"{encapsulated_fragments:,} fragment(s) (at least one per frame)",
        )


def check_npz_member(
    path: str | os.PathLike[str], archive: zipfile.ZipFile, name: str, *, limits: ReadLimits | None = None
) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of array ``name`` in an open ``.npz``, read from its ``.npy`` header only.

    Refused (DicomError) before anything is inflated beyond the header: an object array, a
    header that does not parse, more voxels or bytes than the ceilings, a member whose zip
    size does not match its header, or one compressed more than ``max_npz_ratio`` times.
    """
    limits = limits or current_limits()
    member = f"{name}.npy"
    try:
        info = archive.getinfo(member)
    except KeyError:
        raise DicomError(path, f"missing array {name!r} in the .npz volume") from None
    try:
        with archive.open(info) as stream:
            version = np.lib.format.read_magic(stream)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream, max_header_size=10000)
            elif version in ((2, 0), (3, 0)):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream, max_header_size=10000)
            else:
                raise ValueError(f"unknown .npy format version {version}")
            header_bytes = stream.tell()
    except DicomError:
        raise
    except Exception as exc:  # zipfile/zlib/format errors of a corrupt member
        why = f"{type(exc).__name__}: {exc}"[:200]
        raise DicomError(path, f"array {name!r}: not a readable .npy header ({why})") from None
    del fortran
    if dtype.hasobject:
        raise DicomError(path, f"array {name!r} holds Python objects ({dtype}): refused")
    if any(int(n) < 0 for n in shape):
        raise DicomError(path, f"array {name!r} has a negative size in its shape {shape}")
    count = math.prod(int(n) for n in shape)
    if count > limits.max_voxels:
        raise DicomError(
            path,
            f"array {name!r} of shape {shape} = {count:,} values is over the limit of {limits.max_voxels:,} "
            f"{RAISE_HINT.format(env=ENV_MAX_VOXELS)}",
        )
    nbytes = count * dtype.itemsize
    if nbytes > limits.max_pixel_bytes:
        raise DicomError(
            path,
            f"array {name!r} of shape {shape} ({dtype}) = {_mb(nbytes)} is over the limit of "
            f"{_mb(limits.max_pixel_bytes)} {RAISE_HINT.format(env=ENV_MAX_PIXEL_MB)}",
        )
    if info.file_size != header_bytes + nbytes:
        raise DicomError(
            path,
            f"array {name!r}: the archive says {info.file_size:,} bytes, its header {header_bytes + nbytes:,} "
            "(corrupt or forged .npz)",
        )
    if nbytes > 1024**2 and info.compress_size > 0 and info.file_size / info.compress_size > limits.max_npz_ratio:
        raise DicomError(
            path,
            f"array {name!r} is compressed {info.file_size / info.compress_size:,.0f} times ({_mb(info.compress_size)} "
            f"inflating to {_mb(info.file_size)}): over the limit of {limits.max_npz_ratio:g} for a volume "
            f"(a constant or zero-filled array?) {RAISE_HINT.format(env=ENV_MAX_NPZ_RATIO)}",
        )
    return tuple(int(n) for n in shape), dtype


#: Plausible values of the geometry and rescale tags (inclusive bounds, in the tag's unit); a
#: value outside is refused by every reader (values are also checked to be finite). Zero is
#: refused where it cannot be right (spacing, distances, RescaleSlope: a constant image).
VALUE_RANGES: dict[str, tuple[float, float, bool]] = {
    # keyword: (low, high, zero allowed)
    "PixelSpacing": (1e-4, 100.0, False),  # mm
    "ImagerPixelSpacing": (1e-4, 100.0, False),  # mm
    "ImagePositionPatient": (-1e6, 1e6, True),  # mm
    "ImageOrientationPatient": (-1.001, 1.001, True),  # direction cosines
    "DistanceSourceToDetector": (1.0, 1e5, False),  # mm
    "DistanceSourceToPatient": (1.0, 1e5, False),  # mm
    "DistanceSourceToIsocenter": (1.0, 1e5, False),  # mm
    "PositionerPrimaryAngle": (-360.0, 360.0, True),  # deg
    "PositionerSecondaryAngle": (-360.0, 360.0, True),  # deg
    "PositionerPrimaryAngleIncrement": (-360.0, 360.0, True),  # deg
    "PositionerSecondaryAngleIncrement": (-360.0, 360.0, True),  # deg
    "FieldOfViewRotation": (-360.0, 360.0, True),  # deg
    "RescaleSlope": (-1e6, 1e6, False),
    "RescaleIntercept": (-1e7, 1e7, True),
    "CenterOfCircularShutter": (-1e5, 1e5, True),  # pixels
    "RadiusOfCircularShutter": (0.0, 1e5, True),  # pixels
    "ShutterLeftVerticalEdge": (-1e5, 1e5, True),
    "ShutterRightVerticalEdge": (-1e5, 1e5, True),
    "ShutterUpperHorizontalEdge": (-1e5, 1e5, True),
    "ShutterLowerHorizontalEdge": (-1e5, 1e5, True),
}


def check_values(path: str | os.PathLike[str], keyword: str, values: list[float]) -> None:
    """Refuse a value of ``keyword`` outside :data:`VALUE_RANGES` (other keywords pass)."""
    bounds = VALUE_RANGES.get(keyword)
    if bounds is None:
        return
    low, high, zero_allowed = bounds
    for v in values:
        if not math.isfinite(v):
            raise DicomError(path, f"{tag_name(keyword)} holds a NaN or infinite value")
        if v == 0 and not zero_allowed:
            raise DicomError(path, f"{tag_name(keyword)} is 0: not a usable value")
        if not low <= v <= high and not (v == 0 and zero_allowed):
            raise DicomError(path, f"{tag_name(keyword)} {v:g} is out of range ({low:g} .. {high:g})")
        if keyword.endswith("Spacing") and v < 0:
            raise DicomError(path, f"{tag_name(keyword)} {v:g} is negative")


def check_affine(path: str | os.PathLike[str], index_to_world: np.ndarray, *, what: str = "index_to_world") -> None:
    """Refuse a volume affine whose voxel spacing or origin lies outside the plausible ranges."""
    affine = np.asarray(index_to_world, dtype=np.float64)
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        raise DicomError(path, f"{what} must be a finite 4x4 matrix")
    low, high, _ = VALUE_RANGES["PixelSpacing"]
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if np.any(spacing < low) or np.any(spacing > high):
        raise DicomError(path, f"{what}: voxel spacing {spacing.tolist()} mm is out of range ({low:g} .. {high:g})")
    low, high, _ = VALUE_RANGES["ImagePositionPatient"]
    if np.any(np.abs(affine[:3, 3]) > high):
        raise DicomError(path, f"{what}: origin {affine[:3, 3].tolist()} mm is out of range ({low:g} .. {high:g})")


def check_frame_count(path: str | os.PathLike[str], frames: int, *, limits: ReadLimits | None = None) -> None:
    """Refuse more frames than the ceiling before a loop over them (no pixel data involved)."""
    limits = limits or current_limits()
    if frames > limits.max_frames:
        raise DicomError(
            path,
            f"{tag_name('NumberOfFrames')} {frames:,} is over the limit of {limits.max_frames:,} frames "
            f"{RAISE_HINT.format(env=ENV_MAX_FRAMES)}",
        )


def check_dataset_pixels(
    path: str | os.PathLike[str], ds: Dataset, frames: int, *, limits: ReadLimits | None = None
) -> None:
    """:func:`check_declared_pixels` for a data set whose pixel module was checked (Rows, Columns ... present)."""
    elem = ds["PixelData"]
    value = elem.value if elem.value is not None else b""
    fragments = None
    native_bytes: int | None = len(value)
    if elem.is_undefined_length:  # encapsulated (compressed) pixel data: count the fragments
        native_bytes = None
        try:
            fragments = parse_fragments(value)[0]
        except Exception as exc:  # a corrupt item structure
            why = f"{type(exc).__name__}: {exc}"[:160]
            raise DicomError(path, f"compressed {tag_name('PixelData')} is corrupt ({why})") from None
    bits_allocated = int(ds.BitsAllocated)
    try:
        bits_stored = int(ds.get("BitsStored") or bits_allocated)
    except (TypeError, ValueError):
        raise DicomError(path, f"{tag_name('BitsStored')} is not an integer") from None
    if not 1 <= bits_stored <= bits_allocated:
        raise DicomError(
            path,
            f"{tag_name('BitsStored')} {bits_stored} must lie in 1 .. {tag_name('BitsAllocated')} {bits_allocated}",
        )
    check_declared_pixels(
        path,
        rows=int(ds.Rows),
        cols=int(ds.Columns),
        frames=int(frames),
        samples=int(ds.get("SamplesPerPixel") or 1),
        bits_allocated=int(ds.BitsAllocated),
        pixel_data_bytes=native_bytes,
        encapsulated_fragments=fragments,
        limits=limits,
    )


def check_dataset_file(path: str | os.PathLike[str], *, limits: ReadLimits | None = None) -> None:
    """Before a DICOM file is read whole: its size, and for a deflated data set its inflated size.

    pydicom inflates a Deflated Explicit VR Little Endian data set in one go, so a few kB can
    become gigabytes before any header is seen: the inflated size is counted here first, in
    bounded chunks.
    """
    limits = limits or current_limits()
    size = file_size(path)
    check_file_size(path, size, limits=limits)
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
            found = _file_meta_syntax(head)
            if found is None or found[0] != DeflatedExplicitVRLittleEndian:
                return
            fh.seek(found[1])
            inflater = zlib.decompressobj(-zlib.MAX_WBITS)
            inflated = 0
            while chunk := fh.read(1 << 16):
                while chunk:
                    inflated += len(inflater.decompress(chunk, 1 << 20))
                    chunk = inflater.unconsumed_tail
                    if inflated > limits.max_file_bytes:
                        raise DicomError(
                            path,
                            f"deflated data set inflates to more than {_mb(limits.max_file_bytes)} "
                            f"{RAISE_HINT.format(env=ENV_MAX_FILE_MB)}",
                        )
                if inflater.eof:
                    break
    except DicomError:
        raise
    except Exception:  # not readable here: the reader says why
        return


#: VRs whose explicit-VR header has a 4-byte length (PS3.5 7.1.2).
_LONG_VRS = {b"OB", b"OD", b"OF", b"OL", b"OV", b"OW", b"SQ", b"SV", b"UC", b"UN", b"UR", b"UT", b"UV"}


def _file_meta_syntax(head: bytes) -> tuple[str, int] | None:
    """(TransferSyntaxUID, offset of the data set) from a Part 10 file's first bytes, or None.

    Parsed here (group 0002, explicit VR little endian) rather than by pydicom, which would
    allocate whatever length a corrupt element claims.
    """
    if len(head) < 132 or head[128:132] != b"DICM":
        return None
    at, syntax = 132, None
    while at + 8 <= len(head):
        group, _element = int.from_bytes(head[at : at + 2], "little"), int.from_bytes(head[at + 2 : at + 4], "little")
        if group != 0x0002:
            break
        vr = head[at + 4 : at + 6]
        if vr in _LONG_VRS:
            length, start = int.from_bytes(head[at + 8 : at + 12], "little"), at + 12
        else:
            length, start = int.from_bytes(head[at + 6 : at + 8], "little"), at + 8
        if _element == 0x0010:
            syntax = head[start : start + length].rstrip(b"\x00 ").decode("ascii", "replace")
        at = start + length
    return (syntax, at) if syntax is not None else None


class _CappedReader(io.BufferedReader):
    """A file whose ``read(n)`` never asks for more than what is left in it.

    ``read(n)`` allocates ``n`` bytes up front: a corrupt element length of 2 GB in a 2 kB
    file would allocate 2 GB before finding out the data is not there.
    """

    def __init__(self, raw: io.RawIOBase, size: int) -> None:
        super().__init__(raw)
        self._size = size

    def read(self, n: int | None = -1) -> bytes:
        if n is not None and n > 0:
            n = min(n, max(0, self._size - self.tell()))
            if n == 0:
                return b""
        return super().read(n)


def capped_file(path: str | os.PathLike[str]) -> _CappedReader:
    """Open ``path`` for reading through :class:`_CappedReader` (a context manager)."""
    return _CappedReader(io.FileIO(path, "r"), file_size(path))


def file_size(path: str | os.PathLike[str]) -> int:
    """Size in bytes of ``path`` (0 if it cannot be stat'ed: the reader then says why)."""
    try:
        return Path(path).stat().st_size
    except OSError:
        return 0
