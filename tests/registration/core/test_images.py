"""X-ray images: block averaging, made once per image and factor."""

from __future__ import annotations

import numpy as np
import pytest

from registration.core import images
from registration.core.geometry import CArm
from registration.core.images import XRayImage


def _image() -> XRayImage:
    rng = np.random.default_rng(3)
    rows, cols = 48, 64
    mask = np.zeros((rows, cols), dtype=bool)
    mask[4:44, 6:60] = True
    return XRayImage(rng.normal(1.0, 0.2, (rows, cols)).astype(np.float32), mask, CArm(0.0, 0.0, rows=rows, cols=cols))


def test_block_average_and_mask_by_definition():
    """A 4 x 4 block averages its 16 pixels where it lies wholly in the field (0 elsewhere), by
    the float64 mean of the masked pixels cast to float32: the values the engine compares."""
    view = _image()
    small = view.downsample(4)
    blocks = np.where(view.mask, view.image, 0.0).reshape(12, 4, 16, 4)
    inside = view.mask.reshape(12, 4, 16, 4).all(axis=(1, 3))
    np.testing.assert_array_equal(small.mask, inside)
    np.testing.assert_array_equal(small.image, np.where(inside, blocks.mean(axis=(1, 3)), 0.0).astype(np.float32))
    assert small.geometry == view.geometry.resized(12, 16) and small.meta["downsampled_by"] == 4


def test_each_factor_is_made_once_and_shared_read_only():
    """Every level of a registration asks for the same blocks again: the second call returns
    the first one's image, whose arrays no caller can change under the others; only the most
    recent averages are kept (a long run's frames do not each hold theirs)."""
    view = _image()
    first = view.downsample(2)
    assert view.downsample(2) is first and view.downsample(4) is not first
    with pytest.raises(ValueError, match="read-only"):
        first.image[0, 0] = 5.0
    with pytest.raises(ValueError, match="read-only"):
        first.mask[0, 0] = True
    assert view.downsample(1) is view
    # an image made from another (another object) makes its own
    other = XRayImage(view.image.copy(), view.mask.copy(), view.geometry)
    assert other.downsample(2) is not first
    np.testing.assert_array_equal(other.downsample(2).image, first.image)
    frames = [_image() for _ in range(images.KEPT_AVERAGES)]  # as many newer averages as are kept
    for frame in frames:
        frame.downsample(2)
    again = view.downsample(2)
    assert again is not first  # made anew: it was the oldest
    np.testing.assert_array_equal(again.image, first.image)
