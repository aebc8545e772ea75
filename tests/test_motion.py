"""Tests for the analytic motion model of the synthetic source: paths, speed profiles, trajectories."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from phigenesis import geometry as g
from phigenesis.data.sources.synthetic.motion import Path, Segment, SpeedPhase, SpeedProfile, Trajectory

EXAMPLES = settings(max_examples=60, deadline=None)

#: Finite-difference step (m or s); central differences are then exact to ~1e-9 for these curves.
H = 1e-4


def finite(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(min_value=lo, max_value=hi, allow_nan=False, allow_infinity=False)


# Segments: straights or arcs of radius >= 10 m (curvature up to 0.1 / m, either sense).
segment = st.one_of(
    finite(0.5, 60.0).map(Segment),
    st.builds(Segment, finite(0.5, 60.0), finite(-0.1, 0.1)),
)


@st.composite
def paths(draw: st.DrawFn, max_segments: int = 5) -> Path:
    segs = draw(st.lists(segment, min_size=1, max_size=max_segments))
    start = (draw(finite(-500.0, 500.0)), draw(finite(-500.0, 500.0)))
    return Path(start, draw(finite(-np.pi, np.pi)), segs)


@st.composite
def speed_plans(draw: st.DrawFn) -> tuple[float, list[tuple[str, float, float]]]:
    """An initial speed and a plan of ramps (targets may be negative: build clamps them) and holds."""
    v0 = draw(finite(0.0, 15.0))
    steps = draw(
        st.lists(
            st.one_of(
                st.tuples(st.just("ramp"), finite(-3.0, 15.0), finite(0.3, 4.0)),
                st.tuples(st.just("hold"), finite(0.0, 5.0), st.just(0.0)),
            ),
            min_size=1,
            max_size=6,
        )
    )
    return v0, steps


def heading_vector(heading: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(heading), np.sin(heading)], axis=-1)


def left_normal(heading: np.ndarray) -> np.ndarray:
    return np.stack([-np.sin(heading), np.cos(heading)], axis=-1)


# --------------------------------------------------------------------------------------------
# Path


@EXAMPLES
@given(paths())
def test_path_positions_and_headings_are_continuous_at_segment_joints(path: Path) -> None:
    joints = np.append(path.s_start[1:], [0.0, path.length])  # inner joints and both ends
    eps = 1e-7
    xy_lo, h_lo, _ = path.pose(joints - eps)
    xy_hi, h_hi, _ = path.pose(joints + eps)
    assert np.all(np.linalg.norm(xy_hi - xy_lo, axis=1) <= 2 * eps + 1e-9)
    assert np.all(np.abs(h_hi - h_lo) <= 0.1 * 2 * eps + 1e-9)


@EXAMPLES
@given(paths())
def test_path_start_and_end_poses_match_the_segments(path: Path) -> None:
    (xy0, xy1), (h0, h1), _ = path.pose(np.array([0.0, path.length]))
    assert_allclose(xy0, path.start_xy, atol=1e-9)
    assert h0 == pytest.approx(path.start_heading, abs=1e-12)
    assert_allclose(xy1, path.end_xy, atol=1e-9)
    turned = sum(s.length_m * s.curvature_per_m for s in path.segments)
    assert h1 == pytest.approx(path.start_heading + turned, abs=1e-9)
    assert path.length == pytest.approx(sum(s.length_m for s in path.segments), rel=1e-12)


@EXAMPLES
@given(paths(), st.lists(finite(-0.5, 1.5), min_size=1, max_size=8))
def test_path_is_parameterised_by_arc_length(path: Path, fractions: list[float]) -> None:
    """|dp/ds| = 1, dp/ds points along the heading and dheading/ds is the curvature (also outside)."""
    s = np.array(fractions) * path.length
    xy_m, h_m, _ = path.pose(s - H)
    xy_p, h_p, _ = path.pose(s + H)
    _, heading, kappa = path.pose(s)
    tangent = (xy_p - xy_m) / (2 * H)
    assert_allclose(np.linalg.norm(tangent, axis=1), 1.0, atol=1e-6)
    # A curvature jump inside the stencil tilts the chord by at most H * |jump| / 4.
    assert_allclose(tangent, heading_vector(heading), atol=1e-5)
    # Away from joints the heading changes at the curvature's rate.
    away = np.min(np.abs(s[:, None] - np.append(path.s_start, path.length)[None]), axis=1) > 2 * H
    assert_allclose(((h_p - h_m) / (2 * H))[away], kappa[away], atol=1e-6)


@EXAMPLES
@given(paths(), finite(1e-6, 200.0))
def test_path_extrapolates_in_straight_lines_beyond_both_ends(path: Path, beyond: float) -> None:
    xy_after, h_after, k_after = path.pose(np.array([path.length + beyond]))
    assert_allclose(xy_after[0], path.end_xy + beyond * heading_vector(np.array(path.end_heading)), atol=1e-8)
    assert h_after[0] == pytest.approx(path.end_heading, abs=1e-12)
    assert k_after[0] == 0.0
    xy_before, h_before, k_before = path.pose(np.array([-beyond]))
    start_dir = heading_vector(np.array(path.start_heading))
    assert_allclose(xy_before[0], path.start_xy - beyond * start_dir, atol=1e-8)
    assert h_before[0] == pytest.approx(path.start_heading, abs=1e-12)
    assert k_before[0] == 0.0


def test_path_pose_of_a_quarter_circle_is_exact() -> None:
    radius = 10.0
    path = Path((0.0, 0.0), 0.0, [Segment(5.0), Segment(radius * np.pi / 2, 1.0 / radius), Segment(5.0)])
    (xy,), (h,), (k,) = path.pose(np.array([5.0 + radius * np.pi / 2]))
    assert_allclose(xy, [5.0 + radius, radius], atol=1e-12)
    assert h == pytest.approx(np.pi / 2, abs=1e-12)
    assert k == pytest.approx(0.0)  # the joint belongs to the following straight
    assert_allclose(path.end_xy, [5.0 + radius, radius + 5.0], atol=1e-12)
    # Middle of the arc: on the circle of centre (5, 10).
    (mid,), _, (k_mid,) = path.pose(np.array([5.0 + radius * np.pi / 4]))
    assert np.hypot(mid[0] - 5.0, mid[1] - radius) == pytest.approx(radius, abs=1e-12)
    assert k_mid == pytest.approx(0.1)


@pytest.mark.parametrize("curvature", [2e-12, -1e-10, 1e-8, 1e-6])
def test_nearly_straight_arcs_are_as_accurate_as_lines(curvature: float) -> None:
    """Regression: (sin(h1) - sin(h0)) / k lost ~1e-16 / k metres (30 um at k = 2e-12)."""
    path = Path((3.0, -2.0), 1.0, [Segment(50.0, curvature)])
    s = np.linspace(0.0, 50.0, 11)
    xy, heading, _ = path.pose(s)
    # Exact arc: chord 2 sin(k s / 2) / k along the mean heading 1 + k s / 2 (series to O(k^3)).
    chord = s * (1.0 - (curvature * s) ** 2 / 24.0)
    mean = 1.0 + curvature * s / 2
    expected = np.array([3.0, -2.0]) + chord[:, None] * heading_vector(mean)
    assert_allclose(xy, expected, atol=1e-12)
    assert_allclose(heading, 1.0 + curvature * s, atol=1e-15)
    assert_allclose(np.linalg.norm(np.diff(xy, axis=0), axis=1), 5.0, atol=1e-12)


@EXAMPLES
@given(paths(), finite(-4.5, 4.5), st.lists(finite(0.0, 0.999), min_size=1, max_size=10))
def test_offset_path_stays_at_a_constant_lateral_distance(
    path: Path, left: float, fracs: list[float]
) -> None:
    """Each point of the offset path is ``left`` metres along the original's left normal, same heading."""
    off = path.offset(left)
    # Corresponding arc lengths: each segment's length scales by (1 - curvature * left).
    s = np.array(fracs) * path.length
    idx = np.clip(np.searchsorted(path.s_start, s, side="right") - 1, 0, len(path.segments) - 1)
    scale = 1.0 - path.curvatures[idx] * left
    s_off = off.s_start[idx] + (s - path.s_start[idx]) * scale
    xy, heading, kappa = path.pose(s)
    xy_off, heading_off, kappa_off = off.pose(s_off)
    assert_allclose(xy_off, xy + left * left_normal(heading), atol=1e-7)
    assert_allclose(np.linalg.norm(xy_off - xy, axis=1), abs(left), atol=1e-7)
    assert_allclose(heading_off, heading, atol=1e-9)
    assert_allclose(kappa_off, kappa / scale, rtol=1e-9, atol=1e-12)
    assert off.length == pytest.approx(float(np.sum(np.diff(np.append(off.s_start, off.length)))))


