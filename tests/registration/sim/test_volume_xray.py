"""X-ray images formed from a voxel volume: exact line integrals of the trilinear volume, motion,
devices, and the detector model of the phantom's images."""

from __future__ import annotations

import numpy as np
import pytest

from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.volume import Volume, hu_to_mu_per_mm
from registration.sim.volume_xray import VolumeAttenuator, catheter_devices, default_catheter_path
from registration.sim.xray import simulate_xray

MU_WATER = float(hu_to_mu_per_mm(0.0))


@pytest.fixture(scope="module")
def water_box() -> Volume:
    """Water in the box spanned by the voxel centers (+-40 x +-30 x +-50 mm), 2 x 2 x 5 mm voxels."""
    return Volume.from_grid(np.zeros((21, 31, 41), np.float32), (2.0, 2.0, 5.0))


def _chords(geometry: CArm, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    rr, cc = np.mgrid[0 : geometry.rows, 0 : geometry.cols]
    d = geometry.pixel_to_world(cc, rr) - geometry.source_mm
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    with np.errstate(divide="ignore"):
        t0, t1 = (lo - geometry.source_mm) / d, (hi - geometry.source_mm) / d
    return np.maximum(np.maximum(t0, t1).min(-1) - np.minimum(t0, t1).max(-1), 0.0)


@pytest.mark.parametrize("angles", [(0.0, 0.0), (30.0, 20.0), (90.0, 0.0)])
def test_line_integrals_through_a_uniform_box(water_box: Volume, angles: tuple[float, float]) -> None:
    g = CArm(*angles, rows=24, cols=24, pixel_mm=(6.0, 6.0))
    att = VolumeAttenuator(water_box)
    rr, cc = np.mgrid[0 : g.rows, 0 : g.cols]
    got = att.line_integrals(g.source_mm, g.pixel_to_world(cc, rr).reshape(-1, 3)).reshape(24, 24)
    expected = _chords(g, np.array([-40.0, -30.0, -50.0]), np.array([40.0, 30.0, 50.0])) * MU_WATER
    # a uniform volume is exact under trilinear interpolation inside its box: the midpoint rule
    # integrates the constant exactly, so only float rounding remains
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_motion_moves_the_anatomy(water_box: Volume) -> None:
    g = CArm(0.0, 0.0, rows=24, cols=24, pixel_mm=(6.0, 6.0))
    m = offsets_to_matrix([12.0, -8.0, 5.0, 0.0, 0.0, 0.0], g)
    att = VolumeAttenuator(water_box)
    rr, cc = np.mgrid[0 : g.rows, 0 : g.cols]
    got = att.line_integrals(g.source_mm, g.pixel_to_world(cc, rr).reshape(-1, 3), m).reshape(24, 24)
    shift = m[:3, 3]
    expected = _chords(g, np.array([-40.0, -30.0, -50.0]) + shift, np.array([40.0, 30.0, 50.0]) + shift) * MU_WATER
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_image_of_a_volume_with_a_catheter(water_box: Volume) -> None:
    g = CArm.for_format(15.0, pixels=48)
    att = VolumeAttenuator(water_box)
    devices = catheter_devices(default_catheter_path((0.0, 0.0, 60.0)))
    plain = simulate_xray(att, g, seed=3)
    with_device = simulate_xray(att, g, seed=3, catheter=True, devices=devices)
    assert plain.meta["source"].startswith("trilinear line integrals")
    assert with_device.meta["catheter"] and not plain.meta["catheter"]
    # same noise seed: the difference is the device (bright, i.e. more attenuation, on a thin path)
    diff = (with_device.image - plain.image)[g.field_mask()]
    assert diff.max() > 0.05 and np.mean(np.abs(diff) > 0.02) < 0.2
    with pytest.raises(ValueError, match="devices="):
        simulate_xray(att, g, catheter=True)
