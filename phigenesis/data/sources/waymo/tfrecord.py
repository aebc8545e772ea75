"""TFRecord framing, read and written without TensorFlow, with both CRCs of every record checked.

A record is ``uint64 length | uint32 masked_crc32c(length) | data[length] | uint32
masked_crc32c(data)``, all little-endian, with ``masked(c) = ((c >> 15) | (c << 17)) + 0xa282ead8``
(mod 2^32). Files are uncompressed (Waymo's are).

:func:`index_records` scans a file's headers (checking each length CRC) without reading the
payloads; :func:`read_record` reads one payload and checks its CRC. Errors name the file and the
byte offset of the record.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import google_crc32c

from phigenesis.data.sources.waymo.raw import WaymoFormatError

_HEADER = struct.Struct("<QI")
_FOOTER = struct.Struct("<I")
HEADER_BYTES = _HEADER.size
FOOTER_BYTES = _FOOTER.size
_MASK_DELTA = 0xA282EAD8
#: Records larger than this are taken as a corrupt length (Waymo frames are a few MB).
MAX_RECORD_BYTES = 1 << 31


def masked_crc32c(data: bytes | memoryview) -> int:
    """TFRecord's masked CRC32C of ``data``."""
    crc = google_crc32c.value(bytes(data) if isinstance(data, memoryview) else data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


@dataclass(frozen=True)
class RecordSpan:
    """Where a record's payload lies: ``offset`` of its header, ``length`` of its data (bytes)."""

    offset: int
    length: int

    @property
    def data_offset(self) -> int:
        return self.offset + HEADER_BYTES

    @property
    def end(self) -> int:
        return self.offset + HEADER_BYTES + self.length + FOOTER_BYTES


def _header_error(path: Path, offset: int, what: str) -> WaymoFormatError:
    return WaymoFormatError(f"{path}: record at byte {offset}: {what}")


def _parse_header(path: Path, offset: int, header: bytes, file_size: int) -> RecordSpan:
    if len(header) < HEADER_BYTES:
        raise _header_error(path, offset, f"file ends inside the record header ({len(header)} of 12 bytes)")
    length, length_crc = _HEADER.unpack(header)
    if masked_crc32c(header[:8]) != length_crc:
        raise _header_error(path, offset, "length CRC mismatch (the file is corrupt, or not a TFRecord file)")
    if length > MAX_RECORD_BYTES:
        raise _header_error(path, offset, f"implausible record length {length}")
    span = RecordSpan(offset, length)
    if span.end > file_size:
        raise _header_error(
            path,
            offset,
            f"file is truncated: the record needs {span.end - offset} bytes, {file_size - offset} remain",
        )
    return span


def scan_records(path: str | os.PathLike[str]) -> tuple[list[RecordSpan], WaymoFormatError | None]:
    """The records of a TFRecord file from their headers only (length CRCs checked), up to the
    first bad header: ``(spans, error)`` with ``error`` None if the whole file is sound.

    A bad header (corrupt length, a file that ends inside a record, not a TFRecord) stops the scan
    there, since later offsets cannot be trusted; the records before it stay readable.
    """
    path = Path(path)
    size = path.stat().st_size
    spans: list[RecordSpan] = []
    with open(path, "rb") as f:
        offset = 0
        while offset < size:
            f.seek(offset)
            try:
                span = _parse_header(path, offset, f.read(HEADER_BYTES), size)
            except WaymoFormatError as e:
                return spans, e
            spans.append(span)
            offset = span.end
    return spans, None


def index_records(path: str | os.PathLike[str]) -> list[RecordSpan]:
    """The records of a TFRecord file, from their headers only (length CRCs checked).

    Raises :class:`WaymoFormatError` naming the file and offset if a header is corrupt or the file
    ends inside a record (a truncated download).
    """
    spans, error = scan_records(path)
    if error is not None:
        raise error
    return spans


def read_record(f: BinaryIO, path: str | os.PathLike[str], span: RecordSpan, check_crc: bool = True) -> bytes:
    """The payload of the record at ``span`` in the open file ``f`` (data CRC checked)."""
    f.seek(span.data_offset)
    blob = f.read(span.length + FOOTER_BYTES)
    if len(blob) != span.length + FOOTER_BYTES:
        raise _header_error(Path(path), span.offset, "file is truncated inside the record's data")
    data = blob[: span.length]
    if check_crc:
        (want,) = _FOOTER.unpack_from(blob, span.length)
        if masked_crc32c(data) != want:
            raise _header_error(
                Path(path), span.offset, f"data CRC mismatch over {span.length} bytes (the record is corrupt)"
            )
    return data


def iter_records(path: str | os.PathLike[str], check_crc: bool = True) -> Iterator[tuple[RecordSpan, bytes]]:
    """Every record of a file in order, as (span, payload)."""
    spans = index_records(path)
    with open(path, "rb") as f:
        for span in spans:
            yield span, read_record(f, path, span, check_crc)


def encode_record(data: bytes) -> bytes:
    """One record's bytes (header, data, footer)."""
    header = struct.pack("<Q", len(data))
    return header + struct.pack("<I", masked_crc32c(header)) + data + _FOOTER.pack(masked_crc32c(data))


def write_records(path: str | os.PathLike[str], records: Iterable[bytes]) -> None:
    """Writes a TFRecord file atomically (a temporary name, then renamed into place)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            for data in records:
                f.write(encode_record(data))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
