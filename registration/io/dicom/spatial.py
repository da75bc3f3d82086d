"""The registration result as a DICOM Spatial Registration object (SOP class 1.2.840.10008.5.1.4.1.1.66.1).

What is written (DICOM PS3.3 A.39, C.20.2; read the way 3D Slicer's SlicerRT "DICOM SRO" import
reads them: Registration Sequence -> Matrix Registration Sequence -> Matrix Sequence, each
FrameOfReferenceTransformationMatrix a row-major 4x4 in DICOM patient coordinates (LPS, mm),
the matrices of all items multiplied together, the moving series named in the top-level
Referenced Series Sequence):

* The object's own Frame of Reference (0020,0052) is the **X-ray image's** (the registered
  coordinate system: the patient where the image was taken). Classic XA carries no Frame of
  Reference; one is then derived from the image's SOP Instance UID (the same image always gets
  the same UID) and the image is referenced in the item's Referenced Image Sequence.
* Registration Sequence item 1: the X-ray image's Frame of Reference (and the image, with its
  frame number), matrix identity.
* Registration Sequence item 2: the **volume's** Frame of Reference (from its series), matrix
  ``patient_motion`` (CONVENTIONS §4): anatomy the volume shows at X is at ``M @ X`` in the
  image's coordinates, which is exactly DICOM's "transforms coordinates of the Frame of
  Reference in this item into the Registered RCS". Type RIGID.
* Referenced Series Sequence (Common Instance Reference): the volume's series and the image's
  series with their instances; Patient and Study copied from the X-ray image (else the volume).

:func:`read_registration` reads such an object, ours or another tool's, back:
:meth:`SpatialRegistration.motion_between` relates any two of its Frames of Reference, and
:attr:`SpatialRegistration.patient_motion` is the motion from the one other Frame of Reference
into the registered one (the volume into the image for the objects this module writes).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence
from pydicom.uid import UID, SpatialRegistrationStorage

from registration.core.geometry import check_rigid
from registration.io.dicom._common import (
    Array,
    DicomError,
    _base,
    _ds_number,
    _save,
    _sop_class,
    _text,
    make_uid,
    read_dataset,
    tag_name,
)
from registration.io.dicom._files import _atomic_path

if TYPE_CHECKING:
    from registration.core.images import XRayImage
    from registration.core.volume import Volume

#: Key of an X-ray item without a Frame of Reference: the image it references.
_IMAGE_KEY = "image:"


@dataclass(frozen=True)
class SpatialRegistration:
    """A Spatial Registration object as read back.

    Attributes
    ----------
    frame_of_reference_uid
        The registered coordinate system (the object's own Frame of Reference).
    matrices
        Frame of Reference UID -> 4x4 matrix taking its coordinates into the registered ones.
    sop_instance_uid, series_uid, study_uid
        The object's UIDs.
    referenced_series
        SeriesInstanceUIDs of the Referenced Series Sequence.
    referenced_images
        Frame of Reference UID -> (SOP Instance UID, frame number or None) of referenced images.
    description
        ContentDescription.
    """

    frame_of_reference_uid: str
    matrices: dict[str, Array]
    sop_instance_uid: str = ""
    series_uid: str = ""
    study_uid: str = ""
    referenced_series: tuple[str, ...] = ()
    referenced_images: dict[str, tuple[str, int | None]] = field(default_factory=dict)
    description: str = ""
    path: Path | None = None

    def volume_motion(self, volume_uid: str | None) -> Array:
        """Patient motion (CONVENTIONS §4) of the volume with Frame of Reference ``volume_uid``.

        The motion from the volume's frame into the other one this object relates it to, when
        it names ``volume_uid`` among exactly two; else :attr:`patient_motion`.
        """
        if volume_uid and volume_uid in self.matrices and len(self.matrices) == 2:
            other = next(uid for uid in self.matrices if uid != volume_uid)
            return self.motion_between(volume_uid, other)
        return self.patient_motion

    def motion_between(self, moving_uid: str, fixed_uid: str) -> Array:
        """The 4x4 taking coordinates of Frame of Reference ``moving_uid`` into ``fixed_uid``'s."""
        for uid in (moving_uid, fixed_uid):
            if uid not in self.matrices:
                raise DicomError(self.path or "registration", f"no registration item for Frame of Reference {uid}")
        return np.linalg.inv(self.matrices[fixed_uid]) @ self.matrices[moving_uid]

    @property
    def moving_uids(self) -> list[str]:
        return [uid for uid in self.matrices if uid != self.frame_of_reference_uid]

    @property
    def patient_motion(self) -> Array:
        """The motion from the one non-registered Frame of Reference into the registered one."""
        moving = self.moving_uids
        if len(moving) != 1 or self.frame_of_reference_uid not in self.matrices:
            raise DicomError(
                self.path or "registration",
                f"{tag_name('RegistrationSequence')} relates {len(self.matrices)} Frames of Reference; expected "
                f"the registered one ({tag_name('FrameOfReferenceUID')}) and one other",
            )
        return self.motion_between(moving[0], self.frame_of_reference_uid)


def _x_ray_frame_of_reference(meta: Mapping[str, Any], uid_seed: str | None) -> str:
    uid = str(meta.get("frame_of_reference_uid") or "")
    if uid:
        return uid
    instance = str(meta.get("sop_instance_uid") or "")
    # Derived from the image, so every registration to the same image shares it.
    return str(make_uid(instance, "x-ray frame of reference") if instance else make_uid(uid_seed, "x-ray for"))


def _matrix_item(matrix: Array, comment: str, *, content_based: bool) -> Dataset:
    item = Dataset()
    codes = []
    if content_based:  # CID 7100 RCS Registration Method Type
        code = Dataset()
        code.CodeValue, code.CodingSchemeDesignator = "125024", "DCM"
        code.CodeMeaning = "Image Content-based Alignment"
        codes.append(code)
    item.RegistrationTypeCodeSequence = Sequence(codes)
    item.FrameOfReferenceTransformationComment = comment[:64]  # LO
    entry = Dataset()
    entry.FrameOfReferenceTransformationMatrixType = "RIGID"
    entry.FrameOfReferenceTransformationMatrix = [_ds_number(float(v)) for v in np.asarray(matrix).reshape(-1)]
    item.MatrixSequence = Sequence([entry])
    return item


def _series_item(series_uid: str, instances: list[Any]) -> Dataset:
    item = Dataset()
    item.SeriesInstanceUID = series_uid
    refs = []
    for sop_class, sop_instance in instances:
        ref = Dataset()
        ref.ReferencedSOPClassUID = sop_class
        ref.ReferencedSOPInstanceUID = sop_instance
        refs.append(ref)
    item.ReferencedInstanceSequence = Sequence(refs)
    return item


def _xray_item(xmeta: dict, x_for: str) -> Dataset:
    """Registration item 1: the X-ray image's frame (the registered RCS), identity; the image
    itself referenced."""
    x_item = Dataset()
    x_item.FrameOfReferenceUID = x_for
    if xmeta.get("sop_instance_uid"):
        ref = Dataset()
        ref.ReferencedSOPClassUID = str(xmeta.get("sop_class") or "")
        ref.ReferencedSOPInstanceUID = str(xmeta["sop_instance_uid"])
        if int(xmeta.get("frames", 1) or 1) > 1:
            ref.ReferencedFrameNumber = int(xmeta.get("frame", 0)) + 1  # DICOM frames count from 1
        x_item.ReferencedImageSequence = Sequence([ref])
    identity = _matrix_item(np.eye(4), "X-ray image: registered frame", content_based=False)
    x_item.MatrixRegistrationSequence = Sequence([identity])
    return x_item


def _volume_item(motion: np.ndarray, v_for: str) -> Dataset:
    """Registration item 2: the volume's frame, mapped by the patient motion."""
    v_item = Dataset()
    v_item.FrameOfReferenceUID = v_for
    v_item.MatrixRegistrationSequence = Sequence(
        [_matrix_item(motion, "patient motion M (roadmap3d): volume X is at M @ X in the image", content_based=True)]
    )
    return v_item


def _referenced_series(ds: Dataset, vmeta: dict, xmeta: dict, study: str) -> None:
    """The registered series; the volume's under its own study when it lies in another one."""
    series = []
    if vmeta.get("series_uid"):
        series.append(_series_item(str(vmeta["series_uid"]), list(vmeta.get("instances") or [])))
    if xmeta.get("series_uid") and xmeta.get("sop_instance_uid"):
        series.append(_series_item(str(xmeta["series_uid"]), [[xmeta.get("sop_class"), xmeta["sop_instance_uid"]]]))
    ds.ReferencedSeriesSequence = Sequence(series)
    other_study = str(vmeta.get("study_uid") or "")
    if other_study and other_study != study and vmeta.get("series_uid"):
        study_item = Dataset()
        study_item.StudyInstanceUID = other_study
        study_item.ReferencedSeriesSequence = Sequence([series[0]])
        ds.StudiesContainingOtherReferencedInstancesSequence = Sequence([study_item])
        ds.ReferencedSeriesSequence = Sequence(series[1:])


def write_registration(
    path: str | os.PathLike[str],
    patient_motion: ArrayLike,
    *,
    volume: Volume,
    xray: XRayImage,
    description: str = "",
    uid_seed: str | None = None,
    series_number: int = 900,
) -> Path:
    """Write ``patient_motion`` (CONVENTIONS §4) as a Spatial Registration object (module docstring).

    ``volume`` and ``xray`` are the data that were registered, as the readers gave them (their
    ``meta`` holds the UIDs). Refuses a non-rigid matrix. Written atomically.
    """
    motion = check_rigid(np.asarray(patient_motion, dtype=np.float64), name="patient_motion")
    vmeta, xmeta = volume.meta, xray.meta
    x_for = _x_ray_frame_of_reference(xmeta, uid_seed)
    v_for = str(vmeta.get("frame_of_reference_uid") or "") or str(make_uid(uid_seed, "volume for", volume.label))
    if v_for == x_for:
        raise ValueError(
            f"the volume and the X-ray image share {tag_name('FrameOfReferenceUID')} {v_for}: a registration "
            "between them cannot be told apart from the identity"
        )
    study = str(xmeta.get("study_uid") or vmeta.get("study_uid") or "") or str(make_uid(uid_seed, "reg study"))
    instance = make_uid(uid_seed, "reg instance", motion.tobytes().hex())
    ds = _base(
        SpatialRegistrationStorage,
        "REG",
        study_uid=UID(study),
        series_uid=make_uid(uid_seed, "reg series", motion.tobytes().hex()),
        instance_uid=instance,
        series_number=series_number,
        description="roadmap3d 2D-3D registration",
        patient_name=str(xmeta.get("patient_name") or vmeta.get("patient_name") or "") or "anonymous",
        patient_id=str(xmeta.get("patient_id") or vmeta.get("patient_id") or ""),
    )
    del ds.PatientOrientation  # an image attribute, not part of the Spatial Registration IOD
    ds.InstanceNumber = 1
    ds.ContentLabel = "ROADMAP3D_REG"
    ds.ContentDescription = (description or "patient motion from the 3DRA/CT to the X-ray image (roadmap3d)")[:64]
    ds.ContentCreatorName = "roadmap3d"
    ds.FrameOfReferenceUID = x_for
    ds.PositionReferenceIndicator = ""
    ds.RegistrationSequence = Sequence([_xray_item(xmeta, x_for), _volume_item(motion, v_for)])
    _referenced_series(ds, vmeta, xmeta, study)
    ds.ContentDate = ds.SeriesDate
    ds.ContentTime = datetime.now(UTC).strftime("%H%M%S")
    path = Path(path)
    with _atomic_path(path) as tmp:
        _save(ds, tmp)
    return path


def is_registration_file(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` is a DICOM file of the Spatial Registration SOP class."""
    try:
        ds = read_dataset(path, stop_before_pixels=True)
    except DicomError:
        return False
    return _sop_class(ds) == SpatialRegistrationStorage


def read_registration(path: str | os.PathLike[str]) -> SpatialRegistration:
    """Read a Spatial Registration object; :class:`DicomError` names the file and the tag at fault."""
    path = Path(path)
    ds = read_dataset(path, stop_before_pixels=True)
    sop = _sop_class(ds)
    if sop != SpatialRegistrationStorage:
        name = UID(sop).name if sop else "no SOP class"
        raise DicomError(path, f"not a Spatial Registration object ({tag_name('SOPClassUID')} is {name})")
    registered = _text(ds, "FrameOfReferenceUID")
    if not registered:
        raise DicomError(path, f"missing {tag_name('FrameOfReferenceUID')}")
    items = ds.get("RegistrationSequence")
    if not items:
        raise DicomError(path, f"missing or empty {tag_name('RegistrationSequence')}")
    matrices: dict[str, Array] = {}
    images: dict[str, tuple[str, int | None]] = {}
    for n, item in enumerate(items):
        where = f"{tag_name('RegistrationSequence')} item {n + 1}"
        key = _text(item, "FrameOfReferenceUID")
        refs = item.get("ReferencedImageSequence")
        if refs:
            ref = refs[0]
            frame = ref.get("ReferencedFrameNumber")
            try:
                frame_number = int(frame) if frame not in (None, "") else None
            except (TypeError, ValueError):
                raise DicomError(path, f"{where}: {tag_name('ReferencedFrameNumber')} is not a number") from None
            image = (_text(ref, "ReferencedSOPInstanceUID"), frame_number)
            key = key or _IMAGE_KEY + image[0]
            images[key] = image
        if not key:
            raise DicomError(
                path, f"{where}: neither {tag_name('FrameOfReferenceUID')} nor {tag_name('ReferencedImageSequence')}"
            )
        if key in matrices:
            raise DicomError(path, f"{where}: Frame of Reference {key} appears twice")
        matrices[key] = _item_matrix(path, item, where)
    if registered not in matrices:
        # A registered frame without its own item is related to itself by the identity.
        matrices[registered] = np.eye(4)
    series_items = list(ds.get("ReferencedSeriesSequence") or [])
    for study_item in ds.get("StudiesContainingOtherReferencedInstancesSequence") or []:
        series_items += list(study_item.get("ReferencedSeriesSequence") or [])
    referenced = tuple(_text(s, "SeriesInstanceUID") for s in series_items if _text(s, "SeriesInstanceUID"))
    return SpatialRegistration(
        frame_of_reference_uid=registered,
        matrices=matrices,
        sop_instance_uid=_text(ds, "SOPInstanceUID"),
        series_uid=_text(ds, "SeriesInstanceUID"),
        study_uid=_text(ds, "StudyInstanceUID"),
        referenced_series=referenced,
        referenced_images=images,
        description=_text(ds, "ContentDescription"),
        path=path,
    )


def _item_matrix(path: Path, item: Dataset, where: str) -> Array:
    """The product of an item's matrices, applied in the order they are listed."""
    total = np.eye(4)
    registrations = item.get("MatrixRegistrationSequence")
    if not registrations:
        raise DicomError(path, f"{where}: missing {tag_name('MatrixRegistrationSequence')}")
    for registration in registrations:
        entries = registration.get("MatrixSequence")
        if not entries:
            raise DicomError(path, f"{where}: missing {tag_name('MatrixSequence')}")
        for entry in entries:
            kind = _text(entry, "FrameOfReferenceTransformationMatrixType").upper()
            if kind not in ("RIGID", "RIGID_SCALE", "AFFINE"):
                raise DicomError(
                    path, f"{where}: {tag_name('FrameOfReferenceTransformationMatrixType')} {kind or 'missing'}"
                )
            value = entry.get("FrameOfReferenceTransformationMatrix")
            try:
                matrix = np.array([float(v) for v in value], dtype=np.float64).reshape(4, 4)
            except (TypeError, ValueError):
                raise DicomError(
                    path, f"{where}: {tag_name('FrameOfReferenceTransformationMatrix')} must hold 16 numbers"
                ) from None
            if not np.all(np.isfinite(matrix)):
                raise DicomError(path, f"{where}: {tag_name('FrameOfReferenceTransformationMatrix')} holds a NaN")
            try:
                check_rigid(matrix, name="the matrix")
            except ValueError as exc:
                raise DicomError(
                    path,
                    f"{where}: {tag_name('FrameOfReferenceTransformationMatrix')} is not a rigid motion "
                    f"(roadmap3d relates rigid motions only): {exc}",
                ) from None
            total = matrix @ total
    return total
