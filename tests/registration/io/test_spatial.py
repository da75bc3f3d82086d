"""The registration result as a DICOM Spatial Registration object (registration/io/dicom/spatial.py).

The round trip is checked with pydicom reading the file tag by tag (not only through the
project's reader), and a REG object built by hand in the opposite direction (the volume's
frame registered, the image's moving) must give the same patient motion.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence
from pydicom.uid import SpatialRegistrationStorage, generate_uid

from registration.core.geometry import CArm, invert_rigid, offsets_to_matrix
from registration.core.volume import Volume
from registration.io import dicom
from registration.io.dicom import DicomError
from tests.registration.io.test_dicom import _save, _xray

pytestmark = pytest.mark.filterwarnings("ignore:Invalid value for VR:UserWarning")  # NaN written on purpose

# DS strings keep 16 characters: matrix entries (|v| < 1000) come back to ~1e-12.
MATRIX_TOL = 1e-9


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Volume, object, Path]:
    folder = tmp_path_factory.mktemp("reg")
    data = np.random.default_rng(0).normal(0.0, 300.0, (4, 5, 6)).astype(np.float32)
    volume = Volume(data, np.diag([0.8, 0.8, 2.0, 1.0]) @ np.eye(4), label="small test volume")
    dicom.write_series(volume, folder / "vol", uid_seed="reg test")
    geometry = CArm.for_format(27, pixels=16, primary_deg=20.0, secondary_deg=-10.0)
    dicom.write_xray(_xray(geometry), folder / "xa.dcm", uid_seed="reg test image")
    return dicom.read_volume(folder / "vol"), dicom.read_xray(folder / "xa.dcm"), folder


def test_registration_round_trip(pair, tmp_path: Path) -> None:
    volume, xray, _ = pair
    motion = offsets_to_matrix([4.0, -3.5, 12.0, 2.0, -3.0, 4.5], xray.geometry)
    path = dicom.write_registration(tmp_path / "reg.dcm", motion, volume=volume, xray=xray)
    ds = pydicom.dcmread(path)
    assert ds.SOPClassUID == SpatialRegistrationStorage == "1.2.840.10008.5.1.4.1.1.66.1"
    assert ds.file_meta.MediaStorageSOPClassUID == SpatialRegistrationStorage
    assert ds.Modality == "REG"
    # Same patient and study as the X-ray image; the image's frame is the registered one.
    assert (ds.PatientID, ds.StudyInstanceUID) == (xray.meta["patient_id"], xray.meta["study_uid"])
    x_item, v_item = ds.RegistrationSequence
    assert x_item.FrameOfReferenceUID == ds.FrameOfReferenceUID
    assert x_item.ReferencedImageSequence[0].ReferencedSOPInstanceUID == xray.meta["sop_instance_uid"]
    assert v_item.FrameOfReferenceUID == volume.meta["frame_of_reference_uid"]
    # The volume was written in a study of its own: it is referenced through its study.
    assert volume.meta["study_uid"] != xray.meta["study_uid"]
    assert [item.SeriesInstanceUID for item in ds.ReferencedSeriesSequence] == [xray.meta["series_uid"]]
    (other,) = ds.StudiesContainingOtherReferencedInstancesSequence
    assert other.StudyInstanceUID == volume.meta["study_uid"]
    series = {item.SeriesInstanceUID: item for item in other.ReferencedSeriesSequence}
    assert set(series) == {volume.meta["series_uid"]}
    slices = {r.ReferencedSOPInstanceUID for r in series[volume.meta["series_uid"]].ReferencedInstanceSequence}
    assert len(slices) == 4  # every slice of the series
    written = v_item.MatrixRegistrationSequence[0].MatrixSequence[0]
    assert written.FrameOfReferenceTransformationMatrixType == "RIGID"
    (method,) = v_item.MatrixRegistrationSequence[0].RegistrationTypeCodeSequence
    assert (method.CodeValue, method.CodingSchemeDesignator) == ("125024", "DCM")  # image content-based
    np.testing.assert_allclose(
        np.array(written.FrameOfReferenceTransformationMatrix, dtype=float).reshape(4, 4), motion, atol=MATRIX_TOL
    )
    identity = x_item.MatrixRegistrationSequence[0].MatrixSequence[0].FrameOfReferenceTransformationMatrix
    np.testing.assert_array_equal(np.array(identity, dtype=float).reshape(4, 4), np.eye(4))
    # The project's reader gives the motion back, in both directions.
    reg = dicom.read_registration(path)
    assert set(reg.referenced_series) == {volume.meta["series_uid"], xray.meta["series_uid"]}
    assert reg.sop_instance_uid == ds.SOPInstanceUID and reg.frame_of_reference_uid == ds.FrameOfReferenceUID
    np.testing.assert_allclose(reg.patient_motion, motion, atol=MATRIX_TOL)
    np.testing.assert_allclose(reg.volume_motion(volume.meta["frame_of_reference_uid"]), motion, atol=MATRIX_TOL)
    back = reg.motion_between(reg.frame_of_reference_uid, volume.meta["frame_of_reference_uid"])
    np.testing.assert_allclose(back, invert_rigid(motion), atol=MATRIX_TOL)
    assert dicom.is_registration_file(path) and not dicom.is_registration_file(pair[2] / "xa.dcm")


def _hand_made(path: Path, items: list[tuple[str, np.ndarray]], registered: str) -> Path:
    ds = Dataset()
    ds.SOPClassUID = SpatialRegistrationStorage
    ds.SOPInstanceUID = generate_uid()
    ds.Modality = "REG"
    ds.FrameOfReferenceUID = registered
    sequence = []
    for uid, matrix in items:
        item, reg, entry = Dataset(), Dataset(), Dataset()
        item.FrameOfReferenceUID = uid
        entry.FrameOfReferenceTransformationMatrixType = "RIGID"
        entry.FrameOfReferenceTransformationMatrix = [f"{v:.12g}" for v in np.asarray(matrix).reshape(-1)]
        reg.MatrixSequence = Sequence([entry])
        item.MatrixRegistrationSequence = Sequence([reg])
        sequence.append(item)
    ds.RegistrationSequence = Sequence(sequence)
    return _save(ds, path, SpatialRegistrationStorage)


def test_registration_written_the_other_way_round(pair, tmp_path: Path) -> None:
    # Another tool may register the image's frame to the volume's: the patient motion of the
    # volume is still read out (the inverse of that item's matrix).
    volume, xray, _ = pair
    motion = offsets_to_matrix([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], xray.geometry)
    vol_uid, img_uid = volume.meta["frame_of_reference_uid"], "1.2.3.4.5"
    path = _hand_made(tmp_path / "other.dcm", [(vol_uid, np.eye(4)), (img_uid, invert_rigid(motion))], vol_uid)
    reg = dicom.read_registration(path)
    np.testing.assert_allclose(reg.volume_motion(vol_uid), motion, atol=MATRIX_TOL)


def test_registration_refuses_bad_objects(pair, tmp_path: Path) -> None:
    scaled = _hand_made(tmp_path / "scaled.dcm", [("1.2.3", np.diag([2.0, 2.0, 2.0, 1.0]))], "1.2.4")
    with pytest.raises(DicomError, match=r"scaled.dcm.*FrameOfReferenceTransformationMatrix \(3006,00C6\).*rigid"):
        dicom.read_registration(scaled)
    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(DicomError, match=r"NaN"):
        dicom.read_registration(_hand_made(tmp_path / "nan.dcm", [("1.2.3", nan)], "1.2.4"))
    with pytest.raises(DicomError, match=r"xa.dcm: not a Spatial Registration object.*X-Ray Angiographic"):
        dicom.read_registration(pair[2] / "xa.dcm")
    three = _hand_made(tmp_path / "three.dcm", [("1.1", np.eye(4)), ("1.2", np.eye(4)), ("1.3", np.eye(4))], "1.1")
    with pytest.raises(DicomError, match=r"relates 3 Frames of Reference"):
        _ = dicom.read_registration(three).patient_motion
    volume, xray, _ = pair
    with pytest.raises(ValueError, match="not a rigid transform"):
        dicom.write_registration(tmp_path / "w.dcm", np.diag([1.0, 1.0, -1.0, 1.0]), volume=volume, xray=xray)
    assert not (tmp_path / "w.dcm").exists()
