"""Stereo Forcing's condition: u * z_ren with u as a channel, pooling u to the latent grid (space and
causal-VAE time), condition dropout and guidance."""

from __future__ import annotations

import pytest
import torch
from torch.testing import assert_close

from phigenesis.models.flow import euler_sample
from phigenesis.models.stereo_forcing import (
    drop_condition,
    guided_velocity,
    latent_frame_count,
    pool_to_latent,
    stereo_forcing,
)

B, V, C, T, h, w = 2, 3, 4, 3, 4, 6


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def render(seed: int = 0) -> torch.Tensor:
    return torch.randn(B, V, C, T, h, w, generator=gen(seed))


def test_sf_with_u_zero_is_all_zeros_the_unconditional_input():
    z_ren = render()
    cond = stereo_forcing(torch.zeros(B, V, T, h, w), z_ren)
    assert cond.shape == (B, V, C + 1, T, h, w)
    assert torch.equal(cond, torch.zeros_like(cond))


def test_guidance_with_u_zero_gives_exactly_the_unconditional_branch():
    cond = stereo_forcing(torch.zeros(B, V, T, h, w), render())
    noise = torch.randn(B, V, C, T, h, w, generator=gen(5))

    def toy(z, t, c):  # depends on the condition, so a nonzero condition would show
        return c[:, :, :C] + c[:, :, C:] - 0.5 * z

    uncond = euler_sample(toy, noise, 5, omega=0.0, condition=cond)
    for omega in (1.0, 2.5):
        assert torch.equal(euler_sample(toy, noise, 5, omega=omega, condition=cond), uncond)


def test_sf_with_u_one_keeps_the_render_and_a_ones_channel():
    z_ren = render()
    cond = stereo_forcing(torch.ones(B, V, T, h, w), z_ren)
    assert torch.equal(cond[:, :, :C], z_ren)
    assert torch.equal(cond[:, :, C], torch.ones(B, V, T, h, w))


def test_sf_weighs_each_latent_cell_by_its_u():
    z_ren = render()
    u = torch.rand(B, V, T, h, w, generator=gen(1))
    cond = stereo_forcing(u, z_ren)
    assert torch.equal(cond[:, :, :C], u[:, :, None] * z_ren)
    assert torch.equal(cond[:, :, C], u)
    assert stereo_forcing(u.double(), z_ren).dtype == torch.float32  # the render's dtype


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (1.5, r"u_latent must lie in \[0, 1\]"),
        (-0.1, r"u_latent must lie in \[0, 1\]"),
        (float("nan"), "u_latent has NaN"),
    ],
)
def test_sf_rejects_u_outside_the_unit_interval_or_nan(bad, message):
    u = torch.rand(B, V, T, h, w, generator=gen(1))
    u[1, 2, 0, 3, 5] = bad
    with pytest.raises(ValueError, match=message):
        stereo_forcing(u, render())


def test_sf_rejects_mismatched_shapes_and_a_non_finite_render():
    with pytest.raises(ValueError, match="u_latent must be"):
        stereo_forcing(torch.ones(B, V, T, h, w + 1), render())
    with pytest.raises(ValueError, match="u_latent must be"):
        stereo_forcing(torch.ones(B, V, C, T, h, w), render())
    with pytest.raises(ValueError, match="z_render must be latents"):
        stereo_forcing(torch.ones(B, V, T, h, w), torch.zeros(B, C, T, h, w))
    z_ren = render()
    z_ren[0, 0, 0, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="z_render has NaN"):
        stereo_forcing(torch.ones(B, V, T, h, w), z_ren)
    with pytest.raises(ValueError, match="u_latent must be a floating"):
        stereo_forcing(torch.ones(B, V, T, h, w, dtype=torch.int64), render())


@pytest.mark.parametrize(("size", "latent"), [((32, 48), (4, 6)), ((30, 45), (4, 6)), ((7, 5), (7, 5))])
def test_pooling_a_constant_map_gives_the_constant(size, latent):
    u = torch.full((B, V, *size), 0.37)
    out = pool_to_latent(u, latent)
    assert out.shape == (B, V, *latent)
    assert_close(out, torch.full_like(out, 0.37))
    frames = torch.full((B, V, 9, *size), 0.37)
    out = pool_to_latent(frames, latent, temporal_compression=4)
    assert out.shape == (B, V, 3, *latent)
    assert_close(out, torch.full_like(out, 0.37))


def test_pooling_by_integer_factors_preserves_the_mean_and_averages_each_block():
    u = torch.rand(B, V, 32, 48, generator=gen(2), dtype=torch.float64)
    out = pool_to_latent(u, (4, 6))
    assert_close(out.mean(dim=(-2, -1)), u.mean(dim=(-2, -1)))
    assert_close(out[1, 2, 3, 5], u[1, 2, 24:32, 40:48].mean())


