"""DICOM reading and writing (registration/dicom.py) and the surface meshes.

Files are built tag by tag here with pydicom, independently of the project's writers, so a
reader bug cannot hide behind a matching writer bug; pydicom's bundled example files cover
real-world encodings; hypothesis mutates valid files to check that readers never crash.
"""

from __future__ import annotations

import io
import math
import shutil
import stat
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pydicom
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydicom.data import get_testdata_file
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import (
    CTImageStorage,
    ExplicitVRLittleEndian,
    XRayAngiographicImageStorage,
    generate_uid,
)

from registration.core.geometry import CArm, rotation_x, rotation_z
from registration.core.images import XRayImage
from registration.core.volume import Volume
from registration.io import dicom
from registration.io.dicom import DicomError, UploadError

# Files built by hand mostly carry no collimation: the whole-image warning is expected there
# (test_xa_field_mask_from_shutter_and_border checks it).
pytestmark = pytest.mark.filterwarnings("ignore:.*using the whole image as the field:UserWarning")

# DS strings keep ~16 significant characters: positions in mm read back to ~1e-9 relative.
AFFINE_TOL = 1e-6


# --------------------------------------------------------------------------------------
# Files built tag by tag
# --------------------------------------------------------------------------------------
def _save(ds: Dataset, path: Path, sop_class: str) -> Path:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.save_as(path, enforce_file_format=True)
    return path


def ct_slice(
    path: Path,
    stored: np.ndarray,
    *,
    ipp: tuple[float, float, float],
    iop: tuple[float, ...] = (1, 0, 0, 0, 1, 0),
    spacing: tuple[float, float] = (0.8, 0.6),
    slope: float = 1.0,
    intercept: float = -1024.0,
    series_uid: str = "1.2.3.4",
    modality: str = "CT",
    sop_class: str = CTImageStorage,
) -> Path:
    ds = Dataset()
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = generate_uid()
    ds.StudyInstanceUID = "1.2.3"
    ds.SeriesInstanceUID = series_uid
    ds.Modality = modality
    ds.ImagePositionPatient = [f"{v:.6f}" for v in ipp]
    ds.ImageOrientationPatient = [f"{v:.6f}" for v in iop]
    ds.PixelSpacing = [str(spacing[0]), str(spacing[1])]
    ds.RescaleSlope = str(slope)
    ds.RescaleIntercept = str(intercept)
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = stored.shape
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 12, 11
    ds.PixelRepresentation = 0
    ds.PixelData = stored.astype(np.uint16).tobytes()
    return _save(ds, path, sop_class)


def xa_file(
    path: Path,
    stored: np.ndarray,
    *,
    primary: float = 0.0,
    secondary: float = 0.0,
    sid: float | None = 1200.0,
    sod: float = 800.0,
    imager_spacing: tuple[float, float] | None = (0.5, 0.4),
    pixel_spacing: tuple[float, float] | None = None,
    relationship: str | None = "LOG",
    sign: int | None = 1,
    bits_stored: int = 12,
    shutter: tuple[int, int, int] | None = None,
    increments: tuple[list[float], list[float]] | None = None,
    modality: str = "XA",
    sop_class: str = XRayAngiographicImageStorage,
) -> Path:
    stored = np.asarray(stored)
    ds = Dataset()
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = generate_uid()
    ds.StudyInstanceUID = "1.2.3"
    ds.SeriesInstanceUID = "1.2.3.9"
    ds.Modality = modality
    ds.PositionerPrimaryAngle = str(primary)
    ds.PositionerSecondaryAngle = str(secondary)
    if sid is not None:
        ds.DistanceSourceToDetector = str(sid)
    ds.DistanceSourceToPatient = str(sod)
    if imager_spacing is not None:
        ds.ImagerPixelSpacing = [str(v) for v in imager_spacing]
    if pixel_spacing is not None:
        ds.PixelSpacing = [str(v) for v in pixel_spacing]
    if relationship is not None:
        ds.PixelIntensityRelationship = relationship
    if sign is not None:
        ds.PixelIntensityRelationshipSign = sign
    if shutter is not None:
        ds.ShutterShape = "CIRCULAR"
        ds.CenterOfCircularShutter = [shutter[0], shutter[1]]
        ds.RadiusOfCircularShutter = shutter[2]
    if stored.ndim == 3:
        ds.NumberOfFrames = stored.shape[0]
        ds.PositionerMotion = "DYNAMIC"
        if increments is not None:
            ds.PositionerPrimaryAngleIncrement = [str(v) for v in increments[0]]
            ds.PositionerSecondaryAngleIncrement = [str(v) for v in increments[1]]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = stored.shape[-2:]
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, bits_stored, bits_stored - 1
    ds.PixelRepresentation = 0
    ds.PixelData = stored.astype(np.uint16).tobytes()
    return _save(ds, path, sop_class)


