"""What the status line and the badge say about a registration: one place for the words.

The status line (under Register) tells what last happened: a registration's outcome, the
patient moving, a run playing; the badge (above the readout) tells the state of the roadmap.
Both use the product's words (CONVENTIONS §7): **motion corrected** (the estimate was applied)
or **motion detected, correction withheld** (the roadmap keeps its pose), with the numbers of
the result. No viser here: plain functions of the run's state, tested on their own.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from registration.core.geometry import apply, invert_rigid, rotation_angle_deg

if TYPE_CHECKING:
    from app.web.session_state import RunState
    from registration.core.metrics import Residual


def correction(before: np.ndarray, after: np.ndarray, isocenter_mm: Sequence[float]) -> tuple[float, float]:
    """How far the roadmap moves from pose ``before`` to ``after`` (4x4 patient motions):
    the translation at the iso-center (mm, CONVENTIONS §4) and the rotation angle (degrees)."""
    change = np.asarray(after, np.float64) @ invert_rigid(np.asarray(before, np.float64))
    iso = np.asarray(isocenter_mm, np.float64)
    return float(np.linalg.norm(apply(change, iso) - iso)), float(rotation_angle_deg(change))


def corrected_text(mm: float, deg: float) -> str:
    """'motion corrected 2.1 mm, 1.3°' (the product's message, as the Play run draws it)."""
    return f"motion corrected {mm:.1f} mm, {deg:.1f}°"


def truth_text(residual: Residual | None, *, biplane: bool) -> str:
    """' · 0.03 mm in-plane, 0.25° from the truth' (empty without ground truth)."""
    if residual is None:
        return ""
    where = f"{residual.translation_mm:.2f} mm (3-D)" if biplane else f"{residual.inplane_mm:.2f} mm in-plane"
    return f" · now {where}, {residual.rotation_deg:.2f}° from the truth"


def run_change(run: RunState) -> tuple[float, float] | None:
    """(mm, deg) from the run's start to its result's pose; None without a result."""
    result = run.result
    if result is None or run.initial_motion is None:
        return None
    return correction(run.initial_motion, np.asarray(result.patient_motion), run.isocenter_mm)


def run_outcome(run: RunState, residual: Residual | None = None, *, biplane: bool = False) -> tuple[str, bool]:
    """The status line once a registration ended, and whether it is an error.

    ``residual``: the roadmap's pose now against the truth (the phantom), None without truth.
    Every branch says what the roadmap does (moved to the estimate, or kept its pose) and gives
    the result's numbers; ``run.trigger`` ("Register", "Auto-correct") says who started it.
    """
    who = "Auto-correct" if run.trigger == "Auto-correct" else "Registration"
    truth = truth_text(residual, biplane=biplane)
    if run.abandoned:
        return f"{who} stopped before its first iteration: the roadmap keeps its pose{truth}.", False
    result = run.result
    if result is None:
        return run.error or f"{who} ended without a result: the roadmap keeps its pose.", True
    mm, deg = run_change(run) or (0.0, 0.0)
    seconds = f"{result.seconds:.2f} s"
    if run.error:  # no overlap, or the estimate at the search bounds: never applied
        return f"{run.error} (after {seconds}){truth}", True
    assessment = run.assessment
    if result.stopped:
        return (
            f"{who} stopped after {seconds}: the roadmap shows the best pose so far, {corrected_text(mm, deg)} "
            f"(not assessed){truth}.",
            False,
        )
    if assessment is not None and not assessment["applied"]:
        return (
            f"{who} withheld: {assessment['withheld_reason']} (confidence {assessment['confidence']:.2f}). "
            f"Motion detected ({mm:.1f} mm, {deg:.1f}°), correction withheld: the roadmap keeps its pose{truth}.",
            False,
        )
    how = "Auto-corrected" if who == "Auto-correct" else "Registered"
    confidence = (
        f"confidence {assessment['confidence']:.2f}, applied"
        if assessment is not None
        else "confidence not assessed (see the log), applied"
    )
    return f"{how} in {seconds}: {corrected_text(mm, deg)} ({confidence}){truth}.", False


#: Badge colours: the decision (green applied, orange withheld, red wrong or failed, grey idle).
GREEN, ORANGE, RED, BLUE, GRAY = "#2b8a3e", "#e8590c", "#c92a2a", "#1c7ed6", "#495057"


def badge_state(run: RunState, residual: Residual | None, *, biplane: bool = False) -> tuple[str, str]:
    """The badge's text and colour for the roadmap shown now: the last registration's decision
    in the status line's words, graded against the truth when there is one (the phantom)."""
    criterion = " 3-D" if biplane else ""
    grade = ""
    if residual is not None:
        grade = (
            f"REGISTERED  (< 1 mm{criterion}, < 3°)" if residual.success else f"MISALIGNED  (≥ 1 mm{criterion} or ≥ 3°)"
        )
    mark = "" if residual is None else ("✓ " if residual.success else "✗ ")
    result, assessment = run.result, run.assessment
    if run.running:
        return "REGISTERING…", BLUE
    if result is not None and getattr(result, "at_bounds", ()):
        return "✗ NOT REGISTERED  (estimate at the search bounds)", RED
    if result is not None and run.error:
        return "✗ NOT REGISTERED", RED
    if result is not None and assessment is not None and not assessment["applied"]:
        return f"MOTION DETECTED, CORRECTION WITHHELD  (confidence {assessment['confidence']:.2f})", ORANGE
    if result is not None:
        mm, deg = run_change(run) or (0.0, 0.0)
        what = "STOPPED: BEST POSE SO FAR" if result.stopped else "MOTION CORRECTED"
        text = f"{mark}{what} {mm:.1f} mm, {deg:.1f}°" + (f"  ·  {grade}" if grade else "")
        if residual is None:
            return text, GREEN if not result.stopped else GRAY
        return text, GREEN if residual.success else RED
    # no registration since the roadmap was last placed: the C-arm's sensors only
    if residual is None:
        return "SENSOR ALIGNMENT ONLY", GRAY
    if residual.success:
        return f"✓ SENSOR ALIGNMENT ONLY  (aligned: < 1 mm{criterion}, < 3°)", GRAY
    return f"✗ MISALIGNED  (≥ 1 mm{criterion} or ≥ 3°; sensor alignment only)", RED


def signed(value: float, digits: int) -> str:
    """``value`` with its sign and ``digits`` decimals, never "-0.0" (a value that rounds to 0 is +0)."""
    v = round(float(value), digits)
    return f"{(v if v != 0 else 0.0):+.{digits}f}"


def moved_text(what: str, offsets: Sequence[float], *, has_truth: bool, autocorrect: bool, restarted: bool) -> str:
    """The status line after the motion controls moved the patient (the phantom) or the roadmap
    (the user's data, which has no truth). ``what``: the control ("T4 (Table I)", "Random",
    "Reset", "Patient motion"); ``offsets``: the six offsets now (mm, deg, view frame);
    ``restarted``: the roadmap went back to the sensor pose."""
    o = [float(v) for v in offsets]
    t_mm, r_deg = float(np.linalg.norm(o[:3])), float(np.linalg.norm(o[3:]))
    amount = f"{', '.join(signed(v, 1) for v in o[:3])} mm; {', '.join(signed(v, 1) for v in o[3:])}°"
    if not has_truth:
        if t_mm == 0.0 and r_deg == 0.0:
            return f"{what}: the roadmap is back at the sensor pose."
        return f"{what}: the roadmap moved by hand to {amount} (your data: the controls move the roadmap)."
    if t_mm == 0.0 and r_deg == 0.0:
        tail = "the roadmap is at the sensor pose." if restarted else "the roadmap keeps its last pose."
        return f"{what}: no patient motion; {tail}"
    next_step = "Auto-correct registers in a moment…" if autocorrect else "press **Register**."
    pose = "the roadmap is back at the sensor pose" if restarted else "the roadmap keeps its last pose"
    return f"{what}: the patient moved {amount} ({t_mm:.1f} mm, {r_deg:.1f}°); {pose}: {next_step}"
