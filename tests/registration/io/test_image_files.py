"""TIFF/PNG X-ray images with a geometry side file (registration.io.image_files).

Truth: the DICOM XA that the project writes and reads is the reference. Its TIFF twin (the same
line integrals, mask and geometry in the side file) must read back identical; an intensity PNG
must give -log(I/I0); flips and the principal point must move the pixels and the central ray where
CONVENTIONS §3 puts them (the iso-center projects to the principal point).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.io import dicom
from registration.io.image_files import ImageFileError, read_image_file, write_image_file

GEOMETRY = {"primary_deg": 20.0, "secondary_deg": -10.0, "sid_mm": 1200.0, "sod_mm": 800.0, "pixel_mm": 0.5}


def _xray(rows: int = 48, cols: int = 64) -> XRayImage:
    geometry = CArm(primary_deg=20.0, secondary_deg=-10.0, rows=rows, cols=cols, pixel_mm=(0.5, 0.5))
    mask = geometry.field_mask()
    image = np.random.default_rng(0).random((rows, cols)).astype(np.float32) * mask
    return XRayImage(image, mask, geometry, "fluoro")


def test_tiff_twin_of_a_dicom_reads_back_identical(tmp_path: Path) -> None:
    from_dicom = dicom.read_xray(dicom.write_xray(_xray(), tmp_path / "xa.dcm"))
    write_image_file(from_dicom, tmp_path / "xa.tif")
    twin = dicom.read_xray(tmp_path / "xa.tif")  # the side file xa.json is found by name
    np.testing.assert_array_equal(twin.image, from_dicom.image)
    np.testing.assert_array_equal(twin.mask, from_dicom.mask)
    assert twin.geometry == from_dicom.geometry
    assert twin.meta["format"] == "TIFF" and "mask file" in twin.meta["mask_from"]


def test_intensity_png_gives_line_integrals(tmp_path: Path) -> None:
    intensity = np.full((40, 50), 4000, dtype=np.uint16)
    intensity[10:20, 10:30] = 1000  # a quarter of the X-rays: line integral log(4)
    intensity[:, :3] = intensity[:, -3:] = 0  # a constant dark border: outside the field
    Image.fromarray(intensity).save(tmp_path / "x.png")
    (tmp_path / "x.json").write_text(json.dumps(GEOMETRY))
    xray = read_image_file(tmp_path / "x.png")
    assert not xray.mask[:, :3].any() and not xray.mask[:, -3:].any() and xray.mask[:, 3:-3].all()
    assert xray.image[15, 20] == pytest.approx(np.log(4.0), rel=1e-6)
    assert xray.image[30, 40] == pytest.approx(0.0, abs=1e-7)  # the brightest pixel of the field is I0
    given = read_image_file(tmp_path / "x.png", geometry={**GEOMETRY, "i0": 8000.0})
    assert given.image[30, 40] == pytest.approx(np.log(2.0), rel=1e-6)


def test_flips_and_principal_point(tmp_path: Path) -> None:
    rows, cols = 30, 40
    pixels = np.arange(rows * cols, dtype=np.float32).reshape(rows, cols) + 1.0
    tifffile.imwrite(tmp_path / "f.tif", pixels)
    geometry = {**GEOMETRY, "pixel_values": "line_integral", "principal_point_px": [12.0, 7.0], "flip_horizontal": True}
    xray = read_image_file(tmp_path / "f.tif", geometry=geometry)
    np.testing.assert_array_equal(xray.image, pixels[:, ::-1])
    # the central ray meets the stored pixel (12, 7): after the left-right flip, column 40 - 1 - 12
    np.testing.assert_allclose(xray.geometry.project(np.zeros((1, 3)))[0], [cols - 1 - 12.0, 7.0], atol=1e-9)
    both = read_image_file(tmp_path / "f.tif", geometry={**geometry, "flip_vertical": True})
    np.testing.assert_array_equal(both.image, pixels[::-1, ::-1])
    np.testing.assert_allclose(both.geometry.project(np.zeros((1, 3)))[0], [27.0, rows - 1 - 7.0], atol=1e-9)


@pytest.mark.parametrize(
    ("geometry", "message"),
    [
        ({**GEOMETRY, "sid": 1200}, "unknown key"),
        ({k: v for k, v in GEOMETRY.items() if k != "pixel_mm"}, "missing key.*pixel_mm"),
        ({**GEOMETRY, "primary_deg": "LAO"}, "primary_deg: a finite number"),
        ({**GEOMETRY, "pixel_values": "log"}, "pixel_values"),
        ({k: v for k, v in GEOMETRY.items() if k != "sid_mm"}, "sid_mm and sod_mm are needed"),
    ],
)
def test_bad_geometry_is_named(tmp_path: Path, geometry: dict, message: str) -> None:
    tifffile.imwrite(tmp_path / "g.tif", np.ones((8, 8), dtype=np.float32))
    with pytest.raises(ImageFileError, match=message):
        read_image_file(tmp_path / "g.tif", geometry=geometry)


def test_missing_side_file_and_colour_image(tmp_path: Path) -> None:
    tifffile.imwrite(tmp_path / "alone.tif", np.ones((8, 8), dtype=np.float32))
    with pytest.raises(ImageFileError, match=r"alone\.json: no such geometry file"):
        dicom.read_xray(tmp_path / "alone.tif")
    Image.fromarray(np.zeros((8, 8, 3), dtype=np.uint8)).save(tmp_path / "rgb.png")
    with pytest.raises(ImageFileError, match="PNG mode RGB"):
        read_image_file(tmp_path / "rgb.png", geometry=GEOMETRY)
    tifffile.imwrite(tmp_path / "stack.tif", np.ones((3, 8, 8), dtype=np.float32), photometric="minisblack")
    with pytest.raises(ImageFileError, match="one grayscale image"):
        read_image_file(tmp_path / "stack.tif", geometry=GEOMETRY)


def test_info_reads_image_and_volume_files(tmp_path: Path) -> None:
    from registration.io.volume_files import write_volume_file

    from_dicom = dicom.read_xray(dicom.write_xray(_xray(), tmp_path / "xa.dcm"))
    write_image_file(from_dicom, tmp_path / "xa.tif")
    report = dicom.inspect(tmp_path / "xa.tif")
    assert report["accepted"] and report["kind"] == "xray" and report["geometry"]["primary_deg"] == 20.0
    from registration.core.volume import Volume

    write_volume_file(Volume.from_grid(np.zeros((4, 5, 6)), 1.0), tmp_path / "v.nii.gz")
    report = dicom.inspect(tmp_path / "v.nii.gz")
    assert report["accepted"] and report["format"] == "NIfTI" and report["shape_kji"] == [4, 5, 6]


def test_an_upload_of_a_nifti_and_a_tiff_is_recognised(tmp_path: Path) -> None:
    from registration.core.volume import Volume
    from registration.io.dicom.uploads import classify_upload
    from registration.io.volume_files import write_volume_file

    write_volume_file(Volume.from_grid(np.zeros((4, 5, 6)), 1.0), tmp_path / "ct.nii.gz")
    write_image_file(_xray(), tmp_path / "xa.tif")  # with xa.json and xa-mask.png beside it
    tifffile.imwrite(tmp_path / "other.tif", np.ones((8, 8), dtype=np.float32))  # no side file: not an X-ray
    found = classify_upload(tmp_path)
    assert found == {"volume": tmp_path / "ct.nii.gz", "image": tmp_path / "xa.tif"}
