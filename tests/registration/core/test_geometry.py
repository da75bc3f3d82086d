"""C-arm geometry against CONVENTIONS.md §3-4 (property tests with hypothesis)."""

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.core.geometry import (
    TABLE_I,
    CArm,
    apply,
    invert_rigid,
    load_system,
    matrix_to_offsets,
    offsets_to_matrix,
    rigid,
    rotation_angle_deg,
    rotation_x,
    rotation_y,
    rotation_z,
)

angles = st.floats(-180, 180, allow_nan=False)
small_angles = st.floats(-89, 89, allow_nan=False)
# Exact arithmetic aside, every check below is double precision on ~1e3 mm magnitudes:
# 1e-9 relative error gives ~1e-6 mm, far below anything physical.
TOL = 1e-6


@given(angles, angles, st.floats(900, 1300), st.floats(600, 850))
def test_isocenter_projects_to_image_center(primary, secondary, sid, sod):
    g = CArm(primary, secondary, sid_mm=sid if sid > sod else sod + 100, sod_mm=sod)
    col, row = g.project([0.0, 0.0, 0.0])
    assert col == pytest.approx((g.cols - 1) / 2, abs=TOL)
    assert row == pytest.approx((g.rows - 1) / 2, abs=TOL)


def test_frontal_lao90_cran90():
    frontal = CArm(0, 0)
    np.testing.assert_allclose(frontal.source_mm, [0, 810, 0], atol=TOL)
    np.testing.assert_allclose(frontal.detector_center_mm, [0, -390, 0], atol=TOL)
    np.testing.assert_allclose(frontal.u, [1, 0, 0], atol=TOL)  # columns toward patient's left
    np.testing.assert_allclose(frontal.v, [0, 0, -1], atol=TOL)  # rows toward the feet
    lao90 = CArm(90, 0)
    assert lao90.detector_center_mm[0] == pytest.approx(390.0)  # detector at +x (left)
    cran90 = CArm(0, 90)
    assert cran90.detector_center_mm[2] == pytest.approx(390.0)  # detector toward the head


@given(angles, small_angles)
def test_direction_formula(a, b):
    g = CArm(a, b)
    ra, rb = math.radians(a), math.radians(b)
    expected = [math.sin(ra) * math.cos(rb), -math.cos(ra) * math.cos(rb), math.sin(rb)]
    np.testing.assert_allclose(g.direction, expected, atol=1e-12)
    np.testing.assert_allclose(np.cross(g.u, g.v), -g.direction, atol=1e-12)


def test_magnification_at_isocenter():
    g = CArm.for_format(27)
    # A 10 mm segment at the iso-center, perpendicular to the beam, spans 10 * SID/SOD mm.
    p = g.project([[-5.0, 0, 0], [5.0, 0, 0]])
    length_mm = abs(p[1, 0] - p[0, 0]) * g.pixel_mm[1]
    assert length_mm == pytest.approx(10 * 1200 / 810, rel=1e-12)
    assert g.magnification == pytest.approx(1200 / 810)


def _random_rigid(rng):
    rot = rotation_z(rng.uniform(-180, 180)) @ rotation_y(rng.uniform(-90, 90)) @ rotation_x(rng.uniform(-180, 180))
    return rigid(rot, rng.uniform(-50, 50, 3))


@given(st.integers(0, 2**31))
def test_compose_inverse(seed):
    rng = np.random.default_rng(seed)
    a, b = _random_rigid(rng), _random_rigid(rng)
    np.testing.assert_allclose(a @ invert_rigid(a), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert_rigid(a @ b), invert_rigid(b) @ invert_rigid(a), atol=1e-9)
    pts = rng.uniform(-100, 100, (5, 3))
    np.testing.assert_allclose(apply(a @ b, pts), apply(a, apply(b, pts)), atol=1e-9)


@settings(max_examples=200)
@given(
    angles,
    small_angles,
    st.lists(st.floats(-30, 30), min_size=3, max_size=3),
    st.lists(st.floats(-80, 80), min_size=3, max_size=3),
)
def test_offsets_roundtrip(primary, secondary, t, r):
    g = CArm(primary, secondary)
    o = np.array([*t, *r])
    m = offsets_to_matrix(o, g)
    np.testing.assert_allclose(matrix_to_offsets(m, g), o, atol=1e-7)


def test_offsets_act_in_view_frame():
    g = CArm(90, 0)  # lateral: u = (0, 1, 0)... columns run posterior
    m = offsets_to_matrix([10, 0, 0, 0, 0, 0], g)
    np.testing.assert_allclose(m[:3, 3], 10 * g.u, atol=1e-12)
    # tz moves along -d, toward the source.
    m = offsets_to_matrix([0, 0, 5, 0, 0, 0], g)
    np.testing.assert_allclose(m[:3, 3], -5 * g.direction, atol=1e-12)
    # T3 rotates about the iso-center: it stays fixed.
    m = offsets_to_matrix(TABLE_I["T3"], g)
    np.testing.assert_allclose(apply(m, [0, 0, 0]), [0, 0, 0], atol=1e-12)
    assert rotation_angle_deg(m) == pytest.approx(5.0)


def test_projection_matrix_with_shifted_detector():
    g = CArm(30, 20, detector_shift_mm=(1, 2, 3), detector_tilt_deg=(0.5, -0.3, 0.2), source_shift_mm=(2, 0, -1))
    pix = g.pixel_to_world(np.array([10.0, 400.0]), np.array([300.0, 20.0]))
    for t in (0.3, 0.8):
        x = g.source_mm + t * (pix - g.source_mm)
        np.testing.assert_allclose(g.project(x), [[10, 300], [400, 20]], atol=1e-8)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"sid_mm": 800, "sod_mm": 810}, "must exceed"),
        ({"primary_deg": float("nan")}, "finite"),
        ({"secondary_deg": float("inf")}, "finite"),
        ({"primary_deg": 1e6}, "within"),
        ({"pixel_mm": (0.0, 0.5)}, "pixel_mm"),
        ({"rows": 0}, "rows"),
    ],
)
def test_bad_geometry_raises(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CArm(**kwargs)


def test_system_file(tmp_path: Path):
    spec = load_system(Path(__file__).resolve().parents[3] / "assets" / "carm_system.txt")
    assert (spec.sid_mm, spec.sod_mm) == (1200.0, 810.0)
    assert spec.image_formats_cm == (15, 19, 22, 27, 31, 37, 42, 48)
    assert spec.volume_fov_mm(27) == pytest.approx(270 * 810 / 1200)
    bad = tmp_path / "bad.txt"
    bad.write_text("sid_mm = 700\nsod_mm = 810\nimage_formats_cm = 27\n")
    with pytest.raises(ValueError, match="must exceed"):
        load_system(bad)
