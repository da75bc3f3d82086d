"""Compressed pixel data: JPEG Lossless, JPEG baseline/extended, JPEG-LS, JPEG 2000, RLE.

Lossless files must decode to exactly the pixels of their uncompressed twin: pydicom's
bundled MR_small in RLE, JPEG-LS and JPEG 2000, and (tests/registration/io/data, made with
DCMTK's encoder) JPEG Lossless. Lossy JPEG cannot give the twin's pixels back: there the
error against the twin must be that of quality 95, and for 8 bits two independent decoders
(GDCM's and Pillow's libjpeg-turbo) must agree. The default decoders are permissively licensed
(GDCM for JPEG and JPEG-LS, pylibjpeg's openjpeg and rle plugins); 12-bit JPEG extended needs
the optional GPL plugin and otherwise fails with a message naming it. The phantom's own series and runs,
written compressed, must read back identical to the uncompressed files.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.data import get_testdata_file
from pydicom.uid import JPEG2000Lossless, RLELossless, generate_uid

from registration.core.geometry import CArm
from registration.io import dicom
from registration.io.dicom._common import _pixels
from tests.registration.io.test_dicom import _xray

DATA = Path(__file__).parent / "data"
TWIN = get_testdata_file("MR_small.dcm")

LOSSLESS = [
    (get_testdata_file("MR_small_RLE.dcm"), "pylibjpeg-rle"),
    (get_testdata_file("MR_small_jpeg_ls_lossless.dcm"), "python-gdcm"),
    (get_testdata_file("MR_small_jp2klossless.dcm"), "pylibjpeg-openjpeg"),
    (str(DATA / "MR_small_jpeg_lossless_sv1.dcm"), "python-gdcm"),
    (str(DATA / "MR_small_jpeg_lossless_p14.dcm"), "python-gdcm"),
]


@pytest.fixture(autouse=True)
def _gdcm_installed() -> None:
    from importlib.util import find_spec

    if find_spec("gdcm") is None:
        pytest.fail("python-gdcm, a dependency, is missing: reinstall with pip install -e '.[test]' -c constraints.txt")


def _gpl_jpeg_installed() -> bool:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return bool(version("pylibjpeg-libjpeg"))
    except PackageNotFoundError:
        return False


def _decode(path: str) -> np.ndarray:
    ds = pydicom.dcmread(path)
    return _pixels(Path(path), ds)


@pytest.mark.parametrize(("path", "plugin"), LOSSLESS, ids=[Path(p).name for p, _ in LOSSLESS])
def test_lossless_files_decode_to_their_uncompressed_twin(path: str, plugin: str) -> None:
    ds = pydicom.dcmread(path)
    assert ds.file_meta.TransferSyntaxUID.is_compressed
    np.testing.assert_array_equal(_decode(path), pydicom.dcmread(TWIN).pixel_array)
    name, description = dicom.pixel_decoder(ds)
    assert name in ("gdcm", "pylibjpeg") and plugin in description


def _as_ct_series(source: str, folder: Path, slices: int = 2) -> Path:
    """The file's pixels as a small CT series (headers changed, pixel data untouched)."""
    folder.mkdir()
    for k in range(slices):
        ds = pydicom.dcmread(source)
        ds.Modality = "CT"
        ds.ImagePositionPatient = [0.0, 0.0, 2.0 * k]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.SOPInstanceUID = generate_uid()
        ds.SeriesInstanceUID = "1.2.3.4.5.6"
        ds.save_as(folder / f"{k}.dcm")
    return folder


@pytest.mark.parametrize(("path", "plugin"), LOSSLESS, ids=[Path(p).name for p, _ in LOSSLESS])
def test_compressed_series_reads_like_the_uncompressed_one(path: str, plugin: str, tmp_path: Path) -> None:
    plain = dicom.read_volume(_as_ct_series(TWIN, tmp_path / "plain"))
    packed = dicom.read_volume(_as_ct_series(path, tmp_path / "packed"))
    np.testing.assert_array_equal(packed.data, plain.data)
    np.testing.assert_array_equal(packed.index_to_world, plain.index_to_world)
    assert plugin in packed.meta["decoder"] and plain.meta["decoder"] == "native (uncompressed)"
    report = dicom.inspect(tmp_path / "packed")
    assert report["accepted"] and plugin in report["decoder"]


