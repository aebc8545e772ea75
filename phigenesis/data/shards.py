"""Sharded Arrow IPC caches: an atomic writer, the manifest, a random-access reader and a verifier.

Layout of a cache directory::

    manifest.json          what the cache holds (the commit point: rewritten atomically per scene)
    shards/<scene>-00000.arrow  Arrow IPC files, one row per frame, one record batch per row
    .phigenesis.lock       held by the one run writing the cache (see cache_lock.py, cache_run.py)
    .phigenesis-staging/   the new version an ``overwrite`` run builds before swapping it in

Integrity: the manifest records each shard's size and CRC-32C and, for every record batch (row),
where it ends, where its body starts, the CRC-32C of its metadata and of each top-level column's
bytes, plus the CRC-32C of the file footer (caches written before CRC-32C carry zlib CRC-32s and a
SHA-256 of the file instead, and are read and verified as such; see :data:`SHARD_CHECKSUM`). The
reader checks a shard's size and footer when it opens it, and a row's metadata and the columns it
returns when it reads the row: a flipped byte in anything a caller reads raises an error naming the
shard, row and column, and reading only the images of a frame never hashes its LiDAR.
:func:`verify_cache` re-hashes everything. The writer computes all of these from the bytes as it
writes them, never reading a shard back.

Trust: a manifest is untrusted input. :meth:`Manifest.load` checks it against the cache's schema
once (every field's type and range, the row index's shape, scenes and shards agreeing with each
other) and checks that every shard path resolves, symbolic links included, inside the cache's
``shards/`` folder; whatever reads or deletes a shard goes through :func:`resolve_shard_path`. A
manifest that is itself a symbolic link is refused; scene ids and shard file names are bounded
(:func:`scene_id_problem`, :data:`MAX_FILE_NAME_BYTES`), so no name reaches the file system that
it cannot take.

Atomicity: every file is written under a temporary name, flushed with fsync and renamed; the
manifest is rewritten the same way after each scene completes. A killed run leaves only complete
files under final names, and the manifest lists only scenes whose shards are all complete. A write
that fails (a full disk) removes its temporary file and raises :class:`CacheWriteError` naming the
file and the system's reason.
"""

from __future__ import annotations

import bisect
import contextlib
import ctypes
import errno
import hashlib
import itertools
import json
import logging
import os
import sys
import threading
import uuid
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import google_crc32c
import pyarrow as pa

from phigenesis.data.ipc_layout import (
    LayoutUnknown,
    column_body_ranges,
    column_buffer_counts,
    record_batch_layout,
)
from phigenesis.data.native import load_crc32c_combine
from phigenesis.errors import CacheError, PrepError

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"
SHARDS_DIR = "shards"
CACHE_FORMAT = "phigenesis-cache"
DEFAULT_SHARD_MAX_BYTES = 256 * 1024 * 1024
TMP_MARKER = ".tmp-"
#: Where an ``overwrite`` run builds the new version of a cache, inside the cache directory.
STAGING_DIR = ".phigenesis-staging"
#: Written into the staging folder once the new version is complete, before the old one is
#: touched: a run that finds it finishes the swap.
SWAP_MARKER = "swapping"


class CacheWriteError(PrepError, OSError):
    """A cache file could not be written (a full disk, ...): the message names the file and the
    system's reason. Its temporary file is removed; complete files stay."""


def os_reason(error: OSError) -> str:
    """The system's reason for ``error`` in words ("No space left on device")."""
    if error.strerror:
        return error.strerror
    code = error.args[0] if len(error.args) == 1 else None
    if isinstance(code, int):
        return os.strerror(code)
    return str(error) or type(error).__name__


# --------------------------------------------------------------------------------------------
# Atomic file writes