def test_offset_beyond_an_arc_centre_is_an_error() -> None:
    path = Path((0.0, 0.0), 0.0, [Segment(10.0, 1 / 5.0)])
    with pytest.raises(ValueError, match="beyond the centre"):
        path.offset(5.0)
    assert path.offset(-5.0).length == pytest.approx(2 * 10.0)  # the outside of the arc is longer


@EXAMPLES
@given(paths(), st.lists(finite(-30.0, 300.0), min_size=1, max_size=10))
def test_reversed_path_traces_the_same_points_backwards(path: Path, s_values: list[float]) -> None:
    rev = path.reversed()
    s = np.array(s_values)
    xy, heading, kappa = path.pose(s)
    xy_rev, heading_rev, kappa_rev = rev.pose(path.length - s)
    assert rev.length == pytest.approx(path.length, rel=1e-12)
    assert_allclose(xy_rev, xy, atol=1e-7)
    assert_allclose(g.angle_difference(heading_rev, heading + np.pi), 0.0, atol=1e-9)
    # Curvature flips sign (a left turn driven backwards is a right turn); joints may differ.
    on_joint = np.isclose(s[:, None], np.append(path.s_start, path.length)[None], atol=1e-9).any(axis=1)
    assert_allclose(kappa_rev[~on_joint], -kappa[~on_joint], atol=1e-12)
    assert_allclose(rev.reversed().pose(s)[0], xy, atol=1e-7)


