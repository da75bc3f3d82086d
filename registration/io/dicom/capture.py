"""The registration overlay as a DICOM Secondary Capture image (RGB), for a PACS viewer.

Why Secondary Capture and not a derived XA: the overlay is a picture for people (the X-ray
image with the registered 3DRA vessels drawn over it), not a measurement. A derived XA would
carry the positioner and detector tags of an acquisition and could be taken for one, by a
viewer's measuring tools or by software that re-registers it (this project's own readers accept
XA); a Secondary Capture (SOP class 1.2.840.10008.5.1.4.1.1.7, ImageType DERIVED\\SECONDARY,
ConversionType WSD) is shown by every PACS viewer, is refused by the project's X-ray readers, and
points back at the X-ray image it was derived from (Source Image Sequence).

The capture joins the X-ray image's study and patient (read from the image's ``meta``), in a
series of its own.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence
from pydicom.uid import UID, SecondaryCaptureImageStorage

from registration.io.dicom._common import _base, _save, make_uid
from registration.io.dicom._files import _atomic_path

if TYPE_CHECKING:
    from registration.core.images import XRayImage


def write_overlay_capture(
    path: str | os.PathLike[str],
    rgb: NDArray[np.uint8],
    *,
    xray: XRayImage,
    description: str = "roadmap3d overlay",
    comment: str = "",
    uid_seed: str | None = None,
    series_number: int = 901,
) -> Path:
    """Write ``rgb`` (rows x cols x 3, uint8) as a Secondary Capture derived from ``xray``."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"an overlay capture is rows x cols x 3 uint8, got {rgb.shape} {rgb.dtype}")
    meta = xray.meta
    study = str(meta.get("study_uid") or "") or str(make_uid(uid_seed, "capture study"))
    digest = hashlib.sha256(rgb.tobytes()).hexdigest()[:32]
    ds = _base(
        SecondaryCaptureImageStorage,
        "OT",
        study_uid=UID(study),
        series_uid=make_uid(uid_seed, "capture series", digest),
        instance_uid=make_uid(uid_seed, "capture instance", digest),
        series_number=series_number,
        description=description[:64],
        patient_name=str(meta.get("patient_name") or "") or "anonymous",
        patient_id=str(meta.get("patient_id") or ""),
    )
    ds.ConversionType = "WSD"
    ds.ImageType = ["DERIVED", "SECONDARY"]
    ds.InstanceNumber = 1
    ds.BurnedInAnnotation = "NO"
    if comment:
        ds.ImageComments = comment[:10240]
    if meta.get("sop_instance_uid") and meta.get("sop_class"):
        source = Dataset()
        source.ReferencedSOPClassUID = meta["sop_class"]
        source.ReferencedSOPInstanceUID = meta["sop_instance_uid"]
        if "frame" in meta and meta.get("frames", 1) != 1:
            source.ReferencedFrameNumber = int(meta["frame"]) + 1
        ds.SourceImageSequence = Sequence([source])
        ds.DerivationDescription = "X-ray image with the registered 3DRA vessels overlaid (roadmap3d)"
    ds.SamplesPerPixel = 3
    ds.PhotometricInterpretation = "RGB"
    ds.PlanarConfiguration = 0
    ds.Rows, ds.Columns = int(rgb.shape[0]), int(rgb.shape[1])
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
    ds.PixelRepresentation = 0
    ds.LossyImageCompression = "00"
    ds.PixelData = np.ascontiguousarray(rgb).tobytes()
    path = Path(path)
    with _atomic_path(path) as tmp:
        _save(ds, tmp)
    return path