def fsync_dir(path: Path) -> None:
    """Flushes a directory entry (a rename) to disk, where the platform allows it."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):  # some file systems cannot fsync a directory
            os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Writes ``data`` to ``path`` via a temporary file, fsync and rename.

    On failure the temporary file is removed and ``path`` is left as it was; an OSError becomes a
    :class:`CacheWriteError` naming ``path``."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}{TMP_MARKER}{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise CacheWriteError(f"{path}: cannot write ({os_reason(e)})") from e
        raise
    fsync_dir(path.parent)


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def crc32c_file(path: Path, chunk: int = 1 << 22) -> int:
    """CRC-32C of a whole file (what a shard's ``file_crc32c`` records)."""
    crc = 0
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            crc = google_crc32c.extend(crc, block)
    return crc


# --------------------------------------------------------------------------------------------
# Checksums

#: The checksum of every shard this toolkit writes: CRC-32C (Castagnoli, as TFRecord and ext4 use),
#: which SSE 4.2 / ARMv8 compute at over 20 GB/s, of every row's metadata, every column, the footer
#: and the whole file. ``"crc32"`` (zlib's CRC-32 of the same ranges, with a SHA-256 of the whole
#: file) is the format of caches written before it: still read and verified.
SHARD_CHECKSUM = "crc32c"
CHECKSUMS = ("crc32c", "crc32")


def crc_of(checksum: str, data: pa.Buffer) -> int:
    """The ``checksum`` (one of :data:`CHECKSUMS`) of the bytes of ``data`` (no copy)."""
    if checksum == "crc32c":
        return google_crc32c.value(data)
    return zlib.crc32(data)


def _crc_range(checksum: str, data: pa.Buffer, lo: int, hi: int) -> int:
    """:func:`crc_of` of ``data[lo:hi]``."""
    return crc_of(checksum, data.slice(lo, hi - lo))


def _crc_name(info: ShardInfo) -> str:
    return "CRC-32C" if info.checksum == "crc32c" else "CRC-32"


if google_crc32c.implementation != "c":
    log.warning(
        "google-crc32c has no compiled implementation here: cache checksums will be slow "
        "(reinstall google-crc32c from a binary wheel)"
    )


# --------------------------------------------------------------------------------------------
# Shard writer


@dataclass
class ShardInfo:
    """A complete shard file as the manifest records it.

    Attributes:
        path: relative to the cache directory (POSIX separators).
        scene_id: the scene whose frames it holds.
        rows: number of rows (frames), one record batch each.
        bytes: file size.
        sha256: hex digest of the whole file (``checksum`` ``"crc32"`` only), else None.
        columns: the top-level columns, in schema order.
        row_index: per row ``[end, body_start, metadata_crc, crc of each column...]``: the byte
            offset where the row's record batch ends, where its body (the column buffers) starts,
            the CRC of the bytes from the row's start to its body, and of each column's bytes.
        footer_crc32: CRC of the bytes from the last row's end to the end of the file (the name is
            the manifest's field; its algorithm is ``checksum``'s).
        checksum: the CRC of every range above (:data:`CHECKSUMS`); ``"crc32"`` for manifests
            written before CRC-32C, which name none.
        file_crc32c: CRC-32C of the whole file (``checksum`` ``"crc32c"``), else None.
    """

    path: str
    scene_id: str
    rows: int
    bytes: int
    sha256: str | None
    columns: list[str] = field(default_factory=list)
    row_index: list[list[int]] = field(default_factory=list)
    footer_crc32: int = 0
    checksum: str = "crc32"
    file_crc32c: int | None = None

    def to_dict(self) -> dict[str, Any]:
        """The manifest's entry (the whole-file digest of the other checksum left out)."""
        d = asdict(self)
        for name in ("sha256", "file_crc32c"):
            if d[name] is None:
                del d[name]
        return d

    def row_start(self, row: int) -> int:
        """Byte offset where ``row``'s record batch starts (row 0 starts with the file)."""
        return 0 if row == 0 else self.row_index[row - 1][0]

    @property
    def footer_start(self) -> int:
        """Byte offset where the file footer starts: the end of the last row."""
        return self.row_start(self.rows)


def column_range(column: pa.Array, base_address: int) -> tuple[int, int]:
    """Byte range ``[lo, hi)`` of a column's buffers (children included) relative to
    ``base_address``; ``(0, 0)`` for a column without data.

    Valid for batches read zero-copy from a memory-mapped IPC file, where an IPC body lays out
    each top-level column's buffers contiguously.
    """
    lo = hi = None
    for b in column.buffers():
        if b is not None and b.size:
            a = b.address - base_address
            lo = a if lo is None else min(lo, a)
            hi = a + b.size if hi is None else max(hi, a + b.size)
    return (0, 0) if lo is None else (lo, hi)


def column_ranges(batch: pa.RecordBatch, base_address: int) -> list[tuple[int, int]]:
    """:func:`column_range` of every top-level column of ``batch``, in schema order."""
    return [column_range(c, base_address) for c in batch.columns]


#: The bytes an Arrow IPC file starts with ("ARROW1" and two bytes of padding), before its schema.
_IPC_FILE_MAGIC = b"ARROW1\x00\x00"


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

    Why: on a virtual disk an fsync costs about 1.4 ms per MB written since the last one, even
    after the kernel has written the data out (the host flushes its own cache then). Left to the
    end of a shard, that is one wait of 200-250 ms for a 160 MB shard (10 ms a Waymo frame).
    Flushed a few rows at a time behind the writer, the flushes overlap the next frames' work
    (a thread waiting on the disk takes no CPU), and the closing fsync finds little left to do."""

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


def shard_info(path: Path, scene_id: str, row_ends: list[int], checksum: str = SHARD_CHECKSUM) -> ShardInfo:
    """Size, whole-file digest and the per-row, per-column CRC index of a finished shard file, read
    back from disk: the reference the writer's checksums (computed as it writes) are tested against.

    ``row_ends`` are the file positions after each record batch, as the writer saw them;
    ``checksum`` one of :data:`CHECKSUMS` (``"crc32"`` gives the older format: zlib CRC-32s and a
    SHA-256).
    """
    data = Path(path).read_bytes()
    buffer = pa.py_buffer(data)
    reader = pa.ipc.open_file(buffer)
    if reader.num_record_batches != len(row_ends):
        raise CacheError(
            f"{path}: {reader.num_record_batches} record batches, the writer wrote {len(row_ends)}"
        )
    row_index, start = [], 0
    for i, end in enumerate(row_ends):
        ranges = column_ranges(reader.get_batch(i), buffer.address)
        body_start = min((lo for lo, hi in ranges if hi > lo), default=end)
        if not all(start <= lo <= hi <= end for lo, hi in ranges if hi > lo):
            raise CacheError(f"{path}: row {i}'s buffers lie outside its record batch; cannot index it")
        row_index.append(
            [end, body_start, _crc_range(checksum, buffer, start, body_start)]
            + [_crc_range(checksum, buffer, lo, hi) for lo, hi in ranges]
        )
        start = end
    legacy = checksum == "crc32"
    return ShardInfo(
        path=Path(path).name,
        scene_id=scene_id,
        rows=reader.num_record_batches,
        bytes=len(data),
        sha256=hashlib.sha256(data).hexdigest() if legacy else None,
        columns=list(reader.schema.names),
        row_index=row_index,
        footer_crc32=_crc_range(checksum, buffer, start, len(data)),
        checksum=checksum,
        file_crc32c=None if legacy else crc_of("crc32c", buffer),
    )


def safe_name(scene_id: str) -> str:
    """A file-name-safe form of a scene id."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in scene_id)


#: The longest scene id a cache holds, in characters: its shard files are named after it.
MAX_SCENE_ID_CHARS = 200
#: The longest file name most file systems take (Linux's NAME_MAX), in bytes of UTF-8.
MAX_FILE_NAME_BYTES = 255


def scene_id_problem(scene_id: object) -> str | None:
    """Why ``scene_id`` cannot be a cache's scene id (None if it can): it names the scene's shard
    files (:func:`safe_name` plus ``-00000.arrow``), so it is a non-empty string of at most
    :data:`MAX_SCENE_ID_CHARS` characters without control characters, whose file-name form fits in
    200 bytes."""
    if not isinstance(scene_id, str):
        return "is not a string"
    if not scene_id:
        return "is empty"
    if len(scene_id) > MAX_SCENE_ID_CHARS:
        return (
            f"has {len(scene_id)} characters; a scene id has at most {MAX_SCENE_ID_CHARS} "
            "(it names the scene's shard files)"
        )
    if any(ord(c) < 32 or ord(c) == 127 for c in scene_id):
        return "holds a control character"
    if len(safe_name(scene_id).encode()) > MAX_SCENE_ID_CHARS:
        return f"takes {len(safe_name(scene_id).encode())} bytes as a file name; at most {MAX_SCENE_ID_CHARS}"
    return None


# --------------------------------------------------------------------------------------------
# Manifest


SCENE_STATUSES = ("complete", "skipped", "failed")
CRC32_MAX = (1 << 32) - 1


@dataclass
class SceneEntry:
    """A scene as the manifest records it: ``complete`` (all its frames are in listed shards),
    ``skipped`` (it failed and the run went on; ``error`` says why) or ``failed`` (it stopped the
    run). ``dropped`` counts what the source left out of it as invalid, per kind
    (:meth:`~phigenesis.data.records.DroppedValues.totals`); manifests without it load as empty."""

    id: str
    source: str
    frames: int
    status: str
    shards: list[str] = field(default_factory=list)
    error: str | None = None
    dropped: dict[str, int] = field(default_factory=dict)


@dataclass
class Manifest:
    """The index of a cache: what made it, its scenes and its shard files.

    ``fingerprint`` is a hash of everything that determines the rows (source, its arguments, the
    pipeline spec, the schema version); a rerun into the same directory must match it.
    ``scenes_expected`` lists the scene ids the run's arguments ask for, in order, recorded when
    the run starts (:mod:`phigenesis.data.cache_run`): a cache with fewer finished scenes is
    incomplete. None in manifests written before the field existed (completeness unknown).
    """

    schema_version: int
    source: str
    arguments: dict[str, Any]
    pipeline: dict[str, Any]
    fingerprint: str
    scenes: list[SceneEntry] = field(default_factory=list)
    shards: list[ShardInfo] = field(default_factory=list)
    format: str = CACHE_FORMAT
    phigenesis_version: str = ""
    scenes_expected: list[str] | None = None

    def scene(self, scene_id: str) -> SceneEntry | None:
        for s in self.scenes:
            if s.id == scene_id:
                return s
        return None

    def record_scene(self, entry: SceneEntry, shards: list[ShardInfo]) -> None:
        """Adds or replaces a scene and its shards."""
        self.scenes = [s for s in self.scenes if s.id != entry.id] + [entry]
        self.shards = [s for s in self.shards if s.scene_id != entry.id] + list(shards)

    def unfinished_scenes(self) -> list[str] | None:
        """The scenes of ``scenes_expected`` the run has not finished (none recorded, or recorded
        ``failed``: the run stopped there), in order; None where the manifest does not record
        ``scenes_expected``. A ``skipped`` scene is finished: the run went on past it."""
        if self.scenes_expected is None:
            return None
        finished = {s.id for s in self.scenes if s.status in ("complete", "skipped")}
        return [sid for sid in self.scenes_expected if sid not in finished]

    def to_json(self) -> str:
        d = asdict(self)
        d["shards"] = [sh.to_dict() for sh in self.shards]
        if d["scenes_expected"] is None:
            del d["scenes_expected"]
        return json.dumps(d, indent=1, sort_keys=False)

    def save(self, cache_dir: Path) -> None:
        """Writes ``cache_dir/manifest.json`` atomically (:func:`atomic_write_bytes`)."""
        atomic_write_bytes(Path(cache_dir) / MANIFEST_NAME, self.to_json().encode())

    @classmethod
    def load(cls, cache_dir: str | os.PathLike[str]) -> Manifest:
        """Reads and checks ``cache_dir/manifest.json``.

        Raises one :class:`CacheError` naming the file, and the field where one is wrong, if the
        manifest is missing, truncated or not valid JSON, does not fit the cache's schema (see
        :func:`parse_manifest`), or names a shard outside ``cache_dir/shards/``."""
        path = Path(cache_dir) / MANIFEST_NAME
        return parse_manifest(_read_json(path), path)

    def complete_shards(self) -> list[ShardInfo]:
        """Shards of complete scenes, in scene order then shard order."""
        done = [s.id for s in self.scenes if s.status == "complete"]
        by_scene: dict[str, list[ShardInfo]] = {}
        for sh in self.shards:
            by_scene.setdefault(sh.scene_id, []).append(sh)
        return [sh for sid in done for sh in by_scene.get(sid, [])]


def _read_json(path: Path) -> object:
    """The parsed JSON document of a manifest file; CacheError naming it if it cannot be. A
    manifest that is a symbolic link is refused, as a ``shards/`` folder that is one is: what a
    cache holds lies inside it."""
    if path.is_symlink():
        raise CacheError(
            f"{path}: the manifest is a symbolic link (to {os.readlink(path)}); a cache's "
            f"{MANIFEST_NAME} must be a file inside it"
        )
    if not path.is_file():
        hint = ""
        if (path.parent / STAGING_DIR / SWAP_MARKER).exists():
            hint = (
                f" (an overwrite was swapping in a new version of the cache from {STAGING_DIR}/: "
                "wait for it to finish, or rerun the overwrite if it was stopped)"
            )
        raise CacheError(f"{path}: no manifest; {path.parent} is not a phigenesis cache{hint}")
    try:
        text = path.read_text(errors="replace")
    except OSError as e:
        raise CacheError(f"{path}: cannot read the manifest ({os_reason(e)})") from e
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise CacheError(
            f"{path}: manifest is truncated or not valid JSON "
            f"({e.msg} at line {e.lineno}, column {e.colno}; {len(text)} bytes)"
        ) from e
    except (ValueError, RecursionError) as e:  # an integer too long to convert, nesting too deep
        raise CacheError(f"{path}: manifest is not valid JSON ({e})") from e


def resolve_shard_path(cache_dir: str | os.PathLike[str], relative: str, field: str = "shard path") -> Path:
    """The file a manifest's shard path names, resolved (symbolic links followed).

    Raises :class:`CacheError` naming the manifest and ``field`` unless ``relative`` has the form
    ``shards/<file name>`` and resolves inside ``cache_dir/shards/`` (a ``shards`` folder that is a
    link out of the cache does not count): nothing outside a cache's shards folder is read or
    deleted because a manifest names it."""
    cache_dir = Path(cache_dir)
    where = f"{cache_dir / MANIFEST_NAME}: {field}"
    shown = repr(relative) if len(relative) <= 80 else repr(relative[:77]) + "..."
    if len(relative.encode(errors="replace")) > len(SHARDS_DIR) + 1 + MAX_FILE_NAME_BYTES:
        raise CacheError(
            f"{where}: {shown} is {len(relative)} characters long; a shard's file name has at most "
            f"{MAX_FILE_NAME_BYTES} bytes"
        )
    pure = PurePosixPath(relative)
    if pure.is_absolute():
        raise CacheError(f"{where}: {shown} is an absolute path; shard paths are 'shards/<file name>'")
    if len(pure.parts) != 2 or pure.parts[0] != SHARDS_DIR or pure.as_posix() != relative or "\0" in relative:
        raise CacheError(f"{where}: {shown} is not a file directly in {SHARDS_DIR}/")
    if len(pure.name.encode(errors="replace")) > MAX_FILE_NAME_BYTES:
        raise CacheError(f"{where}: {shown}: a shard's file name has at most {MAX_FILE_NAME_BYTES} bytes")
    root = cache_dir.resolve() / SHARDS_DIR
    try:
        resolved = (cache_dir / relative).resolve()
    except (OSError, RuntimeError) as e:  # a symbolic link loop
        raise CacheError(f"{where}: {shown} cannot be resolved ({e})") from e
    if resolved == root or not resolved.is_relative_to(root):
        raise CacheError(f"{where}: {shown} resolves to {resolved}, outside {root}")
    return resolved


# --------------------------------------------------------------------------------------------
# Manifest schema

_REQUIRED = object()


def _show(value: object) -> str:
    """A JSON value as an error message quotes it (shortened)."""
    text = json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


def _integer_problem(value: object, minimum: int = 0, maximum: int | None = None) -> str | None:
    """Why ``value`` is not an integer in ``[minimum, maximum]`` (None if it is)."""
    is_integer = isinstance(value, int) and not isinstance(value, bool)
    if is_integer and value >= minimum and (maximum is None or value <= maximum):
        return None
    if maximum is not None:
        return f"is not an integer in [{minimum}, {maximum}]"
    return "is not a non-negative integer" if minimum == 0 else f"is not an integer of at least {minimum}"


class _Fields:
    """One JSON object of a manifest, read field by field: each getter checks the field's type and
    range and raises a CacheError naming the file and the field (``shards[3].rows``)."""

    def __init__(self, file: Path, where: str, value: object):
        self.file = file
        self.where = where
        if not isinstance(value, dict):
            raise CacheError(f"{file}: {where}: {_show(value)} is not an object")
        self.value: dict[str, Any] = value

    def name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def error(self, key: str, message: str) -> CacheError:
        return CacheError(f"{self.file}: {self.name(key)}: {message}")

    def raw(self, key: str, default: Any = _REQUIRED) -> Any:
        if key in self.value:
            return self.value[key]
        if default is _REQUIRED:
            raise self.error(key, "missing")
        return default

    def string(self, key: str, default: Any = _REQUIRED) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str):
            raise self.error(key, f"{_show(value)} is not a string")
        return value

    def optional_string(self, key: str) -> str | None:
        value = self.raw(key, None)
        if value is not None and not isinstance(value, str):
            raise self.error(key, f"{_show(value)} is not a string or null")
        return value

    def integer(self, key: str, minimum: int = 0, maximum: int | None = None) -> int:
        value = self.raw(key)
        problem = _integer_problem(value, minimum, maximum)
        if problem:
            raise self.error(key, f"{_show(value)} {problem}")
        return value

    def mapping(self, key: str, default: Any = _REQUIRED) -> dict[str, Any]:
        value = self.raw(key, default)
        if not isinstance(value, dict):
            raise self.error(key, f"{_show(value)} is not an object")
        return value

    def array(self, key: str, default: Any = _REQUIRED) -> list[Any]:
        value = self.raw(key, default)
        if not isinstance(value, list):
            raise self.error(key, f"{_show(value)} is not an array")
        return value

    def strings(self, key: str, default: Any = _REQUIRED) -> list[str]:
        values = self.array(key, default)
        for k, v in enumerate(values):
            if not isinstance(v, str):
                raise CacheError(f"{self.file}: {self.name(key)}[{k}]: {_show(v)} is not a string")
        return list(values)


