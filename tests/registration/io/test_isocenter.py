"""``--isocenter head``: the middle of the head of a head-and-neck CT, its couch left out, against
the geometry the synthetic CT was built with."""

from __future__ import annotations

import numpy as np
import pytest

from registration.core.volume import Volume
from registration.io.isocenter import head_isocenter_mm, resolve_isocenter

#: The synthetic CT: 2 mm voxels, z superior; a head (ball of radius 80 mm about HEAD_MM), a neck
#: (cylinder of radius 45 mm below it, down to the scan's end) and a couch 30 mm behind the head
#: (10 mm thick, the whole scan wide and long).
SPACING_MM = 2.0
HEAD_MM = np.array([30.0, -40.0, 100.0])
HEAD_RADIUS_MM = 80.0
TOP_MM = 180.0


def _ct() -> Volume:
    ni, nj, nk = 160, 150, 170
    affine = np.diag([SPACING_MM, SPACING_MM, SPACING_MM, 1.0])
    affine[:3, 3] = [-130.0, -190.0, -130.0]
    k, j, i = np.meshgrid(np.arange(nk), np.arange(nj), np.arange(ni), indexing="ij")
    p = np.stack([i, j, k], axis=-1) * SPACING_MM + affine[:3, 3]
    rel = p - HEAD_MM
    head = np.linalg.norm(rel, axis=-1) <= HEAD_RADIUS_MM
    neck = (np.hypot(rel[..., 0], rel[..., 1]) <= 45.0) & (rel[..., 2] <= 0.0)
    behind = rel[..., 1] - (HEAD_RADIUS_MM + 30.0)  # +y posterior: the couch lies behind the head
    couch = (behind >= 0.0) & (behind < 10.0)
    data = np.full((nk, nj, ni), -1000.0, np.float32)
    data[head | neck] = 40.0
    data[couch] = 300.0
    return Volume(data, affine)


def test_the_middle_of_the_head_leaves_the_couch_and_the_neck_out():
    ct = _ct()
    center = np.asarray(head_isocenter_mm(ct))
    # the top 180 mm of the grid (its last slice at z 208 mm) reach down to z 28 mm, into the head
    # (z 20 to 180 mm): x and y are the ball's (its equator lies inside), z the middle of 28-180
    # mm; one voxel (2 mm) for the grid's sampling of the ball and the slices' centres
    grid_top = float(ct.world_corners_mm()[:, 2].max())
    expected = np.array([HEAD_MM[0], HEAD_MM[1], 0.5 * (grid_top - TOP_MM + HEAD_MM[2] + HEAD_RADIUS_MM)])
    np.testing.assert_allclose(center, expected, atol=SPACING_MM)
    # the grid's centre lies 50 mm and more from it (in the neck and toward the couch)
    assert np.linalg.norm(ct.center_mm - expected) > 50.0


def test_head_through_resolve_isocenter_and_its_errors():
    ct = _ct()
    iso, source = resolve_isocenter("head", ct)
    assert iso == head_isocenter_mm(ct)
    assert "--isocenter head" in source and "middle of the head" in source
    assert resolve_isocenter(" HEAD ", ct)[0] == iso
    with pytest.raises(ValueError, match="needs the volume"):
        resolve_isocenter("head", None)
    air = Volume(np.full((8, 8, 8), -1000.0, np.float32), np.eye(4))
    with pytest.raises(ValueError, match="no tissue above -300 HU"):
        resolve_isocenter("head", air)
    with pytest.raises(ValueError, match="'head' or 'volume-center'"):
        resolve_isocenter("hed", ct)
