"""Honest X-ray image formation: noise, dose, blur, collimation, devices, validation."""

from __future__ import annotations

import numpy as np
import pytest

from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.images import XRayImage
from registration.sim.phantom import HeadPhantom, make_head_phantom
from registration.sim.xray import device_phantom, simulate_xray

PIXELS = 64  # small images keep the file fast; the physics does not depend on the size


@pytest.fixture(scope="module")
def head() -> HeadPhantom:
    return make_head_phantom(contrast=False)


@pytest.fixture(scope="module")
def geom() -> CArm:
    return CArm.for_format(27, pixels=PIXELS, primary_deg=20.0)


def test_outside_the_field_is_zero_and_masked(head: HeadPhantom, geom: CArm) -> None:
    img = simulate_xray(head, geom)
    np.testing.assert_array_equal(img.mask, geom.field_mask())
    assert np.all(img.image[~img.mask] == 0.0)
    assert not img.mask[0, 0] and img.mask[PIXELS // 2, PIXELS // 2]
    assert img.image.dtype == np.float32 and img.image.shape == (PIXELS, PIXELS)
    assert img.image[img.mask].max() > 2.0  # through the head: attenuation is large


def test_noise_free_limit_is_the_line_integral(head: HeadPhantom, geom: CArm) -> None:
    img = simulate_xray(head, geom, photons_per_pixel=1e12, blur_px=0.0, supersample=1)
    rr, cc = np.nonzero(img.mask)
    exact = head.line_integrals(geom.source_mm, geom.pixel_to_world(cc, rr))
    # at 1e12 photons the Poisson noise is ~1e-6 relative even behind the densest bone
    # (transmission > 1e-3), and the electronic noise (~1.5 photons) vanishes beside it
    np.testing.assert_allclose(img.image[rr, cc], exact, atol=1e-3)


def test_fluoro_is_noisier_than_exposure(head: HeadPhantom, geom: CArm) -> None:
    def noise(kind: str) -> float:
        a = simulate_xray(head, geom, kind=kind, seed=1)
        b = simulate_xray(head, geom, kind=kind, seed=2)
        return float(np.std((a.image - b.image)[a.mask]))

    fluoro, exposure = noise("fluoro"), noise("exposure")
    # 20x the dose: quantum noise sqrt(20) ~ 4.5x lower; demand a clear 3x
    assert fluoro > 3.0 * exposure > 0.0


def test_same_seed_same_image(head: HeadPhantom, geom: CArm) -> None:
    a = simulate_xray(head, geom, seed=5)
    b = simulate_xray(head, geom, seed=5)
    np.testing.assert_array_equal(a.image, b.image)
    c = simulate_xray(head, geom, seed=6)
    assert not np.array_equal(a.image, c.image)


def test_moved_phantom_changes_the_image(head: HeadPhantom, geom: CArm) -> None:
    still = simulate_xray(head, geom, kind="exposure", seed=1)
    motion = offsets_to_matrix([5.0, 0.0, 0.0, 0.0, 0.0, 0.0], geom)
    moved = simulate_xray(head, geom, kind="exposure", seed=1, motion=motion)
    # a 5 mm shift moves every bone edge by ~ 5 * 1.48 / 4.2 ~ 1.8 pixels: a large change
    # against the exposure noise (~0.01)
    assert float(np.mean(np.abs(moved.image - still.image)[still.mask])) > 0.05
    assert moved.meta["motion"] == motion.tolist()


def test_catheter_adds_attenuation_the_volume_lacks(head: HeadPhantom) -> None:
    geom = CArm.for_format(27, pixels=PIXELS)
    plain = simulate_xray(head, geom, kind="exposure", seed=3, blur_px=0.0)
    device = simulate_xray(head, geom, kind="exposure", seed=3, blur_px=0.0, catheter=True)
    diff = (device.image - plain.image)[plain.mask]
    # the guidewire tip (platinum) adds ~ 0.36 mm * 7 / mm ~ 2.5 along its centerline; a
    # 4 mm pixel averages it in intensity, still leaving a clear excess
    assert diff.max() > 0.1
    devices = device_phantom(head)
    assert devices.n_primitives > 10


def test_downsample(head: HeadPhantom, geom: CArm) -> None:
    img = simulate_xray(head, geom)
    half = img.downsample(2)
    assert half.image.shape == (PIXELS // 2, PIXELS // 2)
    assert half.geometry.rows == PIXELS // 2
    assert half.geometry.pixel_mm[0] == pytest.approx(2 * geom.pixel_mm[0])
    blocks = img.mask.reshape(PIXELS // 2, 2, PIXELS // 2, 2).all(axis=(1, 3))
    np.testing.assert_array_equal(half.mask, blocks)
    assert half.image[5, 5 + PIXELS // 4] == pytest.approx(img.image[10:12, 10 + PIXELS // 2 : 12 + PIXELS // 2].mean())
    assert np.all(half.image[~half.mask] == 0.0)
    with pytest.raises(ValueError, match="multiple"):
        img.downsample(3)
    with pytest.raises(ValueError, match="positive integer"):
        img.downsample(0)


def test_xray_image_validation(geom: CArm) -> None:
    good = np.zeros((PIXELS, PIXELS), np.float32)
    mask = geom.field_mask()
    XRayImage(good, mask, geom)
    with pytest.raises(ValueError, match="does not match the geometry"):
        XRayImage(np.zeros((PIXELS, PIXELS + 1)), mask, geom)
    with pytest.raises(ValueError, match="mask shape"):
        XRayImage(good, mask[:-1], geom)
    with pytest.raises(ValueError, match="empty"):
        XRayImage(good, np.zeros_like(mask), geom)
    bad = good.copy()
    bad[PIXELS // 2, PIXELS // 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        XRayImage(bad, mask, geom)
    bad_outside = good.copy()
    bad_outside[0, 0] = np.nan  # outside the field: allowed (carries no signal)
    XRayImage(bad_outside, mask, geom)
    with pytest.raises(ValueError, match="kind"):
        XRayImage(good, mask, geom, kind="ultrasound")
    with pytest.raises(ValueError, match="boolean"):
        XRayImage(good, mask.astype(np.uint8), geom)


def test_simulate_xray_validation(head: HeadPhantom, geom: CArm) -> None:
    with pytest.raises(ValueError, match="kind"):
        simulate_xray(head, geom, kind="drr")
    with pytest.raises(ValueError, match="rigid"):
        simulate_xray(head, geom, motion=np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="blur_px"):
        simulate_xray(head, geom, blur_px=-1.0)
    with pytest.raises(ValueError, match="HeadPhantom"):
        simulate_xray("head", geom)  # type: ignore[arg-type]


def test_bent_geometry_is_used(head: HeadPhantom) -> None:
    nominal = CArm.for_format(27, pixels=PIXELS)
    bent = CArm(**{**nominal.to_dict(), "source_shift_mm": (3.0, 0.0, 2.0), "pixel_mm": nominal.pixel_mm})
    a = simulate_xray(head, nominal, photons_per_pixel=1e12, blur_px=0.0, supersample=1)
    b = simulate_xray(head, bent, photons_per_pixel=1e12, blur_px=0.0, supersample=1)
    assert float(np.mean(np.abs(a.image - b.image)[a.mask])) > 0.01