def parse_manifest(document: object, file: Path) -> Manifest:
    """The manifest a parsed ``manifest.json`` describes, checked against the cache's schema.

    Checks every field's type and range, each shard's row index (one entry per row of 3 + one
    value per column, row ends increasing inside the file, each body inside its row, CRCs of 32
    bits), that scene ids and shard paths are unique, that every shard belongs to a listed scene
    and every scene lists exactly its own shards, and that every shard path stays inside the
    cache's ``shards/`` folder (:func:`resolve_shard_path`). Raises one :class:`CacheError` naming
    ``file`` and the first field that is wrong (``shards[3].rows: -1 is not a non-negative
    integer``)."""
    if not isinstance(document, dict):
        raise CacheError(f"{file}: the manifest is {_show(document)}, not a JSON object")
    top = _Fields(file, "", document)
    if top.raw("format", None) != CACHE_FORMAT:
        raise CacheError(f"{file}: not a {CACHE_FORMAT} manifest (format={top.raw('format', None)!r})")
    shards = [_parse_shard(file, i, v) for i, v in enumerate(top.array("shards"))]
    scenes = [_parse_scene(file, i, v) for i, v in enumerate(top.array("scenes"))]
    _check_listing(file, scenes, shards)
    expected = _parse_scenes_expected(top)
    for i, sh in enumerate(shards):
        resolve_shard_path(file.parent, sh.path, f"shards[{i}].path")
    return Manifest(
        schema_version=top.integer("schema_version", minimum=1),
        source=top.string("source"),
        arguments=top.mapping("arguments"),
        pipeline=top.mapping("pipeline"),
        fingerprint=top.string("fingerprint"),
        scenes=scenes,
        shards=shards,
        format=CACHE_FORMAT,
        phigenesis_version=top.string("phigenesis_version", ""),
        scenes_expected=expected,
    )


