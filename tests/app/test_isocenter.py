"""The Data tab's iso-center field: a bad value changes nothing and says why; a good one moves the
image's iso-center, the scene's marker to exactly those coordinates, and the next registration
registers about it (its residual at that iso-center, against the known truth)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.web.data import FileData
from app.web.gui import RoadmapApp
from app.web.upload import ISOCENTER_MARGIN_MM
from registration.core.geometry import TABLE_I, offsets_to_matrix
from registration.core.metrics import residuals
from registration.io.dicom import read_volume, read_xray, write_npz, write_xray

from .conftest import TEST_CONFIG, wait_until

#: Where the C-arm's iso-center really was when the image was taken (mm, inside the phantom's head;
#: the image file does not say it, as an XA file does not).
TRUE_ISO = (10.0, -5.0, 8.0)


@pytest.fixture(scope="module")
def off_center(app: RoadmapApp, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, np.ndarray]:
    """The phantom's 3DRA (.npz) and a T4-moved fluoro image taken about TRUE_ISO (XA), and the truth."""
    from app.web.data import simulate_xray

    folder = tmp_path_factory.mktemp("off-center")
    phantom = app._phantom_data  # noqa: SLF001
    write_npz(phantom.volume(27.0), folder / "volume.npz")
    geometry = replace(app.session.settings.geometry(TEST_CONFIG.pixels), isocenter_mm=TRUE_ISO)
    truth = offsets_to_matrix(TABLE_I["T4"], geometry)  # T4 in the view frame about TRUE_ISO
    write_xray(simulate_xray(phantom.phantom(True), geometry, motion=truth), folder / "image.dcm")
    return folder / "volume.npz", folder / "image.dcm", truth


def _marker_mm(app: RoadmapApp) -> np.ndarray:
    return np.asarray(app.scene.isocenter.position, np.float64) / 1e-3  # the scene is in metres


@pytest.fixture()
def user_data(fresh: RoadmapApp, off_center) -> FileData:
    """The app showing the off-center image read about the world origin (no --isocenter, no tag)."""
    volume_path, image_path, _ = off_center
    data = FileData(read_volume(volume_path), read_xray(image_path), source="test", config=TEST_CONFIG,
                    isocenter_from="the world origin (default)")  # fmt: skip
    fresh._use_data(data)  # noqa: SLF001 - what an upload does once read
    assert wait_until(lambda: fresh._shown_version == fresh.session.version, 30)  # noqa: SLF001
    yield data
    fresh.phantom_button.value = True  # back to the phantom for the other tests


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ("1, 2", "expected three numbers"),
        ("a, b, c", "expected three numbers"),
        ("nan, 0, 0", "expected three numbers"),
        ("10, -5, inf", "expected three numbers"),
        ("", "expected three numbers"),
        ("1, 2, 3, 4", "expected three numbers"),
        ("0, 0, 2000", "mm outside the volume"),  # a typo: 2 m from a head
    ],
)
def test_a_bad_isocenter_changes_nothing_and_says_why(fresh: RoadmapApp, user_data: FileData, text, said) -> None:
    app = fresh
    before = (user_data.isocenter_mm, user_data.isocenter_text, app.session.version, _marker_mm(app).copy())
    app.isocenter_field.value = text
    app.isocenter_button.value = True  # as a click
    assert "⚠" in app.status.content and "Iso-center" in app.status.content and said in app.status.content
    assert (user_data.isocenter_mm, user_data.isocenter_text, app.session.version) == before[:3]
    assert app.session.xray().geometry.isocenter_mm == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(_marker_mm(app), before[3])


