"""The FDK 3DRA as the default volume, and the optional calibration view (driven by its handles)."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import numpy as np
import pytest

from app.web import data as app_data
from app.web.data import AppConfig, PhantomData
from app.web.gui import RoadmapApp

from .conftest import TEST_CONFIG, wait_until

ERROR = re.compile(r"Calibration error: (\d+\.\d\d) mm")


def test_the_fdk_3dra_is_the_default_and_the_stand_in_stays_selectable(monkeypatch) -> None:
    monkeypatch.delenv("ROADMAP3D_APP_VOLUME", raising=False)
    assert AppConfig.from_env().volume_source == "fdk"
    monkeypatch.setenv("ROADMAP3D_APP_VOLUME", "resampled")
    assert AppConfig.from_env().volume_source == "resampled"
    monkeypatch.setenv("ROADMAP3D_APP_VOLUME", "cone-beam")
    with pytest.raises(ValueError, match="ROADMAP3D_APP_VOLUME"):
        AppConfig.from_env()


def test_the_first_reconstruction_reports_what_it_prepares(monkeypatch) -> None:
    """A reconstruction that takes a while (here a stand-in that sleeps) reports progress each second."""
    import registration.sim.reconstruct as reconstruct

    config = AppConfig(voxels=32, volume_source="fdk")
    calls: list[tuple[int, float, int]] = []

    def slow_reconstruction(seed: int, *, volume_format_cm: float, voxels: int, contrast: bool = True):
        calls.append((seed, volume_format_cm, voxels))
        time.sleep(2.3)
        return PhantomData(AppConfig(voxels=32, volume_source="resampled")).volume(volume_format_cm)

    monkeypatch.setattr(reconstruct, "reconstruct_3dra", slow_reconstruction)
    monkeypatch.setattr(app_data, "TICK_S", 0.5)
    seen: list[tuple[str, float]] = []
    data = PhantomData(config, lambda message, fraction: seen.append((message, fraction)))
    data.volume(27.0)
    assert calls == [(0, 27.0, 32)]
    ticks = [m for m, _ in seen if "simulating the rotational run" in m]
    assert len(ticks) >= 3, seen
    assert all("reconstructing it (FDK" in m and "cached afterwards" in m for m in ticks)
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and fractions[-1] < 0.6  # the bar only moves forward


def test_the_volume_label_is_shown(app: RoadmapApp) -> None:
    label = app.session.data.volume(app.session.settings.volume_format_cm).label
    assert label in app.volume_info.content
    assert "Registration volume" in app.volume_info.content


@pytest.fixture()
def calibration(fresh: RoadmapApp) -> Iterator[RoadmapApp]:
    yield fresh
    fresh.calibration.enabled.value = False
    assert fresh.calibration.idle.wait(30)


def test_calibration_is_off_and_free_by_default(app: RoadmapApp) -> None:
    view = app.calibration
    assert view.enabled.value is False
    assert not view.image.visible and not view.run_folder.visible
    assert view.shots_computed == 0 and view.frames is None
    assert all(not node.visible for node in view._scene_nodes)  # noqa: SLF001


def test_calibration_shows_the_dodecahedron_its_image_and_the_error(calibration: RoadmapApp) -> None:
    app = calibration
    view = app.calibration
    view.enabled.value = True
    assert wait_until(lambda: view.shots_computed >= 1 and view.idle.is_set(), 60)
    # The scene: 20 spheres (vertex 0 the larger marker), the edges, a label.
    spheres = [n for n in view._scene_nodes if "sphere" in n.name]  # noqa: SLF001
    assert len(spheres) == 20 and all(n.visible for n in view._scene_nodes)  # noqa: SLF001
    assert wait_until(lambda: not any(h.visible for h in app.scene.patient), 10)  # imaged on its own
    # The panel: the image with detected spheres (green circles), and the error in mm.
    picture = np.asarray(view.image.image)
    green = (picture[..., 1] > 150) & (picture[..., 0] < 120) & (picture[..., 2] < 140)
    assert green.sum() > 200
    match = ERROR.search(view.readout.content)
    assert match, view.readout.content
    assert float(match[1]) < 0.2  # the paper's figure for the calibrated geometry
    assert "20 spheres detected" in view.readout.content and "Sensors alone" in view.readout.content
    first = view.shot
    # Moving the C-arm re-images the phantom at the new angles.
    app.primary.value = 40.0
    assert wait_until(lambda: view.shot is not first and view.idle.is_set(), 60)
    assert view.shot is not None and view.shot.nominal.primary_deg == 40.0
    # Off again: hidden, nothing more computed.
    view.enabled.value = False
    count = view.shots_computed
    app.primary.value = 0.0
    time.sleep(0.3)
    assert view.shots_computed == count
    assert not any(n.visible for n in view._scene_nodes) and not view.image.visible  # noqa: SLF001
    assert wait_until(lambda: any(h.visible for h in app.scene.patient), 10)  # the patient is back


def test_rotational_run_frames(calibration: RoadmapApp) -> None:
    app = calibration
    view = app.calibration
    if view.frames is None:  # nothing simulated yet: no frame slider that looks live
        assert not view.frame.visible
    view.enabled.value = True
    view.run_button.value = True  # simulated at low resolution (or loaded from the cache)
    assert wait_until(lambda: view.frames is not None and view.idle.is_set(), 60)
    assert view.frames is not None
    n = TEST_CONFIG.run_projections
    assert len(view.frames) == n and view.frame.max == n - 1 and not view.frame.disabled and view.frame.visible
    assert view.frames.images.shape[1:] == (TEST_CONFIG.run_pixels, TEST_CONFIG.run_pixels)
    shown = []
    for index in (0, n // 2):
        view.frame.value = index
        shown.append(np.asarray(view.run_image.image).copy())
        assert f"Frame {index + 1} of {n}" in view.run_readout.content
    assert not np.array_equal(shown[0], shown[1])  # another view of the head
    assert np.ptp(view.frames.primary_deg) == pytest.approx(200.0)
    assert view.run_cached(app.session.settings.volume_format_cm)
