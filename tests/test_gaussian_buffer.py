"""The Gaussian buffer (Stage 2's scene memory across rollout windows): de-duplication by voxel, moving
Gaussians without trails, re-basing, the cap and its eviction order, resumable state, bad input and a
render of its contents."""

from __future__ import annotations

import io
import math
import time

import pytest
import torch

from phigenesis.models.buffer import KEY_HALF, GaussianBuffer, rebase, voxel_keys
from phigenesis.models.gaussians import GaussianScene

K = 19  # unified classes


@pytest.fixture(autouse=True)
def one_thread():
    """One intra-op thread, restored after each test: the machine's cores are shared, and the
    speed asked for is one core's."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def make_scene(
    means: torch.Tensor,
    *,
    velocity: torch.Tensor | None = None,
    dynamic: torch.Tensor | None = None,
    time_s: float | torch.Tensor = 0.0,
    entropy: bool = False,
    seed: int = 0,
    origin: int = 0,
) -> GaussianScene:
    """N Gaussians at ``means`` (N, 3) metres; static unless ``dynamic``/``velocity`` say otherwise."""
    n = len(means)
    g = torch.Generator().manual_seed(seed)
    if velocity is None:
        velocity = torch.zeros(n, 3)
    if dynamic is None:
        dynamic = (velocity != 0).any(dim=1)
    return GaussianScene(
        means=means.float(),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(n, 4).clone(),
        scales=torch.full((n, 3), 0.05),
        opacities=torch.full((n,), 0.8),
        colors=torch.rand(n, 3, generator=g),
        semantic_logits=torch.randn(n, K, generator=g),
        velocity=velocity.float(),
        dynamic=dynamic,
        time_s=torch.as_tensor(time_s, dtype=torch.float32).expand(n).clone(),
        time_origin_micros=origin,
        depth_entropy=torch.rand(n, generator=g) if entropy else None,
    )


def random_scene(n: int, seed: int, *, centre_x: float = 0.0, t: float = 0.0, entropy: bool = False):
    """N Gaussians in a 60 m box around ``(centre_x, 0, 0)``, a third of them moving at up to 10 m/s."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([60.0, 60.0, 6.0])
    means[:, 0] += centre_x
    dynamic = torch.rand(n, generator=g) < 1 / 3
    velocity = (torch.rand(n, 3, generator=g) - 0.5) * 20.0 * dynamic[:, None]
    times = t + torch.rand(n, generator=g) * 0.5
    return make_scene(means, velocity=velocity, dynamic=dynamic, time_s=times, seed=seed, entropy=entropy)


def sorted_rows(x: torch.Tensor) -> torch.Tensor:
    """The rows of (N, D) ``x`` in lexicographic order (to compare contents regardless of order)."""
    order = torch.arange(len(x))
    for d in reversed(range(x.shape[1])):
        order = order[torch.argsort(x[order, d], stable=True)]
    return x[order]


# --------------------------------------------------------------------------------------------
# Voxel keys and re-basing


def test_voxel_keys_agree_with_unique_over_the_integer_coordinates():
    g = torch.Generator().manual_seed(0)
    means = (torch.rand(5000, 3, generator=g) - 0.5) * 4.0  # many Gaussians per 0.2 m voxel
    means = torch.cat([means, torch.tensor([[-209_000.0, 209_000.0, -0.05]])])  # near the range's ends
    keys = voxel_keys(means, 0.2)
    coords = torch.floor(means.double() / 0.2).long()
    _, inverse_coords = torch.unique(coords, dim=0, return_inverse=True)
    _, inverse_keys = torch.unique(keys, return_inverse=True)
    # The same partition of the Gaussians into voxels, whatever the labels.
    pairs = torch.unique(torch.stack([inverse_coords, inverse_keys], dim=1), dim=0)
    assert len(pairs) == len(torch.unique(inverse_coords)) == len(torch.unique(inverse_keys))


