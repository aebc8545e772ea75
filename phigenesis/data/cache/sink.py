"""The byte sink under a shard's Arrow IPC writer: holds each row's bytes, writes them to the file
with ``writev``, hands them to the disk behind the writer (background ``fdatasync`` every
:data:`FLUSH_BYTES`) and keeps the file's CRC-32C from the bytes as they are written, without
reading anything back. Used by :class:`~phigenesis.data.cache.writer.ShardWriter`.
"""

from __future__ import annotations

import bisect
import ctypes
import errno
import itertools
import os
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import google_crc32c
import pyarrow as pa

from phigenesis.data.native import load_crc32c_combine


def _writeback_starter() -> Callable[[int, int, int], object] | None:
    """Linux's ``sync_file_range(fd, offset, nbytes, SYNC_FILE_RANGE_WRITE)``, or None where the C
    library has none: it starts writing a file range to disk without waiting for it."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        function = libc.sync_file_range
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
    function.restype = ctypes.c_int
    return lambda fd, offset, nbytes: function(fd, offset, nbytes, 2)  # SYNC_FILE_RANGE_WRITE = 2


_start_writeback = _writeback_starter()


#: Writes below this size (message headers, metadata, padding) are copied together; larger ones
#: (column buffers) are kept as the IPC writer hands them over and written to the file from there.
_SMALL_WRITE = 1 << 12
#: The most pieces one ``writev`` call takes (Linux's IOV_MAX).
_IOV_MAX = 1024
#: A shard's file is flushed to disk (``fdatasync``) on a background thread each time this many
#: bytes have been written since the last flush, while the next rows are read and converted.
FLUSH_BYTES = 32 * 1024 * 1024


class _BackgroundFlush:
    """One ``fdatasync`` of a file at a time on a thread of its own; :meth:`wait` returns when it
    is done and raises the error it met.

    Why: on a virtual disk an fsync costs time in proportion to the bytes written since the last
    one, even after the kernel has written the data out (the host flushes its own cache then), so
    one fsync at the end of a shard is one long wait. Flushed a few rows at a time behind the
    writer, the flushes overlap the next frames' work (a thread waiting on the disk takes no CPU),
    and the closing fsync finds little left to do (docs/design/cache.md, "Shards are flushed
    behind the writer")."""

    def __init__(self, fd: int):
        self._fd = fd
        self._thread: threading.Thread | None = None
        self._error: OSError | None = None

    def _run(self) -> None:
        try:
            getattr(os, "fdatasync", os.fsync)(self._fd)  # macOS has no fdatasync
        except OSError as e:
            self._error = e

    def start(self) -> bool:
        """Starts a flush unless one is running; whether it started one."""
        if self._thread is not None and self._thread.is_alive():
            return False
        self.wait()
        self._thread = threading.Thread(target=self._run, name="phigenesis-shard-flush", daemon=True)
        self._thread.start()
        return True

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        error, self._error = self._error, None
        if error is not None:
            raise error


class _RowBytes:
    """The bytes of one written row (or the footer) as the pieces they were written in, from file
    offset ``start``: ranges of it read and checksummed without joining the pieces."""

    def __init__(self, start: int, pieces: list[pa.Buffer]):
        self.start = start
        self.pieces = pieces
        self.ends = list(itertools.accumulate(p.size for p in pieces))
        self.size = self.ends[-1] if pieces else 0

    def _spans(self, lo: int, hi: int) -> Iterator[pa.Buffer]:
        """Zero-copy slices of the pieces covering row bytes ``[lo, hi)``."""
        i = bisect.bisect_right(self.ends, lo)
        while lo < hi and i < len(self.pieces):
            begin = self.ends[i] - self.pieces[i].size
            stop = min(hi, self.ends[i])
            yield self.pieces[i].slice(lo - begin, stop - lo)
            lo, i = stop, i + 1

    def read(self, lo: int, hi: int) -> bytes:
        """Row bytes ``[lo, hi)`` (fewer where the row ends first)."""
        return b"".join(span.to_pybytes() for span in self._spans(lo, hi))

    def crc(self, lo: int, hi: int) -> int:
        """CRC-32C of row bytes ``[lo, hi)``."""
        value = 0
        for span in self._spans(lo, hi):
            value = google_crc32c.extend(value, span)
        return value

    def joined(self) -> pa.Buffer:
        return pa.py_buffer(b"".join(self.pieces))


def _write_all(fd: int, pieces: list[pa.Buffer]) -> None:
    """Writes ``pieces`` to ``fd`` in order, with as few ``writev`` calls as they allow."""
    pending = [p for p in pieces if p.size]
    while pending:
        # No writev on Windows: one piece at a time there.
        writev = getattr(os, "writev", None)
        written = writev(fd, pending[:_IOV_MAX]) if writev else os.write(fd, pending[0])
        if written <= 0:
            raise OSError(errno.EIO, "the system wrote nothing")
        done = 0
        while done < len(pending) and written >= pending[done].size:
            written -= pending[done].size
            done += 1
        pending = pending[done:]
        if written:
            pending[0] = pending[0].slice(written)


class _HashingSink:
    """The sink a shard's IPC writer writes into. It holds what the writer hands it until
    :meth:`take` writes it to the file (one ``writev``) and returns it for indexing; each taken
    row is added to the file's CRC-32C in file order, from the CRC-32Cs of its parts where
    :meth:`add_checksummed` is given them, else by reading it. The writer takes each row as soon
    as ``write_batch`` returns, and the footer at the end, so the shard's checksums are computed
    from the bytes as they are written and nothing is read back. Column buffers are not copied on
    the way: the sink keeps the writer's buffers (and so the batch's memory) until the row is taken."""

    def __init__(self, fd: int):
        self.fd = fd
        self._file_crc32c = 0
        self._combine = load_crc32c_combine()
        #: The last row taken, until it is added to the file's CRC-32C.
        self._unhashed: _RowBytes | None = None
        #: Bytes passed on to the file so far.
        self.flushed = 0
        self._pieces: list[pa.Buffer] = []
        self._small = bytearray()
        self._held = 0
        self._closed = False
        self._flush = _BackgroundFlush(fd)
        self._unflushed = 0

    def write(self, data: Any) -> int:
        # Kept as pyarrow buffers: zero-copy slices, and google_crc32c takes them (not memoryviews).
        piece = data if isinstance(data, pa.Buffer) else pa.py_buffer(data)
        if piece.size < _SMALL_WRITE:
            self._small += piece
        else:
            self._seal_small()
            self._pieces.append(piece)
        self._held += piece.size
        return piece.size

    def _seal_small(self) -> None:
        if self._small:
            self._pieces.append(pa.py_buffer(bytes(self._small)))
            self._small = bytearray()

    def take(self) -> _RowBytes:
        """What was written since the last call, after writing it to the file. It joins the file's
        CRC-32C through :meth:`add_checksummed`, or by being read at the next :meth:`take` or
        :attr:`file_crc32c`."""
        self._hash_unhashed()
        self._seal_small()
        row = _RowBytes(self.flushed, self._pieces)
        self._pieces, self._held = [], 0
        _write_all(self.fd, row.pieces)
        if _start_writeback is not None and row.size:
            # Each row is handed to the disk as it is written, so that the fsync that completes
            # the shard does not wait for all of it (advisory: the fsync checks the write).
            _start_writeback(self.fd, row.start, row.size)
        self._unhashed = row
        self.flushed += row.size
        self._unflushed += row.size
        if self._unflushed >= FLUSH_BYTES and self._flush.start():
            self._unflushed = 0
        return row

    def add_checksummed(self, row: _RowBytes, parts: Sequence[tuple[int, int, int]]) -> None:
        """Adds ``row``, the row last taken, to the file's CRC-32C from ``parts``: ``(lo, hi,
        crc)``, the CRC-32C of its bytes ``[lo, hi)`` (disjoint). The bytes between them are read;
        without the native combination (:func:`phigenesis.data.native.load_crc32c_combine`) the
        whole row is."""
        if row is not self._unhashed:
            raise ValueError("add_checksummed: not the row last taken, or already hashed")
        combine = self._combine
        if combine is not None and (crc := _crc_from_parts(row, parts, combine)) is not None:
            self._file_crc32c = combine(self._file_crc32c, crc, row.size)
            self._unhashed = None
        else:
            self._hash_unhashed()

    def _hash_unhashed(self) -> None:
        if self._unhashed is not None:
            for piece in self._unhashed.pieces:
                self._file_crc32c = google_crc32c.extend(self._file_crc32c, piece)
            self._unhashed = None

    @property
    def file_crc32c(self) -> int:
        """CRC-32C of the bytes passed on to the file so far."""
        self._hash_unhashed()
        return self._file_crc32c

    def sync(self) -> None:
        """Waits for the background flush (raising its error), then fsyncs the file."""
        self._flush.wait()
        os.fsync(self.fd)

    def tell(self) -> int:
        return self.flushed + self._held

    def flush(self) -> None:
        """Nothing to do: rows reach the file through :meth:`take`."""

    def writable(self) -> bool:
        return True

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Closes the file; bytes not taken are dropped (the writer takes everything it keeps)."""
        if not self._closed:
            self._closed = True
            self._pieces, self._small = [], bytearray()
            try:
                self._flush.wait()  # never close the descriptor under a running fdatasync
            finally:
                os.close(self.fd)


def _crc_from_parts(
    row: _RowBytes, parts: Sequence[tuple[int, int, int]], combine: Callable[[int, int, int], int]
) -> int | None:
    """CRC-32C of the whole row from the CRC-32Cs ``(lo, hi, crc)`` of parts of it, reading only
    the bytes between them (an IPC message's padding); None if the parts overlap or overrun it."""
    crc, pos = 0, 0
    for lo, hi, part_crc in sorted(part for part in parts if part[1] > part[0]):
        if lo < pos or hi > row.size:
            return None
        if lo > pos:
            crc = combine(crc, row.crc(pos, lo), lo - pos)
        crc, pos = combine(crc, part_crc, hi - lo), hi
    if pos < row.size:
        crc = combine(crc, row.crc(pos, row.size), row.size - pos)
    return crc
