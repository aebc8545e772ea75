"""The shard writer's hashes are computed from the bytes as it writes them: they must equal a
re-hash of the finished files (``shards.shard_info``, which reads a file back from disk)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import google_crc32c
import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis.data import shards
from phigenesis.data.cache import checksums, files, sink, writer
from phigenesis.data.native import load_crc32c_combine
from phigenesis.data.shards import ShardInfo, ShardReader, ShardWriter

SCHEMA = pa.schema(
    [
        ("frame_index", pa.int64()),
        ("image", pa.binary()),
        ("note", pa.string()),  # null in some rows
        ("points", pa.list_(pa.float32())),
        (
            "cameras",
            pa.list_(pa.struct([("name", pa.string()), ("pose", pa.list_(pa.float64(), 16))])),
        ),
    ]
)


def rows(count: int, image_bytes: int = 10_000, seed: int = 0) -> pa.Table:
    """``count`` rows of :data:`SCHEMA` with random contents, ``image_bytes`` per image."""
    rng = np.random.default_rng(seed)
    return pa.table(
        {
            "frame_index": list(range(count)),
            "image": [rng.bytes(image_bytes) for _ in range(count)],
            "note": [None if i % 2 else f"row {i}" for i in range(count)],
            "points": [rng.random(3 * (50 + i), dtype=np.float32) for i in range(count)],
            "cameras": [
                [{"name": f"cam{k}", "pose": rng.random(16).tolist()} for k in range(1 + i % 3)]
                for i in range(count)
            ],
        },
        schema=SCHEMA,
    )


def write(cache: Path, batches: list[pa.RecordBatch], max_bytes: int) -> list[ShardInfo]:
    with ShardWriter(cache, "scene-a", SCHEMA, max_bytes) as writer:
        for batch in batches:
            writer.write(batch)
    return writer.shards


def reread(cache: Path, info: ShardInfo) -> ShardInfo:
    """The manifest entry of ``info``'s file, computed by reading the file back from disk."""
    again = shards.shard_info(cache / info.path, info.scene_id, [row[0] for row in info.row_index])
    again.path = info.path
    return again


def test_written_hashes_equal_a_rehash_of_each_shard_file_on_disk(tmp_path: Path) -> None:
    batches = rows(7).to_batches(max_chunksize=1)  # slices of one table: the IPC writer rebases them
    infos = write(tmp_path, batches, max_bytes=30_000)  # rolls over every few rows
    assert len(infos) > 1 and sum(i.rows for i in infos) == 7
    for info in infos:
        assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))
        assert info.bytes == (tmp_path / info.path).stat().st_size
        assert info.file_crc32c == shards.crc32c_file(tmp_path / info.path) and info.sha256 is None


def test_rows_larger_than_the_writers_buffer_hash_as_the_file_on_disk(tmp_path: Path) -> None:
    batches = rows(3, image_bytes=3 << 20).to_batches(max_chunksize=1)  # 3 MiB rows: the buffer grows
    (info,) = write(tmp_path, batches, max_bytes=1 << 30)
    assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))
    reader = ShardReader(tmp_path, info)  # checks the footer and each row's CRCs as it reads
    assert [reader.read(r).column("image")[0].as_py() for r in range(3)] == [
        b.column("image")[0].as_py() for b in batches
    ]


def test_the_writer_never_reads_a_shard_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the writer read a shard back")

    monkeypatch.setattr(checksums, "shard_info", refuse)
    monkeypatch.setattr(files, "crc32c_file", refuse)
    monkeypatch.setattr(Path, "read_bytes", refuse)
    monkeypatch.setattr(pa, "memory_map", refuse)
    infos = write(tmp_path, rows(4).to_batches(max_chunksize=1), max_bytes=30_000)
    monkeypatch.undo()
    for info in infos:
        assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))