def test_voxel_keys_refuse_centres_beyond_their_range():
    means = torch.tensor([[0.0, 0.0, 0.0], [KEY_HALF * 0.2 + 1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"1 of 2 centres"):
        voxel_keys(means, 0.2)


def test_rebasing_leaves_means_at_unchanged():
    scene = make_scene(
        torch.tensor([[1.0, 2.0, 0.5], [4.0, 0.0, 0.0]]),
        velocity=torch.tensor([[3.0, -1.0, 0.5], [0.0, 0.0, 0.0]]),
        time_s=torch.tensor([0.2, 0.7]),
    )
    moved = rebase(scene, scene.dynamic, 2.9)
    assert moved.time_s.tolist() == pytest.approx([2.9, 0.7])
    for t in (0.0, 1.7, 5.0):
        torch.testing.assert_close(moved.means_at(t), scene.means_at(t))


# --------------------------------------------------------------------------------------------
# De-duplication


def test_static_gaussians_added_twice_at_the_same_positions_do_not_double():
    buffer = GaussianBuffer(voxel_m=0.2)
    scene = random_scene(1000, seed=1)
    static = scene.select(~scene.dynamic)
    buffer.add(static, window=0)
    stats = buffer.add(static, window=1)
    assert len(buffer) == len(static)
    assert stats.replaced == len(static) and stats.added == len(static)
    assert buffer.windows().unique().tolist() == [1]  # the newest observation won


def test_a_new_static_gaussian_replaces_only_the_old_ones_in_its_voxel():
    buffer = GaussianBuffer(voxel_m=0.5)
    buffer.add(make_scene(torch.tensor([[0.1, 0.1, 0.1], [0.2, 0.3, 0.4], [3.0, 0.0, 0.0]])), window=0)
    new = make_scene(torch.tensor([[0.4, 0.4, 0.4]]), seed=9)
    stats = buffer.add(new, window=1)
    assert stats.replaced == 2 and len(buffer) == 2
    contents = buffer.scene()
    torch.testing.assert_close(sorted_rows(contents.means), torch.tensor([[0.4, 0.4, 0.4], [3.0, 0.0, 0.0]]))
    assert torch.equal(contents.colors[buffer.windows() == 1], new.colors)


def reference_contents(windows: list[GaussianScene], voxel_m: float) -> torch.Tensor:
    """The slow obvious version of the rules without a cap (``dynamic_windows = 1``): (N, 3) centres
    at the last window's reference time, one Python step per Gaussian."""
    kept: list[tuple[tuple[int, int, int], list[float], bool]] = []  # (voxel, centre, moving)
    for scene in windows:
        t_ref = float(scene.time_s.max())
        new = []
        for i in range(len(scene)):
            moving = bool(scene.dynamic[i]) and float(scene.velocity[i].norm()) > 0.5
            centre = scene.means_at(t_ref)[i] if moving else scene.means[i]
            voxel = tuple(math.floor(float(c) / voxel_m) for c in centre.double())
            new.append((voxel, centre.tolist(), moving))
        new_static = {v for v, _, m in new if not m}
        kept = [(v, c, m) for v, c, m in kept if not m and v not in new_static] + new
    return torch.tensor([c for _, c, _ in kept]).reshape(-1, 3)


def test_add_agrees_with_a_slow_reference_of_its_rules():
    scenes = []
    for w in range(6):
        g = torch.Generator().manual_seed(100 + w)
        means = torch.randint(-3, 4, (60, 3), generator=g) * 0.3 + 0.05  # few voxels: many repeats
        dynamic = torch.rand(60, generator=g) < 0.3
        velocity = torch.randn(60, 3, generator=g) * dynamic[:, None]  # some slower than 0.5 m/s
        scenes.append(make_scene(means, velocity=velocity, dynamic=dynamic, time_s=w + 0.25 * (w % 2)))
    buffer = GaussianBuffer(voxel_m=0.2, dynamic_windows=1)
    for w, scene in enumerate(scenes):
        buffer.add(scene, window=w)
    expected = reference_contents(scenes, 0.2)
    torch.testing.assert_close(sorted_rows(buffer.scene().means), sorted_rows(expected))


def test_slow_dynamic_gaussians_are_stored_static_and_persist():
    buffer = GaussianBuffer(dynamic_speed_mps=0.5)
    parked = make_scene(
        torch.tensor([[5.0, 1.0, 0.5], [9.0, 1.0, 0.5]]),
        velocity=torch.tensor([[0.3, 0.0, 0.0], [0.0, 0.4, 0.0]]),
        dynamic=torch.tensor([True, True]),
        time_s=1.0,
    )
    stats = buffer.add(parked, window=0)
    assert stats.made_static == 2
    contents = buffer.scene()
    assert not contents.dynamic.any() and torch.equal(contents.velocity, torch.zeros(2, 3))
    torch.testing.assert_close(contents.means, parked.means_at(1.0))  # where they were seen
    for w in range(1, 5):
        buffer.add(make_scene(torch.tensor([[50.0 + w, 0.0, 0.0]]), time_s=1.0 + w), window=w)
    assert len(buffer) == 6  # the two parked ones and one per later window


def car_window(
    w: int, body: torch.Tensor, speed_mps: float, estimated_mps: float, frames: int = 4, window_s: float = 1.0
) -> GaussianScene:
    """Window ``w`` of a car driving along +x: ``frames`` frames, each seeing the same body points
    (B, 3) where the car is then, with the velocity Stage 1 ``estimated_mps``; plus a static road."""
    parts = []
    for f in range(frames):
        t = w * window_s + f * window_s / frames
        means = body + torch.tensor([speed_mps * t, 0.0, 0.0])
        velocity = torch.tensor([[estimated_mps, 0.0, 0.0]]).expand(len(body), 3)
        parts.append(make_scene(means, velocity=velocity, time_s=t, seed=f))
    x = torch.arange(0.0, 300.0, 1.0)
    road = torch.stack([x, torch.full_like(x, 4.0), torch.zeros_like(x)], dim=1)
    parts.append(make_scene(road, time_s=w * window_s))
    return GaussianScene.concatenate(parts)


@pytest.mark.parametrize(("dynamic_windows", "estimated_mps"), [(1, 12.0), (1, 13.2), (2, 12.0)])
def test_a_car_driving_through_20_windows_leaves_no_trail(dynamic_windows: int, estimated_mps: float):
    g = torch.Generator().manual_seed(3)
    body = torch.rand(150, 3, generator=g) * torch.tensor([4.5, 1.8, 1.5]) + torch.tensor([0.0, -0.9, 0.3])
    buffer = GaussianBuffer(voxel_m=0.2, dynamic_windows=dynamic_windows)
    per_window = 4 * len(body)
    for w in range(20):
        buffer.add(car_window(w, body, 12.0, estimated_mps), window=w)
        contents = buffer.scene()
        moving = contents.select(contents.dynamic)
        assert len(moving) <= 1.02 * per_window, (w, len(moving))  # about one window's worth
        assert int((~contents.dynamic).sum()) == 300  # the road persists, the car never turns static
        # Every moving Gaussian is near where the car is now (a velocity error of 1.2 m/s drifts
        # the window's earliest frame by 0.9 m), none where it was.
        t = buffer.reference_time_s
        x = moving.means_at(t)[:, 0]
        front_now = 12.0 * t
        assert float(x.min()) >= front_now - 1.0 and float(x.max()) <= front_now + 4.5 + 1.0


# --------------------------------------------------------------------------------------------
# The cap and eviction


def test_a_200_window_rollout_stays_under_its_cap_with_no_nan():
    cap = 4000
    buffer = GaussianBuffer(voxel_m=0.2, max_gaussians=cap, dynamic_windows=2, far_first_m=80.0)
    for w in range(200):
        before = len(buffer)
        ego_x = 8.0 * w
        scene = random_scene(1500, seed=w, centre_x=ego_x, t=0.5 * w, entropy=True)
        stats = buffer.add(scene, window=w, ego_position_world=[ego_x, 0.0, 0.0])
        assert len(buffer) <= cap and stats.size == len(buffer)
        assert stats.size == before + stats.added - stats.replaced - stats.superseded - stats.evicted
    contents = buffer.scene()
    for name, value in contents.tensors().items():
        assert torch.isfinite(value.float()).all(), name
    assert torch.isfinite(contents.means_at(0.5 * 200)).all()
    assert int(buffer.windows().min()) >= 190  # long forgotten windows are gone


def test_oldest_windows_are_evicted_first():
    buffer = GaussianBuffer(max_gaussians=250)
    for w in range(3):
        means = torch.rand(100, 3, generator=torch.Generator().manual_seed(w)) * 5 + torch.tensor(
            [10.0 * w, 0, 0]
        )
        buffer.add(make_scene(means, time_s=float(w)), window=w)
    assert torch.bincount(buffer.windows(), minlength=3).tolist() == [50, 100, 100]
    stats = buffer.add(make_scene(torch.rand(100, 3) * 5 + torch.tensor([30.0, 0, 0]), time_s=3.0), window=3)
    assert stats.evicted == 100
    assert torch.bincount(buffer.windows(), minlength=4).tolist() == [0, 50, 100, 100]


def test_far_gaussians_go_before_old_near_ones():
    buffer = GaussianBuffer(max_gaussians=150, far_first_m=50.0)
    near_old = make_scene(torch.rand(100, 3) * 5)
    buffer.add(near_old, window=0, ego_position_world=[0.0, 0.0, 0.0])
    near_new = torch.rand(30, 3) * 5 + torch.tensor([10.0, 0, 0])
    far_new = torch.rand(40, 3) * 5 + torch.tensor([200.0, 0, 0])
    stats = buffer.add(
        make_scene(torch.cat([near_new, far_new])), window=1, ego_position_world=[0.0, 0.0, 0.0]
    )
    assert stats.evicted == 20
    assert int((buffer.windows() == 0).sum()) == 100  # the near old ones all stay
    assert int((buffer.scene().means[:, 0] > 100).sum()) == 20  # half of the far new ones went


def test_within_a_window_the_farthest_from_the_ego_go_first():
    buffer = GaussianBuffer(max_gaussians=60, far_first_m=None)
    x = torch.randperm(100, generator=torch.Generator().manual_seed(0)).float() + 1.0  # 1..100 m, shuffled
    means = torch.stack([x, torch.zeros(100), torch.zeros(100)], dim=1)
    buffer.add(make_scene(means), window=0, ego_position_world=torch.zeros(3))
    assert sorted(buffer.scene().means[:, 0].tolist()) == [float(i) for i in range(1, 61)]


def test_a_window_larger_than_the_cap_is_thinned_evenly_without_an_ego():
    buffer = GaussianBuffer(max_gaussians=500)
    frames = [make_scene(torch.rand(400, 3) * 10 + torch.tensor([0, 0, 20.0 * f])) for f in range(4)]
    buffer.add(GaussianScene.concatenate(frames), window=0)
    per_frame = torch.bincount((buffer.scene().means[:, 2] // 20).long(), minlength=4)
    assert len(buffer) == 500 and int(per_frame.min()) > 80  # no frame dropped as a block


# --------------------------------------------------------------------------------------------
# Re-basing in the buffer


def test_means_at_of_a_moving_gaussian_is_unchanged_by_rebasing():
    buffer = GaussianBuffer(dynamic_windows=3)
    mover = make_scene(torch.tensor([[1.0, 2.0, 0.5]]), velocity=torch.tensor([[3.0, -1.0, 0.5]]), time_s=0.2)
    buffer.add(mover, window=0)
    ts = torch.tensor([0.0, 1.7, 5.0])
    expected = torch.stack([mover.means_at(float(t))[0] for t in ts])
    for w, t in ((1, 1.4), (2, 2.9)):
        buffer.add(make_scene(torch.tensor([[-20.0, 0.0, 0.0]]), time_s=t, seed=w), window=w)
    contents = buffer.scene()
    moving = contents.select(contents.dynamic)
    assert len(moving) == 1 and float(moving.time_s[0]) == pytest.approx(2.9)
    assert not torch.allclose(moving.means, mover.means)  # re-based, not left alone
    got = torch.stack([moving.means_at(float(t))[0] for t in ts])
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=0)
    buffer.add(make_scene(torch.tensor([[-30.0, 0.0, 0.0]]), time_s=4.0), window=3)
    assert not buffer.scene().dynamic.any()  # three windows old: superseded


# --------------------------------------------------------------------------------------------
# State, empty and bad input


def test_state_dict_round_trip_gives_identical_contents():
    buffer = GaussianBuffer(max_gaussians=3000, dynamic_windows=2)
    for w in range(4):
        buffer.add(random_scene(1200, seed=w, centre_x=5.0 * w, t=w, entropy=True), window=w)
    state = buffer.state_dict()
    assert all(isinstance(v, torch.Tensor) for v in state.values())
    file = io.BytesIO()
    torch.save(state, file)
    file.seek(0)
    restored = GaussianBuffer(max_gaussians=3000, dynamic_windows=2)
    restored.load_state_dict(torch.load(file, weights_only=True))
    a, b = buffer.scene(), restored.scene()
    assert a.tensors().keys() == b.tensors().keys()
    for name in a.tensors():
        assert torch.equal(a.tensors()[name], b.tensors()[name]), name
    assert torch.equal(buffer.windows(), restored.windows())
    assert (restored.latest_window, restored.reference_time_s) == (
        buffer.latest_window,
        buffer.reference_time_s,
    )
    # Resuming: the next window does the same to both.
    nxt = random_scene(1200, seed=9, centre_x=20.0, t=4.0, entropy=True)
    assert buffer.add(nxt, window=4) == restored.add(nxt, window=4)
    assert torch.equal(buffer.scene().means, restored.scene().means)


def test_load_state_dict_refuses_another_config_and_bad_values():
    buffer = GaussianBuffer()
    buffer.add(random_scene(50, seed=0), window=0)
    state = buffer.state_dict()
    with pytest.raises(ValueError, match=r"config\.voxel_m"):
        GaussianBuffer(voxel_m=0.5).load_state_dict(state)
    bad = dict(state)
    bad["gaussians.means"] = state["gaussians.means"].clone()
    bad["gaussians.means"][3, 1] = float("nan")
    with pytest.raises(ValueError, match=r"gaussians\.means: 1 of 50"):
        GaussianBuffer().load_state_dict(bad)
    with pytest.raises(ValueError, match=r"missing entries \['window'\]"):
        GaussianBuffer().load_state_dict({k: v for k, v in state.items() if k != "window"})


def test_empty_scenes_are_fine():
    buffer = GaussianBuffer()
    assert len(buffer) == 0 and len(buffer.scene()) == 0
    empty = make_scene(torch.zeros(0, 3))
    stats = buffer.add(empty, window=0)
    assert (stats.added, stats.replaced, stats.evicted, stats.size) == (0, 0, 0, 0)
    buffer.add(random_scene(300, seed=1), window=1)
    static = int((~buffer.scene().dynamic).sum())
    stats = buffer.add(empty, window=2)
    assert len(buffer) == static and stats.superseded == 300 - static  # moving ones are a window old
    fresh = GaussianBuffer()
    fresh.load_state_dict(GaussianBuffer().state_dict())
    assert len(fresh) == 0 and fresh.latest_window == -1


def test_nan_input_raises_naming_the_field_and_count():
    buffer = GaussianBuffer()
    buffer.add(random_scene(10, seed=0), window=0)
    scene = random_scene(10, seed=1)
    means, velocity = scene.means.clone(), scene.velocity.clone()
    means[2, 0] = float("nan")
    means[5] = float("inf")
    velocity[7, 2] = float("-inf")
    bad = GaussianScene(**{**scene.__dict__, "means": means, "velocity": velocity})
    with pytest.raises(ValueError, match=r"scene\.means: 2 of 10 Gaussians.*scene\.velocity: 1 of 10"):
        buffer.add(bad, window=1)
    assert len(buffer) == 10 and buffer.latest_window == 0  # unchanged


def test_windows_must_go_forward_and_scenes_must_match():
    buffer = GaussianBuffer()
    buffer.add(random_scene(10, seed=0), window=3)
    with pytest.raises(ValueError, match=r"window 3 was already added"):
        buffer.add(random_scene(10, seed=1), window=2)
    other = random_scene(10, seed=1)
    with pytest.raises(ValueError, match=r"0 semantic classes"):
        buffer.add(GaussianScene(**{**other.__dict__, "semantic_logits": torch.zeros(10, 0)}), window=4)
    with pytest.raises(ValueError, match=r"time_origin_micros"):
        buffer.add(GaussianScene(**{**other.__dict__, "time_origin_micros": 7}), window=4)
    buffer.add(other, window=3)  # a window in several parts is fine


# --------------------------------------------------------------------------------------------
# Rendering and speed


def test_rendering_the_buffer_scene_shows_its_gaussians():
    buffer = GaussianBuffer(voxel_m=0.1)
    g = torch.Generator().manual_seed(5)
    wall = torch.cat(
        [torch.rand(200, 2, generator=g) * 2 - torch.tensor([2.5, 1.0]), torch.full((200, 1), 5.0)], 1
    )
    car = make_scene(torch.tensor([[1.5, 0.0, 5.0]]), velocity=torch.tensor([[0.0, 2.0, 0.0]]), time_s=0.0)
    buffer.add(GaussianScene.concatenate([make_scene(wall), car]), window=0)
    k = torch.tensor([[[16.0, 0.0, 15.5], [0.0, 16.0, 11.5], [0.0, 0.0, 1.0]]])
    out = buffer.scene().render(torch.eye(4)[None], k, 32, 24, 0.0, backend="torch")
    assert out.alpha.shape == (1, 24, 32)
    assert float(out.alpha[0, 12, 8]) > 0.5  # the wall, left of centre at x in [-2.5, -0.5] m
    assert float(out.alpha[0, 12, 20]) > 0.1  # the moving Gaussian at x = 1.5 m, t = 0
    assert float(out.alpha[0, 12, 30]) == 0.0  # nothing there
    later = buffer.scene().render(torch.eye(4)[None], k, 32, 24, 0.5, backend="torch")  # it moved 1 m down
    assert float(later.alpha[0, 12, 20]) < float(later.alpha[0, 15, 20])


def test_per_gaussian_values_render_as_their_blend_weighted_average():
    """``render(values=...)`` gives ``sum_i w_i x_i / sum_i w_i`` per pixel (w_i the blend weights):
    the window trust a rollout scales u by."""
    k = torch.tensor([[[16.0, 0.0, 15.5], [0.0, 16.0, 11.5], [0.0, 0.0, 1.0]]])
    # Two Gaussians on the optical axis, 3 m and 6 m away, the near one half transparent.
    scene = make_scene(torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 6.0]]))
    scene = GaussianScene(**{**scene.tensors(), "opacities": torch.tensor([0.5, 0.9])})
    x = torch.tensor([1.0, 0.25])
    out = scene.render(torch.eye(4)[None], k, 32, 24, 0.0, values=x, backend="torch")
    near, far = (
        scene.select(torch.tensor([i])).render(torch.eye(4)[None], k, 32, 24, 0.0, backend="torch")
        for i in (0, 1)
    )
    w_near = near.alpha  # front to back: the near one's weight is its alpha,
    w_far = (1 - near.alpha) * far.alpha  # the far one's what it lets through times its own
    covered = out.alpha > 1e-3
    expected = (w_near * 1.0 + w_far * 0.25) / (w_near + w_far)
    torch.testing.assert_close(out.value[covered], expected[covered], rtol=1e-4, atol=1e-5)
    assert float(out.value[0, 11, 15]) < 1.0 and float(out.value[0, 11, 15]) > 0.25  # a blend
    assert torch.equal(out.value[~(out.alpha > 0)], torch.zeros_like(out.value[~(out.alpha > 0)]))
    assert scene.render(torch.eye(4)[None], k, 32, 24, 0.0, backend="torch").value is None
    with pytest.raises(ValueError, match="values of shape"):
        scene.render(torch.eye(4)[None], k, 32, 24, 0.0, values=torch.ones(3))


def test_adding_100k_gaussians_to_a_full_200k_buffer_takes_well_under_a_second():
    buffer = GaussianBuffer(voxel_m=0.2, max_gaussians=200_000)
    buffer.add(random_scene(200_000, seed=0), window=0, ego_position_world=[0.0, 0.0, 0.0])
    scene = random_scene(100_000, seed=1, centre_x=5.0, t=1.0)
    start = time.perf_counter()
    stats = buffer.add(scene, window=1, ego_position_world=[5.0, 0.0, 0.0])
    elapsed = time.perf_counter() - start
    assert len(buffer) == 200_000 and stats.evicted > 0
    assert elapsed < 1.0, elapsed
