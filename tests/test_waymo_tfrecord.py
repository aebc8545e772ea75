"""Waymo v1 container: TFRecord framing, masked CRC32C, corruption errors and V1File's readable prefix.

The truth here is computed independently of the library: a bit-by-bit CRC32C (Castagnoli,
reflected polynomial 0x82F63B78) and the mask formula of the TFRecord docs,
``((crc >> 15) | (crc << 17)) + 0xa282ead8`` (mod 2^32).
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from phigenesis.data.sources.waymo.raw import RawFrame, RawLabels, WaymoFormatError
from phigenesis.data.sources.waymo.tfrecord import (
    RecordSpan,
    encode_record,
    index_records,
    iter_records,
    masked_crc32c,
    read_record,
    scan_records,
    write_records,
)
from phigenesis.data.sources.waymo.v1 import V1File, serialize_frame

# --------------------------------------------------------------------------------------------
# Independent CRC32C and mask


def _crc32c_bitwise(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def _mask(crc: int) -> int:
    return ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + 0xA282EAD8) & 0xFFFFFFFF


def _unmask(masked: int) -> int:
    rot = (masked - 0xA282EAD8) & 0xFFFFFFFF
    return ((rot >> 17) | (rot << 15)) & 0xFFFFFFFF


def _record(data: bytes) -> bytes:
    """A record built by hand from the layout, with the test's own CRC."""
    length = struct.pack("<Q", len(data))
    return (
        length
        + struct.pack("<I", _mask(_crc32c_bitwise(length)))
        + data
        + struct.pack("<I", _mask(_crc32c_bitwise(data)))
    )


def _assert_names(err: pytest.ExceptionInfo[WaymoFormatError], path: Path, offset: int, *words: str) -> None:
    msg = str(err.value)
    assert str(path) in msg, msg
    assert re.search(rf"\bbyte {offset}\b", msg), f"offset {offset} not named in: {msg}"
    for w in words:
        assert w in msg, f"{w!r} not in: {msg}"


# --------------------------------------------------------------------------------------------
# CRC


def test_crc32c_reference_vectors_of_the_test_implementation() -> None:
    # The standard CRC-32C check values (RFC 3720 appendix B.4 and the "123456789" check).
    assert _crc32c_bitwise(b"123456789") == 0xE3069283
    assert _crc32c_bitwise(b"") == 0
    assert _crc32c_bitwise(bytes(32)) == 0x8A9136AA
    assert _crc32c_bitwise(b"\xff" * 32) == 0x62A8AB43


def test_masked_crc_known_vectors() -> None:
    got = masked_crc32c(b"123456789")
    assert _unmask(got) == 0xE3069283
    # The mask computed by hand: rotate right by 15, then add the delta.
    rotated = ((0xE3069283 >> 15) | (0xE3069283 << 17)) & 0xFFFFFFFF
    assert got == (rotated + 0xA282EAD8) & 0xFFFFFFFF
    assert _unmask(masked_crc32c(b"")) == 0
    assert masked_crc32c(b"") == 0xA282EAD8
    assert _unmask(masked_crc32c(bytes(32))) == 0x8A9136AA


def test_masked_crc_matches_bitwise_on_random_data_and_memoryview() -> None:
    rng = np.random.default_rng(0)
    for n in (1, 3, 8, 17, 255, 1000):
        data = rng.bytes(n)
        assert masked_crc32c(data) == _mask(_crc32c_bitwise(data))
        assert masked_crc32c(memoryview(data)) == _mask(_crc32c_bitwise(data))
    assert _unmask(_mask(0xDEADBEEF)) == 0xDEADBEEF


# --------------------------------------------------------------------------------------------
# Encoding and round trips


def test_encode_record_layout_byte_by_byte() -> None:
    data = b"waymo"
    rec = encode_record(data)
    assert len(rec) == 8 + 4 + 5 + 4
    assert rec[:8] == bytes([5, 0, 0, 0, 0, 0, 0, 0])
    assert rec[8:12] == _mask(_crc32c_bitwise(rec[:8])).to_bytes(4, "little")
    assert rec[12:17] == data
    assert rec[17:21] == _mask(_crc32c_bitwise(data)).to_bytes(4, "little")
    assert rec == _record(data)
    # An empty record: header and footer only, footer = masked CRC of nothing.
    empty = encode_record(b"")
    assert empty[:8] == bytes(8)
    assert empty[12:] == (0xA282EAD8).to_bytes(4, "little")
    assert len(empty) == 16


def test_write_iter_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    records = [b"first", b"", rng.bytes(1 << 20), b"\x00" * 7, rng.bytes(300)]
    path = tmp_path / "segment.tfrecord"
    write_records(path, iter(records))
    assert path.read_bytes() == b"".join(_record(r) for r in records)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["segment.tfrecord"]  # no temp file left

    offsets = np.cumsum([0] + [16 + len(r) for r in records])
    spans = index_records(path)
    assert spans == [RecordSpan(int(o), len(r)) for o, r in zip(offsets, records, strict=False)]
    assert spans[2].data_offset == offsets[2] + 12
    assert spans[-1].end == path.stat().st_size

    got = list(iter_records(path))
    assert [s for s, _ in got] == spans
    assert [d for _, d in got] == records
    with open(path, "rb") as f:  # random access, out of order
        assert read_record(f, path, spans[3]) == records[3]
        assert read_record(f, path, spans[0]) == records[0]