def ramp(shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 4000, size=shape).astype(np.uint16)


def oblique_volume(seed: int = 0) -> Volume:
    """A small volume with an oblique, anisotropic affine (rotation, not axis-aligned)."""
    rng = np.random.default_rng(seed)
    data = rng.normal(0.0, 400.0, (5, 6, 7)).astype(np.float32)
    rotation = rotation_z(20.0) @ rotation_x(-35.0)
    affine = np.eye(4)
    affine[:3, :3] = rotation @ np.diag([0.45, 0.6, 1.25])
    affine[:3, 3] = (-12.5, 30.25, 7.0)
    return Volume(data, affine, label="oblique test volume (stand-in)")


# --------------------------------------------------------------------------------------
# Volumes
# --------------------------------------------------------------------------------------
def test_series_built_by_hand_is_sorted_by_position_and_mapped_per_dicom(tmp_path: Path) -> None:
    # Slices stack toward the feet (normal = row x col = -z) and file names run against the
    # position order: sorting must follow the normal, not the names.
    row, col = np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])
    normal = np.cross(row, col)
    spacing = (0.8, 0.6)  # (row spacing, column spacing)
    step = 2.5
    origin = np.array([-20.0, 15.0, 40.0])
    stored = [ramp((4, 5), seed=k) for k in range(6)]
    for k in range(6):
        ipp = origin + k * step * normal
        ct_slice(
            tmp_path / f"IM{5 - k:02d}",
            stored[k],
            ipp=tuple(ipp),
            iop=(*row, *col),
            spacing=spacing,
            slope=2.0,
            intercept=-1000.0,
        )
    (tmp_path / "README.txt").write_text("not DICOM: skipped")
    vol = dicom.read_volume(tmp_path)
    assert vol.shape == (6, 4, 5)
    # Positions along the normal grow with k (toward the feet here): k is the volume's slice.
    for k in range(6):
        np.testing.assert_allclose(vol.data[k], stored[k] * 2.0 - 1000.0)
    expected = np.eye(4)
    expected[:3, 0] = row * spacing[1]
    expected[:3, 1] = col * spacing[0]
    expected[:3, 2] = normal * step
    expected[:3, 3] = origin
    np.testing.assert_allclose(vol.index_to_world, expected, atol=1e-5)
    # Pixel (i=3, j=2) of the file at k: IPP + i * row * col_spacing + j * col * row_spacing.
    world = vol.index_to_world @ np.array([3, 2, 1, 1.0])
    np.testing.assert_allclose(world[:3], origin + 1 * step * normal + 3 * 0.6 * row + 2 * 0.8 * col, atol=1e-5)


@pytest.mark.parametrize("writer", ["series", "enhanced", "npz"])
def test_volume_round_trip(tmp_path: Path, writer: str) -> None:
    vol = oblique_volume()
    if writer == "series":
        dicom.write_series(vol, tmp_path / "series")
        back = dicom.read_volume(tmp_path / "series")
        tol = 0.5  # int16 HU
    elif writer == "enhanced":
        dicom.write_enhanced(vol, tmp_path / "enhanced.dcm")
        back = dicom.read_volume(tmp_path / "enhanced.dcm")
        tol = 0.5
    else:
        dicom.write_npz(vol, tmp_path / "v.npz")
        back = dicom.read_volume(tmp_path / "v.npz")
        tol = 0.0
    assert np.max(np.abs(back.data - vol.data)) <= tol + 1e-4
    np.testing.assert_allclose(back.index_to_world, vol.index_to_world, atol=AFFINE_TOL)
    assert back.label == vol.label


def test_left_handed_volume_is_written_in_position_order(tmp_path: Path) -> None:
    # k runs toward the feet while row x column points to the head: the reader sorts along
    # the normal, so k comes back reversed, with the same world position of every voxel.
    data = np.arange(4 * 3 * 2, dtype=np.float32).reshape(4, 3, 2)
    affine = np.diag([1.0, 1.5, -2.0, 1.0])
    dicom.write_series(Volume(data, affine), tmp_path / "s")
    back = dicom.read_volume(tmp_path / "s")
    np.testing.assert_array_equal(back.data, data[::-1])
    for i, j, k in [(0, 0, 0), (1, 2, 3), (1, 0, 2)]:
        np.testing.assert_allclose(back.index_to_world @ [i, j, 3 - k, 1], affine @ [i, j, k, 1], atol=1e-9)


