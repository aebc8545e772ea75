"""The standard depth evaluation protocol (phigenesis.eval.depth_protocol) on hand-made maps whose
answers are worked out by hand here."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from phigenesis.eval.depth_protocol import DEPTH_METRICS, DepthAccumulator, DepthScores, depth_scores


def _approx(scores: DepthScores, **expected: float) -> None:
    for key, value in expected.items():
        assert getattr(scores, key) == pytest.approx(value, abs=1e-12), key


def test_a_prediction_twice_the_truth_scores_by_hand() -> None:
    truth = np.array([[1.0, 2.0], [4.0, 8.0]])
    s = depth_scores(2 * truth, truth)
    # |p - t| / t = 1 everywhere; (p - t)^2 / t = t: mean (1 + 2 + 4 + 8) / 4 = 3.75;
    # RMSE = sqrt((1 + 4 + 16 + 64) / 4); log 2 everywhere; ratio 2 >= 1.25^3 = 1.953125.
    _approx(s, abs_rel=1.0, sq_rel=3.75, rmse_m=math.sqrt(85 / 4), rmse_log=math.log(2))
    _approx(s, delta_1_25=0.0, delta_1_25_2=0.0, delta_1_25_3=0.0)
    assert s.pixels == 4


def test_delta_thresholds_split_the_ratios() -> None:
    truth = np.full((1, 4), 10.0)
    # Ratios 1.2, 1.5 (= t / p for p = 10 / 1.5), 1.9 and 2.0: below 1.25 one, below 1.5625 two,
    # below 1.953125 three.
    pred = np.array([[12.0, 10 / 1.5, 19.0, 20.0]])
    _approx(depth_scores(pred, truth), delta_1_25=0.25, delta_1_25_2=0.5, delta_1_25_3=0.75)


def test_truth_and_prediction_beyond_80_m_are_clamped_to_80() -> None:
    truth = np.array([[100.0, 40.0]])
    pred = np.array([[80.0, 100.0]])
    s = depth_scores(pred, truth)
    # Pixel 1: 80 vs 80, exact. Pixel 2: 80 vs 40: |d| / t = 1, d^2 / t = 40, d^2 = 1600.
    _approx(s, abs_rel=0.5, sq_rel=20.0, rmse_m=math.sqrt(800.0), rmse_log=math.sqrt(math.log(2) ** 2 / 2))
    _approx(s, delta_1_25=0.5)
    _approx(depth_scores(np.array([[120.0]]), np.array([[150.0]])), abs_rel=0.0, rmse_m=0.0, delta_1_25=1.0)


def test_a_pixel_without_prediction_counts_as_a_prediction_of_1e_3_m() -> None:
    truth = np.array([[10.0, 10.0]])
    pred = np.array([[10.0, 0.0]])
    s = depth_scores(pred, truth)
    # Pixel 2: p = 1e-3: |d| / t = 9.999 / 10, d^2 = 9.999^2, log ratio log(1e4).
    _approx(s, abs_rel=0.9999 / 2, sq_rel=9.999**2 / 10 / 2, rmse_m=math.sqrt(9.999**2 / 2))
    _approx(s, rmse_log=math.sqrt(math.log(1e4) ** 2 / 2), delta_1_25_3=0.5)
    assert s.pixels == 2
    _approx(depth_scores(np.array([np.nan]), np.array([10.0])), abs_rel=0.9999)  # NaN: no depth


def test_only_truth_pixels_in_the_mask_are_scored_and_none_give_nan() -> None:
    truth = np.array([[0.0, 5.0], [10.0, 20.0]], np.float32)
    pred = np.array([[3.0, 5.0], [20.0, 20.0]], np.float16)
    _approx(depth_scores(pred, truth), abs_rel=1 / 3, delta_1_25=2 / 3)  # the truth-0 pixel is left out
    mask = np.array([[True, False], [True, False]])
    s = depth_scores(pred, truth, mask)
    _approx(s, abs_rel=1.0, rmse_m=10.0)
    assert s.pixels == 1
    empty = depth_scores(pred, truth, np.array([[True, False], [False, False]]))
    assert empty.pixels == 0 and all(math.isnan(getattr(empty, k)) for k in DEPTH_METRICS)
    with pytest.raises(ValueError, match="boolean"):
        depth_scores(pred, truth, mask.astype(np.uint8))


def test_a_stack_is_pooled_over_its_pixels() -> None:
    truth = np.array([[[1.0, 1.0]], [[2.0, 2.0]]])
    pred = np.array([[[2.0, 1.0]], [[2.0, 2.0]]])
    _approx(depth_scores(pred, truth), abs_rel=0.25, rmse_m=0.5)


def test_per_image_mean_and_pooled_differ_on_images_of_different_sizes() -> None:
    # Image A: one pixel, AbsRel 1 (2 vs 1). Image B: 3 x 1 pixels, all exact (AbsRel 0).
    acc = DepthAccumulator()
    acc.add(np.array([[2.0]]), np.array([[1.0]]))
    acc.add(np.full((3, 1), 4.0), np.full((3, 1), 4.0))
    mean, pooled = acc.image_mean()["all"], acc.pooled()["all"]
    # Per image: (1 + 0) / 2; pooled: (1 + 0 + 0 + 0) / 4. RMSE per image (1 + 0) / 2, pooled sqrt(1 / 4).
    _approx(mean, abs_rel=0.5, rmse_m=0.5, delta_1_25=0.5)
    _approx(pooled, abs_rel=0.25, rmse_m=0.5, delta_1_25=0.75)
    assert mean.pixels == pooled.pixels == 4 and acc.images() == 2


def test_subsets_average_over_their_images_and_are_nan_when_empty() -> None:
    truth = np.array([[[10.0, 10.0]], [[10.0, 10.0]]])
    pred = np.array([[[20.0, 10.0]], [[10.0, 15.0]]])
    lidar = np.array([[[True, False]], [[False, False]]])
    acc = DepthAccumulator(("lidar", "no_lidar", "unused"))
    acc.add(pred, truth, {"lidar": lidar, "no_lidar": ~lidar})
    acc.add(np.array([[10.0]]), np.array([[10.0]]), {"lidar": None})  # no subsets for this image
    mean, pooled = acc.image_mean(), acc.pooled()
    # all: per image 0.5, 0.25, 0 -> 0.25; pooled (1 + 0 + 0 + 0.5 + 0) / 5 = 0.3.
    _approx(mean["all"], abs_rel=0.25)
    _approx(pooled["all"], abs_rel=0.3)
    # lidar: image 1 only (one pixel, AbsRel 1); no_lidar: image 1 (0) and image 2 (0, 0.5: 0.25).
    _approx(mean["lidar"], abs_rel=1.0)
    assert acc.images("lidar") == 1 and acc.images("no_lidar") == 2
    _approx(mean["no_lidar"], abs_rel=0.125)
    _approx(pooled["no_lidar"], abs_rel=0.5 / 3)
    assert math.isnan(mean["unused"].abs_rel) and math.isnan(pooled["unused"].rmse_m)
    assert mean["unused"].pixels == 0
    with pytest.raises(ValueError, match="unknown subsets"):
        acc.add(pred, truth, {"other": lidar})


def test_pooled_equals_the_one_image_function_on_everything() -> None:
    rng = np.random.default_rng(0)
    truth = np.where(rng.random((3, 6, 7)) < 0.3, 0.0, rng.uniform(0.5, 100, (3, 6, 7)))
    pred = np.where(rng.random((3, 6, 7)) < 0.1, 0.0, truth * rng.uniform(0.5, 2.0, (3, 6, 7)))
    acc = DepthAccumulator()
    acc.add(pred, truth)
    pooled, whole = acc.pooled()["all"], depth_scores(pred, truth)
    for key in DEPTH_METRICS:
        assert getattr(pooled, key) == pytest.approx(getattr(whole, key), rel=1e-12)
    per_image = [depth_scores(pred[i], truth[i]) for i in range(3)]
    for key in DEPTH_METRICS:
        assert getattr(acc.image_mean()["all"], key) == pytest.approx(
            np.mean([getattr(s, key) for s in per_image]), rel=1e-12
        )


@given(
    scale=st.floats(0.05, 2.5),
    truth=st.lists(st.floats(0.5, 30.0), min_size=1, max_size=12),
)
def test_scaling_the_truth_gives_abs_rel_of_the_scale_and_delta_by_the_ratio(
    scale: float, truth: list[float]
) -> None:
    assume(abs(scale - 1.25) > 1e-9 and abs(scale - 1 / 1.25) > 1e-9)
    t = np.array(truth)
    s = depth_scores(scale * t, t)
    assert abs(s.abs_rel - abs(scale - 1)) < 1e-9
    assert abs(s.rmse_log - abs(math.log(scale))) < 1e-9
    assert s.delta_1_25 == (1.0 if 1 / 1.25 < scale < 1.25 else 0.0)
