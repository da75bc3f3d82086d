"""The translation-first candidate (registration.core.register.translation_first): two views' search
from the image shift is compared with a candidate that first moves the patient only."""

from __future__ import annotations

import time
from dataclasses import replace

import pytest

from registration.core.geometry import offsets_to_matrix, rigid
from registration.core.metrics import residuals
from registration.core.register import RegistrationOptions, StartOptions
from registration.core.register.inputs import check_inputs
from tests.registration.core.two_views import phantom_pair


@pytest.fixture(scope="module")
def pair():
    # a patient moved, hardly turned: what a table move or a repositioned head leaves
    return phantom_pair((6.0, -5.0, 4.0, 0.8, -0.6, 0.5))


def _from_the_shift(volume, xrays, truth, options, right):  # noqa: ANN001, ANN202
    """Inputs started where an image shift 9 mm short of the patient puts them, and a search's
    estimate from there that turned the head 8 degrees and missed by 6 mm."""
    from registration.core.register.translation_first import translation_first

    shifted_start = rigid(None, (5.0, -4.0, 6.0)) @ truth
    inputs = check_inputs(volume, xrays, shifted_start, truth, None, options)
    wrong = offsets_to_matrix((3.0, 4.0, -3.0, 6.0, -5.0, 2.0), right.geometry) @ truth
    far = replace(right, patient_motion=wrong, start_shift_mm=40.0)
    return inputs, far, translation_first


def test_a_wrong_search_from_the_image_shift_gives_way_to_the_translation_first_candidate(pair) -> None:
    volume, xrays, truth, options, right = pair
    assert right.residual.success_total and not right.start_shift_mm  # clinical offsets: no shifted start
    inputs, far, translation_first = _from_the_shift(volume, xrays, truth, options, right)
    before = residuals(far.patient_motion, truth, far.geometry, optimizes_tz=True)
    kept = translation_first(inputs, far, options, callback=None, start_s=time.perf_counter())
    # the start's rotation is within a degree of the patient's: the translations alone reach the
    # basin, and the polish at 128 px (2 mm pixels at the iso-center) ends within a millimetre
    assert before.translation_mm > 5.0 and before.rotation_deg > 7.0
    assert kept.translation_first and kept.to_dict()["translation_first"] is True
    assert kept.residual.translation_mm < 1.0 and kept.residual.rotation_deg < 1.0, kept.residual
    names = [c.stage for c in kept.stages[len(far.stages) :]]
    assert names[0].startswith("translations alone at 64 px") and names[1].startswith("candidate's polish at 128 px")
    assert kept.drr_count > far.drr_count + 80  # its searches are counted


def test_a_right_search_keeps_its_estimate_or_an_equally_right_one(pair) -> None:
    volume, xrays, truth, options, right = pair
    inputs, far, translation_first = _from_the_shift(volume, xrays, truth, options, right)
    near = replace(far, patient_motion=right.patient_motion)
    kept = translation_first(inputs, near, options, callback=None, start_s=time.perf_counter())
    found = residuals(kept.patient_motion, truth, far.geometry, optimizes_tz=True)
    # both the search's estimate and any candidate kept over it fit the truth within the criterion
    assert found.translation_mm < 1.0 and found.rotation_deg < 1.0
    assert kept.drr_count > near.drr_count


def test_the_candidate_runs_only_for_two_views_from_the_image_shift(pair) -> None:
    volume, xrays, truth, options, right = pair
    inputs, far, translation_first = _from_the_shift(volume, xrays, truth, options, right)
    now = time.perf_counter()
    assert translation_first(inputs, right, options, callback=None, start_s=now) is right  # machine-based start
    off = RegistrationOptions(start=StartOptions(translation_first_evaluations=0))
    assert translation_first(inputs, far, off, callback=None, start_s=now) is far
    stopped = replace(far, stopped=True)
    assert translation_first(inputs, stopped, options, callback=None, start_s=now) is stopped
    one = check_inputs(volume, xrays[:1], None, truth, None, options)
    assert translation_first(one, far, options, callback=None, start_s=now) is far
    assert "translations alone" in options.start.describe()
    assert "translations alone" not in off.start.describe()
    with pytest.raises(ValueError, match="translation_first_evaluations must be >= 0"):
        StartOptions(translation_first_evaluations=-1)


def test_register_says_when_the_candidate_was_kept(pair, capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli.register_command import say_result

    _volume, _xrays, _truth, _options, right = pair
    kept = replace(right, start_shift_mm=41.0, beyond_box=True, translation_first=True, fine_polished=True)
    say_result(kept, 2)
    said = " ".join(capsys.readouterr())
    assert "the search started there; check the estimate by eye" in said
    assert "translation alone from there fit the images better than the full search's: it was kept" in said
    say_result(right, 2)
    assert "translation alone" not in " ".join(capsys.readouterr())
