"""The skull-and-spine check (registration.core.skull_spine): how far the whole volume's fit
lies from a given estimate, against ground truth on the phantom (images from the analytic head,
not from the renderer that scores them)."""

import numpy as np
import pytest

from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.skull_spine import skull_spine_check


@pytest.fixture(scope="module")
def scene():
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    geometry = CArm.for_format(27.0, pixels=256, primary_deg=20.0)
    truth = offsets_to_matrix((3.0, -2.0, 0.0, 2.0, -1.0, 3.0), geometry)
    xray = simulate_xray(make_head_phantom(seed=0, contrast=False), geometry, motion=truth, kind="exposure", seed=1)
    return volume, DRRRenderer(volume, levels=3), geometry, truth, xray


def test_a_right_estimate_agrees(scene) -> None:
    volume, renderer, _, truth, xray = scene
    check = skull_spine_check(volume, xray, truth, renderer=renderer)
    # the whole volume's fit stays at the truth: within 0.3 mm in-plane (this 27 cm / 256 px
    # frame's polish jitter, 0.53 mm pixels at the iso-center) and 0.5 deg
    assert check.agree and check.shift_mm < 0.3 and check.rotation_deg < 0.5, check
    assert check.criterion == "in-plane" and check.drr_count > 0
    assert "agree" in check.message() and check.to_dict()["agree"] is True


def test_an_estimate_pulled_away_disagrees_by_the_pull(scene) -> None:
    """An estimate 3 mm and 2 deg off the anatomy the whole volume sees (as a cranium's estimate
    is, seen from a spine that moved): the check finds the whole volume's fit back at the truth,
    3 mm and 2 deg away."""
    volume, renderer, geometry, truth, xray = scene
    pulled = offsets_to_matrix((3.0, 0.0, 0.0, 0.0, 0.0, 2.0), geometry) @ truth
    check = skull_spine_check(volume, xray, pulled, renderer=renderer)
    assert not check.agree and "DISAGREE" in check.message()
    # the fit returns to the truth: 3 mm in-plane and 2 deg, each within 0.4 (the polish's jitter)
    assert check.shift_mm == pytest.approx(3.0, abs=0.4) and check.rotation_deg == pytest.approx(2.0, abs=0.4), check
    back = np.asarray(check.whole_motion)
    assert np.linalg.norm(back[:3, 3] - truth[:3, 3]) < 1.0