def test_empty_file_has_no_records(tmp_path: Path) -> None:
    path = tmp_path / "empty.tfrecord"
    write_records(path, [])
    assert path.stat().st_size == 0
    assert index_records(path) == []
    assert list(iter_records(path)) == []


def test_write_records_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "x.tfrecord"
    write_records(path, [b"old"])
    before = path.read_bytes()

    def failing():
        yield b"new"
        raise RuntimeError("producer failed")

    with pytest.raises(RuntimeError, match="producer failed"):
        write_records(path, failing())
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.tfrecord"]


# --------------------------------------------------------------------------------------------
# Corrupt and truncated files

RECORDS = [b"alpha" * 3, b"bravo-charlie", b"delta" * 10]


def _file(tmp_path: Path, blob: bytes, name: str = "bad.tfrecord") -> Path:
    path = tmp_path / name
    path.write_bytes(blob)
    return path


def _good() -> tuple[bytes, list[int]]:
    blob = b"".join(_record(r) for r in RECORDS)
    offsets = [0, 16 + len(RECORDS[0]), 32 + len(RECORDS[0]) + len(RECORDS[1])]
    return blob, offsets


@pytest.mark.parametrize(
    ("cut", "words"),
    [
        (5, "record header"),  # 5 of the 12 header bytes of the last record
        (12 + 7, "truncated"),  # inside the data
        (12 + len(RECORDS[2]) + 2, "truncated"),  # inside the footer
    ],
)
def test_truncated_file(tmp_path: Path, cut: int, words: str) -> None:
    blob, offsets = _good()
    path = _file(tmp_path, blob[: offsets[2] + cut])
    with pytest.raises(WaymoFormatError) as err:
        index_records(path)
    _assert_names(err, path, offsets[2], words)
    with pytest.raises(WaymoFormatError) as err:
        list(iter_records(path))
    _assert_names(err, path, offsets[2])


def test_scan_records_returns_the_readable_prefix(tmp_path: Path) -> None:
    blob, offsets = _good()
    sound = _file(tmp_path, blob, "sound.tfrecord")
    spans, error = scan_records(sound)
    assert error is None
    assert [s.offset for s in spans] == offsets
    cut = _file(tmp_path, blob[:-1], "cut.tfrecord")
    spans, error = scan_records(cut)
    assert [(s.offset, s.length) for s in spans] == [
        (offsets[0], len(RECORDS[0])),
        (offsets[1], len(RECORDS[1])),
    ]
    assert isinstance(error, WaymoFormatError)
    assert str(cut) in str(error) and re.search(rf"\bbyte {offsets[2]}\b", str(error))


def test_truncated_after_indexing_is_caught_by_read_record(tmp_path: Path) -> None:
    blob, offsets = _good()
    path = _file(tmp_path, blob)
    spans = index_records(path)
    path.write_bytes(blob[:-3])
    with open(path, "rb") as f, pytest.raises(WaymoFormatError) as err:
        read_record(f, path, spans[2])
    _assert_names(err, path, offsets[2], "truncated")


@pytest.mark.parametrize("where", [0, 3, 7, 8, 11])
def test_flipped_byte_in_header(tmp_path: Path, where: int) -> None:
    """A flip in the length (bytes 0-7) or in its CRC (8-11) of record 1."""
    blob, offsets = _good()
    bad = bytearray(blob)
    bad[offsets[1] + where] ^= 0x01
    path = _file(tmp_path, bytes(bad))
    with pytest.raises(WaymoFormatError) as err:
        index_records(path)
    _assert_names(err, path, offsets[1], "length CRC mismatch")


def test_flipped_byte_in_data(tmp_path: Path) -> None:
    blob, offsets = _good()
    bad = bytearray(blob)
    bad[offsets[1] + 12 + 4] ^= 0x20
    path = _file(tmp_path, bytes(bad))
    spans = index_records(path)  # headers are intact: indexing does not read the data
    assert [s.offset for s in spans] == offsets
    with open(path, "rb") as f:
        assert read_record(f, path, spans[0]) == RECORDS[0]
        assert read_record(f, path, spans[2]) == RECORDS[2]
        with pytest.raises(WaymoFormatError) as err:
            read_record(f, path, spans[1])
        _assert_names(err, path, offsets[1], "data CRC mismatch")
        corrupt = read_record(f, path, spans[1], check_crc=False)
    assert corrupt != RECORDS[1]
    assert corrupt == bytes(bad[offsets[1] + 12 : offsets[1] + 12 + len(RECORDS[1])])
    with pytest.raises(WaymoFormatError) as err:
        list(iter_records(path))
    _assert_names(err, path, offsets[1], "data CRC mismatch")
    assert [d for _, d in iter_records(path, check_crc=False)] == [RECORDS[0], corrupt, RECORDS[2]]


