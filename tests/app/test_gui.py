"""Drive the app through its GUI handles, as a browser would (no browser needed)."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from app.web.gui import RoadmapApp
from app.web.status import correction
from registration.core.geometry import TABLE_I

from .conftest import parse_readout, wait_until


def shown(app: RoadmapApp) -> bool:
    """The presenter has caught up with the session."""
    return app._shown_version == app.session.version  # noqa: SLF001


def test_t4_then_register_reaches_sub_millimetre(fresh: RoadmapApp) -> None:
    app = fresh
    app.table_buttons["T4"].value = True
    assert np.allclose([s.value for s in app.offset_sliders], TABLE_I["T4"], atol=0.01)
    assert wait_until(lambda: shown(app), 10)
    inplane_before, _, _ = parse_readout(app.readout.content)
    assert inplane_before > 3.0  # T4 moves the head 5.7 mm in-plane

    drawn_before, skipped_before = len(app.presenter.live_reports), app.presenter.live_skipped
    app.register_button.value = True
    assert app.session.running
    # Conflicting controls are disabled for the run, Stop is enabled.
    assert app.register_button.disabled and not app.stop_button.disabled
    assert all(c.disabled for c in app.carm_controls + app.motion_controls)
    start = time.monotonic()
    assert app.session.wait(120), "registration did not finish"
    duration = time.monotonic() - start
    assert wait_until(lambda: shown(app) and not app.register_button.disabled, 5)

    inplane, total, rotation = parse_readout(app.readout.content)
    assert inplane < 1.0, app.readout.content  # the paper's success criterion (single view: in-plane)
    assert rotation < 3.0, app.readout.content
    assert "REGISTERED" in app.badge.content
    assert "DRRs" in app.details.content and "done" in app.details.content
    # the estimate was assessed as register --confidence assesses it, and applied (it is right)
    assessment = app.session.run.assessment
    assert assessment is not None and assessment["applied"], assessment
    assert f"Confidence {assessment['confidence']:.2f}: applied" in app.details.content
    # The status line tells what happened, with the result's numbers (not "Ready." or the start's hint):
    # the roadmap's move from the sensor pose at the iso-center, the decision, the residual to the truth.
    result = app.session.run.result
    mm, deg = correction(np.eye(4), result.patient_motion, app.session.geometry().isocenter_mm)
    assert mm > 3.0  # T4 moved the head 5.7 mm at the iso-center: the correction is of that size
    assert wait_until(lambda: app.status.content.startswith("Registered in"), 5), app.status.content
    assert app.status.content == (
        f"Registered in {result.seconds:.2f} s: motion corrected {mm:.1f} mm, {deg:.1f}° "
        f"(confidence {assessment['confidence']:.2f}, applied) · now {inplane:.2f} mm in-plane, "
        f"{rotation:.2f}° from the truth."
    )
    assert f"MOTION CORRECTED {mm:.1f} mm, {deg:.1f}°" in app.badge.content  # the badge says the same
    # The overlay and readout were refreshed live while it ran, each time with the newest of the
    # optimizer's reports: the numbers shown only grow, and every report was drawn or counted as
    # skipped (none queued). How many frames fit depends on the machine, so no rate is asserted
    # (test_live_frames_show_the_newest_report_and_count_the_skipped_ones measures the behaviour).
    reports = list(app.presenter.live_reports)[drawn_before:]
    total = len(app.session.run.iterations or [])
    if duration > 1.0:  # the presenter wakes every 0.1 s: a run of a second is drawn live at least once
        assert reports, "no live frame while the registration ran"
    assert all(b > a for a, b in zip(reports, reports[1:], strict=False)), reports
    assert not reports or reports[-1] <= total
    assert not reports or len(reports) + app.presenter.live_skipped - skipped_before == reports[-1]
    assert not any(c.disabled for c in app.carm_controls + app.motion_controls)

    # Ticking Biplane afterwards does not re-grade this single-plane result in 3-D: the readout and
    # the badge still give the in-plane grade of the same estimate.
    badge, readout = app.badge.content, app.readout.content
    try:
        app.biplane.value = True
        assert wait_until(lambda: shown(app), 30)
        assert app.readout.content == readout and app.badge.content == badge, (app.readout.content, app.badge.content)
        assert "out-of-plane" not in app.readout.content and "3-D" not in app.badge.content
    finally:
        app.biplane.value = False
    assert wait_until(lambda: shown(app), 30)


def test_live_frames_show_the_newest_report_and_count_the_skipped_ones(app: RoadmapApp) -> None:
    """Reports that arrive while the presenter is busy are not queued: its next frame draws the
    newest one and counts the others as skipped, however fast or slow the machine is."""
    from app.web.main import make_server
    from app.web.session import Session
    from app.web.session_state import RunState
    from registration.core.register import Progress

    server = make_server("127.0.0.1", 0)
    session = Session(app._phantom_data, app.session.config)  # noqa: SLF001 - the data is built already
    built = RoadmapApp(server, session)  # not started: the test is the presenter's clock
    presenter = built.presenter

    def report(n: int) -> None:  # what the registration's callback does for its n-th report
        motion = np.eye(4)
        motion[:3, 3] = (0.5 * n, -0.25 * n, 0.1 * n)
        with session.lock:
            session.run.iterations.append(n)
            session.run.similarity.append(0.1 * n)
            session.run.temperature.append(1.0)
            session.run.progress = Progress(n, 1, 1.0, motion, motion, 0.1 * n, 0.1 * n, 10 * n, 0.1 * n)

    try:
        presenter.present()  # the first frame, before any run
        with session.lock:
            session.run = RunState(running=True, iterations=[], similarity=[], temperature=[])
        for n in range(1, 8):  # seven reports while the presenter is busy elsewhere
            report(n)
        presenter.present()
        assert list(presenter.live_reports) == [7] and presenter.live_skipped == 6  # one frame: the newest
        # the scene shows report 7's pose (metres; exact: the same float64 numbers, scaled)
        np.testing.assert_allclose(built.scene.patient[0].position, np.array([3.5, -1.75, 0.7]) * 1e-3, atol=1e-12)
        time.sleep(0.1)  # past the presenter's pacing (0.8 / LIVE_HZ): a sleep never makes it sooner
        presenter.present()
        assert list(presenter.live_reports) == [7]  # nothing new: nothing drawn as live
        for n in range(8, 10):
            report(n)
        time.sleep(0.1)
        presenter.present()
        assert list(presenter.live_reports) == [7, 9] and presenter.live_skipped == 7
        assert presenter.live_skipped + len(presenter.live_reports) == 9  # every report drawn or counted
    finally:
        built.close()
        server.stop()


def test_stop_cancels_quickly(fresh: RoadmapApp) -> None:
    app = fresh
    app.table_buttons["T2"].value = True
    app.register_button.value = True
    assert wait_until(lambda: app.session.run.progress is not None, 30)  # the optimizer is under way
    assert app.session.running
    start = time.monotonic()
    app.stop_button.value = True
    assert app.session.wait(5)
    latency = time.monotonic() - start
    assert latency < 1.0, f"stop took {latency:.2f} s"  # the issue asks 0.5 s; margin for a loaded CI machine
    assert app.session.run.result is not None and app.session.run.result.stopped
    assert wait_until(lambda: not app.register_button.disabled, 3)
    result = app.session.run.result
    mm, deg = correction(np.eye(4), result.patient_motion, (0.0, 0.0, 0.0))
    assert wait_until(lambda: "stopped after" in app.status.content, 5), app.status.content
    assert app.status.content.startswith(
        f"Registration stopped after {result.seconds:.2f} s: the roadmap shows the best pose so far, "
        f"motion corrected {mm:.1f} mm, {deg:.1f}° (not assessed)"
    ), app.status.content


def test_carm_change_keeps_the_patient_in_the_room(fresh: RoadmapApp) -> None:
    app = fresh
    app.table_buttons["T1"].value = True
    truth = app.session.true_motion.copy()
    app.primary.value = 30.0
    assert app.session.settings.primary_deg == 30.0
    assert np.allclose(app.session.true_motion, truth)  # the patient did not move
    # ...but its offsets in the new view frame did, and the sliders show them.
    assert not np.allclose([s.value for s in app.offset_sliders], TABLE_I["T1"], atol=0.05)
    assert app.session.xray().geometry.primary_deg == 30.0
    assert wait_until(lambda: shown(app), 10)
    assert app._shown_geometry is not None and app._shown_geometry.primary_deg == 30.0  # noqa: SLF001


def test_absurd_input_gives_a_message_not_a_traceback(fresh: RoadmapApp) -> None:
    app = fresh
    # A 48 cm image of a 15 cm volume with the head pushed to the corner of the field.
    app.image_format.value = "48 cm"
    app.volume_format.value = "15 cm"
    for slider in app.offset_sliders:
        slider.value = slider.max
    app.secondary.value = 50.0
    assert wait_until(lambda: shown(app), 30)
    # Something the session refuses reaches the page as a message.
    app.session.run.running = True  # pretend a run is in progress
    try:
        app.offset_sliders[0].value = 1.0
    finally:
        app.session.run.running = False
    assert "Stop first" in app.status.content or "press Stop" in app.status.content
    app.register_button.value = True
    assert app.session.wait(120)
    assert wait_until(lambda: shown(app), 10)
    parse_readout(app.readout.content)  # still a readout, whatever the outcome


def test_random_stays_within_25_mm_and_10_degrees(fresh: RoadmapApp) -> None:
    app = fresh
    for _ in range(20):
        app.random_button.value = True
        o = np.array([s.value for s in app.offset_sliders])
        assert np.linalg.norm(o[:3]) <= 25.0 + 0.05
        assert np.linalg.norm(o[3:]) <= 10.0 + 0.05
        assert np.allclose(app.session.estimate, np.eye(4))  # roadmap restarts from the sensors


def test_autocorrect_reregisters_when_the_patient_moves(fresh: RoadmapApp) -> None:
    app = fresh
    app.autocorrect.value = True
    # switching it on registers at once (the patient may have moved already): let that run end
    # before the patient moves, or the move can land during it and the run read below is a
    # second one from the first's estimate (the CI saw 0.47 mm of "correction" so)
    if wait_until(lambda: app.session.running, 3):
        assert app.session.wait(120)
    app.offset_sliders[0].value = 6.0
    assert wait_until(lambda: app.session.running, 5), "auto-correct did not start"
    assert app.session.wait(120)
    assert wait_until(lambda: shown(app), 10)
    inplane, _, _ = parse_readout(app.readout.content)
    assert inplane < 1.0
    # told as Auto-correct's, with its numbers: 6 mm along the image columns corrected
    assert wait_until(lambda: app.status.content.startswith("Auto-corrected in"), 5), app.status.content
    mm, _ = correction(app.session.run.initial_motion, app.session.run.result.patient_motion, (0.0, 0.0, 0.0))
    assert abs(mm - 6.0) < 1.0 and f"motion corrected {mm:.1f} mm" in app.status.content  # < 1 mm: success
    app.autocorrect.value = False


def test_stop_before_the_first_iteration_lets_the_run_go(fresh: RoadmapApp, monkeypatch) -> None:
    """Before the optimizer's first callback nothing can interrupt it: Stop still ends the run."""
    import app.web.session as session_module

    def slow_register(*args, **kwargs):
        time.sleep(1.5)  # preparing, no callback yet
        raise AssertionError("the result of an abandoned run must be dropped")

    monkeypatch.setattr(session_module, "register", slow_register)
    app = fresh
    app.table_buttons["T1"].value = True
    app.register_button.value = True
    start = time.monotonic()
    app.stop_button.value = True
    assert time.monotonic() - start < 0.5
    assert not app.session.running and app.session.run.abandoned
    assert np.allclose(app.session.estimate, np.eye(4))  # the pose shown is kept
    assert wait_until(lambda: not app.register_button.disabled, 3)
    assert app.session.wait(5)  # the let-go worker ends on its own
    assert app.session.run.error is None


