"""Similarity measures: gradient difference (Penney et al. 1998), gradient correlation, NCC."""

import numpy as np
import pytest
from scipy import ndimage

from registration.core.similarity import (
    GradientDifference,
    gradient_correlation,
    gradient_difference,
    gradient_mask,
    ncc,
)

SHAPE = (64, 64)


def _disc_mask(shape=SHAPE, margin=3.0) -> np.ndarray:
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    radius = min(shape) / 2.0 - margin
    return (rr - (shape[0] - 1) / 2.0) ** 2 + (cc - (shape[1] - 1) / 2.0) ** 2 <= radius**2


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    """A DRR-like image: smooth background, bright ridges and blobs (bone and vessel edges)."""
    rng = np.random.default_rng(7)
    img = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (96, 96)), 4.0) * 20.0
    rr, cc = np.mgrid[0:96, 0:96]
    img += 3.0 * np.exp(-(((rr - 40) ** 2 + (cc - 55) ** 2) / 30.0))
    img += 2.0 * (np.abs(rr + 0.5 * cc - 70) < 2)
    img = ndimage.gaussian_filter(img, 1.0)
    return img[16:80, 16:80].astype(np.float32) + 5.0  # (64, 64)


def _shifted(img: np.ndarray, dr: float, dc: float) -> np.ndarray:
    return ndimage.shift(img, (dr, dc), order=3, mode="nearest").astype(np.float32)


# ----------------------------------------------------------------------------------------------
# gradient difference
# ----------------------------------------------------------------------------------------------
def test_gd_maximal_at_alignment(image):
    mask = _disc_mask()
    measure = GradientDifference(image, mask)
    aligned = measure(image)
    assert aligned == pytest.approx(2.0, abs=1e-9)  # identical gradients: every term is 1
    previous = aligned
    for shift in (0.5, 1.0, 2.0, 4.0):
        values = [measure(_shifted(image, dr, dc)) for dr, dc in ((shift, 0), (0, shift), (-shift, shift))]
        assert max(values) < aligned
        assert np.mean(values) < previous  # decreasing with the misalignment
        previous = float(np.mean(values))


def test_gd_maximal_at_alignment_with_noise(image):
    rng = np.random.default_rng(0)
    xray = image + rng.normal(0.0, 0.05, image.shape).astype(np.float32)
    measure = GradientDifference(xray, _disc_mask())
    aligned = measure(image)
    for dr, dc in ((1, 0), (0, 1), (1, 1), (-2, 1), (3, -3)):
        assert measure(_shifted(image, dr, dc)) < aligned


@pytest.mark.parametrize("a, b", [(3.0, 0.0), (0.25, 100.0), (-2.0, 7.0), (1000.0, -5e4)])
def test_gd_invariant_to_xray_scale_and_offset(image, a, b):
    mask = _disc_mask()
    drr = _shifted(image, 1.3, -0.7)
    reference = gradient_difference(drr, image, mask)
    # the optimal DRR scale s absorbs a; b has no gradient. The scale search converges to
    # 1e-5 of its bracket, and GD is flat at its maximum: equal to 1e-7.
    xray = image.astype(np.float64) * a + b  # in float64: float32 would round b + small gradients
    assert gradient_difference(drr, xray, mask) == pytest.approx(reference, rel=1e-7)


def test_gd_invariant_to_drr_scale(image):
    mask = _disc_mask()
    xray = _shifted(image, 0.8, 0.4)
    measure = GradientDifference(xray, mask)
    value = measure(image)
    s1 = measure.last_scale
    assert measure(image * 5.0 + 3.0) == pytest.approx(value, rel=1e-7)
    assert measure.last_scale == pytest.approx(s1 / 5.0, rel=1e-4)


def test_gd_ignores_pixels_outside_mask(image):
    mask = _disc_mask()
    drr = _shifted(image, 0.6, -1.1)
    measure = GradientDifference(image, mask)
    value = measure(drr)
    rng = np.random.default_rng(1)
    wild_xray = image.copy()
    wild_drr = drr.copy()
    wild_xray[~mask] = rng.uniform(-1e4, 1e4, (~mask).sum())
    wild_drr[~mask] = rng.uniform(-1e4, 1e4, (~mask).sum())
    assert GradientDifference(wild_xray, mask)(wild_drr) == value
    assert gradient_difference(wild_drr, wild_xray, mask) == value
    # and the Sobel footprint never reaches outside the mask: the eroded mask is used
    used = GradientDifference(image, mask).gradient_mask
    assert not np.any(ndimage.binary_dilation(used, np.ones((3, 3), bool)) & ~mask)


def test_gd_finite_for_constant_images(image):
    flat = np.full(SHAPE, 3.0, np.float32)
    for drr, xray in ((flat, flat), (image, flat), (flat, image)):
        value = gradient_difference(drr, xray)
        assert np.isfinite(value)
        assert 0.0 < value <= 2.0
    # a constant DRR explains nothing of a structured X-ray: less than a perfect match
    assert gradient_difference(flat, image) < gradient_difference(image, image)


def test_gd_prepared_equals_function_and_is_normalised(image):
    mask = _disc_mask()
    drr = _shifted(image, 2.0, 1.0)
    measure = GradientDifference(image, mask)
    assert measure(drr) == gradient_difference(drr, image, mask)
    assert measure.n_pixels == gradient_mask(mask).sum()
    # normalised by the pixel count: comparable across image sizes
    big = ndimage.zoom(image, 2, order=1)
    big_drr = ndimage.zoom(drr, 2, order=1)
    assert 0.0 < gradient_difference(big_drr, big) <= 2.0


