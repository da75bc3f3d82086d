"""DICOM in and out: 3DRA/CT volumes, XA/RF images, the project's ``.npz``, safe uploads.

Everything DICOM-specific (tag lookups, slice sorting, intensity relationships, shutters)
lives in this package; the rest of the engine sees a :class:`~registration.core.volume.Volume`
and an :class:`~registration.sim.xray.XRayImage` that follow ``shared/CONVENTIONS.md``.

Modules (import from the package, ``from registration.io.dicom import read_volume``):

``volumes``, ``volumes_write``
    Slice series, enhanced multi-frame volumes and the ``.npz``: reading (CONVENTIONS §2,
    tilted or uneven stacks rejected) and writing.
``xray``
    XA/RF images: geometry from the positioner tags (CONVENTIONS §3), intensities to
    attenuation line integrals and the field mask (§5).
``xray_write``
    Writing single XA images and runs.
``runs``
    Multi-frame runs (CONVENTIONS §7): :func:`read_xray_run` gives an :class:`XRayRun` (per-frame
    times, geometry, plane; frames decoded on demand), :func:`write_xray_run` writes one.
``spatial``
    The registration result as a DICOM Spatial Registration object: :func:`write_registration`,
    :func:`read_registration` (a :class:`SpatialRegistration`), :func:`is_registration_file`.
``inspection``
    :func:`inspect`, what ``roadmap3d info`` shows.
``uploads``
    Safe unpacking of a zip uploaded through the web app and finding its volume and image.
``_common``, ``_files``
    Errors, constants and tag helpers; atomic output files and the project's JSON.

Errors are :class:`DicomError` (a ``ValueError``) naming the file and the tag.
"""

from __future__ import annotations

from registration.io.dicom._common import (
    ENHANCED_VOLUME_CLASSES,
    IMPLEMENTATION_UID,
    IN_PLANE_TOLERANCE,
    LOG_UNITS_PER_ATTENUATION,
    LOG_ZERO_VALUE,
    MAX_FOLDER_FILES,
    MAX_PIXEL_BYTES,
    NO_SIGNAL_VALUE,
    ORIENTATION_TOLERANCE,
    POSITION_TOLERANCE_MM,
    SPACING_TOLERANCE,
    VOLUME_MODALITIES,
    WRITTEN_SIGN,
    XRAY_CLASSES,
    Array,
    DicomError,
    UploadError,
    lookup,
    make_uid,
    pixel_decoder,
    read_dataset,
    tag_name,
)
from registration.io.dicom._files import atomic_folder, json_dumps, write_bytes_atomic, write_text_atomic
from registration.io.dicom.inspection import HEADER_TAGS, inspect
from registration.io.dicom.runs import XRayRun, frame_times, read_xray_run, write_xray_run
from registration.io.dicom.spatial import (
    SpatialRegistration,
    is_registration_file,
    read_registration,
    write_registration,
)
from registration.io.dicom.uploads import classify_upload, unpack_upload
from registration.io.dicom.volumes import read_npz, read_series, read_volume, write_npz
from registration.io.dicom.volumes_write import write_enhanced, write_series
from registration.io.dicom.xray import read_xray, read_xray_angles
from registration.io.dicom.xray_write import write_xray

__all__ = [
    "ENHANCED_VOLUME_CLASSES",
    "HEADER_TAGS",
    "IMPLEMENTATION_UID",
    "IN_PLANE_TOLERANCE",
    "LOG_UNITS_PER_ATTENUATION",
    "LOG_ZERO_VALUE",
    "MAX_FOLDER_FILES",
    "MAX_PIXEL_BYTES",
    "NO_SIGNAL_VALUE",
    "ORIENTATION_TOLERANCE",
    "POSITION_TOLERANCE_MM",
    "SPACING_TOLERANCE",
    "VOLUME_MODALITIES",
    "WRITTEN_SIGN",
    "XRAY_CLASSES",
    "SpatialRegistration",
    "XRayRun",
    "Array",
    "DicomError",
    "UploadError",
    "atomic_folder",
    "classify_upload",
    "frame_times",
    "inspect",
    "is_registration_file",
    "json_dumps",
    "lookup",
    "make_uid",
    "pixel_decoder",
    "read_dataset",
    "read_npz",
    "read_registration",
    "read_series",
    "read_volume",
    "read_xray",
    "read_xray_angles",
    "read_xray_run",
    "tag_name",
    "unpack_upload",
    "write_bytes_atomic",
    "write_enhanced",
    "write_npz",
    "write_registration",
    "write_series",
    "write_text_atomic",
    "write_xray",
    "write_xray_run",
]