@EXAMPLES
@given(paths(max_segments=3), finite(0.0, 30.0), finite(0.0, 30.0), finite(-50.0, 300.0))
def test_extended_path_is_the_same_curve_shifted_by_the_added_length(
    path: Path, before: float, after: float, s: float
) -> None:
    ext = path.extended(before, after)
    assert ext.length == pytest.approx(path.length + before + after, rel=1e-12)
    xy, heading, _ = path.pose(np.array([s]))
    xy_ext, heading_ext, _ = ext.pose(np.array([s + before]))
    assert_allclose(xy_ext, xy, atol=1e-7)
    assert_allclose(heading_ext, heading, atol=1e-9)


def test_path_rejects_empty_or_non_positive_segments() -> None:
    with pytest.raises(ValueError, match="at least one segment"):
        Path((0, 0), 0.0, [])
    with pytest.raises(ValueError, match="positive"):
        Path((0, 0), 0.0, [Segment(5.0), Segment(0.0)])


# --------------------------------------------------------------------------------------------
# SpeedProfile


@EXAMPLES
@given(speed_plans(), finite(-5.0, 5.0), finite(-100.0, 100.0))
def test_speed_profile_arc_length_integrates_the_speed(
    plan: tuple[float, list[tuple[str, float, float]]], t0: float, s0: float
) -> None:
    v0, steps = plan
    prof = SpeedProfile.build(t0, s0, v0, steps)
    t = np.linspace(t0 - 3.0, prof.end_time_s + 3.0, 4001)
    s, v, _ = prof.state(t)
    # Trapezoidal integration is exact for piecewise-linear v up to the knots' cells: O(a dt^2).
    dt = t[1] - t[0]
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    assert_allclose(s - s[0], integral, atol=4.0 * dt**2 * (len(prof.phases) + 1) + 1e-9)
    assert prof.state(t0)[0] == pytest.approx(s0)
    # ds/dt = v and dv/dt = a away from the knots.
    knots = np.cumsum([t0] + [p.duration_s for p in prof.phases])
    tq = t[np.min(np.abs(t[:, None] - knots[None]), axis=1) > 2 * H]
    s_m, v_m, _ = prof.state(tq - H)
    s_p, v_p, _ = prof.state(tq + H)
    _, v_q, a_q = prof.state(tq)
    assert_allclose((s_p - s_m) / (2 * H), v_q, atol=1e-6)
    assert_allclose((v_p - v_m) / (2 * H), a_q, atol=1e-6)