def _count_fallbacks(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Counts the rows indexed by decoding (:func:`writer._row_entry`) instead of from metadata."""
    calls: list[int] = []
    decode = writer._row_entry

    def counting(*args: object, **kwargs: object) -> object:
        calls.append(1)
        return decode(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(writer, "_row_entry", counting)
    return calls


def test_rows_are_indexed_from_their_metadata_as_decoding_them_indexes_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fallbacks = _count_fallbacks(monkeypatch)
    batches = rows(9, image_bytes=20_000, seed=3).to_batches(max_chunksize=1)
    infos = write(tmp_path, batches, max_bytes=70_000)
    assert not fallbacks and len(infos) > 1  # every row (file starts included) from the metadata
    for info in infos:
        assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))


def test_a_type_the_metadata_reader_does_not_know_is_indexed_by_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fallbacks = _count_fallbacks(monkeypatch)
    schema = pa.schema([("frame_index", pa.int64()), ("nothing", pa.null())])
    table = pa.table({"frame_index": [0, 1, 2], "nothing": pa.nulls(3)}, schema=schema)
    with ShardWriter(tmp_path, "scene-a", schema, 1 << 30) as writer:
        for batch in table.to_batches(max_chunksize=1):
            writer.write(batch)
    (info,) = writer.shards
    assert len(fallbacks) == 3
    again = shards.shard_info(tmp_path / info.path, info.scene_id, [row[0] for row in info.row_index])
    again.path = info.path
    assert dataclasses.asdict(info) == dataclasses.asdict(again)


def test_short_writes_are_continued_where_they_stopped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    writev = sink.os.writev

    def short(fd: int, pieces: list[object]) -> int:  # at most 1,000 bytes a call, split mid-piece
        data = b"".join(bytes(p) for p in pieces)[:1000]  # type: ignore[call-overload]
        return writev(fd, [data])

    monkeypatch.setattr(sink.os, "writev", short)
    batches = rows(3, image_bytes=9_000).to_batches(max_chunksize=1)
    (info,) = write(tmp_path, batches, max_bytes=1 << 30)
    monkeypatch.undo()
    assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))
    reader = ShardReader(tmp_path, info)
    assert [reader.read(r).column("image")[0].as_py() for r in range(3)] == [
        b.column("image")[0].as_py() for b in batches
    ]


def test_shards_are_flushed_behind_the_writer_and_a_failed_flush_names_the_shard(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    flushed: list[int] = []
    fdatasync = sink.os.fdatasync

    def counting(fd: int) -> None:
        flushed.append(fd)
        fdatasync(fd)

    monkeypatch.setattr(sink, "FLUSH_BYTES", 15_000)
    monkeypatch.setattr(sink.os, "fdatasync", counting)
    (info,) = write(tmp_path / "a", rows(6, image_bytes=10_000).to_batches(max_chunksize=1), 1 << 30)
    assert flushed  # flushed along the way (fdatasync), not only by the closing fsync
    assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path / "a", info))

    def failing(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sink.os, "fdatasync", failing)
    with pytest.raises(shards.CacheWriteError, match=r"scene-a-00000\.arrow: cannot write .*No space left"):
        write(tmp_path / "b", rows(6, image_bytes=10_000).to_batches(max_chunksize=1), 1 << 30)
    assert list((tmp_path / "b" / shards.SHARDS_DIR).iterdir()) == []  # the unfinished file is gone


def test_the_cache_schemas_buffer_counts_are_the_ipc_buffers_of_their_columns() -> None:
    from phigenesis.data.ipc_layout import column_buffer_counts
    from phigenesis.data.schema import CacheContents, frame_schema

    every = CacheContents(depth=True, pseudo_semantics=True, range_view=True, lidar_range_image=True)
    for schema in (frame_schema(), frame_schema(every), SCHEMA):
        columns = [pa.nulls(1, f.type) for f in schema]  # every nested buffer, in pre-order
        assert column_buffer_counts(schema) == [len(c.buffers()) for c in columns]
    assert column_buffer_counts(pa.schema([("x", pa.null())])) is None


def test_a_system_without_writev_or_fdatasync_writes_the_same_shards(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    batches = rows(5, image_bytes=10_000).to_batches(max_chunksize=1)
    (expected,) = write(tmp_path / "a", batches, max_bytes=1 << 30)
    monkeypatch.delattr(sink.os, "writev")
    monkeypatch.delattr(sink.os, "fdatasync")
    monkeypatch.setattr(sink, "FLUSH_BYTES", 15_000)
    (info,) = write(tmp_path / "b", batches, max_bytes=1 << 30)
    monkeypatch.undo()
    assert dataclasses.asdict(info) == dataclasses.asdict(expected)
    assert (tmp_path / "a" / info.path).read_bytes() == (tmp_path / "b" / info.path).read_bytes()


needs_combine = pytest.mark.skipif(load_crc32c_combine() is None, reason="native data kernels not built here")


@needs_combine
@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), st.binary(max_size=300), st.binary(max_size=300))
def test_the_crc32c_combination_is_the_crc32c_of_the_concatenation(a: bytes, b: bytes, c: bytes) -> None:
    combine = load_crc32c_combine()
    assert combine is not None
    crc = google_crc32c.value
    assert combine(crc(a), crc(b), len(b)) == crc(a + b)
    assert combine(combine(crc(a), crc(b), len(b)), crc(c), len(c)) == crc(a + b + c)


@needs_combine
@pytest.mark.parametrize("length", [1 << 20, (1 << 33) + 5, (1 << 62) + 3])
def test_the_crc32c_combination_composes_over_lengths_no_test_can_write(length: int) -> None:
    combine = load_crc32c_combine()
    assert combine is not None
    x, y, z = 0x12345678, 0x9ABCDEF0, 0x0F1E2D3C
    # Shifting by lengths m then n is shifting by m + n: (x y) z == x (y z).
    assert combine(combine(x, y, length), z, 77) == combine(x, combine(y, z, 77), length + 77)
    with pytest.raises(ValueError, match="negative length"):
        combine(x, y, -1)


def _hashed_bytes(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Counts the bytes the shard writer passes to CRC-32C."""
    counted: list[int] = []
    real = google_crc32c.extend

    def extend(crc: int, data: pa.Buffer) -> int:
        counted.append(len(memoryview(data)))
        return real(crc, data)

    monkeypatch.setattr(sink, "google_crc32c", SimpleNamespace(extend=extend, value=google_crc32c.value))
    return counted


@pytest.mark.parametrize("native_combine", [True, False])
def test_the_file_crc_comes_from_the_rows_crcs_without_a_second_pass(
    native_combine: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    if native_combine and load_crc32c_combine() is None:
        pytest.skip("native data kernels not built here")
    if not native_combine:
        monkeypatch.setattr(sink, "load_crc32c_combine", lambda: None)
    hashed = _hashed_bytes(monkeypatch)
    (info,) = write(
        tmp_path, rows(5, image_bytes=200_000, seed=4).to_batches(max_chunksize=1), max_bytes=1 << 30
    )
    monkeypatch.undo()
    assert info.file_crc32c == shards.crc32c_file(tmp_path / info.path)
    assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))
    passes = sum(hashed) / info.bytes
    # Each row's metadata and columns are hashed once; the file's CRC adds only the padding
    # between them with the native combination, and a second pass over every byte without it.
    assert (1.0 <= passes < 1.01) if native_combine else (1.99 < passes < 2.01)


def test_parts_that_overlap_or_overrun_the_row_are_not_combined() -> None:
    def combine(a: int, b: int, n: int) -> int:
        return 0

    row = sink._RowBytes(0, [pa.py_buffer(b"0123456789")])
    assert sink._crc_from_parts(row, [(0, 6, 1), (5, 8, 2)], combine) is None
    assert sink._crc_from_parts(row, [(4, 11, 1)], combine) is None
    real = load_crc32c_combine()
    if real is not None:
        crc = google_crc32c.value
        parts = [(2, 5, crc(b"234")), (7, 7, 123), (8, 10, crc(b"89"))]  # gaps and an empty part
        assert sink._crc_from_parts(row, parts, real) == crc(b"0123456789")