def test_written_series_is_a_plain_ct_series(tmp_path: Path) -> None:
    vol = oblique_volume()
    files = dicom.write_series(vol, tmp_path / "s")
    assert len(files) == vol.shape[0]
    ds = pydicom.dcmread(files[2])
    assert ds.SOPClassUID == CTImageStorage and ds.Modality == "CT"
    assert float(ds.RescaleSlope) == 1.0 and ds.RescaleType == "HU"
    np.testing.assert_allclose(
        [float(v) for v in ds.ImagePositionPatient], (vol.index_to_world @ [0, 0, 2, 1])[:3], atol=1e-6
    )
    with pytest.raises(ValueError, match="not empty"):
        dicom.write_series(vol, tmp_path / "s")


def _series(tmp_path: Path, positions: list[tuple[float, float, float]], **kwargs) -> Path:
    folder = tmp_path / "series"
    folder.mkdir(exist_ok=True)
    for k, p in enumerate(positions):
        ct_slice(folder / f"s{k}.dcm", ramp((4, 4), k), ipp=p, **kwargs)
    return folder


@pytest.mark.parametrize(
    ("positions", "message"),
    [
        ([(0, 0, 0), (0, 0, 1), (0, 0, 2), (0, 0, 4)], "uneven slice spacing"),
        ([(0, 0, 0), (0.3, 0, 1), (0.6, 0, 2), (0.9, 0, 3)], "gantry tilt"),
        ([(0, 0, 0), (0, 0, 1), (0, 0, 1), (0, 0, 2)], "same ImagePositionPatient"),
    ],
)
def test_bad_stacks_are_rejected_naming_the_tag(tmp_path: Path, positions, message: str) -> None:
    folder = _series(tmp_path, positions)
    with pytest.raises(DicomError, match=message) as info:
        dicom.read_volume(folder)
    assert "ImagePositionPatient (0020,0032)" in str(info.value)
    assert str(folder) in str(info.value)


def test_positions_rounded_by_the_scanner_are_accepted(tmp_path: Path) -> None:
    # 0.625 mm slices with positions written to 0.01 mm (as some scanners do): an even stack.
    positions = [(0.0, 0.0, round(-50.0 + 0.625 * k, 2)) for k in range(9)]
    vol = dicom.read_volume(_series(tmp_path, positions))
    assert vol.spacing_mm[2] == pytest.approx(0.625, abs=2e-3)


def test_mixed_series_and_orientations_are_rejected(tmp_path: Path) -> None:
    folder = _series(tmp_path, [(0, 0, 0), (0, 0, 1)])
    ct_slice(folder / "other.dcm", ramp((4, 4)), ipp=(0, 0, 2), series_uid="9.9.9")
    with pytest.raises(DicomError, match="mixed series"):
        dicom.read_volume(folder)
    (folder / "other.dcm").unlink()
    ct_slice(folder / "tilted.dcm", ramp((4, 4)), ipp=(0, 0, 2), iop=(1, 0, 0, 0, 0.8, 0.6))
    with pytest.raises(DicomError, match=r"ImageOrientationPatient \(0020,0037\)"):
        dicom.read_volume(folder)


def test_pydicom_examples(tmp_path: Path) -> None:
    ct = Path(get_testdata_file("CT_small.dcm"))
    with pytest.raises(DicomError, match="single 2-D image"):
        dicom.read_volume(ct)
    with pytest.raises(DicomError, match=r"wrong modality.*MR"):
        dicom.read_volume(get_testdata_file("MR_small.dcm"))
    truncated = tmp_path / "truncated.dcm"
    truncated.write_bytes(ct.read_bytes()[:1500])
    with pytest.raises(DicomError, match="truncated.dcm"):
        dicom.read_volume(truncated)
    with pytest.raises(DicomError, match="truncated.dcm"):
        dicom.read_xray(truncated)
    # A 3-slice series made from CT_small (positions moved along its normal).
    template = pydicom.dcmread(ct)
    folder = tmp_path / "ct"
    folder.mkdir()
    for k in range(3):
        template.ImagePositionPatient = [-158.135803, -179.035797, -75.7 + 5.0 * k]
        template.SOPInstanceUID = generate_uid()
        template.save_as(folder / f"{k}.dcm")
    vol = dicom.read_volume(folder)
    assert vol.shape == (3, 128, 128)
    np.testing.assert_allclose(vol.data[1], template.pixel_array.astype(np.float32) - 1024.0)
    np.testing.assert_allclose(vol.spacing_mm, [0.661468, 0.661468, 5.0], atol=1e-6)