@pytest.mark.parametrize(
    "path",
    [DATA / "MR_small_8bit_jpeg_baseline.dcm", DATA / "MR_small_12bit_jpeg_extended.dcm"],
    ids=["baseline-8bit", "extended-12bit"],
)
def test_lossy_jpeg_decodes_close_to_its_twin(path: Path) -> None:
    ds = pydicom.dcmread(path)
    if int(ds.BitsStored) > 8 and not _gpl_jpeg_installed():
        with pytest.raises(dicom.DicomError, match=r"roadmap3d\[gpl-jpeg\]"):
            _decode(str(path))
        pytest.skip("12-bit JPEG extended needs the optional pylibjpeg-libjpeg (GPL-3.0); its message was checked")
    assert dicom.pixel_decoder(ds)[0] == ("gdcm" if int(ds.BitsStored) == 8 else "pylibjpeg")
    ours = _decode(str(path)).astype(np.int64)
    twin = pydicom.dcmread(str(path).replace("_jpeg_baseline", "").replace("_jpeg_extended", ""))
    error = np.abs(ours - twin.pixel_array.astype(np.int64))
    # IJG quality 95: seen at most 8 steps off, 1.2-1.5 on average (8 and 12 bits); an offset
    # or a scaling mistake would be tens of steps everywhere.
    assert 0 < np.max(error) <= 12, np.max(error)
    assert np.mean(error) < 3.0
    if int(ds.BitsStored) == 8:
        # Pillow (libjpeg-turbo) is an independent decoder (8-bit only): seen identical to GDCM;
        # IDCT rounding may differ by one step between JPEG libraries.
        pillow = pydicom.pixels.pixel_array(ds, decoding_plugin="pillow").astype(np.int64)
        assert np.max(np.abs(ours - pillow)) <= 1


#: ``../shared/data/real-xa`` beside the project, or ``$ROADMAP3D_SHARED_DATA/real-xa``.
REAL_XA = (
    Path(os.environ.get("ROADMAP3D_SHARED_DATA") or Path(__file__).resolve().parents[3].parent / "shared" / "data")
    / "real-xa"
    / "coronary-xa-96-frames.dcm"
)


def test_real_jpeg_baseline_run_decodes_like_pillow() -> None:
    """The real XA run (JPEG baseline, 8 bits): GDCM, the default, and Pillow give the same pixels."""
    if not REAL_XA.exists():
        pytest.skip(f"real X-ray data not found at {REAL_XA} (kept outside the repository)")
    ds = pydicom.dcmread(REAL_XA)
    assert dicom.pixel_decoder(ds)[0] == "gdcm"
    ours = _pixels(REAL_XA, ds, index=40).astype(np.int64)
    pillow = pydicom.pixels.pixel_array(ds, index=40, decoding_plugin="pillow").astype(np.int64)
    # seen identical on all 96 frames; one step of IDCT rounding is what separates JPEG libraries
    assert np.max(np.abs(ours - pillow)) <= 1
    assert ours.std() > 10  # a real angiogram, not a blank frame


@pytest.fixture(scope="module")
def phantom_series(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from registration.sim.phantom import registration_volume

    volume = registration_volume(0, 27.0, voxels=32, cache=False)
    folder = tmp_path_factory.mktemp("phantom") / "series"
    dicom.write_series(volume, folder, uid_seed="compressed test")
    return folder


@pytest.mark.parametrize("syntax", [RLELossless, JPEG2000Lossless], ids=["RLE", "JPEG2000"])
def test_phantom_series_written_compressed_reads_back_identical(
    phantom_series: Path, tmp_path: Path, syntax: str
) -> None:
    folder = tmp_path / "packed"
    folder.mkdir()
    for path in sorted(phantom_series.iterdir()):
        ds = pydicom.dcmread(path)
        ds.compress(syntax, generate_instance_uid=False)  # RLE: pydicom/pylibjpeg-rle; J2K: openjpeg
        ds.save_as(folder / path.name)
    plain = dicom.read_volume(phantom_series)
    packed = dicom.read_volume(folder)
    assert pydicom.dcmread(next(folder.iterdir())).file_meta.TransferSyntaxUID == syntax
    np.testing.assert_array_equal(packed.data, plain.data)
    np.testing.assert_array_equal(packed.index_to_world, plain.index_to_world)


@pytest.mark.parametrize("syntax", [RLELossless, JPEG2000Lossless], ids=["RLE", "JPEG2000"])
def test_xa_run_written_compressed_reads_back_identical(tmp_path: Path, syntax: str) -> None:
    base = CArm.for_format(27, pixels=64)  # JPEG 2000's 6 resolution levels need >= 32 pixels
    frames = [_xray(base.with_angles(10.0 * n, 0.0), seed=n) for n in range(3)]
    plain = dicom.read_xray_run(dicom.write_xray_run(frames, tmp_path / "plain.dcm"))
    packed = dicom.read_xray_run(dicom.write_xray_run(frames, tmp_path / "packed.dcm", transfer_syntax=syntax))
    assert pydicom.dcmread(packed.path).file_meta.TransferSyntaxUID == syntax
    for a, b in zip(plain, packed, strict=True):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.mask, b.mask)
    assert packed[0].meta["decoder"].startswith("pylibjpeg")
    single = dicom.write_xray(frames[0], tmp_path / "one.dcm", transfer_syntax=syntax)
    np.testing.assert_array_equal(dicom.read_xray(single).image, plain[0].image)
    with pytest.raises(ValueError, match="not one the writer compresses to"):
        dicom.write_xray(frames[0], tmp_path / "bad.dcm", transfer_syntax="1.2.840.10008.1.2.4.50")
    assert not (tmp_path / "bad.dcm").exists()
