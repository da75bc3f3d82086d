"""The Play run panel: a short simulated run played at its frame times; frames shown or skipped,
the product's message, the strip chart; Pause holds the run, Stop ends it (one shared playback)."""

from __future__ import annotations

import time

import numpy as np

from app.web.playback import motion_message
from registration.sim.fluoro import RunScript
from registration.studies.tracking import TrackingCase
from tests.app.conftest import wait_until

#: 3 s at 15 frames/s, 64 px frames, one sudden move (the app's 128^3 stand-in volume).
SHORT = TrackingCase(
    "short", RunScript(duration_s=3.0, seed=11, still_start_s=1.0, sudden_moves=1, min_move_mm=6.0, max_move_mm=10.0,
                       min_move_deg=2.0, max_move_deg=4.0, drift=False, breathing_mm=0.0),
    pixels=64,
)  # fmt: skip


def test_play_run_shows_every_frame_or_skips_it(fresh) -> None:
    panel = fresh.playback
    panel.case = SHORT
    panel.play_button.value = True  # as a click
    assert wait_until(lambda: panel.playing, 5.0)
    assert panel.play_button.disabled and not panel.stop_button.disabled
    assert wait_until(lambda: panel.finished.is_set(), 240.0)
    frames = SHORT.script.frames
    # every frame was either shown or skipped (arrived while the engine was busy), none queued
    assert panel.frames_shown + panel.skipped == frames
    assert panel.frames_shown == len(panel.estimates) > 0
    assert all(e.status in ("applied", "withheld", "unchanged") for e in panel.estimates)
    shown_frames = [e.frame for e in panel.estimates]
    assert shown_frames == sorted(set(shown_frames))
    # the strip chart holds one point per shown frame; the image is RGB
    assert len(panel.chart.data[0]) == panel.frames_shown
    assert panel.image.image.ndim == 3
    message = panel.last_message
    assert message == "no motion" or message.startswith(("motion corrected", "motion detected"))
    assert "frames shown" in panel.stats.content
    assert not panel.play_button.disabled and panel.stop_button.disabled
    # the status line tells the run's end with its counts, and the last correction (or withholding)
    applied = sum(e.status == "applied" for e in panel.estimates)
    withheld = sum(e.status == "withheld" for e in panel.estimates)
    status = fresh.status.content
    assert status.startswith(f"Play run finished: {panel.frames_shown} frames shown, {panel.skipped} skipped"), status
    assert f"{applied} corrections applied, {withheld} withheld." in status
    events = [e for e in panel.estimates if e.status in ("applied", "withheld")]
    if events:
        assert f"Last: frame {events[-1].frame} at {events[-1].t_s:.2f} s: motion" in status, status


#: SHORT with read-out glitches (frames the tracker must withhold) in its still start and after its
#: move: at least one of them arrives when the tracker is free, however slow the machine.
GLITCHED = TrackingCase(
    "short-glitched", RunScript(duration_s=3.0, seed=11, still_start_s=1.0, sudden_moves=1, min_move_mm=6.0,
                                max_move_mm=10.0, min_move_deg=2.0, max_move_deg=4.0, drift=False, breathing_mm=0.0,
                                glitch_times_s=(0.4, 2.6)),
    pixels=64,
)  # fmt: skip


def scene_pose(fresh) -> np.ndarray:
    """The 4x4 pose (mm) the 3-D scene shows the patient's vessels at."""
    import viser.transforms as vtf

    handle = next(h for h in fresh.scene.patient if "vessel" in h.name)
    pose = np.eye(4)
    pose[:3, :3] = vtf.SO3(np.asarray(handle.wxyz, np.float64)).as_matrix()
    pose[:3, 3] = np.asarray(handle.position, np.float64) / 1e-3  # the scene is in metres
    return pose


def assert_same_pose(shown: np.ndarray, expected: np.ndarray) -> None:
    # Tolerance: the pose goes 4x4 -> quaternion + metres -> 4x4 in float64 (~1e-15 relative);
    # 1e-9 (rotation entries) and 1e-9 mm are far below anything a viewer could see.
    np.testing.assert_allclose(shown[:3, :3], expected[:3, :3], atol=1e-9)
    np.testing.assert_allclose(shown[:3, 3], expected[:3, 3], atol=1e-9)


