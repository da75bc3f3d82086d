"""Intensities matched to the DRR's whatever display chain stored them (registration.core.intensity).

The images are the analytic phantom's (registration.sim.xray, not the DRR renderer that scores)
passed through the vendor display chain of registration.sim.clinical (window, S-curve, gamma,
polarity, bit depth, edge enhancement, JPEG).
"""

from __future__ import annotations

import numpy as np
import pytest

from registration.core.geometry import TABLE_I, CArm, offsets_to_matrix
from registration.core.images import XRayImage
from registration.core.intensity import match_intensities, needs_matching, reference_geometry
from registration.core.metrics import residuals
from registration.core.register import PolishOptions, RegistrationOptions, register
from registration.sim.clinical.display import display_pixels
from registration.sim.clinical.effects import Display
from registration.sim.phantom import make_head_phantom
from registration.sim.threedra import VolumeRecipe
from registration.sim.xray import simulate_xray

#: Monotone display chains without edge enhancement or JPEG: pure look-up tables of the line
#: integrals (either polarity, 10 to 16 bits).
LUT_ONLY = {
    "linear 16-bit, bone bright": Display(
        bits=16, polarity="bone_bright", gamma=1.0, s_curve=0.0, edge_amount=0.0, jpeg_quality=None
    ),  # fmt: skip
    "S-curve 12-bit, bone dark": Display(
        bits=12, polarity="bone_dark", gamma=0.75, s_curve=4.0, edge_amount=0.0, jpeg_quality=None
    ),  # fmt: skip
    "gamma 1.6 10-bit, narrow window": Display(
        bits=10,
        polarity="bone_bright",
        gamma=1.6,
        s_curve=2.0,
        window_percentiles=(2.0, 98.0),
        edge_amount=0.0,
        jpeg_quality=None,
    ),  # fmt: skip
}


@pytest.fixture(scope="module")
def case():
    volume = VolumeRecipe(phantom_seed=0, volume_format_cm=27.0, source="resampled", voxels=128, contrast=True,
                          noise_seed=0).build()  # fmt: skip
    carm = CArm.for_format(27.0, pixels=256)
    truth = offsets_to_matrix(np.asarray(TABLE_I["T2"]), carm)
    xray = simulate_xray(make_head_phantom(seed=0, contrast=True), carm, motion=truth, kind="fluoro", seed=0)
    return volume, carm, truth, xray


def _displayed(xray: XRayImage, display: Display) -> XRayImage:
    stored, _ = display_pixels(xray.image, xray.mask, xray.mask, xray.geometry, display)
    # as the DICOM reader gives a DISP image: its stored values, read as LOG with the sign +1
    return XRayImage(stored.astype(np.float32), xray.mask, xray.geometry, meta={"intensity_note": "DISP read as LOG"})


def test_every_monotone_lut_gives_the_same_matched_image(case) -> None:
    volume, carm, _, xray = case
    ref_g = reference_geometry(carm)
    rng = np.random.default_rng(3)
    reference = simulate_xray(make_head_phantom(seed=0, contrast=True), ref_g, kind="exposure", seed=1).image
    ref_mask = ref_g.field_mask()
    base, info = match_intensities(xray.image, xray.mask, reference, ref_mask)
    assert info.polarity == 1
    v = xray.image.astype(np.float64)
    luts = [(np.exp(2.0 * v), 1), (-np.sqrt(v - v.min()), -1), (-(v**3) + 5.0, -1),
            (np.arctan(4 * v) * 1e4 + rng.uniform(), 1)]  # fmt: skip
    for lut, polarity in luts:
        matched, other = match_intensities(lut, xray.mask, reference, ref_mask)
        # strictly monotone maps keep every pixel's rank: the matched images are the same
        # (float rounding of the maps aside, which may break a few near-ties)
        assert np.abs(matched - base)[xray.mask].max() < 1e-3 * np.ptp(base[xray.mask])
        assert other.polarity == polarity
        # the other polarity correlates negatively: a large margin (correlations about +-0.8)
        assert other.polarity_margin > 0.5


def test_polarity_found_on_display_processed_pixels(case) -> None:
    _, carm, _, xray = case
    ref_g = reference_geometry(carm)
    reference = simulate_xray(make_head_phantom(seed=0, contrast=True), ref_g, kind="exposure", seed=1).image
    for display in [*LUT_ONLY.values(), Display()]:  # Display(): 8 bits, bone dark, edges, JPEG
        shown = _displayed(xray, display)
        _, info = match_intensities(shown.image, shown.mask, reference, ref_g.field_mask())
        assert info.polarity == (-1 if display.polarity == "bone_dark" else 1), display
        assert info.polarity_margin > 0.5


def test_auto_matches_only_images_not_known_as_line_integrals(case) -> None:
    _, _, _, xray = case
    assert not needs_matching(xray, "auto")
    assert needs_matching(_displayed(xray, Display()), "auto")
    assert needs_matching(xray, "match") and not needs_matching(_displayed(xray, Display()), "as-read")
    with pytest.raises(ValueError, match="intensity"):
        needs_matching(xray, "sometimes")
    with pytest.raises(ValueError, match="intensity"):
        RegistrationOptions(intensity="sometimes")


#: Display chains that are more than a look-up table: 8 bits, edge enhancement, lossy JPEG.
PROCESSED = {
    "gamma 0.5 S-curve 6, 8-bit, bone dark": Display(
        bits=8, polarity="bone_dark", gamma=0.5, s_curve=6.0, edge_amount=0.0, jpeg_quality=None
    ),  # fmt: skip
    "edge-enhanced 0.5, 8-bit JPEG 90, bone dark": Display(
        bits=8, polarity="bone_dark", gamma=0.75, s_curve=4.0, edge_amount=0.5, jpeg_quality=90
    ),  # fmt: skip
}


@pytest.mark.slow
def test_intensity_variants_register_to_the_same_pose(case) -> None:
    """One image, stored through different display chains (either polarity, 8-16 bits, a
    window, S-curve and gamma, edge enhancement, JPEG): each registers, matched, to the same pose
    as the line-integral image. The polish converges to 0.01 (PolishOptions.xtol; the default
    0.1 lets any change of the image move the end by about that much), and every estimate is
    rotation-checked (no screen: whether it skips depends on a margin the display chain moves a
    little, and a check's polishes refine the end), so the comparison is of where the measure
    peaks."""
    volume, carm, truth, xray = case
    options = RegistrationOptions(intensity="match", polish=PolishOptions(xtol=0.01, evaluations=120),
                                  rotation_check_skip_margin=None)  # fmt: skip
    first = register(volume, xray, truth=truth, seed=0, options=options)
    assert first.success and first.intensity[0]["polarity"] == 1
    for name, display in (LUT_ONLY | PROCESSED).items():
        result = register(volume, _displayed(xray, display), truth=truth, seed=0, options=options)
        assert result.success, name
        between = residuals(result.patient_motion, first.patient_motion, carm)
        # look-up tables alone: the same matched image but for the ties of fewer bits (measured
        # 0.004 mm); 8 bits, edges and JPEG change the image itself (measured up to 0.081 mm,
        # 0.10 deg): the same pose within 0.1 mm
        assert between.inplane_mm < 0.1 and between.rotation_deg < 0.2, (name, between)
        assert result.intensity[0]["polarity"] == (-1 if display.polarity == "bone_dark" else 1)
