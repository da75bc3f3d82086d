"""The Compare and Evidence tabs without a browser: overlay modes, zoom, the large layout, the
machine-based ghost, the camera's framing, the report button."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.web.gui import RoadmapApp
from app.web.qa_panel import ComparePanel
from app.web.scene import CAMERA_FILL, EDGE_FILL, frame_points, screen_extent
from registration.studies import qa_report
from registration.studies.qa_images import OVERLAY_LABELS, OVERLAY_MODES

from .conftest import wait_until


def _panel(app: RoadmapApp) -> ComparePanel:
    return next(p for p in app.panels if isinstance(p, ComparePanel))


def _drawn(app: RoadmapApp) -> np.ndarray:
    """The Roadmap tab's picture once the presenter has drawn the session's newest state."""
    for _ in range(2):  # the second frame began after the change (the first may have been under way)
        shown = app.presenter.frames_shown
        app.presenter.force_refresh()
        assert wait_until(lambda shown=shown: app.presenter.frames_shown > shown, 60)
    return np.asarray(app.images.image).copy()


@pytest.fixture()
def compare(fresh: RoadmapApp):
    panel = _panel(fresh)
    yield panel
    panel.overlay.value = OVERLAY_LABELS["outline"]
    panel.zoom.value = 1.0
    panel.large.value = False
    panel.show_initial.value = False
    panel.view_from_source.value = False


def test_every_overlay_mode_draws_its_own_picture(fresh: RoadmapApp, compare: ComparePanel):
    fresh.table_buttons["T4"].value = True  # the image moves; the roadmap stays at the machine-based pose
    size = fresh.session.config.display_px
    pictures = {}
    for mode in OVERLAY_MODES:
        compare.overlay.value = OVERLAY_LABELS[mode]
        assert compare.settings().mode == mode
        pictures[mode] = _drawn(fresh)[:, :size]  # the fluoro tile (the DRR is beside it)
    for mode, tile in pictures.items():
        assert tile.std() > 10, mode  # not blank
    for i, a in enumerate(OVERLAY_MODES):
        for b in OVERLAY_MODES[i + 1 :]:
            changed = float(np.any(pictures[a] != pictures[b], axis=2).mean())
            # the outline and the wipe share the image on one side and differ by their lines only
            floor = 0.002 if {a, b} <= {"outline", "wipe", "edges"} else 0.10
            assert changed > floor, (a, b, changed)
    compare.checker.value = 16
    finer = _drawn(fresh)[:, :size]
    compare.overlay.value = OVERLAY_LABELS["checkerboard"]
    assert np.any(finer != pictures["checkerboard"])


def test_zoom_and_the_large_layout(fresh: RoadmapApp, compare: ComparePanel):
    normal = _drawn(fresh)
    compare.zoom.value = 2.0
    zoomed = _drawn(fresh)
    assert zoomed.shape == normal.shape and np.any(zoomed != normal)
    compare.large.value = True
    large = _drawn(fresh)
    # the fluoro tile alone, larger than the two tiles side by side
    assert large.shape[0] > normal.shape[0] and large.shape[1] == large.shape[0], (large.shape, normal.shape)


def test_machine_based_ghost_sits_at_the_sensors_pose(fresh: RoadmapApp, compare: ComparePanel):
    fresh.table_buttons["T4"].value = True
    fresh.register_button.value = True
    assert fresh.session.wait(240)
    compare.show_initial.value = True
    _drawn(fresh)
    nodes = fresh.scene.initial
    assert nodes and all(n.visible for n in nodes)
    np.testing.assert_allclose(nodes[0].position, np.zeros(3), atol=1e-12)  # the machine-based pose: no correction
    np.testing.assert_allclose(nodes[0].wxyz, [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    registered = fresh.scene.patient[0].position
    assert np.linalg.norm(np.asarray(registered) - np.asarray(nodes[0].position)) > 1e-3  # apart (T4: ~6 mm)
    compare.show_initial.value = False
    _drawn(fresh)
    assert not any(n.visible for n in nodes)


def test_framing_fills_the_view_and_stays_inside_it():
    rng = np.random.default_rng(0)
    points = rng.uniform([-0.05, -0.03, -0.05], [0.05, 0.03, 0.05], size=(500, 3))  # a 10 x 6 x 10 cm tree
    up = np.array([0.0, -1.0, 0.0])
    for aspect in (0.38, 1.0, 1.7):
        position, look_at = frame_points(points, aspect=aspect)
        height, width = screen_extent(points, position, look_at, up, math.radians(50.0), aspect)
        assert width <= EDGE_FILL + 1e-6 and height <= CAMERA_FILL + 1e-6
        # one of the two limits is reached (bisection to 1e-6 of the distance's ratio)
        assert max(height / CAMERA_FILL, width / EDGE_FILL) > 0.999, (aspect, height, width)
        assert height > 1 / 3, (aspect, height)  # the third of the view's height


def test_view_from_source_puts_the_default_camera_at_the_source(fresh: RoadmapApp, compare: ComparePanel):
    compare.view_from_source.value = True
    _drawn(fresh)
    g = fresh.session.geometry()
    camera = fresh.server.initial_camera
    np.testing.assert_allclose(camera.position, g.source_mm * 1e-3, atol=1e-9)
    np.testing.assert_allclose(camera.look_at, np.asarray(g.isocenter_mm) * 1e-3, atol=1e-9)
    fresh.primary.value = 30.0  # the C-arm turns: the camera follows
    _drawn(fresh)
    g = fresh.session.geometry()
    assert g.primary_deg == 30.0
    np.testing.assert_allclose(camera.position, g.source_mm * 1e-3, atol=1e-9)
    compare.view_from_source.value = False
    _drawn(fresh)
    assert np.linalg.norm(np.asarray(camera.position) - g.source_mm * 1e-3) > 0.1  # back on the vessels


def test_report_button_writes_the_last_registration(fresh: RoadmapApp, compare: ComparePanel, tmp_path, monkeypatch):
    monkeypatch.setenv("ROADMAP3D_REPORTS", str(tmp_path))
    with pytest.raises(ValueError, match="Register first"):
        fresh.session.reset()
        compare.write_report()
    fresh.table_buttons["T4"].value = True
    fresh.register_button.value = True
    assert fresh.session.wait(240)
    result = fresh.session.run.result
    # the Evidence tab draws its plots
    # this run's evidence (an earlier test's plots may still be shown until it is drawn)
    assert wait_until(lambda: compare.evidence_text.content.startswith("Confidence"), 180)
    assert compare.profiles_image.image.shape[0] > 100
    # the decision is stated (in the full suite's order this T4 has also been withheld: the button must work either way)
    assert "applied" in compare.evidence_text.content or "withheld" in compare.evidence_text.content
    compare.report_button.value = True
    assert wait_until(lambda: compare.last_report is not None, 180)
    out = compare.last_report
    assert out.parent == tmp_path
    text = (out / qa_report.REPORT_HTML).read_text()
    saved = json.loads((out / qa_report.REPORT_JSON).read_text())
    assert saved["patient_motion"] == result.to_dict()["patient_motion"]
    numbers = qa_report.read_report_numbers(text)
    assert float(numbers["similarity"]) == pytest.approx(result.similarity, abs=5e-5)
    assert float(numbers["confidence"]) == pytest.approx(fresh.session.run.assessment["confidence"], abs=5e-4)
    assert (out / "overlay_outline.png").exists() and (out / "evidence_profiles.png").exists()
    assert str(out) in fresh.status.content


def test_biplane_evidence_shows_both_planes(fresh: RoadmapApp, compare: ComparePanel):
    try:
        fresh.biplane.value = True
        fresh.table_buttons["T4"].value = True
        fresh.register_button.value = True
        assert fresh.session.wait(240)
        run = fresh.session.run
        assert len(run.views) == 2
        # this run's evidence (the text of an earlier test's run also starts with "Confidence")
        shown = lambda: compare._shown_run is run and compare.plane_b_shown  # noqa: E731, SLF001
        assert wait_until(lambda: shown() and compare.evidence_text.content.startswith("Confidence"), 180)
        # plane A's and plane B's measure around the same estimate, each its own picture
        assert compare.plane_b_shown and compare.profiles_b_image.visible
        a, b = np.asarray(compare.profiles_image.image), np.asarray(compare.profiles_b_image.image)
        assert a.shape[0] > 100 and b.shape == a.shape and not np.array_equal(a, b)
        assert "plane B" in compare.evidence_text.content
    finally:
        fresh.biplane.value = False
    fresh.table_buttons["T4"].value = True
    fresh.register_button.value = True
    assert fresh.session.wait(240)
    single = fresh.session.run
    shown = lambda: compare._shown_run is single and not compare.plane_b_shown  # noqa: E731, SLF001
    assert wait_until(lambda: shown() and compare.evidence_text.content.startswith("Confidence"), 180)
    assert not compare.profiles_b_image.visible  # one plane again: plane B's picture leaves
