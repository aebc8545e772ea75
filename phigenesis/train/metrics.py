"""Evaluation metrics against known truth.

Depth metrics follow the usual definitions (Eigen et al. 2014; KITTI depth completion): errors in
metres on the pixels where both the prediction and the truth have a depth (> 0).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class DepthErrors:
    """Depth errors over a set of pixels.

    Attributes:
        pixels: truth pixels considered (truth > 0 and in the mask).
        covered: of those, how many the prediction has a depth for.
        coverage: covered / pixels (NaN when there are no pixels).
        rmse_m, mae_m: root-mean-square and mean absolute error, metres, on covered pixels.
        abs_rel: mean |pred - truth| / truth.
        delta_1_25: share of covered pixels with max(pred / truth, truth / pred) < 1.25.
    """

    pixels: int
    covered: int
    coverage: float
    rmse_m: float
    mae_m: float
    abs_rel: float
    delta_1_25: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def depth_errors(
    pred_m: NDArray[np.floating], truth_m: NDArray[np.floating], mask: NDArray[np.bool_] | None = None
) -> DepthErrors:
    """Errors of a depth map (0 = no prediction) against truth (0 = no surface) on ``mask``.

    All arrays share a shape (any, e.g. (H, W) or a stack of images); depths in metres.
    """
    pred = np.asarray(pred_m, np.float64)
    truth = np.asarray(truth_m, np.float64)
    if pred.shape != truth.shape:
        raise ValueError(f"prediction {pred.shape} and truth {truth.shape} differ in shape")
    valid = truth > 0
    if mask is not None:
        valid &= np.asarray(mask, bool)
    covered = valid & (pred > 0)
    n, k = int(valid.sum()), int(covered.sum())
    if k == 0:
        return DepthErrors(n, 0, 0.0 if n else float("nan"), *([float("nan")] * 4))
    p, t = pred[covered], truth[covered]
    err = p - t
    ratio = np.maximum(p / t, t / p)
    return DepthErrors(
        pixels=n,
        covered=k,
        coverage=k / n,
        rmse_m=float(np.sqrt(np.mean(err**2))),
        mae_m=float(np.mean(np.abs(err))),
        abs_rel=float(np.mean(np.abs(err) / t)),
        delta_1_25=float(np.mean(ratio < 1.25)),
    )


def see_through_share(
    sparse_m: NDArray[np.floating],
    truth_m: NDArray[np.floating],
    rel_tol: float = 0.05,
    abs_tol_m: float = 0.1,
) -> tuple[int, int]:
    """(see-through pixels, projected pixels): pixels whose projected depth lies more than
    ``rel_tol * truth + abs_tol_m`` behind the visible surface (or that show a depth where the
    truth has no surface), among the pixels with a projected depth."""
    sparse = np.asarray(sparse_m, np.float64)
    truth = np.asarray(truth_m, np.float64)
    has = sparse > 0
    behind = has & ((truth <= 0) | (sparse > truth * (1 + rel_tol) + abs_tol_m))
    return int(behind.sum()), int(has.sum())
