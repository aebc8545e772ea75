"""The shard writer: one scene's rows into Arrow IPC files of bounded size, atomically, each row
indexed (its end, body start, metadata CRC and one CRC per top-level column) as it is written.

A shard is written under a temporary name and renamed when complete; :meth:`ShardWriter.close`
returns the :class:`~phigenesis.data.cache.checksums.ShardInfo` of every complete shard for the
manifest.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Callable
from pathlib import Path

import pyarrow as pa

from phigenesis.data.cache.checksums import SHARD_CHECKSUM, ShardInfo, _crc_range, column_ranges
from phigenesis.data.cache.files import (
    DEFAULT_SHARD_MAX_BYTES,
    SHARDS_DIR,
    TMP_MARKER,
    CacheWriteError,
    fsync_dir,
    os_reason,
    safe_name,
    scene_id_problem,
)
from phigenesis.data.cache.sink import _HashingSink, _RowBytes
from phigenesis.data.ipc_layout import (
    LayoutUnknown,
    column_body_ranges,
    column_buffer_counts,
    record_batch_layout,
)
from phigenesis.errors import CacheError, PrepError

#: The bytes an Arrow IPC file starts with ("ARROW1" and two bytes of padding), before its schema.
_IPC_FILE_MAGIC = b"ARROW1\x00\x00"


#: A row's index entry ``[end, body_start, metadata_crc, crc of each column...]`` and the
#: ``(lo, hi, crc)`` of the row's byte ranges those CRCs cover.
_Indexed = tuple[list[int], list[tuple[int, int, int]]]


def _indexed(
    start: int, size: int, body_start: int, ranges: list[tuple[int, int]], crc: Callable[[int, int], int]
) -> _Indexed:
    """The row index entry of a row of ``size`` bytes at file offset ``start`` whose body starts at
    ``body_start`` and whose columns span ``ranges`` (row offsets), with ``crc(lo, hi)`` the CRC-32C
    of its bytes ``[lo, hi)``; and those spans with their CRCs."""
    spans = [(0, body_start), *ranges]
    crcs = [crc(lo, hi) for lo, hi in spans]
    return [start + size, start + body_start, *crcs], [
        (lo, hi, c) for (lo, hi), c in zip(spans, crcs, strict=True)
    ]


def _row_entry(buffer: pa.Buffer, start: int, schema: pa.Schema, where: str) -> _Indexed:
    """The row index entry ``[end, body_start, metadata_crc, crc of each column...]`` (CRC-32C) of
    one record batch, from the bytes the IPC writer wrote for it (``buffer``, starting at file
    offset ``start``; row 0 also holds the file's magic and schema).

    The batch is decoded zero-copy from ``buffer``, so each column's byte range is the span of its
    buffers' addresses, as :func:`shard_info` finds them in a finished file."""
    skip = 0
    if start == 0:
        if buffer.slice(0, len(_IPC_FILE_MAGIC)).to_pybytes() != _IPC_FILE_MAGIC:
            raise CacheError(f"{where}: the IPC writer did not start the file with Arrow's magic bytes")
        skip = len(_IPC_FILE_MAGIC)
    messages = pa.ipc.MessageReader.open_stream(buffer.slice(skip))
    message = messages.read_next_message()
    while message.type != "record batch":
        message = messages.read_next_message()
    ranges = column_ranges(pa.ipc.read_record_batch(message, schema), buffer.address)
    end = buffer.size
    body_start = min((lo for lo, hi in ranges if hi > lo), default=end)
    if not all(0 <= lo <= hi <= end for lo, hi in ranges if hi > lo):
        raise CacheError(f"{where}: a row's buffers lie outside its record batch; cannot index it")
    return _indexed(start, end, body_start, ranges, lambda lo, hi: _crc_range(SHARD_CHECKSUM, buffer, lo, hi))


def _row_entry_from_layout(row: _RowBytes, counts: list[int], where: str) -> _Indexed:
    """:func:`_row_entry` of a row from its message's metadata (:mod:`phigenesis.data.ipc_layout`),
    without joining its pieces; raises :class:`LayoutUnknown` where the metadata is not one that
    module reads."""
    pos = 0
    if row.start == 0:
        if row.read(0, len(_IPC_FILE_MAGIC)) != _IPC_FILE_MAGIC:
            raise CacheError(f"{where}: the IPC writer did not start the file with Arrow's magic bytes")
        pos = len(_IPC_FILE_MAGIC)
    layout = record_batch_layout(row.read, pos)
    body = layout.body_start
    if body + layout.body_length != row.size:
        raise LayoutUnknown(f"the message ends at {body + layout.body_length}, the row at {row.size}")
    ranges = [(body + lo, body + hi) for lo, hi in column_body_ranges(layout, counts)]
    body_start = min((lo for lo, hi in ranges if hi > lo), default=row.size)
    return _indexed(row.start, row.size, body_start, ranges, row.crc)


class ShardWriter:
    """Writes one scene's rows into Arrow IPC shards of bounded size, atomically.

    Rows are written one record batch each; a shard is closed and a new one started once it
    exceeds ``max_bytes``. Each shard is renamed to its final name only when complete; the list of
    complete shards comes back from :meth:`close`. Use as a context manager: on an exception the
    unfinished temporary file is removed.

    The manifest's checksums of a shard (CRC-32C of the whole file, of each row's metadata and
    columns, of the footer) are computed from the bytes as they are written (:class:`_HashingSink`): the same
    values :func:`shard_info` computes by reading the finished file back.
    """

    def __init__(
        self, cache_dir: Path, scene_id: str, schema: pa.Schema, max_bytes: int = DEFAULT_SHARD_MAX_BYTES
    ):
        problem = scene_id_problem(scene_id)
        if problem:
            shown = scene_id[:57] + "..." if len(scene_id) > 60 else scene_id
            raise PrepError(f"scene id {shown!r} {problem}; cannot write its shards")
        self.cache_dir = Path(cache_dir)
        self.scene_id = scene_id
        self.schema = schema
        self.max_bytes = int(max_bytes)
        self.shards: list[ShardInfo] = []
        self._sink: _HashingSink | None = None
        self._writer: pa.ipc.RecordBatchFileWriter | None = None
        self._tmp: Path | None = None
        self._row_index: list[list[int]] = []
        self._buffer_counts = column_buffer_counts(schema)
        shard_dir = self.cache_dir / SHARDS_DIR
        try:
            shard_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise CacheWriteError(f"{shard_dir}: cannot create ({os_reason(e)})") from e

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _final_path(self, index: int) -> Path:
        return self.cache_dir / SHARDS_DIR / f"{safe_name(self.scene_id)}-{index:05d}.arrow"

    def write(self, batch: pa.RecordBatch) -> None:
        """Appends a one-row batch of this writer's schema.

        Raises :class:`CacheWriteError` naming the shard if the file cannot be written (the
        unfinished shard is removed; complete shards stay)."""
        if not batch.schema.equals(self.schema):
            raise ValueError(f"scene {self.scene_id}: batch schema differs from the cache schema")
        try:
            if self._writer is None:
                self._open_shard()
            assert self._writer is not None and self._sink is not None
            self._writer.write_batch(batch)
            row = self._sink.take()
            entry, checksummed = self._index(row)
            self._sink.add_checksummed(row, checksummed)
            self._row_index.append(entry)
            if self._row_index[-1][0] >= self.max_bytes:
                self._finish_shard()
        except OSError as e:
            raise self._write_failed(e) from e

    def _index(self, row: _RowBytes) -> _Indexed:
        """The row index entry of a row just written: from its metadata, or, for a message
        :mod:`phigenesis.data.ipc_layout` does not read, by decoding the joined row."""
        if self._buffer_counts is not None:
            with contextlib.suppress(LayoutUnknown):
                return _row_entry_from_layout(row, self._buffer_counts, str(self._tmp))
        return _row_entry(row.joined(), row.start, self.schema, str(self._tmp))

    def _open_shard(self) -> None:
        final = self._final_path(len(self.shards))
        self._tmp = final.with_name(f"{final.name}{TMP_MARKER}{uuid.uuid4().hex[:8]}")
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0)
        self._sink = _HashingSink(os.open(self._tmp, flags, 0o666))
        self._writer = pa.ipc.new_file(self._sink, self.schema)
        self._row_index = []

    def _finish_shard(self) -> None:
        assert self._writer is not None and self._sink is not None and self._tmp is not None
        self._writer.close()
        # The footer: from the last row's end to the end of the file.
        footer = self._sink.take()
        footer_crc32 = footer.crc(0, footer.size)
        self._sink.add_checksummed(footer, [(0, footer.size, footer_crc32)])
        size, file_crc32c = self._sink.flushed, self._sink.file_crc32c
        self._sink.sync()
        self._sink.close()
        final = self._final_path(len(self.shards))
        rows = self._row_index
        os.replace(self._tmp, final)
        fsync_dir(final.parent)
        self.shards.append(
            ShardInfo(
                path=final.relative_to(self.cache_dir).as_posix(),
                scene_id=self.scene_id,
                rows=len(rows),
                bytes=size,
                sha256=None,
                columns=list(self.schema.names),
                row_index=rows,
                footer_crc32=footer_crc32,
                checksum=SHARD_CHECKSUM,
                file_crc32c=file_crc32c,
            )
        )
        self._writer = self._sink = self._tmp = None

    def _write_failed(self, error: OSError) -> CacheWriteError:
        """Drops the unfinished shard and says which file could not be written and why."""
        final = self._final_path(len(self.shards))
        self.abort()
        return CacheWriteError(f"{final}: cannot write ({os_reason(error)})")

    def close(self) -> list[ShardInfo]:
        """Completes the open shard; returns every complete shard of this writer."""
        if self._writer is not None:
            try:
                self._finish_shard()
            except OSError as e:
                raise self._write_failed(e) from e
        return self.shards

    def abort(self) -> None:
        """Drops the unfinished shard (complete shards stay, unlisted until a manifest names them)."""
        with contextlib.suppress(OSError, pa.ArrowException):  # already failing; drop the file below
            if self._writer is not None:
                self._writer.close()
            if self._sink is not None:
                self._sink.close()
        if self._tmp is not None:
            with contextlib.suppress(OSError):
                self._tmp.unlink(missing_ok=True)
        self._writer = self._sink = self._tmp = None
