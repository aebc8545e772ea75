"""Depth as a distribution: log-spaced depth bins with a residual within the bin.

Stage 1's depth head classifies each pixel's depth (DrivingRecon's head: bins between the near and
far bounds, cross-entropy against the LiDAR's bin, an expected depth refined by a residual), so
that every pixel also carries the entropy of its depth distribution, one of the uncertainty maps
Stage 2's Stereo Forcing takes.

Bins are uniform in log depth: ``K`` bins between ``near_m`` and ``far_m``, bin ``k`` spanning
``[near (far/near)^(k/K), near (far/near)^((k+1)/K))``, of width ``step = log(far/near) / K`` in log
depth and centred at ``log c_k = log near + (k + 1/2) step`` (a relative resolution that is the
same at 2 m and at 80 m, as the depth loss and the protocol's AbsRel are relative).

A pixel's depth from its bin probabilities ``p`` and residual ``r`` (in bins, in [-1/2, 1/2])::

    log z = sum_k p_k log c_k + r * step

the expected log depth (a geometric mean: the expectation in log depth, where the bins are
uniform) moved by the residual. One-hot probabilities at the bin holding ``z`` with the residual
:meth:`DepthBins.encode` gives reproduce ``z`` exactly (to rounding).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

#: The residual's bound, in bins: it moves the expected depth by at most half a bin either way.
RESIDUAL_BOUND = 0.5


@dataclass(frozen=True)
class DepthBins:
    """``count`` log-spaced depth bins between ``near_m`` and ``far_m`` (camera z, metres)."""

    near_m: float
    far_m: float
    count: int

    def __post_init__(self) -> None:
        if not (0 < self.near_m < self.far_m and math.isfinite(self.far_m)):
            raise ValueError(f"DepthBins: need 0 < near_m < far_m < inf, got {self.near_m}, {self.far_m}")
        if self.count < 2:
            raise ValueError(f"DepthBins: need at least 2 bins, got {self.count}")

    @property
    def step(self) -> float:
        """Width of one bin in log depth (natural log)."""
        return math.log(self.far_m / self.near_m) / self.count

    def log_centres(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> Tensor:
        """(K,) log of every bin's centre depth."""
        k = torch.arange(self.count, dtype=torch.float64, device=device)
        return (math.log(self.near_m) + (k + 0.5) * self.step).to(dtype)

    def index(self, depth_m: Tensor) -> Tensor:
        """int64 bin of each depth (same shape; depths outside [near, far] go to the end bins)."""
        z = depth_m.double().clamp(self.near_m, self.far_m)
        k = torch.floor((torch.log(z) - math.log(self.near_m)) / self.step)
        return k.clamp(0, self.count - 1).long()

    def encode(self, depth_m: Tensor) -> tuple[Tensor, Tensor]:
        """(bin index int64, residual in bins) of each depth, clamped to [near, far]: the one-hot
        target that :meth:`decode` turns back into the depth."""
        k = self.index(depth_m)
        log_z = torch.log(depth_m.double().clamp(self.near_m, self.far_m))
        centre = math.log(self.near_m) + (k.double() + 0.5) * self.step
        residual = ((log_z - centre) / self.step).clamp(-RESIDUAL_BOUND, RESIDUAL_BOUND)
        return k, residual.to(depth_m.dtype if depth_m.is_floating_point() else torch.float32)

    def expected_log_depth(self, probs: Tensor) -> Tensor:
        """(...) ``sum_k p_k log c_k`` of (..., K) bin probabilities."""
        return probs @ self.log_centres(probs.dtype, probs.device)

    def decode(self, probs: Tensor, residual: Tensor) -> Tensor:
        """(...) depth in metres from (..., K) bin probabilities and (...) residuals (bins),
        clamped to [near, far]."""
        log_z = self.expected_log_depth(probs) + residual * self.step
        return torch.exp(log_z).clamp(self.near_m, self.far_m)

    def decode_logits(self, logits: Tensor, residual_raw: Tensor) -> tuple[Tensor, Tensor]:
        """(depth m, entropy nats) of (..., K) logits and (...) unbounded residual outputs (mapped
        to [-1/2, 1/2] bins by ``tanh``)."""
        log_p = torch.log_softmax(logits, dim=-1)
        probs = log_p.exp()
        residual = RESIDUAL_BOUND * torch.tanh(residual_raw)
        return self.decode(probs, residual), entropy_from_log_probs(log_p)


def entropy_from_log_probs(log_probs: Tensor) -> Tensor:
    """(...) entropy in nats ``-sum p log p`` of (..., K) log probabilities: 0 for a one-hot
    distribution, ``log K`` for a uniform one (terms with p = 0 count 0)."""
    probs = log_probs.exp()
    return -(probs * torch.where(probs > 0, log_probs, torch.zeros_like(log_probs))).sum(-1)


def entropy(probs: Tensor) -> Tensor:
    """(...) entropy in nats of (..., K) probabilities (each row sums to 1)."""
    return entropy_from_log_probs(torch.log(probs.clamp(min=0)))
