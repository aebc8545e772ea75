"""The image losses and metrics of ``phigenesis.models.losses`` against direct computations."""

from __future__ import annotations

import math

import numpy as np
import torch

from phigenesis.models.losses import ssim


def _ssim_at(a: np.ndarray, b: np.ndarray, i: int, j: int, window: int, sigma: float) -> float:
    """SSIM of one pixel of [H, W, C] images, straight from Wang et al.'s definition: Gaussian
    weights over the window around (i, j), reflected at the borders, averaged over channels."""
    h, w, _ = a.shape
    r = window // 2
    offsets = np.arange(-r, r + 1)
    g = np.exp(-(offsets**2) / (2 * sigma**2))
    weights = np.outer(g, g) / np.outer(g, g).sum()

    def reflect(k: int, n: int) -> int:
        return -k if k < 0 else 2 * (n - 1) - k if k >= n else k

    rows = [reflect(i + o, h) for o in offsets]
    cols = [reflect(j + o, w) for o in offsets]
    pa, pb = a[np.ix_(rows, cols)], b[np.ix_(rows, cols)]  # [window, window, C]
    values = []
    for ch in range(a.shape[2]):
        x, y = pa[..., ch], pb[..., ch]
        mx, my = (weights * x).sum(), (weights * y).sum()
        vx = (weights * (x - mx) ** 2).sum()
        vy = (weights * (y - my) ** 2).sum()
        cov = (weights * (x - mx) * (y - my)).sum()
        c1, c2 = 0.01**2, 0.03**2
        values.append((2 * mx * my + c1) * (2 * cov + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    return float(np.mean(values))


def test_ssim_matches_the_definition_pixel_by_pixel_borders_included():
    """Every pixel of a 9 x 11 image (most of them within 3 pixels of a border, where the window
    reflects) against the definition, in float64; leading dimensions pass through."""
    rng = np.random.default_rng(0)
    a = rng.random((2, 9, 11, 3))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    got = ssim(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    assert got.shape == (2, 9, 11)
    want = np.array(
        [[[_ssim_at(a[n], b[n], i, j, 7, 1.5) for j in range(11)] for i in range(9)] for n in range(2)]
    )
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_ssim_of_an_image_with_itself_is_one_and_falls_with_noise():
    rng = np.random.default_rng(1)
    a = torch.from_numpy(rng.random((16, 20, 3)))
    np.testing.assert_allclose(ssim(a, a).numpy(), 1.0, atol=1e-12)
    noisy = (a + 0.1 * torch.from_numpy(rng.standard_normal(a.shape))).clamp(0, 1)
    noisier = (a + 0.3 * torch.from_numpy(rng.standard_normal(a.shape))).clamp(0, 1)
    assert 1 > float(ssim(a, noisy).mean()) > float(ssim(a, noisier).mean()) > 0
    # A constant image against a shifted constant: only the luminance term remains.
    flat = torch.full((8, 8, 3), 0.5, dtype=torch.float64)
    want = (2 * 0.5 * 0.7 + 1e-4) / (0.5**2 + 0.7**2 + 1e-4)
    assert math.isclose(float(ssim(flat, flat + 0.2).mean()), want, rel_tol=1e-12)
