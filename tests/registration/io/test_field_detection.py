"""The usable field: shutter and collimator tags, blades and burned-in graphics found in the pixels,
overlay planes, the user's mask, and the two real X-ray files.

The synthetic images are drawn here (smooth "anatomy" of Gaussian blobs and a skull-like ring,
blades as an attenuation step with more noise behind, text with OpenCV at full white), never
with the project's renderers, so the detector is judged against pixels it did not make.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import cv2
import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence
from scipy import ndimage

from registration.core.images import XRayImage
from registration.io import dicom
from registration.io.dicom import DicomError
from registration.io.field import find_field
from registration.io.image_files import ImageFileError
from tests.registration.io.test_dicom import xa_file

#: ``../shared/data/real-xa`` beside the project, or ``$ROADMAP3D_SHARED_DATA/real-xa``.
REAL_XA = (
    Path(os.environ.get("ROADMAP3D_SHARED_DATA") or Path(__file__).resolve().parents[3].parent / "shared" / "data")
    / "real-xa"
)
SIZE = 256
#: Stored LOG values: 3200 at zero attenuation, 500 stored steps per unit (sign +1: bright = X-rays).
ZERO, UNITS, WHITE = 3200.0, 500.0, 4095


def _anatomy(seed: int) -> np.ndarray:
    """Attenuation 0.3..2.6: a skull-like ring, soft blobs and fine vessels (no extreme value)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    r = np.hypot((xx - 128) / 100, (yy - 124) / 110)
    att = 0.8 + 0.9 * np.exp(-(((r - 1.0) / 0.05) ** 2)) + 0.4 * (r < 1.0)
    for _ in range(25):
        cx, cy, s, a = rng.uniform(20, 236), rng.uniform(20, 236), rng.uniform(4, 20), rng.uniform(-0.3, 0.5)
        att += a * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    for _ in range(6):  # vessels: thin curved lines
        t = np.linspace(0, 1, 400)
        x0, y0, dx, dy, bend = *rng.uniform(30, 220, 2), *rng.uniform(-120, 120, 2), rng.uniform(-40, 40)
        px, py = x0 + dx * t + bend * np.sin(3 * t), y0 + dy * t + bend * np.cos(2 * t)
        ok = (px >= 0) & (px < SIZE) & (py >= 0) & (py < SIZE)
        line = np.zeros((SIZE, SIZE))
        line[py[ok].astype(int), px[ok].astype(int)] = 1.0
        att += 0.3 * ndimage.gaussian_filter(line, 1.2) / 0.13
    return np.clip(att, 0.3, 2.6)


def _stored(att: np.ndarray, noise: np.ndarray | float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed + 100)
    values = ZERO - UNITS * att + rng.normal(0.0, 1.0, att.shape) * noise
    return np.clip(np.rint(values), 0, WHITE - 200).astype(np.uint16)


def _within(mask: np.ndarray, truth: np.ndarray, px: float) -> float:
    """Largest distance (px) of a pixel where ``mask`` and ``truth`` disagree from ``truth``'s boundary."""
    wrong = mask != truth
    if not wrong.any():
        return 0.0
    inside = ndimage.distance_transform_edt(truth)
    outside = ndimage.distance_transform_edt(~truth)
    return float(np.max(np.where(truth, inside, outside)[wrong]))


def _worst_miss_px(mask: np.ndarray, distance: np.ndarray, open_field: np.ndarray) -> float:
    """How far (px) from the open field's edge the mask disagrees with it at most (0: nowhere)."""
    return float(np.abs(distance[mask != open_field]).max(initial=0.0))


