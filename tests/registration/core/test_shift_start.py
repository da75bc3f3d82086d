"""The shifted start (registration.core.register.shift_start): a patient moved far across the
image, found by phase correlation, against ground truth on the phantom (images from the analytic
head, not from the renderer that scores them)."""

import numpy as np
import pytest

from registration.core.assess import veto
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, apply, offsets_to_matrix
from registration.core.register import DepthOptions, RegistrationOptions, StartOptions, register
from registration.core.register.shift_start import view_shift_mm


@pytest.fixture(scope="module")
def scene():
    from registration.sim.phantom import make_head_phantom, registration_volume

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    return volume, DRRRenderer(volume, levels=3), CArm.for_format(27.0, pixels=256, primary_deg=20.0)


def _image(geometry: CArm, truth: np.ndarray):
    from registration.sim.phantom import make_head_phantom
    from registration.sim.xray import simulate_xray

    return simulate_xray(make_head_phantom(seed=0, contrast=False), geometry, motion=truth, kind="exposure", seed=1)


def test_the_shift_across_the_beam_is_found(scene) -> None:
    volume, renderer, geometry = scene
    truth = offsets_to_matrix((38.0, -22.0, 0.0, 0.0, 0.0, 0.0), geometry)
    shift = view_shift_mm(renderer, _image(geometry, truth), np.eye(4), level=2)
    iso = np.asarray(geometry.isocenter_mm)
    expected = apply(truth, iso) - iso
    # 43.9 mm across the beam found within 2 mm (measured 0.4): the ~128 px images at the coarse
    # level have 0.8 mm pixels at the iso-center, the phase correlation a quarter pixel
    assert np.linalg.norm(shift - expected) < 2.0, (shift, expected)


def test_a_patient_beyond_the_box_registers_from_the_shift_and_is_withheld(scene) -> None:
    volume, renderer, geometry = scene
    truth = offsets_to_matrix((38.0, -22.0, 0.0, 2.0, -1.0, 3.0), geometry)
    xray = _image(geometry, truth)
    result = register(volume, xray, truth=truth, seed=0)
    assert result.start_shift_mm > 25.0 and result.to_dict()["start_shift_mm"] == result.start_shift_mm
    assert result.residual.success, result.residual  # the paper's in-plane criterion (measured 0.11 mm)
    assert "image shift" in veto(result)  # beyond the box around the machine-based pose: a look first
    # without it and without the second search the search misses (measured 39.4 mm in-plane and
    # 21 deg off after one walk)
    never = StartOptions(shift_mm=None, recheck_mm=None)
    # (nor searched again along the beam: one search alone, whose DRRs the second search's exceed)
    alone = RegistrationOptions(start=never, depth=DepthOptions(restart_beyond_mm=None))
    off = register(volume, xray, truth=truth, seed=0, options=alone)
    assert not off.residual.success and off.start_shift_mm == 0.0
    # without the shifted start, the image shift left at that wrong estimate starts a second search
    # from the shift, whose better measure is kept
    again = register(volume, xray, truth=truth, seed=0, options=RegistrationOptions(start=StartOptions(shift_mm=None)))
    assert again.second_search and again.start_shift_mm > 25.0 and again.residual.success, again.residual
    assert again.drr_count > off.drr_count  # both searches' DRRs are counted
    assert "image shift" in veto(again)  # still beyond the box around the machine-based pose


def test_within_the_clinical_offsets_the_start_is_the_machine_pose(scene) -> None:
    volume, renderer, geometry = scene
    truth = offsets_to_matrix((4.0, 4.0, 0.0, 2.0, 3.0, 4.0), geometry)  # Table I's T4
    result = register(volume, _image(geometry, truth), truth=truth, seed=0, renderer=renderer)
    assert result.start_shift_mm == 0.0 and "start_shift_mm" not in result.to_dict()
    assert result.residual.success