def test_gd_accepts_float64_and_integer_images(image):
    measure = GradientDifference(image)
    assert measure(image.astype(np.float64)) == pytest.approx(2.0)
    assert np.isfinite(measure(np.round(image * 10).astype(np.int32)))


def test_gd_bad_input(image):
    mask = _disc_mask()
    with pytest.raises(ValueError, match="shape"):
        gradient_difference(image[:10], image, mask)
    with pytest.raises(ValueError, match="shape"):
        GradientDifference(image, mask)(image[:, :10])
    with pytest.raises(ValueError, match="mask shape"):
        gradient_difference(image, image, mask[:10])
    with pytest.raises(ValueError, match="empty"):
        gradient_difference(image, image, np.zeros(SHAPE, bool))
    thin = np.zeros(SHAPE, bool)
    thin[10, :] = True
    with pytest.raises(ValueError, match="3x3"):
        GradientDifference(image, thin)
    with pytest.raises(ValueError, match="boolean"):
        GradientDifference(image, mask.astype(np.uint8))
    bad = image.copy()
    bad[5, 5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        GradientDifference(bad, mask)
    with pytest.raises(ValueError, match="NaN"):
        GradientDifference(image, mask)(bad)
    bad[5, 5] = np.inf
    with pytest.raises(ValueError, match="NaN"):
        gradient_difference(bad, image)
    with pytest.raises(ValueError, match="2-D"):
        gradient_difference(image[None], image[None])


# ----------------------------------------------------------------------------------------------
# gradient correlation and NCC
# ----------------------------------------------------------------------------------------------
def test_ncc(image):
    mask = _disc_mask()
    assert ncc(image, image * 3.0 + 2.0, mask) == pytest.approx(1.0)
    assert ncc(image, -image, mask) == pytest.approx(-1.0)
    assert ncc(image, _shifted(image, 2, 2), mask) < 1.0
    assert ncc(np.ones(SHAPE), image) == 0.0
    wild = image.copy()
    wild[~mask] = 1e6
    assert ncc(wild, image, mask) == pytest.approx(ncc(image, image, mask))


def test_gradient_correlation(image):
    mask = _disc_mask()
    assert gradient_correlation(image, image * 2.0 - 1.0, mask) == pytest.approx(1.0)
    aligned = gradient_correlation(image, image, mask)
    for dr, dc in ((1, 0), (0, 2), (2, -2)):
        assert gradient_correlation(_shifted(image, dr, dc), image, mask) < aligned
    assert gradient_correlation(np.ones(SHAPE), image) == 0.0
    wild = image.copy()
    wild[~mask] = -1e6
    assert gradient_correlation(wild, image, mask) == pytest.approx(aligned)


def test_gc_ncc_bad_input(image):
    with pytest.raises(ValueError, match="shape"):
        ncc(image, image[:5])
    with pytest.raises(ValueError, match="empty"):
        gradient_correlation(image, image, np.zeros(SHAPE, bool))
    bad = image.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ncc(bad, image)


def test_gd_is_the_maximum_over_the_scale_of_penneys_sum(image):
    """The compiled measure (vectorised sums, Newton on the scale) against a plain numpy
    evaluation of Penney's sum on a fine grid of scales, refined by a bounded scalar search."""
    from scipy import optimize

    mask = _disc_mask()
    xray = image.astype(np.float64)
    rng = np.random.default_rng(3)
    for dr, dc, noise in ((0.0, 0.0, 0.0), (2.0, 1.0, 0.0), (-1.5, 3.0, 0.05), (6.0, -4.0, 0.2)):
        drr = (_shifted(image, dr, dc) * 0.37 + rng.normal(0.0, noise, SHAPE)).astype(np.float32)
        used = gradient_mask(mask)
        xv, xh = ndimage.sobel(xray, axis=0)[used], ndimage.sobel(xray, axis=1)[used]
        dd = drr.astype(np.float64)
        dv, dh = ndimage.sobel(dd, axis=0)[used], ndimage.sobel(dd, axis=1)[used]
        av, ah = xv.var(), xh.var()

        def gd(s, xv=xv, xh=xh, dv=dv, dh=dh, av=av, ah=ah):
            return float(np.mean(av / (av + (xv - s * dv) ** 2) + ah / (ah + (xh - s * dh) ** 2)))

        scales = np.linspace(0.0, 12.0, 4801)  # the DRR is 0.37 of the image: s near 2.7
        values = [gd(s) for s in scales]
        best = int(np.argmax(values))
        lo, hi = scales[max(best - 1, 0)], scales[min(best + 1, scales.size - 1)]
        ref = optimize.minimize_scalar(lambda s: -gd(s), bounds=(lo, hi), method="bounded",
                                       options={"xatol": 1e-10})  # fmt: skip
        measure = GradientDifference(xray, mask)
        # 1e-9: the maximum is flat (a scale off by 1e-4 changes the value by ~1e-8 relative at
        # most); the sums' order differs (vectorised), ~1e-15 each
        assert measure(drr) == pytest.approx(-ref.fun, rel=1e-9)
        assert measure(drr) >= max(values) - 1e-12
        assert measure.last_scale == pytest.approx(ref.x, rel=1e-3)