def _parse_scenes_expected(top: _Fields) -> list[str] | None:
    """``scenes_expected``: absent or null (a manifest written before it existed), or an array of
    distinct scene ids."""
    if top.raw("scenes_expected", None) is None:
        return None
    expected = top.strings("scenes_expected")
    seen: set[str] = set()
    for k, scene_id in enumerate(expected):
        _check_scene_id(top, f"scenes_expected[{k}]", scene_id)
        if scene_id in seen:
            raise CacheError(f"{top.file}: scenes_expected[{k}]: {scene_id[:60]!r} is listed twice")
        seen.add(scene_id)
    return expected


def _check_scene_id(f: _Fields, key: str, scene_id: str) -> None:
    """CacheError naming the manifest and ``key`` if ``scene_id`` cannot be a scene id."""
    problem = scene_id_problem(scene_id)
    if problem:
        raise f.error(key, f"{_show(scene_id)} {problem}")


def _parse_shard(file: Path, i: int, value: object) -> ShardInfo:
    """One entry of ``shards``, checked (see :func:`parse_manifest`)."""
    f = _Fields(file, f"shards[{i}]", value)
    path = f.string("path")
    scene_id = f.string("scene_id")
    _check_scene_id(f, "scene_id", scene_id)
    rows = f.integer("rows")
    size = f.integer("bytes")
    checksum = f.string("checksum", "crc32")
    if checksum not in CHECKSUMS:
        raise f.error("checksum", f"{_show(checksum)} is not one of {list(CHECKSUMS)}")
    sha256, file_crc32c = None, None
    if checksum == "crc32":
        sha256 = f.string("sha256")
        if len(sha256) != 64 or not set(sha256) <= set("0123456789abcdef"):
            raise f.error("sha256", f"{_show(sha256)} is not a SHA-256 hex digest")
    else:
        file_crc32c = f.integer("file_crc32c", 0, CRC32_MAX)
    columns = f.strings("columns")
    if len(set(columns)) != len(columns):
        raise f.error("columns", f"{_show(columns)} names a column twice")
    row_index = _parse_row_index(f, rows, len(columns), size)
    footer_crc32 = f.integer("footer_crc32", 0, CRC32_MAX)
    return ShardInfo(
        path, scene_id, rows, size, sha256, columns, row_index, footer_crc32, checksum, file_crc32c
    )