def test_the_scene_follows_the_played_run(fresh) -> None:
    from registration.studies.tracking import case_runs

    panel, presenter = fresh.playback, fresh.presenter
    panel.case = GLITCHED
    # a run played before (kept in the scene until the session changed: `fresh` changed it) is let go
    # by the presenter's loop; only then are the frames it draws this run's
    assert wait_until(lambda: presenter.followed is None, 10.0)
    drawn_before = len(presenter.followed_frames)
    panel.play_button.value = True
    assert wait_until(lambda: panel.finished.is_set() and not panel.playing, 240.0)
    estimates = panel.estimates
    # the run over, the scene keeps its last frame (drawn at the presenter's next frame, <= 0.1 s)
    assert wait_until(lambda: presenter.followed_frames[-1][0] == estimates[-1].frame, 5.0)
    by_frame = {e.frame: e for e in estimates}
    drawn = list(presenter.followed_frames)[drawn_before:]
    assert drawn and all(frame in by_frame for frame, _ in drawn)
    for frame, pose in drawn:  # every pose the scene showed is the roadmap's (applied) pose of that frame
        np.testing.assert_array_equal(pose, by_frame[frame].patient_motion)
    # withheld (and unchanged) frames show nothing new: the last applied pose stays
    applied_pose = np.eye(4)
    withheld = 0
    for e in estimates:
        if e.status == "applied":
            applied_pose = e.patient_motion
        else:
            np.testing.assert_allclose(e.patient_motion, applied_pose, atol=1e-12)
            withheld += e.status == "withheld"
    glitches = [n for n, phase in enumerate(case_runs(GLITCHED)[0].phases) if phase == "glitch"]
    processed = [by_frame[n] for n in glitches if n in by_frame]
    assert processed, [e.frame for e in estimates]  # one arrived while the tracker was free
    assert all(e.status == "withheld" for e in processed), [(e.frame, e.status, e.reason) for e in processed]
    assert withheld >= len(processed)
    # the vessels' nodes are at the last frame's pose ...
    assert_same_pose(scene_pose(fresh), estimates[-1].patient_motion)
    assert fresh.scene.frustum is not None
    # ... until the session changes: then it shows the session (its estimate) again
    fresh.offset_sliders[0].value = 1.0
    assert wait_until(lambda: np.allclose(scene_pose(fresh), fresh.session.estimate, atol=1e-9), 10.0)
    assert fresh._shown_geometry is not None  # noqa: SLF001 - the session's C-arm is drawn again
    statuses = [e.status for e in estimates]
    if "applied" in statuses:  # a correction moved the roadmap: the scene followed it off the start
        moved = estimates[statuses.index("applied")]
        assert any(frame >= moved.frame and not np.allclose(pose, np.eye(4)) for frame, pose in drawn)


def test_a_biplane_run_plays_in_biplane_mode(fresh) -> None:
    """Biplane mode: the phantom's run has both planes (plane B at the C-arm tab's angles), tracked
    together, shown side by side; both C-arms in the scene show the run's views, then the session's."""
    import viser.transforms as vtf

    from app.web.playback import DISPLAY_PX

    panel, presenter = fresh.playback, fresh.presenter
    panel.case = SHORT
    try:
        fresh.biplane.value = True
        fresh.secondary_b.value = 10.0
        assert wait_until(lambda: presenter.followed is None, 10.0)
        panel.play_button.value = True
        assert wait_until(lambda: panel.finished.is_set() and not panel.playing, 240.0)
        assert panel.planes == 2 and panel.frames_shown + panel.skipped == SHORT.script.frames
        assert panel.image.image.shape[1] > 2 * DISPLAY_PX  # plane A | plane B
        assert wait_until(lambda: presenter.followed_frames[-1][0] == panel.estimates[-1].frame, 5.0)
        followed = presenter.followed
        assert followed is not None and followed.geometry_b is not None
        g_b = followed.geometry_b
        assert (g_b.primary_deg, g_b.secondary_deg) == (fresh.session.settings.primary_b_deg, 10.0)
        # plane B's frustum looks along the run's plane B beam (the scene's camera convention, app.scene)
        rotation = vtf.SO3(np.asarray(fresh.scene.frustum_b.wxyz, np.float64)).as_matrix()
        np.testing.assert_allclose(rotation[:, 2], g_b.direction, atol=1e-9)  # float64 quaternion round trip
        assert_same_pose(scene_pose(fresh), panel.estimates[-1].patient_motion)
    finally:
        fresh.secondary_b.value = 0.0
        fresh.biplane.value = False
    # back to one plane: the session changed, the run's plane B leaves the scene
    assert wait_until(lambda: fresh.scene.frustum_b is None and presenter.followed is None, 10.0)


