"""The fine polish (registration.core.register.fine_polish): two views' estimate found away from the
machine-based pose is polished once more on the full images and the volume's own grid."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from registration.core.geometry import offsets_to_matrix, rigid
from registration.core.metrics import residuals
from registration.core.register import RegistrationOptions, StartOptions
from registration.core.register.fine_polish import BEAM_LINE_EVALUATIONS, far_from_machine, fine_polish, started_away
from registration.core.register.inputs import check_inputs
from tests.registration.core.two_views import phantom_pair


@pytest.fixture(scope="module")
def pair():
    return phantom_pair((4.0, 4.0, -3.0, 2.0, 3.0, 4.0))


def test_an_estimate_from_far_away_is_polished_onto_the_truth(pair) -> None:
    volume, xrays, truth, options, right = pair
    assert right.residual.success and not started_away(right)  # started at the machine-based pose
    inputs = check_inputs(volume, xrays, None, truth, None, options)
    # the estimate a search from the image shift might leave: 1.2 mm and 0.8 deg off the truth
    off = offsets_to_matrix((0.8, -0.6, 0.7, 0.5, -0.4, 0.3), right.geometry) @ truth
    before = residuals(off, truth, right.geometry, optimizes_tz=True)
    far = replace(right, patient_motion=off, start_shift_mm=40.0)
    polished = fine_polish(inputs, far, options, callback=None, start_s=time.perf_counter())
    # the phantom's own volume at level 0 (1.4 mm voxels), 256-px images (1 mm pixels at the
    # iso-center): a polish from 1.2 mm ends within a few tenths of the truth
    assert before.translation_mm > 1.0 and polished.residual.translation_mm < 0.4, polished.residual
    assert polished.residual.rotation_deg < before.rotation_deg
    assert polished.fine_polished and polished.to_dict()["fine_polished"] is True
    # its stages after the search's: the beam scan and the polish, twice when the scan moved the
    # estimate (at most BEAM_SCAN_ROUNDS times), then the line search along each beam
    added = polished.stages[len(far.stages) :]
    names = [s.stage.split(" at ")[0] for s in added]
    rounds = (["beam scan", "fine polish"], ["beam scan", "fine polish"] * 2)
    assert names in [r + ["line search"] for r in rounds], names
    assert added[1].stage.startswith("fine polish at 256 px, volume level 0")
    assert polished.drr_count == far.drr_count + sum(s.drrs for s in added) > far.drr_count
    # the offsets stay relative to the search's own start: they move by the polish's correction
    moved = np.abs(np.asarray(polished.offsets) - np.asarray(far.offsets))
    assert np.all(moved < 1.6) and moved.max() > 0.1


def test_the_polish_runs_only_after_a_start_away_with_two_views(pair) -> None:
    volume, xrays, truth, options, right = pair
    inputs = check_inputs(volume, xrays, None, truth, None, options)
    now = time.perf_counter()
    assert fine_polish(inputs, right, options, callback=None, start_s=now) is right  # machine-based start
    walked = replace(right, walk_hops=1)
    off = RegistrationOptions(start=StartOptions(fine_polish_evaluations=0))
    assert fine_polish(inputs, walked, off, callback=None, start_s=now) is walked
    stopped = replace(walked, stopped=True)
    assert fine_polish(inputs, stopped, options, callback=None, start_s=now) is stopped
    one = check_inputs(volume, xrays[:1], None, truth, None, options)
    assert fine_polish(one, walked, options, callback=None, start_s=now) is walked
    # a landmark start is not the machine-based pose: its estimate is polished like one from away
    landmarks = RegistrationOptions(start=StartOptions(from_landmarks=True))
    polished = fine_polish(inputs, right, landmarks, callback=None, start_s=now)
    assert polished is not right and polished.fine_polished
    assert "from landmarks: a fine polish" in landmarks.start.describe()
    with pytest.raises(ValueError, match="fine_polish_px must be >= 16"):
        StartOptions(fine_polish_px=8)


def test_an_estimate_far_from_the_machine_is_polished_though_its_search_started_there(pair) -> None:
    volume, xrays, truth, options, right = pair
    # the machine-based pose 30 mm from the truth (plane A's x and z): the search started there
    # and found the patient inside its box, 30 mm away
    machine = offsets_to_matrix((18.0, 0.0, 24.0, 0.0, 0.0, 0.0), right.geometry) @ truth
    inputs = check_inputs(volume, xrays, machine, truth, None, options)
    off = offsets_to_matrix((0.8, -0.6, 0.7, 0.5, -0.4, 0.3), right.geometry) @ truth
    far = replace(right, patient_motion=off)
    assert not started_away(far) and far_from_machine(far, machine, 25.0)  # 30 mm >= 25 mm
    assert not far_from_machine(far, machine, 31.0) and not far_from_machine(far, machine, None)
    now = time.perf_counter()
    polished = fine_polish(inputs, far, options, callback=None, start_s=now)
    # as from the image shift above: from 1.2 mm to within a few tenths of the truth
    assert polished.fine_polished and polished.residual.translation_mm < 0.4, polished.residual
    # with the rule off, or the machine-based pose near the estimate, it is left as it is
    only_away = RegistrationOptions(start=StartOptions(fine_polish_beyond_mm=None))
    assert fine_polish(inputs, far, only_away, callback=None, start_s=now) is far
    near = check_inputs(volume, xrays, None, truth, None, options)
    assert fine_polish(near, far, options, callback=None, start_s=now) is far
    assert "or 25 mm or more from it: a fine polish" in options.start.describe()
    with pytest.raises(ValueError, match="fine_polish_beyond_mm"):
        StartOptions(fine_polish_beyond_mm=0.0)


def test_the_beam_scan_brings_back_a_depth_left_off_along_one_beam(pair) -> None:
    volume, xrays, truth, options, right = pair
    inputs = check_inputs(volume, xrays, None, truth, None, options)
    # 8 mm off along plane A's central ray (which plane A barely sees), and a little elsewhere
    along = np.asarray(xrays[0].geometry.direction)
    off = rigid(None, 8.0 * along) @ offsets_to_matrix((0.3, -0.2, 0.0, 0.3, -0.2, 0.2), right.geometry) @ truth
    far = replace(right, patient_motion=off, start_shift_mm=40.0)
    now = time.perf_counter()
    scanned = fine_polish(inputs, far, options, callback=None, start_s=now)
    # the scan's 1.5 mm steps reach within 0.75 mm of the truth along the ray, the polish the rest
    # (as from 1.2 mm above: within a few tenths)
    assert scanned.residual.translation_mm < 0.4, scanned.residual
    assert scanned.stages[len(far.stages)].stage.startswith("beam scan at 256 px, volume level 0")
    # without it (and without the line search after the polish) a polish of +-3 mm cannot get there
    without = RegistrationOptions(start=StartOptions(beam_scan_mm=None, beam_line_mm=None, fine_polish_reach_mm=3.0))
    alone = fine_polish(inputs, far, without, callback=None, start_s=now)
    assert alone.residual.translation_mm > 4.0, alone.residual
    assert not any(s.stage.startswith("beam scan") for s in alone.stages)
    assert "moved along each view's beam within +-15 mm" in options.start.describe()


def test_the_polish_reaches_an_estimate_several_millimetres_off_in_every_direction(pair) -> None:
    volume, xrays, truth, options, right = pair
    inputs = check_inputs(volume, xrays, None, truth, None, options)
    # 7 mm off, across both beams and along them, and 1 deg: no single beam's line leads back, so
    # neither the beam scan nor the line search after the polish (both off here) would
    off = offsets_to_matrix((4.0, -3.0, 4.5, 0.6, -0.5, 0.6), right.geometry) @ truth
    far = replace(right, patient_motion=off, start_shift_mm=40.0)
    start = StartOptions(beam_scan_mm=None, beam_line_mm=None)
    now = time.perf_counter()
    wide = fine_polish(inputs, far, replace(options, start=start), callback=None, start_s=now)
    # the default reach (+-10 mm / 5 deg) holds the truth: within a few tenths, as from 1.2 mm above
    assert start.fine_polish_reach_mm >= 7.0 and wide.residual.translation_mm < 0.4, wide.residual
    # a polish bounded at +-3 mm / 2 deg stops at its bounds (tx 4 mm and tz 4.5 mm lie beyond
    # them): it ends 1.8 mm off here, beyond the 1 mm criterion by more than the polish's own spread
    short = replace(start, fine_polish_reach_mm=3.0, fine_polish_reach_deg=2.0)
    bounded = fine_polish(inputs, far, replace(options, start=short), callback=None, start_s=now)
    assert bounded.residual.translation_mm > 1.5, bounded.residual
    assert "120 evaluations over +-10 mm / 5 deg (COBYQA)" in options.start.describe()


def test_a_second_scan_round_is_prepared_around_where_the_first_ended(pair, monkeypatch) -> None:
    """The level-0 preparation covers one round's reach (the scan and the polish) around its
    start; a second round starts where the first ended, up to the scan's 15 mm further, so its
    volume is prepared again around that start (a render beyond the crop would miss anatomy)."""
    import sys

    module = sys.modules["registration.core.register.fine_polish"]
    centers = []
    real = module.Reach

    class Recording:  # the reach each preparation is made for, and around which pose
        @staticmethod
        def of_search(*args, initial_motion, **kwargs):  # noqa: ANN002, ANN003, ANN205
            centers.append(np.asarray(initial_motion, dtype=np.float64).copy())
            return real.of_search(*args, initial_motion=initial_motion, **kwargs)

    monkeypatch.setattr(module, "Reach", Recording)
    volume, xrays, truth, options, right = pair
    inputs = check_inputs(volume, xrays, None, truth, None, options)
    along = np.asarray(xrays[0].geometry.direction)
    off = rigid(None, 8.0 * along) @ truth  # the first scan moves it about 8 mm: a second round runs
    scanned = fine_polish(inputs, replace(right, patient_motion=off, start_shift_mm=40.0), options, callback=None,
                          start_s=time.perf_counter())  # fmt: skip
    rounds = sum(s.stage.startswith("beam scan") for s in scanned.stages)
    assert rounds == 2 and len(centers) == 2, (rounds, len(centers))
    np.testing.assert_allclose(centers[0], off)
    iso = np.asarray(xrays[0].geometry.isocenter_mm)
    # the second preparation lies where the first round ended: at least one scan step away
    assert np.linalg.norm(centers[1][:3, :3] @ iso + centers[1][:3, 3] - (off[:3, :3] @ iso + off[:3, 3])) >= 1.5


def test_the_line_search_climbs_the_depth_a_short_polish_left(pair) -> None:
    volume, xrays, truth, options, right = pair
    inputs = check_inputs(volume, xrays, None, truth, None, options)
    # 2 mm off along plane A's central ray, which plane A barely sees; a polish of a few
    # evaluations (no beam scan) stands for one whose trust region shrank before it climbed there
    along = np.asarray(xrays[0].geometry.direction)
    far = replace(right, patient_motion=rigid(None, 2.0 * along) @ truth, start_shift_mm=40.0)
    short = StartOptions(beam_scan_mm=None, fine_polish_evaluations=3)
    now = time.perf_counter()
    left = fine_polish(inputs, far, replace(options, start=replace(short, beam_line_mm=None)), callback=None,
                       start_s=now)  # fmt: skip
    lined = fine_polish(inputs, far, replace(options, start=short), callback=None, start_s=now)
    assert left.residual.translation_mm > 1.5, left.residual  # the short polish barely moved
    # the line search's tolerance is 0.1 mm along the ray; plane B (lateral, 1 mm pixels at the
    # iso-center) holds the depth to a few tenths
    assert lined.residual.translation_mm < 0.5, lined.residual
    assert lined.stages[-1].stage.startswith("line search at 256 px, volume level 0")
    assert 0 < lined.stages[-1].drrs <= 2 * 2 * (BEAM_LINE_EVALUATIONS + 1)  # two views, each image per view
    assert "a line search along each view's beam within +-3 mm" in options.start.describe()
    with pytest.raises(ValueError, match="beam_line_mm"):
        StartOptions(beam_line_mm=-1.0)