def _parse_row_index(f: _Fields, rows: int, columns: int, size: int) -> list[list[int]]:
    """A shard's ``row_index``: ``rows`` entries of ``[end, body_start, metadata_crc32, one crc32
    per column]``, the ends increasing and inside the file, each body start inside its row."""
    index = f.array("row_index")
    name = f.name("row_index")
    if len(index) != rows:
        raise CacheError(f"{f.file}: {name}: {len(index)} entries, but the shard has {rows} rows")
    width = 3 + columns
    start = 0
    for r, entry in enumerate(index):
        where = f"{f.file}: {name}[{r}]"
        if not isinstance(entry, list) or len(entry) != width:
            raise CacheError(
                f"{where}: {_show(entry)} is not {width} integers "
                f"(end, body start, metadata CRC and a CRC for each of {columns} columns)"
            )
        for k, v in enumerate(entry):
            problem = _integer_problem(v, 0, CRC32_MAX if k >= 2 else None)
            if problem:
                raise CacheError(f"{where}[{k}]: {_show(v)} {problem}")
        end, body_start = entry[0], entry[1]
        if end <= start:
            raise CacheError(f"{where}[0]: row end {end} is not after the row's start {start}")
        if end > size:
            raise CacheError(f"{where}[0]: row end {end} is past the end of the file ({size} bytes)")
        if not start <= body_start <= end:
            raise CacheError(f"{where}[1]: body start {body_start} lies outside the row ({start}..{end})")
        start = end
    return [list(e) for e in index]


def _parse_scene(file: Path, i: int, value: object) -> SceneEntry:
    """One entry of ``scenes``, checked (see :func:`parse_manifest`)."""
    f = _Fields(file, f"scenes[{i}]", value)
    status = f.string("status")
    if status not in SCENE_STATUSES:
        raise f.error("status", f"{_show(status)} is not one of {', '.join(SCENE_STATUSES)}")
    dropped = f.mapping("dropped", {})
    for what, count in dropped.items():
        problem = _integer_problem(count)
        if problem:
            raise CacheError(f"{file}: {f.name('dropped')}[{what!r}]: {_show(count)} {problem}")
    scene_id = f.string("id")
    _check_scene_id(f, "id", scene_id)
    return SceneEntry(
        id=scene_id,
        source=f.string("source"),
        frames=f.integer("frames"),
        status=status,
        shards=f.strings("shards", []),
        error=f.optional_string("error"),
        dropped=dict(dropped),
    )


def _check_listing(file: Path, scenes: list[SceneEntry], shards: list[ShardInfo]) -> None:
    """Scenes and shards agree: scene ids and shard paths are unique, every shard belongs to a
    listed scene, and every scene lists exactly its own shards, in order (none if not complete)."""
    scene_at: dict[str, int] = {}
    for i, scene in enumerate(scenes):
        if scene.id in scene_at:
            raise CacheError(
                f"{file}: scenes[{i}].id: {scene.id!r} is listed twice (also scenes[{scene_at[scene.id]}])"
            )
        scene_at[scene.id] = i
    shard_at: dict[str, int] = {}
    for i, sh in enumerate(shards):
        if sh.path in shard_at:
            raise CacheError(
                f"{file}: shards[{i}].path: {sh.path!r} is listed twice (also shards[{shard_at[sh.path]}])"
            )
        shard_at[sh.path] = i
        if sh.scene_id not in scene_at:
            raise CacheError(f"{file}: shards[{i}].scene_id: {sh.scene_id!r} is not a scene of the manifest")
    paths_of: dict[str, list[str]] = {}
    for sh in shards:
        paths_of.setdefault(sh.scene_id, []).append(sh.path)
    for i, scene in enumerate(scenes):
        for k, path in enumerate(scene.shards):
            if path not in shard_at:
                raise CacheError(f"{file}: scenes[{i}].shards[{k}]: {path!r} is not a shard of the manifest")
        own = paths_of.get(scene.id, [])
        if scene.shards != own:
            raise CacheError(
                f"{file}: scenes[{i}].shards: {_show(scene.shards)} are not the shards of scene "
                f"{scene.id!r} in the manifest's shard list ({_show(own)})"
            )
        if own and scene.status != "complete":
            raise CacheError(
                f"{file}: scenes[{i}].shards: a {scene.status} scene lists shards ({_show(own)})"
            )


