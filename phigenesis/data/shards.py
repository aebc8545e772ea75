"""Sharded Arrow IPC caches: an atomic writer, the manifest, a random-access reader and a verifier.

Layout of a cache directory::

    manifest.json          what the cache holds (written last, atomically)
    shards/<scene>-00000.arrow  Arrow IPC files, one row per frame, one record batch per row

Integrity: the manifest records each shard's size and SHA-256 and, for every record batch (row),
where it ends, where its body starts, the CRC-32 of its metadata and the CRC-32 of each top-level
column's bytes, plus the CRC-32 of the file footer. The reader checks a shard's size and footer
when it opens it, and a row's metadata and the columns it returns when it reads the row: a flipped
byte in anything a caller reads raises an error naming the shard, row and column, and reading only
the images of a frame never hashes its LiDAR. :func:`verify_cache` re-hashes everything.

Atomicity: every file is written under a temporary name, flushed with fsync and renamed; the
manifest is rewritten the same way after each scene completes. A killed run leaves only complete
files under final names, and the manifest lists only scenes whose shards are all complete.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import uuid
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

from phigenesis.errors import CacheError

MANIFEST_NAME = "manifest.json"
SHARDS_DIR = "shards"
CACHE_FORMAT = "phigenesis-cache"
DEFAULT_SHARD_MAX_BYTES = 256 * 1024 * 1024
TMP_MARKER = ".tmp-"


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
    """Writes ``data`` to ``path`` via a temporary file, fsync and rename."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}{TMP_MARKER}{uuid.uuid4().hex[:8]}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


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
        sha256: hex digest of the whole file.
        columns: the top-level columns, in schema order.
        row_index: per row ``[end, body_start, metadata_crc32, crc32 of each column...]``: the byte
            offset where the row's record batch ends, where its body (the column buffers) starts,
            the CRC-32 of the bytes from the row's start to its body, and of each column's bytes.
        footer_crc32: CRC-32 of the bytes from the last row's end to the end of the file.
    """

    path: str
    scene_id: str
    rows: int
    bytes: int
    sha256: str
    columns: list[str] = field(default_factory=list)
    row_index: list[list[int]] = field(default_factory=list)
    footer_crc32: int = 0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ShardInfo:
        keys = ("path", "scene_id", "rows", "bytes", "sha256", "columns", "row_index", "footer_crc32")
        return cls(**{k: d[k] for k in keys})

    def row_start(self, row: int) -> int:
        return 0 if row == 0 else self.row_index[row - 1][0]


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


class ShardWriter:
    """Writes one scene's rows into Arrow IPC shards of bounded size, atomically.

    Rows are written one record batch each; a shard is closed and a new one started once it
    exceeds ``max_bytes``. Each shard is renamed to its final name only when complete; the list of
    complete shards comes back from :meth:`close`. Use as a context manager: on an exception the
    unfinished temporary file is removed.
    """

    def __init__(
        self, cache_dir: Path, scene_id: str, schema: pa.Schema, max_bytes: int = DEFAULT_SHARD_MAX_BYTES
    ):
        self.cache_dir = Path(cache_dir)
        self.scene_id = scene_id
        self.schema = schema
        self.max_bytes = int(max_bytes)
        self.shards: list[ShardInfo] = []
        self._sink: pa.NativeFile | None = None
        self._writer: pa.ipc.RecordBatchFileWriter | None = None
        self._tmp: Path | None = None
        self._ends: list[int] = []
        (self.cache_dir / SHARDS_DIR).mkdir(parents=True, exist_ok=True)

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
        """Appends a one-row batch of this writer's schema."""
        if not batch.schema.equals(self.schema):
            raise ValueError(f"scene {self.scene_id}: batch schema differs from the cache schema")
        if self._writer is None:
            final = self._final_path(len(self.shards))
            self._tmp = final.with_name(f"{final.name}{TMP_MARKER}{uuid.uuid4().hex[:8]}")
            self._sink = pa.OSFile(str(self._tmp), "wb")
            self._writer = pa.ipc.new_file(self._sink, self.schema)
            self._ends = []
        self._writer.write_batch(batch)
        self._ends.append(self._sink.tell())
        if self._ends[-1] >= self.max_bytes:
            self._finish_shard()

    def _finish_shard(self) -> None:
        assert self._writer is not None and self._sink is not None and self._tmp is not None
        self._writer.close()
        self._sink.close()
        with open(self._tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        final = self._final_path(len(self.shards))
        info = shard_info(self._tmp, self.scene_id, self._ends)
        os.replace(self._tmp, final)
        fsync_dir(final.parent)
        info.path = final.relative_to(self.cache_dir).as_posix()
        self.shards.append(info)
        self._writer = self._sink = self._tmp = None

    def close(self) -> list[ShardInfo]:
        """Completes the open shard; returns every complete shard of this writer."""
        if self._writer is not None:
            self._finish_shard()
        return self.shards

    def abort(self) -> None:
        """Drops the unfinished shard (complete shards stay, unlisted until a manifest names them)."""
        with contextlib.suppress(OSError, pa.ArrowException):  # already failing; drop the file below
            if self._writer is not None:
                self._writer.close()
            if self._sink is not None:
                self._sink.close()
        if self._tmp is not None:
            self._tmp.unlink(missing_ok=True)
        self._writer = self._sink = self._tmp = None


def shard_info(path: Path, scene_id: str, row_ends: list[int]) -> ShardInfo:
    """Size, SHA-256 and the per-row, per-column CRC index of a finished shard file.

    ``row_ends`` are the file positions after each record batch, as the writer saw them.
    """
    data = Path(path).read_bytes()
    buffer = pa.py_buffer(data)
    reader = pa.ipc.open_file(buffer)
    view = memoryview(data)
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
            [end, body_start, zlib.crc32(view[start:body_start])]
            + [zlib.crc32(view[lo:hi]) for lo, hi in ranges]
        )
        start = end
    return ShardInfo(
        path=Path(path).name,
        scene_id=scene_id,
        rows=reader.num_record_batches,
        bytes=len(data),
        sha256=hashlib.sha256(data).hexdigest(),
        columns=list(reader.schema.names),
        row_index=row_index,
        footer_crc32=zlib.crc32(view[start:]),
    )


