"""The user's own data: `roadmap3d app --volume --image` and the browser upload of a zip."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from app.web.data import FileData
from app.web.gui import RoadmapApp
from app.web.upload import read_upload
from registration.core.geometry import TABLE_I, offsets_to_matrix
from registration.io.dicom import UploadError, write_npz, write_xray

from .conftest import TEST_CONFIG, wait_until


@pytest.fixture(scope="module")
def exported(app: RoadmapApp, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The phantom's volume (.npz) and a T4-moved fluoro image (XA), as a user would bring them."""
    folder = tmp_path_factory.mktemp("user-data")
    phantom = app._phantom_data  # noqa: SLF001
    write_npz(phantom.volume(27.0), folder / "volume.npz")
    from app.web.data import simulate_xray

    geometry = app.session.settings.geometry(TEST_CONFIG.pixels)
    xray = simulate_xray(phantom.phantom(True), geometry, motion=offsets_to_matrix(TABLE_I["T4"], geometry))
    write_xray(xray, folder / "image.dcm")
    return folder


def zipped(folder: Path, names: list[str]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name in names:
            zf.write(folder / name, arcname=f"case/{name}")
    return buf.getvalue()


def test_upload_registers_the_users_data(fresh: RoadmapApp, exported: Path) -> None:
    app = fresh
    data = read_upload("case.zip", zipped(exported, ["volume.npz", "image.dcm"]), max_bytes=10**9, config=TEST_CONFIG)
    assert isinstance(data, FileData) and data.fixed_xray is not None
    # the .npz has no IsocenterPosition: placed about the world origin, and the Data tab says so
    assert data.isocenter_text == "(0.00, 0.00, 0.00) mm, from the world origin (default)"
    try:
        app._use_data(data)  # noqa: SLF001 - what the upload callback does after reading
        assert all(c.disabled for c in app.carm_controls)  # the file sets the C-arm
        assert wait_until(lambda: app._shown_version == app.session.version, 20)  # noqa: SLF001
        assert "no ground truth" in app.readout.content
        app.register_button.value = True
        assert app.session.wait(120)
        result = app.session.run.result
        assert result is not None and result.residual is None
        # The image shows the phantom moved by T4: the estimate must have found it.
        geometry = app.session.geometry()
        truth = offsets_to_matrix(TABLE_I["T4"], geometry)
        err = app.session.estimate @ np.linalg.inv(truth)
        shift = err[:3, 3]
        inplane = np.linalg.norm(shift - (shift @ geometry.direction) * geometry.direction)
        assert inplane < 1.0
    finally:
        app.phantom_button.value = True  # back to the phantom for the other tests
        assert app.session.data is app._phantom_data  # noqa: SLF001
        assert not any(c.disabled for c in app.carm_controls)


def test_a_volume_without_contrast_shows_no_vessels_and_says_why(fresh: RoadmapApp) -> None:
    """The user's volume without contrast agent (the phantom with blood, not iodine, in its
    arteries): no vessel surface in the scene, and the panel says why; back on the phantom
    (contrast) its vessels and no note."""
    from app.web.data import simulate_xray
    from registration.sim.phantom import make_head_phantom, registration_volume

    app = fresh
    plain = make_head_phantom(seed=0, contrast=False)
    volume = registration_volume(plain, 27.0, voxels=TEST_CONFIG.voxels)
    xray = simulate_xray(plain, app.session.settings.geometry(TEST_CONFIG.pixels))
    data = FileData(volume, xray, source="phantom without contrast (test)", config=TEST_CONFIG)
    try:
        app._use_data(data)  # noqa: SLF001 - what the upload callback does after reading
        assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001
        assert "vessels" not in data.meshes() and "bone" in data.meshes()
        assert "No contrast-filled vessels found in this volume" in app.vessel_info.content
        assert [h.name for h in app.scene.patient] == ["/patient/bone"]
    finally:
        app.phantom_button.value = True  # back to the phantom for the other tests
    assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001
    assert app.vessel_info.content == ""
    assert "/patient/vessels" in [h.name for h in app.scene.patient]


@pytest.mark.parametrize(
    ("name", "content", "expected"),
    [
        ("notes.txt", b"hello", "expected a .zip"),
        ("case.zip", b"not a zip at all", "not a readable zip"),
        ("case.zip", b"", "not a readable zip"),
    ],
)
def test_bad_uploads_are_refused_with_a_message(name: str, content: bytes, expected: str) -> None:
    with pytest.raises(UploadError, match=expected):
        read_upload(name, content, max_bytes=10**6, config=TEST_CONFIG)


def test_upload_without_an_image_or_too_big(exported: Path) -> None:
    with pytest.raises(UploadError, match="no an XA/RF image|found no an XA/RF image|XA/RF"):
        read_upload("v.zip", zipped(exported, ["volume.npz"]), max_bytes=10**9, config=TEST_CONFIG)
    with pytest.raises(UploadError, match="limit"):
        read_upload("v.zip", zipped(exported, ["volume.npz", "image.dcm"]), max_bytes=1000, config=TEST_CONFIG)


def test_bad_upload_through_the_gui_shows_a_message(fresh: RoadmapApp) -> None:
    app = fresh
    before = app.session.data
    assert not app.load_upload("evil.zip", b"PK\x03\x04 broken")  # what the upload button calls
    assert "⚠" in app.status.content
    assert app.session.data is before


def test_the_users_skull_is_drawn_whole_on_a_ct_like_grid() -> None:
    """A CT's grid (1.25 x 1.25 x 3 mm voxels, a field twice the skull's width): the app's bone
    surface is the skull in one closed piece (its outer and inner surfaces), not plates. The app
    strided the voxels (ceil(240 / skull_detail 32) = 8: 10 x 10 x 24 mm cells) and drew the 3 mm
    shell as dozens of loose plates."""
    from app.web.scene import _decimated
    from registration.core.geometry import CArm
    from registration.core.images import XRayImage
    from tests.registration.io.test_meshes import SHELL_RADIUS_MM, _components, _ct_like_skull

    volume, _parts = _ct_like_skull()
    geometry = CArm.for_format(27.0, pixels=64)
    image = XRayImage(np.zeros((64, 64), np.float32), np.ones((64, 64), bool), geometry)
    data = FileData(volume, image, source="CT-like skull (test)", config=TEST_CONFIG)
    bone = data.meshes()["bone"]
    # outer and inner surface of the shell and the small bone, each closed with a sphere's topology
    assert len(_components(bone)) == 3 and bone.is_watertight and bone.euler_number == 6
    # drawn as extracted: under the scene's face budget (not simplified)
    assert _decimated(bone, 120_000) is bone
    r = np.linalg.norm(np.asarray(bone.vertices) - volume.center_mm, axis=1)
    # the shell where it is: vertices within a cell (6.25 mm) of its 68.5..71.5 mm (see the
    # registration test of bone_surface for the reason)
    shell = r[r < SHELL_RADIUS_MM + 20.0]
    assert shell.min() > 68.5 - 6.25 and shell.max() < 71.5 + 6.25


def test_the_users_field_mask_narrows_the_field_and_is_shown(fresh: RoadmapApp) -> None:
    """The Data tab's field mask (as register --image-mask): the image's field narrowed to it, the
    Display tab's Usable field shading what is left out; refused for the phantom and for a file
    that is no image."""
    import cv2

    from app.web.data import simulate_xray
    from registration.sim.phantom import make_head_phantom, registration_volume

    app = fresh
    anatomy = make_head_phantom(seed=0, contrast=False)
    volume = registration_volume(make_head_phantom(seed=0), 27.0, voxels=TEST_CONFIG.voxels)
    xray = simulate_xray(anatomy, app.session.settings.geometry(TEST_CONFIG.pixels))
    rows, cols = xray.shape
    drawn = np.full((rows, cols), 255, np.uint8)
    drawn[:, : cols // 2] = 0  # a blade over the left half, say
    ok, png = cv2.imencode(".png", drawn)
    assert ok
    with pytest.raises(ValueError, match="a field mask is for your data"):
        app.controller.load_field_mask("mask.png", png.tobytes())
    data = FileData(volume, xray, source="phantom image (test)", config=TEST_CONFIG)
    try:
        app._use_data(data)  # noqa: SLF001 - what the upload callback does after reading
        with pytest.raises(ValueError, match="notes.txt: a field mask is a PNG or TIFF image"):
            app.controller.load_field_mask("notes.txt", b"hello")
        app.controller.load_field_mask("mask.png", png.tobytes())
        mask = app.session.data.fixed_xray.mask
        assert not mask[:, : cols // 2].any() and mask[:, cols // 2 :].sum() == xray.mask[:, cols // 2 :].sum()
        assert "user mask" in app.session.data.fixed_xray.meta["mask_from"]
        assert app.show_field.value
        assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001
        tile = np.asarray(app.images.image)
        size = tile.shape[0]  # the fluoro tile: the row's first square
        left, right = tile[40:-40, 10 : size // 2 - 10], tile[40:-40, size // 2 + 10 : size - 10]
        # left of the mask's edge the fluoro tile is shaded blue; right of it the image is gray
        assert left[..., 2].mean() > left[..., 0].mean() + 40 and abs(right[..., 2].mean() - right[..., 0].mean()) < 15
    finally:
        app.show_field.value = False
        app.phantom_button.value = True
    assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001


def test_the_users_region_mask_is_what_the_registration_follows(fresh: RoadmapApp) -> None:
    """The Data tab's region mask (as register --roi-mask): outside it bone becomes soft tissue in
    the registration's volume, the scene keeps the whole volume; refused for the phantom and for
    a file of another kind."""
    import io

    from app.web.data import simulate_xray
    from registration.sim.phantom import make_head_phantom, registration_volume

    app = fresh
    volume = registration_volume(make_head_phantom(seed=0), 27.0, voxels=TEST_CONFIG.voxels)
    xray = simulate_xray(make_head_phantom(seed=0, contrast=False), app.session.settings.geometry(TEST_CONFIG.pixels))
    mask = np.zeros(volume.shape, dtype=np.uint8)
    mask[volume.shape[0] // 2 :] = 1  # the upper half of the slices
    buffer = io.BytesIO()
    np.savez(buffer, mask=mask)
    with pytest.raises(ValueError, match="a region mask is for your data"):
        app.controller.load_region("head.npz", buffer.getvalue())
    data = FileData(volume, xray, source="phantom (test)", config=TEST_CONFIG)
    try:
        app._use_data(data)  # noqa: SLF001 - what the upload callback does after reading
        with pytest.raises(ValueError, match="notes.txt: a region mask is .npz, NIfTI"):
            app.controller.load_region("notes.txt", b"hello")
        app.controller.load_region("head.npz", buffer.getvalue())
        followed = app.session.data.volume()
        lower = slice(0, volume.shape[0] // 2)
        assert (followed.data[lower][volume.data[lower] > 40] == 40).all()  # no bone below the region
        np.testing.assert_array_equal(followed.data[volume.shape[0] // 2 :], volume.data[volume.shape[0] // 2 :])
        assert "region: head.npz" in followed.label and "region: head.npz" in app.volume_info.content
        assert data.region is not None and int(data.region.mask.sum()) == int(mask.sum())
        # a registration on the region says whether the whole volume (its lower half too) agrees
        assert app.start_registration()
        assert app.session.wait(120)
        check = app.session.run.skull_spine
        assert check is not None and check.drr_count > 0
        assert wait_until(lambda: "skull and spine" in app.status.content, 30), app.status.content
        # the image is the same phantom unmoved: both halves agree within the polish's jitter on
        # this 256 px image of a 128^3 volume (measured 0.07 mm, 0.42 deg; bounds 0.3 mm, 1 deg)
        assert check.agree and check.shift_mm < 0.3 and check.rotation_deg < 1.0, check
    finally:
        app.phantom_button.value = True
    assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001