# --------------------------------------------------------------------------------------------
# Reader


class ShardReader:
    """Random access to the rows of one shard, checking the manifest's CRCs of what it returns.

    Each row's metadata and each column of a row is checked the first time this reader returns it
    (its memory map stays the one it checked): a DataLoader that reads every frame once per epoch
    pays for the CRCs in its first epoch only. A file damaged on disk is still refused on its first
    read in every process; ``verify`` re-hashes everything.
    """

    def __init__(self, cache_dir: Path, info: ShardInfo, check_crc: bool = True):
        self.info = info
        resolve_shard_path(cache_dir, info.path)  # never read a file outside the cache's shards/
        self.path = Path(cache_dir) / info.path
        self.check_crc = check_crc
        if not self.path.is_file():
            raise CacheError(f"{self.path}: shard listed in the manifest is missing")
        size = self.path.stat().st_size
        if size != info.bytes:
            raise CacheError(
                f"{self.path}: shard is {size} bytes, the manifest says {info.bytes} (truncated or replaced)"
            )
        self._mmap = pa.memory_map(str(self.path), "r")
        self._buffer = self._mmap.read_buffer()
        if check_crc:
            self._check(info.footer_start, info.bytes, info.footer_crc32, "the footer")
        try:
            self._reader = pa.ipc.open_file(self._buffer)
        except (pa.ArrowInvalid, OSError) as e:
            raise CacheError(f"{self.path}: not a readable Arrow IPC file ({e})") from e
        if self._reader.num_record_batches != info.rows:
            raise CacheError(
                f"{self.path}: holds {self._reader.num_record_batches} rows, the manifest says {info.rows}"
            )
        self._column_index = {name: i for i, name in enumerate(info.columns)}
        self._checked: set[tuple[int, int]] = set()  # (row, column index; -1: metadata) seen intact

    def _check(self, start: int, end: int, expected: int, what: str) -> None:
        if _crc_range(self.info.checksum, self._buffer, start, end) != expected:
            raise CacheError(
                f"{self.path}: {what} is corrupt ({_crc_name(self.info)} mismatch in bytes {start}..{end})"
            )

    def __len__(self) -> int:
        return self.info.rows

    def read(self, row: int, columns: Sequence[str] | None = None) -> pa.RecordBatch:
        """The one-row batch of ``row`` (only ``columns``, if given), after checking the CRCs of its
        metadata and of the columns returned."""
        if not 0 <= row < self.info.rows:
            raise IndexError(f"{self.path}: row {row} out of range ({self.info.rows} rows)")
        names = list(self.info.columns if columns is None else columns)
        unknown = [c for c in names if c not in self._column_index]
        if unknown:
            raise KeyError(f"{self.path}: no columns {unknown}; it has {self.info.columns}")
        entry = self.info.row_index[row]
        checked = self._checked
        if self.check_crc and (row, -1) not in checked:
            self._check(self.info.row_start(row), entry[1], entry[2], f"row {row} (metadata)")
            checked.add((row, -1))
        try:
            batch = self._reader.get_batch(row)
        except (pa.ArrowInvalid, OSError) as e:
            raise CacheError(f"{self.path}: row {row} does not decode ({e})") from e
        if self.check_crc:
            for name in names:
                k = self._column_index[name]
                if (row, k) in checked:
                    continue
                lo, hi = column_range(batch.column(k), self._buffer.address)
                self._check(lo, hi, entry[3 + k], f"row {row}, column {name!r}")
                checked.add((row, k))
        return batch if columns is None else batch.select(names)

    @property
    def schema(self) -> pa.Schema:
        return self._reader.schema


#: Columns every row of a frame cache has (:mod:`phigenesis.data.schema`), which a frame needs.
FRAME_KEY_COLUMNS = ("scene_id", "frame_index", "frame_timestamp_micros", "world_from_ego", "cameras")