def test_flipped_byte_in_footer(tmp_path: Path) -> None:
    blob, offsets = _good()
    bad = bytearray(blob)
    bad[offsets[2] - 2] ^= 0x80  # last CRC byte of record 1
    path = _file(tmp_path, bytes(bad))
    spans = index_records(path)
    with open(path, "rb") as f, pytest.raises(WaymoFormatError) as err:
        read_record(f, path, spans[1])
    _assert_names(err, path, offsets[1], "data CRC mismatch")
    with open(path, "rb") as f:
        assert read_record(f, path, spans[1], check_crc=False) == RECORDS[1]


def test_implausible_length_with_a_valid_crc(tmp_path: Path) -> None:
    blob, offsets = _good()
    length = struct.pack("<Q", (1 << 31) + 1)
    header = length + struct.pack("<I", _mask(_crc32c_bitwise(length)))
    path = _file(tmp_path, blob[: offsets[1]] + header + b"x" * 64)
    with pytest.raises(WaymoFormatError) as err:
        index_records(path)
    _assert_names(err, path, offsets[1], "implausible record length")


PNG_BYTES = cv2.imencode(".png", np.arange(48, dtype=np.uint8).reshape(6, 8))[1].tobytes()


@pytest.mark.parametrize(
    ("blob", "words"),
    [
        (PNG_BYTES, "length CRC mismatch"),
        (b"segment_name,frame,timestamp\n" * 4, "length CRC mismatch"),
        (b"tiny", "record header"),
    ],
    ids=["png", "text", "short"],
)
def test_not_a_tfrecord(tmp_path: Path, blob: bytes, words: str) -> None:
    path = _file(tmp_path, blob, "image.png")
    with pytest.raises(WaymoFormatError) as err:
        index_records(path)
    _assert_names(err, path, 0, words)


# --------------------------------------------------------------------------------------------
# V1File


def _raw_frame(k: int) -> RawFrame:
    pose = np.eye(4)
    pose[:3, 3] = (1000.0 + k, -20.0, 3.0)
    return RawFrame(
        segment="seg_0001",
        timestamp_micros=1_550_000_000_000_000 + 100_000 * k,
        global_from_vehicle=pose,
        camera_calibrations=[],
        laser_calibrations=[],
        images=[],
        lasers=[],
        labels=RawLabels.empty(),
    )


def test_v1file_keeps_the_readable_prefix_before_a_corrupt_header(tmp_path: Path) -> None:
    blobs = [serialize_frame(_raw_frame(k)) for k in range(4)]
    path = tmp_path / "segment.tfrecord"
    write_records(path, blobs)
    good = V1File(path)
    assert len(good) == 4 and good.error is None
    offset2 = good.spans[2].offset
    assert offset2 == 2 * 16 + len(blobs[0]) + len(blobs[1])

    raw = bytearray(path.read_bytes())
    raw[offset2 + 1] ^= 0xFF  # the length of record 2
    path.write_bytes(bytes(raw))
    f = V1File(path)
    assert len(f) == 2
    assert f.error is not None
    assert str(path) in f.error
    assert re.search(rf"\bbyte {offset2}\b", f.error), f.error
    assert "length CRC mismatch" in f.error
    for k in range(2):
        frame = f.frame(k)
        assert frame.timestamp_micros == 1_550_000_000_000_000 + 100_000 * k
        assert frame.segment == "seg_0001"
        np.testing.assert_array_equal(frame.global_from_vehicle[:3, 3], (1000.0 + k, -20.0, 3.0))
        assert frame.where == f"{path} (record {k} at byte {f.spans[k].offset})"
    with pytest.raises(IndexError):
        f.frame(2)


def test_v1file_data_corruption_is_reported_on_read(tmp_path: Path) -> None:
    blobs = [serialize_frame(_raw_frame(k)) for k in range(3)]
    path = tmp_path / "segment.tfrecord"
    write_records(path, blobs)
    offset1 = 16 + len(blobs[0])
    raw = bytearray(path.read_bytes())
    raw[offset1 + 12 + len(blobs[1]) // 2] ^= 0x04
    path.write_bytes(bytes(raw))
    f = V1File(path)
    assert len(f) == 3 and f.error is None
    assert f.frame(2).timestamp_micros == 1_550_000_000_200_000
    assert f.frame(0).timestamp_micros == 1_550_000_000_000_000
    with pytest.raises(WaymoFormatError) as err:
        f.frame(1)
    _assert_names(err, path, offset1, "data CRC mismatch")


def test_v1file_errors(tmp_path: Path) -> None:
    with pytest.raises(WaymoFormatError, match="cannot read"):
        V1File(tmp_path / "missing.tfrecord")
    # A valid TFRecord whose record is not a Frame.
    path = tmp_path / "other.tfrecord"
    write_records(path, [b"\x08\x01", PNG_BYTES])
    f = V1File(path)
    assert len(f) == 2
    for k in range(2):
        with pytest.raises(WaymoFormatError) as err:
            f.frame(k)
        _assert_names(err, path, f.spans[k].offset)