def test_compressed_pixels_without_decoder_name_the_transfer_syntax(tmp_path: Path) -> None:
    # pydicom has no decoder for MPEG-4 video: the message must name the syntax and the tag.
    from pydicom.uid import MPEG4HP41

    source = pydicom.dcmread(get_testdata_file("MR_small_jpeg_ls_lossless.dcm"))
    source.file_meta.TransferSyntaxUID = MPEG4HP41
    folder = tmp_path / "mpeg"
    folder.mkdir()
    for k in range(2):
        source.Modality = "CT"
        source.ImagePositionPatient = [0, 0, float(k)]
        source.SOPInstanceUID = generate_uid()
        source.save_as(folder / f"{k}.dcm")
    with pytest.raises(DicomError, match=r"PixelData \(7FE0,0010\).*MPEG-4"):
        dicom.read_volume(folder)


def test_not_dicom_and_missing_paths(tmp_path: Path) -> None:
    (tmp_path / "a.dcm").write_bytes(b"hello, not dicom" * 20)
    with pytest.raises(DicomError, match="a.dcm"):
        dicom.read_volume(tmp_path / "a.dcm")
    with pytest.raises(DicomError, match="no DICOM files"):
        dicom.read_volume(tmp_path)
    with pytest.raises(DicomError, match="no such file"):
        dicom.read_xray(tmp_path / "missing.dcm")
    with pytest.raises(DicomError, match="no such file"):
        dicom.read_volume(tmp_path / "missing")


# --------------------------------------------------------------------------------------
# X-ray images
# --------------------------------------------------------------------------------------
def test_xa_geometry_from_the_positioner_tags(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((40, 50)), primary=90.0, secondary=0.0, sid=1100.0, sod=750.0)
    img = dicom.read_xray(path, isocenter_mm=(1.0, 2.0, 3.0))
    g = img.geometry
    assert (g.rows, g.cols) == (40, 50)
    assert g.pixel_mm == (0.5, 0.4)
    assert (g.sid_mm, g.sod_mm) == (1100.0, 750.0)
    assert g.isocenter_mm == (1.0, 2.0, 3.0)
    # CONVENTIONS §3: LAO 90 puts the detector at the patient's left (+x).
    np.testing.assert_allclose(g.direction, [1.0, 0.0, 0.0], atol=1e-12)


def test_rf_image_and_a_folder_of_projections(tmp_path: Path) -> None:
    from pydicom.uid import XRayRadiofluoroscopicImageStorage

    folder = tmp_path / "rf"
    folder.mkdir()
    path = xa_file(folder / "rf.dcm", ramp((8, 8)), modality="RF", sop_class=XRayRadiofluoroscopicImageStorage)
    with pytest.warns(UserWarning, match="whole image"):
        img = dicom.read_xray(path)
    assert img.kind == "dicom" and img.meta["format"] == "RF" and img.meta["acquisition"] == "fluoro"
    with pytest.raises(DicomError, match="RF projection image"):
        dicom.read_volume(folder)


def test_xa_log_and_lin_intensities(tmp_path: Path) -> None:
    attenuation = np.linspace(0.0, 3.0, 30 * 30).reshape(30, 30)
    # LOG, sign +1 (lower values = less intensity): stored = max - 1000 - 1000 * attenuation.
    stored = np.rint(4095 - 1000 - 1000 * attenuation)
    img = dicom.read_xray(xa_file(tmp_path / "log.dcm", stored, relationship="LOG", sign=1))
    np.testing.assert_allclose(img.image, attenuation, atol=0.5e-3 + 1e-6)
    # LOG, sign -1: stored = 1000 + 1000 * attenuation.
    stored = np.rint(1000 + 1000 * attenuation)
    img = dicom.read_xray(xa_file(tmp_path / "logm.dcm", stored, relationship="LOG", sign=-1))
    np.testing.assert_allclose(img.image, attenuation, atol=0.5e-3 + 1e-6)
    # LIN, sign +1: stored proportional to intensity; attenuation relative to the brightest pixel.
    intensity = 4000.0 * np.exp(-attenuation)
    img = dicom.read_xray(xa_file(tmp_path / "lin.dcm", np.rint(intensity), relationship="LIN", sign=1))
    np.testing.assert_allclose(img.image, attenuation, atol=0.5 / intensity.min())
    # LIN, sign -1: higher values = less intensity.
    img = dicom.read_xray(xa_file(tmp_path / "linm.dcm", np.rint(4095 - intensity), relationship="LIN", sign=-1))
    np.testing.assert_allclose(img.image, attenuation, atol=0.5 / intensity.min())