def test_a_wrong_estimate_is_withheld_and_the_roadmap_keeps_its_pose(fresh: RoadmapApp, monkeypatch) -> None:
    """The app's Register assesses its estimate (CONVENTIONS §7): here the optimizer's result is
    replaced by a pose 2 mm / 4 degrees off the truth (a wrong optimum), which the confidence
    rule withholds (the measure's peak is not there); the roadmap stays where it was."""
    import app.web.session as session_module
    from registration.core.geometry import offsets_to_matrix

    app = fresh
    app.table_buttons["T4"].value = True
    assert wait_until(lambda: shown(app), 10)
    before = app.session.estimate.copy()
    real_register = session_module.register

    def wrong_register(*args, **kwargs):
        result = real_register(*args, **kwargs)
        off = offsets_to_matrix([2.0, 0.0, 0.0, 0.0, 4.0, 0.0], app.session.geometry())
        return replace(result, patient_motion=off @ app.session.true_motion)

    monkeypatch.setattr(session_module, "register", wrong_register)
    app.register_button.value = True
    assert app.session.wait(120), "registration did not finish"
    assert wait_until(lambda: shown(app) and not app.register_button.disabled, 5)
    assessment = app.session.run.assessment
    assert assessment is not None and not assessment["applied"], assessment
    np.testing.assert_array_equal(app.session.estimate, before)  # not moved to the wrong pose
    assert "WITHHELD" in app.badge.content
    assert "withheld" in app.details.content and "the roadmap keeps its pose" in app.details.content
    # the status line: the decision, why, and how far the withheld estimate would have moved the roadmap
    wrong = app.session.run.result.patient_motion
    mm, deg = correction(before, wrong, (0.0, 0.0, 0.0))
    assert wait_until(lambda: app.status.content.startswith("Registration withheld:"), 5), app.status.content
    assert app.status.content.startswith(
        f"Registration withheld: {assessment['withheld_reason']} (confidence {assessment['confidence']:.2f})."
    )
    assert f"Motion detected ({mm:.1f} mm, {deg:.1f}°), correction withheld: the roadmap keeps its pose" in (
        app.status.content
    )
