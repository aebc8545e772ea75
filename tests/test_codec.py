"""The PNG map encodings: exact round trips within their quantisation, decoding into given arrays,
and clear errors for maps of the wrong kind or size."""

from __future__ import annotations

import numpy as np
import pytest

from phigenesis.data import codec


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(3)


def test_depth_round_trips_within_half_a_step_and_marks_out_of_range_unknown(rng: np.random.Generator):
    depth = rng.uniform(0.5, 250.0, size=(12, 17)).astype(np.float32)
    depth[0, 0], depth[0, 1], depth[0, 2], depth[0, 3] = 0.0, np.inf, np.nan, 300.0
    back = codec.decode_depth(codec.encode_depth(depth))
    ok = np.isfinite(depth) & (depth > 0) & (depth < codec.DEPTH_MAX_M)
    assert np.abs(back[ok] - depth[ok]).max() <= 0.5 / codec.DEPTH_SCALE + 1e-6
    assert np.all(back[0, :4] == 0.0)


def test_flow_round_trips_in_both_layouts_and_into_a_given_array(rng: np.random.Generator):
    flow = rng.uniform(-30.0, 30.0, size=(9, 11, 3)).astype(np.float32)
    data = codec.encode_flow(flow)
    hwc = codec.decode_flow(data)
    assert np.abs(hwc - flow).max() <= 0.5 / codec.FLOW_SCALE + 1e-6
    out = np.full((3, 9, 11), np.nan, np.float32)
    chw = codec.decode_flow(data, out, channels_first=True)
    assert chw is out
    assert np.array_equal(chw, hwc.transpose(2, 0, 1))


def test_decoding_into_given_arrays_equals_plain_decoding(rng: np.random.Generator):
    depth = rng.uniform(1.0, 80.0, size=(6, 7))
    sem = rng.integers(0, 19, size=(6, 7), dtype=np.uint8)
    inst = rng.integers(0, 60000, size=(6, 7), dtype=np.uint16)
    d_out, s_out, i_out = np.empty((6, 7), np.float32), np.empty((6, 7), np.uint8), np.empty((6, 7), np.int32)
    assert np.array_equal(
        codec.decode_depth(codec.encode_depth(depth), d_out), codec.decode_depth(codec.encode_depth(depth))
    )
    assert np.array_equal(codec.decode_semantic(codec.encode_semantic(sem), s_out), sem)
    assert np.array_equal(codec.decode_instance(codec.encode_instance(inst), i_out), inst.astype(np.int32))
    assert i_out.dtype == np.int32


def test_a_map_of_the_wrong_kind_or_size_is_refused():
    with pytest.raises(ValueError, match="expected a 1-channel uint16 PNG"):
        codec.decode_depth(codec.encode_semantic(np.zeros((4, 4), np.uint8)))
    with pytest.raises(ValueError, match="do not decode"):
        codec.decode_flow(b"garbage")
    with pytest.raises(ValueError):
        codec.decode_depth(codec.encode_depth(np.ones((4, 4))), np.empty((5, 4), np.float32))
