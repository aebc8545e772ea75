"""Depth bins of Stage 1's classification head: exact encode/decode, entropy's bounds, and the head
inside the adapter (initial depth, entropy output, the regression head kept for old checkpoints)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis.models.depth_bins import RESIDUAL_BOUND, DepthBins, entropy, entropy_from_log_probs

BINS = DepthBins(0.5, 120.0, 64)


@settings(max_examples=200, deadline=None)
@given(st.floats(0.5, 120.0), st.sampled_from([2, 7, 64, 200]))
def test_one_hot_bin_and_residual_reproduce_a_known_depth(depth_m, count):
    bins = DepthBins(0.5, 120.0, count)
    z = torch.tensor([depth_m], dtype=torch.float64)
    k, residual = bins.encode(z)
    assert 0 <= int(k) < count and abs(float(residual)) <= RESIDUAL_BOUND
    probs = torch.nn.functional.one_hot(k, count).double()
    back = bins.decode(probs, residual)
    np.testing.assert_allclose(back.numpy(), [depth_m], rtol=1e-12)


def test_bin_edges_are_log_spaced_and_depths_outside_go_to_the_end_bins():
    bins = DepthBins(1.0, 100.0, 2)  # edges 1, 10, 100
    z = torch.tensor([0.1, 1.0, 9.99, 10.0, 99.0, 100.0, 1e6])
    assert bins.index(z).tolist() == [0, 0, 0, 1, 1, 1, 1]
    np.testing.assert_allclose(bins.log_centres(torch.float64).exp().numpy(), [10**0.5, 10**1.5], rtol=1e-12)
    # Residual +1/2 bin from the first centre is the first edge between bins: 10 m.
    np.testing.assert_allclose(
        bins.decode(torch.tensor([[1.0, 0.0]]), torch.tensor([0.5])).numpy(), [10.0], rtol=1e-6
    )


def test_entropy_of_one_hot_is_zero_and_of_uniform_is_log_k():
    for k in (2, 64, 200):
        one_hot = torch.zeros(3, k)
        one_hot[:, 1] = 1.0
        assert entropy(one_hot).abs().max().item() == 0.0
        uniform = torch.full((3, k), 1.0 / k, dtype=torch.float64)
        np.testing.assert_allclose(entropy(uniform).numpy(), math.log(k), rtol=1e-12)
        np.testing.assert_allclose(
            entropy_from_log_probs(torch.log_softmax(torch.zeros(k, dtype=torch.float64), -1)).item(),
            math.log(k),
            rtol=1e-12,
        )


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-30, 30), min_size=8, max_size=8))
def test_entropy_lies_between_zero_and_log_k_and_its_gradient_is_finite(values):
    logits = torch.tensor(values, dtype=torch.float64, requires_grad=True)
    h = entropy_from_log_probs(torch.log_softmax(logits, -1))
    assert -1e-12 <= h.item() <= math.log(8) + 1e-12
    h.backward()
    assert torch.isfinite(logits.grad).all()


def test_decode_logits_at_zero_is_the_geometric_middle_with_full_entropy():
    depth, h = BINS.decode_logits(torch.zeros(4, 64), torch.zeros(4))
    np.testing.assert_allclose(depth.numpy(), math.sqrt(0.5 * 120.0), rtol=1e-5)
    np.testing.assert_allclose(h.numpy(), math.log(64), rtol=1e-6)


def test_invalid_bins_are_refused():
    for args in ((0.0, 10.0, 4), (5.0, 1.0, 4), (0.5, math.inf, 4), (0.5, 10.0, 1)):
        with pytest.raises(ValueError, match="DepthBins"):
            DepthBins(*args)