def test_the_bound_is_the_volume_grid_plus_the_margin(fresh: RoadmapApp, user_data: FileData) -> None:
    from app.web.upload import isocenter_field

    volume = user_data.volume()
    top = float(np.asarray(volume.world_corners_mm())[:, 2].max())  # the grid's last voxel centre on z
    inside = isocenter_field(f"0, 0, {top + ISOCENTER_MARGIN_MM - 1.0}", volume)[0]
    assert inside == (0.0, 0.0, top + ISOCENTER_MARGIN_MM - 1.0)
    with pytest.raises(ValueError, match=f"lies {ISOCENTER_MARGIN_MM + 1.0:.0f} mm outside the volume"):
        isocenter_field(f"0, 0, {top + ISOCENTER_MARGIN_MM + 1.0}", volume)


def test_the_phantom_keeps_its_isocenter(fresh: RoadmapApp) -> None:
    app = fresh
    assert all(c.disabled for c in app.layout.isocenter_controls)
    assert "the world origin" in app.layout.isocenter_info.content
    version = app.session.version
    app.isocenter_field.value = "10, -5, 8"
    app.isocenter_button.value = True  # even if a click got through: refused, nothing changed
    assert "⚠" in app.status.content and "the phantom is imaged about the world origin" in app.status.content
    assert app.session.version == version and app.session.geometry().isocenter_mm == (0.0, 0.0, 0.0)


def test_a_good_isocenter_moves_the_marker_and_the_next_registration_uses_it(
    fresh: RoadmapApp, user_data: FileData, off_center, monkeypatch
) -> None:
    import app.web.session as session_module

    app = fresh
    _, _, truth = off_center
    assert not any(c.disabled for c in app.layout.isocenter_controls)
    assert "(0.00, 0.00, 0.00) mm, from the world origin (default)" in app.layout.isocenter_info.content
    app.isocenter_field.value = " 10, -5, 8 mm"
    app.isocenter_button.value = True
    assert "⚠" not in app.status.content, app.status.content
    assert app.status.content.startswith("Iso-center set to (10.00, -5.00, 8.00) mm, from the Data tab")
    assert user_data.isocenter_mm == TRUE_ISO and app.session.xray().geometry.isocenter_mm == TRUE_ISO
    assert "(10.00, -5.00, 8.00) mm, from the Data tab" in app.layout.isocenter_info.content
    assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001
    # the marker sits at the typed coordinates (metres in the scene: mm * 1e-3 and back, float64)
    np.testing.assert_allclose(_marker_mm(app), TRUE_ISO, rtol=0, atol=1e-9)

    seen = []
    real_register = session_module.register

    def spy(volume, views, **kwargs):
        seen.append([v.geometry.isocenter_mm for v in (views if isinstance(views, list) else [views])])
        return real_register(volume, views, **kwargs)

    monkeypatch.setattr(session_module, "register", spy)
    app.register_button.value = True
    assert app.session.wait(120), "registration did not finish"
    assert seen == [[TRUE_ISO]]  # registered about the typed iso-center
    # CONVENTIONS §4 at that iso-center, single plane: in-plane residual < 1 mm, rotation < 3 deg
    residual = residuals(app.session.estimate, truth, app.session.geometry())
    assert residual.inplane_mm < 1.0 and residual.rotation_deg < 3.0, residual

    # "volume center": the center of the volume's grid, exactly
    app.volume_center_button.value = True
    center = tuple(float(v) for v in user_data.volume().center_mm)
    assert user_data.isocenter_mm == center
    assert "from the center of the volume's grid (Data tab)" in app.layout.isocenter_info.content
    assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001
    np.testing.assert_allclose(_marker_mm(app), center, rtol=0, atol=1e-9)

    # "the middle of the head", exactly as --isocenter head
    from registration.io.isocenter import head_isocenter_mm

    app.head_center_button.value = True
    head = head_isocenter_mm(user_data.volume())
    assert user_data.isocenter_mm == head
    assert "from the middle of the head (Data tab)" in app.layout.isocenter_info.content
    assert wait_until(lambda: app._shown_version == app.session.version, 30)  # noqa: SLF001
    np.testing.assert_allclose(_marker_mm(app), head, rtol=0, atol=1e-9)