def test_xa_missing_tags_and_fallbacks(tmp_path: Path) -> None:
    with pytest.raises(DicomError, match=r"missing DistanceSourceToDetector \(0018,1110\)") as info:
        dicom.read_xray(xa_file(tmp_path / "nosid.dcm", ramp((8, 8)), sid=None))
    assert "nosid.dcm" in str(info.value)
    with pytest.warns(UserWarning, match="PixelSpacing"):
        img = dicom.read_xray(xa_file(tmp_path / "ps.dcm", ramp((8, 8)), imager_spacing=None, pixel_spacing=(0.3, 0.3)))
    assert img.geometry.pixel_mm == (0.3, 0.3)
    with pytest.raises(DicomError, match="ImagerPixelSpacing"):
        dicom.read_xray(xa_file(tmp_path / "nops.dcm", ramp((8, 8)), imager_spacing=None))
    with pytest.warns(UserWarning, match="PixelIntensityRelationship"):
        dicom.read_xray(xa_file(tmp_path / "norel.dcm", ramp((8, 8)), relationship=None))
    with pytest.raises(DicomError, match="wrong modality"):
        dicom.read_xray(get_testdata_file("CT_small.dcm"))
    with pytest.raises(DicomError, match="inconsistent geometry"):
        dicom.read_xray(xa_file(tmp_path / "sod.dcm", ramp((8, 8)), sid=700.0, sod=800.0))
    with pytest.raises(DicomError, match="is an XA projection image"):
        dicom.read_volume(tmp_path / "ps.dcm")


def test_xa_field_mask_from_shutter_and_border(tmp_path: Path) -> None:
    stored = ramp((21, 21)) // 2 + 100
    rr, cc = np.mgrid[0:21, 0:21]
    inside = (rr - 10) ** 2 + (cc - 10) ** 2 <= 8**2
    # Shutter only (1-based center 11, 11 is pixel index 10, 10).
    img = dicom.read_xray(xa_file(tmp_path / "shutter.dcm", stored, shutter=(11, 11, 8)))
    np.testing.assert_array_equal(img.mask, inside)
    assert np.all(img.image[~img.mask] == 0)
    # Constant border only (collimator blades at 0).
    img = dicom.read_xray(xa_file(tmp_path / "border.dcm", np.where(inside, stored, 0)))
    np.testing.assert_array_equal(img.mask, inside)
    # Neither: whole image, with a warning.
    with pytest.warns(UserWarning, match="whole image"):
        img = dicom.read_xray(xa_file(tmp_path / "none.dcm", stored))
    assert img.mask.all()


def test_multiframe_angles_from_increments(tmp_path: Path) -> None:
    frames = ramp((4, 8, 8))
    vector = xa_file(
        tmp_path / "v.dcm",
        frames,
        primary=-30.0,
        secondary=10.0,
        increments=([0.0, 10.0, 20.0, 30.0], [0.0, -1.0, -2.0, -3.0]),
    )
    assert dicom.read_xray_angles(vector) == [(-30.0, 10.0), (-20.0, 9.0), (-10.0, 8.0), (0.0, 7.0)]
    img = dicom.read_xray(vector, frame=2)
    assert (img.geometry.primary_deg, img.geometry.secondary_deg) == (-10.0, 8.0)
    scalar = xa_file(tmp_path / "s.dcm", frames, primary=-30.0, secondary=10.0, increments=([2.5], [0.0]))
    assert [a for a, _ in dicom.read_xray_angles(scalar)] == [-30.0, -27.5, -25.0, -22.5]
    with pytest.raises(DicomError, match=r"out of range.*NumberOfFrames"):
        dicom.read_xray(vector, frame=4)
    with pytest.warns(UserWarning, match="using frame 0"):
        dicom.read_xray(vector)
    bad = xa_file(tmp_path / "b.dcm", frames, increments=([1.0, 2.0], [0.0, 0.0]))
    with pytest.raises(DicomError, match="PositionerPrimaryAngleIncrement"):
        dicom.read_xray(bad, frame=1)


def test_enhanced_xa_per_frame_angles(tmp_path: Path) -> None:
    # Enhanced XA keeps geometry in functional groups: distances and spacing shared, angles per frame.
    from pydicom.sequence import Sequence
    from pydicom.uid import EnhancedXAImageStorage

    ds = Dataset()
    ds.SOPClassUID = EnhancedXAImageStorage
    ds.SOPInstanceUID = generate_uid()
    ds.Modality = "XA"
    ds.NumberOfFrames = 3
    shared = Dataset()
    geometry_item = Dataset()
    geometry_item.DistanceSourceToIsocenter = 785.0
    geometry_item.DistanceSourceToDetector = "1195"
    shared.XRayGeometrySequence = Sequence([geometry_item])
    ds.ImagerPixelSpacing = ["0.3", "0.3"]
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for n in range(3):
        item, position = Dataset(), Dataset()
        position.PositionerPrimaryAngle = str(-40.0 + 40.0 * n)
        position.PositionerSecondaryAngle = str(5.0 * n)
        item.PositionerPositionSequence = Sequence([position])
        frames.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.PixelIntensityRelationship = "LOG"
    ds.PixelIntensityRelationshipSign = 1
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = ds.Columns = 8
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.PixelData = ramp((3, 8, 8)).tobytes()
    path = _save(ds, tmp_path / "exa.dcm", EnhancedXAImageStorage)
    assert dicom.read_xray_angles(path) == [(-40.0, 0.0), (0.0, 5.0), (40.0, 10.0)]
    img = dicom.read_xray(path, frame=2)
    g = img.geometry
    assert (g.primary_deg, g.secondary_deg, g.sid_mm, g.sod_mm, g.pixel_mm) == (40.0, 10.0, 1195.0, 785.0, (0.3, 0.3))
    assert img.meta["format"] == "enhanced XA"


