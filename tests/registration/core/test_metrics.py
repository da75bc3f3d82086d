"""Residuals per CONVENTIONS §4."""

import numpy as np
import pytest

from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.metrics import residuals


def test_pure_inplane_translation():
    g = CArm(30, 10)
    est = offsets_to_matrix([0.6, 0.3, 0, 0, 0, 0], g)
    r = residuals(est, np.eye(4), g)
    assert r.inplane_mm == pytest.approx(np.hypot(0.6, 0.3))
    assert r.outofplane_mm == pytest.approx(0.0, abs=1e-12)
    assert r.rotation_deg == pytest.approx(0.0, abs=1e-6)
    assert r.success and r.success_total


def test_out_of_plane_counts_only_in_total():
    g = CArm(0, 0)
    truth = offsets_to_matrix([4, 4, 0, 2, 3, 4], g)
    est = offsets_to_matrix([0, 0, 5, 0, 0, 0], g) @ truth  # 5 mm along the beam
    r = residuals(est, truth, g)
    assert r.translation_mm == pytest.approx(5.0)
    assert r.outofplane_mm == pytest.approx(5.0)
    assert r.inplane_mm == pytest.approx(0.0, abs=1e-9)
    assert r.success and not r.success_total


def test_rotation_and_mtre():
    g = CArm(0, 0)
    est = offsets_to_matrix([0, 0, 0, 0, 0, 4.0], g)
    pts = np.array([[50.0, 0, 0], [0, 0, 50.0]])
    r = residuals(est, np.eye(4), g, pts)
    assert r.rotation_deg == pytest.approx(4.0)
    assert not r.success
    # Both points sit 50 mm from the iso-center; rz (about the beam, world y) moves the point on
    # x by the chord 2 * 50 * sin(2 deg), and the one on z by the same chord.
    assert r.mtre_mm == pytest.approx(2 * 50 * np.sin(np.radians(2.0)))


def test_rejects_non_rigid():
    with pytest.raises(ValueError, match="rigid"):
        residuals(np.diag([2.0, 1, 1, 1]), np.eye(4), CArm())
