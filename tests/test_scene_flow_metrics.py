"""STORM's scene-flow and dynamic-region metrics (phigenesis.eval.scene_flow) on hand-made flows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import taxonomy as tx
from phigenesis.eval.scene_flow import (
    FlowAccumulator,
    dynamic_mask,
    flow_pixels,
    masked_mean,
    masked_psnr,
    numpy_flow_errors,
)


def test_hand_made_flows_give_the_metrics_worked_out_by_hand():
    # Four pixels of one view, truth a car at 10 m/s along x and static scenery.
    truth = torch.tensor([[[[10.0, 0, 0], [10.0, 0, 0], [0.0, 0, 0], [0.0, 0, 0]]]])  # [1, 1, 4, 3]
    pred = torch.tensor([[[[10.4, 0, 0], [0.0, 10.0, 0], [0.03, 0, 0], [0.0, 0, 0.2]]]])
    acc = FlowAccumulator()
    acc.add(pred, truth, torch.ones(1, 1, 4, dtype=torch.bool))
    got = acc.summary()
    errors = [0.4, math.hypot(10, 10), 0.03, 0.2]
    assert got["epe3d_mps"] == pytest.approx(sum(errors) / 4)
    # e < 0.05 or e/|v| < 0.05: pixel 1 (0.4 / 10 = 0.04) and pixel 3 (0.03 m/s).
    assert got["acc5"] == pytest.approx(0.5)
    # e < 0.1 or e/|v| < 0.1: the same two (pixel 4 is 0.2 m/s off a static surface).
    assert got["acc10"] == pytest.approx(0.5)
    # e > 0.3 or e/|v| > 0.1: all four: pixel 1 is 0.4 m/s off (though 4 % of its speed), pixel 2
    # 14 m/s, and pixels 3 and 4 are static (r is huge).
    assert got["outlier"] == pytest.approx(1.0)
    # Angles only where |v| > 0.1: 0 and 90 degrees.
    assert got["angle_rad"] == pytest.approx(math.pi / 4)
    assert got["flow_pixels"] == 4


def test_a_batch_without_motion_is_skipped_as_storm_skips_it():
    acc = FlowAccumulator()
    truth = torch.zeros(1, 2, 3, 3)
    truth[0, 0, 0] = torch.tensor([0.9, 0.0, 0.0])  # slower than 1 m/s everywhere
    acc.add(torch.ones(1, 2, 3, 3), truth, torch.ones(1, 2, 3, dtype=torch.bool))
    assert acc.skipped_static == 1 and acc.batches == 0 and math.isnan(acc.summary()["epe3d_mps"])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(2, 200))
def test_the_accumulator_equals_the_numpy_reference(seed: int, n: int):
    rng = np.random.default_rng(seed)
    truth = rng.normal(0, 3, (n, 3)) * (rng.random((n, 1)) < 0.6)
    truth[0] = [5.0, 0.0, 0.0]  # the batch moves
    pred = truth + rng.normal(0, 0.2, (n, 3)) * rng.choice([0.0, 0.1, 1.0, 20.0], (n, 1))
    acc = FlowAccumulator()
    acc.add(torch.from_numpy(pred)[None], torch.from_numpy(truth)[None], torch.ones(1, n, dtype=torch.bool))
    got, want = acc.summary(), numpy_flow_errors(pred, truth)
    for key, value in want.items():
        # arccos near 0 amplifies the rounding of the two ways of normalising: 1e-7 rad.
        tolerance = 1e-7 if key == "angle_rad" else 1e-12
        assert got[key] == pytest.approx(value, rel=1e-9, abs=tolerance, nan_ok=True), key


def test_ground_and_empty_pixels_are_not_scored_and_moving_ones_are_dynamic():
    depth = torch.tensor([[0.0, 5.0, 5.0, 5.0]])
    semantic = torch.tensor(
        [[tx.CLASS_NAMES.index("car"), tx.CLASS_NAMES.index("road"), 255, tx.CLASS_NAMES.index("car")]]
    )
    assert flow_pixels(depth, semantic).tolist() == [[False, False, True, True]]
    flow = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [0, 1.5, 0], [0, 0, -3.0]]])
    assert dynamic_mask(flow).tolist() == [[False, False, True, True]]


def test_dynamic_psnr_and_ssim_cover_only_the_masked_pixels_and_skip_empty_masks():
    truth = torch.zeros(2, 2, 2, 3)
    pred = truth.clone()
    pred[0, 0, 0] = 0.1  # the one masked pixel is off by 0.1 in every channel
    pred[0, 1, 1] = 1.0  # an unmasked pixel far off does not count
    mask = torch.zeros(2, 2, 2, dtype=torch.bool)
    mask[0, 0, 0] = True
    assert masked_psnr(pred, truth, mask) == [pytest.approx(20.0)]
    ssim_map = torch.arange(8.0).reshape(2, 2, 2)
    mask[0, 1, 0] = True
    assert masked_mean(ssim_map, mask) == [pytest.approx(1.0)]
