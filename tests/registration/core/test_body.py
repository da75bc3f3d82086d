"""The patient's body apart from the CT's couch and head holder (core.prepare.probe_blocks with
core.protrusions.with_protrusions), on the shared real head-and-neck CT."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from registration.core.prepare import BODY_HU, probe_blocks
from registration.studies.volume import find_real_ct


@pytest.fixture(scope="module")
def real_ct():
    path = find_real_ct()
    if path is None:
        pytest.skip("the shared real CT (../shared/data/real-ct/head-neck-ct or ROADMAP3D_REAL_CT) is not here")
    from registration.io import dicom

    return dicom.read_volume(path)


@pytest.mark.slow
def test_the_couch_is_removed_and_nothing_of_the_head(real_ct) -> None:
    volume = real_ct
    blocks = probe_blocks(volume)
    assert blocks.body is not None
    si, sj, sk = (int(s) for s in blocks.step)
    body = (
        blocks.body.repeat(sk, 0).repeat(sj, 1).repeat(si, 2)[: volume.shape[0], : volume.shape[1], : volume.shape[2]]
    )
    dense = volume.data > BODY_HU
    z = volume.index_to_world[2, 2] * np.arange(volume.shape[0]) + volume.index_to_world[2, 3]
    head = z >= z.max() - 150.0  # the top 150 mm: the head, narrower than 200 mm across
    spacing_i = abs(volume.index_to_world[0, 0])
    # the couch, found independently: rows of a head slice with dense voxels over more than 300 mm
    width = dense[head].sum(axis=2) * spacing_i  # (slice, row) mm
    couch_rows = width > 300.0
    assert couch_rows.any(axis=1).mean() > 0.8, "the head lies on the couch"
    couch_top = int(np.nonzero(couch_rows.any(axis=0))[0].min())  # its most anterior row (j grows posterior)
    couch = dense[head] & couch_rows[:, :, None]
    removed = couch & ~body[head]
    # the couch plate is gone (its rows also hold the rim of the body where it rests on them)
    assert removed.sum() > 0.97 * couch.sum(), (removed.sum(), couch.sum())
    # nothing of the head: every voxel of fat, skin, soft tissue or bone (above -150 HU; 20 voxels
    # of -300..-186 HU, the skin's partial volume at the vertex in the scan's last two slices, are
    # not kept) in the head slices anterior to the couch's top by more than 45 mm (the head
    # holder's height) is kept, and so is the whole skull (the largest connected bone), the
    # occiput lying in the head holder included
    anterior = np.arange(volume.shape[1]) < couch_top - 45
    head_voxels = (volume.data[head] > -150.0) & anterior[None, :, None]
    assert (head_voxels & ~body[head]).sum() == 0
    labels, _ = ndimage.label(volume.data[head] > 300.0)
    skull = labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1
    assert skull.sum() > 100_000 and (skull & ~body[head]).sum() == 0
    # the nose's tip (the most anterior dense voxel of the head slices) is kept
    rows = np.nonzero(head_voxels.any(axis=(0, 2)))[0]
    assert body[head][:, rows.min()][head_voxels[:, rows.min()]].all()


@pytest.mark.slow
def test_the_preparation_says_what_lies_outside_the_body(real_ct) -> None:
    """The shared CT's couch plate and head holder are left out and said so (blocks of material
    away from the body; the plate alone, about 10 x 450 x 200 mm, is some 900 ml); the phantom,
    with no couch, next to nothing."""
    from dataclasses import replace

    from registration.core.geometry import CArm
    from registration.core.images import XRayImage
    from registration.core.register import RegistrationOptions, prepared_volume
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.studies.volume import head_isocenter_mm

    def view(carm: CArm) -> XRayImage:
        return XRayImage(np.zeros((128, 128), np.float32), np.ones((128, 128), bool), carm)

    carm = CArm.for_format(27.0, pixels=128)
    at_head = replace(carm, isocenter_mm=head_isocenter_mm(real_ct))
    said = prepared_volume(real_ct, (view(at_head),), np.eye(4), RegistrationOptions()).body_summary()
    assert said["body_only"] and said["outside_body_ml"] > 900.0
    phantom = registration_volume(make_head_phantom(seed=0), 27.0, voxels=64)
    said = prepared_volume(phantom, (view(carm),), np.eye(4), RegistrationOptions()).body_summary()
    assert said["outside_body_ml"] is None or said["outside_body_ml"] < 5.0  # a stray block at most
