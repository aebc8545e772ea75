"""The shared cache check finds non-finite values wherever they hide, and allows documented NaNs."""

from __future__ import annotations

import math

import pyarrow as pa

from tests.cache_checks import non_finite_in_batch, non_finite_values


def _batch(points: list[float], acceleration: list[float]) -> pa.RecordBatch:
    lidar = pa.array([{"points_ego": points}], pa.struct([("points_ego", pa.list_(pa.float32()))]))
    box = pa.struct([("acceleration_world", pa.list_(pa.float64(), 3)), ("yaw_world", pa.float64())])
    boxes = pa.array([[{"acceleration_world": acceleration, "yaw_world": None}]], pa.list_(box))
    return pa.RecordBatch.from_arrays([lidar, boxes], ["lidar", "boxes"])


def test_nested_nan_and_inf_are_found_and_documented_nan_is_allowed():
    assert non_finite_in_batch(_batch([1.0, 2.0, 3.0], [math.nan, 0.0, 0.0])) == []
    assert non_finite_in_batch(_batch([1.0, math.nan, math.inf], [0.0, 0.0, 0.0])) == [
        "lidar.points_ego: 2 non-finite"
    ]
    assert non_finite_in_batch(_batch([1.0, 2.0, 3.0], [math.inf, 0.0, 0.0])) == [
        "boxes.acceleration_world: 1 non-finite"
    ]


def test_the_session_cache_is_finite(tiny_cache):
    assert non_finite_values(tiny_cache) == []