class CacheReader:
    """Random access to every frame of a cache, in manifest order (scene by scene).

    Shards are memory-mapped on first use; the reader can be pickled (open files are reopened in
    the new process), so it works inside DataLoader workers.
    """

    def __init__(self, cache_dir: str | os.PathLike[str], check_crc: bool = True):
        self.cache_dir = Path(cache_dir)
        self.check_crc = check_crc
        self.manifest = Manifest.load(self.cache_dir)
        self.shards = self.manifest.complete_shards()
        self._index: list[tuple[int, int]] = [
            (i, r) for i, sh in enumerate(self.shards) for r in range(sh.rows)
        ]
        self._open: dict[int, ShardReader] = {}

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_open"] = {}
        return state

    def __len__(self) -> int:
        return len(self._index)

    def shard(self, index: int) -> ShardReader:
        if index not in self._open:
            self._open[index] = ShardReader(self.cache_dir, self.shards[index], self.check_crc)
        return self._open[index]

    def read(self, frame: int, columns: Sequence[str] | None = None) -> pa.RecordBatch:
        """The one-row batch of global frame index ``frame`` (only ``columns``, if given)."""
        if not -len(self) <= frame < len(self):
            raise IndexError(f"frame {frame} out of range for a cache of {len(self)} frames")
        shard, row = self._index[frame]
        return self.shard(shard).read(row, columns)

    def columns_of(self, frame: int) -> list[str]:
        """The top-level columns of the shard holding global frame index ``frame``."""
        return self.shards[self._index[frame][0]].columns

    def locate(self, frame: int) -> tuple[Path, int]:
        """The shard file and row holding global frame index ``frame``."""
        shard, row = self._index[frame]
        return self.cache_dir / self.shards[shard].path, row

    def __iter__(self) -> Iterator[pa.RecordBatch]:
        for i in range(len(self)):
            yield self.read(i)

    def scene_ids(self) -> list[str]:
        return [s.id for s in self.manifest.scenes if s.status == "complete"]

    def frames_of(self, scene_id: str) -> range:
        """Global frame indices of a scene's frames."""
        first = None
        count = 0
        for i, (shard, _row) in enumerate(self._index):
            if self.shards[shard].scene_id == scene_id:
                first = i if first is None else first
                count += 1
        if first is None:
            raise KeyError(f"{self.cache_dir}: no complete scene {scene_id!r}")
        return range(first, first + count)

    def _check_frames(self, frame: int) -> None:
        """CacheError naming the manifest if the shard holding ``frame`` does not hold frames (a
        Stage 2 latent cache holds one row per window)."""
        if not -len(self) <= frame < len(self):
            return  # read() says it is out of range
        missing = [c for c in FRAME_KEY_COLUMNS if c not in self.columns_of(frame)]
        if missing:
            raise CacheError(
                f"{self.cache_dir / MANIFEST_NAME}: a cache of source {self.manifest.source!r} whose rows "
                f"are not frames (no column {', '.join(missing)}); only frame caches (written by prep, "
                "render or generate) hold frames to read or preview"
            )

    def frame(self, frame: int, decode_truth: bool = True):  # -> records.Frame
        """The :class:`~phigenesis.data.records.Frame` record of a global frame index.

        The record validates what it is given, as it does for a source: a row holding an invalid
        value (a cache written before the scene model refused it, or a crafted one) raises a
        :class:`CacheError` naming the shard, the row and the field."""
        # the scene model and the schema (0.17 s more to import) load only when a frame is decoded
        from phigenesis.data.records import InvalidRecord
        from phigenesis.data.schema import row_to_frame

        self._check_frames(frame)
        batch = self.read(frame)
        try:
            return row_to_frame(batch, 0, decode_truth)
        except InvalidRecord as e:
            path, row = self.locate(frame)
            raise CacheError(f"{path}: row {row}: {e}") from None


# --------------------------------------------------------------------------------------------
# Verification


@dataclass
class VerifyReport:
    """What verifying a cache found: ``errors`` (damage: the cache cannot be trusted), ``warnings``
    (nothing a reader trips on), and whether the run that wrote it finished.

    ``scenes_expected``: the scenes the writing run asked for (None for a cache written before
    manifests recorded them, whose completeness cannot be known); ``unfinished``: those of them
    it has not finished (:meth:`Manifest.unfinished_scenes`); both empty where the manifest could not
    be read (:attr:`manifest_read`)."""

    cache_dir: str
    frames: int = 0
    shards: int = 0
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    scenes_expected: list[str] | None = None
    unfinished: list[str] = field(default_factory=list)
    manifest_read: bool = False  # the manifest could be read and checked

    @property
    def ok(self) -> bool:
        """No damage (an incomplete cache is still ok: what it lists is intact)."""
        return not self.errors

    @property
    def complete(self) -> bool | None:
        """Whether every expected scene is finished; None where the manifest cannot tell."""
        return None if self.scenes_expected is None else not self.unfinished

    @property
    def status(self) -> str:
        """``"DAMAGED"`` (errors), else ``"INCOMPLETE"`` (unfinished scenes), else ``"OK"``."""
        if self.errors:
            return "DAMAGED"
        return "INCOMPLETE" if self.unfinished else "OK"

    def completeness(self) -> str:
        """One line on whether the writing run finished, for the report."""
        if self.scenes_expected is None:
            return (
                "the manifest does not record which scenes its run asked for (written before manifests "
                "did): whether the cache is complete cannot be checked"
            )
        total = len(self.scenes_expected)
        if not self.unfinished:
            return f"all {total} scenes its run asked for are finished"
        missing = ", ".join(self.unfinished[:10]) + (" ..." if len(self.unfinished) > 10 else "")
        return (
            f"{total - len(self.unfinished)} of the {total} scenes its run asked for are finished "
            f"(missing: {missing}); rerunning the command that wrote it resumes it"
        )


def verify_cache(cache_dir: str | os.PathLike[str]) -> VerifyReport:
    """Re-checks a cache against its manifest: everything the reader relies on, and the hashes.

    The manifest is checked against the schema (:meth:`Manifest.load`: field types, the row
    index's shape, shard paths inside ``shards/``); then every shard's presence, size, SHA-256,
    footer CRC, Arrow structure, row count, columns and schema version, and each row's metadata
    CRC and every column's CRC, whether or not the file's SHA-256 matches (a manifest whose row
    index is wrong fails the reader as surely as a damaged file). Each problem is reported by
    shard, row and column. Then whether the run that wrote the cache finished: the scenes its
    manifest records as asked for (``scenes_expected``) against those it lists as finished
    (:attr:`VerifyReport.status`: ``DAMAGED``, ``INCOMPLETE`` or ``OK``). Never raises on a bad
    cache: problems are in the report."""
    cache_dir = Path(cache_dir)
    report = VerifyReport(str(cache_dir))
    try:
        manifest = Manifest.load(cache_dir)
    except CacheError as e:
        report.errors.append(str(e))
        return report
    report.warnings += _schema_version_warnings(cache_dir, manifest)
    report.manifest_read = True
    report.scenes_expected = manifest.scenes_expected
    report.unfinished = manifest.unfinished_scenes() or []
    for info in manifest.shards:
        report.shards += 1
        try:
            problems = _shard_problems(cache_dir, info, manifest.schema_version)
        except OSError as e:  # a file that cannot even be looked at
            problems = [f"{cache_dir / info.path}: cannot be read ({os_reason(e)})"]
        report.errors += problems
        if not problems:
            report.frames += info.rows
    report.errors += _scene_problems(manifest)
    report.warnings += [
        f"scene {scene.id}: {scene.status}" + (f" ({scene.error})" if scene.error else "")
        for scene in manifest.scenes
        if scene.status != "complete"
    ]
    report.warnings += _leftover_warnings(cache_dir, manifest)
    return report


