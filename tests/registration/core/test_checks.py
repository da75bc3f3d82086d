"""No success without information (issue 15): inputs without edges are refused, bounds flagged."""

from __future__ import annotations

import numpy as np
import pytest

from registration.core.checks import NoInformationError, check_information, parameters_at_bounds
from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.core.volume import Volume


def _volume(data: np.ndarray) -> Volume:
    return Volume(data.astype(np.float32), np.diag([1.0, 1.0, 1.0, 1.0]), label="test volume")


def _ball(n: int = 32) -> Volume:
    k, j, i = np.mgrid[0:n, 0:n, 0:n] - n / 2
    return _volume(np.where(k**2 + j**2 + i**2 < (n / 4) ** 2, 1000.0, -1000.0))


def _image(values: np.ndarray) -> XRayImage:
    geometry = CArm.for_format(22, pixels=values.shape[0])
    mask = geometry.field_mask()
    return XRayImage(
        np.where(mask, values, 0).astype(np.float32), mask, geometry, kind="dicom", meta={"source": "x.dcm"}
    )


def _step_image(n: int = 64) -> XRayImage:
    values = np.zeros((n, n))
    values[:, n // 2 :] = 2.0  # one vertical edge through the field: n rows of gradient
    return _image(values)


def test_a_volume_with_structure_and_an_image_with_an_edge_pass() -> None:
    check_information(_ball(), _step_image())


@pytest.mark.parametrize("value", [0.0, -1000.0, 3071.0])
def test_a_constant_volume_cannot_be_registered(value: float) -> None:
    with pytest.raises(NoInformationError, match="cannot register: the volume 'test volume' is constant"):
        check_information(_volume(np.full((16, 16, 16), value)), _step_image())


def test_a_volume_with_only_noise_below_the_structure_threshold_cannot_be_registered() -> None:
    noise = np.random.default_rng(0).normal(0.0, 10.0, (16, 16, 16))  # 10 HU noise: 5 sigma below 50 HU
    with pytest.raises(NoInformationError, match="nearly uniform"):
        check_information(_volume(noise), _step_image())


def test_a_constant_image_cannot_be_registered() -> None:
    """RescaleSlope 0 gave similarity 2.0 at each of 970 DRRs and the identity as the result."""
    with pytest.raises(NoInformationError, match=r"cannot register: the X-ray image x.dcm has 0 of \d+ field pixels"):
        check_information(_ball(), _image(np.full((64, 64), 1.5)))


def test_an_image_with_too_few_edge_pixels_cannot_be_registered() -> None:
    values = np.zeros((64, 64))
    values[32, 32] = 5.0  # one bright pixel: 4 neighbours with gradient, far below 50
    with pytest.raises(NoInformationError, match="field pixels with gradient"):
        check_information(_ball(), _image(values))


def test_parameters_at_bounds() -> None:
    bounds = [(-20.0, 20.0)] * 3 + [(-15.0, 15.0)] * 3
    # the all-zero volume: (-21.9, +29.7, -3.6 mm; -15, -15, +13.4 deg) clipped to the box
    assert parameters_at_bounds([-20.0, 20.0, -3.6, -15.0, -15.0, 13.4], bounds) == [0, 1, 3, 4]
    assert parameters_at_bounds([0.0] * 6, bounds) == []
    assert parameters_at_bounds([19.7, 0, 0, 0, 0, 0], bounds) == [0]  # within 1 % of the 40 mm span


def test_register_refuses_inputs_without_information_before_searching() -> None:
    """An all-zero uploaded volume got the REGISTERED badge at the search bounds."""
    from registration.core.register import register

    with pytest.raises(NoInformationError, match="cannot register: the volume 'test volume' is constant"):
        register(_volume(np.zeros((16, 16, 16))), _step_image())
    with pytest.raises(NoInformationError, match="cannot register: the X-ray image"):
        register(_ball(), _image(np.full((64, 64), 1.5)))
