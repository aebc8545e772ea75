"""Waymo v2 column conversion, Arrow to numpy, for the reader (:mod:`.v2`): numbers with nulls
filled, camera and LiDAR names stored as codes or strings, transforms as float32 or float64
(fixed-size or plain lists) into (N, 4, 4) float64, range images into their declared shapes. A
value the reader cannot use raises :class:`_ColumnError` naming the column and the row.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import NDArray

from phigenesis.data.sources.waymo.raw import (
    WaymoFormatError,
)
from phigenesis.data.sources.waymo.v2_schema import (
    _CAM,
    _LASER,
    _OBJ,
    _c,
)


class _ColumnError(ValueError):
    """A column value the reader cannot use; the message names the column and the row (and its
    key: camera, LiDAR or object). The segment prefixes the file and frame."""


_KEY_COLUMNS = ((_CAM, "camera"), (_LASER, "LiDAR"), (_OBJ, "object"))
_CAST_ERRORS = (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError)


def _row_name(table: pa.Table, row: int) -> str:
    """``row R (camera FRONT)`` for row ``row`` of a frame's rows, with its key where it has one."""
    keys = [
        f"{label} {table.column(col)[row].as_py()!r}"
        for col, label in _KEY_COLUMNS
        if col in table.column_names and row < table.num_rows
    ]
    return f"row {row}" + (f" ({', '.join(keys)})" if keys else "")


def _column(table: pa.Table, name: str) -> pa.Array:
    chunked = table.column(name)
    # combine_chunks copies even a single chunk (a frame's range images: ~20 MB).
    col = chunked.chunk(0) if chunked.num_chunks == 1 else chunked.combine_chunks()
    return pc.dictionary_decode(col) if pa.types.is_dictionary(col.type) else col


def _cast(table: pa.Table, name: str, type_: pa.DataType) -> pa.Array:
    """Column ``name`` cast to ``type_``; raises :class:`_ColumnError` naming the first row whose
    value does not convert (a string such as 'abc' in a number column)."""
    col = _column(table, name)
    try:
        return pc.cast(col, type_)
    except _CAST_ERRORS as e:
        for row in range(len(col)):
            try:
                pc.cast(col.slice(row, 1), type_)
            except _CAST_ERRORS:
                raise _ColumnError(
                    f"column {name} {_row_name(table, row)} holds {col[row].as_py()!r}, not a {type_} ({e})"
                ) from None
        raise _ColumnError(f"column {name} of type {col.type} does not convert to {type_} ({e})") from None


def _numbers(table: pa.Table, name: str, type_: pa.DataType, fill: float) -> NDArray[Any]:
    """Column ``name`` cast to ``type_`` as numpy (nulls -> ``fill``). A column already of that
    type without nulls is taken as it is (a frame reads some 30 such columns, and each compute
    call costs tens of microseconds of Python)."""
    col = _column(table, name)
    if col.type != type_:
        col = _cast(table, name, type_)
    if col.null_count:
        col = pc.fill_null(col, fill)
    return col.to_numpy(zero_copy_only=False)


def _floats(table: pa.Table, name: str, fill: float = np.nan) -> NDArray[np.float64]:
    """Column ``name`` as float64 (nulls -> ``fill``)."""
    return _numbers(table, name, pa.float64(), fill)


def _ints(table: pa.Table, name: str, fill: int = -1) -> NDArray[np.int64]:
    """Column ``name`` as int64 (nulls -> ``fill``); ``fill`` for every row when it is absent."""
    if name not in table.column_names:
        return np.full(table.num_rows, fill, np.int64)
    return _numbers(table, name, pa.int64(), fill)


def _name_codes(table: pa.Table, name: str, codes: dict[str, int], where: Path) -> NDArray[np.int32]:
    """Camera / LiDAR name column as int32 codes, whether stored as integers or as names."""
    col = _column(table, name)
    if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
        values = col.to_pylist()
        unknown = sorted({v for v in values if v not in codes}, key=str)
        if unknown:
            raise WaymoFormatError(f"{where}: column {name} has unknown names {unknown}")
        return np.array([codes[v] for v in values], np.int32)
    if col.null_count:
        raise WaymoFormatError(f"{where}: column {name} has null entries")
    return _cast(table, name, pa.int32()).to_numpy(zero_copy_only=False)