def test_pause_holds_and_stop_ends(fresh) -> None:
    panel = fresh.playback
    panel.case = SHORT
    panel.play_button.value = True
    assert wait_until(lambda: panel.frames_shown >= 2, 120.0)
    panel.pause_button.value = True
    assert panel.paused and panel.pause_button.label == "Resume"
    time.sleep(0.3)  # a frame being processed when Pause came may still finish
    held = panel.frames_shown
    time.sleep(0.8)
    assert panel.frames_shown == held  # paused: no frame shown, none skipped
    panel.stop_button.value = True
    assert wait_until(lambda: panel.finished.is_set(), 30.0)
    assert panel.frames_shown < SHORT.script.frames and "Stopped" in panel.stats.content


def test_motion_message() -> None:
    from registration.core.geometry import CArm, rigid
    from registration.core.tracking import FrameEstimate

    def est(status: str, motion: np.ndarray) -> FrameEstimate:
        return FrameEstimate(0, 0.0, status, motion, motion, "refine", 0.9, "", 10.0, 1.8, 0.0, 10)

    g = CArm.for_format(27.0, pixels=64)
    moved = rigid(None, (3.0, 0.0, 0.0))
    assert motion_message(est("applied", moved), np.eye(4), g)[0] == "motion corrected 3.0 mm, 0.0°"
    assert motion_message(est("withheld", np.eye(4)), np.eye(4), g)[0] == "motion detected, correction withheld"
    assert motion_message(est("unchanged", np.eye(4)), np.eye(4), g)[0] == "no motion"


def test_uploaded_run_plays_without_truth(fresh, tmp_path) -> None:
    from registration.io import dicom
    from registration.studies.tracking import case_runs

    panel = fresh.playback
    run = case_runs(SHORT)[0]
    path = dicom.write_xray_run(list(run), tmp_path / "run.dcm", times_s=run.times_s)
    assert not panel.load_run("junk.dcm", b"not dicom")
    assert "junk.dcm" in panel.message.content
    assert panel.load_run("run.dcm", path.read_bytes())
    assert "45 frames" in panel.message.content and panel.phantom_run_button.visible
    panel.play_button.value = True
    assert wait_until(lambda: panel.finished.is_set() and not panel.playing, 240.0)
    assert panel.frames_shown + panel.skipped == len(run)
    assert np.all(np.isnan(panel.chart.data[1]))  # no truth: the true series stays empty
    assert np.all(np.isfinite(panel.chart.data[2]))
    panel.phantom_run_button.value = True
    assert panel.user_run is None and not panel.phantom_run_button.visible


#: Where the C-arm's iso-center was when the uploaded run was taken (mm): the user's data is the
#: phantom moved there, so the phantom's run is what that C-arm saw (the run's file does not say it).
RUN_ISO = (10.0, -5.0, 8.0)


