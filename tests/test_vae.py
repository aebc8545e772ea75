"""The causal video VAE: shapes, causality, KL, decoder features, training, checkpoints, freezing."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
import torch

from phigenesis.models import create_model
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.train.checkpoint import CheckpointError, save_checkpoint

if TYPE_CHECKING:
    from phigenesis.models.vae import VideoVAE

# phigenesis.models.vae is imported inside the tests, never at collection: importing it registers
# vae_tiny and vae_base, and tests/test_segformer.py parametrises over every registered variant at
# its own collection, expecting segmenters.
VARIANTS = ("vae_tiny", "vae_base")


def _tiny(seed: int = 0, **overrides: object) -> VideoVAE:
    import phigenesis.models.vae  # noqa: F401  (registers the variants)

    torch.manual_seed(seed)
    return create_model("vae_tiny", **overrides)  # type: ignore[return-value]


def _video(b: int, t: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, t, h, w, generator=g) * 2 - 1


def _moving_pattern(b: int, t: int, h: int, w: int) -> torch.Tensor:
    """A bright blob moving right over a fixed colour gradient, in [-1, 1]: ``[B, 3, T, H, W]``."""
    ys = torch.linspace(-1, 1, h).view(1, 1, h, 1)
    xs = torch.linspace(-1, 1, w).view(1, 1, 1, w)
    frames = []
    for k in range(t):
        cx = torch.linspace(-0.6, 0.6, b).view(b, 1, 1, 1) + 0.1 * k
        blob = torch.exp(-((xs - cx).square() + ys.square()) / 0.08)  # [B, 1, H, W]
        background = torch.cat([0.5 * xs.expand(b, 1, h, w), 0.5 * ys.expand(b, 1, h, w), -0.3 + 0 * blob], 1)
        frames.append((background + blob).clamp(-1, 1))
    return torch.stack(frames, dim=2)


@pytest.mark.parametrize("name", VARIANTS)
def test_every_variant_compresses_4x_in_time_keeping_the_first_frame_alone(name: str) -> None:
    from phigenesis.models.vae import CONFIGS

    assert set(VARIANTS) == set(CONFIGS)
    torch.manual_seed(0)
    model = create_model(name).eval()
    c = model.config
    s = c.spatial_compression
    assert model.name == name and c.temporal_compression == 4
    assert s == {"vae_tiny": 4, "vae_base": 8}[name]
    with torch.no_grad():
        post = model.encode(_video(1, 5, 2 * s, 3 * s))
        assert post.mean.shape == (1, c.latent_channels, 2, 2, 3)
        assert model.decode(post.mean).shape == (1, 3, 5, 2 * s, 3 * s)


@pytest.mark.parametrize(("t", "h", "w"), [(1, 16, 16), (5, 16, 24), (9, 32, 16), (13, 8, 8)])
def test_forward_shapes_for_images_and_videos(t: int, h: int, w: int) -> None:
    model = _tiny()
    out = model(_video(2, t, h, w))
    t_lat = 1 + (t - 1) // 4
    assert out.reconstruction.shape == (2, 3, t, h, w)
    assert out.posterior.mean.shape == out.posterior.logvar.shape == (2, 4, t_lat, h // 4, w // 4)
    assert out.kl.shape == (2,) and bool((out.kl > 0).all())
    assert torch.isfinite(out.reconstruction).all()


def test_sizes_that_do_not_divide_are_rejected_with_the_shape() -> None:
    model = _tiny()
    with pytest.raises(AssertionError, match="T - 1 must divide by 4"):
        model.encode(_video(1, 4, 16, 16))
    with pytest.raises(AssertionError, match="H and W by 4"):
        model.encode(_video(1, 5, 18, 16))


def test_causal_conv_output_at_t_ignores_later_frames() -> None:
    from phigenesis.models.vae import CausalConv3d

    torch.manual_seed(0)
    conv = CausalConv3d(3, 4)
    x = _video(1, 6, 8, 8)
    y = x.clone()
    y[:, :, 3:] = torch.randn_like(y[:, :, 3:])
    with torch.no_grad():
        a, b = conv(x), conv(y)
    torch.testing.assert_close(a[:, :, :3], b[:, :, :3])
    assert not torch.allclose(a[:, :, 3], b[:, :, 3])


@pytest.mark.parametrize("k", [0, 1])
def test_changing_frames_after_4k_leaves_latents_up_to_k_and_frames_up_to_4k_unchanged(k: int) -> None:
    model = _tiny().eval()
    x = _video(1, 9, 16, 16)
    y = x.clone()
    y[:, :, 4 * k + 1 :] = _video(1, 8 - 4 * k, 16, 16, seed=1)  # frames after 4k only
    with torch.no_grad():
        za, zb = model.encode(x).mean, model.encode(y).mean
        torch.testing.assert_close(za[:, :, : k + 1], zb[:, :, : k + 1])
        assert not torch.allclose(za[:, :, k + 1], zb[:, :, k + 1])
        # Decoding: latent frames after k change only output frames after 4k.
        za_mod = za.clone()
        za_mod[:, :, k + 1 :] = torch.randn_like(za_mod[:, :, k + 1 :])
        va, vb = model.decode(za), model.decode(za_mod)
        torch.testing.assert_close(va[:, :, : 4 * k + 1], vb[:, :, : 4 * k + 1])
        assert not torch.allclose(va[:, :, 4 * k + 1], vb[:, :, 4 * k + 1])
        # End to end, the first frame's reconstruction equals that of the image alone.
        torch.testing.assert_close(model.predict(x)[:, :, :1], model.predict(x[:, :, :1]))


def test_kl_is_zero_at_the_prior_and_positive_elsewhere() -> None:
    from phigenesis.models.vae import DiagonalGaussian

    shape = (2, 4, 3, 2, 2)
    zero = torch.zeros(shape)
    assert torch.equal(DiagonalGaussian(zero, zero).kl(), torch.zeros(2))
    shifted = DiagonalGaussian(torch.full(shape, 0.5), zero).kl()
    torch.testing.assert_close(shifted, torch.full((2,), 0.5 * 0.25 * math.prod(shape[1:])))
    assert bool((DiagonalGaussian(zero, torch.full(shape, -1.0)).kl() > 0).all())


def test_logvar_is_clamped_and_samples_are_reparameterised() -> None:
    model = _tiny(logvar_min=-2.0, logvar_max=1.0)
    post = model.encode(_video(1, 1, 8, 8) * 1e3)  # huge inputs push the log-variance out of range
    assert post.logvar.min() >= -2.0 and post.logvar.max() <= 1.0
    g = torch.Generator().manual_seed(3)
    z = post.sample(g)
    z.sum().backward()
    assert model.encoder.conv_out.conv.weight.grad is not None
    assert z.shape == post.mean.shape and not torch.equal(z, post.mode())


def test_decode_features_are_coarse_to_fine_and_end_at_the_output_size() -> None:
    model = _tiny().eval()
    z = torch.randn(2, 4, 3, 4, 6)
    with torch.no_grad():
        feats = model.decode_features(z)
    assert [tuple(f.shape) for f in feats] == [(2, 64, 3, 4, 6), (2, 32, 5, 8, 12), (2, 16, 9, 16, 24)]
    base = create_model("vae_base").eval()
    with torch.no_grad():
        feats = base.decode_features(torch.randn(1, 16, 2, 2, 2))
    assert [tuple(f.shape) for f in feats] == [
        (1, 256, 2, 2, 2),
        (1, 256, 2, 4, 4),
        (1, 128, 3, 8, 8),
        (1, 64, 5, 16, 16),
    ]


def test_a_short_training_run_cuts_the_reconstruction_loss_threefold_on_a_moving_pattern() -> None:
    torch.manual_seed(0)
    model = _tiny()
    from phigenesis.models.vae import vae_loss

    video = _moving_pattern(2, 5, 16, 16)
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    losses = []
    for _ in range(60):
        parts = vae_loss(model(video), video, beta=1e-6)
        opt.zero_grad()
        parts["loss"].backward()
        opt.step()
        losses.append(parts["reconstruction"].item())
    first, last = sum(losses[:5]) / 5, sum(losses[-5:]) / 5
    assert last < 0.3 * first, (first, last)


def test_vae_loss_weights_kl_per_input_element_and_supports_l2() -> None:
    from phigenesis.models.vae import vae_loss

    model = _tiny()
    video = _video(2, 5, 8, 8)
    out = model(video)
    l1 = vae_loss(out, video, beta=0.0)
    assert torch.equal(l1["loss"], l1["reconstruction"])
    l2 = vae_loss(out, video, beta=2.0, reconstruction="l2")
    expected = (out.reconstruction - video).square().mean() + 2.0 * out.kl.mean() / video[0].numel()
    torch.testing.assert_close(l2["loss"], expected)
    with pytest.raises(ValueError, match="unknown reconstruction"):
        vae_loss(out, video, reconstruction="ssim")  # type: ignore[arg-type]


def test_checkpoint_round_trip_rebuilds_the_same_model(tmp_path: Path) -> None:
    model = _tiny(seed=1).eval()
    video = _video(1, 5, 8, 8)
    path = save_checkpoint(tmp_path / "vae.pt", model, meta={"steps": 3})
    ckpt = load_checkpoint(path, model_name="vae_tiny")
    assert ckpt.model_name == "vae_tiny" and ckpt.meta == {"steps": 3}
    assert ckpt.model.config == model.config
    torch.testing.assert_close(ckpt.model.predict(video), model.predict(video))
    # Another config under the same name is refused when the caller names the variant.
    save_checkpoint(tmp_path / "wide.pt", _tiny(latent_channels=8))
    with pytest.raises(CheckpointError, match="latent_channels"):
        load_checkpoint(tmp_path / "wide.pt", model_name="vae_tiny")
    assert load_checkpoint(tmp_path / "wide.pt").model.config.latent_channels == 8


def test_freeze_makes_parameters_non_trainable_and_keeps_eval_mode() -> None:
    model = _tiny()
    assert all(p.requires_grad for p in model.parameters())
    assert model.freeze() is model
    assert not any(p.requires_grad for p in model.parameters())
    model.train()
    assert not model.training and not any(m.training for m in model.modules())
    out = model(_video(1, 1, 8, 8))
    assert not out.reconstruction.requires_grad


def test_config_rejects_mismatched_levels_and_groups() -> None:
    from phigenesis.models.vae import CONFIGS, VideoVAEConfig

    with pytest.raises(ValueError, match="temporal_downsample needs 2 entries"):
        VideoVAEConfig(channels=(16, 32, 64), temporal_downsample=(True,), norm_groups=8)
    with pytest.raises(ValueError, match="norm_groups"):
        VideoVAEConfig(channels=(16, 30), temporal_downsample=(True,), norm_groups=8)
    c = CONFIGS["vae_tiny"]
    assert VideoVAEConfig.from_dict(c.to_dict()) == c
