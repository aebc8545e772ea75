"""Metrics of predictions against known truth, shared by training (a segmenter's validation) and
evaluation (:mod:`phigenesis.eval`).

Depth metrics follow the usual definitions (Eigen et al. 2014; KITTI depth completion): errors in
metres on the pixels where both the prediction and the truth have a depth (> 0).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


def truth_pixels(
    pred_m: ArrayLike, truth_m: ArrayLike, mask: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """(prediction, truth) as float64 and the bool map of the pixels to score: truth > 0 and in
    ``mask`` (boolean, the maps' shape). Raises ValueError when the shapes or the mask disagree."""
    pred = np.asarray(pred_m, np.float64)
    truth = np.asarray(truth_m, np.float64)
    if pred.shape != truth.shape:
        raise ValueError(f"prediction {pred.shape} and truth {truth.shape} differ in shape")
    valid = truth > 0
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != truth.shape or m.dtype != np.bool_:
            raise ValueError(f"mask must be boolean of shape {truth.shape}, got {m.dtype} {m.shape}")
        valid &= m
    return pred, truth, valid


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
    pred, truth, valid = truth_pixels(pred_m, truth_m, None if mask is None else np.asarray(mask, bool))
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


# --------------------------------------------------------------------------------------------
# Semantic segmentation


def confusion_matrix(
    pred: NDArray[np.integer], truth: NDArray[np.integer], num_classes: int, ignore_id: int = 255
) -> NDArray[np.int64]:
    """(K, K + 1) int64 counts over the pixels whose truth is a class (not ``ignore_id``): rows =
    truth class, columns = predicted class, and a last column for pixels given no class (a
    prediction outside 0..K-1, e.g. 255 from a labeller that abstains). Any shapes, equal sizes."""
    pred = np.asarray(pred).reshape(-1).astype(np.int64)
    truth = np.asarray(truth).reshape(-1).astype(np.int64)
    if pred.shape != truth.shape:
        raise ValueError(f"prediction {pred.shape} and truth {truth.shape} differ in size")
    keep = (truth != ignore_id) & (truth >= 0) & (truth < num_classes)
    p = pred[keep]
    p = np.where((p >= 0) & (p < num_classes), p, num_classes)
    index = truth[keep] * (num_classes + 1) + p
    return np.bincount(index, minlength=num_classes * (num_classes + 1)).reshape(num_classes, num_classes + 1)


@dataclass(frozen=True)
class SegmentationScores:
    """Scores from a confusion matrix (:func:`confusion_matrix`).

    Attributes:
        miou: mean IoU over the classes present in the truth (NaN if none).
        iou: (K,) per-class IoU = TP / (TP + FP + FN), a pixel given no class being a false
            negative of its truth class; NaN for classes absent from the truth.
        pixel_accuracy: correct / truth pixels (pixels given no class count as wrong).
        labelled: share of truth pixels that got a class (1.0 for a segmenter).
        labelled_accuracy: correct / truth pixels that got a class (the precision of the labels given).
        truth_pixels: truth pixels counted (ignore excluded).
    """

    miou: float
    iou: tuple[float, ...]
    pixel_accuracy: float
    labelled: float
    labelled_accuracy: float
    truth_pixels: int


def segmentation_scores(confusion: NDArray[np.integer]) -> SegmentationScores:
    """IoUs and accuracies of a (K, K + 1) confusion matrix from :func:`confusion_matrix`."""
    cm = np.asarray(confusion, np.float64)
    k = cm.shape[0]
    assert cm.shape == (k, k + 1), cm.shape
    tp = np.diag(cm[:, :k])
    truth, predicted, given = cm.sum(axis=1), cm[:, :k].sum(axis=0), cm[:, :k].sum()
    total = cm.sum()
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(truth > 0, tp / (truth + predicted - tp), np.nan)
    present = truth > 0
    nan = float("nan")
    return SegmentationScores(
        miou=float(np.mean(iou[present])) if present.any() else nan,
        iou=tuple(float(v) for v in iou),
        pixel_accuracy=float(tp.sum() / total) if total else nan,
        labelled=float(given / total) if total else nan,
        labelled_accuracy=float(tp.sum() / given) if given else nan,
        truth_pixels=int(total),
    )
