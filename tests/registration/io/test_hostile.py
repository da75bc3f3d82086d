"""The hostile and broken files of issues 12 and 15, one test each: a clean DicomError naming the
file and the tag, bounded memory (tracemalloc peak), nothing else.

Files are built tag by tag with pydicom (tests/registration/io/test_dicom.py's builders) or
from the project's own writers.
"""

from __future__ import annotations

import io
import time
import tracemalloc
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.uid import DeflatedExplicitVRLittleEndian, EnhancedCTImageStorage

from registration.core.volume import Volume
from registration.io import dicom
from registration.io.dicom import DicomError
from registration.io.dicom.limits import ReadLimits, current_limits
from tests.registration.io.test_dicom import ct_slice, ramp, xa_file
from tests.registration.io.test_fuzz import deflated_zeros, one_member_zip

pytestmark = [
    pytest.mark.filterwarnings("ignore:.*using the whole image as the field:UserWarning"),
    pytest.mark.filterwarnings("ignore:Invalid value for VR DS:UserWarning"),  # pydicom, on writing nan/inf
    pytest.mark.filterwarnings("ignore:The value length .* exceeds:UserWarning"),
]

#: A refusal may hold the parsed header and a few small arrays: 20 MB is far below any of the
#: allocations the hostile files used to trigger (1.35 GB to 5 GB) and far above a header.
REFUSAL_PEAK_BYTES = 20 * 1024**2


def refused(call: Callable[[], object], *needles: str) -> tuple[str, int]:
    """Run ``call``, expect a DicomError containing every needle; (message, tracemalloc peak)."""
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(DicomError) as info:
                call()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    message = str(info.value)
    for needle in needles:
        assert needle in message, message
    assert peak < REFUSAL_PEAK_BYTES, f"{peak / 1e6:.0f} MB traced for a refusal: {message}"
    return message, peak


def _enhanced(tmp_path: Path) -> Path:
    small = Volume(np.zeros((3, 4, 5), np.float32), np.diag([1.0, 1.0, 2.0, 1.0]), label="small")
    return dicom.write_enhanced(small, tmp_path / "enhanced.dcm")


# --------------------------------------------------------------------------------------
# Issue 12, the three cases
# --------------------------------------------------------------------------------------
def test_enhanced_ct_declaring_two_billion_frames_is_refused_at_once(tmp_path: Path) -> None:
    """1 x 1 pixels, NumberOfFrames 2,147,483,647, 2 bytes of PixelData: ran > 20 min at 5 GB."""
    ds = pydicom.dcmread(_enhanced(tmp_path))
    ds.NumberOfFrames = 2**31 - 1
    ds.Rows, ds.Columns = 1, 1
    ds.PixelData = b"\x00\x00"
    del ds.PerFrameFunctionalGroupsSequence
    path = tmp_path / "bomb.dcm"
    ds.save_as(path)
    assert path.stat().st_size < 4000
    start = time.perf_counter()
    message, _ = refused(lambda: dicom.read_volume(path), str(path), "NumberOfFrames (0028,0008)")
    assert time.perf_counter() - start < 5.0  # generous: the header is parsed once (was > 20 min)


def test_frames_within_the_ceiling_but_not_in_the_file_are_refused(tmp_path: Path) -> None:
    ds = pydicom.dcmread(_enhanced(tmp_path))
    ds.NumberOfFrames = 1000
    path = tmp_path / "short.dcm"
    ds.save_as(path)
    refused(lambda: dicom.read_volume(path), "PixelData (7FE0,0010) holds 120 bytes", "declare 40,000")


def test_xa_frames_not_in_the_file_are_refused(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((2, 8, 8)))
    ds = pydicom.dcmread(path)
    ds.NumberOfFrames = 10_000
    ds.save_as(path)
    refused(lambda: dicom.read_xray(path, frame=0), str(path), "PixelData (7FE0,0010)")


def test_field_of_view_rotation_inf_is_a_message(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((8, 8)))
    ds = pydicom.dcmread(path)
    ds.FieldOfViewRotation = "inf"
    ds.save_as(path)
    refused(lambda: dicom.read_xray(path), str(path), "FieldOfViewRotation (0018,7032)")


