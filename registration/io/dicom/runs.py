"""X-ray runs: multi-frame XA/RF read and written as a whole (CONVENTIONS §7).

The engine-facing API for fluoroscopy runs and rotational runs::

    run = read_xray_run("run.dcm")          # header read once, frames decoded on demand
    len(run), run.times_s, run.geometries   # per-frame times (s) and C-arm views (CArm)
    image = run[n]                          # frame n as an XRayImage (attenuation, mask, geometry)
    for image in run: ...                   # every frame, in order
    write_xray_run(images, "run.dcm", times_s=times)   # one multi-frame XA

Frame times (seconds from the first frame), the first form present wins:

1. FrameTimeVector (0018,1065): the increments (ms) between frames, one per frame, the
   first 0 (a non-zero first value is ignored, with a warning): ``t_n = sum(v[1..n]) / 1000``;
2. FrameTime (0018,1063): ``t_n = n * FrameTime / 1000``;
3. CineRate (0018,0040) frames/s: ``t_n = n / CineRate``;
4. (enhanced XA/RF only) FrameAcquisitionDateTime (0018,9074) of each frame's Frame Content
   functional group, relative to the first frame.

A multi-frame file with none of them is refused unless the caller supplies ``frame_time_ms``.
A single-frame file is a run of one frame at t = 0.

Per-frame geometry follows :func:`registration.io.dicom.read_xray` (CONVENTIONS §3): the
positioner angles plus the angle increment tags (classic XA/RF) or the per-frame functional
groups (enhanced XA/RF), distances and pixel spacing per frame where the file gives them per
frame. Plane Identification (0018,9457, CONVENTIONS §6) is read per frame where present.

Writing stores the frames' nominal geometry (angles as increments from the first frame) and
the times as FrameTime when evenly spaced, else FrameTimeVector; the reader gives them back.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydicom.dataset import Dataset
from pydicom.valuerep import DT

from registration.core.geometry import CArm
from registration.io.dicom._common import DicomError, _floats, _text, lookup, tag_name
from registration.io.dicom.xray import (
    _check_isocenter,
    _open_xray,
    _xray_frame,
    frame_plane,
)
from registration.io.dicom.xray_geometry import _field_rotation_shape, _geometry
from registration.io.dicom.xray_write import write_xray

if TYPE_CHECKING:
    from registration.core.images import XRayImage

#: Frame times must not exceed this (s): a run of a day is not a fluoroscopy run.
MAX_RUN_SECONDS = 24 * 3600.0


@dataclass(frozen=True, eq=False)
class XRayRun(Sequence["XRayImage"]):
    """A multi-frame XA/RF run: per-frame times and geometry, frames decoded on demand.

    Attributes
    ----------
    path
        The file.
    times_s
        (frames,) float64 seconds from the first frame (CONVENTIONS §7), non-decreasing.
    times_from
        Which tag gave the times ("FrameTimeVector", "FrameTime", "CineRate",
        "FrameAcquisitionDateTime", "frame_time_ms" or "single frame").
    geometries
        One :class:`CArm` per frame (the nominal view its positioner tags state).
    planes
        One Plane Identification per frame ("MONOPLANE", "PLANE A", "PLANE B"), or "" where
        the file does not say.
    meta
        What :func:`read_xray_run` read (modality, frames, angle and distance sources, and
        ``acquisition_datetime``: AcquisitionDateTime, else AcquisitionDate + AcquisitionTime,
        as DICOM text, "" when absent).

    ``run[n]`` decodes frame ``n`` as an :class:`~registration.core.images.XRayImage` whose
    geometry is ``geometries[n]`` and whose ``meta`` holds ``frame``, ``t_s`` and ``plane``.
    ``run.frames()`` decodes them all (memory: frames x rows x cols x 4 bytes).
    """

    path: Path
    times_s: NDArray[np.float64]
    times_from: str
    geometries: tuple[CArm, ...]
    planes: tuple[str, ...]
    meta: dict[str, Any] = field(default_factory=dict)
    _ds: Dataset | None = field(default=None, repr=False)
    _read: dict[str, Any] = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.geometries)

    def __getitem__(self, index: int) -> XRayImage:  # type: ignore[override]
        if isinstance(index, slice):
            raise TypeError("XRayRun frames are read one at a time: run[n]")
        n = int(index)
        if n < 0:
            n += len(self)
        if not 0 <= n < len(self):
            raise IndexError(f"frame {index} out of range: the run has {len(self)} frames")
        if self._ds is None:
            raise ValueError("this XRayRun holds no pixel data")
        image = _xray_frame(
            self.path,
            self._ds,
            n,
            len(self),
            self._read["rows"],
            self._read["cols"],
            self._read["iso"],
            kind=self._read["kind"],
            sid_mm=self._read["sid_mm"],
            sod_mm=self._read["sod_mm"],
            pixel_mm=self._read.get("pixel_mm"),
            image_mask=self._read.get("image_mask"),
            field_cache=self._read.setdefault("field_cache", {}),
        )
        image.meta.update(t_s=float(self.times_s[n]), times_from=self.times_from)
        return image

    def __iter__(self) -> Iterator[XRayImage]:
        for n in range(len(self)):
            yield self[n]

    def frames(self) -> list[XRayImage]:
        """Every frame decoded (see the class docstring for the memory this takes)."""
        return list(self)

    @property
    def angles_deg(self) -> list[tuple[float, float]]:
        """(primary_deg, secondary_deg) of every frame."""
        return [(g.primary_deg, g.secondary_deg) for g in self.geometries]


def read_xray_run(
    path: str | os.PathLike[str],
    *,
    isocenter_mm: ArrayLike = (0.0, 0.0, 0.0),
    kind: str | None = None,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    frame_time_ms: float | None = None,
    image_mask: str | os.PathLike[str] | None = None,
    pixel_mm: float | None = None,
) -> XRayRun:
    """Read an XA/RF run: times and per-frame geometry now, pixels frame by frame later.

    ``isocenter_mm``, ``kind``, ``sid_mm``, ``sod_mm`` and ``pixel_mm`` mean what they mean for
    :func:`registration.io.dicom.read_xray`. ``frame_time_ms`` supplies the frame spacing for
    files that state no times (see the module docstring); a file that does state them wins.
    ``image_mask``: the user's field mask for every frame (as for ``read_xray``).
    Raises :class:`DicomError` naming the file and the tag for anything unreadable.
    """
    path = Path(path)
    iso = _check_isocenter(isocenter_mm)
    ds, frames, rows, cols = _open_xray(path)
    times, times_from = frame_times(path, ds, frames, frame_time_ms=frame_time_ms)
    geometries: list[CArm] = []
    info: dict[str, Any] = {}
    with warnings.catch_warnings():
        # The same warnings (PixelSpacing fallback, ...) would repeat once per frame: say them once.
        warnings.simplefilter("once")
        for n in range(frames):
            out_rows, out_cols = _field_rotation_shape(path, ds, rows, cols, n)
            geometry, info = _geometry(path, ds, n, frames, out_rows, out_cols, iso, sid_mm=sid_mm, sod_mm=sod_mm,
                                       pixel_mm=pixel_mm)  # fmt: skip
            geometries.append(geometry)
    planes = tuple(frame_plane(path, ds, n) for n in range(frames))
    meta = {
        "source": str(path),
        "frames": frames,
        "modality": _text(ds, "Modality").upper(),
        "times_from": times_from,
        # When the first frame was taken (CONVENTIONS §6 pairs the planes of a biplane run by it).
        "acquisition_datetime": _text(ds, "AcquisitionDateTime")
        or (_text(ds, "AcquisitionDate") + _text(ds, "AcquisitionTime")),
        **info,
    }
    read = {
        "rows": rows,
        "cols": cols,
        "iso": iso,
        "kind": kind,
        "sid_mm": sid_mm,
        "sod_mm": sod_mm,
        "pixel_mm": pixel_mm,
        "image_mask": image_mask,
    }
    return XRayRun(
        path=path,
        times_s=times,
        times_from=times_from,
        geometries=tuple(geometries),
        planes=planes,
        meta=meta,
        _ds=ds,
        _read=read,
    )


def frame_times(
    path: Path, ds: Dataset, frames: int, *, frame_time_ms: float | None = None
) -> tuple[NDArray[np.float64], str]:
    """Seconds from the first frame for every frame, and the tag they came from (module docstring)."""
    if frames == 1:
        return np.zeros(1), "single frame"
    vector = _floats(path, ds, "FrameTimeVector", None, required=False) if "FrameTimeVector" in ds else None
    if vector:
        if len(vector) != frames:
            raise DicomError(path, f"{tag_name('FrameTimeVector')} holds {len(vector)} values for {frames} frames")
        steps = np.asarray(vector, dtype=np.float64)
        if np.any(steps[1:] < 0):
            raise DicomError(path, f"{tag_name('FrameTimeVector')} holds a negative time increment")
        if steps[0] != 0:
            warnings.warn(
                f"{path}: {tag_name('FrameTimeVector')} starts with {steps[0]:g} ms, not 0; ignoring it "
                "(the first frame is at t = 0)",
                stacklevel=3,
            )
        times = np.concatenate([[0.0], np.cumsum(steps[1:])]) / 1000.0
        return _checked_times(path, times, "FrameTimeVector"), "FrameTimeVector"
    frame_time = _floats(path, ds, "FrameTime", 1, required=False) if "FrameTime" in ds else None
    if frame_time:
        if frame_time[0] <= 0:
            raise DicomError(path, f"{tag_name('FrameTime')} must be positive, got {frame_time[0]:g} ms")
        return _checked_times(path, np.arange(frames) * frame_time[0] / 1000.0, "FrameTime"), "FrameTime"
    rate = _floats(path, ds, "CineRate", 1, required=False) if "CineRate" in ds else None
    if rate:
        if rate[0] <= 0:
            raise DicomError(path, f"{tag_name('CineRate')} must be positive, got {rate[0]:g} frames/s")
        return _checked_times(path, np.arange(frames) / rate[0], "CineRate"), "CineRate"
    stamps = _frame_datetimes(path, ds, frames)
    if stamps is not None:
        return _checked_times(path, stamps - stamps[0], "FrameAcquisitionDateTime"), "FrameAcquisitionDateTime"
    if frame_time_ms is not None:
        value = float(frame_time_ms)
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f"frame_time_ms must be a positive number, got {frame_time_ms}")
        return np.arange(frames) * value / 1000.0, "frame_time_ms"
    raise DicomError(
        path,
        f"{frames} frames but no frame times: missing {tag_name('FrameTimeVector')}, {tag_name('FrameTime')} "
        f"and {tag_name('CineRate')} (supply them with frame_time_ms, --frame-time-ms)",
    )


def _frame_datetimes(path: Path, ds: Dataset, frames: int) -> NDArray[np.float64] | None:
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    if not per_frame or len(per_frame) != frames:
        return None
    stamps = []
    for n in range(frames):
        value = lookup(ds, "FrameAcquisitionDateTime", n)
        if value in (None, ""):
            return None
        try:
            stamps.append(DT(str(value)).timestamp())
        except (TypeError, ValueError, OverflowError):
            raise DicomError(
                path, f"{tag_name('FrameAcquisitionDateTime')} of frame {n} is not a date-time: {str(value)[:32]!r}"
            ) from None
    out = np.asarray(stamps, dtype=np.float64)
    if np.all(out == out[0]):
        return None  # one date-time for all frames (e.g. only the top level's): no frame times
    return out


def _checked_times(path: Path, times: NDArray[np.float64], keyword: str) -> NDArray[np.float64]:
    if not np.all(np.isfinite(times)):
        raise DicomError(path, f"{tag_name(keyword)} gives non-finite frame times")
    if np.any(np.diff(times) < 0):
        raise DicomError(path, f"{tag_name(keyword)} gives frame times that go backwards")
    if times[-1] > MAX_RUN_SECONDS:
        raise DicomError(path, f"{tag_name(keyword)} gives a run of {times[-1]:.0f} s (more than a day)")
    return times


def write_xray_run(
    images: Sequence[XRayImage],
    path: str | os.PathLike[str],
    *,
    times_s: ArrayLike | None = None,
    plane: str | None = None,
    study_uid: str | None = None,
    uid_seed: str | None = None,
    description: str | None = None,
    patient_name: str = "roadmap3d^phantom",
    patient_id: str = "ROADMAP3D",
    transfer_syntax: str | None = None,
) -> Path:
    """Write ``images`` as one multi-frame XA (classic XA IOD) with per-frame angles and times.

    Every frame keeps its own PositionerPrimary/SecondaryAngle (as increments from the first
    frame); the frames must share size, SID, SOD and pixel spacing. ``times_s`` are seconds
    from the first frame (default 30 frames/s), ``plane`` the Plane Identification of a
    biplane run, ``transfer_syntax`` an optional lossless compression (RLE Lossless, JPEG 2000
    Lossless). :func:`read_xray_run` reads the file back. Written atomically.
    """
    if isinstance(images, (str, bytes)) or not isinstance(images, Sequence) or not len(images):
        raise ValueError("write_xray_run needs a non-empty sequence of XRayImage frames")
    return write_xray(
        list(images),
        path,
        study_uid=study_uid,
        uid_seed=uid_seed,
        description=description,
        patient_name=patient_name,
        patient_id=patient_id,
        times_s=times_s,
        plane=plane,
        transfer_syntax=transfer_syntax,
    )
