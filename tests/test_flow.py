"""Rectified flow of Stage 2: the velocity's sign, timesteps and their shift, the Euler sampler
(exact on straight paths, held history frames, guidance) and the masked flow loss."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch.testing import assert_close

from phigenesis.models.flow import (
    Anchor,
    FixedFrames,
    as_frame_time,
    broadcast_time,
    euler_sample,
    flow_loss,
    guided_velocity,
    interpolate,
    resolution_shift,
    sample_time,
    shift_time,
    time_grid,
    velocity_target,
)

SHAPE = (2, 3, 4, 5, 3, 2)  # B, V, C, T, h, w


def latents(seed: int, shape: tuple[int, ...] = SHAPE, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def test_velocity_target_is_z0_minus_eps_the_negative_time_derivative_of_the_path():
    z0, eps = latents(0), latents(1)
    assert torch.equal(velocity_target(z0, eps), z0 - eps)
    t = torch.full((SHAPE[0],), 0.3, dtype=torch.float64, requires_grad=True)
    dz_dt = torch.autograd.grad(interpolate(z0, eps, t).sum(), t)[0]  # [B]: sum of dz_t/dt per clip
    assert_close(dz_dt, -velocity_target(z0, eps).sum(dim=(1, 2, 3, 4, 5)))


def test_interpolate_is_clean_at_zero_and_noise_at_one():
    z0, eps = latents(0), latents(1)
    assert torch.equal(interpolate(z0, eps, 0.0), z0)
    assert torch.equal(interpolate(z0, eps, 1.0), eps)
    assert_close(interpolate(z0, eps, 0.25), 0.75 * z0 + 0.25 * eps)


def test_one_euler_step_with_the_target_velocity_lands_on_z0():
    z0, eps = latents(0), latents(1)
    out = euler_sample(lambda z, t, c: velocity_target(z0, eps), eps, steps=1)
    assert_close(out, z0, rtol=0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 60), st.floats(0.1, 10.0), st.integers(0, 2**16))
def test_euler_with_the_exact_constant_velocity_recovers_z0_for_any_steps_and_shift(steps, shift, seed):
    z0, eps = latents(seed), latents(seed + 1)
    out = euler_sample(lambda z, t, c: velocity_target(z0, eps), eps, steps=steps, shift=shift)
    assert_close(out, z0, rtol=0, atol=1e-10)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 40), st.floats(0.1, 10.0))
def test_euler_with_the_single_point_oracle_field_recovers_z0(steps, shift):
    # For data at one point z0 the exact field is v(z_t, t) = (z0 - z_t) / t: it needs the right
    # z_t and the right t at every step to stay on the straight path.
    z0, eps = latents(3), latents(4)
    seen = []

    def oracle(z, t, c):
        seen.append(t.clone())
        return (z0 - z) / broadcast_time(t, z)

    out = euler_sample(oracle, eps, steps=steps, shift=shift)
    assert_close(out, z0, rtol=0, atol=1e-9)
    grid = time_grid(steps, shift)
    assert [float(t[0, 0]) for t in seen] == grid[:-1].tolist()


def test_euler_recovers_z0_in_float32_to_float_tolerance():
    z0, eps = latents(0, dtype=torch.float32), latents(1, dtype=torch.float32)
    out = euler_sample(lambda z, t, c: velocity_target(z0, eps), eps, steps=30, shift=3.0)
    assert out.dtype == torch.float32
    assert_close(out, z0, rtol=0, atol=1e-5)


def _cell_weight(seed: int) -> torch.Tensor:
    """[B, V, 1, T, h, w] weights in [0, 1] with exact zeros and ones among them."""
    w = torch.rand(SHAPE[0], SHAPE[1], 1, *SHAPE[3:], generator=torch.Generator().manual_seed(seed))
    w[..., 0, 0] = 0.0
    w[..., 1, 0] = 1.0
    return w.double()


def test_a_full_anchor_to_the_end_lands_on_its_latents_and_a_zero_weight_leaves_the_network_alone():
    ref, noise = latents(5), latents(6)
    weight = _cell_weight(0)
    free = euler_sample(lambda z, t, c: -z, noise, steps=5, shift=2.0)
    out = euler_sample(lambda z, t, c: -z, noise, steps=5, shift=2.0, anchor=Anchor(ref, weight))
    full = (weight == 1).expand_as(ref)
    none = (weight == 0).expand_as(ref)
    assert torch.equal(out[full], ref[full])
    assert torch.equal(out[none], free[none])
    between = ((weight > 0) & (weight < 1)).expand_as(ref)
    assert bool(((out - ref).abs()[between] < (free - ref).abs()[between]).float().mean() > 0.9)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 30), st.floats(0.2, 5.0), st.floats(0.0, 0.95), st.integers(0, 2**16))
def test_anchoring_to_the_latents_the_exact_velocity_leads_to_changes_nothing(steps, shift, until, seed):
    # The anchor's path is the straight one from the sampler's noise to its latents: a network
    # that already follows it is not moved, whatever the weights.
    z0, eps = latents(seed), latents(seed + 1)
    plain = euler_sample(lambda z, t, c: velocity_target(z0, eps), eps, steps=steps, shift=shift)
    anchored = euler_sample(
        lambda z, t, c: velocity_target(z0, eps),
        eps,
        steps=steps,
        shift=shift,
        anchor=Anchor(z0, _cell_weight(seed), until=until),
    )
    assert_close(anchored, plain, rtol=0, atol=1e-10)


def test_an_anchor_stops_at_its_time_and_leaves_held_frames_as_held():
    ref, noise, hist = latents(5), latents(6), latents(7)
    grid = time_grid(4).tolist()  # 1, 0.75, 0.5, 0.25, 0
    states = []
    fixed = FixedFrames(mask=torch.tensor([True, False, False, False, False]), z0=hist, level=0.0)
    anchor = Anchor(ref, torch.ones(SHAPE[0], SHAPE[1], 1, *SHAPE[3:], dtype=torch.float64), until=0.5)
    euler_sample(
        lambda z, t, c: -z, noise, 4, fixed=fixed, anchor=anchor, callback=lambda i, t, z: states.append(z)
    )
    for step, z in enumerate(states):
        t_now = grid[step + 1]
        on_path = interpolate(ref, noise, t_now)[:, :, :, 1:]
        assert torch.equal(z[:, :, :, 0], hist[:, :, :, 0])
        if t_now >= 0.5:
            assert_close(z[:, :, :, 1:], on_path, rtol=0, atol=1e-12)
        else:  # the network's own steps from there: dz = -(t - t') z
            assert_close(z[:, :, :, 1:], states[step - 1][:, :, :, 1:] * (1 - (grid[step] - t_now)))


@pytest.mark.parametrize("bad", ["weight", "until", "nan", "shape"])
def test_a_bad_anchor_raises(bad):
    weight = torch.ones(SHAPE[0], SHAPE[1], 1, *SHAPE[3:])
    if bad == "weight":
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            Anchor(latents(0), weight * 1.5)
    elif bad == "until":
        with pytest.raises(ValueError, match="until"):
            Anchor(latents(0), weight, until=1.0)
    elif bad == "nan":
        with pytest.raises(ValueError, match="NaN"):
            Anchor(latents(0) * float("nan"), weight)
    else:
        with pytest.raises(ValueError, match=r"anchor\.z0 and noise"):
            euler_sample(
                lambda z, t, c: -z, latents(1, (1, 3, 4, 5, 3, 2)), 2, anchor=Anchor(latents(0), weight)
            )


def test_shift_time_fixes_the_endpoints_is_monotone_and_is_the_identity_at_one():
    t = torch.linspace(0, 1, 1001, dtype=torch.float64)
    assert torch.equal(shift_time(t, 1.0), t)
    for r in (0.25, 0.5, 2.0, 3.0, 10.0):
        s = shift_time(t, r)
        assert float(s[0]) == 0.0 and float(s[-1]) == 1.0
        assert bool((s[1:] > s[:-1]).all())
        assert bool((s >= t).all()) if r > 1 else bool((s <= t).all())
        assert_close(shift_time(s, 1 / r), t)  # 1 / r undoes r
    assert shift_time(0.5, 3.0) == pytest.approx(0.75)


@pytest.mark.parametrize("shift", [0.0, -1.0, math.inf, math.nan])
def test_shift_must_be_positive_and_finite(shift):
    with pytest.raises(ValueError, match="shift"):
        shift_time(0.5, shift)


def test_resolution_shift_follows_magicdrivedit_on_image_pixels_and_is_clamped_to_one():
    assert resolution_shift(512, 512, 1) == 1.0
    assert resolution_shift(1024, 1024, 4) == pytest.approx(4.0)  # sqrt(4) * sqrt(4)
    assert resolution_shift(576, 1024, 9) == pytest.approx(math.sqrt(576 * 1024 / 512**2) * 3)
    assert resolution_shift(160, 240, 1) == 1.0  # 0.38 unclamped
    assert resolution_shift(256, 256, 1, base_pixels=128 * 128) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="latent_frames"):
        resolution_shift(512, 512, 0)


def test_time_grid_falls_strictly_from_one_to_zero_on_the_shifted_uniform_grid():
    for steps, shift in [(1, 1.0), (30, 1.0), (30, 3.0), (7, 0.5)]:
        grid = time_grid(steps, shift)
        assert grid.shape == (steps + 1,) and grid.dtype == torch.float64
        assert float(grid[0]) == 1.0 and float(grid[-1]) == 0.0
        assert bool((grid[1:] < grid[:-1]).all())
        assert_close(grid, shift_time(torch.linspace(1, 0, steps + 1, dtype=torch.float64), shift))
    with pytest.raises(ValueError, match="steps"):
        time_grid(0)


def test_logit_normal_times_lie_in_the_open_interval_with_median_one_half():
    t = sample_time(20000, torch.Generator().manual_seed(0))
    assert t.shape == (20000,) and t.dtype == torch.float32
    assert bool(((t > 0) & (t < 1)).all())
    assert float(t.median()) == pytest.approx(0.5, abs=0.02)
    # The shift moves the median to r / (1 + r).
    shifted = sample_time(20000, torch.Generator().manual_seed(0), shift=3.0)
    assert float(shifted.median()) == pytest.approx(0.75, abs=0.02)
    again = sample_time(20000, torch.Generator().manual_seed(0))
    assert torch.equal(t, again)


def test_per_frame_times_are_independent_levels_per_latent_frame():
    t = sample_time(4000, torch.Generator().manual_seed(1), per_frame=3)
    assert t.shape == (4000, 3)
    assert not torch.equal(t[:, 0], t[:, 1])
    corr = torch.corrcoef(t.T.double())
    assert float((corr - torch.eye(3, dtype=torch.float64)).abs().max()) < 0.06


def test_per_clip_and_per_frame_time_broadcast_against_latents():
    z = latents(0)
    batch, frames = SHAPE[0], SHAPE[3]
    per_clip = torch.tensor([0.2, 0.7], dtype=torch.float64)
    per_frame = torch.rand(batch, frames, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    assert broadcast_time(per_clip, z).shape == (batch, 1, 1, 1, 1, 1)
    assert broadcast_time(per_frame, z).shape == (batch, 1, 1, frames, 1, 1)
    assert torch.equal(as_frame_time(per_clip, batch, frames), per_clip[:, None].expand(batch, frames))
    eps = latents(1)
    zt = interpolate(z, eps, per_frame)
    for b in range(batch):
        for k in range(frames):
            s = float(per_frame[b, k])
            assert_close(zt[b, :, :, k], (1 - s) * z[b, :, :, k] + s * eps[b, :, :, k])
    # A per-clip time equals the per-frame time that repeats it.
    assert torch.equal(
        interpolate(z, eps, per_clip), interpolate(z, eps, as_frame_time(per_clip, batch, frames))
    )


@pytest.mark.parametrize("bad", [torch.zeros(3), torch.zeros(2, 4), torch.zeros(2, 5, 1)])
def test_time_of_the_wrong_shape_raises(bad):
    with pytest.raises(ValueError, match="time must be"):
        interpolate(latents(0), latents(1), bad.double())


def test_latents_must_be_six_dimensional():
    with pytest.raises(ValueError, match=r"\[B, V, C, T, h, w\]"):
        interpolate(torch.zeros(2, 3, 4), torch.zeros(2, 3, 4), 0.5)


def test_fixed_frames_stay_exactly_at_their_level_and_are_given_that_time():
    z0_hist, eps_fixed, noise = latents(0), latents(1), latents(2)
    mask = torch.tensor([True, True, False, False, False])
    fixed = FixedFrames(mask=mask, z0=z0_hist, level=0.1, noise=eps_fixed)
    held = interpolate(z0_hist, eps_fixed, 0.1)
    times, states = [], []

    def velocity_fn(z, t, c):
        times.append(t.clone())
        assert torch.equal(z[:, :, :, :2], held[:, :, :, :2])
        return -z

    out = euler_sample(
        velocity_fn, noise, steps=6, shift=2.0, fixed=fixed, callback=lambda i, t, z: states.append((i, t, z))
    )
    assert len(times) == 6 and [i for i, _, _ in states] == list(range(6))
    for t in [*times, *(t for _, t, _ in states)]:
        assert t.shape == (SHAPE[0], SHAPE[3])
        assert bool((t[:, :2] == torch.tensor(0.1, dtype=t.dtype)).all())
    for _, _, z in states:
        assert torch.equal(z[:, :, :, :2], held[:, :, :, :2])
    assert torch.equal(out[:, :, :, :2], held[:, :, :, :2])
    assert float(states[-1][1][0, 2]) == 0.0  # the generated frames end at t = 0
    assert not torch.equal(out[:, :, :, 2:], noise[:, :, :, 2:])


def test_fixed_frames_per_sample_mask_and_noise_from_the_generator_are_reproducible():
    z0_hist, noise = latents(0), latents(2)
    mask = torch.zeros(SHAPE[0], SHAPE[3], dtype=torch.bool)
    mask[0, 0] = mask[1, :3] = True
    fixed = FixedFrames(mask=mask, z0=z0_hist, level=0.05)
    runs = [
        euler_sample(lambda z, t, c: -z, noise, 4, fixed=fixed, generator=torch.Generator().manual_seed(9))
        for _ in range(2)
    ]
    assert torch.equal(runs[0], runs[1])
    eps = torch.randn(SHAPE, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    held = interpolate(z0_hist, eps, 0.05)
    assert torch.equal(runs[0][0, :, :, 0], held[0, :, :, 0])
    assert torch.equal(runs[0][1, :, :, :3], held[1, :, :, :3])
    assert not torch.equal(runs[0][0, :, :, 1], held[0, :, :, 1])


def test_fixed_frames_at_level_zero_hold_the_clean_history():
    z0_hist = latents(0)
    fixed = FixedFrames(mask=torch.tensor([True, False, False, False, False]), z0=z0_hist, level=0.0)
    out = euler_sample(lambda z, t, c: -z, latents(2), 3, fixed=fixed)
    assert torch.equal(out[:, :, :, 0], z0_hist[:, :, :, 0])


@pytest.mark.parametrize("level", [-0.1, 1.0])
def test_fixed_frames_level_must_be_in_the_half_open_unit_interval(level):
    with pytest.raises(ValueError, match="level"):
        FixedFrames(mask=torch.ones(5, dtype=torch.bool), z0=latents(0), level=level)


def test_masked_loss_ignores_the_frames_left_out():
    z0, eps = latents(0), latents(1)
    pred = latents(2)
    mask = torch.tensor([False, True, True, False, True])
    loss = flow_loss(pred, z0, eps, mask)
    err = (pred - (z0 - eps)) ** 2
    assert_close(loss, err[:, :, :, mask].mean())
    wild = pred.clone()
    wild[:, :, :, ~mask] = float("nan")
    assert_close(flow_loss(wild, z0, eps, mask), loss)
    wild.requires_grad_(True)
    flow_loss(wild, z0, eps, mask).backward()
    assert bool((wild.grad[:, :, :, ~mask] == 0).all())
    assert bool(torch.isfinite(wild.grad).all())


def test_loss_without_a_mask_is_the_plain_mse_and_a_per_sample_mask_counts_its_own_frames():
    z0, eps, pred = latents(0), latents(1), latents(2)
    err = (pred - velocity_target(z0, eps)) ** 2
    assert_close(flow_loss(pred, z0, eps), err.mean())
    assert float(flow_loss(velocity_target(z0, eps), z0, eps)) == 0.0
    mask = torch.zeros(SHAPE[0], SHAPE[3], dtype=torch.bool)
    mask[0, 4] = mask[1, 1:] = True
    expected = torch.cat([err[0, :, :, 4].flatten(), err[1, :, :, 1:].flatten()]).mean()
    assert_close(flow_loss(pred, z0, eps, mask), expected)
    with pytest.raises(ValueError, match="counts no frame"):
        flow_loss(pred, z0, eps, torch.zeros(SHAPE[3], dtype=torch.bool))


def toy_velocity(z, t, c):
    """A velocity that depends on the latents, the time and the condition."""
    return c - 0.5 * z * (1 + broadcast_time(t, z))


def hand_euler(velocity, noise, steps, shift):
    grid = time_grid(steps, shift).tolist()
    z = noise
    for i in range(steps):
        t = torch.full((noise.shape[0], noise.shape[3]), grid[i], dtype=noise.dtype)
        z = z + (grid[i] - grid[i + 1]) * velocity(z, t)
    return z


def counting(fn, calls):
    def wrapped(z, t, c):
        calls.append(None if c is None else c.clone())
        return fn(z, t, c)

    return wrapped


def test_omega_zero_is_exactly_the_unconditional_trajectory_and_skips_the_conditional_pass():
    noise, cond = latents(0), latents(1)
    calls = []
    out = euler_sample(counting(toy_velocity, calls), noise, 5, shift=2.0, omega=0.0, condition=cond)
    assert len(calls) == 5 and all(torch.equal(c, torch.zeros_like(cond)) for c in calls)
    zeros = torch.zeros_like(cond)
    assert torch.equal(out, hand_euler(lambda z, t: toy_velocity(z, t, zeros), noise, 5, 2.0))


def test_omega_one_is_exactly_the_conditional_trajectory_and_skips_the_unconditional_pass():
    noise, cond = latents(0), latents(1)
    calls = []
    out = euler_sample(counting(toy_velocity, calls), noise, 5, shift=2.0, omega=1.0, condition=cond)
    assert len(calls) == 5 and all(torch.equal(c, cond) for c in calls)
    assert torch.equal(out, hand_euler(lambda z, t: toy_velocity(z, t, cond), noise, 5, 2.0))


def test_no_condition_runs_the_network_once_per_step_with_none():
    calls = []
    euler_sample(counting(lambda z, t, c: -z, calls), latents(0), 4, omega=3.0)
    assert calls == [None] * 4


def test_guidance_in_between_is_the_linear_combination_of_the_two_passes():
    noise, cond = latents(0), latents(1)
    zeros = torch.zeros_like(cond)
    for omega in (0.3, 2.0, -0.5):
        calls = []
        out = euler_sample(counting(toy_velocity, calls), noise, 6, shift=1.5, omega=omega, condition=cond)
        assert len(calls) == 12

        def combined(z, t, omega=omega):
            v_c, v_u = toy_velocity(z, t, cond), toy_velocity(z, t, zeros)
            return v_u + omega * (v_c - v_u)

        assert_close(out, hand_euler(combined, noise, 6, 1.5), rtol=0, atol=1e-12)
    # A velocity that ignores z makes the whole trajectory linear in omega.
    field = lambda z, t, c: c * broadcast_time(t, z) - 0.3  # noqa: E731
    ends = {w: euler_sample(field, noise, 7, shift=2.0, omega=w, condition=cond) for w in (0.0, 1.0, 0.4)}
    assert_close(ends[0.4], 0.6 * ends[0.0] + 0.4 * ends[1.0], rtol=0, atol=1e-12)


def test_guided_velocity_is_exact_at_zero_and_one():
    v_c, v_u = latents(0), latents(1)
    assert guided_velocity(v_c, v_u, 0.0) is v_u
    assert guided_velocity(v_c, v_u, 1.0) is v_c
    assert_close(guided_velocity(v_c, v_u, 2.0), 2 * v_c - v_u)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_or_inf_in_the_noise_raises(bad):
    noise = latents(0)
    noise[1, 2, 3, 4, 0, 1] = bad
    with pytest.raises(ValueError, match="noise has NaN"):
        euler_sample(lambda z, t, c: -z, noise, 3)


def test_a_velocity_of_the_wrong_shape_raises():
    with pytest.raises(ValueError, match="velocity_fn returned shape"):
        euler_sample(lambda z, t, c: z[:, :1], latents(0), 2)
