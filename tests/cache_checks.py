"""Checks on whole caches that several test modules share."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from phigenesis.data.shards import Manifest

#: Float fields whose NaN means "unknown" by the schema's own documentation; Inf is never allowed.
NAN_MEANS_UNKNOWN = frozenset(
    {
        "boxes.acceleration_world",
        "cameras.boxes.acceleration_world",
        "lidar_range_image.beam_inclination_rad",
        "lidar_range_image.column_origin_ego",
    }
)


def _float_leaves(array: pa.Array, path: str):
    """(path, float values) of every floating-point leaf under ``array`` (lists and structs walked)."""
    t = array.type
    if pa.types.is_floating(t):
        yield path, array
    elif pa.types.is_struct(t):
        for i in range(t.num_fields):
            child = pc.struct_field(array, [i]) if len(array) else array.field(i)
            yield from _float_leaves(child, f"{path}.{t.field(i).name}")
    elif pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t):
        yield from _float_leaves(pc.list_flatten(array), path)


def non_finite_in_batch(batch: pa.RecordBatch) -> list[str]:
    """``field: count`` for every field of ``batch`` holding a non-finite float where the schema
    does not document NaN as "unknown" (and every Inf anywhere)."""
    problems = []
    for name in batch.schema.names:
        for path, values in _float_leaves(batch.column(name), name):
            arr = np.asarray(values.drop_null().to_numpy(zero_copy_only=False), np.float64)
            bad = np.isinf(arr) if path in NAN_MEANS_UNKNOWN else ~np.isfinite(arr)
            if bad.any():
                problems.append(f"{path}: {int(bad.sum())} non-finite")
    return problems


def non_finite_values(cache_dir: str | Path) -> list[str]:
    """:func:`non_finite_in_batch` of every row of every complete shard, as ``shard row field``;
    empty for a clean cache."""
    cache_dir = Path(cache_dir)
    problems = []
    for info in Manifest.load(cache_dir).complete_shards():
        with pa.memory_map(str(cache_dir / info.path)) as mm:
            reader = pa.ipc.open_file(mm)
            for row in range(reader.num_record_batches):
                problems += [f"{info.path} row {row} {p}" for p in non_finite_in_batch(reader.get_batch(row))]
    return problems
