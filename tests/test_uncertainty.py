"""Stereo Forcing's uncertainty maps: the localization potential against its closed form and against
central differences of a plain projection, the entropy, random and coverage maps, and the maps'
range on hard inputs (holes, zero, tiny and huge depths, broken cameras)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import geometry
from phigenesis.models.depth_bins import DepthBins, entropy, entropy_from_log_probs
from phigenesis.models.uncertainty import (
    DEFAULT_LOG_DEPTH_STEP,
    HistoryViews,
    UncertaintyConfig,
    coverage_map,
    depth_bin_width_m,
    entropy_map,
    localization_potential,
    localization_potential_to_u,
    random_map,
    uncertainty_map,
)

H, W = 7, 9  # target images; the optical axis passes through pixel (CX, CY)
CX, CY = 3, 2


def intrinsics(fx: float, fy: float, cx: float, cy: float, skew: float = 0.0) -> torch.Tensor:
    return torch.tensor([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)


def pose(
    rotation: np.ndarray | None = None, translation: tuple[float, float, float] = (0, 0, 0)
) -> torch.Tensor:
    rotation = np.eye(3) if rotation is None else rotation
    return torch.from_numpy(geometry.make_transform(rotation, np.asarray(translation, dtype=np.float64)))


def lateral_lp(fx: float, fy: float, depth_m: float, history_translation: tuple[float, float, float]):
    """LP of a constant-depth target at the origin against one history camera of the same
    orientation at ``history_translation``, its principal point placed so that the target's optical
    axis projects to history pixel (4, 3)."""
    k_t = intrinsics(fx, fy, CX, CY)[None]
    bx, by, _ = history_translation
    k_h = intrinsics(fx, fy, 4 + fx * bx / depth_m, 3 + fy * by / depth_m)[None]
    depth = torch.full((1, H, W), depth_m, dtype=torch.float64)
    return localization_potential(
        depth, k_t, pose()[None], k_h, pose(None, history_translation)[None], (7, 9)
    )


@settings(max_examples=60, deadline=None)
@given(
    st.floats(50.0, 2000.0),
    st.floats(0.05, 5.0),
    st.sampled_from([1.0, -1.0]),
    st.floats(0.5, 200.0),
    st.sampled_from(["x", "y"]),
)
def test_lateral_baseline_gives_focal_times_baseline_over_depth_squared_on_the_axis(f, b, sign, d, axis):
    fx, fy = f, 0.8 * f  # the baseline's own focal length counts: fx along x, fy along y
    t = (sign * b, 0.0, 0.0) if axis == "x" else (0.0, sign * b, 0.0)
    lp = lateral_lp(fx, fy, d, t)
    expected = (fx if axis == "x" else fy) * b / d**2
    assert lp.dtype == torch.float64
    assert abs(lp[0, CY, CX].item() - expected) <= 1e-9 * expected


def test_reference_note_two_view_formula_matches_an_oblique_baseline():
    # Baseline b at angle theta to the ray (in the x-z plane): |d phi / d d| = b sin(theta) /
    # (d^2 + b^2 - 2 b d cos(theta)); in pixels near the history's principal point it is f times that.
    f, b, d, theta = 500.0, 2.0, 10.0, math.radians(60.0)
    t = (b * math.sin(theta), 0.0, b * math.cos(theta))
    k_t = intrinsics(f, f, CX, CY)[None]
    # Turn the history camera to look at the point so that it sees it on its principal ray.
    yaw = math.atan2(-t[0], d - t[2])
    rot = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]])
    depth = torch.full((1, H, W), d, dtype=torch.float64)
    lp = localization_potential(
        depth, k_t, pose()[None], intrinsics(f, f, 4, 3)[None], pose(rot, t)[None], (7, 9)
    )
    expected = f * b * math.sin(theta) / (d**2 + b**2 - 2 * b * d * math.cos(theta))
    np.testing.assert_allclose(lp[0, CY, CX].item(), expected, rtol=1e-9)


def test_history_camera_at_the_target_position_gives_zero_whatever_its_rotation():
    k = intrinsics(120.0, 110.0, 4.3, 2.7, skew=1.5)[None]
    depth = torch.linspace(1.0, 60.0, H * W, dtype=torch.float64).reshape(1, H, W)
    target = pose(geometry.euler_zyx_to_matrix(0.1, -0.2, 0.3), (1.0, -2.0, 0.5))
    turn = geometry.euler_zyx_to_matrix(0.05, 0.1, -0.08)
    k_hist = intrinsics(120.0, 110.0, 200.0, 200.0)[None]  # a wide image: every point is inside
    for rotation in (np.eye(3), turn):
        history = target.clone()
        history[:3, :3] = torch.from_numpy(rotation) @ target[:3, :3]
        lp = localization_potential(depth, k, target[None], k_hist, history[None], (400, 400))
        assert lp.abs().max().item() < 1e-9
        history[:3, 3] += 0.1  # moved off the target's centre, every pixel has a potential
        moved = localization_potential(depth, k, target[None], k_hist, history[None], (400, 400))
        assert moved.min().item() > 1e-3


def test_point_behind_a_history_camera_gives_zero():
    k = intrinsics(100.0, 100.0, CX, CY)[None]
    depth = torch.full((1, H, W), 10.0, dtype=torch.float64)
    # Beyond the point, looking the same way: the point is 10 m behind it.
    beyond = pose(None, (0.5, 0.0, 20.0))[None]
    lp = localization_potential(depth, k, pose()[None], k, beyond, (H, W))
    assert lp.abs().max().item() == 0.0
    # Turned around there, it sees the point in front and has a potential.
    turned = pose(np.diag([-1.0, 1.0, -1.0]), (0.5, 0.0, 20.0))[None]
    lp = localization_potential(depth, k, pose()[None], k, turned, (H, W))
    assert lp[0, CY, CX].item() > 0.0


@pytest.mark.parametrize(
    ("u_on_history", "inside"), [(-0.4, True), (-0.6, False), (9 - 0.51, True), (8.5, False)]
)
def test_projection_outside_the_history_image_gives_zero_with_pixel_centres_at_integers(u_on_history, inside):
    f, b, d = 200.0, 1.0, 10.0  # the axis point lands at history u = cx_h - f b / d
    k = intrinsics(f, f, CX, CY)[None]
    k_h = intrinsics(f, f, u_on_history + f * b / d, 3.0)[None]
    depth = torch.full((1, H, W), d, dtype=torch.float64)
    lp = localization_potential(depth, k, pose()[None], k_h, pose(None, (b, 0, 0))[None], (7, 9))
    assert (lp[0, CY, CX].item() > 0) == inside
    if inside:
        np.testing.assert_allclose(lp[0, CY, CX].item(), f * b / d**2, rtol=1e-9)


@pytest.mark.parametrize(
    ("history_depth_m", "visible"),
    [(5.0, False), (10.0 / 1.06, False), (10.0 / 1.04, True), (10.0, True), (30.0, True), (0.0, True)],
)
def test_occlusion_by_a_history_depth_map_gives_zero(history_depth_m, visible):
    # The axis point at 10 m sits at z = 10 m in the history camera; 5 % tolerance, 0 = unknown.
    f, b, d = 200.0, 1.0, 10.0
    k = intrinsics(f, f, CX, CY)[None]
    k_h = intrinsics(f, f, 4 + f * b / d, 3.0)[None]
    depth = torch.full((1, H, W), d, dtype=torch.float64)
    history_depth = torch.full((1, 7, 9), 50.0, dtype=torch.float64)
    history_depth[0, 3, 4] = history_depth_m  # the pixel the axis point projects to
    lp = localization_potential(
        depth, k, pose()[None], k_h, pose(None, (b, 0, 0))[None], (7, 9), history_depth_m=history_depth
    )
    assert (lp[0, CY, CX].item() > 0) == visible


def test_several_history_views_take_the_largest_potential():
    f, d = 300.0, 12.0
    k = intrinsics(f, f, CX, CY)[None]
    baselines = [0.5, 2.0, -1.0, 0.0]
    k_h = torch.stack([intrinsics(f, f, 4 + f * b / d, 3.0) for b in baselines])
    poses = torch.stack([pose(None, (b, 0.0, 0.0)) for b in baselines])
    depth = torch.full((2, H, W), d, dtype=torch.float64)
    k2, target = k.expand(2, 3, 3), pose()[None].expand(2, 4, 4)
    lp = localization_potential(depth, k2, target, k_h, poses, (7, 9))
    np.testing.assert_allclose(lp[:, CY, CX].numpy(), f * 2.0 / d**2, rtol=1e-9)
    flipped = localization_potential(depth, k2, target, k_h.flip(0), poses.flip(0), (7, 9))
    assert torch.equal(lp, flipped)
    singles = [
        localization_potential(depth, k2, target, k_h[i : i + 1], poses[i : i + 1], (7, 9)) for i in range(4)
    ]
    assert torch.equal(lp, torch.stack(singles).amax(0))


def reference_lp(depth, k_t, world_from_target, k_h, world_from_history, hw, rel_step=1e-5):
    """The plain twin: per pixel and history view, central differences of a numpy projection."""
    out = np.zeros(depth.shape)
    for v in range(depth.shape[0]):
        k_inv = np.linalg.inv(k_t[v])
        for row in range(depth.shape[1]):
            for col in range(depth.shape[2]):
                d = depth[v, row, col]
                ray = k_inv @ np.array([col, row, 1.0])
                for n in range(k_h.shape[0]):
                    history_from_target = np.linalg.inv(world_from_history[n]) @ world_from_target[v]

                    def project(depth_m, n=n, ray=ray, history_from_target=history_from_target):
                        x = history_from_target[:3, :3] @ (depth_m * ray) + history_from_target[:3, 3]
                        return (k_h[n] @ x)[:2] / x[2], x[2]

                    (u, vv), z = project(d)
                    if z <= 1e-6 or not (-0.5 <= u < hw[1] - 0.5 and -0.5 <= vv < hw[0] - 0.5):
                        continue
                    h = rel_step * d
                    derivative = (project(d + h)[0] - project(d - h)[0]) / (2 * h)
                    out[v, row, col] = max(out[v, row, col], float(np.hypot(*derivative)))
    return out


def random_rig(seed: int, views: int, histories: int):
    rng = np.random.default_rng(seed)

    def random_pose(spread_m: float) -> np.ndarray:
        angles = rng.uniform(-0.25, 0.25, 3)
        return geometry.make_transform(
            geometry.euler_zyx_to_matrix(*angles), rng.uniform(-spread_m, spread_m, 3)
        )

    def random_k(hw: tuple[int, int]) -> np.ndarray:
        f = rng.uniform(0.6, 1.4) * hw[1]
        return np.array(
            [
                [f, rng.uniform(-2, 2), hw[1] / 2 + rng.uniform(-3, 3)],
                [0, f * rng.uniform(0.8, 1.2), hw[0] / 2 + rng.uniform(-3, 3)],
                [0, 0, 1],
            ]
        )

    hw = (12, 16)
    k_t = np.stack([random_k((5, 6)) for _ in range(views)])
    world_from_target = np.stack([random_pose(1.0) for _ in range(views)])
    k_h = np.stack([random_k(hw) for _ in range(histories)])
    world_from_history = np.stack([random_pose(3.0) for _ in range(histories)])
    depth = rng.uniform(2.0, 50.0, (views, 5, 6))
    return depth, k_t, world_from_target, k_h, world_from_history, hw


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_lp_equals_central_differences_of_the_projection_for_random_poses(seed):
    depth, k_t, world_from_target, k_h, world_from_history, hw = random_rig(seed, views=2, histories=3)
    expected = reference_lp(depth, k_t, world_from_target, k_h, world_from_history, hw)
    lp = localization_potential(
        *(torch.from_numpy(a) for a in (depth, k_t, world_from_target, k_h, world_from_history)), hw
    ).numpy()
    np.testing.assert_allclose(lp, expected, rtol=1e-6, atol=1e-9 * max(expected.max(), 1.0))


def test_leading_dims_flatten_and_float32_depth_gives_float32():
    depth, k_t, world_from_target, k_h, world_from_history, hw = random_rig(3, views=4, histories=2)
    args = [torch.from_numpy(a) for a in (depth, k_t, world_from_target, k_h, world_from_history)]
    flat = localization_potential(*args, hw)
    batched = localization_potential(
        args[0].reshape(2, 2, 5, 6), args[1].reshape(2, 2, 3, 3), args[2].reshape(2, 2, 4, 4), *args[3:], hw
    )
    assert batched.shape == (2, 2, 5, 6)
    assert torch.equal(batched.reshape(4, 5, 6), flat)
    single = localization_potential(args[0].float(), *args[1:], hw)
    assert single.dtype == torch.float32
    torch.testing.assert_close(single.double(), flat, rtol=1e-6, atol=1e-9)


def test_holes_and_unknown_depth_give_zero_potential():
    f, b, d = 200.0, 1.0, 10.0
    k = intrinsics(f, f, CX, CY)[None]
    k_h = intrinsics(f, f, 200, 200)[None]  # a wide image: every point is inside
    depth = torch.full((1, H, W), d, dtype=torch.float64)
    depth[0, 0, :3] = torch.tensor([0.0, math.nan, math.inf])
    alpha = torch.ones(1, H, W)
    alpha[0, 1, 0] = 0.49
    history = pose(None, (b, 0, 0))[None]
    lp = localization_potential(depth, k, pose()[None], k_h, history, (400, 400), alpha=alpha)
    assert lp[0, 0, :3].tolist() == [0.0, 0.0, 0.0]
    assert lp[0, 1, 0].item() == 0.0
    others = torch.ones(1, H, W, dtype=torch.bool)
    others[0, 0, :3] = others[0, 1, 0] = False
    assert (lp[others] > 0).all()


def test_entropy_of_one_hot_gives_u_one_and_uniform_gives_u_zero():
    k = 64
    probs = torch.zeros(2, H, W, k, dtype=torch.float64)
    probs[0, ..., 5] = 1.0  # one-hot
    probs[1] = 1.0 / k  # uniform
    h = entropy(probs)
    alpha = torch.ones(2, H, W, dtype=torch.float64)
    u = entropy_map(h, k, alpha)
    assert torch.equal(u[0], torch.ones(H, W, dtype=torch.float64))
    assert u[1].abs().max().item() < 1e-12
    half = entropy_from_log_probs(torch.log(torch.tensor([0.5, 0.5] + [0.0] * (k - 2))))
    np.testing.assert_allclose(entropy_map(half, k, torch.tensor(1.0)).item(), 1 - math.log(2) / math.log(k))


def test_entropy_map_is_clipped_to_the_unit_interval_and_zero_in_holes():
    h = torch.tensor([[-0.1, 0.0, 2.0, 10.0, math.nan, 1.0]])
    alpha = torch.tensor([[1.0, 1.0, 1.0, 1.0, 1.0, 0.2]])
    u = entropy_map(h, 16, alpha)
    expected = [1.0, 1.0, 1 - 2.0 / math.log(16), 0.0, 0.0, 0.0]
    np.testing.assert_allclose(u.numpy()[0], expected, rtol=1e-6)
    assert u.dtype == torch.float32


def test_random_map_is_constant_within_a_patch_and_differs_between_patches():
    alpha = torch.ones(2, 20, 30)
    u = random_map(alpha.shape, 8, torch.Generator().manual_seed(1), alpha)
    assert u.shape == (2, 20, 30) and u.dtype == torch.float32
    patches = []
    for r0 in range(0, 20, 8):
        for c0 in range(0, 30, 8):
            block = u[:, r0 : r0 + 8, c0 : c0 + 8]
            assert torch.equal(block, block[:, :1, :1].expand_as(block))  # constant within a patch
            patches.append(block[:, 0, 0])
    levels = torch.cat(patches)
    assert levels.unique().numel() == levels.numel() == 2 * 3 * 4  # cut patches at the edge count too
    assert levels.min().item() >= 0.0 and levels.max().item() <= 1.0


def test_random_map_is_reproducible_with_a_seed_and_changes_with_it():
    alpha = torch.ones(3, 16, 24)
    first = random_map(alpha.shape, 4, torch.Generator().manual_seed(7), alpha)
    again = random_map(alpha.shape, 4, torch.Generator().manual_seed(7), alpha)
    other = random_map(alpha.shape, 4, torch.Generator().manual_seed(8), alpha)
    assert torch.equal(first, again)
    assert not torch.equal(first, other)


def test_random_map_is_zero_in_holes():
    alpha = torch.rand(2, 16, 16, generator=torch.Generator().manual_seed(0))
    u = random_map(alpha.shape, 4, torch.Generator().manual_seed(3), alpha)
    assert (u[alpha < 0.5] == 0).all()
    assert (u[alpha >= 0.5] > 0).all()


def test_coverage_map_is_one_where_rendered_and_zero_in_holes():
    alpha = torch.tensor([[0.0, 0.49, 0.5, 0.7, 1.0, math.nan]])
    assert coverage_map(alpha).tolist() == [[0.0, 0.0, 1.0, 1.0, 1.0, 0.0]]
    assert coverage_map(alpha, hole_alpha=0.0).tolist() == [[1.0, 1.0, 1.0, 1.0, 1.0, 0.0]]


def test_lp_to_u_is_exp_of_pixels_moved_per_depth_bin_stable_or_one_minus_it_localised():
    bins = DepthBins(0.5, 120.0, 64)
    depth = torch.tensor([[2.0, 10.0, 10.0, 10.0, 80.0, 10.0]], dtype=torch.float64)
    alpha = torch.tensor([[1.0, 1.0, 1.0, 1.0, 1.0, 0.2]], dtype=torch.float64)  # the last is a hole
    width = depth_bin_width_m(depth, bins.step)
    # The bin's width is its edges' distance: a bin centred at d spans d e^(-step/2) .. d e^(step/2).
    np.testing.assert_allclose(
        width.numpy(), (depth * (math.exp(bins.step / 2) - math.exp(-bins.step / 2))).numpy()
    )
    # 0, 1, 3, 1e9, 0 px per bin, and a hole.
    lp = torch.tensor([[0.0, 1.0, 3.0, 1e9, 0.0, 1.0]], dtype=torch.float64) / width
    kwargs = {"log_depth_step": bins.step, "scale_px": 1.0}
    stable = localization_potential_to_u(lp, depth, alpha, **kwargs)
    np.testing.assert_allclose(
        stable.numpy()[0], [1.0, math.exp(-1), math.exp(-3), 0.0, 1.0, 0.0], rtol=1e-12, atol=1e-300
    )
    assert torch.equal(stable, localization_potential_to_u(lp, depth, alpha, **kwargs, trust="stable"))
    localised = localization_potential_to_u(lp, depth, alpha, **kwargs, trust="localised")
    np.testing.assert_allclose(
        localised.numpy()[0], [0.0, 1 - math.exp(-1), 1 - math.exp(-3), 1.0, 0.0, 0.0], rtol=1e-12
    )
    # Covered pixels: the two readings are each other's complement.
    np.testing.assert_allclose((stable + localised)[0, :5].numpy(), 1.0, rtol=1e-12)
    wide = localization_potential_to_u(lp, depth, alpha, log_depth_step=bins.step, scale_px=3.0)
    np.testing.assert_allclose(wide[0, 2].item(), math.exp(-1), rtol=1e-12)
    with pytest.raises(ValueError, match="trust"):
        localization_potential_to_u(lp, depth, alpha, trust="sure")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="lp_trust"):
        UncertaintyConfig(lp_trust="sure")  # type: ignore[arg-type]


@pytest.mark.parametrize("trust", ["stable", "localised"])
def test_lateral_pair_u_follows_disparity_times_the_bins_relative_width(trust):
    f, b = 200.0, 1.5
    alpha = torch.ones(1, H, W)
    us = []
    for d in (5.0, 10.0, 40.0):
        lp = lateral_lp(f, f, d, (b, 0.0, 0.0))
        depth = torch.full((1, H, W), d, dtype=torch.float64)
        u = localization_potential_to_u(lp, depth, alpha, trust=trust)
        moved_px = f * b / d * 2 * math.sinh(DEFAULT_LOG_DEPTH_STEP / 2)
        want = math.exp(-moved_px) if trust == "stable" else 1 - math.exp(-moved_px)
        np.testing.assert_allclose(u[0, CY, CX].item(), want, rtol=1e-9)
        us.append(u[0, CY, CX].item())
    if trust == "stable":
        assert 0 < us[0] < us[1] < us[2] < 1  # a far point's render barely moves with its depth error
    else:
        assert us[0] > us[1] > us[2] > 0  # farther points are less well localised


def hard_inputs():
    values = [0.0, 1e-6, 1e6, math.nan, math.inf, 5.0, 1e-300, 20.0]
    depth = torch.tensor(values * 8, dtype=torch.float64)[: 2 * 4 * 6].reshape(2, 4, 6)
    k = intrinsics(50.0, 50.0, 2.5, 1.5).expand(2, 3, 3)
    targets = torch.stack([pose(), pose(None, (0.0, 0.0, 1.0))])
    history = HistoryViews(
        intrinsics=torch.stack([intrinsics(50.0, 50.0, 3.0, 2.0)] * 3),
        world_from_camera=torch.stack(
            [
                pose(None, (1.0, 0.0, 0.0)),
                pose(None, (0.0, 0.0, 1e-6)),
                pose(np.diag([-1.0, 1.0, -1.0]), (0, 0, 3)),
            ]
        ),
        hw=(4, 6),
        depth_m=torch.tensor([0.0, 1e-6, 4.0, 1e6] * 18, dtype=torch.float64).reshape(3, 4, 6),
    )
    alpha = torch.tensor([1.0, 0.0, 0.5, math.nan] * 12).reshape(2, 4, 6)
    entropy_nats = torch.tensor([0.0, -1.0, math.nan, 100.0, 1.0, math.inf] * 8).reshape(2, 4, 6)
    return alpha, depth, k, targets, history, entropy_nats


@pytest.mark.parametrize("kind", ["random", "entropy", "localization_potential", "coverage"])
def test_all_maps_lie_in_the_unit_interval_without_nan_on_hard_inputs(kind):
    alpha, depth, k, targets, history, entropy_nats = hard_inputs()
    u = uncertainty_map(
        kind,
        alpha,
        config=UncertaintyConfig(num_bins=8, patch_px=2),
        generator=torch.Generator().manual_seed(0),
        entropy_nats=entropy_nats,
        depth_m=depth,
        intrinsics=k,
        world_from_camera=targets,
        history=history,
    )
    assert u.shape == alpha.shape
    assert torch.isfinite(u).all() and (u >= 0).all() and (u <= 1).all()
    assert (u[~(alpha >= 0.5)] == 0).all()


def test_hard_depths_give_finite_potentials_and_u():
    _, depth, k, targets, history, _ = hard_inputs()
    lp = localization_potential(
        depth,
        k,
        targets,
        history.intrinsics,
        history.world_from_camera,
        history.hw,
        history_depth_m=history.depth_m,
    )
    assert torch.isfinite(lp).all() and (lp >= 0).all()
    assert (lp[~(torch.isfinite(depth) & (depth > 0))] == 0).all()
    u = localization_potential_to_u(torch.full_like(depth, math.inf), depth, torch.ones_like(depth))
    assert torch.isfinite(u).all() and (u >= 0).all() and (u <= 1).all()


def broken_cameras():
    nan_pose = pose()
    nan_pose[0, 3] = math.nan
    scaled = pose(2.0 * np.eye(3))
    sheared = pose(np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    mirrored = pose(np.diag([1.0, 1.0, -1.0]))
    bottom = pose()
    bottom[3, 0] = 0.5
    nan_k = intrinsics(100.0, 100.0, 2.0, 2.0)
    nan_k[0, 2] = math.nan
    bad_row = intrinsics(100.0, 100.0, 2.0, 2.0)
    bad_row[2, 2] = 2.0
    return {
        "nan pose": (nan_pose, None),
        "scaled rotation": (scaled, None),
        "sheared rotation": (sheared, None),
        "mirror": (mirrored, None),
        "bottom row": (bottom, None),
        "fx zero": (None, intrinsics(0.0, 100.0, 2.0, 2.0)),
        "fx negative": (None, intrinsics(-100.0, 100.0, 2.0, 2.0)),
        "fy zero": (None, intrinsics(100.0, 0.0, 2.0, 2.0)),
        "nan intrinsics": (None, nan_k),
        "not a pinhole matrix": (None, bad_row),
    }


@pytest.mark.parametrize("which", ["target", "history"])
@pytest.mark.parametrize("case", list(broken_cameras()))
def test_broken_cameras_raise_a_clear_value_error(case, which):
    bad_pose, bad_k = broken_cameras()[case]
    good_k, good_pose = intrinsics(100.0, 100.0, 2.0, 2.0)[None], pose(None, (1.0, 0, 0))[None]
    k_t, pose_t, k_h, pose_h = good_k, pose()[None], good_k, good_pose
    if which == "target":
        k_t = k_t if bad_k is None else bad_k[None]
        pose_t = pose_t if bad_pose is None else bad_pose[None]
    else:
        k_h = k_h if bad_k is None else bad_k[None]
        pose_h = pose_h if bad_pose is None else bad_pose[None]
    depth = torch.full((1, 4, 5), 10.0, dtype=torch.float64)
    with pytest.raises(ValueError, match=which):
        localization_potential(depth, k_t, pose_t, k_h, pose_h, (4, 5))


def test_mismatched_shapes_raise_value_errors():
    k, p = intrinsics(100.0, 100.0, 2.0, 2.0)[None], pose()[None]
    depth = torch.ones(1, 4, 5, dtype=torch.float64)
    with pytest.raises(ValueError, match="intrinsics"):
        localization_potential(depth, k.expand(2, 3, 3), p, k, p, (4, 5))
    with pytest.raises(ValueError, match="history depth"):
        localization_potential(depth, k, p, k, p, (4, 5), history_depth_m=torch.ones(1, 5, 4))
    with pytest.raises(ValueError, match="alpha"):
        random_map((1, 4, 6), 2, torch.Generator(), torch.ones(1, 4, 5))
    with pytest.raises(ValueError, match="NaN"):
        localization_potential_to_u(torch.full((1, 2), math.nan), torch.ones(1, 2), torch.ones(1, 2))


def test_uncertainty_map_dispatches_each_kind_to_its_function():
    alpha, depth, k, targets, history, entropy_nats = hard_inputs()
    config = UncertaintyConfig(num_bins=8, patch_px=2, scale_px=0.5)
    common = {"alpha": alpha, "config": config}
    assert torch.equal(uncertainty_map("coverage", **common), coverage_map(alpha))
    assert torch.equal(
        uncertainty_map("random", **common, generator=torch.Generator().manual_seed(4)),
        random_map(alpha.shape, 2, torch.Generator().manual_seed(4), alpha),
    )
    assert torch.equal(
        uncertainty_map("entropy", **common, entropy_nats=entropy_nats), entropy_map(entropy_nats, 8, alpha)
    )
    lp = localization_potential(
        depth, k, targets, history.intrinsics, history.world_from_camera, history.hw, alpha, history.depth_m
    )
    got = uncertainty_map(
        "localization_potential",
        **common,
        depth_m=depth,
        intrinsics=k,
        world_from_camera=targets,
        history=history,
    )
    assert torch.equal(got, localization_potential_to_u(lp, depth, alpha, scale_px=0.5))
    localised = uncertainty_map(
        "localization_potential",
        alpha,
        config=UncertaintyConfig(num_bins=8, patch_px=2, scale_px=0.5, lp_trust="localised"),
        depth_m=depth,
        intrinsics=k,
        world_from_camera=targets,
        history=history,
    )
    assert torch.equal(
        localised, localization_potential_to_u(lp, depth, alpha, scale_px=0.5, trust="localised")
    )


def test_uncertainty_map_names_what_a_kind_is_missing():
    alpha = torch.ones(1, 4, 5)
    with pytest.raises(ValueError, match="generator"):
        uncertainty_map("random", alpha)
    with pytest.raises(ValueError, match="entropy_nats"):
        uncertainty_map("entropy", alpha)
    with pytest.raises(ValueError, match="history"):
        uncertainty_map(
            "localization_potential",
            alpha,
            depth_m=torch.ones(1, 4, 5),
            intrinsics=intrinsics(1.0, 1.0, 0.0, 0.0)[None],
            world_from_camera=pose()[None],
        )
    with pytest.raises(ValueError, match="kind"):
        uncertainty_map("lidar", alpha)  # type: ignore[arg-type]