@EXAMPLES
@given(speed_plans())
def test_speed_is_never_negative_and_arc_length_never_decreases(
    plan: tuple[float, list[tuple[str, float, float]]],
) -> None:
    v0, steps = plan
    prof = SpeedProfile.build(0.0, 0.0, v0, steps)
    t = np.linspace(-5.0, prof.end_time_s + 5.0, 2001)
    s, v, _ = prof.state(t)
    assert np.all(v >= 0.0)
    assert np.all(np.diff(s) >= -1e-9)


@EXAMPLES
@given(speed_plans(), finite(-10.0, 10.0))
def test_speed_profile_build_ramps_reach_their_targets(
    plan: tuple[float, list[tuple[str, float, float]]], t0: float
) -> None:
    v0, steps = plan
    prof = SpeedProfile.build(t0, 0.0, v0, steps)
    t, v_expected = t0, v0
    for kind, a, b in steps:
        if kind == "hold":
            t += a
        else:
            target = max(a, 0.0)
            t += abs(target - v_expected) / abs(b)
            v_expected = target
        assert prof.state(t)[1] == pytest.approx(v_expected, abs=1e-6)
    assert prof.end_time_s == pytest.approx(t, abs=1e-6)
    # After the plan the final speed is kept; before t0 the initial one.
    s_end, v_end, a_end = prof.state(t + 50.0)
    assert v_end == pytest.approx(v_expected, abs=1e-6) and a_end == 0.0
    assert s_end == pytest.approx(prof.state(t)[0] + 50.0 * v_end, abs=1e-6)
    assert prof.state(t0 - 2.0)[1] == pytest.approx(v0)
    assert prof.state(t0 - 2.0)[0] == pytest.approx(-2.0 * v0)


def test_speed_profile_build_does_not_drift_on_ramps_below_its_resolution() -> None:
    """Regression: a skipped 1e-9 m/s ramp used to shift the planned speed off the real one, so the
    final ramp to rest planned from 2 - 1e-9 m/s overshot below zero and build raised."""
    prof = SpeedProfile.build(0.0, 0.0, 0.0, [("ramp", 1e-9, 1.0), ("ramp", 2.0, 1.0), ("ramp", 0.0, 1.0)])
    _, v, _ = prof.state(np.array([2.0, 4.0, 10.0]))
    assert_allclose(v, [2.0, 0.0, 0.0], atol=1e-12)


def test_speed_profile_ramp_respects_its_acceleration() -> None:
    prof = SpeedProfile.build(1.0, 10.0, 10.0, [("hold", 2.0, 0.0), ("ramp", 0.0, 2.5), ("ramp", 5.0, 1.0)])
    # Brakes from t = 3 s for 4 s, stands for an instant at t = 7 s, accelerates to 5 m/s by t = 12 s.
    s, v, a = prof.state(np.array([2.0, 5.0, 7.0, 9.0, 12.0, 20.0]))
    assert_allclose(v, [10.0, 5.0, 0.0, 2.0, 5.0, 5.0], atol=1e-12)
    assert_allclose(a, [0.0, -2.5, 1.0, 1.0, 0.0, 0.0], atol=1e-12)
    assert_allclose(s[2], 10.0 + 2 * 10.0 + 0.5 * 10.0 * 4.0, atol=1e-12)  # 20 m hold + 20 m braking
    assert_allclose(s[4] - s[2], 0.5 * 5.0 * 5.0, atol=1e-12)


