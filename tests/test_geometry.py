"""Tests for phigenesis.geometry: angles, quaternions, rigid transforms, cameras and boxes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from phigenesis import geometry as g

# --------------------------------------------------------------------------------------------
# Shared strategies and helpers

FAST = settings(max_examples=60, deadline=None)
SLOW = settings(max_examples=50, deadline=None)

# A realistic Waymo-like front camera (pixels).
WIDTH, HEIGHT = 1920, 1280
K_WAYMO = g.intrinsic_matrix(2055.0, 2055.0, 960.0, 640.0)


def finite(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(min_value=lo, max_value=hi, allow_nan=False, allow_infinity=False)


def vec3(lo: float = -1e3, hi: float = 1e3) -> st.SearchStrategy[np.ndarray]:
    return st.tuples(finite(lo, hi), finite(lo, hi), finite(lo, hi)).map(np.array)


@st.composite
def unit_quaternions(draw: st.DrawFn) -> np.ndarray:
    q = np.array(draw(st.tuples(*[finite(-1.0, 1.0)] * 4)))
    norm = np.linalg.norm(q)
    assume(norm > 0.1)
    return q / norm


@st.composite
def unit_vectors(draw: st.DrawFn) -> np.ndarray:
    v = draw(vec3(-1.0, 1.0))
    norm = np.linalg.norm(v)
    assume(norm > 0.1)
    return v / norm


@st.composite
def rigid_transforms(draw: st.DrawFn) -> np.ndarray:
    return g.pose_to_transform(draw(vec3()), draw(unit_quaternions()))


@st.composite
def point_clouds(draw: st.DrawFn, lo: float = -1e3, hi: float = 1e3) -> np.ndarray:
    n = draw(st.integers(1, 8))
    return np.array(draw(st.lists(vec3(lo, hi), min_size=n, max_size=n)))


@st.composite
def waymo_like_distortion(draw: st.DrawFn) -> np.ndarray:
    return np.array(
        [
            draw(finite(-0.35, 0.1)),  # k1
            draw(finite(-0.1, 0.1)),  # k2
            draw(finite(-2e-3, 2e-3)),  # p1
            draw(finite(-2e-3, 2e-3)),  # p2
            draw(finite(-0.02, 0.02)),  # k3
        ]
    )


def axis_angle_quaternion(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[np.cos(0.5 * angle)], np.sin(0.5 * angle) * axis])


def rotation_angle_between(q0: np.ndarray, q1: np.ndarray) -> float:
    """Angle in [0, pi] of the rotation taking q0 to q1 (sign-independent, accurate near zero)."""
    rel = g.quaternion_multiply(
        g.quaternion_conjugate(g.quaternion_normalize(q0)), g.quaternion_normalize(q1)
    )
    return float(2.0 * np.arctan2(np.linalg.norm(rel[1:]), abs(rel[0])))


def assert_same_up_to_sign(a: np.ndarray, b: np.ndarray, atol: float) -> None:
    sign = 1.0 if np.dot(a, b) >= 0 else -1.0
    assert_allclose(a, sign * b, rtol=0, atol=atol)


def assert_is_rotation(r: np.ndarray, atol: float = 1e-12) -> None:
    assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), rtol=0, atol=atol)
    assert_allclose(np.linalg.det(r), 1.0, rtol=0, atol=atol)


# --------------------------------------------------------------------------------------------
# Angles


def test_wrap_angle_maps_pi_to_minus_pi():
    assert g.wrap_angle(np.pi) == -np.pi
    assert g.wrap_angle(-np.pi) == -np.pi
    assert g.wrap_angle(3 * np.pi) == -np.pi


def test_yaw_wraps_across_pi():
    assert_allclose(g.wrap_angle(np.pi + 0.1), -np.pi + 0.1, rtol=0, atol=1e-15)
    assert_allclose(g.wrap_angle(-np.pi - 0.1), np.pi - 0.1, rtol=0, atol=1e-15)


def test_wrap_angle_of_values_just_outside_the_range_stays_in_range():
    # np.mod rounds these onto the seam; the result must still be in [-pi, pi) and the same angle.
    for angle in [np.nextafter(-np.pi, -np.inf), np.nextafter(np.pi, np.inf), -np.pi - 1e-15]:
        wrapped = float(g.wrap_angle(angle))
        assert -np.pi <= wrapped < np.pi
        assert_allclose([np.cos(wrapped), np.sin(wrapped)], [np.cos(angle), np.sin(angle)], atol=2e-15)


def test_wrap_angle_of_tiny_negative_angle_is_near_zero():
    wrapped = g.wrap_angle(np.array([-1e-300, -1e-17, 1e-17]))
    assert np.all(wrapped >= -np.pi) and np.all(wrapped < np.pi)
    assert_allclose(wrapped, 0.0, rtol=0, atol=1e-16)


def test_wrap_angle_of_huge_angles_matches_high_precision_reference():
    # 1e6 - 2 pi * round(1e6 / (2 pi)), evaluated with 50-digit arithmetic.
    reference = -0.357564167085735044
    assert_allclose(g.wrap_angle(1e6), reference, rtol=0, atol=1e-9)
    assert_allclose(g.wrap_angle(-1e6), -reference, rtol=0, atol=1e-9)


def test_angle_difference_across_the_seam_is_the_short_way_round():
    assert_allclose(np.degrees(g.angle_difference(np.radians(179.0), np.radians(-179.0))), -2.0, atol=1e-9)
    assert_allclose(np.degrees(g.angle_difference(np.radians(-179.0), np.radians(179.0))), 2.0, atol=1e-9)


def test_angle_difference_broadcasts_over_arrays():
    diff = g.angle_difference(np.array([0.0, 3.0, -3.0]), 0.5)
    assert_allclose(diff, [-0.5, 2.5, 2 * np.pi - 3.5], rtol=0, atol=1e-15)


@FAST
@given(finite(-1e4, 1e4))
def test_wrap_angle_lands_in_half_open_range_and_preserves_direction(angle):
    wrapped = float(g.wrap_angle(angle))
    assert -np.pi <= wrapped < np.pi
    assert_allclose([np.cos(wrapped), np.sin(wrapped)], [np.cos(angle), np.sin(angle)], rtol=0, atol=1e-11)
    turns = (angle - wrapped) / (2 * np.pi)
    assert_allclose(turns, np.round(turns), rtol=0, atol=1e-9)


@FAST
@given(finite(-50.0, 50.0), finite(-50.0, 50.0))
def test_angle_difference_added_to_b_gives_a_modulo_two_pi(a, b):
    diff = float(g.angle_difference(a, b))
    assert -np.pi <= diff < np.pi
    assert_allclose(float(g.angle_difference(b + diff, a)), 0.0, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Quaternions


def test_zero_quaternion_normalises_to_identity():
    assert_array_equal(g.quaternion_normalize(np.zeros(4)), [1.0, 0.0, 0.0, 0.0])
    assert_array_equal(g.quaternion_to_matrix(np.zeros(4)), np.eye(3))


def test_non_finite_quaternions_normalise_to_identity_row_by_row():
    q = np.array(
        [[0.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 0.0], [np.inf, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = g.quaternion_normalize(q)
    assert_array_equal(out, [[1, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1]])


def test_tiny_but_non_zero_quaternion_is_normalised_not_replaced():
    assert_allclose(g.quaternion_normalize([0.0, 1e-10, 0.0, 0.0]), [0.0, 1.0, 0.0, 0.0], rtol=0, atol=1e-15)


def test_quaternion_canonical_has_non_negative_w():
    assert_allclose(g.quaternion_canonical([-2.0, 0.0, 0.0, 0.0]), [1.0, 0.0, 0.0, 0.0], atol=0)
    assert_allclose(g.quaternion_canonical([-0.6, 0.8, 0.0, 0.0]), [0.6, -0.8, 0.0, 0.0], atol=1e-15)


def test_quaternion_multiply_follows_hamilton_rules():
    one, i, j, k = np.eye(4)
    assert_array_equal(g.quaternion_multiply(i, j), k)
    assert_array_equal(g.quaternion_multiply(j, i), -k)
    assert_array_equal(g.quaternion_multiply(j, k), i)
    assert_array_equal(g.quaternion_multiply(k, i), j)
    assert_array_equal(g.quaternion_multiply(i, i), -one)
    assert_array_equal(g.quaternion_multiply(np.stack([i, j]), np.stack([j, k])), np.stack([k, i]))


def test_quaternion_to_matrix_of_quarter_turn_about_z_maps_x_to_y():
    r = g.quaternion_to_matrix(axis_angle_quaternion([0, 0, 1], np.pi / 2))
    assert_allclose(r, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], rtol=0, atol=1e-15)


def test_quaternion_to_matrix_of_known_rotation_about_x():
    angle = 0.3
    r = g.quaternion_to_matrix(axis_angle_quaternion([1, 0, 0], angle))
    c, s = np.cos(angle), np.sin(angle)
    assert_allclose(r, [[1, 0, 0], [0, c, -s], [0, s, c]], rtol=0, atol=1e-15)


def test_quaternion_to_matrix_normalises_its_input():
    q = axis_angle_quaternion([1, 2, 3], 0.7)
    assert_allclose(g.quaternion_to_matrix(3.5 * q), g.quaternion_to_matrix(q), rtol=0, atol=1e-15)


def test_matrix_to_quaternion_of_identity_is_identity_quaternion():
    assert_allclose(g.matrix_to_quaternion(np.eye(3)), [1, 0, 0, 0], rtol=0, atol=0)


@pytest.mark.parametrize(
    "axis",
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 2, 3], [-1, 0.5, -2], [1e-3, 0, 1]],
)
def test_half_turn_rotations_round_trip_through_matrix_to_quaternion(axis):
    q = axis_angle_quaternion(axis, np.pi)
    r = g.quaternion_to_matrix(q)
    back = g.matrix_to_quaternion(r)
    assert abs(back[0]) < 1e-12
    assert_same_up_to_sign(back, q, atol=1e-12)
    assert_allclose(g.quaternion_to_matrix(back), r, rtol=0, atol=1e-12)


def test_matrix_to_quaternion_handles_batches():
    qs = np.array(
        [axis_angle_quaternion(ax, a) for ax, a in [([1, 0, 0], 3.0), ([0, 1, 1], -2.0), ([1, 2, 3], 0.1)]]
    )
    rs = g.quaternion_to_matrix(qs.reshape(3, 1, 4))
    assert rs.shape == (3, 1, 3, 3)
    back = g.matrix_to_quaternion(rs)
    assert back.shape == (3, 1, 4)
    for q, b in zip(qs, back[:, 0], strict=True):
        assert_same_up_to_sign(b, q, atol=1e-12)
        assert b[0] >= 0.0


@FAST
@given(unit_quaternions())
def test_quaternion_matrix_round_trip_recovers_the_rotation(q):
    r = g.quaternion_to_matrix(q)
    assert_is_rotation(r)
    back = g.matrix_to_quaternion(r)
    assert back[0] >= 0.0
    assert_allclose(np.linalg.norm(back), 1.0, rtol=0, atol=1e-14)
    assert_same_up_to_sign(back, q, atol=1e-12)
    assert_allclose(g.quaternion_to_matrix(back), r, rtol=0, atol=1e-12)


@FAST
@given(unit_vectors())
def test_random_half_turns_round_trip_through_matrix_to_quaternion(axis):
    r = g.quaternion_to_matrix(np.concatenate([[0.0], axis]))
    back = g.matrix_to_quaternion(r)
    assert abs(back[0]) < 1e-12
    assert_allclose(g.quaternion_to_matrix(back), r, rtol=0, atol=1e-12)


@FAST
@given(unit_quaternions())
def test_antipodal_quaternions_give_the_same_matrix(q):
    assert_allclose(g.quaternion_to_matrix(-q), g.quaternion_to_matrix(q), rtol=0, atol=1e-15)


@FAST
@given(unit_quaternions(), unit_quaternions())
def test_quaternion_multiply_matches_matrix_product(a, b):
    product = g.quaternion_multiply(a, b)
    expected = g.quaternion_to_matrix(a) @ g.quaternion_to_matrix(b)
    assert_allclose(g.quaternion_to_matrix(product), expected, rtol=0, atol=1e-12)
    assert_allclose(np.linalg.norm(product), 1.0, rtol=0, atol=1e-14)


@FAST
@given(unit_quaternions())
def test_conjugate_is_the_inverse_rotation(q):
    conj = g.quaternion_conjugate(q)
    assert_allclose(g.quaternion_multiply(q, conj), [1, 0, 0, 0], rtol=0, atol=1e-14)
    assert_allclose(g.quaternion_multiply(conj, q), [1, 0, 0, 0], rtol=0, atol=1e-14)
    assert_allclose(g.quaternion_to_matrix(conj), g.quaternion_to_matrix(q).T, rtol=0, atol=1e-15)


# --------------------------------------------------------------------------------------------
# Slerp


@FAST
@given(unit_quaternions(), unit_quaternions())
def test_slerp_hits_its_endpoints(q0, q1):
    assert_same_up_to_sign(g.quaternion_slerp(q0, q1, 0.0), q0, atol=1e-12)
    assert_same_up_to_sign(g.quaternion_slerp(q0, q1, 1.0), q1, atol=1e-12)


@FAST
@given(unit_quaternions(), unit_quaternions(), finite(-1.0, 2.0))
def test_slerp_stays_unit_norm(q0, q1, t):
    assert_allclose(np.linalg.norm(g.quaternion_slerp(q0, q1, t)), 1.0, rtol=0, atol=1e-14)


@FAST
@given(unit_quaternions(), unit_quaternions(), finite(0.0, 1.0))
def test_slerp_moves_at_constant_angular_speed_along_the_short_arc(q0, q1, t):
    total = rotation_angle_between(q0, q1)  # in [0, pi]: the short arc
    q = g.quaternion_slerp(q0, q1, t)
    assert_allclose(rotation_angle_between(q0, q), t * total, rtol=0, atol=1e-9)
    assert_allclose(rotation_angle_between(q, q1), (1.0 - t) * total, rtol=0, atol=1e-9)


@FAST
@given(unit_quaternions(), finite(0.0, 1.0))
def test_slerp_between_antipodal_quaternions_stays_constant(q, t):
    out = g.quaternion_slerp(q, -q, t)
    assert np.all(np.isfinite(out))
    assert_same_up_to_sign(out, q, atol=1e-15)
    assert_allclose(g.quaternion_to_matrix(out), g.quaternion_to_matrix(q), rtol=0, atol=1e-15)


@pytest.mark.parametrize("angle", [1e-12, 1e-9, 1e-7, 1e-5, 1e-3])
def test_small_angle_slerp_is_finite_and_accurate(angle):
    q0 = axis_angle_quaternion([0.3, -1.0, 0.5], 2.0)
    axis = np.array([1.0, 2.0, -0.5])
    q1 = g.quaternion_multiply(q0, axis_angle_quaternion(axis, angle))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for t in [0.0, 0.25, 0.5, 0.9, 1.0]:
            out = g.quaternion_slerp(q0, q1, t)
            assert np.all(np.isfinite(out))
            expected = g.quaternion_multiply(q0, axis_angle_quaternion(axis, t * angle))
            assert_allclose(out, expected, rtol=0, atol=2e-15)
            assert_allclose(rotation_angle_between(q0, out), t * angle, rtol=0, atol=1e-15)


def test_slerp_of_yaws_interpolates_the_yaw():
    q = g.quaternion_slerp(g.yaw_to_quaternion(0.2), g.yaw_to_quaternion(1.0), 0.25)
    assert_allclose(g.quaternion_yaw(q), 0.4, rtol=0, atol=1e-14)


def test_slerp_of_yaws_across_the_seam_goes_through_pi_not_zero():
    q = g.quaternion_slerp(g.yaw_to_quaternion(3.0), g.yaw_to_quaternion(-3.0), 0.5)
    assert_allclose(g.angle_difference(g.quaternion_yaw(q), np.pi), 0.0, rtol=0, atol=1e-12)
    q = g.quaternion_slerp(g.yaw_to_quaternion(3.0), g.yaw_to_quaternion(-3.0), 0.25)
    assert_allclose(g.angle_difference(g.quaternion_yaw(q), 3.0 + 0.25 * (2 * np.pi - 6.0)), 0.0, atol=1e-12)


def test_slerp_extrapolates_beyond_the_endpoints():
    q = g.quaternion_slerp(g.yaw_to_quaternion(0.0), g.yaw_to_quaternion(0.5), 2.0)
    assert_allclose(g.quaternion_yaw(q), 1.0, rtol=0, atol=1e-14)


def test_slerp_handles_batches_row_by_row():
    q0 = np.array([axis_angle_quaternion([1, 0, 0], 0.5), axis_angle_quaternion([0, 1, 1], -2.0)])
    q1 = np.array([axis_angle_quaternion([0, 0, 1], 1.5), -axis_angle_quaternion([1, 2, 3], 2.5)])
    t = np.array([0.3, 0.8])
    out = g.quaternion_slerp(q0, q1, t)
    assert out.shape == (2, 4)
    for i in range(2):
        assert_allclose(out[i], g.quaternion_slerp(q0[i], q1[i], t[i]), rtol=0, atol=1e-15)


# --------------------------------------------------------------------------------------------
# Yaw helpers


@FAST
@given(finite(-10.0, 10.0))
def test_yaw_to_quaternion_matches_rotation_z(yaw):
    assert_allclose(g.quaternion_to_matrix(g.yaw_to_quaternion(yaw)), g.rotation_z(yaw), rtol=0, atol=1e-15)


@FAST
@given(finite(-10.0, 10.0))
def test_quaternion_yaw_recovers_the_yaw_of_a_pure_yaw_rotation(yaw):
    recovered = g.quaternion_yaw(g.yaw_to_quaternion(yaw))
    assert -np.pi <= recovered < np.pi
    assert_allclose(g.angle_difference(recovered, yaw), 0.0, rtol=0, atol=1e-13)


def test_rotation_z_quarter_turn_maps_x_to_y():
    assert_allclose(g.rotation_z(np.pi / 2) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], rtol=0, atol=1e-15)
    assert g.rotation_z(np.zeros((2, 5))).shape == (2, 5, 3, 3)


def test_quaternion_yaw_is_the_heading_of_the_forward_axis_under_pitch_and_roll():
    q = g.quaternion_multiply(
        g.yaw_to_quaternion(0.7),
        g.quaternion_multiply(axis_angle_quaternion([0, 1, 0], 0.3), axis_angle_quaternion([1, 0, 0], 0.5)),
    )
    assert_allclose(g.quaternion_yaw(q), 0.7, rtol=0, atol=1e-14)
    assert_allclose(g.matrix_yaw(g.quaternion_to_matrix(q)), 0.7, rtol=0, atol=1e-14)


def test_matrix_yaw_accepts_4x4_transforms_and_wraps():
    t = g.yaw_pose_to_transform([1.0, 2.0, 3.0], np.array([0.5, np.pi, -np.pi + 1e-3]))
    assert_allclose(g.matrix_yaw(t), [0.5, -np.pi, -np.pi + 1e-3], rtol=0, atol=1e-14)


# --------------------------------------------------------------------------------------------
# Rigid transforms


def test_make_transform_places_rotation_translation_and_homogeneous_row():
    r = g.rotation_z(0.4)
    t = g.make_transform(r, [1.0, -2.0, 3.0])
    assert_array_equal(t[:3, :3], r)
    assert_array_equal(t[:3, 3], [1.0, -2.0, 3.0])
    assert_array_equal(t[3], [0.0, 0.0, 0.0, 1.0])


def test_make_transform_broadcasts_a_shared_rotation_over_translations():
    t = g.make_transform(np.eye(3), np.arange(15.0).reshape(5, 3))
    assert t.shape == (5, 4, 4)
    assert_array_equal(t[:, :3, 3], np.arange(15.0).reshape(5, 3))
    assert_array_equal(t[:, :3, :3], np.broadcast_to(np.eye(3), (5, 3, 3)))


def test_pose_to_transform_maps_the_source_origin_and_axes_into_the_target():
    t = g.pose_to_transform([10.0, 20.0, 30.0], g.yaw_to_quaternion(np.pi / 2))
    pts = g.transform_points(t, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    assert_allclose(pts, [[10, 20, 30], [10, 21, 30], [10, 20, 32]], rtol=0, atol=1e-14)


def test_yaw_pose_to_transform_matches_pose_to_transform():
    assert_allclose(
        g.yaw_pose_to_transform([1.0, 2.0, 3.0], 2.5),
        g.pose_to_transform([1.0, 2.0, 3.0], g.yaw_to_quaternion(2.5)),
        rtol=0,
        atol=1e-15,
    )


@FAST
@given(rigid_transforms())
def test_transform_times_its_inverse_is_identity(t):
    inv = g.invert_transform(t)
    # Translations reach 1e3 m, so their rounding is ~1e-13 m.
    assert_allclose(t @ inv, np.eye(4), rtol=0, atol=1e-10)
    assert_allclose(inv @ t, np.eye(4), rtol=0, atol=1e-10)
    assert_array_equal(inv[3], [0.0, 0.0, 0.0, 1.0])


@FAST
@given(rigid_transforms())
def test_inverting_twice_returns_the_transform(t):
    inv_inv = g.invert_transform(g.invert_transform(t))
    assert_allclose(inv_inv[:3, :3], t[:3, :3], rtol=0, atol=1e-15)
    assert_allclose(inv_inv[:3, 3], t[:3, 3], rtol=0, atol=1e-10)


@FAST
@given(rigid_transforms(), rigid_transforms())
def test_inverse_of_a_composition_is_the_reversed_composition_of_inverses(a, b):
    assert_allclose(
        g.invert_transform(a @ b), g.invert_transform(b) @ g.invert_transform(a), rtol=0, atol=1e-9
    )


@FAST
@given(rigid_transforms(), rigid_transforms(), point_clouds())
def test_transform_points_agrees_with_composition(a, b, pts):
    assert_allclose(
        g.transform_points(a @ b, pts), g.transform_points(a, g.transform_points(b, pts)), rtol=0, atol=1e-9
    )


@FAST
@given(rigid_transforms(), point_clouds())
def test_transform_points_agrees_with_the_homogeneous_matrix_product(t, pts):
    homogeneous = np.concatenate([pts, np.ones((len(pts), 1))], axis=1)
    assert_allclose(g.transform_points(t, pts), (t @ homogeneous.T).T[:, :3], rtol=0, atol=1e-10)


@FAST
@given(rigid_transforms(), point_clouds())
def test_inverse_transform_brings_points_back(t, pts):
    moved = g.transform_points(t, pts)
    assert_allclose(g.transform_points(g.invert_transform(t), moved), pts, rtol=0, atol=1e-9)


@FAST
@given(rigid_transforms(), point_clouds())
def test_rigid_transforms_preserve_pairwise_distances(t, pts):
    moved = g.transform_points(t, pts)
    before = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    after = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    assert_allclose(after, before, rtol=0, atol=1e-9)


def test_transform_points_broadcasts_over_a_batch_of_transforms():
    ts = g.yaw_pose_to_transform(np.array([[1.0, 0, 0], [0, 2.0, 0]]), np.array([0.0, np.pi / 2]))
    pts = np.array([[[1.0, 0, 0], [0, 0, 1.0]], [[1.0, 0, 0], [0, 0, 1.0]]])
    out = g.transform_points(ts, pts)
    assert_allclose(out, [[[2, 0, 0], [1, 0, 1]], [[0, 3, 0], [0, 2, 1]]], rtol=0, atol=1e-15)


def test_transform_directions_rotates_without_translating():
    t = g.yaw_pose_to_transform([100.0, 200.0, 300.0], np.pi / 2)
    assert_allclose(g.transform_directions(t, [[1.0, 0.0, 0.0]]), [[0.0, 1.0, 0.0]], rtol=0, atol=1e-15)


@FAST
@given(unit_quaternions())
def test_orthonormalize_rotation_repairs_a_float32_rounded_rotation(q):
    r = g.quaternion_to_matrix(q)
    r32 = r.astype(np.float32).astype(np.float64)
    fixed = g.orthonormalize_rotation(r32)
    assert_is_rotation(fixed, atol=1e-14)
    assert_allclose(fixed, r, rtol=0, atol=2e-7)
    # It is the nearest rotation, so at least as close to the float32 matrix as the original was.
    assert np.linalg.norm(fixed - r32) <= np.linalg.norm(r - r32) + 1e-15


def test_orthonormalize_rotation_keeps_an_exact_rotation():
    r = g.quaternion_to_matrix(axis_angle_quaternion([1, -2, 0.5], 1.2))
    assert_allclose(g.orthonormalize_rotation(r), r, rtol=0, atol=1e-15)


def test_orthonormalize_rotation_turns_a_reflection_into_a_proper_rotation():
    reflection = np.diag([1.0, 1.0, -1.0]) @ g.rotation_z(0.3)
    fixed = g.orthonormalize_rotation(reflection)
    assert_is_rotation(fixed, atol=1e-14)


def test_orthonormalize_rotation_handles_batches():
    rs = g.quaternion_to_matrix(np.array([axis_angle_quaternion([1, 0, 0], 0.3), [0.0, 0.0, 1.0, 0.0]]))
    noisy = rs + 1e-6 * np.array([[[1, 0, 0], [0, -1, 0], [0, 0, 1]], [[0, 1, 0], [1, 0, 0], [0, 0, -1]]])
    fixed = g.orthonormalize_rotation(noisy)
    assert fixed.shape == (2, 3, 3)
    assert_is_rotation(fixed, atol=1e-14)
    assert_allclose(fixed, rs, rtol=0, atol=1e-5)


# --------------------------------------------------------------------------------------------
# Cameras


def test_intrinsic_matrix_layout():
    assert_array_equal(g.intrinsic_matrix(1.0, 2.0, 3.0, 4.0), [[1, 0, 3], [0, 2, 4], [0, 0, 1]])


def test_project_points_of_a_known_point_without_distortion():
    k = g.intrinsic_matrix(1000.0, 900.0, 960.0, 640.0)
    uv, valid = g.project_points([[1.0, 0.5, 2.0], [0.0, 0.0, 5.0]], k)
    assert_array_equal(valid, [True, True])
    assert_allclose(uv, [[1460.0, 865.0], [960.0, 640.0]], rtol=0, atol=1e-12)


def test_project_points_applies_skew_to_u():
    k = np.array([[1000.0, 5.0, 960.0], [0.0, 900.0, 640.0], [0.0, 0.0, 1.0]])
    uv, _ = g.project_points([[1.0, 0.5, 2.0]], k)
    assert_allclose(uv, [[1460.0 + 5.0 * 0.25, 865.0]], rtol=0, atol=1e-12)
    assert_allclose(g.unproject_pixels(uv, k, depth_m=[2.0]), [[1.0, 0.5, 2.0]], rtol=0, atol=1e-12)


def test_distort_normalized_matches_the_opencv_formula_on_a_known_point():
    k1, k2, p1, p2, k3 = -0.3, 0.1, 1e-3, -2e-3, 0.01
    x, y = 0.3, -0.2
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    expected = [
        x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    ]
    assert_allclose(g.distort_normalized([x, y], [k1, k2, p1, p2, k3]), expected, rtol=0, atol=1e-15)


def test_project_points_matches_cv2_project_points():
    cv2 = pytest.importorskip("cv2")
    dist = np.array([-0.32, 0.12, 1.2e-3, -0.8e-3, -0.02])
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-5, 5, 50), rng.uniform(-3, 3, 50), rng.uniform(8, 60, 50)])
    uv, valid = g.project_points(pts, K_WAYMO, dist)
    assert valid.all()
    expected, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_WAYMO, dist)
    assert_allclose(uv, expected.reshape(-1, 2), rtol=0, atol=1e-6)


def test_distortion_must_have_five_coefficients():
    with pytest.raises(AssertionError):
        g.distort_normalized([0.1, 0.1], [0.1, 0.2, 0.3, 0.4])


NO_DISTORTION = None
WAYMO_DISTORTION = np.array([-0.32, 0.12, 1e-3, -1e-3, -0.02])
BARREL_DISTORTION = np.array([-0.5, 0.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("distortion", [NO_DISTORTION, WAYMO_DISTORTION, BARREL_DISTORTION])
def test_points_behind_or_on_the_camera_plane_are_invalid_with_nan_uv(distortion):
    pts = np.array(
        [
            [1.0, 2.0, -1.0],
            [1.0, 2.0, 0.0],
            [1.0, 2.0, -0.0],
            [0.0, 0.0, 0.0],
            [1e-9, 1e-9, g.MIN_PROJECTION_DEPTH_M],
            [1e-9, 1e-9, 0.5 * g.MIN_PROJECTION_DEPTH_M],
            [0.1, 0.1, 1.0],
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv, valid = g.project_points(pts, K_WAYMO, distortion)
    assert_array_equal(valid, [False] * 6 + [True])
    assert np.isnan(uv[:6]).all()
    assert np.isfinite(uv[6]).all()


def test_min_depth_is_configurable():
    uv, valid = g.project_points([[0.0, 0.0, 0.5], [0.0, 0.0, 2.0]], K_WAYMO, min_depth_m=1.0)
    assert_array_equal(valid, [False, True])
    assert np.isnan(uv[0]).all()
    assert_allclose(uv[1], [960.0, 640.0], rtol=0, atol=0)


@pytest.mark.parametrize("distortion", [NO_DISTORTION, WAYMO_DISTORTION, BARREL_DISTORTION])
def test_non_finite_points_are_invalid_without_warnings(distortion):
    inf, nan = np.inf, np.nan
    pts = np.array(
        [
            [nan, 0.0, 1.0],
            [0.0, nan, 1.0],
            [0.0, 0.0, nan],
            [inf, 0.0, 1.0],
            [0.0, inf, 1.0],
            [-inf, inf, 1.0],
            [0.0, 0.0, inf],
            [1.0, 1.0, -inf],
            [0.2, -0.1, 1.0],
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv, valid = g.project_points(pts, K_WAYMO, distortion)
    assert_array_equal(valid, [False] * 8 + [True])
    assert np.isnan(uv[:8]).all()
    expected, _ = g.project_points(pts[8:], K_WAYMO, distortion)
    assert_allclose(uv[8], expected[0], rtol=0, atol=0)


def test_far_off_axis_points_that_fold_back_under_barrel_distortion_are_invalid():
    # k1 = -0.5: r (1 - 0.5 r^2) peaks at r = sqrt(2/3); beyond it the model folds back.
    r_max = np.sqrt(2.0 / 3.0)
    assert_allclose(g.max_monotonic_radius(BARREL_DISTORTION), r_max, rtol=0, atol=1e-12)
    radii = np.array([1.3, np.sqrt(2.0), 1.6, 3.0, 50.0])
    directions = np.array([[1.0, 0.0], [0.6, 0.8], [-1.0, 0.0], [-0.8, 0.6], [0.6, -0.8]])
    xy = radii[:, None] * directions
    # Premise: the folded model would put most of these right inside the image.
    folded_uv = g.distort_normalized(xy, BARREL_DISTORTION) * 2055.0 + [960.0, 640.0]
    assert g.in_image(folded_uv[:3], WIDTH, HEIGHT).all()
    depth = 7.0
    pts = np.column_stack([xy * depth, np.full(len(xy), depth)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv, valid = g.project_points(pts, K_WAYMO, BARREL_DISTORTION)
    assert not valid.any()
    assert np.isnan(uv).all()


def test_points_just_inside_the_monotonic_radius_stay_valid():
    r_max = np.sqrt(2.0 / 3.0)
    pts = np.array([[0.999 * r_max, 0.0, 1.0], [0.0, -0.5 * r_max, 1.0], [1.001 * r_max, 0.0, 1.0]])
    uv, valid = g.project_points(pts, K_WAYMO, BARREL_DISTORTION)
    assert_array_equal(valid, [True, True, False])
    expected_u = 960.0 + 2055.0 * 0.999 * r_max * (1 - 0.5 * (0.999 * r_max) ** 2)
    assert_allclose(uv[0], [expected_u, 640.0], rtol=0, atol=1e-9)


def test_points_outside_the_image_stay_valid():
    uv, valid = g.project_points([[10.0, 0.0, 1.0], [0.0, -3.0, 0.1]], K_WAYMO)
    assert valid.all()
    assert_allclose(uv, [[960.0 + 20550.0, 640.0], [960.0, 640.0 - 61650.0]], rtol=1e-12)
    assert not g.in_image(uv, WIDTH, HEIGHT).any()


def test_in_image_uses_pixel_footprints():
    eps = 1e-9
    uv = np.array(
        [
            [-0.5, -0.5],
            [-0.5 - eps, 0.0],
            [0.0, -0.5 - eps],
            [WIDTH - 0.5 - eps, HEIGHT - 0.5 - eps],
            [WIDTH - 0.5, 0.0],
            [0.0, HEIGHT - 0.5],
            [np.nan, 0.0],
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inside = g.in_image(uv, WIDTH, HEIGHT)
    assert_array_equal(inside, [True, False, False, True, False, False, False])


def test_pixel_grid_is_row_major_pixel_centres():
    assert_array_equal(g.pixel_grid(3, 2), [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]])
    assert g.pixel_grid(3, 2).dtype == np.float64


def test_unproject_without_depth_returns_rays_with_unit_z():
    rays = g.unproject_pixels([[960.0, 640.0], [960.0 + 2055.0, 640.0 - 1027.5]], K_WAYMO)
    assert_allclose(rays, [[0.0, 0.0, 1.0], [1.0, -0.5, 1.0]], rtol=0, atol=1e-15)


def test_unproject_with_depth_scales_the_ray_to_that_z_depth():
    pts = g.unproject_pixels([[960.0 + 2055.0, 640.0 - 1027.5]], K_WAYMO, depth_m=[4.0])
    assert_allclose(pts, [[4.0, -2.0, 4.0]], rtol=0, atol=1e-14)


def test_undistort_without_distortion_returns_a_copy():
    xy = np.array([[0.1, 0.2]])
    out = g.undistort_normalized(xy, None)
    assert_array_equal(out, xy)
    assert out is not xy


@FAST
@given(finite(-2.0, 2.0), finite(-2.0, 2.0), finite(0.1, 1e3))
def test_project_then_unproject_round_trips_without_distortion(x, y, z):
    pt = np.array([[x * z, y * z, z]])
    uv, valid = g.project_points(pt, K_WAYMO)
    assert valid.all()
    assert_allclose(g.unproject_pixels(uv, K_WAYMO, depth_m=[z]), pt, rtol=1e-12, atol=1e-12)


@FAST
@given(finite(-0.5, WIDTH - 0.5), finite(-0.5, HEIGHT - 0.5), finite(0.1, 1e3))
def test_unproject_then_project_round_trips_without_distortion(u, v, depth):
    pt = g.unproject_pixels(np.array([[u, v]]), K_WAYMO, depth_m=[depth])
    assert_allclose(pt[0, 2], depth, rtol=0, atol=0)
    uv, valid = g.project_points(pt, K_WAYMO)
    assert valid.all()
    assert_allclose(uv, [[u, v]], rtol=0, atol=1e-9)


@SLOW
@given(waymo_like_distortion(), finite(0.0, 0.95), finite(-np.pi, np.pi), finite(0.5, 200.0))
def test_project_then_unproject_round_trips_with_distortion_inside_the_image(dist, frac, phi, z):
    r = frac * min(g.max_monotonic_radius(dist), 1.0)
    pt = np.array([[r * np.cos(phi) * z, r * np.sin(phi) * z, z]])
    uv, valid = g.project_points(pt, K_WAYMO, dist)
    assert valid.all()
    assume(g.in_image(uv, WIDTH, HEIGHT).all())
    assert_allclose(g.unproject_pixels(uv, K_WAYMO, dist, depth_m=[z]), pt, rtol=0, atol=1e-10 * z)


@SLOW
@given(waymo_like_distortion(), finite(-0.5, WIDTH - 0.5), finite(-0.5, HEIGHT - 0.5))
def test_unproject_then_project_round_trips_with_distortion_inside_the_image(dist, u, v):
    ray = g.unproject_pixels(np.array([[u, v]]), K_WAYMO, dist)
    # Only pixels that some undistorted ray inside the monotonic region maps to are invertible.
    assume(np.hypot(ray[0, 0], ray[0, 1]) < 0.95 * g.max_monotonic_radius(dist))
    uv, valid = g.project_points(ray, K_WAYMO, dist)
    assert valid.all()
    assert_allclose(uv, [[u, v]], rtol=0, atol=1e-7)


@SLOW
@given(waymo_like_distortion(), finite(-0.6, 0.6), finite(-0.45, 0.45))
def test_undistort_inverts_distort_for_waymo_like_coefficients(dist, x, y):
    assume(np.hypot(x, y) < 0.9 * g.max_monotonic_radius(dist))
    xy = np.array([x, y])
    assert_allclose(g.undistort_normalized(g.distort_normalized(xy, dist), dist), xy, rtol=0, atol=1e-10)


def test_undistort_inverts_distort_on_a_grid_of_the_waymo_image():
    xy = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 41), np.linspace(-0.35, 0.35, 29)), axis=-1)
    back = g.undistort_normalized(g.distort_normalized(xy, WAYMO_DISTORTION), WAYMO_DISTORTION)
    assert back.shape == xy.shape
    assert_allclose(back, xy, rtol=0, atol=1e-10)


def brute_force_monotonic_radius(dist: np.ndarray, limit: float = 10.0, step: float = 1e-5) -> float:
    """First radius where r * radial(r^2) stops increasing, found by scanning the function itself."""
    r = np.arange(0.0, limit + step, step)
    k1, k2, _, _, k3 = dist
    s = r * r
    f = r * (1 + k1 * s + k2 * s * s + k3 * s * s * s)
    decreasing = np.flatnonzero(np.diff(f) <= 0.0)
    return float(min(r[decreasing[0]], limit)) if decreasing.size else limit


@pytest.mark.parametrize(
    "dist",
    [
        [-0.5, 0.0, 0.0, 0.0, 0.0],
        [-0.3, -0.05, 1e-3, 1e-3, 0.0],
        [-0.3, 0.05, 0.0, 0.0, 0.0],
        [0.1, -0.2, 0.0, 0.0, 0.0],
        [-0.2, 0.01, 0.0, 0.0, -0.05],
        [0.05, 0.01, 0.0, 0.0, -0.01],
        [-0.35, 0.12, 1e-3, -1e-3, -0.02],
        [0.0, 0.0, 0.0, 0.0, 0.0],
        [0.2, 0.1, 0.0, 0.0, 0.01],
    ],
)
def test_max_monotonic_radius_matches_a_brute_force_search(dist):
    expected = brute_force_monotonic_radius(np.array(dist))
    assert_allclose(g.max_monotonic_radius(dist), expected, rtol=0, atol=2e-5)


def test_max_monotonic_radius_of_pure_k1_barrel_is_closed_form():
    for k1 in [-0.05, -0.2, -0.5, -1.0]:
        assert_allclose(g.max_monotonic_radius([k1, 0, 0, 0, 0]), np.sqrt(-1.0 / (3.0 * k1)), rtol=1e-12)


@pytest.mark.parametrize("k3", [1e-60, 1e-100, 1e-200, 5e-324, -1e-100])
@pytest.mark.parametrize("base", [[-0.3, 0.0, 0.0, 0.0], [-0.35, 0.1, 0.0, 0.0], [-0.3, -0.05, 0.0, 0.0]])
def test_max_monotonic_radius_is_unaffected_by_a_negligible_k3(base, k3):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with_k3 = g.max_monotonic_radius([*base, k3])
    assert_allclose(with_k3, g.max_monotonic_radius([*base, 0.0]), rtol=1e-12)
    assert_allclose(with_k3, brute_force_monotonic_radius(np.array([*base, 0.0])), rtol=0, atol=2e-5)


def test_max_monotonic_radius_is_capped_by_the_search_limit():
    dist = [-0.001, 0.0, 0.0, 0.0, 0.0]  # turning point at sqrt(1 / 0.003) ~ 18.26
    assert g.max_monotonic_radius(dist) == 10.0
    assert_allclose(g.max_monotonic_radius(dist, search_limit=30.0), np.sqrt(1 / 0.003), rtol=1e-12)
    assert g.max_monotonic_radius(None, search_limit=4.0) == 4.0


# --------------------------------------------------------------------------------------------
# Boxes


def test_box_corners_of_an_axis_aligned_box_follow_the_waymo_order():
    corners = g.box_corners([1.0, 2.0, 3.0], [4.0, 2.0, 1.0], 0.0)
    expected = [
        [3, 3, 2.5],
        [-1, 3, 2.5],
        [-1, 1, 2.5],
        [3, 1, 2.5],
        [3, 3, 3.5],
        [-1, 3, 3.5],
        [-1, 1, 3.5],
        [3, 1, 3.5],
    ]
    assert_allclose(corners, expected, rtol=0, atol=0)


def test_box_corners_rotate_with_a_quarter_turn_of_yaw():
    corners = g.box_corners([1.0, 2.0, 3.0], [4.0, 2.0, 1.0], np.pi / 2)
    # Local (+2, +1) becomes (-1, +2) after a quarter turn.
    assert_allclose(corners[0], [0.0, 4.0, 2.5], rtol=0, atol=1e-15)
    assert_allclose(corners[2], [2.0, 0.0, 2.5], rtol=0, atol=1e-15)


def test_box_corner_faces_are_counter_clockwise_seen_from_above():
    corners = g.box_corners([5.0, -3.0, 1.0], [4.5, 1.8, 1.6], 2.2)
    for face in (corners[:4], corners[4:]):
        xy = face[:, :2]
        signed_area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
        assert_allclose(signed_area, 4.5 * 1.8, rtol=1e-12)
    assert_allclose(corners[:4, 2], 0.2, rtol=0, atol=1e-15)
    assert_allclose(corners[4:, 2], 1.8, rtol=0, atol=1e-15)


def test_box_edges_have_the_box_dimensions():
    corners = g.box_corners([0.0, 0.0, 0.0], [4.0, 2.0, 1.0], 0.7)
    lengths = [np.linalg.norm(corners[a] - corners[b]) for a, b in g.BOX_EDGES]
    assert len(g.BOX_EDGES) == 12
    assert_allclose(sorted(lengths), [1.0] * 4 + [2.0] * 4 + [4.0] * 4, rtol=1e-14)


@FAST
@given(vec3(), vec3(0.1, 20.0), finite(-np.pi, np.pi), finite(-10.0, 10.0))
def test_box_corners_are_equivariant_under_yaw_rotation(center, size, yaw, turn):
    r = g.rotation_z(turn)
    rotated = g.box_corners(r @ center, size, yaw + turn)
    assert_allclose(rotated, g.box_corners(center, size, yaw) @ r.T, rtol=0, atol=1e-9)


@FAST
@given(vec3(), vec3(0.1, 20.0), finite(-np.pi, np.pi), vec3())
def test_box_corners_are_equivariant_under_translation(center, size, yaw, shift):
    assert_allclose(
        g.box_corners(center + shift, size, yaw), g.box_corners(center, size, yaw) + shift, rtol=0, atol=1e-9
    )


def test_box_corners_handle_batches():
    centers = np.array([[0.0, 0.0, 0.0], [10.0, -5.0, 1.0]])
    sizes = np.array([[4.0, 2.0, 1.5], [1.0, 1.0, 2.0]])
    yaws = np.array([0.3, -2.0])
    corners = g.box_corners(centers, sizes, yaws)
    assert corners.shape == (2, 8, 3)
    for i in range(2):
        assert_allclose(corners[i], g.box_corners(centers[i], sizes[i], yaws[i]), rtol=0, atol=0)


def local_to_world(local: np.ndarray, center: np.ndarray, yaw: float) -> np.ndarray:
    return local @ g.rotation_z(yaw).T + center


@FAST
@given(vec3(), vec3(0.1, 20.0), finite(-np.pi, np.pi))
def test_points_in_box_contains_its_own_corners_within_a_nanometre(center, size, yaw):
    corners = g.box_corners(center, size, yaw)
    assert g.points_in_box(corners, center, size, yaw, margin_m=1e-9).all()


def test_points_in_box_counts_exact_boundary_points_as_inside():
    center, size = np.array([1.0, 2.0, 3.0]), np.array([4.0, 2.0, 1.0])
    corners = g.box_corners(center, size, 0.0)
    face_centres = center + np.array([[2.0, 0, 0], [0, -1.0, 0], [0, 0, 0.5]])
    assert g.points_in_box(np.concatenate([corners, face_centres]), center, size, 0.0).all()


@FAST
@given(vec3(), vec3(0.1, 20.0), finite(-np.pi, np.pi), point_clouds(-1.0, 1.0))
def test_points_in_box_contains_shrunk_points_and_rejects_enlarged_ones(center, size, yaw, unit):
    # `unit` in [-1, 1]^3 scaled to the box; the largest coordinate is pushed onto the boundary.
    scale = np.max(np.abs(unit), axis=1, keepdims=True)
    assume(np.all(scale > 1e-3))
    on_boundary = unit / scale * 0.5 * size
    inside = local_to_world(0.999 * on_boundary, center, yaw)
    outside = local_to_world(1.001 * on_boundary, center, yaw)
    assert g.points_in_box(inside, center, size, yaw).all()
    assert not g.points_in_box(outside, center, size, yaw).any()


@FAST
@given(vec3(), vec3(0.1, 20.0), finite(-np.pi, np.pi), finite(0.01, 2.0))
def test_margin_enlarges_the_box_on_every_side(center, size, yaw, margin):
    half = 0.5 * size
    signs = g.BOX_CORNER_SIGNS
    just_inside = local_to_world(signs * (half + 0.99 * margin), center, yaw)
    just_outside = local_to_world(signs * (half + 1.01 * margin), center, yaw)
    assert g.points_in_box(just_inside, center, size, yaw, margin_m=margin).all()
    assert not g.points_in_box(just_inside, center, size, yaw).any()
    assert not g.points_in_box(just_outside, center, size, yaw, margin_m=margin).any()


def test_points_in_box_follows_the_yaw_of_the_footprint():
    pts = np.array([[0.0, 1.5, 0.0], [1.5, 0.0, 0.0]])
    assert_array_equal(g.points_in_box(pts, [0, 0, 0], [4.0, 1.0, 1.0], np.pi / 2), [True, False])
    assert_array_equal(g.points_in_box(pts, [0, 0, 0], [4.0, 1.0, 1.0], 0.0), [False, True])


def test_points_in_boxes_returns_minus_one_outside_every_box():
    centers = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    sizes = np.array([[2.0, 2.0, 2.0], [2.0, 2.0, 2.0]])
    pts = np.array([[5.0, 0.0, 0.0], [0.0, 0.0, 1.5], [10.0, 1.5, 0.0], [0.5, 0.5, 0.5], [10.0, 0.0, -1.0]])
    out = g.points_in_boxes(pts, centers, sizes, [0.0, 0.3])
    assert out.dtype == np.int64
    assert_array_equal(out, [-1, -1, -1, 0, 1])


def test_points_in_boxes_returns_the_first_box_index_for_overlaps():
    centers = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    sizes = np.array([[2.0, 2.0, 2.0], [2.0, 2.0, 2.0]])
    pts = np.array([[0.5, 0.0, 0.0], [1.8, 0.0, 0.0], [-0.8, 0.0, 0.0]])
    assert_array_equal(g.points_in_boxes(pts, centers, sizes, [0.0, 0.0]), [0, 1, 0])
    assert_array_equal(g.points_in_boxes(pts, centers[::-1], sizes, [0.0, 0.0]), [0, 0, 1])


def test_points_in_boxes_with_no_boxes_or_no_points():
    assert_array_equal(
        g.points_in_boxes(np.zeros((3, 3)), np.zeros((0, 3)), np.zeros((0, 3)), []), [-1, -1, -1]
    )
    assert g.points_in_boxes(np.zeros((0, 3)), [[0.0, 0, 0]], [[1.0, 1, 1]], [0.0]).shape == (0,)


def test_points_in_boxes_finds_points_in_the_corners_added_by_the_margin():
    # A 2 m cube with a 1 m margin reaches the corner (2, 2, 2), at 2 * sqrt(3) ~ 3.46 m from the
    # centre: the coarse sphere around the box must cover the enlarged box, not the box plus margin.
    pts = np.array([[1.9, 1.9, 1.9], [-1.95, 1.95, -1.95]])
    assert g.points_in_box(pts, [0.0, 0.0, 0.0], [2.0, 2.0, 2.0], 0.0, margin_m=1.0).all()
    assert_array_equal(
        g.points_in_boxes(pts, [[0.0, 0.0, 0.0]], [[2.0, 2.0, 2.0]], [0.0], margin_m=1.0), [0, 0]
    )


@st.composite
def boxes_and_points(draw: st.DrawFn):
    m = draw(st.integers(1, 4))
    centers = np.array(draw(st.lists(vec3(-5.0, 5.0), min_size=m, max_size=m)))
    sizes = np.array(draw(st.lists(vec3(0.1, 6.0), min_size=m, max_size=m)))
    yaws = np.array(draw(st.lists(finite(-np.pi, np.pi), min_size=m, max_size=m)))
    margin = draw(st.sampled_from([0.0, 0.0, 0.1, 1.0, 3.0]))
    n = draw(st.integers(1, 12))
    owners = draw(st.lists(st.integers(0, m - 1), min_size=n, max_size=n))
    unit = np.array(draw(st.lists(vec3(-1.3, 1.3), min_size=n, max_size=n)))
    # Points scattered around (and often exactly on the corners of) the enlarged boxes.
    on_corner = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    unit[on_corner] = np.sign(unit[on_corner]) + (unit[on_corner] == 0)
    pts = np.array(
        [
            local_to_world(u * (0.5 * sizes[o] + margin), centers[o], yaws[o])
            for u, o in zip(unit, owners, strict=True)
        ]
    )
    return pts, centers, sizes, yaws, margin


@FAST
@given(boxes_and_points())
def test_points_in_boxes_agrees_with_the_first_matching_points_in_box(case):
    pts, centers, sizes, yaws, margin = case
    masks = np.array(
        [g.points_in_box(pts, c, s, y, margin) for c, s, y in zip(centers, sizes, yaws, strict=True)]
    )
    expected = np.where(masks.any(axis=0), np.argmax(masks, axis=0), -1)
    assert_array_equal(g.points_in_boxes(pts, centers, sizes, yaws, margin), expected)
