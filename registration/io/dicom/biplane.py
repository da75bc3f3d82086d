"""A biplane pair: two XA/RF files, one per plane, of the same moment (CONVENTIONS.md §6).

Each file states its plane in Plane Identification (0018,9457) ("PLANE A" / "PLANE B"; a file
that says nothing, or MONOPLANE, takes the place its position on the command line gives it).
The two frames pair by acquisition time (FrameAcquisitionDateTime 0018,9074, else
AcquisitionDateTime 0008,002A, else AcquisitionDate + AcquisitionTime): frames taken more than
:data:`PAIR_TOLERANCE_S` apart are two moments, not one, and are refused, as are pairs without
times, two files of the same plane, or the same file twice.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from pydicom.valuerep import DT

from registration.core.images import XRayImage
from registration.io.dicom._errors import DicomError
from registration.io.dicom.xray import read_xray

#: Largest time between the two planes' frames of one moment (seconds). Biplane systems expose
#: both planes within one frame period (interleaved pulses, ~30 ms at 30 frames/s).
PAIR_TOLERANCE_S = 0.5


def acquisition_seconds(image: XRayImage) -> float | None:
    """The frame's acquisition time (POSIX seconds) from ``meta["acquisition_datetime"]``."""
    text = str(image.meta.get("acquisition_datetime") or "").strip()
    if not text:
        return None
    try:
        return DT(text).timestamp()
    except (TypeError, ValueError, OverflowError):
        source = image.meta.get("source", "?")
        raise DicomError(source, f"acquisition date-time {text[:32]!r} is not a DICOM DT") from None


def pair_views(images: Sequence[XRayImage], *, tolerance_s: float = PAIR_TOLERANCE_S) -> tuple[XRayImage, XRayImage]:
    """Order two views as (plane A, plane B) and check they show the same moment."""
    if len(images) != 2:
        raise ValueError(f"a biplane pair is two images, got {len(images)}")
    sources = [str(img.meta.get("source", f"image {n + 1}")) for n, img in enumerate(images)]
    if sources[0] == sources[1] and not sources[0].startswith("image "):
        raise ValueError(f"{sources[0]} given twice: a biplane pair needs one image of each plane")
    planes = [str(img.meta.get("plane") or "") for img in images]
    if planes[0] == planes[1] and planes[0] in ("PLANE A", "PLANE B"):
        raise ValueError(
            f"{sources[0]} and {sources[1]} are both {planes[0]}: a biplane pair needs plane A and plane B"
        )
    ordered = list(images)
    if planes[0] == "PLANE B" or planes[1] == "PLANE A":
        ordered.reverse()
        sources.reverse()
    times = [acquisition_seconds(img) for img in ordered]
    missing = [s for s, t in zip(sources, times, strict=True) if t is None]
    if missing:
        raise ValueError(
            f"{', '.join(missing)}: no acquisition time (FrameAcquisitionDateTime 0018,9074 / AcquisitionDateTime "
            "0008,002A), so the pair cannot be shown to be one moment"
        )
    gap = abs(times[0] - times[1])  # type: ignore[operator]
    if gap > tolerance_s:
        raise ValueError(
            f"{sources[0]} and {sources[1]} were acquired {gap:.3f} s apart (more than {tolerance_s:g} s): two "
            "different moments, not a biplane pair; give the two planes' frames of the same moment"
        )
    return ordered[0], ordered[1]


def read_biplane(
    paths: Sequence[str | os.PathLike[str]],
    *,
    frames: Sequence[int | None] = (None, None),
    sid_mm: float | None = None,
    sod_mm: float | None = None,
) -> tuple[XRayImage, XRayImage]:
    """Read two XA/RF files (any order) as (plane A, plane B) of one moment; see the module doc."""
    if len(paths) != 2:
        raise ValueError(f"a biplane pair is two files, got {len(paths)}")
    images = [read_xray(Path(p), frame=f, sid_mm=sid_mm, sod_mm=sod_mm) for p, f in zip(paths, frames, strict=True)]
    return pair_views(images)
