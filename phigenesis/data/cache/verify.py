"""Verification of a whole cache against its manifest (:func:`verify_cache`): every shard's size,
digest, footer, Arrow structure and every row's and column's CRC, then whether the run that wrote
it finished. Problems are reported by shard, row and column, never raised.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa

from phigenesis.data.cache.checksums import ShardInfo, _crc_name, _crc_range, column_ranges, crc_of
from phigenesis.data.cache.files import MANIFEST_NAME, SHARDS_DIR, STAGING_DIR, TMP_MARKER, os_reason
from phigenesis.data.cache.manifest import Manifest
from phigenesis.errors import CacheError


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