def test_field_of_view_rotation_is_undone(tmp_path: Path) -> None:
    stored = ramp((6, 6))
    path = xa_file(tmp_path / "rot.dcm", stored)
    ds = pydicom.dcmread(path)
    ds.FieldOfViewRotation = "90"
    ds.FieldOfViewHorizontalFlip = "YES"
    ds.save_as(path)
    with pytest.warns(UserWarning, match="FieldOfViewRotation"):
        img = dicom.read_xray(path)
    expected = (4095 - 1000 - np.rot90(stored[:, ::-1], k=1).astype(np.float64)) / dicom.LOG_UNITS_PER_ATTENUATION
    np.testing.assert_allclose(img.image, expected, atol=1e-6)


def _xray(geometry: CArm, seed: int = 0, kind: str = "fluoro") -> XRayImage:
    rng = np.random.default_rng(seed)
    image = rng.uniform(-0.5, 6.0, (geometry.rows, geometry.cols)).astype(np.float32)
    mask = geometry.field_mask()
    return XRayImage(
        image=np.where(mask, image, 0).astype(np.float32), mask=mask, geometry=geometry, kind=kind, meta={}
    )


@pytest.mark.parametrize("pixels", [32, 33])
def test_xa_writer_round_trip(tmp_path: Path, pixels: int) -> None:
    geometry = CArm.for_format(22, pixels=pixels, primary_deg=-35.5, secondary_deg=12.25)
    original = _xray(geometry, kind="exposure")
    path = dicom.write_xray(original, tmp_path / "xa.dcm")
    ds = pydicom.dcmread(path)
    assert ds.PixelIntensityRelationship == "LOG" and int(ds.PixelIntensityRelationshipSign) == 1
    assert ds.SOPClassUID == XRayAngiographicImageStorage
    back = dicom.read_xray(path)
    # DS strings hold 16 characters: lengths come back to ~1e-14 relative.
    for key, value in geometry.to_dict().items():
        np.testing.assert_allclose(back.geometry.to_dict()[key], value, rtol=1e-12)
    np.testing.assert_array_equal(back.mask, original.mask)
    # Quantisation: one stored step is 1 / LOG_UNITS_PER_ATTENUATION.
    assert np.max(np.abs(back.image - original.image)) <= 0.5 / dicom.LOG_UNITS_PER_ATTENUATION + 1e-6
    assert back.kind == "exposure"


def test_xa_run_writer_round_trip(tmp_path: Path) -> None:
    base = CArm.for_format(27, pixels=24)
    frames = [_xray(base.with_angles(-20.0 + 7.5 * n, 5.0 - n), seed=n) for n in range(5)]
    path = dicom.write_xray(frames, tmp_path / "run.dcm")
    assert dicom.read_xray_angles(path) == [(-20.0 + 7.5 * n, 5.0 - n) for n in range(5)]
    back = dicom.read_xray(path, frame=3)
    assert (back.geometry.primary_deg, back.geometry.secondary_deg) == (2.5, 2.0)
    assert np.max(np.abs(back.image - frames[3].image)) <= 0.5e-3 + 1e-6


def test_inspect_reports_and_never_raises(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((16, 16)), primary=12.0)
    report = dicom.inspect(path)
    assert report["accepted"] and report["kind"] == "xray"
    assert report["geometry"]["primary_deg"] == 12.0
    report = dicom.inspect(get_testdata_file("MR_small.dcm"))
    assert not report["accepted"] and "wrong modality" in report["problem"]
    report = dicom.inspect(tmp_path / "nothing")
    assert not report["accepted"]
    report = dicom.inspect("/dev/null")
    assert not report["accepted"] and "regular file" in report["problem"]