def safe_name(scene_id: str) -> str:
    """A file-name-safe form of a scene id."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in scene_id)


# --------------------------------------------------------------------------------------------
# Manifest


@dataclass
class SceneEntry:
    """A scene as the manifest records it: ``complete`` (all its frames are in listed shards) or
    ``skipped`` (it failed and the run went on; ``error`` says why)."""

    id: str
    source: str
    frames: int
    status: str
    shards: list[str] = field(default_factory=list)
    error: str | None = None


@dataclass
class Manifest:
    """The index of a cache: what made it, its scenes and its shard files.

    ``fingerprint`` is a hash of everything that determines the rows (source, its arguments, the
    pipeline spec, the schema version); a rerun into the same directory must match it.
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

    def scene(self, scene_id: str) -> SceneEntry | None:
        for s in self.scenes:
            if s.id == scene_id:
                return s
        return None

    def record_scene(self, entry: SceneEntry, shards: list[ShardInfo]) -> None:
        """Adds or replaces a scene and its shards."""
        self.scenes = [s for s in self.scenes if s.id != entry.id] + [entry]
        self.shards = [s for s in self.shards if s.scene_id != entry.id] + list(shards)

    def to_json(self) -> str:
        d = asdict(self)
        return json.dumps(d, indent=1, sort_keys=False)

    def save(self, cache_dir: Path) -> None:
        atomic_write_bytes(Path(cache_dir) / MANIFEST_NAME, self.to_json().encode())

    @classmethod
    def load(cls, cache_dir: Path) -> Manifest:
        """Reads ``cache_dir/manifest.json``; raises :class:`CacheError` naming the file if it is
        missing, truncated or malformed."""
        path = Path(cache_dir) / MANIFEST_NAME
        if not path.is_file():
            raise CacheError(f"{path}: no manifest; {cache_dir} is not a phigenesis cache")
        text = path.read_text(errors="replace")
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise CacheError(
                f"{path}: manifest is truncated or not valid JSON "
                f"({e.msg} at line {e.lineno}, column {e.colno}; {len(text)} bytes)"
            ) from e
        try:
            if d.get("format") != CACHE_FORMAT:
                raise CacheError(f"{path}: not a {CACHE_FORMAT} manifest (format={d.get('format')!r})")
            return cls(
                schema_version=int(d["schema_version"]),
                source=d["source"],
                arguments=d["arguments"],
                pipeline=d["pipeline"],
                fingerprint=d["fingerprint"],
                scenes=[SceneEntry(**s) for s in d["scenes"]],
                shards=[ShardInfo.from_dict(s) for s in d["shards"]],
                format=d["format"],
                phigenesis_version=d.get("phigenesis_version", ""),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise CacheError(f"{path}: manifest is malformed ({type(e).__name__}: {e})") from e

    def complete_shards(self) -> list[ShardInfo]:
        """Shards of complete scenes, in scene order then shard order."""
        done = [s.id for s in self.scenes if s.status == "complete"]
        by_scene: dict[str, list[ShardInfo]] = {}
        for sh in self.shards:
            by_scene.setdefault(sh.scene_id, []).append(sh)
        return [sh for sid in done for sh in by_scene.get(sid, [])]


# --------------------------------------------------------------------------------------------
# Reader


class ShardReader:
    """Random access to the rows of one shard, checking the manifest's CRCs of what it returns."""

    def __init__(self, cache_dir: Path, info: ShardInfo, check_crc: bool = True):
        self.info = info
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
        self._view = memoryview(self._buffer)
        if check_crc and info.rows:
            self._check(info.row_index[-1][0], info.bytes, info.footer_crc32, "the footer")
        try:
            self._reader = pa.ipc.open_file(self._buffer)
        except (pa.ArrowInvalid, OSError) as e:
            raise CacheError(f"{self.path}: not a readable Arrow IPC file ({e})") from e
        if self._reader.num_record_batches != info.rows:
            raise CacheError(
                f"{self.path}: holds {self._reader.num_record_batches} rows, the manifest says {info.rows}"
            )
        self._column_index = {name: i for i, name in enumerate(info.columns)}

    def _check(self, start: int, end: int, expected: int, what: str) -> None:
        if zlib.crc32(self._view[start:end]) != expected:
            raise CacheError(f"{self.path}: {what} is corrupt (CRC-32 mismatch in bytes {start}..{end})")

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
        if self.check_crc:
            self._check(self.info.row_start(row), entry[1], entry[2], f"row {row} (metadata)")
        try:
            batch = self._reader.get_batch(row)
        except (pa.ArrowInvalid, OSError) as e:
            raise CacheError(f"{self.path}: row {row} does not decode ({e})") from e
        if self.check_crc:
            for name in names:
                k = self._column_index[name]
                lo, hi = column_range(batch.column(k), self._buffer.address)
                self._check(lo, hi, entry[3 + k], f"row {row}, column {name!r}")
        return batch if columns is None else batch.select(names)

    @property
    def schema(self) -> pa.Schema:
        return self._reader.schema


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

    def frame(self, frame: int, decode_truth: bool = True):  # -> records.Frame
        """The :class:`~phigenesis.data.records.Frame` record of a global frame index."""
        from phigenesis.data.schema import row_to_frame

        return row_to_frame(self.read(frame), 0, decode_truth)


# --------------------------------------------------------------------------------------------
# Verification


@dataclass
class VerifyReport:
    """Problems found in a cache: ``errors`` make it unusable, ``warnings`` do not."""

    cache_dir: str
    frames: int = 0
    shards: int = 0
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors


def _locate_damage(path: Path, info: ShardInfo) -> list[str]:
    """Which rows, columns or footer of a shard fail their CRCs (for a shard whose hash is wrong)."""
    data = path.read_bytes()
    view = memoryview(data)
    buffer = pa.py_buffer(data)
    bad = []
    try:
        reader = (
            pa.ipc.open_file(buffer)
            if zlib.crc32(view[info.row_index[-1][0] :]) == info.footer_crc32
            else None
        )
    except pa.ArrowInvalid:
        reader = None
    if reader is None:
        bad.append("footer")
    for row, entry in enumerate(info.row_index):
        if zlib.crc32(view[info.row_start(row) : entry[1]]) != entry[2]:
            bad.append(f"row {row} (metadata)")
            continue
        if reader is None:
            continue
        ranges = column_ranges(reader.get_batch(row), buffer.address)
        for k, (lo, hi) in enumerate(ranges):
            if zlib.crc32(view[lo:hi]) != entry[3 + k]:
                bad.append(f"row {row}, column {info.columns[k]!r}")
    return bad or ["bytes between buffers"]


def verify_cache(cache_dir: str | os.PathLike[str]) -> VerifyReport:
    """Re-checks every shard of a cache against its manifest: presence, size, SHA-256, each row's
    CRC, Arrow structure, row counts and the schema version. Names every bad file."""
    cache_dir = Path(cache_dir)
    report = VerifyReport(str(cache_dir))
    try:
        manifest = Manifest.load(cache_dir)
    except CacheError as e:
        report.errors.append(str(e))
        return report
    listed = set()
    for info in manifest.shards:
        path = cache_dir / info.path
        listed.add(path.resolve())
        report.shards += 1
        if not path.is_file():
            report.errors.append(f"{path}: missing")
            continue
        size = path.stat().st_size
        if size != info.bytes:
            report.errors.append(f"{path}: {size} bytes, manifest says {info.bytes}")
            continue
        if sha256_file(path) != info.sha256:
            report.errors.append(
                f"{path}: SHA-256 mismatch (corrupt: {', '.join(_locate_damage(path, info))})"
            )
            continue
        try:
            with pa.memory_map(str(path)) as mm:
                reader = pa.ipc.open_file(mm)
                version = (reader.schema.metadata or {}).get(b"phigenesis.schema_version", b"").decode()
                if reader.num_record_batches != info.rows:
                    report.errors.append(
                        f"{path}: {reader.num_record_batches} rows, manifest says {info.rows}"
                    )
                if version != str(manifest.schema_version):
                    report.errors.append(
                        f"{path}: schema version {version!r}, manifest says {manifest.schema_version}"
                    )
        except (pa.ArrowInvalid, OSError) as e:
            report.errors.append(f"{path}: not a readable Arrow IPC file ({e})")
            continue
        report.frames += info.rows
    for scene in manifest.scenes:
        if scene.status != "complete":
            report.warnings.append(
                f"scene {scene.id}: {scene.status}" + (f" ({scene.error})" if scene.error else "")
            )
            continue
        rows = sum(s.rows for s in manifest.shards if s.scene_id == scene.id)
        if rows != scene.frames:
            report.errors.append(
                f"scene {scene.id}: manifest lists {scene.frames} frames but its shards hold {rows}"
            )
    shard_dir = cache_dir / SHARDS_DIR
    if shard_dir.is_dir():
        for p in sorted(shard_dir.iterdir()):
            if p.resolve() not in listed:
                what = (
                    "unfinished temporary file" if TMP_MARKER in p.name else "file not listed in the manifest"
                )
                report.warnings.append(f"{p}: {what} (ignored by readers; removed by the next prep run)")
    return report