# --------------------------------------------------------------------------------------
# Suspicious values (issue 12) and geometry values out of range
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("slope", ["0", "-1"])
def test_ct_rescale_slope_zero_or_negative_is_refused(tmp_path: Path, slope: str) -> None:
    folder = tmp_path / "ct"
    folder.mkdir()
    for k in range(3):
        path = ct_slice(folder / f"{k}.dcm", ramp((6, 6), k), ipp=(0, 0, 2.0 * k))
        ds = pydicom.dcmread(path)
        ds.RescaleSlope = slope
        ds.save_as(path)
    refused(lambda: dicom.read_volume(folder), "RescaleSlope (0028,1053)")


def test_xa_rescale_slope_zero_is_refused(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((8, 8)))
    ds = pydicom.dcmread(path)
    ds.RescaleSlope = "0"
    ds.save_as(path)
    refused(lambda: dicom.read_xray(path), "RescaleSlope (0028,1053) is 0")


def test_bits_stored_above_bits_allocated_is_refused(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((8, 8)))
    ds = pydicom.dcmread(path)
    ds.BitsStored = 24
    ds.save_as(path)
    refused(lambda: dicom.read_xray(path), "BitsStored (0028,0101) 24")


def test_primary_angle_outside_the_dicom_range_is_read_with_a_warning(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((8, 8)), primary=360.0)
    with pytest.warns(UserWarning, match="outside DICOM's ranges"):
        image = dicom.read_xray(path)
    assert image.geometry.primary_deg == 360.0


def test_xa_slices_inside_a_ct_series_are_refused(tmp_path: Path) -> None:
    folder = tmp_path / "mixed"
    folder.mkdir()
    for k in range(3):
        ct_slice(folder / f"{k}.dcm", ramp((6, 6), k), ipp=(0, 0, 2.0 * k), modality="XA" if k == 1 else "CT")
    refused(lambda: dicom.read_volume(folder), "Modality (0008,0060)", "CT, XA")


@pytest.mark.parametrize(
    ("keyword", "value"),
    [
        (keyword, value)
        for keyword in ("DistanceSourceToDetector", "DistanceSourceToPatient", "ImagerPixelSpacing")
        for value in ("0", "-1", "nan", "inf", "1e308")
    ]
    + [("PositionerPrimaryAngle", value) for value in ("nan", "inf", "1e308", "-361")],  # 0 and -1 deg are valid
)
def test_xa_geometry_values_out_of_range_are_refused(tmp_path: Path, keyword: str, value: str) -> None:
    path = xa_file(tmp_path / "xa.dcm", ramp((8, 8)))
    ds = pydicom.dcmread(path)
    ds[keyword].value = [value, value] if keyword == "ImagerPixelSpacing" else value
    ds.save_as(path)
    refused(lambda: dicom.read_xray(path), str(path), keyword)


@pytest.mark.parametrize("value", ["0", "-0.5", "nan", "1e300"])
def test_ct_pixel_spacing_out_of_range_is_refused(tmp_path: Path, value: str) -> None:
    """PixelSpacing 1e300 passed `info`, then `register` raised OverflowError."""
    folder = tmp_path / "ct"
    folder.mkdir()
    for k in range(3):
        path = ct_slice(folder / f"{k}.dcm", ramp((6, 6), k), ipp=(0, 0, 2.0 * k))
        ds = pydicom.dcmread(path)
        ds.PixelSpacing = [value, "0.5"]
        ds.save_as(path)
    refused(lambda: dicom.read_volume(folder), "PixelSpacing (0028,0030)")


def test_ct_position_1e308_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "ct"
    folder.mkdir()
    for k in range(3):
        ct_slice(folder / f"{k}.dcm", ramp((6, 6), k), ipp=(0, 0, 2.0 * k if k < 2 else 1e308))
    refused(lambda: dicom.read_volume(folder), "ImagePositionPatient (0020,0032)")