# --------------------------------------------------------------------------------------
# Fuzzing: mutated and truncated files never raise anything but ValueError
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def valid_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("fuzz")
    xa = xa_file(folder / "xa.dcm", ramp((2, 12, 12)), increments=([0.0, 5.0], [0.0, 1.0]), shutter=(6, 6, 5))
    ct = ct_slice(folder / "ct.dcm", ramp((12, 12)), ipp=(0, 0, 0))
    small = Volume(np.zeros((3, 4, 5), np.float32), np.diag([1.0, 1.0, 2.0, 1.0]), label="fuzz")
    enhanced = dicom.write_enhanced(small, folder / "enhanced.dcm")
    return {"xa": xa.read_bytes(), "ct": ct.read_bytes(), "enhanced": enhanced.read_bytes()}


def _read_all(path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for reader in (
            lambda: dicom.read_xray(path, frame=1),
            lambda: dicom.read_volume(path),
            lambda: dicom.inspect(path),
        ):
            try:
                reader()
            except ValueError:
                pass


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzz_mutated_files(tmp_path: Path, valid_files: dict[str, bytes], data: st.DataObject) -> None:
    source = bytearray(valid_files[data.draw(st.sampled_from(["xa", "ct", "enhanced"]))])
    edits = data.draw(st.lists(st.tuples(st.integers(0, len(source) - 1), st.integers(0, 255)), max_size=8))
    for position, value in edits:
        source[position] = value
    cut = data.draw(st.one_of(st.none(), st.integers(0, len(source))))
    path = tmp_path / "fuzz.dcm"
    path.write_bytes(bytes(source[:cut]))
    _read_all(path)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(primary=st.text(max_size=12), spacing=st.lists(st.text(max_size=8), max_size=3), sign=st.integers(-3, 3))
def test_fuzz_tag_values(tmp_path: Path, primary: str, spacing: list[str], sign: int) -> None:
    path = xa_file(tmp_path / "t.dcm", ramp((6, 6)))
    ds = pydicom.dcmread(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds["PositionerPrimaryAngle"].value = primary.replace("\\", "")
            ds["ImagerPixelSpacing"].value = [s.replace("\\", "") for s in spacing]
            ds.PixelIntensityRelationshipSign = sign
            ds.save_as(path)
    except Exception:
        return  # pydicom refused the value: nothing to read
    _read_all(path)


# --------------------------------------------------------------------------------------
# Uploads
# --------------------------------------------------------------------------------------
def _zip(entries: list[tuple[str | zipfile.ZipInfo, bytes]]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, payload in entries:
            archive.writestr(name, payload)
    return buffer.getvalue()


def test_unpack_upload_keeps_safe_members(tmp_path: Path) -> None:
    payload = _zip([("series/a.dcm", b"a" * 10), ("series/sub/b.dcm", b"b" * 20), ("xa.dcm", b"x")])
    files = dicom.unpack_upload(payload, tmp_path / "up", max_bytes=10_000)
    assert sorted(p.relative_to(tmp_path / "up").as_posix() for p in files) == [
        "series/a.dcm",
        "series/sub/b.dcm",
        "xa.dcm",
    ]
    assert stat.S_IMODE((tmp_path / "up").stat().st_mode) == 0o700


def _symlink_member() -> zipfile.ZipInfo:
    info = zipfile.ZipInfo("link")
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info


@pytest.mark.parametrize(
    ("entries", "message"),
    [
        ([("../evil.dcm", b"x")], r"'\.\.'"),
        ([("a/../../evil.dcm", b"x")], r"'\.\.'"),
        ([("/etc/evil", b"x")], "absolute"),
        ([("C:\\evil", b"x")], "absolute"),
        ([(_symlink_member(), b"/etc/passwd")], "symbolic link"),
        ([("a.dcm", b"x"), ("A.dcm", b"y")], "duplicate"),
        ([("bomb.bin", b"\0" * 3_000_000)], "limit|ratio"),
    ],
)
def test_unpack_upload_refuses_unsafe_archives(tmp_path: Path, entries, message: str) -> None:
    dest = tmp_path / "up"
    with pytest.raises(UploadError, match=message):
        dicom.unpack_upload(_zip([("ok.dcm", b"fine"), *entries]), dest, max_bytes=1_000_000)
    assert not any(dest.iterdir())  # nothing left behind
    assert not (tmp_path / "evil.dcm").exists()


def test_unpack_upload_limits(tmp_path: Path) -> None:
    with pytest.raises(UploadError, match="not a readable zip"):
        dicom.unpack_upload(b"PK\x03\x04 garbage", tmp_path / "a", max_bytes=1000)
    with pytest.raises(UploadError, match="exceeds the limit"):
        dicom.unpack_upload(b"x" * 2000, tmp_path / "b", max_bytes=1000)
    with pytest.raises(UploadError, match="members"):
        dicom.unpack_upload(_zip([(f"{n}.dcm", b"") for n in range(5)]), tmp_path / "c", max_bytes=10**6, max_files=3)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzz_unpack_upload(tmp_path_factory: pytest.TempPathFactory, data: st.DataObject) -> None:
    archive = bytearray(_zip([("series/a.dcm", b"a" * 300), ("b.dcm", bytes(range(256)) * 4)]))
    for position, value in data.draw(st.lists(st.tuples(st.integers(0, len(archive) - 1), st.integers(0, 255)))):
        archive[position] = value
    root = tmp_path_factory.mktemp("fuzzup")
    try:
        files = dicom.unpack_upload(bytes(archive), root / "up", max_bytes=4000)
    except UploadError:
        assert not any((root / "up").iterdir())
        return
    assert all(f.resolve().is_relative_to((root / "up").resolve()) for f in files)
    assert sum(f.stat().st_size for f in files) <= 4000


def test_upload_of_a_written_phantom_is_classified(tmp_path: Path) -> None:
    vol = oblique_volume()
    dicom.write_series(vol, tmp_path / "data" / "volume")
    dicom.write_xray(_xray(CArm.for_format(27, pixels=16)), tmp_path / "data" / "xa.dcm")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for p in sorted((tmp_path / "data").rglob("*.dcm")):
            archive.write(p, p.relative_to(tmp_path / "data").as_posix())
    dicom.unpack_upload(buffer.getvalue(), tmp_path / "up", max_bytes=10**7)
    found = dicom.classify_upload(tmp_path / "up")
    assert found["image"] == tmp_path / "up" / "xa.dcm"
    assert found["volume"] == tmp_path / "up" / "volume"
    assert dicom.read_volume(found["volume"]).shape == vol.shape
    shutil.rmtree(tmp_path / "up")
    # A flat archive: slices and the XA side by side (and a "./" entry); the XA is not a slice.
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("./", b"")
        for p in sorted((tmp_path / "data").rglob("*.dcm")):
            archive.write(p, p.name)
    dicom.unpack_upload(buffer.getvalue(), tmp_path / "flat", max_bytes=10**7)
    found = dicom.classify_upload(tmp_path / "flat")
    assert found == {"volume": tmp_path / "flat", "image": tmp_path / "flat" / "xa.dcm"}
    assert dicom.read_volume(found["volume"]).shape == vol.shape


# --------------------------------------------------------------------------------------
# Surface meshes
# --------------------------------------------------------------------------------------
def test_surface_meshes_of_a_tube_and_a_shell(tmp_path: Path) -> None:
    import trimesh

    from registration.io.meshes import surface_meshes, write_meshes

    n, spacing = 80, 0.5
    z, y, x = (np.mgrid[0:n, 0:n, 0:n] - (n - 1) / 2.0) * spacing
    r = np.sqrt(x**2 + y**2 + z**2)
    hu = np.zeros((n, n, n), np.float32)
    # A contrast-filled "vessel": a tube of radius 2 mm, 24 mm long along x, in soft tissue, its
    # ends 4 mm inside a bone shell (a vessel runs, away from bone: surface_meshes' vessel rules).
    tube = (np.hypot(y, z) < 2.0) & (np.abs(x) < 12.0)
    hu[tube] = 500.0
    hu[(r > 16.0) & (r < 17.5)] = 1500.0  # a bone shell
    vol = Volume.from_grid(hu, spacing, center_mm=(10.0, -5.0, 3.0))
    meshes = surface_meshes(vol)
    assert set(meshes) == {"vessels", "bone"}
    vessel = meshes["vessels"]
    assert vessel.is_watertight
    # The 250 HU iso-surface of a voxelised tube sits at its radius within half a voxel: its
    # volume is that of a cylinder of radius 2 mm, 24 mm long (its ends, within half a voxel of
    # where they are, change the radius by < 1 %).
    radius = math.sqrt(vessel.volume / (math.pi * 24.0))
    assert abs(radius - 2.0) < spacing / 2
    np.testing.assert_allclose(vessel.centroid, (10.0, -5.0, 3.0), atol=0.05)
    for suffix in (".stl", ".ply", ".glb"):
        out = write_meshes(meshes, tmp_path / f"m{suffix}")
        loaded = trimesh.load(out, force="mesh")
        assert len(loaded.faces) == sum(len(m.faces) for m in meshes.values())
    with pytest.raises(ValueError, match="mesh format"):
        write_meshes(meshes, tmp_path / "m.obj")
    coarse = surface_meshes(vol, bone_step=2)
    assert len(coarse["vessels"].faces) == len(vessel.faces)
    assert len(coarse["bone"].faces) < len(meshes["bone"].faces) / 2
