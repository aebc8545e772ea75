"""Where each column's bytes lie in an Arrow IPC record batch message, read from the message's
own metadata (its FlatBuffers header), without decoding the batch.

The shard writer indexes every row it writes (the CRC of each top-level column's byte range). It
gets the bytes of a row as the pieces the IPC writer hands it: small pieces of metadata and
padding, and the column buffers themselves. Decoding the row to find the columns would need the
pieces copied into one contiguous buffer first (8 MB a Waymo frame); the metadata lists every
buffer's offset and length in the body, which is all the index needs.

Format (Arrow columnar spec, "Encapsulated message format"): a message is ``0xFFFFFFFF``, an
int32 metadata length, the FlatBuffers ``Message`` table (padded to 8 bytes), then the body.
``Message``: ``version`` (field 0), ``header_type`` (1), ``header`` (2, a union), ``bodyLength``
(3). ``RecordBatch``: ``length`` (0), ``nodes`` (1), ``buffers`` (2, a vector of
``{offset: int64, length: int64}`` structs, in the pre-order of the schema's fields),
``compression`` (3). Anything this module does not expect (a dictionary batch, compression, a type
whose buffer count it does not know) raises :class:`LayoutUnknown`, and the caller decodes the
batch instead (:func:`phigenesis.data.cache.writer._row_entry`).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

import pyarrow as pa

CONTINUATION = 0xFFFFFFFF
_SCHEMA, _RECORD_BATCH = 1, 3  # MessageHeader union tags


class LayoutUnknown(Exception):
    """The message is not one this module reads; decode the batch instead."""


@dataclass(frozen=True)
class BatchLayout:
    """A record batch message: where its body starts (an offset into the bytes parsed), its
    length, and each buffer's ``(offset, length)`` within the body, in IPC order."""

    body_start: int
    body_length: int
    buffers: list[tuple[int, int]]


def _u8(data: bytes, pos: int) -> int:
    return data[pos]


def _u16(data: bytes, pos: int) -> int:
    return int(struct.unpack_from("<H", data, pos)[0])


def _u32(data: bytes, pos: int) -> int:
    return int(struct.unpack_from("<I", data, pos)[0])


def _field(data: bytes, table: int, field_id: int) -> int | None:
    """Position of field ``field_id`` of the FlatBuffers table at ``table``, None when absent."""
    vtable = table - int(struct.unpack_from("<i", data, table)[0])
    slot = 4 + 2 * field_id
    if slot >= _u16(data, vtable):
        return None
    offset = _u16(data, vtable + slot)
    return table + offset if offset else None


def _target(data: bytes, pos: int) -> int:
    """Where the FlatBuffers offset stored at ``pos`` points."""
    return pos + _u32(data, pos)


def record_batch_layout(read: Callable[[int, int], bytes], pos: int = 0) -> BatchLayout:
    """The layout of the first record batch message at or after ``pos``, skipping a schema
    message before it (a file's first row holds the schema). ``read(lo, hi)`` returns those bytes
    of the stream. Raises :class:`LayoutUnknown` for anything else."""
    try:
        while True:
            continuation, size = struct.unpack("<Ii", read(pos, pos + 8))
            if continuation != CONTINUATION or size <= 0:
                raise LayoutUnknown("no encapsulated message here")
            meta_start = pos + 8
            meta = read(meta_start, meta_start + size)
            if len(meta) != size:
                raise LayoutUnknown("the message's metadata runs past the bytes written")
            root = _u32(meta, 0)
            kind_pos = _field(meta, root, 1)
            kind = 0 if kind_pos is None else _u8(meta, kind_pos)
            length_pos = _field(meta, root, 3)
            body_length = 0 if length_pos is None else int(struct.unpack_from("<q", meta, length_pos)[0])
            if kind == _SCHEMA:
                pos = meta_start + size + body_length
                continue
            header_pos = _field(meta, root, 2)
            if kind != _RECORD_BATCH or header_pos is None:
                raise LayoutUnknown(f"message type {kind} is not a record batch")
            header = _target(meta, header_pos)
            if _field(meta, header, 3) is not None:
                raise LayoutUnknown("the body is compressed")
            buffers_pos = _field(meta, header, 2)
            buffers: list[tuple[int, int]] = []
            if buffers_pos is not None:
                vector = _target(meta, buffers_pos)
                count = _u32(meta, vector)
                flat = struct.unpack_from(f"<{2 * count}q", meta, vector + 4)
                buffers = list(zip(flat[0::2], flat[1::2], strict=True))
            return BatchLayout(meta_start + size, body_length, buffers)
    except (struct.error, IndexError) as e:
        raise LayoutUnknown(f"unreadable metadata ({e})") from None


_VARIABLE_WIDTH = (pa.types.is_binary, pa.types.is_string, pa.types.is_large_binary, pa.types.is_large_string)
_FIXED_WIDTH = (
    pa.types.is_boolean,
    pa.types.is_integer,
    pa.types.is_floating,
    pa.types.is_fixed_size_binary,
    pa.types.is_temporal,
    pa.types.is_decimal,
)


def _buffer_count(t: pa.DataType) -> int:
    """How many IPC buffers an array of type ``t`` has, children included."""
    if pa.types.is_struct(t):
        return 1 + sum(_buffer_count(t.field(i).type) for i in range(t.num_fields))
    if pa.types.is_list(t) or pa.types.is_large_list(t):
        return 2 + _buffer_count(t.value_type)
    if pa.types.is_fixed_size_list(t):
        return 1 + _buffer_count(t.value_type)
    if any(is_kind(t) for is_kind in _VARIABLE_WIDTH):
        return 3  # validity, offsets, data
    if any(is_kind(t) for is_kind in _FIXED_WIDTH):
        return 2  # validity, values
    raise LayoutUnknown(f"no buffer count for type {t}")


def column_buffer_counts(schema: pa.Schema) -> list[int] | None:
    """The IPC buffer count of each top-level column of ``schema``, or None where a type is one
    :func:`_buffer_count` does not know (then rows are decoded to be indexed)."""
    try:
        return [_buffer_count(f.type) for f in schema]
    except LayoutUnknown:
        return None


def column_body_ranges(layout: BatchLayout, counts: list[int]) -> list[tuple[int, int]]:
    """Each top-level column's byte range ``[lo, hi)`` within the body: the span of its non-empty
    buffers, ``(0, 0)`` for a column without data (as :func:`phigenesis.data.shards.column_range`
    finds them in a decoded batch)."""
    if sum(counts) != len(layout.buffers):
        raise LayoutUnknown(f"{len(layout.buffers)} buffers for a schema of {sum(counts)}")
    out, k = [], 0
    for count in counts:
        spans = [(o, o + n) for o, n in layout.buffers[k : k + count] if n > 0]
        k += count
        if any(lo < 0 or hi > layout.body_length for lo, hi in spans):
            raise LayoutUnknown("a buffer lies outside the body")
        out.append((min(lo for lo, _ in spans), max(hi for _, hi in spans)) if spans else (0, 0))
    return out
