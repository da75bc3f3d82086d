"""Rotation vector <-> matrix (core/geometry.py): one implementation, checked against its
definitions at random, small-angle and near-pi rotations (hypothesis)."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from registration.core.geometry import (
    axis_rotation,
    rotation_angle_deg,
    rotation_matrix,
    rotation_vector,
    rotation_x,
    rotation_y,
    rotation_z,
)

unit = st.tuples(*[st.floats(-1.0, 1.0)] * 3).map(np.array).filter(lambda a: np.linalg.norm(a) > 0.1)
unit = unit.map(lambda a: a / np.linalg.norm(a))
#: angles from zero through tiny ones to pi itself (radians)
angles = st.one_of(
    st.floats(0.0, math.pi),
    st.floats(0.0, 1e-5),
    st.floats(math.pi - 1e-3, math.pi),
    st.just(0.0),
    st.just(math.pi),
)


@settings(max_examples=300, deadline=None)
@given(axis=unit, angle=angles)
def test_matrix_is_a_rotation_by_the_angle_about_the_axis(axis, angle):
    r = rotation_matrix(axis * angle)
    # orthonormal with determinant 1, to rounding (1e-12: a few float64 ulps of 3x3 products)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(r) - 1.0) < 1e-12
    # the axis is fixed; a vector across it turns by the angle (its cosine: 1e-12)
    np.testing.assert_allclose(r @ axis, axis, atol=1e-12)
    across = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    assert abs(float(across @ r @ across) - math.cos(angle)) < 1e-12
    # the sense: right-handed about the axis (sin of the angle, same tolerance)
    assert abs(float(np.cross(across, r @ across) @ axis) - math.sin(angle)) < 1e-12


@settings(max_examples=300, deadline=None)
@given(axis=unit, angle=angles)
def test_vector_inverts_the_matrix(axis, angle):
    v = rotation_vector(rotation_matrix(axis * angle))
    assert np.linalg.norm(v) <= math.pi + 1e-12
    if angle < math.pi - 1e-6:
        # 1e-9 rad: near pi the matrix itself holds the axis only to ~1e-16 / (pi - angle)
        np.testing.assert_allclose(v, axis * angle, atol=1e-9)
    else:
        # at pi, v and -v are the same rotation: compare the matrices
        np.testing.assert_allclose(rotation_matrix(v), rotation_matrix(axis * angle), atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(angles_deg=st.tuples(*[st.floats(-180.0, 180.0)] * 3))
@example(angles_deg=(0.0, 0.0, 1e-6))  # below the arccosine of the trace's resolution
def test_round_trip_of_any_rotation_and_its_angle(angles_deg):
    r = rotation_z(angles_deg[2]) @ rotation_y(angles_deg[1]) @ rotation_x(angles_deg[0])
    v = rotation_vector(r)
    # 1e-9: the round trip through the vector at rotations near pi (1e-12 elsewhere)
    np.testing.assert_allclose(rotation_matrix(v), r, atol=1e-9)
    # 1e-7 deg: between 179.7 and 179.95 deg the vector's angle comes from the arccosine of the
    # trace, up to 3e-8 deg off (200,000 draws); elsewhere the two agree to 1e-9
    assert abs(math.degrees(np.linalg.norm(v)) - rotation_angle_deg(r)) < 1e-7


@pytest.mark.parametrize("angle_deg", [1e-9, 1e-6, 0.5, 90.0, 179.9, 180.0])
def test_rotation_angle_keeps_its_digits(angle_deg):
    """The angle of a rotation about a slanted axis, to 1e-12 relative (2 ulp of double
    arithmetic, with margin) at any angle: the arccosine of the trace would read 1e-9 deg as 0."""
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    r = axis_rotation(axis, math.radians(angle_deg))
    assert rotation_angle_deg(r) == pytest.approx(angle_deg, rel=1e-12, abs=1e-12)


def test_small_angles_keep_their_digits():
    """At 1e-9 rad the arccos of the trace would give ~2e-8 (all digits lost); the skew part keeps them."""
    v = np.array([1e-9, -2e-9, 0.5e-9])
    np.testing.assert_allclose(rotation_vector(rotation_matrix(v)), v, rtol=1e-6)
    np.testing.assert_allclose(rotation_vector(axis_rotation(v, np.linalg.norm(v))), v, rtol=1e-6)
