"""The scene-flow and dynamic-region metrics feed-forward driving reconstruction papers report
(STORM, arXiv 2501.00602, ``engine_storm.py::evaluate`` and ``evaluate_flow``; the flow formulas
are Neural Scene Flow Prior's, as EmerNeRF also uses them), so Stage 1's figures can stand beside
theirs.

Scene flow, per pixel, of a predicted velocity ``v_hat`` against the truth ``v`` (both world frame,
**metres per second**: STORM's unit; EmerNeRF's flow is displacement per 0.1 s frame, ten times
smaller, so its thresholds are ten times looser and its numbers do not compare), with
``e = |v_hat - v|`` and ``r = e / (|v| + 1e-20)``:

- ``epe3d_mps`` = mean e;
- ``acc5`` = share of pixels with e < 0.05 or r < 0.05 (STORM's ``acc3d_strict``, reported x 100
  there, a share in [0, 1] here);
- ``acc10`` = share with e < 0.1 or r < 0.1 (``acc3d_relax``);
- ``outlier`` = share with e > 0.3 or r > 0.1;
- ``angle_rad`` = mean angle between v_hat and v over the pixels where |v| > 0.1 m/s (a predicted
  velocity of exactly 0 has no direction and counts as 90 degrees).

Pixels scored (:func:`flow_pixels`): truth depth > 0 and not ground, as STORM does; a batch of
views is scored only when its fastest truth pixel exceeds :data:`MOVING_MPS` (STORM skips clips
without motion). Values are pooled over every scored pixel of every scored batch.

Dynamic regions (:func:`dynamic_mask`): the pixels of the truth's moving things. STORM (and
EmerNeRF) mark the 2D rectangle around every projected box faster than 1 m/s; with a synthetic
cache's exact per-pixel flow the mask here is the moving surfaces themselves (truth flow faster than
:data:`MOVING_MPS`), which leaves the background inside a rectangle out. PSNR over them is
-10 log10 of the mean squared error over the masked pixels of an image; SSIM is the mean of the
full SSIM map over them; images whose mask is empty are skipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from phigenesis.taxonomy import GROUND_IDS

#: A surface is moving (dynamic) when its truth speed exceeds this, m/s (STORM's threshold).
MOVING_MPS = 1.0
#: Speed below which the angle between flows is not scored, m/s.
ANGLE_MIN_MPS = 0.1
_TINY = 1e-20


def flow_pixels(truth_depth: Tensor, truth_semantic: Tensor) -> Tensor:
    """[..., H, W] bool: the pixels whose flow is scored: a truth depth > 0 and a class that is not
    ground (road, sidewalk, ...)."""
    ground = torch.zeros_like(truth_semantic, dtype=torch.bool)
    for k in GROUND_IDS:
        ground |= truth_semantic == k
    return (truth_depth > 0) & ~ground


def dynamic_mask(truth_flow_mps: Tensor) -> Tensor:
    """[..., H, W] bool: the pixels whose truth speed (norm of [..., H, W, 3], m/s) exceeds
    :data:`MOVING_MPS`."""
    return torch.linalg.vector_norm(truth_flow_mps.float(), dim=-1) > MOVING_MPS


@dataclass
class FlowAccumulator:
    """Running sums of the scene-flow metrics (module docstring) over scored pixels."""

    pixels: int = 0
    sum_epe: float = 0.0
    acc5: int = 0
    acc10: int = 0
    outliers: int = 0
    angle_pixels: int = 0
    sum_angle: float = 0.0
    batches: int = 0
    skipped_static: int = 0

    def add(self, pred_mps: Tensor, truth_mps: Tensor, valid: Tensor) -> None:
        """Scores a batch of views: ``pred_mps`` and ``truth_mps`` [..., H, W, 3] world-frame
        velocities (m/s), ``valid`` [..., H, W] bool (:func:`flow_pixels`). A batch whose truth is
        nowhere faster than :data:`MOVING_MPS` is skipped (counted in ``skipped_static``)."""
        truth = truth_mps.double()
        speed = torch.linalg.vector_norm(truth, dim=-1)
        if not bool((speed > MOVING_MPS).any()):
            self.skipped_static += 1
            return
        self.batches += 1
        v, v_hat, s = truth[valid], pred_mps.double()[valid], speed[valid]
        e = torch.linalg.vector_norm(v_hat - v, dim=-1)
        r = e / (s + _TINY)
        self.pixels += int(e.numel())
        self.sum_epe += float(e.sum())
        self.acc5 += int(((e < 0.05) | (r < 0.05)).sum())
        self.acc10 += int(((e < 0.1) | (r < 0.1)).sum())
        self.outliers += int(((e > 0.3) | (r > 0.1)).sum())
        fast = s > ANGLE_MIN_MPS
        if bool(fast.any()):
            unit = v[fast] / s[fast, None]
            norm_hat = torch.linalg.vector_norm(v_hat[fast], dim=-1, keepdim=True)
            unit_hat = v_hat[fast] / norm_hat.clamp_min(_TINY)
            cos = (unit * unit_hat).sum(-1).clamp(-1.0, 1.0)
            self.angle_pixels += int(cos.numel())
            self.sum_angle += float(torch.arccos(cos).sum())

    def summary(self) -> dict[str, float]:
        """``epe3d_mps``, ``acc5``, ``acc10``, ``outlier``, ``angle_rad`` (NaN without a scored
        pixel) and ``flow_pixels``."""
        n = self.pixels
        nan = float("nan")
        return {
            "epe3d_mps": self.sum_epe / n if n else nan,
            "acc5": self.acc5 / n if n else nan,
            "acc10": self.acc10 / n if n else nan,
            "outlier": self.outliers / n if n else nan,
            "angle_rad": self.sum_angle / self.angle_pixels if self.angle_pixels else nan,
            "flow_pixels": float(n),
        }


def masked_psnr(pred: Tensor, truth: Tensor, mask: Tensor) -> list[float]:
    """PSNR (dB) of each image of [N, H, W, 3] RGB in [0, 1] over its ``mask`` [N, H, W] pixels (all
    three channels); images with an empty mask are left out."""
    out = []
    for p, t, m in zip(pred, truth, mask, strict=True):
        if bool(m.any()):
            mse = float(((p[m] - t[m]) ** 2).mean())
            out.append(-10.0 * float(np.log10(max(mse, 1e-10))))
    return out


def masked_mean(per_pixel: Tensor, mask: Tensor) -> list[float]:
    """Mean of each image's [N, H, W] per-pixel values (an SSIM map) over its ``mask`` pixels;
    images with an empty mask are left out."""
    return [float(v[m].mean()) for v, m in zip(per_pixel, mask, strict=True) if bool(m.any())]


def numpy_flow_errors(pred_mps: NDArray[np.floating], truth_mps: NDArray[np.floating]) -> dict[str, float]:
    """The flow metrics of (P, 3) predicted and true velocities (m/s) at P already chosen points,
    in plain numpy: the reference the tests compare :class:`FlowAccumulator` with (no motion
    threshold, no pixel selection)."""
    e = np.linalg.norm(pred_mps - truth_mps, axis=-1)
    s = np.linalg.norm(truth_mps, axis=-1)
    r = e / (s + _TINY)
    fast = s > ANGLE_MIN_MPS
    cos = np.sum(pred_mps[fast] * truth_mps[fast], axis=-1) / (
        np.maximum(np.linalg.norm(pred_mps[fast], axis=-1), _TINY) * s[fast]
    )
    return {
        "epe3d_mps": float(e.mean()),
        "acc5": float(np.mean((e < 0.05) | (r < 0.05))),
        "acc10": float(np.mean((e < 0.1) | (r < 0.1))),
        "outlier": float(np.mean((e > 0.3) | (r > 0.1))),
        "angle_rad": float(np.mean(np.arccos(np.clip(cos, -1.0, 1.0)))) if fast.any() else float("nan"),
    }