# --------------------------------------------------------------------------------------
# The .npz (issue 15): sizes from the member headers, before inflating
# --------------------------------------------------------------------------------------
def _npz(path: Path, data: np.ndarray, affine: np.ndarray | None = None) -> Path:
    np.savez(path, data=data, index_to_world=np.eye(4) if affine is None else affine, label=np.array("x"))
    return path


def zeros_npz(tmp_path: Path, shape: tuple[int, ...]) -> Path:
    """A small .npz whose float32 ``data.npy`` of ``shape`` is deflated zeros (it inflates to
    4 bytes a voxel), with an identity ``index_to_world.npy``."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": shape})
    size = int(np.prod(shape)) * 4
    payload, crc = deflated_zeros(size, header.getvalue())
    path = tmp_path / "zeros.npz"
    path.write_bytes(one_member_zip("data.npy", payload, crc, size + len(header.getvalue())))
    affine = io.BytesIO()
    np.save(affine, np.eye(4))
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("index_to_world.npy", affine.getvalue())
    return path


def test_npz_of_compressed_zeros_is_refused_before_inflating(tmp_path: Path) -> None:
    """A ~1 MB .npz inflating to 1.35 GB took 1.35 GB in `info` and 4.7 GB in `register`."""
    path = zeros_npz(tmp_path, (1280, 512, 512))  # float32: 1.34 GB
    assert path.stat().st_size < 3 * 1024**2
    refused(lambda: dicom.read_volume(path), str(path), "compressed", "ROADMAP3D_MAX_NPZ_RATIO")


def test_npz_declaring_more_than_the_voxel_ceiling_is_refused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("ROADMAP3D_MAX_VOXELS", "1000")
    path = _npz(tmp_path / "v.npz", np.ones((11, 10, 10), np.float32))
    refused(lambda: dicom.read_volume(path), "1,100 values is over the limit of 1,000", "ROADMAP3D_MAX_VOXELS")
    monkeypatch.setenv("ROADMAP3D_MAX_VOXELS", "1100")
    assert dicom.read_volume(path).shape == (11, 10, 10)  # raising the ceiling lets it through


def test_npz_with_a_forged_member_size_is_refused(tmp_path: Path) -> None:
    path = _npz(tmp_path / "v.npz", np.ones((4, 4, 4), np.float32))
    raw = bytearray(path.read_bytes())
    # 'shape': (4, 4, 4) -> (4, 4, 9) in the data member's header: the zip sizes no longer match
    at = raw.find(b"(4, 4, 4)")
    assert at > 0
    raw[at : at + 9] = b"(4, 4, 9)"
    path.write_bytes(bytes(raw))
    refused(lambda: dicom.read_volume(path), str(path))


@pytest.mark.parametrize(
    ("arrays", "needle"),
    [
        ({"data": np.ones((4, 4), np.float32), "index_to_world": np.eye(4)}, "3 axes"),
        ({"data": np.ones((4, 4, 4), np.float32), "index_to_world": np.eye(3)}, "(4, 4)"),
        ({"data": np.ones((4, 4, 4), np.float32)}, "missing array(s) index_to_world"),
        ({"data": np.full((4, 4, 4), np.nan, np.float32), "index_to_world": np.eye(4)}, "NaN"),
        ({"data": np.ones((4, 4, 4), np.float32), "index_to_world": np.diag([1e300, 1, 1, 1])}, "spacing"),
    ],
)
def test_npz_with_wrong_arrays_is_refused(tmp_path: Path, arrays: dict, needle: str) -> None:
    path = tmp_path / "v.npz"
    np.savez(path, **arrays)
    message, _ = refused(lambda: dicom.read_volume(path), str(path))
    assert needle in message, message


def test_deflated_data_set_bomb_is_refused_while_inflating(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("ROADMAP3D_MAX_FILE_MB", "2")
    path = ct_slice(tmp_path / "big.dcm", np.zeros((1200, 1200), np.uint16), ipp=(0, 0, 0))  # 2.9 MB of zeros
    ds = pydicom.dcmread(path)
    ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
    ds.save_as(path)
    assert path.stat().st_size < 100_000
    refused(lambda: dicom.read_volume(path), "deflated data set inflates", "ROADMAP3D_MAX_FILE_MB")


def test_limits_come_from_the_environment(monkeypatch) -> None:
    monkeypatch.setenv("ROADMAP3D_MAX_PIXEL_MB", "16")
    monkeypatch.setenv("ROADMAP3D_MAX_FRAMES", "7")
    limits = current_limits()
    assert limits.max_pixel_bytes == 16 * 1024**2 and limits.max_frames == 7
    monkeypatch.setenv("ROADMAP3D_MAX_FRAMES", "many")
    with pytest.raises(ValueError, match="ROADMAP3D_MAX_FRAMES must be a number"):
        current_limits()
    with pytest.raises(ValueError, match="max_frames"):
        ReadLimits(max_frames=0)


def test_enhanced_frames_over_the_frame_ceiling_are_refused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("ROADMAP3D_MAX_FRAMES", "2")
    path = _enhanced(tmp_path)
    assert pydicom.dcmread(path).SOPClassUID == EnhancedCTImageStorage
    refused(lambda: dicom.read_volume(path), "NumberOfFrames (0028,0008) 3 is over the limit of 2")


# --------------------------------------------------------------------------------------
# Messages that did not name the file (issue 15), sizes that cannot be (issue 12)
# --------------------------------------------------------------------------------------
def test_a_transfer_syntax_uid_that_is_not_one_is_named_with_the_file(tmp_path: Path) -> None:
    """It was "error: UID is not a transfer syntax." without the file."""
    path = xa_file(tmp_path / "xa.dcm", ramp((8, 8)))
    ds = pydicom.dcmread(path)
    ds.file_meta.TransferSyntaxUID = "1.2.840.1000.1.2.1"
    ds.save_as(path, enforce_file_format=False)
    refused(lambda: dicom.read_xray(path), str(path))


def test_pixels_that_do_not_fit_the_declared_columns_are_named_with_the_file(tmp_path: Path) -> None:
    """It was "cannot reshape array of size 65536 ..." without the file."""
    ds = pydicom.dcmread(_enhanced(tmp_path))
    ds.Columns = 2  # 3 frames x 4 x 2 declared, 3 x 4 x 5 stored
    path = tmp_path / "columns.dcm"
    ds.save_as(path)
    message, _ = refused(lambda: dicom.read_volume(path), str(path))
    assert "PixelData" in message


@pytest.mark.parametrize("rows", [0, 65535])
def test_rows_zero_or_all_ones_are_refused(tmp_path: Path, rows: int) -> None:
    """Rows = -1 stored in an unsigned tag reads as 65535 (or 0 after other tools' clamping)."""
    path = xa_file(tmp_path / "xa.dcm", ramp((8, 8)))
    ds = pydicom.dcmread(path)
    ds.Rows = rows
    ds.save_as(path)
    refused(lambda: dicom.read_xray(path), str(path), "Rows (0028,0010)")


def test_info_refuses_the_compressed_zeros_npz_without_inflating_it(tmp_path: Path, capsys) -> None:
    """`roadmap3d info` took 1.35 GB on a 1 MB .npz."""
    path = zeros_npz(tmp_path, (512, 512, 512))
    tracemalloc.start()
    try:
        report = dicom.inspect(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "compressed" in str(report) and peak < REFUSAL_PEAK_BYTES


def test_a_series_folder_larger_than_the_pixel_ceiling_is_refused_before_reading(tmp_path: Path, monkeypatch) -> None:
    """Every slice of a folder is held in memory until the stack is checked: its size counts first."""
    folder = tmp_path / "ct"
    folder.mkdir()
    for k in range(3):
        ct_slice(folder / f"{k}.dcm", ramp((300, 300), k), ipp=(0, 0, 2.0 * k))  # 180 kB each
    monkeypatch.setenv("ROADMAP3D_MAX_PIXEL_MB", "0.25")
    refused(lambda: dicom.read_volume(folder), str(folder), "its 3 files hold", "ROADMAP3D_MAX_PIXEL_MB")
    monkeypatch.setenv("ROADMAP3D_MAX_PIXEL_MB", "1")
    assert dicom.read_volume(folder).shape == (3, 300, 300)