def test_speed_profile_rejects_negative_speeds_and_bad_plans() -> None:
    with pytest.raises(ValueError, match="negative"):
        SpeedProfile(0.0, 0.0, 2.0, [SpeedPhase(2.0, -2.0)])
    with pytest.raises(ValueError, match="positive acceleration"):
        SpeedProfile.build(0.0, 0.0, 2.0, [("ramp", 5.0, 0.0)])
    with pytest.raises(ValueError, match="unknown"):
        SpeedProfile.build(0.0, 0.0, 2.0, [("coast", 5.0, 1.0)])


# --------------------------------------------------------------------------------------------
# Trajectory


@EXAMPLES
@given(
    paths(),
    speed_plans(),
    finite(0.0, 2.0),
    st.sampled_from([0.0, np.pi]),
    st.lists(finite(-5.0, 30.0), min_size=1, max_size=8),
)
def test_trajectory_velocity_and_yaw_rate_equal_finite_differences(
    path: Path,
    plan: tuple[float, list[tuple[str, float, float]]],
    z: float,
    yaw_offset: float,
    times: list[float],
) -> None:
    v0, steps = plan
    traj = Trajectory(path, SpeedProfile.build(0.0, 0.0, v0, steps), z, yaw_offset)
    h = 1e-6  # small: an acceleration jump inside the stencil biases the difference by h |jump| / 4
    t = np.array(times)
    pos, yaw, vel, rate = traj.state(t)
    pos_m, yaw_m, _, _ = traj.state(t - h)
    pos_p, yaw_p, _, _ = traj.state(t + h)
    assert_allclose((pos_p - pos_m) / (2 * h), vel, atol=1e-5)
    # Yaw is wrapped; its derivative through the wrap is the yaw rate wherever the curvature does
    # not jump inside the stencil (and between the two one-sided rates where it does).
    fd_rate = g.angle_difference(yaw_p, yaw_m) / (2 * h)
    speed = np.linalg.norm(vel, axis=-1)
    assert np.all(np.abs(fd_rate - rate) <= 1e-5 + 0.2 * speed)
    k_m = path.pose(traj.speed.state(t - h)[0])[2]
    k_p = path.pose(traj.speed.state(t + h)[0])[2]
    assert_allclose(fd_rate[k_m == k_p], rate[k_m == k_p], atol=1e-5)
    assert np.all((yaw >= -np.pi) & (yaw < np.pi))
    assert_allclose(pos[:, 2], z)
    # The body's heading is the direction of travel turned by the yaw offset.
    moving = speed > 1e-6
    travel = np.arctan2(vel[moving, 1], vel[moving, 0])
    assert_allclose(g.angle_difference(yaw[moving], travel + yaw_offset), 0.0, atol=1e-9)
    # world_from_body agrees with the state.
    pose = traj.world_from_body(t)
    assert_allclose(pose[:, :3, 3], pos, atol=1e-12)
    assert_allclose(g.angle_difference(g.matrix_yaw(pose), yaw), 0.0, atol=1e-12)


def test_trajectory_is_static_only_without_speed_or_acceleration() -> None:
    path = Path((0.0, 0.0), 0.3, [Segment(10.0)])
    parked = Trajectory(path, SpeedProfile(0.0, 4.0, 0.0, []), 0.8, np.pi)
    assert parked.is_static()
    pos, yaw, vel, rate = parked.state(np.array([-10.0, 0.0, 10.0]))
    assert_allclose(pos, np.tile([4.0 * np.cos(0.3), 4.0 * np.sin(0.3), 0.8], (3, 1)), atol=1e-12)
    assert_allclose(yaw, g.wrap_angle(0.3 + np.pi))
    assert_allclose(vel, 0.0)
    assert_allclose(rate, 0.0)
    starting = Trajectory(path, SpeedProfile(0.0, 0.0, 0.0, [SpeedPhase(1.0, 1.0)]))
    assert not starting.is_static()
