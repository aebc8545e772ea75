"""Losses and image metrics shared by Stage 1 training and evaluation (torch, differentiable).

Images are (..., H, W, 3) RGB in [0, 1] unless said otherwise; depths are camera z in metres with
0 meaning unknown.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from phigenesis.taxonomy import IGNORE_ID


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype) -> Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(a: Tensor, b: Tensor, window: int = 7, sigma: float = 1.5) -> Tensor:
    """Structural similarity per pixel, (..., H, W), of (..., H, W, C) images in [0, 1].

    Gaussian-weighted local statistics (``window`` x ``window``, reflect padding at the borders),
    constants of Wang et al. 2004 for a data range of 1, averaged over channels. A 7-pixel window
    suits the small images of CPU training (the usual 11 smooths a 48-pixel-high view too much).
    """
    lead, (h, w, c) = a.shape[:-3], a.shape[-3:]
    x = a.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    y = b.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    g = _gaussian_window(window, sigma, a.dtype).to(a.device)
    pad = window // 2
    # The five local statistics in one pass; the Gaussian window is separable (rows, then columns:
    # 2 x window products per pixel instead of window^2).
    z = F.pad(torch.cat([x, y, x * x, y * y, x * y], dim=1), (pad, pad, pad, pad), mode="reflect")
    n = z.shape[1]
    z = F.conv2d(z, g.view(1, 1, window, 1).expand(n, 1, window, 1), groups=n)
    z = F.conv2d(z, g.view(1, 1, 1, window).expand(n, 1, 1, window), groups=n)
    mx, my, xx, yy, xy = z.split(c, dim=1)
    vx = xx - mx * mx
    vy = yy - my * my
    cov = xy - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * cov + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return s.mean(1).reshape(*lead, h, w)


def photometric_loss(render: Tensor, target: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """``(1 - w) L1 + w (1 - SSIM)`` over (..., H, W, 3) images, the 3DGS photometric loss."""
    l1 = (render - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(render, target)).mean()


def log_depth_loss(pred: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Confidence-weighted mean ``|log pred - log target|`` over pixels where both depths are known
    (> 0): a relative error, so a 1 m miss at 50 m counts as little as 2 cm at 1 m."""
    known = (target > 0) & (pred > 0)
    w = torch.where(known, weight, torch.zeros_like(weight))
    total = w.sum()
    if total <= 0:
        return pred.sum() * 0.0
    err = (torch.log(pred.clamp(min=1e-6)) - torch.log(target.clamp(min=1e-6))).abs()
    return (w * torch.where(known, err, torch.zeros_like(err))).sum() / total


def edge_aware_smoothness(depth: Tensor, image: Tensor, edge_scale: float = 10.0) -> Tensor:
    """Mean ``|d(1/z)| exp(-edge_scale |dI|)`` over horizontal and vertical neighbours of (..., H, W)
    depths (metres, > 0) in (..., H, W, 3) images in [0, 1]; the inverse depth is divided by its mean
    per image, so the loss does not shrink the scene. Smooth where the image is, free at its edges
    (Monodepth's prior): it carries depth from pixels the LiDAR measured to those it never reached,
    like the upper floors of a wall."""
    inv = 1.0 / depth.clamp(min=1e-6)
    inv = inv / inv.mean(dim=(-2, -1), keepdim=True).clamp(min=1e-6)
    grad_img_x = (image[..., :, 1:, :] - image[..., :, :-1, :]).abs().mean(-1)
    grad_img_y = (image[..., 1:, :, :] - image[..., :-1, :, :]).abs().mean(-1)
    dx = (inv[..., :, 1:] - inv[..., :, :-1]).abs() * torch.exp(-edge_scale * grad_img_x)
    dy = (inv[..., 1:, :] - inv[..., :-1, :]).abs() * torch.exp(-edge_scale * grad_img_y)
    return dx.mean() + dy.mean()


def semantic_loss(logits: Tensor, labels: Tensor) -> Tensor:
    """Cross-entropy of (..., K) logits against (...) uint8 labels; 255 is ignored."""
    target = labels.long().reshape(-1)
    if not (target != IGNORE_ID).any():
        return logits.sum() * 0.0
    return F.cross_entropy(logits.reshape(-1, logits.shape[-1]), target, ignore_index=IGNORE_ID)


def psnr(a: Tensor, b: Tensor) -> Tensor:
    """Peak signal-to-noise ratio (dB) of (..., H, W, 3) images in [0, 1], one per leading index."""
    mse = ((a - b) ** 2).flatten(-3).mean(-1)
    return -10 * torch.log10(mse.clamp(min=1e-10))
