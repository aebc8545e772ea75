"""The Stage 2 multi-view DiT: shapes, zero initialisation, the condition path, ring-neighbour
cross-view attention, per-frame flow times, Plücker rays, the registry, input checks, overfitting."""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis.models import create_model, list_models
from phigenesis.models.dit import CONFIGS, DiTConfig, MultiViewDiT, plucker_rays
from phigenesis.models.stage1 import pixel_rays

C = 4  # stage2_tiny's latent channels (vae_tiny's)


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """These tensors are tiny: one thread is faster than two on a shared 2-core machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _tiny(seed: int = 0, **overrides: object) -> MultiViewDiT:
    torch.manual_seed(seed)
    return create_model("stage2_tiny", **overrides)  # type: ignore[return-value]


def _inputs(
    b: int = 1, v: int = 3, t: int = 2, h: int = 4, w: int = 6, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(z_t, t, condition, plucker) of random values, t per clip."""
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(b, v, C, t, h, w, generator=g)
    times = torch.rand(b, generator=g)
    cond = torch.randn(b, v, C + 1, t, h, w, generator=g)
    rays = torch.randn(b, v, 6, t, h, w, generator=g)
    return z, times, cond, rays


def _perturb(model: MultiViewDiT, skip: str | None = "cond_embed", std: float = 0.1, seed: int = 1) -> None:
    """Adds N(0, std) noise to every parameter except those under ``skip``."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if skip is None or not name.startswith(skip):
                p.add_(torch.randn(p.shape, generator=g) * std)


# --------------------------------------------------------------------------------------------
# Shapes and initialisation


@pytest.mark.parametrize("views", [1, 2, 5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_output_has_the_latent_shape_and_the_input_dtype(views: int, dtype: torch.dtype) -> None:
    model = _tiny()
    _perturb(model, skip=None)
    z, t, cond, rays = _inputs(v=views)
    out = model(z.to(dtype), t, cond, rays)
    assert out.shape == z.shape and out.dtype == dtype
    assert bool(torch.isfinite(out).all()) and out.abs().max() > 0


def test_output_is_exactly_zero_at_initialisation() -> None:
    out = _tiny()(*_inputs(v=5))
    assert torch.equal(out, torch.zeros_like(out))


def test_output_ignores_the_condition_while_its_embedding_is_zero() -> None:
    model = _tiny()
    _perturb(model, skip="cond_embed")
    assert torch.equal(model.cond_embed.weight, torch.zeros_like(model.cond_embed.weight))
    z, t, cond, rays = _inputs()
    out = model(z, t, cond, rays)
    assert out.abs().max() > 1e-3  # the final layer is no longer zero
    assert torch.equal(out, model(z, t, 5 * torch.randn_like(cond), rays))
    assert torch.equal(out, model(z, t, torch.zeros_like(cond), rays))


def test_output_depends_on_the_condition_once_its_embedding_is_nonzero() -> None:
    model = _tiny()
    _perturb(model, skip=None)
    z, t, cond, rays = _inputs()
    with_cond, without = model(z, t, cond, rays), model(z, t, torch.zeros_like(cond), rays)
    assert (with_cond - without).abs().max() > 1e-3
    # The uncertainty channel alone is seen too.
    u_only = torch.zeros_like(cond)
    u_only[:, :, -1] = 1.0
    assert (model(z, t, u_only, rays) - without).abs().max() > 1e-3


def test_x0_skip_starts_as_the_velocity_towards_the_condition() -> None:
    """Untrained, ``x0_skip`` predicts the clean latent u * z_ren: v = (u z_ren - z_t) / max(t, t_min)."""
    from phigenesis.models.dit import X0_MIN_TIME

    model = _tiny(prediction="x0_skip")
    z, _, cond, rays = _inputs(v=3)
    t = torch.tensor([[0.5, 0.01]])  # per latent frame; the second below t_min
    out = model(z, t, cond, rays)
    x0 = cond[:, :, :C]
    expected = torch.stack(
        [(x0[:, :, :, 0] - z[:, :, :, 0]) / 0.5, (x0[:, :, :, 1] - z[:, :, :, 1]) / X0_MIN_TIME], 3
    )
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-5)
    # A zero condition (guidance's unconditional branch) has no skip: x0 is the network's alone.
    zero = model(z, t, torch.zeros_like(cond), rays)
    torch.testing.assert_close(
        zero, expected - x0 / torch.tensor([0.5, X0_MIN_TIME])[None, None, None, :, None, None]
    )


def test_x0_skip_untrained_euler_sampling_lands_on_the_render_latent() -> None:
    """Euler steps of at least t_min end exactly at the predicted clean latent: with u = 1 the
    untrained model returns z_ren from pure noise, and a trained one corrects it from there."""
    from phigenesis.models.flow import euler_sample

    model = _tiny(prediction="x0_skip")
    z, _, _, rays = _inputs(v=3)
    z_ren = torch.randn(z.shape, generator=torch.Generator().manual_seed(7))
    cond = torch.cat([z_ren, torch.ones_like(z_ren[:, :, :1])], dim=2)
    noise = torch.randn(z.shape, generator=torch.Generator().manual_seed(8))
    out = euler_sample(lambda x, t, c: model(x, t, c, rays), noise, steps=10, condition=cond)
    torch.testing.assert_close(out, z_ren, rtol=1e-4, atol=1e-4)
    # The velocity default is unchanged: the untrained model's velocity is 0 and noise stays noise.
    vel = _tiny()
    same = euler_sample(lambda x, t, c: vel(x, t, c, rays), noise, steps=10, condition=cond)
    assert torch.equal(same, noise)


def test_old_configs_without_a_prediction_load_as_velocity() -> None:
    values = CONFIGS["stage2_tiny"].to_dict()
    values.pop("prediction")
    assert DiTConfig.from_dict(values).prediction == "velocity"
    values.pop("latent_mean"), values.pop("latent_std")
    assert DiTConfig.from_dict(values).latent_mean is None


def test_latent_statistics_standardise_and_restore_latents_per_channel() -> None:
    model = _tiny(latent_mean=[1.0, -2.0, 0.0, 0.5], latent_std=[2.0, 0.5, 1.0, 4.0])
    assert model.config.latent_mean == (1.0, -2.0, 0.0, 0.5)  # lists (as checkpoints hold them) become tuples
    z, *_ = _inputs()
    n = model.normalize_latents(z)
    assert torch.allclose(n[:, :, 1], (z[:, :, 1] + 2.0) / 0.5)
    torch.testing.assert_close(model.denormalize_latents(n), z)
    # [V, C, T, h, w] with the channels at dim 1
    torch.testing.assert_close(model.normalize_latents(z[0], channel_dim=1), n[0])
    plain = _tiny()
    assert plain.normalize_latents(z) is z and plain.denormalize_latents(z) is z
    with pytest.raises(ValueError, match=r"latent_std\[0\] = 0.0: must be a number in \(0, "):
        DiTConfig(latent_channels=1, latent_mean=(0.0,), latent_std=(0.0,))
    with pytest.raises(ValueError, match="come together"):
        DiTConfig(latent_channels=1, latent_mean=(0.0,))
    with pytest.raises(ValueError, match=r"latent_mean\[1\] = nan: must be a number .* \(finite\)"):
        DiTConfig(latent_channels=4, latent_mean=(0.0, math.nan, 0.0, 0.0), latent_std=(1.0,) * 4)


# --------------------------------------------------------------------------------------------
# Cross-view attention


def _view_gradients(model: MultiViewDiT, views: int, out_view: int = 0) -> torch.Tensor:
    """[V] largest |d output[view out_view] / d z_t[view j]| under a random upstream gradient."""
    z, t, cond, rays = _inputs(v=views)
    z.requires_grad_(True)
    out = model(z, t, cond, rays)
    upstream = torch.randn(out[:, out_view].shape, generator=torch.Generator().manual_seed(3))
    (grad,) = torch.autograd.grad((out[:, out_view] * upstream).sum(), z)
    return grad.abs().amax(dim=(0, 2, 3, 4, 5))


def test_one_block_mixes_each_view_only_with_its_ring_neighbours() -> None:
    # One block: view 0's output sees views 4, 0 and 1 (its ring neighbours) and nothing of views
    # 2 and 3; the same statement for view 3 is that a change of view 3 reaches views 2, 3, 4 only.
    model = _tiny(depth=1)
    _perturb(model, skip=None)
    grad = _view_gradients(model, views=5, out_view=0)
    assert bool((grad[[0, 1, 4]] > 0).all()), grad
    assert grad[2] == 0 and grad[3] == 0, grad
    grad = _view_gradients(model, views=5, out_view=3)
    assert bool((grad[[2, 3, 4]] > 0).all()) and grad[0] == 0 and grad[1] == 0, grad


def test_two_blocks_reach_the_neighbours_of_the_neighbours() -> None:
    model = _tiny(depth=2)
    _perturb(model, skip=None)
    assert bool((_view_gradients(model, views=5) > 0).all())  # 2 hops cover a ring of 5
    assert bool((_view_gradients(model, views=7) > 0).sum() == 5)  # views 5 .. 2 of 7, not 3, 4


def test_two_views_attend_to_each_other() -> None:
    model = _tiny(depth=1)
    _perturb(model, skip=None)
    assert bool((_view_gradients(model, views=2) > 0).all())


def test_output_rolls_with_the_ring_of_views() -> None:
    # No positional embedding of views: rotating the order of every input rotates the output.
    model = _tiny()
    _perturb(model, skip=None)
    z, t, cond, rays = _inputs(v=5)
    out = model(z, t, cond, rays)
    rolled = model(z.roll(2, dims=1), t, cond.roll(2, dims=1), rays.roll(2, dims=1))
    torch.testing.assert_close(rolled, out.roll(2, dims=1), rtol=1e-4, atol=1e-5)


# --------------------------------------------------------------------------------------------
# Flow time


def test_per_frame_times_match_the_clip_time_when_equal_and_change_the_output_when_not() -> None:
    model = _tiny()
    _perturb(model, skip=None)
    z, _, cond, rays = _inputs(b=2, t=3)
    clip = torch.tensor([0.3, 0.7])
    per_clip = model(z, clip, cond, rays)
    torch.testing.assert_close(model(z, clip[:, None].expand(2, 3), cond, rays), per_clip, rtol=0, atol=0)
    frames = torch.tensor([[0.3, 0.3, 0.9], [0.05, 0.7, 0.7]])  # history at a low level, as DF does
    per_frame = model(z, frames, cond, rays)
    assert per_frame.shape == z.shape
    assert (per_frame - per_clip).abs().max() > 1e-3


# --------------------------------------------------------------------------------------------
# Plücker rays


def test_plucker_rays_match_a_hand_computation() -> None:
    k = torch.tensor([[2.0, 0.0, 1.0], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    # Camera z forward -> world x, camera x right -> world -y, camera y down -> world -z.
    pose[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pose[:3, 3] = torch.tensor([10.0, 0.0, 1.5])
    rays = plucker_rays(k, pose, 2, 3)
    assert rays.shape == (6, 2, 3)
    # Pixel centre (u=2, v=1): K^-1 (2, 1, 1) = (0.5, 0, 1) in the camera, (1, -0.5, 0) in the world.
    r5 = math.sqrt(5.0)
    d = torch.tensor([2 / r5, -1 / r5, 0.0], dtype=torch.float64)
    m = torch.tensor([1.5 / r5, 3 / r5, -10 / r5], dtype=torch.float64)  # (10, 0, 1.5) x d
    torch.testing.assert_close(rays[:, 1, 2], torch.cat([d, m]))
    # Pixel centre (u=1, v=1) is the principal point: the optical axis, world +x.
    torch.testing.assert_close(rays[:3, 1, 1], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))


def test_plucker_directions_are_unit_and_follow_the_stage1_pixel_convention() -> None:
    k = torch.tensor([[[30.0, 0.5, 8.0], [0.0, 25.0, 5.5], [0.0, 0.0, 1.0]]]).expand(4, 3, 3)
    pose = torch.eye(4).expand(2, 4, 4, 4).clone()  # [T=2, V=4, 4, 4] broadcast against [V, 3, 3]
    pose[..., :3, 3] = torch.randn(2, 4, 3)
    rays = plucker_rays(k, pose, 12, 18)
    assert rays.shape == (2, 4, 6, 12, 18)
    torch.testing.assert_close(rays[:, :, :3].norm(dim=2), torch.ones(2, 4, 12, 18))
    expected = torch.nn.functional.normalize(pixel_rays(k, 12, 18), dim=-3)  # identity rotation
    torch.testing.assert_close(rays[:, :, :3], expected.expand(2, 4, 3, 12, 18))
    # The moment is perpendicular to the direction.
    assert (rays[:, :, :3] * rays[:, :, 3:]).sum(dim=2).abs().max() < 1e-4


def _rotation(q: tuple[float, float, float, float]) -> torch.Tensor:
    w, x, y, z = torch.nn.functional.normalize(torch.tensor(q, dtype=torch.float64), dim=0).tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


finite = st.floats(-5.0, 5.0, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(
    q=st.tuples(finite, finite, finite, finite).filter(lambda q: sum(c * c for c in q) > 0.1),
    origin=st.tuples(finite, finite, finite),
    slide=st.floats(-20.0, 20.0, allow_nan=False),
    pixel=st.tuples(st.integers(0, 3), st.integers(0, 4)),
)
def test_plucker_moment_is_invariant_to_sliding_the_origin_along_the_ray(
    q: tuple[float, float, float, float],
    origin: tuple[float, float, float],
    slide: float,
    pixel: tuple[int, int],
) -> None:
    k = torch.tensor([[3.0, 0.0, 2.0], [0.0, 4.0, 1.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = _rotation(q)
    pose[:3, 3] = torch.tensor(origin, dtype=torch.float64)
    rays = plucker_rays(k, pose, 4, 5)
    row, col = pixel
    d = rays[:3, row, col]
    moved = pose.clone()
    moved[:3, 3] += slide * d
    rays_moved = plucker_rays(k, moved, 4, 5)
    torch.testing.assert_close(rays_moved[:3], rays[:3])  # directions do not depend on the origin
    torch.testing.assert_close(rays_moved[3:, row, col], rays[3:, row, col], rtol=0, atol=1e-9)


# --------------------------------------------------------------------------------------------
# Registry and config


def test_the_registry_lists_the_tiny_and_base_variants() -> None:
    assert list_models("dit") == ["stage2_base", "stage2_tiny"]
    assert set(CONFIGS) == {"stage2_base", "stage2_tiny"}


@pytest.mark.parametrize("name", ["stage2_tiny", "stage2_base"])
def test_every_variant_round_trips_its_config_and_rebuilds_from_it(name: str) -> None:
    with torch.device("meta"):  # no memory or init time for the base variant
        model = create_model(name)
        assert model.name == name and model.config == CONFIGS[name]
        values = model.config.to_dict()
        assert DiTConfig.from_dict(values) == model.config
        assert create_model(name, **values).config == model.config  # how checkpoints rebuild


def test_variant_sizes_fit_their_machines() -> None:
    tiny = _tiny()
    assert tiny.config.latent_channels == 4 and 3e5 < tiny.num_parameters() < 1e6
    with torch.device("meta"):
        base = create_model("stage2_base")
    assert base.config.latent_channels == 16 and 2e8 < base.num_parameters() < 2.5e8
    tiny.x_embed.requires_grad_(False)
    assert tiny.num_parameters() == tiny.num_parameters(trainable=False) - tiny.x_embed.weight.numel() - 64


def test_bad_configs_are_rejected() -> None:
    with pytest.raises(ValueError, match="must divide by heads"):
        DiTConfig(hidden=64, heads=5)
    with pytest.raises(ValueError, match="prediction = 'eps': must be one of 'velocity', 'x0_skip'"):
        DiTConfig(prediction="eps")


# --------------------------------------------------------------------------------------------
# Input checks


def _bad_shape_cases() -> list[tuple[str, tuple[int, ...], str]]:
    return [
        ("z_t", (1, 3, C, 2, 5, 6), "must divide by patch_size=2"),
        ("z_t", (1, 3, C + 1, 2, 4, 6), "z_t must be"),
        ("condition", (1, 3, C, 2, 4, 6), r"condition must be .*got \(1, 3, 4, 2, 4, 6\)"),
        ("condition", (1, 2, C + 1, 2, 4, 6), "condition must be"),
        ("plucker", (1, 3, 6, 3, 4, 6), r"plucker must be .*got \(1, 3, 6, 3, 4, 6\)"),
        ("t", (1, 3), r"t must be \[B\] = \[1\] or \[B, T\] = \[1, 2\], got \(1, 3\)"),
    ]


@pytest.mark.parametrize(("which", "shape", "message"), _bad_shape_cases())
def test_inputs_of_the_wrong_shape_are_rejected_with_the_shapes(
    which: str, shape: tuple[int, ...], message: str
) -> None:
    model = _tiny()
    args = dict(zip(("z_t", "t", "condition", "plucker"), _inputs(), strict=True))
    args[which] = torch.rand(shape)
    with pytest.raises(ValueError, match=message):
        model(**args)


@pytest.mark.parametrize("which", ["z_t", "t", "condition", "plucker"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_inputs_are_rejected_naming_the_input(which: str, bad: float) -> None:
    model = _tiny()
    args = dict(zip(("z_t", "t", "condition", "plucker"), _inputs(), strict=True))
    args[which] = (
        args[which].clone().flatten().index_fill(0, torch.tensor([0]), bad).reshape(args[which].shape)
    )
    with pytest.raises(ValueError, match=f"^{which} has NaN or Inf"):
        model(**args)


def test_flow_times_outside_the_unit_interval_are_rejected() -> None:
    z, _, cond, rays = _inputs()
    with pytest.raises(ValueError, match=r"t must lie in \[0, 1\]"):
        _tiny()(z, torch.tensor([1.5]), cond, rays)


# --------------------------------------------------------------------------------------------
# Training


def test_the_tiny_model_overfits_one_fixed_batch() -> None:
    model = _tiny()
    z, t, cond, rays = _inputs(v=3, t=2, h=4, w=6)
    target = torch.randn(z.shape, generator=torch.Generator().manual_seed(5))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(100):
        loss = (model(z, t, cond, rays) - target).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.01 * losses[0], (losses[0], losses[-1])
    assert model.cond_embed.weight.abs().max() > 0  # the zero-initialised condition path trains
