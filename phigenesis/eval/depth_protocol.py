"""The standard depth evaluation protocol of surround-view depth (SurroundDepth, DiST-4D, Omni-Scene).

Per image, on the pixels whose truth depth is > 0 (and in an optional mask):

1. prediction and truth are clamped to ``[min_depth_m, max_depth_m]`` (1e-3 and 80 m): a truth of
   100 m is scored as 80 m, and a pixel the prediction has NO depth for (0, negative or NaN) is
   scored as a prediction of ``min_depth_m``, i.e. as a very wrong one (AbsRel about 1, ratio
   ``truth / 1e-3``). Every truth pixel is scored, not only those the prediction covers;
2. both are z-depths (along the camera's +z), metres;
3. with ``p`` the prediction and ``t`` the truth:

   - ``abs_rel`` = mean |p - t| / t;
   - ``sq_rel`` = mean (p - t)^2 / t (metres);
   - ``rmse_m`` = sqrt(mean (p - t)^2) (metres);
   - ``rmse_log`` = sqrt(mean (log p - log t)^2);
   - ``delta_1_25``, ``delta_1_25_2``, ``delta_1_25_3``: share of pixels with
     max(p / t, t / p) < 1.25, 1.25^2, 1.25^3.

SurroundDepth averages the per-image values over the images (the field's number);
:class:`DepthAccumulator` gives that and the values pooled over all pixels of all images. Images
without a pixel in a subset are left out of that subset's mean; a subset with no pixel at all has
NaN metrics.

Example::

    acc = DepthAccumulator(subsets=("lidar",))
    acc.add(pred, truth, {"lidar": lidar_mask})  # [N, H, W] or [H, W] each
    acc.image_mean()["all"].abs_rel, acc.pooled()["lidar"].rmse_m
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from phigenesis.models.metrics import truth_pixels

#: Depth range of the protocol (metres): prediction and truth are clamped into it.
MIN_DEPTH_M = 1e-3
MAX_DEPTH_M = 80.0
#: The delta thresholds 1.25, 1.25^2, 1.25^3 (on max(p / t, t / p), strictly below).
DELTA_THRESHOLDS = (1.25, 1.25**2, 1.25**3)
#: The subset every image scores: all its truth pixels (in the image's own mask, if any).
ALL = "all"


@dataclass(frozen=True)
class DepthScores:
    """The protocol's metrics over a set of pixels (see the module docstring); NaN when ``pixels`` is 0.

    Attributes:
        abs_rel: mean |p - t| / t.
        sq_rel: mean (p - t)^2 / t, metres.
        rmse_m: sqrt(mean (p - t)^2), metres.
        rmse_log: sqrt(mean (log p - log t)^2), natural log.
        delta_1_25, delta_1_25_2, delta_1_25_3: share of pixels with max(p / t, t / p) below 1.25,
            1.25^2 and 1.25^3, in [0, 1].
        pixels: truth pixels scored (for a per-image mean: summed over the images averaged).
    """

    abs_rel: float
    sq_rel: float
    rmse_m: float
    rmse_log: float
    delta_1_25: float
    delta_1_25_2: float
    delta_1_25_3: float
    pixels: int

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


#: The metric names, in table order (the float fields of :class:`DepthScores`).
DEPTH_METRICS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(DepthScores) if f.name != "pixels")
#: Sums kept per image and subset: |d| / t, d^2 / t, d^2, (log p - log t)^2, the 3 delta counts, pixels.
_SUMS = 8


def _pixel_sums(
    pred_m: ArrayLike,
    truth_m: ArrayLike,
    mask: ArrayLike | None,
    min_depth_m: float,
    max_depth_m: float,
) -> NDArray[np.float64]:
    """(_SUMS,) sums of the protocol over the truth pixels of ``pred_m`` / ``truth_m`` in ``mask``."""
    pred, truth, valid = truth_pixels(pred_m, truth_m, mask)
    p = np.clip(np.nan_to_num(pred[valid], nan=0.0), min_depth_m, max_depth_m)
    t = np.clip(truth[valid], min_depth_m, max_depth_m)
    d = p - t
    log_d = np.log(p) - np.log(t)
    ratio = np.maximum(p / t, t / p)
    out = np.empty(_SUMS)
    out[0] = np.sum(np.abs(d) / t)
    out[1] = np.sum(d**2 / t)
    out[2] = np.sum(d**2)
    out[3] = np.sum(log_d**2)
    out[4:7] = [np.count_nonzero(ratio < thr) for thr in DELTA_THRESHOLDS]
    out[7] = p.size
    return out


def _scores(sums: NDArray[np.float64]) -> DepthScores:
    """The metrics of pooled sums (:func:`_pixel_sums`)."""
    n = int(sums[7])
    if n == 0:
        return DepthScores(*([float("nan")] * len(DEPTH_METRICS)), pixels=0)
    mean = sums[:7] / n
    return DepthScores(
        abs_rel=float(mean[0]),
        sq_rel=float(mean[1]),
        rmse_m=float(np.sqrt(mean[2])),
        rmse_log=float(np.sqrt(mean[3])),
        delta_1_25=float(mean[4]),
        delta_1_25_2=float(mean[5]),
        delta_1_25_3=float(mean[6]),
        pixels=n,
    )


def depth_scores(
    pred_m: ArrayLike,
    truth_m: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    min_depth_m: float = MIN_DEPTH_M,
    max_depth_m: float = MAX_DEPTH_M,
) -> DepthScores:
    """The protocol's metrics of a predicted z-depth map against the truth (see the module docstring).

    Args:
        pred_m: predicted z-depth, metres, any float dtype; 0 (or negative, or NaN) = no depth,
            scored as ``min_depth_m``.
        truth_m: truth z-depth, metres, same shape; pixels with truth > 0 are scored.
        mask: optional boolean map of the same shape restricting the scored pixels.
        min_depth_m, max_depth_m: the clamp range of prediction and truth.

    Shapes: (H, W) or any stack (N, H, W): a stack is pooled over all its pixels (use
    :class:`DepthAccumulator` for the per-image mean). Returns NaN metrics when no pixel is scored.
    """
    return _scores(_pixel_sums(pred_m, truth_m, mask, min_depth_m, max_depth_m))


class DepthAccumulator:
    """Scores images one after another under the protocol, over all their truth pixels (subset
    :data:`ALL`) and over named subsets of them.

    ``image_mean()`` is the field's number (metrics per image, averaged over the images with a
    pixel in the subset); ``pooled()`` the metrics over all pixels of all images at once.
    """

    def __init__(
        self,
        subsets: Sequence[str] = (),
        *,
        min_depth_m: float = MIN_DEPTH_M,
        max_depth_m: float = MAX_DEPTH_M,
    ):
        if ALL in subsets or len(set(subsets)) != len(subsets):
            raise ValueError(f"subsets {list(subsets)} must be distinct and other than {ALL!r}")
        self.subsets: tuple[str, ...] = (ALL, *subsets)
        self.min_depth_m = min_depth_m
        self.max_depth_m = max_depth_m
        self._sums: dict[str, list[NDArray[np.float64]]] = {s: [] for s in self.subsets}

    def add(
        self,
        pred_m: ArrayLike,
        truth_m: ArrayLike,
        masks: Mapping[str, ArrayLike | None] | None = None,
    ) -> None:
        """Adds images: ``pred_m`` and ``truth_m`` of shape (H, W) (one image) or (N, H, W) (N images),
        metres; ``masks``: per subset a boolean map of that shape selecting its pixels among the
        truth pixels, or None (or absent) when the images have no such subset (they are then left
        out of it). ``masks[ALL]``, when given, restricts the all-pixels subset too."""
        masks = dict(masks or {})
        unknown = set(masks) - set(self.subsets)
        if unknown:
            raise ValueError(f"unknown subsets {sorted(unknown)}; declared: {list(self.subsets)}")
        pred = np.asarray(pred_m)
        truth = np.asarray(truth_m)
        if truth.ndim not in (2, 3) or pred.shape != truth.shape:
            raise ValueError(
                f"expected (H, W) or (N, H, W) maps of one shape, got {pred.shape}, {truth.shape}"
            )
        stack = truth.ndim == 3
        for name in self.subsets:
            mask = masks.get(name)
            if name != ALL and mask is None:
                continue
            for i in range(truth.shape[0] if stack else 1):
                m = None if mask is None else (np.asarray(mask)[i] if stack else mask)
                p, t = (pred[i], truth[i]) if stack else (pred, truth)
                sums = _pixel_sums(p, t, m, self.min_depth_m, self.max_depth_m)
                if sums[7] > 0:
                    self._sums[name].append(sums)

    def images(self, subset: str = ALL) -> int:
        """How many images have a pixel in ``subset``."""
        return len(self._sums[subset])

    def image_mean(self) -> dict[str, DepthScores]:
        """Per subset: each metric computed per image, averaged over the images with a pixel in it
        (``pixels``: their pixels summed); NaN metrics for a subset without any."""
        out = {}
        for name, per_image in self._sums.items():
            if not per_image:
                out[name] = _scores(np.zeros(_SUMS))
                continue
            scores = [_scores(s) for s in per_image]
            means = {k: float(np.mean([getattr(s, k) for s in scores])) for k in DEPTH_METRICS}
            out[name] = DepthScores(**means, pixels=sum(s.pixels for s in scores))
        return out

    def pooled(self) -> dict[str, DepthScores]:
        """Per subset: the metrics over all its pixels of all images at once (NaN without any)."""
        return {name: _scores(np.sum(s, axis=0) if s else np.zeros(_SUMS)) for name, s in self._sums.items()}
