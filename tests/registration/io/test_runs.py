"""Multi-frame X-ray runs (registration/io/dicom/runs.py, CONVENTIONS §7).

Files are built tag by tag with pydicom (the helpers of test_dicom.py), so the three forms
of frame times are each read from a file the project's writer did not make.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence
from pydicom.uid import EnhancedXAImageStorage, generate_uid

from registration.core.geometry import CArm
from registration.io import dicom
from registration.io.dicom import DicomError
from tests.registration.io.test_dicom import _save, _xray, ramp, xa_file

pytestmark = [
    pytest.mark.filterwarnings("ignore:.*using the whole image as the field:UserWarning"),
    pytest.mark.filterwarnings("ignore:Invalid value for VR:UserWarning"),  # bad values written on purpose
]


def _with(path: Path, **tags: object) -> Path:
    ds = pydicom.dcmread(path)
    for key, value in tags.items():
        setattr(ds, key, value)
    ds.save_as(path)
    return path


def _run_file(tmp_path: Path, name: str, frames: int = 4, **tags: object) -> Path:
    path = xa_file(
        tmp_path / name,
        ramp((frames, 8, 8)),
        primary=-30.0,
        secondary=10.0,
        increments=([10.0 * n for n in range(frames)], [-1.0 * n for n in range(frames)]),
    )
    return _with(path, **tags)


def test_frame_times_from_frame_time_vector(tmp_path: Path) -> None:
    # Increments in ms, the first one 0 (DICOM C.7.6.5.1.2): t = cumulative sum / 1000.
    path = _run_file(tmp_path, "ftv.dcm", FrameTimeVector=["0", "66.7", "33.3", "100"], FrameTime="50")
    run = dicom.read_xray_run(path)
    # FrameTimeVector wins over FrameTime (CONVENTIONS §7); DS values are exact decimals here.
    np.testing.assert_allclose(run.times_s, [0.0, 0.0667, 0.1, 0.2], rtol=0, atol=1e-12)
    assert run.times_from == "FrameTimeVector"


def test_frame_times_from_frame_time(tmp_path: Path) -> None:
    run = dicom.read_xray_run(_run_file(tmp_path, "ft.dcm", FrameTime="66.666", CineRate="30"))
    np.testing.assert_allclose(run.times_s, np.arange(4) * 0.066666, rtol=0, atol=1e-12)
    assert run.times_from == "FrameTime"


def test_frame_times_from_cine_rate(tmp_path: Path) -> None:
    run = dicom.read_xray_run(_run_file(tmp_path, "cr.dcm", CineRate="15"))
    np.testing.assert_allclose(run.times_s, np.arange(4) / 15.0, rtol=0, atol=1e-12)
    assert run.times_from == "CineRate"
    assert "from CineRate" in dicom.inspect(run.path)["frame_times"]  # what roadmap3d info shows


def test_frame_times_refused_or_supplied(tmp_path: Path) -> None:
    bare = _run_file(tmp_path, "none.dcm")
    with pytest.raises(DicomError, match=r"none.dcm.*FrameTimeVector \(0018,1065\).*FrameTime \(0018,1063\)"):
        dicom.read_xray_run(bare)
    run = dicom.read_xray_run(bare, frame_time_ms=40.0)
    np.testing.assert_allclose(run.times_s, [0.0, 0.04, 0.08, 0.12], atol=1e-12)
    assert run.times_from == "frame_time_ms"
    with pytest.raises(DicomError, match=r"FrameTimeVector \(0018,1065\) holds 3 values for 4 frames"):
        dicom.read_xray_run(_run_file(tmp_path, "short.dcm", FrameTimeVector=["0", "1", "2"]))
    with pytest.raises(DicomError, match=r"FrameTimeVector.*negative"):
        dicom.read_xray_run(_run_file(tmp_path, "neg.dcm", FrameTimeVector=["0", "10", "-5", "10"]))
    with pytest.raises(DicomError, match=r"FrameTime \(0018,1063\) must be positive"):
        dicom.read_xray_run(_run_file(tmp_path, "zero.dcm", FrameTime="0"))
    with pytest.raises(DicomError, match=r"CineRate \(0018,0040\) must be positive"):
        dicom.read_xray_run(_run_file(tmp_path, "rate.dcm", CineRate="-3"))
    with pytest.raises(DicomError, match=r"FrameTimeVector \(0018,1065\) holds a NaN"):
        dicom.read_xray_run(_run_file(tmp_path, "nan.dcm", FrameTimeVector=["0", "nan", "1", "1"]))


def test_run_frames_carry_their_angles_and_times(tmp_path: Path) -> None:
    run = dicom.read_xray_run(_run_file(tmp_path, "angles.dcm", CineRate="10"))
    assert len(run) == 4
    assert run.angles_deg == [(-30.0, 10.0), (-20.0, 9.0), (-10.0, 8.0), (0.0, 7.0)]
    frame = run[2]
    assert (frame.geometry.primary_deg, frame.geometry.secondary_deg) == (-10.0, 8.0)
    assert frame.meta["t_s"] == pytest.approx(0.2, abs=1e-12)
    assert frame.geometry == run.geometries[2]
    # Frame n of the run is frame n of read_xray, pixel for pixel.
    np.testing.assert_array_equal(frame.image, dicom.read_xray(run.path, frame=2).image)
    assert [img.meta["frame"] for img in run] == [0, 1, 2, 3]
    with pytest.raises(IndexError, match="out of range"):
        run[4]


def _enhanced_run(path: Path, *, frames: int, stamps: list[str] | None, planes: list[str] | None) -> Path:
    ds = Dataset()
    ds.SOPClassUID = EnhancedXAImageStorage
    ds.SOPInstanceUID = generate_uid()
    ds.Modality = "XA"
    ds.NumberOfFrames = frames
    shared, geometry_item = Dataset(), Dataset()
    geometry_item.DistanceSourceToIsocenter = 785.0
    geometry_item.DistanceSourceToDetector = "1195"
    shared.XRayGeometrySequence = Sequence([geometry_item])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    ds.ImagerPixelSpacing = ["0.3", "0.3"]
    items = []
    for n in range(frames):
        item, position, content = Dataset(), Dataset(), Dataset()
        position.PositionerPrimaryAngle = str(-40.0 + 40.0 * n)
        position.PositionerSecondaryAngle = str(5.0 * n)
        item.PositionerPositionSequence = Sequence([position])
        if stamps is not None:
            content.FrameAcquisitionDateTime = stamps[n]
            item.FrameContentSequence = Sequence([content])
        if planes is not None:
            item.PlaneIdentification = planes[n]
        items.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(items)
    ds.PixelIntensityRelationship = "LOG"
    ds.PixelIntensityRelationshipSign = 1
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = ds.Columns = 8
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.PixelData = ramp((frames, 8, 8)).tobytes()
    return _save(ds, path, EnhancedXAImageStorage)


def test_enhanced_run_times_angles_and_planes_per_frame(tmp_path: Path) -> None:
    stamps = ["20260101120000.000000", "20260101120000.066667", "20260101120000.200000"]
    path = _enhanced_run(tmp_path / "exa.dcm", frames=3, stamps=stamps, planes=["PLANE A", "PLANE A", "PLANE B"])
    run = dicom.read_xray_run(path)
    # DT has microsecond resolution; a POSIX timestamp as float64 keeps ~0.2 us at 2026.
    np.testing.assert_allclose(run.times_s, [0.0, 0.066667, 0.2], rtol=0, atol=1e-6)
    assert run.times_from == "FrameAcquisitionDateTime"
    assert run.angles_deg == [(-40.0, 0.0), (0.0, 5.0), (40.0, 10.0)]
    assert run.planes == ("PLANE A", "PLANE A", "PLANE B")
    assert run[2].meta["plane"] == "PLANE B"
    assert dicom.read_xray(path, frame=0).meta["plane"] == "PLANE A"
    assert run.geometries[1].sod_mm == 785.0
    same = _enhanced_run(tmp_path / "same.dcm", frames=2, stamps=["20260101120000"] * 2, planes=None)
    with pytest.raises(DicomError, match="no frame times"):  # one moment for every frame is no time line
        dicom.read_xray_run(same)
    bad = _enhanced_run(tmp_path / "bad.dcm", frames=2, stamps=["20260101120000", "tomorrow"], planes=None)
    with pytest.raises(DicomError, match=r"FrameAcquisitionDateTime \(0018,9074\) of frame 1"):
        dicom.read_xray_run(bad)
    wrong = _enhanced_run(tmp_path / "plane.dcm", frames=2, stamps=None, planes=["PLANE C", "PLANE A"])
    with pytest.raises(DicomError, match=r"PlaneIdentification \(0018,9457\)"):
        dicom.read_xray_run(wrong, frame_time_ms=10.0)


@pytest.mark.parametrize("times", [[0.0, 0.1, 0.2, 0.3, 0.4], [0.0, 0.0667, 0.1, 0.25, 0.3]])
def test_write_xray_run_round_trip(tmp_path: Path, times: list[float]) -> None:
    base = CArm.for_format(27, pixels=24)
    frames = [_xray(base.with_angles(-20.0 + 7.5 * n, 5.0 - n), seed=n) for n in range(5)]
    path = dicom.write_xray_run(frames, tmp_path / "run.dcm", times_s=times, plane="PLANE B")
    ds = pydicom.dcmread(path)
    even = len({round(b - a, 9) for a, b in zip(times, times[1:], strict=False)}) == 1
    assert ("FrameTime" in ds, "FrameTimeVector" in ds) == (even, not even)
    run = dicom.read_xray_run(path)
    # DS strings keep 16 characters: times come back to ~1e-12 s.
    np.testing.assert_allclose(run.times_s, times, rtol=0, atol=1e-9)
    assert run.angles_deg == [(-20.0 + 7.5 * n, 5.0 - n) for n in range(5)]
    assert run.planes == ("PLANE B",) * 5
    assert run.meta["acquisition_datetime"] == ds.AcquisitionDateTime  # for pairing biplane runs (§6)
    for original, back in zip(frames, run, strict=True):
        # One stored step is 1 / LOG_UNITS_PER_ATTENUATION (rounding: half of it).
        assert np.max(np.abs(back.image - original.image)) <= 0.5 / dicom.LOG_UNITS_PER_ATTENUATION + 1e-6
        np.testing.assert_array_equal(back.mask, original.mask)


def test_write_xray_run_refuses_bad_times(tmp_path: Path) -> None:
    frames = [_xray(CArm.for_format(27, pixels=16), seed=n) for n in range(3)]
    with pytest.raises(ValueError, match="one time per frame"):
        dicom.write_xray_run(frames, tmp_path / "a.dcm", times_s=[0.0, 0.1])
    with pytest.raises(ValueError, match="must not decrease"):
        dicom.write_xray_run(frames, tmp_path / "b.dcm", times_s=[0.0, 0.2, 0.1])
    with pytest.raises(ValueError, match=r"times_s\[0\] must be 0"):
        dicom.write_xray_run(frames, tmp_path / "c.dcm", times_s=[1.0, 1.1, 1.2])
    with pytest.raises(ValueError, match="plane must be one of"):
        dicom.write_xray_run(frames, tmp_path / "d.dcm", plane="PLANE Z")
    assert not list(tmp_path.iterdir())  # nothing half-written


@pytest.mark.filterwarnings("ignore:.*undid FieldOfViewRotation:UserWarning")
def test_enhanced_field_of_view_per_frame(tmp_path: Path) -> None:
    # Frame 1 was stored rotated 90 deg clockwise (its Field of View functional group says so),
    # frame 0 not: each frame is turned back on its own.
    path = _enhanced_run(tmp_path / "fov.dcm", frames=2, stamps=None, planes=None)
    ds = pydicom.dcmread(path)
    fov = Dataset()
    fov.FieldOfViewRotation = "90"
    fov.FieldOfViewHorizontalFlip = "NO"
    ds.PerFrameFunctionalGroupsSequence[1].FieldOfViewSequence = Sequence([fov])
    ds.save_as(path)
    stored = ds.pixel_array
    run = dicom.read_xray_run(path, frame_time_ms=100.0)
    physical = [stored[0], np.rot90(stored[1])]  # rotated back counter-clockwise
    expected = [(4095 - 1000 - p.astype(float)) / dicom.LOG_UNITS_PER_ATTENUATION for p in physical]
    for n in range(2):
        np.testing.assert_allclose(run[n].image, expected[n], atol=1e-6)
    assert "field_rotation" in run[1].meta and "field_rotation" not in run[0].meta
