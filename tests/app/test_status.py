"""What the status line and the badge say (app.status): the correction's numbers against
motions whose translation at the iso-center and rotation are known in closed form, and every
outcome of a run told with its decision."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from app.web.session_state import RunState
from app.web.status import badge_state, correction, moved_text, run_outcome
from registration.core.geometry import rigid, rotation_z


def _result(motion: np.ndarray, *, seconds: float = 0.42, stopped: bool = False) -> SimpleNamespace:
    """The fields of a RegistrationResult the status reads."""
    return SimpleNamespace(patient_motion=motion, seconds=seconds, stopped=stopped, at_bounds=(), drr_count=950)


def _run(motion: np.ndarray, *, iso=(0.0, 0.0, 0.0), assessment=None, **kwargs) -> RunState:
    return RunState(result=_result(motion, **kwargs), assessment=assessment, initial_motion=np.eye(4), isocenter_mm=iso)


def test_correction_of_known_motions() -> None:
    # a pure translation (3, 4, 0) mm moves every point 5 mm, whatever the iso-center
    assert correction(np.eye(4), rigid(None, (3.0, 4.0, 0.0)), (247.5, -276.0, -90.0)) == pytest.approx((5.0, 0.0))
    # 2 degrees about z through the world origin, seen at an iso-center 100 mm away on x: the
    # iso-center moves along a chord of 2 * 100 * sin(1 deg) = 3.4905 mm
    mm, deg = correction(np.eye(4), rigid(rotation_z(2.0)), (100.0, 0.0, 0.0))
    assert mm == pytest.approx(200.0 * math.sin(math.radians(1.0)), abs=1e-9)  # float64 rounding only
    assert deg == pytest.approx(2.0, abs=1e-9)
    # measured from where the roadmap was: moving back to the start is no correction at all
    start = rigid(rotation_z(5.0), (1.0, 2.0, 3.0))
    assert correction(start, start, (10.0, 0.0, 0.0)) == pytest.approx((0.0, 0.0), abs=1e-9)


def test_applied_outcome_gives_the_decision_and_the_numbers() -> None:
    run = _run(rigid(None, (3.0, 4.0, 0.0)), assessment={"confidence": 0.88, "applied": True, "withheld_reason": ""})
    text, error = run_outcome(run)
    assert not error
    assert text == "Registered in 0.42 s: motion corrected 5.0 mm, 0.0° (confidence 0.88, applied)."
    badge, _ = badge_state(run, None)
    assert badge == "MOTION CORRECTED 5.0 mm, 0.0°"  # the same words and numbers as the status line
    run.trigger = "Auto-correct"
    assert run_outcome(run)[0].startswith("Auto-corrected in 0.42 s: motion corrected 5.0 mm")


def test_withheld_outcome_says_why_and_that_the_roadmap_stays() -> None:
    reason = "the measure's peak is not at the estimate"
    run = _run(rigid(rotation_z(4.0)), iso=(100.0, 0.0, 0.0),
               assessment={"confidence": 0.12, "applied": False, "withheld_reason": reason})  # fmt: skip
    text, error = run_outcome(run)
    assert not error
    chord = 200.0 * math.sin(math.radians(2.0))  # 6.98 mm at the iso-center, 4.0 deg
    assert text.startswith(f"Registration withheld: {reason} (confidence 0.12).")
    assert f"Motion detected ({chord:.1f} mm, 4.0°), correction withheld" in text
    assert "the roadmap keeps its pose" in text
    badge, color = badge_state(run, None)
    assert badge.startswith("MOTION DETECTED, CORRECTION WITHHELD  (confidence 0.12)")


def test_stopped_failed_and_abandoned_outcomes() -> None:
    stopped = _run(rigid(None, (0.0, 0.0, 2.0)), stopped=True, seconds=0.31)
    assert run_outcome(stopped) == (
        "Registration stopped after 0.31 s: the roadmap shows the best pose so far, motion corrected 2.0 mm, "
        "0.0° (not assessed).",
        False,
    )
    failed = RunState(error="Registration failed: cannot register: the image has no usable edges")
    assert run_outcome(failed) == ("Registration failed: cannot register: the image has no usable edges", True)
    bounds = _run(rigid(None, (25.0, 0.0, 0.0)))
    bounds.error = "Not registered: the estimate ended at the search bounds (tx); the roadmap keeps its pose."
    text, error = run_outcome(bounds)
    assert error and text.startswith("Not registered: the estimate ended at the search bounds (tx)")
    abandoned = RunState(abandoned=True)
    assert run_outcome(abandoned) == (
        "Registration stopped before its first iteration: the roadmap keeps its pose.",
        False,
    )


def test_moved_text_names_the_motion_and_the_next_step() -> None:
    t4 = (4.0, 4.0, 0.0, 2.0, 3.0, 4.0)
    text = moved_text("T4 (Table I)", t4, has_truth=True, autocorrect=False, restarted=True)
    assert text == (
        "T4 (Table I): the patient moved +4.0, +4.0, +0.0 mm; +2.0, +3.0, +4.0° (5.7 mm, 5.4°); "
        "the roadmap is back at the sensor pose: press **Register**."
    )  # |(4, 4, 0)| = 5.66 mm, |(2, 3, 4)| = 5.39 deg
    auto = moved_text("Patient motion", t4, has_truth=True, autocorrect=True, restarted=False)
    assert auto.endswith("the roadmap keeps its last pose: Auto-correct registers in a moment…")
    assert moved_text("Reset", (0.0,) * 6, has_truth=True, autocorrect=False, restarted=True) == (
        "Reset: no patient motion; the roadmap is at the sensor pose."
    )
    assert "the roadmap moved by hand" in moved_text("Roadmap offset", t4, has_truth=False, autocorrect=False,
                                                      restarted=False)  # fmt: skip


def test_signed_offsets_never_read_minus_zero() -> None:
    from app.web.status import signed

    assert [signed(v, 1) for v in (-0.04, -0.0, 0.0, 0.04, -0.06, 1.25)] == ["+0.0", "+0.0", "+0.0", "+0.0", "-0.1",
                                                                             "+1.2"]  # fmt: skip
    text = moved_text("Patient motion", [0.0, -0.01, 0.0, 0.0, -0.02, 0.3], has_truth=True,
                             autocorrect=False, restarted=False)  # fmt: skip
    assert "-0.0" not in text and "+0.0, +0.0, +0.0 mm; +0.0, +0.0, +0.3°" in text
