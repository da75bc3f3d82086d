"""A second search held near the poses picked landmarks allow, when the first left them.

Far from the machine-based pose the views may see only part of the head, and the measure can
have optima several millimetres to centimetres from the truth that fit the images as well as it
or better. A landmark start lies within a few millimetres of the truth, yet the search from it
(a box of +-30 mm / 15 deg around it) can settle on such an optimum: the estimate then moves the
landmarks' projections further than their picking allows, and their check
(:meth:`~registration.core.landmarks.LandmarkStart.veto`) withholds it.

For two or more views such an estimate is replaced by a second search from the landmark start in
which every pose that moves the landmarks beyond the check's limit costs more
(:meth:`~registration.core.landmarks.LandmarkStart.wall`, ``StartOptions.landmark_wall``): it neither
starts from the image shift nor searches again from it, and its estimate is fine-polished under
the same wall. Its estimate is shown but never applied automatically
(:func:`registration.core.assess.veto`): the images alone preferred a pose the landmarks do not
allow, so a user looks. Estimates that keep to the landmarks are untouched and cost nothing more.
Decision record: ``docs/decisions/2026-12-06-landmark-wall.md``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from registration.core.register.inputs import Inputs
from registration.core.register.result import RegistrationResult


def held_by_landmarks(
    search_held: Callable[[], RegistrationResult], inputs: Inputs, result: RegistrationResult
) -> RegistrationResult:
    """``result``, or, when it moves ``inputs.landmarks`` further than their check allows (and was
    not stopped), the held search's estimate (``search_held()``) carrying both searches' costs
    and why (``held_by_landmarks``)."""
    landmarks = inputs.landmarks
    if landmarks is None or result.stopped:
        return result
    moved = landmarks.moved_mm(result.patient_motion)
    if moved <= landmarks.limit_mm():
        return result
    held = search_held()
    if held.stopped:
        return result
    held.held_by_landmarks = (
        f"the first estimate moved the landmarks {moved:.1f} mm, more than their check allows: the search ran "
        "again from their start, held near them"
    )
    held.drr_count = result.drr_count + held.drr_count
    held.seconds = max(result.seconds, held.seconds)  # both timed from the registration's start
    held.similarity_trace = list(result.similarity_trace) + list(held.similarity_trace)
    held.stages = result.stages + tuple(replace(c, stage=f"held by the landmarks: {c.stage}") for c in held.stages)
    return held