def _schema_version_warnings(cache_dir: Path, manifest: Manifest) -> list[str]:
    # the schema (0.17 s more to import) loads only when a cache is verified
    from phigenesis.data.schema import SCHEMA_VERSION

    if manifest.schema_version == SCHEMA_VERSION:
        return []
    return [
        f"{cache_dir / MANIFEST_NAME}: schema version {manifest.schema_version}; "
        f"this toolkit writes version {SCHEMA_VERSION}"
    ]


def _shard_problems(cache_dir: Path, info: ShardInfo, schema_version: int) -> list[str]:
    """Every problem of one shard, each naming the file (and the row and column)."""
    path = cache_dir / info.path
    if not path.is_file():
        return [f"{path}: missing"]
    size = path.stat().st_size
    if size != info.bytes:
        return [f"{path}: {size} bytes, manifest says {info.bytes}"]
    digest = "SHA-256" if info.checksum == "crc32" else "whole-file CRC-32C"
    try:
        with pa.memory_map(str(path)) as mm:
            buffer = mm.read_buffer()
            if info.checksum == "crc32":
                file_ok = hashlib.sha256(memoryview(buffer)).hexdigest() == info.sha256
            else:
                file_ok = crc_of("crc32c", buffer) == info.file_crc32c
            damage = _content_problems(info, buffer, schema_version)
    except (OSError, pa.ArrowException) as e:
        return [f"{path}: cannot be read ({e})"]
    if file_ok:
        why = f"the file matches its {digest}: the manifest's index of it is wrong"
        return [f"{path}: {d} ({why})" for d in damage]
    if not damage:
        return [f"{path}: {digest} mismatch (corrupt between the checked byte ranges)"]
    return [f"{path}: {d} ({digest} mismatch: the file is corrupt)" for d in damage]


def _content_problems(info: ShardInfo, buffer: pa.Buffer, schema_version: int) -> list[str]:
    """What in a shard's bytes disagrees with its manifest entry: the footer, the Arrow
    structure (rows, columns, schema version), each row's metadata and each column's CRC."""
    problems = []
    if _crc_range(info.checksum, buffer, info.footer_start, buffer.size) != info.footer_crc32:
        problems.append(f"footer: {_crc_name(info)} mismatch")
    try:
        reader = pa.ipc.open_file(buffer)
    except pa.ArrowInvalid as e:
        return [*problems, f"not a readable Arrow IPC file ({e})"]
    version = (reader.schema.metadata or {}).get(b"phigenesis.schema_version", b"").decode(errors="replace")
    if version != str(schema_version):
        problems.append(f"schema version {version!r}, manifest says {schema_version}")
    if reader.num_record_batches != info.rows:
        problems.append(f"{reader.num_record_batches} rows, manifest says {info.rows}")
    columns_ok = reader.schema.names == info.columns
    if not columns_ok:
        problems.append(f"columns {reader.schema.names}, manifest says {info.columns}")
    for row in range(min(info.rows, reader.num_record_batches)):
        problems += _row_problems(info, reader, buffer, row, columns_ok)
    return problems


def _row_problems(
    info: ShardInfo, reader: pa.ipc.RecordBatchFileReader, buffer: pa.Buffer, row: int, columns_ok: bool
) -> list[str]:
    """The checks the reader makes on one row: its metadata CRC, then each column's CRC over the
    column's bytes (which must lie inside the row)."""
    start, (end, body_start, metadata_crc32) = info.row_start(row), info.row_index[row][:3]
    if _crc_range(info.checksum, buffer, start, body_start) != metadata_crc32:
        return [f"row {row} (metadata): {_crc_name(info)} mismatch"]
    if not columns_ok:
        return []
    try:
        ranges = column_ranges(reader.get_batch(row), buffer.address)
    except (pa.ArrowInvalid, OSError) as e:
        return [f"row {row}: does not decode ({e})"]
    problems = []
    for k, (lo, hi) in enumerate(ranges):
        where = f"row {row}, column {info.columns[k]!r}"
        if hi > lo and not start <= lo <= hi <= end:
            problems.append(f"{where}: bytes {lo}..{hi} lie outside the row ({start}..{end})")
        elif _crc_range(info.checksum, buffer, lo, hi) != info.row_index[row][3 + k]:
            problems.append(f"{where}: {_crc_name(info)} mismatch")
    return problems


def _scene_problems(manifest: Manifest) -> list[str]:
    """Complete scenes whose frame count disagrees with their shards' rows."""
    rows_of: dict[str, int] = {}
    for sh in manifest.shards:
        rows_of[sh.scene_id] = rows_of.get(sh.scene_id, 0) + sh.rows
    problems = []
    for scene in manifest.scenes:
        rows = rows_of.get(scene.id, 0)
        if scene.status == "complete" and rows != scene.frames:
            problems.append(
                f"scene {scene.id}: manifest lists {scene.frames} frames but its shards hold {rows}"
            )
    return problems


def _leftover_warnings(cache_dir: Path, manifest: Manifest) -> list[str]:
    """Files of unfinished runs: unlisted files in ``shards/`` and an overwrite's staging folder."""
    warnings = []
    listed = {Path(s.path).name for s in manifest.shards}
    shard_dir = cache_dir / SHARDS_DIR
    if shard_dir.is_dir():
        for p in sorted(shard_dir.iterdir()):
            if p.name not in listed:
                what = (
                    "unfinished temporary file" if TMP_MARKER in p.name else "file not listed in the manifest"
                )
                warnings.append(f"{p}: {what} (ignored by readers; removed by the next run writing it)")
    staging = cache_dir / STAGING_DIR
    if staging.is_dir():
        warnings.append(
            f"{staging}: the new version of an unfinished overwrite (ignored by readers; "
            "rerunning the overwrite resumes it)"
        )
    return warnings
