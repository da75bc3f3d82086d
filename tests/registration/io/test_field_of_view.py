"""FieldOfViewRotation / FieldOfViewHorizontalFlip / FieldOfViewOrigin onto CONVENTIONS §3 axes.

A world point is placed on the ray through a chosen physical detector pixel; the physical
image gets a mark there; the file stores that image the way DICOM says a system does
(rotated clockwise, then flipped; cropped to the field of view). After reading, the geometry
must project the point onto the pixel that holds its mark.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
import pytest

from registration.core.geometry import CArm
from registration.io import dicom
from registration.io.dicom import DicomError
from tests.registration.io.test_dicom import xa_file

pytestmark = [
    pytest.mark.filterwarnings("ignore:.*using the whole image as the field:UserWarning"),
    pytest.mark.filterwarnings("ignore:.*undid FieldOfViewRotation:UserWarning"),
]

BACKGROUND = 2000
#: Physical detector pixels (col, row) that get marks, each a different stored value.
MARKS = [(3, 4), (25, 7), (11, 33), (28, 38)]


def _points(geometry: CArm) -> np.ndarray:
    """World points that project exactly onto MARKS (on the rays, 60 % of the way to the detector)."""
    source = geometry.source_mm
    targets = np.array([geometry.pixel_to_world(c, r) for c, r in MARKS])
    return source + 0.6 * (targets - source)


def _stored(rows: int, cols: int, offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    image = np.full((rows, cols), BACKGROUND, dtype=np.uint16)
    for k, (c, r) in enumerate(MARKS):
        image[r - offset[0], c - offset[1]] = 3000 + 200 * k
    return image


def _as_stored(physical: np.ndarray, rotation: int, flip: bool) -> np.ndarray:
    """DICOM: the field is rotated clockwise relative to the detector, then flipped horizontally."""
    image = np.rot90(physical, k=-(rotation // 90))
    return image[:, ::-1] if flip else image


def _check_marks(image, points: np.ndarray) -> None:
    for k, point in enumerate(points):
        col, row = image.geometry.project(point)
        r, c = int(round(row)), int(round(col))
        assert abs(row - r) < 1e-6 and abs(col - c) < 1e-6  # exactly on a pixel center
        expected = (4095 - 1000 - (3000 + 200 * k)) / dicom.LOG_UNITS_PER_ATTENUATION
        assert image.image[r, c] == pytest.approx(expected, abs=1e-6), (k, r, c)


@pytest.mark.parametrize("flip", [False, True], ids=["noflip", "flip"])
@pytest.mark.parametrize("rotation", [0, 90, 180, 270])
def test_rotation_and_flip_map_world_points_onto_their_pixels(tmp_path: Path, rotation: int, flip: bool) -> None:
    # 40 x 30 pixels of 0.5 x 0.4 mm (rows x columns): a transposed axis or spacing shows.
    physical = CArm(primary_deg=20.0, secondary_deg=-10.0, rows=40, cols=30, pixel_mm=(0.5, 0.4))
    stored = _as_stored(_stored(40, 30), rotation, flip)
    spacing = (0.4, 0.5) if rotation in (90, 270) else (0.5, 0.4)  # of the stored rows, columns
    path = xa_file(
        tmp_path / "fov.dcm", stored, primary=20.0, secondary=-10.0, sid=1200.0, sod=810.0, imager_spacing=spacing
    )
    ds = pydicom.dcmread(path)
    ds.FieldOfViewRotation = str(rotation)
    ds.FieldOfViewHorizontalFlip = "YES" if flip else "NO"
    ds.save_as(path)
    image = dicom.read_xray(path)
    assert (image.geometry.rows, image.geometry.cols, image.geometry.pixel_mm) == (40, 30, (0.5, 0.4))
    _check_marks(image, _points(physical))


@pytest.mark.parametrize(("rotation", "flip"), [(0, False), (90, True)])
def test_field_of_view_origin_places_a_cropped_field(tmp_path: Path, rotation: int, flip: bool) -> None:
    # The physical detector: 50 x 40 elements of 0.4 mm, its active area all of it; the central
    # ray meets its center. The image is the field of view: 40 x 28 elements from (row 2, col 1).
    detector = CArm(primary_deg=-15.0, secondary_deg=5.0, rows=50, cols=40, pixel_mm=(0.4, 0.4))
    origin = (2, 1)
    physical = _stored(40, 28, offset=origin)
    path = xa_file(
        tmp_path / "crop.dcm",
        _as_stored(physical, rotation, flip),
        primary=-15.0,
        secondary=5.0,
        sid=1200.0,
        sod=810.0,
        imager_spacing=(0.4, 0.4),
    )
    ds = pydicom.dcmread(path)
    ds.FieldOfViewOrigin = [str(v) for v in origin]
    ds.FieldOfViewRotation = str(rotation)
    ds.FieldOfViewHorizontalFlip = "YES" if flip else "NO"
    ds.FieldOfViewShape = "RECTANGLE"
    ds.FieldOfViewDimensionsInFloat = [40 * 0.4, 28 * 0.4]
    ds.DetectorElementSpacing = ["0.4", "0.4"]
    ds.DetectorActiveDimensions = [str(50 * 0.4), str(40 * 0.4)]
    ds.save_as(path)
    image = dicom.read_xray(path)
    assert (image.geometry.rows, image.geometry.cols) == (40, 28)
    assert "from the central ray" in image.meta["field_of_view_origin"]
    points = _points(detector)
    # Marks (col, row) of the detector sit at (col - 1, row - 2) of the field.
    for (c, r), point in zip(MARKS, points, strict=True):
        np.testing.assert_allclose(image.geometry.project(point), [c - origin[1], r - origin[0]], atol=1e-6)
    _check_marks_cropped(image, points, origin)


def _check_marks_cropped(image, points: np.ndarray, origin: tuple[int, int]) -> None:
    for k, point in enumerate(points):
        col, row = image.geometry.project(point)
        expected = (4095 - 1000 - (3000 + 200 * k)) / dicom.LOG_UNITS_PER_ATTENUATION
        assert image.image[int(round(row)), int(round(col))] == pytest.approx(expected, abs=1e-6)


def test_field_of_view_origin_without_detector_tags_is_ignored_with_a_warning(tmp_path: Path) -> None:
    path = xa_file(tmp_path / "o.dcm", _stored(40, 30))
    ds = pydicom.dcmread(path)
    ds.FieldOfViewOrigin = ["4", "4"]
    ds.save_as(path)
    with pytest.warns(UserWarning, match=r"FieldOfViewOrigin \(0018,7030\) ignored.*DetectorElementSpacing"):
        image = dicom.read_xray(path)
    assert image.geometry.detector_shift_mm == (0.0, 0.0, 0.0)
    ds.FieldOfViewHorizontalFlip = "SIDEWAYS"
    ds.save_as(path)
    with pytest.raises(DicomError, match=r"o.dcm.*FieldOfViewHorizontalFlip \(0018,7034\)"):
        dicom.read_xray(path)


def test_shutter_follows_the_rotation(tmp_path: Path) -> None:
    # A rectangular shutter given in stored pixel positions (1-based) must mask the same pixels
    # once the rotation is undone.
    stored = np.full((20, 30), 2500, dtype=np.uint16)
    path = xa_file(tmp_path / "s.dcm", stored)
    ds = pydicom.dcmread(path)
    ds.ShutterShape = "RECTANGULAR"
    ds.ShutterLeftVerticalEdge, ds.ShutterRightVerticalEdge = 1, 10  # stored columns 0..9
    ds.ShutterUpperHorizontalEdge, ds.ShutterLowerHorizontalEdge = 1, 20
    ds.FieldOfViewRotation = "90"
    ds.save_as(path)
    image = dicom.read_xray(path)
    expected = np.zeros((20, 30), dtype=bool)
    expected[:, :10] = True
    np.testing.assert_array_equal(image.mask, np.rot90(expected, k=1))