def _blades(angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Rectangular blades turned by ``angle_deg`` about the center: the signed distance (px) into
    the open field (positive inside) and the open field."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    a = math.radians(angle_deg)
    u = (xx - 127.5) * math.cos(a) + (yy - 127.5) * math.sin(a)
    v = -(xx - 127.5) * math.sin(a) + (yy - 127.5) * math.cos(a)
    distance = np.minimum.reduce([u + 70.0, 85.0 - u, v + 80.0, 60.0 - v])
    return distance, distance > 0


@pytest.mark.parametrize("angle", [0.0, 7.0, -12.0])
def test_rectangular_blades_with_noise_behind_them_are_masked_within_2_px(tmp_path: Path, angle: float) -> None:
    att = _anatomy(1)
    distance, open_field = _blades(angle)
    # 8 % transmission: ln(12.5) more attenuation behind the blades, the edge blurred by 0.7 px;
    # fewer photons behind them: 3.5 x the noise (never a constant value).
    behind = 1.0 - 1.0 / (1.0 + np.exp(distance / 0.7))
    total = att + math.log(12.5) * (1.0 - behind)
    stored = _stored(total, np.where(open_field, 12.0, 42.0), 1)
    image = dicom.read_xray(xa_file(tmp_path / "blades.dcm", stored, bits_stored=12))
    # The mask may differ from the open field only within 2 px of its edge (the penumbra).
    assert _worst_miss_px(image.mask, distance, open_field) <= 2.0
    assert image.mask.sum() >= open_field.sum() - 2 * 4 * 150  # at most ~2 px lost along the edges
    assert image.meta["field"]["found_by"].startswith("collimator blade")
    assert "whole image" not in image.meta["mask_from"]


def _display_band(angle_deg: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-bit display-processed pixels (bone dark) whose blades' shadow the window's toe flattened:
    a dark, noisy band with no anatomy, dense anatomy along the field's edge (a step of about a
    tenth of the field's range), an unsharp mask's halo along the edge, and the intensifier's
    circle darker still. Returns the stored pixels, the signed distance into the open field and
    the open field."""
    att = _anatomy(seed)
    distance, open_field = _blades(angle_deg)
    rng = np.random.default_rng(seed)
    field = 60.0 + 180.0 * (1.0 - (att - att.min()) / (att.max() - att.min()))
    field = 34.0 + (field - 34.0) * (0.1 + 0.9 * np.clip(np.abs(distance) / 60.0, 0.0, 1.0))
    band = 22.0 + rng.normal(0.0, 3.0, att.shape)
    inside = 1.0 / (1.0 + np.exp(-distance / 0.7))
    signal = inside * field + (1.0 - inside) * band
    signal = signal + 0.8 * (signal - ndimage.gaussian_filter(signal, 3.0))
    stored, circle = _in_circle(signal, rng)
    return stored, distance, open_field & circle


def _in_circle(signal: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """8-bit stored pixels: ``signal`` inside the intensifier's circle, a dark noisy outside."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    circle = np.hypot(xx - 127.5, yy - 127.5) < 126
    signal = np.where(circle, signal, rng.normal(2.0, 1.0, signal.shape))
    return np.clip(np.rint(signal), 0, 255).astype(np.uint16), circle


def _read_disp(path: Path, stored: np.ndarray) -> XRayImage:
    """``stored`` written as an 8-bit DISP XA file and read back."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # DISP read as LOG
        return dicom.read_xray(xa_file(path, stored, bits_stored=8, relationship="DISP"))


@pytest.mark.parametrize("angle", [0.0, 7.0, -12.0])
def test_blades_whose_shadow_the_display_flattened_are_masked_within_3_px(tmp_path: Path, angle: float) -> None:
    stored, distance, open_field = _display_band(angle, 5)
    image = _read_disp(tmp_path / "band.dcm", stored)
    # Within 3 px of the true edge: the penumbra (0.7 px) and the unsharp mask's halo (about 2 px).
    assert _worst_miss_px(image.mask, distance, open_field) <= 3.0
    assert (image.mask & ~open_field).sum() < 100  # nothing of the bands is taken for anatomy
    assert "collimator blade" in image.meta["mask_from"]


def _air_behind_blades(angle_deg: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-bit display-processed pixels of a head that leaves air inside the intensifier's circle:
    behind the 8 % blades the head falls into the window's toe (black, joined to the circle's
    outside) while the air behind them keeps as much signal as dense bone in the field, so a
    blade's edge runs along the outside for most of its length and past thin tissue or air for
    the rest. Returns the stored pixels, the signed distance into the open field and the open
    field."""
    att = _anatomy(seed)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    att = np.where(np.hypot((xx - 140) / 115, (yy - 100) / 150) < 1.0, att, 0.05)
    distance, open_field = _blades(angle_deg)
    rng = np.random.default_rng(seed)
    total = att + math.log(12.5) / (1.0 + np.exp(distance / 0.7))
    signal = 255.0 * np.clip((3.2 - total) / 3.0, 0.0, 1.0) + rng.normal(0.0, 1.5, att.shape)
    stored, circle = _in_circle(signal, rng)
    return stored, distance, open_field & circle


@pytest.mark.parametrize("angle", [0.0, 7.0, -12.0])
def test_air_behind_blades_along_the_outside_is_masked_within_3_px(tmp_path: Path, angle: float) -> None:
    stored, distance, open_field = _air_behind_blades(angle, 3)
    image = _read_disp(tmp_path / "air.dcm", stored)
    # Within 3 px of the true edge: the penumbra (0.7 px) and the outside's margin (2 px). Without
    # the blades' lines along the outside, about 3,900 px of air behind them stay in the mask.
    assert _worst_miss_px(image.mask, distance, open_field) <= 3.0
    assert (image.mask & ~open_field).sum() < 100
    assert image.mask.sum() >= open_field.sum() - 3 * 4 * 150  # at most ~3 px lost along the edges


def test_clean_images_lose_nothing(tmp_path: Path) -> None:
    # The same anatomy without blades or text: no pixel masked (the detector sees no field edge).
    stored = _stored(_anatomy(2), 12.0, 2)
    with pytest.warns(UserWarning, match="whole image"):
        image = dicom.read_xray(xa_file(tmp_path / "clean.dcm", stored))
    assert image.mask.all()
    # A written phantom image keeps exactly its circular field.
    from registration.core.geometry import CArm
    from registration.core.images import XRayImage

    g = CArm.for_format(27.0, pixels=SIZE)
    circle = g.field_mask()
    xray = XRayImage(np.where(circle, _anatomy(3), 0.0).astype(np.float32), circle, g, "fluoro")
    back = dicom.read_xray(dicom.write_xray(xray, tmp_path / "phantom.dcm"))
    np.testing.assert_array_equal(back.mask, circle)
    assert back.meta["mask_from"] == "shutter tags (circular), constant border"


def _burn(stored: np.ndarray, value: int) -> tuple[np.ndarray, np.ndarray]:
    canvas = np.zeros(stored.shape, dtype=np.uint8)
    cv2.putText(canvas, "LAO 12 CRAN 5", (60, 140), cv2.FONT_HERSHEY_SIMPLEX, 0.45, 255, 1)
    cv2.putText(canvas, "15 fps 73 kV", (20, 40), cv2.FONT_HERSHEY_PLAIN, 1.0, 255, 1)
    cv2.line(canvas, (230, 40), (230, 220), 255, 1)  # a ruler with ticks every 20 px
    for y in range(40, 221, 20):
        cv2.line(canvas, (224, y), (230, y), 255, 1)
    burned = canvas > 0
    return np.where(burned, value, stored).astype(np.uint16), burned


def test_burned_in_text_and_ruler_are_masked_within_2_px(tmp_path: Path) -> None:
    stored, burned = _burn(_stored(_anatomy(4), 12.0, 4), WHITE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        image = dicom.read_xray(xa_file(tmp_path / "text.dcm", stored))
    assert not (image.mask & burned).any()  # every burned pixel masked
    grown = ndimage.binary_dilation(burned, iterations=2)
    assert not (~image.mask & ~grown).any()  # nothing more than 2 px from a stroke
    assert "burned-in graphics" in image.meta["mask_from"]


def test_dark_burned_in_text_is_masked_and_a_clipped_vessel_is_not(tmp_path: Path) -> None:
    """Text at full black (some systems burn it in dark on a bright field) beside a thin vessel
    clipped to the same black by the display window: the text is masked within 2 px, the vessel
    (long, not a line of characters) stays in the field."""
    stored = _stored(_anatomy(6), 12.0, 6)
    canvas = np.zeros(stored.shape, dtype=np.uint8)
    cv2.putText(canvas, "PAT 0427 12/03", (30, 60), cv2.FONT_HERSHEY_SIMPLEX, 0.45, 255, 1)
    cv2.putText(canvas, "RAO 20", (150, 230), cv2.FONT_HERSHEY_PLAIN, 1.0, 255, 1)
    text = canvas > 0
    vessel = np.zeros(stored.shape, dtype=np.uint8)
    t = np.linspace(0.0, 1.0, 600)
    cv2.polylines(vessel, [np.stack([60 + 140 * t, 100 + 90 * t + 12 * np.sin(6 * t)], axis=1).astype(np.int32)],
                  False, 255, 2)  # fmt: skip
    clipped = (vessel > 0) & ~ndimage.binary_dilation(text, iterations=4)
    stored = np.where(text | clipped, 0, stored).astype(np.uint16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        image = dicom.read_xray(xa_file(tmp_path / "dark.dcm", stored))
    assert not (image.mask & text).any()  # every character's pixel masked
    assert not (~image.mask & ~ndimage.binary_dilation(text, iterations=2)).any()  # nothing 2 px beyond them
    assert image.mask[clipped].all()  # the vessel is anatomy
    assert "burned-in graphics" in image.meta["mask_from"]


def _overlay(ds: Dataset, plane: np.ndarray, origin: tuple[int, int], frames: int = 1, first: int = 1) -> None:
    rows, cols = plane.shape[-2:]
    ds.add_new(0x60000010, "US", rows)
    ds.add_new(0x60000011, "US", cols)
    ds.add_new(0x60000040, "CS", "G")
    ds.add_new(0x60000050, "SS", list(origin))
    ds.add_new(0x60000100, "US", 1)
    ds.add_new(0x60000102, "US", 0)
    if frames > 1:
        ds.add_new(0x60000015, "IS", str(frames))
        ds.add_new(0x60000051, "US", first)
    ds.add_new(0x60003000, "OW", pydicom.pixels.pack_bits(plane.astype(np.uint8).ravel(), pad=True))


def test_overlay_planes_are_read_and_masked(tmp_path: Path) -> None:
    stored = _stored(_anatomy(5), 12.0, 5)
    plane = np.zeros((40, 60), dtype=bool)
    plane[10:12, 5:55] = True  # a line and a box outline, placed at row 101, column 31 (1-based)
    plane[20:35, 20] = plane[20:35, 40] = True
    path = xa_file(tmp_path / "ov.dcm", stored)
    ds = pydicom.dcmread(path)
    _overlay(ds, plane, (101, 31))
    ds.save_as(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        image = dicom.read_xray(path)
    drawn = np.zeros((SIZE, SIZE), dtype=bool)
    drawn[100:140, 30:90] = plane
    assert not (image.mask & drawn).any()
    assert not (~image.mask & ~ndimage.binary_dilation(drawn, iterations=2)).any()
    assert image.meta["field"]["overlays"][0]["pixels"] == int(drawn.sum())
    # The retired form: the overlay in bit 12 of 16-bit words holding 12-bit pixels.
    path = xa_file(tmp_path / "emb.dcm", stored | (drawn.astype(np.uint16) << 12))
    ds = pydicom.dcmread(path)
    for element, vr, value in ((0x10, "US", SIZE), (0x11, "US", SIZE), (0x40, "CS", "G"), (0x50, "SS", [1, 1])):
        ds.add_new(0x60000000 | element, vr, value)
    ds.add_new(0x60000100, "US", 16)
    ds.add_new(0x60000102, "US", 12)
    ds.save_as(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        embedded = dicom.read_xray(path)
    np.testing.assert_array_equal(embedded.mask, image.mask)
    np.testing.assert_allclose(embedded.image[embedded.mask], image.image[image.mask])  # the bit is not a value


def test_a_multi_frame_overlay_masks_its_own_frames(tmp_path: Path) -> None:
    frames = np.stack([_stored(_anatomy(6), 12.0, k) for k in range(3)])
    plane = np.zeros((2, 20, 20), dtype=bool)
    plane[0, 5, :] = True  # overlay frame 1 -> image frame 2 (ImageFrameOrigin 2)
    plane[1, :, 5] = True  # overlay frame 2 -> image frame 3
    path = xa_file(tmp_path / "mf.dcm", frames)
    ds = pydicom.dcmread(path)
    _overlay(ds, plane, (11, 11), frames=2, first=2)
    ds.save_as(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        masks = [dicom.read_xray(path, frame=k).mask for k in range(3)]
    assert masks[0][8:32, 8:32].all()  # overlay frames 1 and 2 draw on image frames 2 and 3 only
    assert not masks[1][15, 10:30].any() and masks[1][20:30, 15].all()
    assert masks[2][20:30, 20:30].all() and not masks[2][10:30, 15].any()


def test_shutter_tags_rectangular_circular_polygonal_and_per_frame(tmp_path: Path) -> None:
    stored = _stored(_anatomy(7), 12.0, 7)
    rr, cc = np.mgrid[0:SIZE, 0:SIZE]
    path = xa_file(tmp_path / "s.dcm", stored)
    ds = pydicom.dcmread(path)
    ds.ShutterShape = "RECTANGULAR\\CIRCULAR"
    ds.ShutterLeftVerticalEdge, ds.ShutterRightVerticalEdge = 21, 200  # columns 20..199
    ds.ShutterUpperHorizontalEdge, ds.ShutterLowerHorizontalEdge = 31, 220  # rows 30..219
    ds.CenterOfCircularShutter, ds.RadiusOfCircularShutter = [129, 129], 110
    ds.ShutterPresentationValue = 0
    ds.save_as(path)
    image = dicom.read_xray(path)
    expected = (cc >= 20) & (cc <= 199) & (rr >= 30) & (rr <= 219) & ((rr - 128) ** 2 + (cc - 128) ** 2 <= 110**2)
    np.testing.assert_array_equal(image.mask, expected)
    assert image.meta["field"]["shutter"] == "rectangular and circular"
    assert image.meta["field"]["shutter_presentation_value"] == 0
    # A polygon (row, column vertices): a triangle.
    del ds.ShutterLeftVerticalEdge, ds.ShutterRightVerticalEdge, ds.CenterOfCircularShutter
    ds.ShutterShape = "POLYGONAL"
    ds.VerticesOfThePolygonalShutter = [11, 11, 11, 241, 241, 11]
    ds.save_as(path)
    image = dicom.read_xray(path)
    assert image.mask[20, 20] and image.mask[15, 200] and not image.mask[200, 200] and not image.mask[5, 5]
    assert abs(int(image.mask.sum()) - 230 * 230 // 2) < 460  # the hypotenuse's 325 pixels, half in or out
    # Per frame (enhanced functional groups): each frame its own rectangle.
    frames = np.stack([stored, stored])
    path = xa_file(tmp_path / "pf.dcm", frames)
    ds = pydicom.dcmread(path)
    items = []
    for left in (11, 101):
        shutter = Dataset()
        shutter.ShutterShape = "RECTANGULAR"
        shutter.ShutterLeftVerticalEdge, shutter.ShutterRightVerticalEdge = left, 240
        shutter.ShutterUpperHorizontalEdge, shutter.ShutterLowerHorizontalEdge = 11, 240
        group = Dataset()
        group.FrameDisplayShutterSequence = Sequence([shutter])
        items.append(group)
    ds.PerFrameFunctionalGroupsSequence = Sequence(items)
    ds.save_as(path)
    first, second = dicom.read_xray(path, frame=0), dicom.read_xray(path, frame=1)
    assert first.mask[100, 50] and not second.mask[100, 50] and second.mask[100, 150]
    assert first.meta["field"]["shutter"] == "rectangular (per frame)"
    ds.PerFrameFunctionalGroupsSequence[1].FrameDisplayShutterSequence[0].ShutterShape = "HEXAGONAL"
    ds.save_as(path)
    with pytest.raises(DicomError, match=r"pf.dcm.*ShutterShape \(0018,1600\) 'HEXAGONAL'"):
        dicom.read_xray(path, frame=1)


def test_the_users_mask_is_intersected_and_checked(tmp_path: Path) -> None:
    from PIL import Image

    stored = _stored(_anatomy(8), 12.0, 8)
    path = xa_file(tmp_path / "u.dcm", stored, shutter=(129, 129, 120))
    user = np.zeros((SIZE, SIZE), dtype=np.uint8)
    user[:, :128] = 255
    Image.fromarray(user).save(tmp_path / "mask.png")
    Image.fromarray(np.stack([user] * 3, axis=-1)).save(tmp_path / "mask_rgb.png")
    plain = dicom.read_xray(path)
    masked = dicom.read_xray(path, image_mask=tmp_path / "mask.png")
    np.testing.assert_array_equal(masked.mask, plain.mask & (user > 0))
    assert "user mask mask.png" in masked.meta["mask_from"]
    np.testing.assert_array_equal(dicom.read_xray(path, image_mask=tmp_path / "mask_rgb.png").mask, masked.mask)
    Image.fromarray(user[:100]).save(tmp_path / "small.png")
    with pytest.raises(ImageFileError, match=r"small.png.*100x256 pixels; the image is 256x256"):
        dicom.read_xray(path, image_mask=tmp_path / "small.png")
    Image.fromarray(np.zeros_like(user)).save(tmp_path / "empty.png")
    with pytest.raises(ImageFileError, match="empty.png.*no pixel as usable"):
        dicom.read_xray(path, image_mask=tmp_path / "empty.png")


def _real(name: str) -> Path:
    path = REAL_XA / name
    if not path.is_file():
        pytest.skip(f"{path} is absent (the real X-ray files live in ../shared/data/real-xa)")
    return path


def _real_field(path: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """The field of frame 0 (the files carry no C-arm geometry, so the reader's field step alone)."""
    from registration.io.dicom.xray import _field_mask

    ds = pydicom.dcmread(path)
    stored = ds.pixel_array
    stored = stored[0] if stored.ndim == 3 else stored
    mask, info = _field_mask(path, ds, stored, 0)
    return mask, stored, info


def test_real_coronary_run_octagon_and_blade() -> None:
    path = _real("coronary-xa-96-frames.dcm")
    mask, stored, info = _real_field(path)
    assert info["found_by"] == "dark outside, collimator blade x2"
    # The dark outside (the octagon's corners and the bottom below row 473) is excluded.
    assert not mask[:40, :40].any() and not mask[-40:, -40:].any() and not mask[476:, :].any()
    dark = ndimage.median_filter(stored, 5) <= 12
    assert not (mask & dark & ndimage.binary_erosion(dark, iterations=3)).any()
    # The structureless band behind the left blade (columns 22..40) and the band under the bottom
    # blade (rows 463..472) are excluded, the lung beside them kept.
    assert not mask[466:472, 100:400].any()
    assert not mask[100:400, 22:40].any() and mask[100:400, 50:60].all()
    # Every pixel of the anatomy in the field's middle is kept; ~3/4 of the image is usable.
    assert mask[60:400, 60:450].all()
    assert 0.70 < mask.mean() < 0.78, mask.mean()


def test_real_shoulder_circle_cut_by_the_image_edge() -> None:
    path = _real("shoulder-rf.dcm")
    mask, stored, info = _real_field(path)
    assert info["found_by"] == "constant border"
    outside = stored == 0
    assert not (mask & outside).any()
    # Nothing farther than 2 px from the outside is lost: the saturated air at the top, the wire kept.
    far = ndimage.distance_transform_edt(~outside) > 2
    assert mask[far].all()
    assert 0.82 < mask.mean() < 0.85, mask.mean()


def test_pixels_search_is_quick_to_skip_small_images() -> None:
    # Below 64 px only a constant border is looked for: a small noisy image keeps every pixel.
    rng = np.random.default_rng(0)
    found = find_field(rng.integers(0, 4000, (40, 40)))
    assert found.mask.all() and found.parts == []


def test_info_says_how_the_field_was_found_and_what_was_assumed(tmp_path: Path) -> None:
    distance, open_field = _blades(5.0)
    behind = 1.0 - 1.0 / (1.0 + np.exp(distance / 0.7))
    stored = _stored(_anatomy(9) + math.log(12.5) * (1.0 - behind), np.where(open_field, 12.0, 42.0), 9)
    stored, _ = _burn(stored, WHITE)
    report = dicom.inspect(xa_file(tmp_path / "i.dcm", stored, relationship=None, sign=None))
    assert report["accepted"]
    assert report["field"].startswith("collimator blade x4, burned-in graphics; ")
    assert "% of the image" in report["field"] and report["field_pixels"] < open_field.sum()
    assert "collimator blade:" in report["field_masked"] and "burned-in graphics:" in report["field_masked"]
    assert report["intensity_assumed"].startswith("missing read as LOG, sign +1 (lower stored values")
    assert "assumed (no PixelIntensityRelationshipSign)" in report["intensity_assumed"]
    assert "12 bits stored" in report["intensity_assumed"]
    # Without the C-arm geometry the field and the intensities are still reported.
    report = dicom.inspect(xa_file(tmp_path / "nogeo.dcm", stored, sid=None))
    assert not report["accepted"] and "DistanceSourceToDetector" in report["problem"]
    assert report["field"].startswith("collimator blade x4") and "LOG (from" in report["intensity_assumed"]


def test_a_missing_sign_is_read_from_the_collimated_outside(tmp_path: Path) -> None:
    # Bone bright (higher stored values = more attenuation), no sign tag: the outside of the
    # circular field, where no X-rays arrive, is the brightest value and gives the polarity.
    # (A digitally blanked, constant outside is not used: systems blank it black whatever the
    # polarity.)
    att = _anatomy(10)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    circle = np.hypot(yy - 127.5, xx - 127.5) < 120
    rng = np.random.default_rng(10)
    shadow = 4000.0 + rng.normal(0, 15.0, att.shape)
    stored = np.clip(np.rint(np.where(circle, 400.0 + UNITS * att, shadow)), 0, 4095).astype(np.uint16)
    path = xa_file(tmp_path / "bright.dcm", stored, relationship="LOG", sign=None)
    with pytest.warns(UserWarning, match=r"collimated outside says -1"):
        image = dicom.read_xray(path)
    assert image.meta["pixel_intensity_relationship_sign"] == -1
    inside = image.mask & ndimage.binary_erosion(circle, iterations=3)
    assert np.corrcoef(image.image[inside], att[inside])[0, 1] > 0.99  # attenuation grows with attenuation
    assert not (image.mask & ~circle).any()
    assert "collimated outside" in dicom.inspect(path)["intensity_assumed"]


def test_the_command_line_takes_the_users_mask(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from PIL import Image

    from app import cli

    path = xa_file(tmp_path / "c.dcm", _stored(_anatomy(11), 12.0, 11), shutter=(129, 129, 120))
    user = np.zeros((SIZE, SIZE), dtype=np.uint8)
    user[50:200, 50:200] = 1
    Image.fromarray(user).save(tmp_path / "m.png")
    Image.fromarray(user[:10]).save(tmp_path / "bad.png")

    def run(argv: list[str]) -> tuple[int, str, str]:
        with pytest.raises(SystemExit) as info:
            cli.main(argv)
        out, err = capsys.readouterr()
        assert "Traceback" not in err
        return int(info.value.code or 0), out, err

    code, out, _ = run(["info", str(path), "--image-mask", str(tmp_path / "m.png")])
    assert code == 0 and "user mask m.png" in out and f"{150 * 150} pixels usable" in out
    code, _, err = run(["info", str(path), "--image-mask", str(tmp_path / "bad.png")])
    assert code == 2 and "bad.png" in err and "10x256 pixels; the image is 256x256" in err
    # register refuses a mask of the wrong size before the registration starts (exit 2)
    volume = tmp_path / "v.npz"
    from registration.core.volume import Volume

    dicom.write_npz(Volume(np.zeros((8, 8, 8), np.float32), np.diag([2.0, 2.0, 2.0, 1.0]), label="v"), volume)
    code, _, err = run(
        ["register", "--volume", str(volume), "--image", str(path), "--image-mask", str(tmp_path / "bad.png")]
    )
    assert code == 2 and "bad.png" in err
    code, _, err = run(
        ["register", "--volume", str(volume), "--image", str(path), "--image-mask", "a.png", "--image-mask", "b.png"]
    )
    assert code == 2 and "--image-mask: one mask per --image (1), got 2" in err


@pytest.mark.parametrize("seed", range(6))
def test_stroke_widths_and_rings_measured_near_the_components_are_the_whole_images(seed: int) -> None:
    # The burned-in graphics search measures each component left after its cheap tests on a box
    # around them; the widths and ring means must be exactly what the whole image gives, whichever
    # components are left (clutter, strokes and blobs of every size, some on the image's edge).
    from registration.io.graphics import _ring_means, _widest

    rng = np.random.default_rng(seed)
    shape = (160, 200)
    candidates = np.zeros(shape, dtype=np.uint8)
    for _ in range(40):
        r, c = int(rng.integers(-5, shape[0] + 5)), int(rng.integers(-5, shape[1] + 5))
        if rng.random() < 0.5:
            cv2.line(candidates, (c, r), (c + int(rng.integers(-40, 40)), r + int(rng.integers(-40, 40))), 1,
                     int(rng.integers(1, 4)))  # fmt: skip
        else:
            cv2.circle(candidates, (c, r), int(rng.integers(1, 12)), 1, -1)
    candidates = candidates.astype(bool)
    values = rng.normal(0.0, 1.0, shape)
    field_mask = rng.random(shape) > 0.1
    labels, n = ndimage.label(candidates, structure=np.ones((3, 3), bool))
    boxes = ndimage.find_objects(labels)
    ids = sorted(int(i) for i in rng.choice(np.arange(1, n + 1), size=max(1, n // 3), replace=False))
    # the whole image's measures
    width = ndimage.distance_transform_edt(candidates)
    ring = ndimage.binary_dilation(candidates, iterations=3) & ~ndimage.binary_dilation(candidates) & field_mask
    ring_labels = ndimage.grey_dilation(labels, size=(7, 7)) * ring
    with np.errstate(invalid="ignore", divide="ignore"):
        whole = ndimage.mean(values, ring_labels, ids)  # summed in the image's order, as on the box
    widest = _widest(labels, ids, boxes)
    means = _ring_means(values, field_mask, candidates, labels, ids, boxes)
    for i, mean in zip(ids, whole, strict=True):
        assert widest[i] == width[labels == i].max()
        assert means[i] == mean or (np.isnan(means[i]) and np.isnan(mean))


def test_a_run_reads_its_polarity_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A run without the sign tag: the polarity is read from the first frame's collimated outside
    # and kept for the run (the collimation is kept the same way); burned-in graphics are still
    # looked for on every frame.
    from registration.io import field
    from registration.io.dicom.runs import read_xray_run

    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    circle = np.hypot(yy - 127.5, xx - 127.5) < 120
    rng = np.random.default_rng(12)
    frames = np.stack([
        np.clip(np.rint(np.where(circle, 400.0 + UNITS * _anatomy(20 + f), 4000.0 + rng.normal(0, 15.0, circle.shape))),
                0, 4095)
        for f in range(3)
    ]).astype(np.uint16)  # fmt: skip
    canvas = np.zeros((SIZE, SIZE), dtype=np.uint8)
    cv2.putText(canvas, "F 2/3 15 fps", (60, 90), cv2.FONT_HERSHEY_SIMPLEX, 0.45, 255, 1)
    text = canvas > 0
    frames[1][text] = 0  # text burned in black on the second frame only (the bright side of this polarity)
    path = xa_file(tmp_path / "run.dcm", frames, relationship="LOG", sign=None)
    calls = []
    read_sign = field.infer_signal_up
    monkeypatch.setattr(field, "infer_signal_up", lambda values: calls.append(1) or read_sign(values))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = read_xray_run(path, frame_time_ms=66.7)
        images = [run[f] for f in range(3)]
        alone = dicom.read_xray(path, frame=0)
    assert len(calls) == 2  # once for the run's frames, once for the first frame read alone
    assert [im.meta["pixel_intensity_relationship_sign"] for im in images] == [-1, -1, -1]
    np.testing.assert_array_equal(images[0].mask, alone.mask)
    np.testing.assert_array_equal(images[0].image, alone.image)
    assert not (images[1].mask & text).any() and images[2].mask[text].all()


@pytest.mark.parametrize("seed", range(4))
def test_line_peaks_are_scikit_images(seed: int) -> None:
    # The blades' Hough peaks, looked for only above the threshold, are exactly scikit-image's
    # (the same counts, angles and distances in the same order), ties and the angle's wrap included.
    from skimage.draw import line
    from skimage.transform import hough_line, hough_line_peaks

    from registration.io.field import line_peaks

    rng = np.random.default_rng(seed)
    for trial in range(25):
        edges = np.zeros((int(rng.integers(40, 160)), int(rng.integers(40, 160))), dtype=bool)
        for _ in range(int(rng.integers(0, 8))):
            rr, cc = line(*(int(rng.integers(0, n)) for n in (*edges.shape, *edges.shape)))
            edges[rr, cc] = True
        edges |= rng.random(edges.shape) < rng.uniform(0.0, 0.05)
        angles = np.deg2rad(np.arange(-90.0, 90.0, 0.5)) if trial % 2 else np.linspace(-np.pi / 2, np.pi / 2, 45, False)
        hspace, thetas, dists = hough_line(edges, theta=angles)
        for fraction, min_distance, min_angle, num_peaks in ((0.5, 7, 6, 12), (0.2, 3, 2, 50)):
            threshold = int(fraction * hspace.max())
            ours = line_peaks(hspace, thetas, dists, min_distance=min_distance, min_angle=min_angle,
                              threshold=threshold, num_peaks=num_peaks)  # fmt: skip
            theirs = hough_line_peaks(hspace, thetas, dists, min_distance=min_distance, min_angle=min_angle,
                                      threshold=threshold, num_peaks=num_peaks)  # fmt: skip
            for a, b in zip(ours, theirs, strict=True):
                np.testing.assert_array_equal(a, b)