def _is_list(type_: pa.DataType) -> bool:
    return pa.types.is_list(type_) or pa.types.is_large_list(type_) or pa.types.is_fixed_size_list(type_)


def _list_column(table: pa.Table, name: str, value_type: pa.DataType | None = None) -> pa.Array:
    """List column ``name`` as a plain list array (of ``value_type`` if given)."""
    col = _column(table, name)
    if not _is_list(col.type):
        raise _ColumnError(f"column {name} is {col.type}, not a list column")
    target = pa.list_(col.type.value_type if value_type is None else value_type)
    if col.type == target:
        return col
    try:
        return col.cast(target)
    except _CAST_ERRORS as e:
        for row in range(len(col)):
            try:
                col.slice(row, 1).cast(target)
            except _CAST_ERRORS:
                raise _ColumnError(
                    f"column {name} {_row_name(table, row)} holds {col[row].as_py()!r}, not a {target} ({e})"
                ) from None
        raise _ColumnError(f"column {name} does not convert to {target} ({e})") from None


def _list_values(
    table: pa.Table, name: str, value_type: pa.DataType | None = None
) -> list[NDArray[Any] | None]:
    """Each row of list column ``name`` as a 1-D array (None for null rows)."""
    col = _list_column(table, name, value_type)
    # The offsets and the child array (zero-copy views; the offsets index the whole child, which
    # a sliced column shares with its neighbours) instead of compute calls, which cost tens of
    # microseconds of Python each.
    offsets = col.offsets.to_numpy(zero_copy_only=False).tolist()
    flat = col.values.to_numpy(zero_copy_only=False)
    valid = col.is_valid().to_numpy(zero_copy_only=False).tolist() if col.null_count else [True] * len(col)
    return [flat[lo:hi] if ok else None for lo, hi, ok in zip(offsets[:-1], offsets[1:], valid, strict=True)]


def _transforms(table: pa.Table, name: str, where: Path) -> NDArray[np.float64]:
    """(N, 4, 4) float64 from a column of 16 row-major values (fixed-size or plain list)."""
    col = _list_column(table, name, pa.float64())
    if col.null_count:
        raise WaymoFormatError(f"{where}: column {name} has null transforms")
    lengths = pc.list_value_length(col).to_numpy(zero_copy_only=False)
    bad = np.flatnonzero(lengths != 16)
    if len(bad):
        raise WaymoFormatError(
            f"{where}: column {name} {_row_name(table, int(bad[0]))} holds {int(lengths[bad[0]])} values, "
            "a transform needs 16"
        )
    flat = pc.list_flatten(col).to_numpy(zero_copy_only=False).astype(np.float64)
    return flat.reshape(len(col), 4, 4)


def _range_image(
    values: NDArray[Any] | None, shape_values: NDArray[Any] | None, channels: int, what: Callable[[], str]
) -> NDArray[np.float32] | None:
    """One row's range image as (H, W, channels) float32 (None if null or empty); raises
    naming ``what()`` if its shape is not three positive dims holding its values."""
    if values is None or shape_values is None or values.size == 0:
        return None
    shape = tuple(int(x) for x in shape_values)
    if len(shape) != 3 or shape[2] != channels or min(shape) <= 0 or math.prod(shape) != values.size:
        raise WaymoFormatError(f"{what()} has {values.size} values for shape {list(shape)}")
    return values.astype(np.float32, copy=False).reshape(shape)


def _range_images(
    table: pa.Table, tag: str, ret: int, channels: int, where: Path
) -> list[NDArray[np.float32] | WaymoFormatError | None]:
    """Range images ``range_image_return{ret}`` as (H, W, channels) float32 (None if null/absent),
    or the error of a row whose shape does not hold its values."""
    values_col, shape_col = (
        _c(tag, f"range_image_return{ret}.values"),
        _c(tag, f"range_image_return{ret}.shape"),
    )
    if values_col not in table.column_names:
        return [None] * table.num_rows
    values = _list_values(table, values_col, pa.float32())
    shapes = _list_values(table, shape_col, pa.int64())
    out: list[NDArray[np.float32] | WaymoFormatError | None] = []
    for row, (v, shape) in enumerate(zip(values, shapes, strict=True)):
        try:
            what = lambda r=row: f"{where}: {values_col} {_row_name(table, r)}"  # noqa: E731 (named on error only)
            out.append(_range_image(v, shape, channels, what))
        except WaymoFormatError as e:
            out.append(e)
    return out