def test_an_uploaded_run_is_read_about_the_datas_isocenter(fresh, tmp_path, monkeypatch) -> None:
    """An uploaded run is tracked and read out about the iso-center a single registration of the
    data uses (the data's, here the volume's IsocenterPosition), not about the world origin."""
    from dataclasses import replace

    import app.web.playback
    from app.web.data import FileData
    from app.web.status import correction
    from registration.core.geometry import matrix_to_offsets, rigid
    from registration.core.metrics import residuals
    from registration.core.volume import Volume
    from registration.io import dicom
    from registration.studies.tracking import case_runs
    from tests.app.conftest import TEST_CONFIG

    seen: list[tuple[float, ...]] = []  # the iso-centers the Play run's messages were taken at

    def spy(before, after, isocenter_mm):
        seen.append(tuple(float(v) for v in isocenter_mm))
        return correction(before, after, isocenter_mm)

    monkeypatch.setattr(app.web.playback, "correction", spy)
    panel = fresh.playback
    run = case_runs(SHORT)[0]  # the phantom imaged about the world origin, its truth per frame
    to_iso, from_iso = rigid(None, RUN_ISO), rigid(None, -np.asarray(RUN_ISO))
    phantom = fresh._phantom_data.volume(SHORT.volume_format_cm)  # noqa: SLF001
    moved = Volume(phantom.data, to_iso @ phantom.index_to_world, label="the phantom moved to RUN_ISO",
                   meta={"isocenter_mm": RUN_ISO, "isocenter_from": "IsocenterPosition of the volume"})  # fmt: skip
    # The same anatomy RUN_ISO further: a C-arm about RUN_ISO sees it as the run's C-arm saw the
    # phantom, and the patient's motion, conjugated, is the run's truth.
    truth = [to_iso @ m @ from_iso for m in run.truth]
    image = replace(run[0], geometry=replace(run[0].geometry, isocenter_mm=RUN_ISO))
    data = FileData(moved, image, source="test", config=TEST_CONFIG, isocenter_from="IsocenterPosition of the volume")
    fresh._use_data(data)  # noqa: SLF001 - what an upload does once read
    try:
        assert wait_until(lambda: fresh._shown_version == fresh.session.version, 60)  # noqa: SLF001
        path = dicom.write_xray_run(list(run), tmp_path / "run.dcm", times_s=run.times_s)
        assert panel.load_run("run.dcm", path.read_bytes())
        panel.play_button.value = True
        assert wait_until(lambda: panel.finished.is_set() and not panel.playing, 240.0)
        geometry = fresh.session.geometry()
        assert geometry.isocenter_mm == RUN_ISO
        # CONVENTIONS §4 at the iso-center, one plane: the roadmap's last pose < 1 mm in-plane and
        # < 3 deg from the truth (the success criterion). Read about the world origin, the run's C-arm
        # stood |RUN_ISO| = 13 mm from where it was: no frame applied (withheld or unchanged), the
        # roadmap left at the start, 4.1 mm in-plane and 2.7 deg from the truth after the run's move.
        last = panel.estimates[-1]
        residual = residuals(last.patient_motion, truth[last.frame], geometry)
        statuses = [(e.frame, e.status, e.reason) for e in panel.estimates]
        assert residual.inplane_mm < 1.0 and residual.rotation_deg < 3.0, (residual, statuses)
        applied = [e for e in panel.estimates if e.status == "applied"]
        assert applied, statuses
        # The strip chart's roadmap tx, ty are view-frame offsets about RUN_ISO: the last frame's
        # within 1 mm of the truth's (the in-plane bound above: their difference is the in-plane
        # residual up to the residual rotation, ~0.1 deg, times the run's ~10 mm move, < 0.05 mm).
        true_tx_ty = matrix_to_offsets(truth[last.frame], geometry)[:2]
        shown_tx_ty = np.array([panel.chart.data[2][-1], panel.chart.data[4][-1]])
        assert np.linalg.norm(shown_tx_ty - true_tx_ty) < 1.0, (shown_tx_ty, true_tx_ty)
        assert np.all(np.isnan(panel.chart.data[1]))  # the app has no truth for an upload
        # Each message's magnitude ('motion corrected x mm, y°') is taken at RUN_ISO (CONVENTIONS §4).
        assert seen and all(iso == RUN_ISO for iso in seen), set(seen)
    finally:
        panel.use_phantom_run()
        fresh.phantom_button.value = True  # back to the phantom for the other tests


def test_the_run_report_and_the_source_view_follow_the_played_run(fresh, tmp_path, monkeypatch) -> None:
    """The camera "from the source" rides on the run's C-arm while it plays; afterwards Write run
    report writes the played run's report (the same as ``roadmap3d track --report``)."""
    import json

    from app.web.qa_panel import ComparePanel
    from registration.studies import qa_report

    monkeypatch.setenv("ROADMAP3D_REPORTS", str(tmp_path))
    panel, presenter = fresh.playback, fresh.presenter
    compare = next(p for p in fresh.panels if isinstance(p, ComparePanel))
    panel.case = SHORT
    fresh.primary.value = 30.0  # the session's C-arm elsewhere than the run's
    try:
        compare.view_from_source.value = True
        assert wait_until(lambda: presenter.followed is None, 10.0)
        panel.play_button.value = True
        assert wait_until(lambda: panel.playing, 5.0)
        assert panel.report_button.disabled  # nothing to report while it plays
        assert wait_until(lambda: panel.finished.is_set() and not panel.playing, 240.0)
        assert wait_until(lambda: presenter.followed_frames[-1][0] == panel.estimates[-1].frame, 5.0)
        run_geometry = presenter.followed.geometry
        assert run_geometry.primary_deg != 30.0
        camera = fresh.server.initial_camera
        np.testing.assert_allclose(camera.position, run_geometry.source_mm * 1e-3, atol=1e-9)
        np.testing.assert_allclose(camera.look_at, np.asarray(run_geometry.isocenter_mm) * 1e-3, atol=1e-9)
        assert not panel.report_button.disabled
        panel.report_button.value = True
        assert wait_until(lambda: panel.last_report is not None, 120.0)
        out = panel.last_report
        assert out.parent == tmp_path
        saved = json.loads((out / qa_report.REPORT_JSON).read_text())
        # every processed frame with the decision it got in the app
        assert [f["frame"] for f in saved["frames"]] == [e.frame for e in panel.estimates]
        assert [f["status"] for f in saved["frames"]] == [e.status for e in panel.estimates]
        assert saved["summary"]["skipped"] == panel.skipped and saved["frame_count"] == SHORT.script.frames
        assert (out / "strip_charts.png").stat().st_size > 10_000 and (out / qa_report.REPORT_HTML).exists()
    finally:
        compare.view_from_source.value = False
        fresh.primary.value = 0.0
