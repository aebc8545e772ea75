"""The cache's checksums: which CRC a shard's ranges carry, the manifest's record of a shard
(:class:`ShardInfo`), the byte range of each column of a row, and :func:`shard_info`, the
read-back reference for the checksums the writer computes as it writes.

CRC-32C for every shard this toolkit writes (:data:`SHARD_CHECKSUM`); zlib's CRC-32 with a
SHA-256 of the whole file for caches written before it, still read and verified.
"""

from __future__ import annotations

import hashlib
import logging
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import google_crc32c
import pyarrow as pa

from phigenesis.errors import CacheError

log = logging.getLogger("phigenesis.data.shards")  # the name the warning below had in shards.py

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
