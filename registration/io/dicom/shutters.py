"""What an XA/RF file says about its usable field: shutters, collimator tags and overlay planes.

Display shutters (Display Shutter module, 0018,1600..1622) and the X-Ray Collimator module
(0018,1700..1720) describe the same kind of shape in stored pixel positions (1-based): a
rectangle (left/right column, upper/lower row, inclusive), a circle (center row, column and
radius) and a polygon (row, column vertices); ``ShutterShape`` may combine them
(``CIRCULAR\\RECTANGULAR``) and the field is then their intersection. Enhanced XA/RF states them
per frame (Frame Display Shutter Sequence in the functional groups), which :func:`lookup` finds.
``ShutterPresentationValue`` is only the gray a viewer paints outside: it is reported, not used.

Overlay planes (60xx, x even) are graphics a viewer draws over the image (text, rulers,
markers, regions). The pixels under them are masked: annotations sit where something was
marked, and systems often burn the same graphics into the pixels. An overlay is read from
OverlayData (60xx,3000, one bit per pixel, ``OverlayRows`` x ``OverlayColumns`` per frame
placed at ``OverlayOrigin``; multi-frame overlays from ``ImageFrameOrigin``) or, in the
retired form, from the bit ``OverlayBitPosition`` of the stored pixel words.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import Dataset
from scipy import ndimage
from skimage.draw import polygon2mask

from registration.io.dicom._common import DicomError, _floats, lookup, tag_name

#: Overlay graphics are masked with this margin (px): anti-aliased strokes and lossy ringing.
OVERLAY_MARGIN_PX = 2

_SHAPES = ("RECTANGULAR", "CIRCULAR", "POLYGONAL")


def _shape_mask(
    path: Path, ds: Dataset, rows: int, cols: int, frame: int | None, prefix: str
) -> tuple[NDArray[np.bool_] | None, list[str]]:
    """The field a shutter (``prefix`` "Shutter") or collimator ("Collimator") description leaves."""
    shape_tag = f"{prefix}Shape"
    value = lookup(ds, shape_tag, frame)
    if value is None:
        return None, []
    items = value if hasattr(value, "__iter__") and not isinstance(value, str) else str(value).split("\\")
    words = [str(v).strip().upper() for v in items]
    words = [w for w in words if w]
    mask = np.ones((rows, cols), dtype=bool)
    rr, cc = np.mgrid[0:rows, 0:cols]
    used: list[str] = []
    for word in words:
        if word == "RECTANGULAR":
            left = _floats(path, ds, f"{prefix}LeftVerticalEdge", 1, frame)[0] - 1  # type: ignore[index]
            right = _floats(path, ds, f"{prefix}RightVerticalEdge", 1, frame)[0] - 1  # type: ignore[index]
            upper = _floats(path, ds, f"{prefix}UpperHorizontalEdge", 1, frame)[0] - 1  # type: ignore[index]
            lower = _floats(path, ds, f"{prefix}LowerHorizontalEdge", 1, frame)[0] - 1  # type: ignore[index]
            if right < left or lower < upper:
                raise DicomError(path, f"{tag_name(shape_tag)} RECTANGULAR: the edges enclose no pixel")
            mask &= (cc >= left) & (cc <= right) & (rr >= upper) & (rr <= lower)
        elif word == "CIRCULAR":
            center_tag = "CenterOfCircularShutter" if prefix == "Shutter" else "CenterOfCircularCollimator"
            radius_tag = "RadiusOfCircularShutter" if prefix == "Shutter" else "RadiusOfCircularCollimator"
            center = _floats(path, ds, center_tag, 2, frame)
            radius = _floats(path, ds, radius_tag, 1, frame)[0]  # type: ignore[index]
            assert center is not None
            if radius <= 0:
                raise DicomError(path, f"{tag_name(radius_tag)} must be positive, got {radius:g}")
            mask &= (rr - (center[0] - 1)) ** 2 + (cc - (center[1] - 1)) ** 2 <= radius**2
        elif word == "POLYGONAL":
            vertex_tag = "VerticesOfThePolygonalShutter" if prefix == "Shutter" else "VerticesOfThePolygonalCollimator"
            vertices = _floats(path, ds, vertex_tag, None, frame)
            assert vertices is not None
            if len(vertices) % 2 or len(vertices) < 6:
                raise DicomError(path, f"{tag_name(vertex_tag)} must hold 3 or more (row, column) pairs")
            points = np.asarray(vertices, dtype=np.float64).reshape(-1, 2) - 1.0
            mask &= polygon2mask((rows, cols), points)
        elif word == "BITMAP":
            continue  # a presentation state's bitmap shutter: overlay planes carry it
        else:
            raise DicomError(path, f"{tag_name(shape_tag)} {word[:16]!r} is none of {', '.join(_SHAPES)}")
        used.append(word.lower())
    return (mask if used else None), used


def shutter_field(
    path: Path, ds: Dataset, rows: int, cols: int, frame: int | None = None
) -> tuple[NDArray[np.bool_] | None, dict[str, Any]]:
    """The field the shutter and collimator tags leave (stored pixel positions), and what was read.

    None when the file states neither. The info names the shapes and where they came from.
    """
    mask: NDArray[np.bool_] | None = None
    info: dict[str, Any] = {}
    for prefix, what in (("Shutter", "shutter"), ("Collimator", "collimator")):
        part, shapes = _shape_mask(path, ds, rows, cols, frame, prefix)
        if part is None:
            continue
        mask = part if mask is None else mask & part
        per_frame = _per_frame(ds, f"{prefix}Shape", frame)
        info[what] = " and ".join(shapes) + (" (per frame)" if per_frame else "")
    presentation = lookup(ds, "ShutterPresentationValue", frame)
    if presentation not in (None, ""):
        info["shutter_presentation_value"] = int(presentation)
    if mask is not None and not mask.any():
        raise DicomError(path, f"the shutter ({tag_name('ShutterShape')}) leaves no pixel of the image")
    return mask, info


def _per_frame(ds: Dataset, keyword: str, frame: int | None) -> bool:
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    if frame is None or not per_frame or not 0 <= frame < len(per_frame):
        return False
    shared = ds.get("SharedFunctionalGroupsSequence")
    return keyword not in ds and not (shared and lookup(shared[0], keyword) is not None)


def _groups(ds: Dataset) -> list[int]:
    """Overlay groups 0x6000..0x601E present in ``ds``."""
    return [g for g in range(0x6000, 0x6020, 2) if (g << 16 | 0x0010) in ds]


def _group_int(ds: Dataset, group: int, element: int, default: int | None = None) -> int | None:
    tag = group << 16 | element
    if tag not in ds or ds[tag].value in (None, ""):
        return default
    value = ds[tag].value
    if isinstance(value, (list, tuple)) or hasattr(value, "__len__") and not isinstance(value, (str, bytes)):
        value = value[0]
    return int(value)


def _overlay_plane(
    path: Path, ds: Dataset, group: int, shape: tuple[int, int], frame: int, raw_words: NDArray[Any] | None
) -> tuple[NDArray[np.bool_] | None, dict[str, Any]]:
    """One overlay plane's bits on ``frame`` (None when it draws nothing there or cannot be read
    here) and its note (name, type, description, where its bits came from)."""
    name = f"overlay {group:04X}"
    o_rows, o_cols = shape
    n_frames = _group_int(ds, group, 0x0015, 1) or 1
    first = _group_int(ds, group, 0x0051, 1) or 1
    kind = str(ds.get(group << 16 | 0x0040).value if (group << 16 | 0x0040) in ds else "G").strip().upper()
    description = str(ds[group << 16 | 0x0022].value).strip() if (group << 16 | 0x0022) in ds else ""
    note: dict[str, Any] = {"plane": name, "type": "ROI" if kind == "R" else "graphics"}
    if description:
        note["description"] = description[:64]
    # A single-frame overlay on a multi-frame image is drawn on every frame.
    index = 0 if n_frames == 1 else frame - (first - 1)
    if not 0 <= index < n_frames:
        note["pixels"] = 0
        return None, note
    data_tag = group << 16 | 0x3000
    if data_tag in ds and ds[data_tag].value:
        raw = np.frombuffer(bytes(ds[data_tag].value), dtype=np.uint8)
        bits = np.unpackbits(raw, bitorder="little")
        per = o_rows * o_cols
        if bits.size < per * n_frames:
            raise DicomError(
                path,
                f"{name}: OverlayData ({group:04X},3000) holds {bits.size} bits for {n_frames} frame(s) of "
                f"{o_rows}x{o_cols}",
            )
        plane = bits[index * per : (index + 1) * per].reshape(o_rows, o_cols).astype(bool)
        note["from"] = "OverlayData"
    else:
        position = _group_int(ds, group, 0x0102, 0) or 0
        if raw_words is None or position <= 0 or (o_rows, o_cols) != raw_words.shape:
            note["from"] = f"pixel bit {position} (not readable here)"
            note["pixels"] = 0
            return None, note
        plane = ((raw_words.astype(np.int64) >> position) & 1).astype(bool)
        note["from"] = f"pixel data bit {position}"
    return plane, note


def overlay_graphics(
    path: Path, ds: Dataset, rows: int, cols: int, frame: int, raw_words: NDArray[Any] | None = None
) -> tuple[NDArray[np.bool_] | None, list[dict[str, Any]]]:
    """Pixels (stored positions) where overlay planes draw on ``frame``, and one note per plane.

    ``raw_words`` are the frame's stored pixel words with their unused high bits intact (for
    overlays embedded in the pixel data); without them such an overlay is reported, not read.
    """
    found: NDArray[np.bool_] | None = None
    notes: list[dict[str, Any]] = []
    for group in _groups(ds):
        name = f"overlay {group:04X}"
        o_rows = _group_int(ds, group, 0x0010)
        o_cols = _group_int(ds, group, 0x0011)
        if not o_rows or not o_cols or o_rows < 0 or o_cols < 0:
            raise DicomError(
                path, f"{name}: OverlayRows/OverlayColumns ({group:04X},0010/0011) missing or not positive"
            )
        origin_tag = group << 16 | 0x0050
        origin = [1, 1]
        if origin_tag in ds and ds[origin_tag].value not in (None, ""):
            value = ds[origin_tag].value
            origin = [int(v) for v in (value if hasattr(value, "__iter__") and not isinstance(value, str) else [value])]
            if len(origin) != 2:
                raise DicomError(path, f"{name}: OverlayOrigin ({group:04X},0050) must hold row and column")
        plane, note = _overlay_plane(path, ds, group, (o_rows, o_cols), frame, raw_words)
        if plane is None:
            notes.append(note)
            continue
        full = np.zeros((rows, cols), dtype=bool)
        r0, c0 = origin[0] - 1, origin[1] - 1
        rs, cs = max(r0, 0), max(c0, 0)
        re, ce = min(r0 + o_rows, rows), min(c0 + o_cols, cols)
        if re > rs and ce > cs:
            full[rs:re, cs:ce] = plane[rs - r0 : re - r0, cs - c0 : ce - c0]
        note["pixels"] = int(full.sum())
        notes.append(note)
        if full.any():
            found = full if found is None else found | full
    if found is not None:
        found = ndimage.binary_dilation(found, iterations=OVERLAY_MARGIN_PX)
    return found, notes


def embedded_overlay_bits(ds: Dataset) -> list[int]:
    """Bit positions of overlays stored in the pixel words (the retired form)."""
    out = []
    for group in _groups(ds):
        if (group << 16 | 0x3000) in ds:
            continue
        position = _group_int(ds, group, 0x0102, 0) or 0
        if position > 0:
            out.append(position)
    return out


def shutter_text(info: dict[str, Any]) -> str:
    """'shutter tags (circular and rectangular)' and the like, for ``mask_from``."""
    parts = [f"{k} tags ({v})" for k, v in info.items() if k in ("shutter", "collimator")]
    return " and ".join(parts)


__all__ = ["OVERLAY_MARGIN_PX", "embedded_overlay_bits", "overlay_graphics", "shutter_field", "shutter_text"]
