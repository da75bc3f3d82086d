"""Two views' depth confirmation (``beam_margin``) against ground truth: honest exposures of the
phantom at LAO 20 and RAO 70 (not made by the renderer that scores them) against its 128^3 3DRA
stand-in."""

import numpy as np
import pytest

from registration.core.confidence import DEFAULT_RULE, Evidence
from registration.core.geometry import CArm, offsets_to_matrix, rigid
from registration.core.images import XRayImage
from registration.core.tracking.evidence import beam_margin


@pytest.fixture(scope="module")
def scene():
    from registration.core.drr import DRRRenderer
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    planes = [CArm.for_format(27.0, pixels=128, primary_deg=20.0), CArm.for_format(27.0, pixels=128, primary_deg=-70.0)]
    phantom = make_head_phantom(seed=0, contrast=False)
    views = [simulate_xray(phantom, g, kind="exposure", seed=1 + n) for n, g in enumerate(planes)]
    return volume, views, DRRRenderer(volume, levels=3)


def test_both_views_confirm_the_true_pose(scene):
    volume, views, renderer = scene
    margin = beam_margin(volume, views, np.eye(4), renderer=renderer)
    # 6 mm along either beam is 5.6 mm across the other (90 deg apart): measured 0.02-0.05 on the
    # phantom's quick studies for right estimates; the rule's ``beam_good`` (0.003) leaves 3x room
    assert margin is not None and margin > DEFAULT_RULE.beam_good, margin
    assert beam_margin(volume, views[:1], np.eye(4), renderer=renderer) is None  # one view: no such evidence


def test_a_pose_off_along_one_beam_is_not_confirmed(scene):
    volume, views, renderer = scene
    # 9 mm off along plane A's beam, right across it: plane A barely sees it, plane B does, and
    # moving 6 mm back toward the truth fits plane B better
    off = rigid(None, 9.0 * np.asarray(views[0].geometry.direction))
    margin = beam_margin(volume, views, off, renderer=renderer)
    assert margin is not None and margin < 0.0, margin
    e = Evidence(margin=0.01, agreement=1.0, edges=0.3, beam_margin=margin)
    decided = DEFAULT_RULE.assess(e)
    assert not decided.applied and "not confirmed" in decided.reason, decided


def test_a_view_without_anatomy_confirms_nothing(scene):
    volume, views, renderer = scene
    # plane B's image replaced by noise alone (its field sees no anatomy): its measure is flat
    # along plane A's beam, below the rule's beam_good (its noise over 128 px: ~0.001 relative)
    rng = np.random.default_rng(3)
    b = views[1]
    noise = XRayImage(
        rng.normal(1.0, 0.02, b.image.shape).astype(np.float32) * b.mask, b.mask, b.geometry, kind="exposure"
    )
    margin = beam_margin(volume, [views[0], noise], np.eye(4), renderer=renderer)
    assert margin is not None and margin < DEFAULT_RULE.beam_good, margin
    # the same views at a pose 1 mm off across plane B's beam keep their evidence finite
    assert np.isfinite(beam_margin(volume, views, offsets_to_matrix([1.0, 0, 0, 0, 0, 0], views[1].geometry),
                                   renderer=renderer))  # fmt: skip