def test_pooling_by_a_non_integer_factor_stays_in_the_unit_interval():
    u = torch.rand(2, 31, 45, generator=gen(3))
    out = pool_to_latent(u, (4, 6))
    assert out.shape == (2, 4, 6)
    assert bool(((out >= 0) & (out <= 1)).all())
    # Adaptive windows: rows floor(i 31 / 4) .. ceil((i + 1) 31 / 4) - 1.
    assert_close(out[0, 1, 0], u[0, 7:16, 0:8].mean())


def test_temporal_pooling_follows_the_causal_vae_for_nine_frames_at_compression_four():
    # Frame f holds the constant f (plus a per-pixel pattern that spatial pooling removes).
    pattern = torch.tensor([[0.0, 0.05], [0.05, 0.0]]).repeat(2, 2)  # 4 x 4, mean 0.025
    u = torch.stack([torch.full((4, 4), f / 10) + pattern for f in range(9)])  # [F=9, 4, 4]
    out = pool_to_latent(u[None], (1, 1), temporal_compression=4)  # [1, T=3, 1, 1]
    assert out.shape == (1, 3, 1, 1)
    expected = torch.tensor([0.0, (1 + 2 + 3 + 4) / 40, (5 + 6 + 7 + 8) / 40]) + 0.025
    assert_close(out.flatten(), expected)
    assert latent_frame_count(9, 4) == 3 and latent_frame_count(1, 4) == 1
    single = pool_to_latent(u[:1], (2, 2), temporal_compression=4)
    assert_close(single, pool_to_latent(u[:1], (2, 2)))


def test_pooling_rejects_bad_maps_and_shapes():
    with pytest.raises(ValueError, match=r"u must lie in \[0, 1\]"):
        pool_to_latent(torch.full((8, 8), 1.01), (2, 2))
    with pytest.raises(ValueError, match="u has NaN"):
        pool_to_latent(torch.full((8, 8), float("nan")), (2, 2))
    with pytest.raises(ValueError, match="latent_hw must be within"):
        pool_to_latent(torch.rand(8, 8), (16, 2))
    with pytest.raises(ValueError, match=r"takes 1 \+ k \* 4 frames, got 8"):
        pool_to_latent(torch.rand(8, 8, 8), (2, 2), temporal_compression=4)
    with pytest.raises(ValueError, match="temporal pooling needs frames"):
        pool_to_latent(torch.rand(8, 8), (2, 2), temporal_compression=4)
    with pytest.raises(ValueError, match=r"\[\.\.\., H, W\]"):
        pool_to_latent(torch.rand(8), (2, 2))


def test_drop_condition_drops_at_rate_p_and_zeroes_whole_samples_exactly():
    condition = torch.rand(4000, 2, 3) + 0.5  # no zeros of its own
    dropped, keep = drop_condition(condition, 0.3, gen(4))
    assert keep.shape == (4000,) and keep.dtype == torch.bool
    assert 1 - float(keep.float().mean()) == pytest.approx(0.3, abs=0.03)
    assert torch.equal(dropped[~keep], torch.zeros_like(dropped[~keep]))
    assert torch.equal(dropped[keep], condition[keep])
    again, keep_again = drop_condition(condition, 0.3, gen(4))
    assert torch.equal(keep, keep_again) and torch.equal(dropped, again)


def test_drop_condition_at_zero_and_one_keeps_or_drops_everything():
    condition = torch.rand(50, 3) + 0.5
    kept, keep = drop_condition(condition, 0.0, gen(0))
    assert bool(keep.all()) and torch.equal(kept, condition)
    gone, keep = drop_condition(condition, 1.0, gen(0))
    assert not bool(keep.any()) and torch.equal(gone, torch.zeros_like(condition))
    with pytest.raises(ValueError, match="p must be in"):
        drop_condition(condition, 1.5, gen(0))


def test_dropped_condition_equals_sf_with_u_zero():
    cond = stereo_forcing(torch.rand(B, V, T, h, w, generator=gen(6)), render())
    dropped, _ = drop_condition(cond, 1.0)
    assert torch.equal(dropped, stereo_forcing(torch.zeros(B, V, T, h, w), render()))


def test_guided_velocity_combines_the_two_branches():
    v_c, v_u = render(1), render(2)
    assert torch.equal(guided_velocity(v_c, v_u, 0.0), v_u)
    assert torch.equal(guided_velocity(v_c, v_u, 1.0), v_c)
    assert_close(guided_velocity(v_c, v_u, 0.25), 0.75 * v_u + 0.25 * v_c)
    with pytest.raises(ValueError, match="same shape"):
        guided_velocity(v_c, v_u[:1], 2.0)
