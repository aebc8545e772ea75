"""A cache directory is untrusted input, and a prep run is one writer that never loses a cache.

Crafted manifests (paths outside the cache, every kind of malformed field), verify on caches the
reader rejects, two writers on one directory, a lock left by a killed run, an overwrite with a bad
input or killed part-way, a full disk, dropped values, the pipeline-name lookup and interrupts.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest
import yaml

from phigenesis import prep
from phigenesis.data import cache_run, shards
from phigenesis.data.cache_lock import LOCK_NAME, CacheLock, LockHolder
from phigenesis.data.loader import FrameDataset
from phigenesis.data.pipeline import (
    PipelineSpec,
    PrepError,
    PrepInterrupted,
    StageSpec,
    load_pipeline,
)
from phigenesis.data.records import Scene
from phigenesis.data.shards import (
    MANIFEST_NAME,
    SHARDS_DIR,
    STAGING_DIR,
    TMP_MARKER,
    CacheError,
    CacheReader,
    CacheWriteError,
    Manifest,
    ShardReader,
    ShardWriter,
    verify_cache,
)
from phigenesis.data.stages import STAGES, register_stage
from tests.conftest import TINY_PREP_ARGS

SCENE_IDS = [f"synthetic-s{TINY_PREP_ARGS['seed']}-{i:04d}" for i in range(TINY_PREP_ARGS["scenes"])]
#: A run with other arguments than the tiny cache's (so it is an overwrite), and quick.
OTHER_ARGS: dict[str, Any] = {**TINY_PREP_ARGS, "scenes": 1, "frames": 1, "seed": 8}
ENOSPC_REASON = os.strerror(errno.ENOSPC)


# --------------------------------------------------------------------------------------------
# Helpers


def copy_cache(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def read_manifest(cache: Path) -> Any:
    return json.loads((cache / MANIFEST_NAME).read_text())


def write_manifest(cache: Path, document: Any) -> None:
    (cache / MANIFEST_NAME).write_text(json.dumps(document))


def file_state(root: Path) -> dict[str, tuple[str, int]]:
    """Every file under ``root`` with its SHA-256 and mtime."""
    return {
        p.relative_to(root).as_posix(): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def row_keys(cache: Path) -> list[tuple[str, int]]:
    return [(b.column("scene_id")[0].as_py(), b.column("frame_index")[0].as_py()) for b in CacheReader(cache)]


def leftovers(cache: Path) -> list[str]:
    """Temporary files and unlisted shards anywhere in a cache directory."""
    listed = {Path(s.path).name for s in Manifest.load(cache).shards}
    found = [p for p in cache.rglob("*") if TMP_MARKER in p.name]
    shard_dir = cache / SHARDS_DIR
    found += [p for p in shard_dir.iterdir() if p.name not in listed] if shard_dir.is_dir() else []
    return sorted(p.relative_to(cache).as_posix() for p in found)


def spec_with(*stages: StageSpec) -> PipelineSpec:
    return dataclasses.replace(load_pipeline("synthetic"), stages=stages)


@pytest.fixture(scope="module")
def bare_spec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic pipeline without stages, as a spec file: quick runs for other processes."""
    path = tmp_path_factory.mktemp("spec") / "bare.yaml"
    path.write_text(yaml.safe_dump(spec_with().to_dict()))
    return path


def python(script: str, *args: str, cwd: Path | None = None) -> subprocess.Popen[str]:
    """Starts ``script`` in a new Python process (stdout piped, text mode)."""
    return subprocess.Popen(
        [sys.executable, "-c", script, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
    )


def wait_for(condition: Callable[[], bool], proc: subprocess.Popen[str], timeout_s: float = 120) -> bool:
    """Polls ``condition`` until it holds (True) or ``proc`` ends or the time is up (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        if proc.poll() is not None:
            return condition()
        time.sleep(0.01)
    return False


def complete_scenes(cache: Path) -> list[str]:
    """Complete scenes of the manifest on disk now ([] while it is missing or being replaced)."""
    try:
        d = json.loads((cache / MANIFEST_NAME).read_text())
    except (OSError, ValueError):
        return []
    return [s["id"] for s in d["scenes"] if s["status"] == "complete"]


# --------------------------------------------------------------------------------------------
# Paths a manifest names must stay inside the cache's shards/ folder


def outside_paths(cache: Path, outside: Path) -> dict[str, str]:
    """Shard paths that name ``outside`` (a file beside the cache), in each way a manifest can."""
    return {
        "relative": os.path.relpath(outside, cache),
        "absolute": str(outside),
        "dot-dot inside shards": f"{SHARDS_DIR}/../../{outside.name}",
    }


@pytest.mark.parametrize("form", ["relative", "absolute", "dot-dot inside shards"])
def test_overwrite_never_deletes_a_file_outside_the_cache_that_a_manifest_names(
    tiny_cache: Path, tmp_path: Path, form: str
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    precious = tmp_path / "precious.txt"
    precious.write_text("keep me")
    d = read_manifest(cache)
    d["shards"][0]["path"] = outside_paths(cache, precious)[form]
    d["scenes"][0]["shards"] = [d["shards"][0]["path"]]
    write_manifest(cache, d)

    prep.synthetic(cache, overwrite=True, progress=False, **OTHER_ARGS)

    assert precious.read_text() == "keep me"
    assert row_keys(cache) == [("synthetic-s8-0000", 0)]
    report = verify_cache(cache)
    assert report.ok and report.warnings == [], report.errors + report.warnings


@pytest.mark.parametrize("form", ["relative", "absolute", "dot-dot inside shards", "symbolic link"])
def test_reader_loader_and_verify_refuse_a_shard_outside_the_cache_naming_the_manifest_and_path(
    tiny_cache: Path, tmp_path: Path, form: str
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    d = read_manifest(cache)
    first = cache / d["shards"][0]["path"]
    outside = tmp_path / "outside.arrow"  # a sound shard, so that reading it would succeed
    shutil.copy(first, outside)
    if form == "symbolic link":
        first.unlink()
        first.symlink_to(outside)
        path = d["shards"][0]["path"]
    else:
        path = outside_paths(cache, outside)[form]
    d["shards"][0]["path"] = path
    d["scenes"][0]["shards"] = [path]
    write_manifest(cache, d)
    expected = f"{cache / MANIFEST_NAME}: shards[0].path: {path!r}"

    with pytest.raises(CacheError) as reader_error:
        CacheReader(cache).read(0)
    assert str(reader_error.value).startswith(expected)
    with pytest.raises(CacheError, match=r"shards\[0\]\.path"):
        FrameDataset(cache)[0]
    report = verify_cache(cache)
    assert not report.ok
    assert len(report.errors) == 1 and report.errors[0].startswith(expected), report.errors


def test_a_shard_reader_refuses_a_path_outside_the_shards_folder(tiny_cache: Path) -> None:
    info = dataclasses.replace(Manifest.load(tiny_cache).shards[0], path=f"../{tiny_cache.name}/x.arrow")
    with pytest.raises(CacheError, match=r"is not a file directly in shards/"):
        ShardReader(tiny_cache, info)


def test_prep_refuses_a_shards_folder_that_links_out_of_the_cache_and_deletes_nothing(
    tiny_cache: Path, tmp_path: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    elsewhere = tmp_path / "elsewhere"
    (cache / SHARDS_DIR).rename(elsewhere)
    (cache / SHARDS_DIR).symlink_to(elsewhere)
    before = file_state(elsewhere)
    with pytest.raises(PrepError, match=rf"{SHARDS_DIR} is a symbolic link"):
        prep.synthetic(cache, overwrite=True, progress=False, **OTHER_ARGS)
    assert file_state(elsewhere) == before


# --------------------------------------------------------------------------------------------
# The manifest is checked against the schema, once, with one error naming the file and field


def _shard0(d: Any) -> Any:
    return d["shards"][0]


def _dropping_last_row(d: Any) -> Any:
    _shard0(d)["row_index"] = _shard0(d)["row_index"][:-1]
    return d


def _setting(where: Callable[[Any], Any], key: Any, value: Any) -> Callable[[Any], Any]:
    def edit(d: Any) -> Any:
        where(d)[key] = value
        return d

    return edit


def _appending(where: Callable[[Any], Any], value: Callable[[Any], Any]) -> Callable[[Any], Any]:
    def edit(d: Any) -> Any:
        where(d).append(value(d))
        return d

    return edit


def _deleting(where: Callable[[Any], Any], key: str) -> Callable[[Any], Any]:
    def edit(d: Any) -> Any:
        del where(d)[key]
        return d

    return edit


def _row(r: int) -> Callable[[Any], Any]:
    return lambda d: _shard0(d)["row_index"][r]


def _previous_end(d: Any) -> Any:
    _row(1)(d)[0] = _row(0)(d)[0]
    return d


def _body_before_row(d: Any) -> Any:
    _row(1)(d)[1] = _row(0)(d)[0] - 1
    return d


def _row_1_one_value_short(d: Any) -> Any:
    _shard0(d)["row_index"][1] = _row(1)(d)[:-1]
    return d


def _end_past_file(d: Any) -> Any:
    _row(-1)(d)[0] = _shard0(d)["bytes"] + 1
    return d


BAD_MANIFESTS: dict[str, tuple[Callable[[Any], Any], str]] = {
    "an array": (lambda d: [], "the manifest is [], not a JSON object"),
    "null": (lambda d: None, "the manifest is null, not a JSON object"),
    "a string": (lambda d: "cache", 'the manifest is "cache", not a JSON object'),
    "a shard listed twice": (
        _appending(lambda d: d["shards"], lambda d: dict(_shard0(d))),
        f"shards[2].path: 'shards/{SCENE_IDS[0]}-00000.arrow' is listed twice (also shards[0])",
    ),
    "a scene listed twice": (
        _appending(lambda d: d["scenes"], lambda d: dict(d["scenes"][0])),
        f"scenes[2].id: '{SCENE_IDS[0]}' is listed twice (also scenes[0])",
    ),
    "negative rows": (_setting(_shard0, "rows", -1), "shards[0].rows: -1 is not a non-negative integer"),
    "rows as a string": (_setting(_shard0, "rows", "3"), 'shards[0].rows: "3" is not a non-negative integer'),
    "rows as a boolean": (
        _setting(_shard0, "rows", True),
        "shards[0].rows: true is not a non-negative integer",
    ),
    "a shortened row index": (_dropping_last_row, "shards[0].row_index: 2 entries, but the shard has 3 rows"),
    "an empty row index": (
        _setting(_shard0, "row_index", []),
        "shards[0].row_index: 0 entries, but the shard has 3 rows",
    ),
    "a string row index": (
        _setting(_shard0, "row_index", "abc"),
        'shards[0].row_index: "abc" is not an array',
    ),
    "a negative row end": (
        _setting(_row(0), 0, -5),
        "shards[0].row_index[0][0]: -5 is not a non-negative integer",
    ),
    "a row of the wrong width": (_row_1_one_value_short, "integers (end, body start, metadata CRC and"),
    "row ends not increasing": (_previous_end, "shards[0].row_index[1][0]: row end"),
    "a row end past the file": (_end_past_file, "is past the end of the file"),
    "a body start outside its row": (_body_before_row, "shards[0].row_index[1][1]: body start"),
    "a CRC of more than 32 bits": (
        _setting(_row(0), 2, 1 << 32),
        "shards[0].row_index[0][2]: 4294967296 is not an integer in [0, 4294967295]",
    ),
    "a negative footer CRC": (
        _setting(_shard0, "footer_crc32", -1),
        "shards[0].footer_crc32: -1 is not an integer in [0, 4294967295]",
    ),
    "a file CRC of more than 32 bits": (
        _setting(_shard0, "file_crc32c", 1 << 32),
        "shards[0].file_crc32c: 4294967296 is not an integer in [0, 4294967295]",
    ),
    "an unknown checksum": (
        _setting(_shard0, "checksum", "md5"),
        'shards[0].checksum: "md5" is not one of',
    ),
    "a legacy entry's SHA-256 that is not hex": (
        lambda d: (_shard0(d).update(checksum="crc32", sha256="xyz"), d)[1],
        'shards[0].sha256: "xyz" is not a SHA-256 hex digest',
    ),
    "a missing field": (_deleting(_shard0, "bytes"), "shards[0].bytes: missing"),
    "a shard that is not an object": (_setting(lambda d: d["shards"], 0, 5), "shards[0]: 5 is not an object"),
    "shards that are not an array": (
        _setting(lambda d: d, "shards", {"a": 1}),
        'shards: {"a": 1} is not an array',
    ),
    "a shard of an unknown scene": (
        _setting(_shard0, "scene_id", "ghost"),
        "shards[0].scene_id: 'ghost' is not a scene of the manifest",
    ),
    "a scene naming a shard that is not listed": (
        _appending(lambda d: d["scenes"][0]["shards"], lambda d: "shards/nope.arrow"),
        "scenes[0].shards[1]: 'shards/nope.arrow' is not a shard of the manifest",
    ),
    "an unknown scene status": (
        _setting(lambda d: d["scenes"][0], "status", "done"),
        'scenes[0].status: "done" is not one of complete, skipped, failed',
    ),
    "negative frames": (
        _setting(lambda d: d["scenes"][0], "frames", -3),
        "scenes[0].frames: -3 is not a non-negative integer",
    ),
    "a negative dropped count": (
        _setting(lambda d: d["scenes"][0], "dropped", {"LiDAR points": -1}),
        "scenes[0].dropped['LiDAR points']: -1 is not a non-negative integer",
    ),
    "a schema version as a string": (
        _setting(lambda d: d, "schema_version", "5"),
        'schema_version: "5" is not an integer of at least 1',
    ),
    "arguments that are not an object": (
        _setting(lambda d: d, "arguments", [1]),
        "arguments: [1] is not an object",
    ),
}


def bad_manifest(tiny_cache: Path, tmp_path: Path, case: str) -> tuple[Path, str]:
    """A copy of the tiny cache with the manifest ``case`` of BAD_MANIFESTS, and the message
    its error must carry."""
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    edit, message = BAD_MANIFESTS[case]
    write_manifest(cache, edit(read_manifest(cache)))
    return cache, message


@pytest.mark.parametrize("case", list(BAD_MANIFESTS))
def test_a_malformed_manifest_is_refused_with_one_error_naming_the_file_and_field(
    tiny_cache: Path, tmp_path: Path, case: str
) -> None:
    cache, message = bad_manifest(tiny_cache, tmp_path, case)
    with pytest.raises(CacheError) as error:
        Manifest.load(cache)
    text = str(error.value)
    assert text.startswith(f"{cache / MANIFEST_NAME}: "), text
    assert message in text
    with pytest.raises(CacheError, match=MANIFEST_NAME):
        CacheReader(cache)


@pytest.mark.parametrize("case", list(BAD_MANIFESTS))
def test_verify_reports_a_malformed_manifest_without_raising(
    tiny_cache: Path, tmp_path: Path, case: str
) -> None:
    cache, message = bad_manifest(tiny_cache, tmp_path, case)
    report = verify_cache(cache)
    assert not report.ok
    assert len(report.errors) == 1, report.errors
    assert report.errors[0].startswith(f"{cache / MANIFEST_NAME}: ") and message in report.errors[0]


def test_a_row_of_the_wrong_width_is_named_with_the_width_expected(tiny_cache: Path, tmp_path: Path) -> None:
    cache, _ = bad_manifest(tiny_cache, tmp_path, "a row of the wrong width")
    columns = len(read_manifest(cache)["shards"][0]["columns"])
    with pytest.raises(CacheError, match=rf"row_index\[1\]: .* is not {3 + columns} integers"):
        Manifest.load(cache)


def test_a_manifest_without_dropped_counts_still_loads_with_none(tiny_cache: Path, tmp_path: Path) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    d = read_manifest(cache)
    for scene in d["scenes"]:
        scene.pop("dropped", None)
    write_manifest(cache, d)
    assert [s.dropped for s in Manifest.load(cache).scenes] == [{}, {}]
    assert verify_cache(cache).ok


# --------------------------------------------------------------------------------------------
# verify checks everything the reader relies on, even when the file's SHA-256 matches


def corrupt_index(tiny_cache: Path, tmp_path: Path, edit: Callable[[Any], None]) -> tuple[Path, Path]:
    """A copy of the tiny cache whose first shard's manifest entry is edited (the file intact)."""
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    d = read_manifest(cache)
    edit(_shard0(d))
    write_manifest(cache, d)
    return cache, cache / _shard0(d)["path"]


def test_verify_reports_a_wrong_column_crc_in_the_manifest_by_shard_row_and_column(
    tiny_cache: Path, tmp_path: Path
) -> None:
    def edit(shard: Any) -> None:
        k = shard["columns"].index("cameras")
        shard["row_index"][1][3 + k] ^= 1

    cache, shard = corrupt_index(tiny_cache, tmp_path, edit)
    report = verify_cache(cache)
    assert report.errors == [
        f"{shard}: row 1, column 'cameras': CRC-32C mismatch "
        "(the file matches its whole-file CRC-32C: the manifest's index of it is wrong)"
    ]
    with pytest.raises(CacheError, match=r"row 1, column 'cameras' is corrupt"):
        CacheReader(cache).read(1)  # what verify reports is what the reader refuses


def test_verify_reports_a_wrong_metadata_crc_and_a_wrong_footer_crc_each_on_its_own_line(
    tiny_cache: Path, tmp_path: Path
) -> None:
    def edit(shard: Any) -> None:
        shard["row_index"][2][2] ^= 1
        shard["footer_crc32"] ^= 1

    cache, shard = corrupt_index(tiny_cache, tmp_path, edit)
    report = verify_cache(cache)
    why = "(the file matches its whole-file CRC-32C: the manifest's index of it is wrong)"
    assert report.errors == [
        f"{shard}: footer: CRC-32C mismatch {why}",
        f"{shard}: row 2 (metadata): CRC-32C mismatch {why}",
    ]
    assert report.frames == TINY_PREP_ARGS["frames"]  # the other shard's frames are sound
    with pytest.raises(CacheError, match="the footer is corrupt"):
        CacheReader(cache).read(0)


def test_verify_reports_columns_in_another_order_than_the_file(tiny_cache: Path, tmp_path: Path) -> None:
    cache, shard = corrupt_index(tiny_cache, tmp_path, lambda s: s["columns"].reverse())
    report = verify_cache(cache)
    assert len(report.errors) == 1 and report.errors[0].startswith(f"{shard}: columns ["), report.errors


def test_verify_names_every_damaged_row_and_column_of_a_corrupt_file(
    tiny_cache: Path, tmp_path: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    info = Manifest.load(cache).shards[0]
    path = cache / info.path
    buffer = pa.py_buffer(path.read_bytes())
    reader = pa.ipc.open_file(buffer)
    data = bytearray(path.read_bytes())
    damaged = [(0, "boxes"), (2, "cameras")]
    for row, column in damaged:
        lo, hi = shards.column_range(reader.get_batch(row).column(column), buffer.address)
        data[(lo + hi) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    report = verify_cache(cache)
    assert report.errors == [
        f"{path}: row {row}, column {column!r}: CRC-32C mismatch "
        "(whole-file CRC-32C mismatch: the file is corrupt)"
        for row, column in damaged
    ]


# --------------------------------------------------------------------------------------------
# One writer per cache directory

HOLD_LOCK = r"""
import sys, time
from phigenesis.data.cache_lock import CacheLock
CacheLock(sys.argv[1]).acquire()
print("locked", flush=True)
time.sleep(300)
"""

WRITER = r"""
import json, sys
from phigenesis import prep
prep.synthetic(sys.argv[1], progress=False, **json.loads(sys.argv[2]))
"""


def test_a_second_writer_is_refused_naming_the_pid_of_the_run_writing_the_cache(
    tmp_path: Path, bare_spec: Path
) -> None:
    cache = tmp_path / "cache"
    args = {**TINY_PREP_ARGS, "pipeline": str(bare_spec)}
    first = python(WRITER, str(cache), json.dumps(args))
    try:
        assert wait_for(lambda: (cache / MANIFEST_NAME).exists(), first), first.communicate()
        with pytest.raises(PrepError, match=rf"another prep run is writing this cache \(PID {first.pid} on "):
            prep.synthetic(cache, progress=False, **args)  # type: ignore[arg-type]
        assert first.wait(timeout=300) == 0, first.communicate()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert row_keys(cache) == [(s, k) for s in SCENE_IDS for k in range(TINY_PREP_ARGS["frames"])]
    report = verify_cache(cache)
    assert report.ok and report.warnings == [], report.errors + report.warnings
    assert not (cache / LOCK_NAME).exists()


def test_a_lock_left_by_a_killed_process_is_taken_over_and_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    holder = python(HOLD_LOCK, str(cache))
    assert holder.stdout is not None and holder.stdout.readline() == "locked\n", holder.communicate()
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert f"pid: {holder.pid}" in (cache / LOCK_NAME).read_text()

    with caplog.at_level(logging.WARNING, logger="phigenesis.prep"):
        prep.synthetic(cache, progress=False, **OTHER_ARGS)
    taken = [r.getMessage() for r in caplog.records if "taking over the lock" in r.getMessage()]
    assert len(taken) == 1 and f"PID {holder.pid} on {socket.gethostname()}" in taken[0], taken
    assert row_keys(cache) == [("synthetic-s8-0000", 0)]
    assert not (cache / LOCK_NAME).exists()


def test_a_live_lock_holder_is_named_and_the_directory_left_untouched(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    holder = python(HOLD_LOCK, str(cache))
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "locked\n", holder.communicate()
        with pytest.raises(PrepError, match=rf"PID {holder.pid} on {socket.gethostname()}, started "):
            prep.synthetic(cache, overwrite=True, progress=False, **OTHER_ARGS)
    finally:
        holder.kill()
        holder.wait()
    assert sorted(p.name for p in cache.iterdir()) == [LOCK_NAME]


def test_the_running_prep_holds_the_lock_under_its_own_pid_and_removes_it_at_the_end(tmp_path: Path) -> None:
    seen: list[str] = []

    @register_stage("tests-trust-read-lock")
    def read_lock(scene: Scene, params: dict[str, Any]) -> Scene:
        seen.append((Path(params["cache"]) / LOCK_NAME).read_text())
        return scene

    try:
        cache = tmp_path / "cache"
        spec = spec_with(StageSpec("tests-trust-read-lock", {"cache": str(cache)}))
        prep.synthetic(cache, pipeline=spec, progress=False, **OTHER_ARGS)
    finally:
        STAGES.pop("tests-trust-read-lock", None)
    assert len(seen) == 1 and LockHolder.from_text(seen[0]) is not None
    holder = LockHolder.from_text(seen[0])
    assert (holder.pid, holder.host) == (os.getpid(), socket.gethostname())
    assert not (cache / LOCK_NAME).exists()


def test_a_lock_file_that_is_a_symbolic_link_is_refused_and_its_target_left_untouched(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    target = tmp_path / "notes.txt"
    target.write_text("keep me")
    (cache / LOCK_NAME).symlink_to(target)
    with pytest.raises(PrepError, match=r"lock file is a symbolic link"):
        prep.synthetic(cache, progress=False, **OTHER_ARGS)
    assert target.read_text() == "keep me"
    assert sorted(p.name for p in cache.iterdir()) == [LOCK_NAME]


def test_without_flock_the_recorded_pid_decides_whether_a_lock_is_stale(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from phigenesis.data import cache_lock

    def no_flock(fd: int, operation: int) -> None:
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(cache_lock.fcntl, "flock", no_flock)
    lock_file = tmp_path / LOCK_NAME
    lock_file.write_text(LockHolder(os.getpid(), socket.gethostname(), "2024-01-01T00:00:00+00:00").to_text())
    with pytest.raises(PrepError, match=rf"PID {os.getpid()} on "):
        CacheLock(tmp_path).acquire()

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    lock_file.write_text(LockHolder(gone.pid, socket.gethostname(), "2024-01-01T00:00:00+00:00").to_text())
    with CacheLock(tmp_path):
        assert LockHolder.from_text(lock_file.read_text()).pid == os.getpid()
    assert not lock_file.exists()


# --------------------------------------------------------------------------------------------
# --overwrite builds the new cache beside the old one and swaps it in at the end


def test_an_overwrite_whose_input_fails_leaves_the_old_cache_intact_and_verify_clean(
    tiny_cache: Path, tmp_path: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    before = file_state(cache)
    waymo_input = tmp_path / "segments"
    waymo_input.mkdir()
    (waymo_input / "garbage.tfrecord").write_bytes(os.urandom(1000))
    with pytest.raises(PrepError, match=r"garbage\.tfrecord.*the cache in .* is unchanged"):
        prep.waymo(cache, input=waymo_input, overwrite=True, progress=False)
    assert file_state(cache) == before
    report = verify_cache(cache)
    assert report.ok and report.warnings == [], report.errors + report.warnings
    assert row_keys(cache) == row_keys(tiny_cache)


def test_the_old_cache_stays_readable_and_verify_clean_while_an_overwrite_runs(
    tiny_cache: Path, tmp_path: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    during: list[tuple[list[tuple[str, int]], bool, list[str]]] = []

    @register_stage("tests-trust-read-old-cache")
    def read_old_cache(scene: Scene, params: dict[str, Any]) -> Scene:
        report = verify_cache(params["cache"])
        during.append((row_keys(Path(params["cache"])), report.ok, report.errors))
        return scene

    try:
        spec = spec_with(StageSpec("tests-trust-read-old-cache", {"cache": str(cache)}))
        prep.synthetic(cache, pipeline=spec, overwrite=True, progress=False, **OTHER_ARGS)
    finally:
        STAGES.pop("tests-trust-read-old-cache", None)
    assert during == [(row_keys(tiny_cache), True, [])]
    assert row_keys(cache) == [("synthetic-s8-0000", 0)]
    assert not (cache / STAGING_DIR).exists()
    report = verify_cache(cache)
    assert report.ok and report.warnings == [], report.errors + report.warnings


def test_a_killed_overwrite_leaves_the_old_cache_intact_and_a_rerun_resumes_it(
    tiny_cache: Path, tmp_path: Path, bare_spec: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    before = file_state(cache)
    args = {**TINY_PREP_ARGS, "seed": 8, "overwrite": True, "pipeline": str(bare_spec)}
    staging = cache / STAGING_DIR
    proc = python(WRITER, str(cache), json.dumps(args))
    try:
        caught = wait_for(lambda: len(complete_scenes(staging)) == 1, proc)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert caught and proc.returncode == -signal.SIGKILL, "the overwrite ended before it could be killed"

    old_files = {k: v for k, v in file_state(cache).items() if not k.startswith((STAGING_DIR, LOCK_NAME))}
    assert old_files == before
    report = verify_cache(cache)
    assert report.ok, report.errors
    assert [w for w in report.warnings if STAGING_DIR in w] == report.warnings and report.warnings
    assert row_keys(cache) == row_keys(tiny_cache)

    summary = prep.synthetic(cache, progress=False, **args)  # type: ignore[arg-type]
    assert summary.scenes_already_complete == ["synthetic-s8-0000"]
    assert summary.scenes_written == ["synthetic-s8-0001"]
    assert row_keys(cache) == [(f"synthetic-s8-{s:04d}", k) for s in range(2) for k in range(3)]
    assert not staging.exists()
    report = verify_cache(cache)
    assert report.ok and report.warnings == [], report.errors + report.warnings


def test_a_swap_stopped_part_way_is_finished_by_the_next_run(
    tiny_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    calls = []

    def interrupt_after_moving_the_shards(path: Path) -> None:
        calls.append(path)
        if len(calls) == 2:  # the old manifest is removed and the new shards are in shards/
            raise KeyboardInterrupt

    monkeypatch.setattr(cache_run, "fsync_dir", interrupt_after_moving_the_shards)
    with pytest.raises(PrepInterrupted, match="while swapping the new version"):
        prep.synthetic(cache, overwrite=True, progress=False, **OTHER_ARGS)
    monkeypatch.undo()
    assert not (cache / MANIFEST_NAME).exists()
    with pytest.raises(CacheError, match="was swapping in a new version"):
        CacheReader(cache)

    summary = prep.synthetic(cache, overwrite=True, progress=False, **OTHER_ARGS)
    assert summary.scenes_written == [] and summary.scenes_already_complete == ["synthetic-s8-0000"]
    assert row_keys(cache) == [("synthetic-s8-0000", 0)]
    assert sorted(p.name for p in cache.iterdir()) == [MANIFEST_NAME, SHARDS_DIR]
    report = verify_cache(cache)
    assert report.ok and report.warnings == [], report.errors + report.warnings


# --------------------------------------------------------------------------------------------
# A full disk


def fail_fsync_of(monkeypatch: pytest.MonkeyPatch, name_part: str, error: OSError) -> None:
    """Makes fsync fail with ``error`` for every open file whose path contains ``name_part``."""
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        if name_part in os.readlink(f"/proc/self/fd/{fd}"):
            raise error
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)


def disk_fills_after(monkeypatch: pytest.MonkeyPatch, limit: int) -> None:
    """Makes the shard writer's writes fail as a full disk does once a file would pass ``limit``
    bytes: what fits is written, then ENOSPC."""
    real_writev = os.writev

    def writev(fd: int, pieces: list[Any]) -> int:
        room = limit - os.fstat(fd).st_size
        data = b"".join(bytes(p) for p in pieces)
        if room <= 0:
            raise OSError(errno.ENOSPC, ENOSPC_REASON)
        return real_writev(fd, [data[:room]])

    monkeypatch.setattr(os, "writev", writev)


def test_a_full_disk_while_writing_rows_removes_the_unfinished_shard_and_names_it(
    tiny_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    batches = list(CacheReader(tiny_cache))
    limit = int(1.5 * Manifest.load(tiny_cache).shards[0].row_index[0][0])  # room for one row
    disk_fills_after(monkeypatch, limit)
    writer = ShardWriter(tmp_path, "scene-a", batches[0].schema)
    writer.write(batches[0])
    with pytest.raises(CacheWriteError) as error:
        writer.write(batches[1])
    final = tmp_path / SHARDS_DIR / "scene-a-00000.arrow"
    assert str(error.value) == f"{final}: cannot write ({ENOSPC_REASON})"
    assert list((tmp_path / SHARDS_DIR).iterdir()) == []


def test_a_full_disk_while_closing_a_shard_keeps_the_complete_ones_and_names_the_file(
    tiny_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    batches = list(CacheReader(tiny_cache))
    fail_fsync_of(monkeypatch, "scene-a-00001", OSError(errno.ENOSPC))
    max_bytes = int(1.5 * max(b.nbytes for b in batches))
    with (
        pytest.raises(CacheWriteError) as error,
        ShardWriter(tmp_path, "scene-a", batches[0].schema, max_bytes) as writer,
    ):
        for batch in batches:
            writer.write(batch)
    final = tmp_path / SHARDS_DIR / "scene-a-00001.arrow"
    assert str(error.value) == f"{final}: cannot write ({ENOSPC_REASON})"
    assert sorted(p.name for p in (tmp_path / SHARDS_DIR).iterdir()) == ["scene-a-00000.arrow"]
    assert ShardReader(tmp_path, writer.shards[0]).read(0).equals(batches[0])


@pytest.mark.parametrize("on_error", ["raise", "skip"])
def test_a_full_disk_during_prep_stops_the_run_naming_the_shard_and_keeps_complete_scenes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, on_error: str
) -> None:
    fail_fsync_of(monkeypatch, SCENE_IDS[1], OSError(errno.ENOSPC, ENOSPC_REASON))
    args = {**TINY_PREP_ARGS, "frames": 1}
    with pytest.raises(CacheWriteError) as error:
        prep.synthetic(tmp_path, pipeline=spec_with(), on_error=on_error, progress=False, **args)  # type: ignore[arg-type]
    monkeypatch.undo()
    shard = tmp_path / SHARDS_DIR / f"{SCENE_IDS[1]}-00000.arrow"
    assert str(error.value).startswith(f"{shard}: cannot write ({ENOSPC_REASON})")
    assert complete_scenes(tmp_path) == [SCENE_IDS[0]]
    assert [s.id for s in Manifest.load(tmp_path).scenes] == [
        SCENE_IDS[0]
    ]  # the full disk is no scene's fault
    assert leftovers(tmp_path) == []
    report = verify_cache(tmp_path)
    assert report.ok and report.warnings == [], report.errors + report.warnings


def test_a_full_disk_while_saving_the_manifest_keeps_the_previous_one_and_names_the_file(
    tiny_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    before = (cache / MANIFEST_NAME).read_bytes()
    fail_fsync_of(monkeypatch, f"{MANIFEST_NAME}{TMP_MARKER}", OSError(errno.ENOSPC, ENOSPC_REASON))
    with pytest.raises(CacheWriteError) as error:
        Manifest.load(cache).save(cache)
    assert str(error.value) == f"{cache / MANIFEST_NAME}: cannot write ({ENOSPC_REASON})"
    assert (cache / MANIFEST_NAME).read_bytes() == before
    assert sorted(p.name for p in cache.iterdir()) == [MANIFEST_NAME, SHARDS_DIR]


# --------------------------------------------------------------------------------------------
# Dropped values reach the manifest and the log

POINTS = "LiDAR points with non-finite coordinates"


@register_stage("tests-trust-drop-points")
def _drop_points(scene: Scene, params: dict[str, Any]) -> Scene:
    if scene.scene_id == params["scene_id"]:
        scene.dropped.add(POINTS, 0, 12)
        scene.dropped.add(POINTS, 2, 3)
    return scene


def test_dropped_values_are_recorded_in_the_scene_entry_and_logged_once_per_scene(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    spec = spec_with(StageSpec("tests-trust-drop-points", {"scene_id": SCENE_IDS[0]}))
    with caplog.at_level(logging.WARNING, logger="phigenesis.prep"):
        prep.synthetic(tmp_path, pipeline=spec, progress=False, **TINY_PREP_ARGS)  # type: ignore[arg-type]
    assert [s.dropped for s in Manifest.load(tmp_path).scenes] == [{POINTS: 15}, {}]
    assert read_manifest(tmp_path)["scenes"][0]["dropped"] == {POINTS: 15}
    lines = [r.getMessage() for r in caplog.records if POINTS in r.getMessage()]
    assert lines == [f"scene {SCENE_IDS[0]}: the source left out 15 {POINTS} (2 frames)"]


# --------------------------------------------------------------------------------------------
# A bare name is a bundled pipeline


def test_folders_named_like_the_bundled_pipelines_do_not_shadow_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("waymo", "nuscenes", "synthetic"):
        (tmp_path / name).mkdir()
    monkeypatch.chdir(tmp_path)
    assert [load_pipeline(n).source for n in ("waymo", "nuscenes", "synthetic")] == [
        "waymo",
        "nuscenes",
        "synthetic",
    ]
    # the guide's try-it command (docs/guide/sources.md): segments converted from a folder called waymo/
    with pytest.raises(PrepError) as error:  # the empty input folder, not the pipeline, is the problem
        prep.waymo(tmp_path / "waymo-cache", input="waymo", progress=False)
    assert f"{tmp_path / 'waymo'}: " in str(error.value) and "pipeline spec" not in str(error.value)


def test_an_unknown_bundled_pipeline_name_lists_the_bundled_ones() -> None:
    with pytest.raises(
        PrepError, match=r"no bundled pipeline named 'kitti'; the bundled ones are nuscenes, synthetic, waymo"
    ):
        load_pipeline("kitti")


def test_a_spec_path_is_one_with_a_yaml_suffix_or_a_separator(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "specs").mkdir()
    (tmp_path / "specs" / "mine").write_text("source: {name: synthetic}\n")
    monkeypatch.chdir(tmp_path)
    assert load_pipeline("specs/mine").source == "synthetic"
    assert load_pipeline(Path("specs") / "mine").source == "synthetic"
    with pytest.raises(PrepError, match=r"waymo\.yml: pipeline spec not found"):
        load_pipeline("waymo.yml")
    with pytest.raises(PrepError, match=r"no bundled pipeline named 'mine'"):
        load_pipeline("mine")


# --------------------------------------------------------------------------------------------
# Interrupts leave the cache consistent and say what was kept

INTERRUPT_STAGE = "tests-trust-interrupt"


@register_stage(INTERRUPT_STAGE)
def _interrupt_mid_scene(scene: Scene, params: dict[str, Any]) -> Scene:
    """Raises KeyboardInterrupt while frame 1 of scene ``scene_id`` is loaded (frame 0 is then in
    an open temporary shard)."""
    if scene.scene_id != params["scene_id"]:
        return scene

    def interrupt_at_frame_1(frame: Any) -> Any:
        if frame.frame_index == 1:
            raise KeyboardInterrupt
        return frame

    return dataclasses.replace(scene, frames=scene.frames.map(interrupt_at_frame_1))


def test_an_interrupted_prep_keeps_complete_scenes_removes_temporaries_and_releases_the_lock(
    tmp_path: Path,
) -> None:
    spec = spec_with(StageSpec(INTERRUPT_STAGE, {"scene_id": SCENE_IDS[1]}))
    with pytest.raises(PrepInterrupted) as interrupt:
        prep.synthetic(tmp_path, pipeline=spec, progress=False, **TINY_PREP_ARGS)  # type: ignore[arg-type]
    e = interrupt.value
    assert isinstance(e, KeyboardInterrupt)
    frames = TINY_PREP_ARGS["frames"]
    assert (e.cache_dir, e.scenes_complete, e.scenes_total, e.frames_complete, e.staging_dir) == (
        str(tmp_path),
        1,
        2,
        frames,
        None,
    )
    assert str(e) == (
        f"interrupted: 1 of 2 scenes ({frames} frames) are complete in {tmp_path}; "
        "rerun the same command to resume"
    )
    assert complete_scenes(tmp_path) == [SCENE_IDS[0]]
    assert leftovers(tmp_path) == []
    assert not (tmp_path / LOCK_NAME).exists()
    report = verify_cache(tmp_path)
    assert report.ok and report.warnings == [], report.errors + report.warnings


def test_an_interrupted_overwrite_says_the_old_cache_is_unchanged_and_where_the_new_one_is(
    tiny_cache: Path, tmp_path: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    before = file_state(cache)
    spec = spec_with(StageSpec(INTERRUPT_STAGE, {"scene_id": "synthetic-s8-0001"}))
    args = {**TINY_PREP_ARGS, "seed": 8}
    with pytest.raises(PrepInterrupted) as interrupt:
        prep.synthetic(cache, pipeline=spec, overwrite=True, progress=False, **args)  # type: ignore[arg-type]
    e = interrupt.value
    assert (e.scenes_complete, e.scenes_total, e.staging_dir) == (1, 2, str(cache / STAGING_DIR))
    assert str(e).startswith(f"interrupted: the cache in {cache} is unchanged; 1 of 2 scenes")
    assert {k: v for k, v in file_state(cache).items() if not k.startswith(STAGING_DIR)} == before
    assert complete_scenes(cache / STAGING_DIR) == ["synthetic-s8-0000"]
    assert leftovers(cache / STAGING_DIR) == []


POOL_RUN = r"""
import dataclasses, json, multiprocessing, sys, time

from phigenesis.data.pipeline import PrepInterrupted, StageSpec, load_pipeline, prepare
from phigenesis.data.stages import STAGES, register_stage


@register_stage("tests-trust-slow-frames")
def slow_frames(scene, params):
    def slow(frame):
        time.sleep(params["seconds"])
        return frame

    return dataclasses.replace(scene, frames=scene.frames.map(slow))


if __name__ == "__main__":
    spec = dataclasses.replace(
        load_pipeline("synthetic"), stages=(StageSpec("tests-trust-slow-frames", {"seconds": 0.3}),)
    )
    try:
        prepare(sys.argv[1], "synthetic", json.loads(sys.argv[2]), pipeline=spec, workers=2, progress=False)
    except PrepInterrupted as e:
        print(json.dumps({"complete": e.scenes_complete, "total": e.scenes_total, "message": str(e),
                          "children": len(multiprocessing.active_children())}))
        sys.exit(130)
"""


@pytest.mark.slow
def test_an_interrupt_stops_the_worker_pool_and_leaves_a_consistent_cache(tmp_path: Path) -> None:
    script = tmp_path / "pool_run.py"  # a file, so that spawned workers register its stage too
    script.write_text(POOL_RUN)
    cache = tmp_path / "cache"
    args = {**TINY_PREP_ARGS, "scenes": 4}
    proc = subprocess.Popen(
        [sys.executable, str(script), str(cache), json.dumps(args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        caught = wait_for(lambda: len(complete_scenes(cache)) >= 1, proc)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert caught and proc.returncode == 130, stdout + stderr
    result = json.loads(stdout)
    kept = complete_scenes(cache)
    assert 1 <= result["complete"] == len(kept) < 4 and result["total"] == 4
    assert result["children"] == 0
    assert result["message"].startswith(f"interrupted: {len(kept)} of 4 scenes")
    assert leftovers(cache) == []
    assert not (cache / LOCK_NAME).exists()
    report = verify_cache(cache)
    assert report.ok and report.warnings == [], report.errors + report.warnings


def test_a_row_holding_an_invalid_value_is_a_cache_error_naming_shard_row_and_field(
    tiny_cache: Path, tmp_path: Path
) -> None:
    # A crafted (or pre-validation) cache: one row's pose scaled by 1e6, with the manifest's hashes
    # made to match, so only the scene model's own check can catch it.
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    manifest = Manifest.load(cache)
    info = manifest.shards[0]
    table = pa.ipc.open_file(pa.memory_map(str(cache / info.path))).read_all()
    poses = table.column("world_from_ego").to_pylist()
    poses[1] = [v * 1e6 for v in poses[1][:12]] + poses[1][12:]
    index = table.schema.get_field_index("world_from_ego")
    pose_field = table.schema.field(index)
    table = table.set_column(index, pose_field, pa.array(poses, pose_field.type))
    (cache / info.path).unlink()
    with ShardWriter(cache, info.scene_id, table.schema) as writer:
        for batch in table.to_batches(max_chunksize=1):
            writer.write(batch)
    (new,) = writer.shards
    manifest.shards[0] = new
    manifest.save(cache)
    reader = CacheReader(cache)
    reader.frame(0)  # the untouched row still reads
    with pytest.raises(CacheError) as e:
        reader.frame(1)
    assert str(e.value).startswith(f"{cache / info.path}: row 1: world_from_ego is not a rigid transform")


def _as_legacy_checksums(cache: Path) -> None:
    """Rewrites ``cache``'s manifest as toolkits before CRC-32C wrote it: zlib CRC-32s of the same
    ranges and a SHA-256 of each file, no ``checksum`` field."""
    d = read_manifest(cache)
    for entry in d["shards"]:
        legacy = shards.shard_info(
            cache / entry["path"], entry["scene_id"], [row[0] for row in entry["row_index"]], "crc32"
        )
        entry.update(row_index=legacy.row_index, footer_crc32=legacy.footer_crc32, sha256=legacy.sha256)
        del entry["checksum"], entry["file_crc32c"]
    write_manifest(cache, d)


def test_a_cache_with_the_older_crc32_and_sha256_entries_reads_and_verifies(
    tiny_cache: Path, tmp_path: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    _as_legacy_checksums(cache)
    manifest = Manifest.load(cache)
    assert {sh.checksum for sh in manifest.shards} == {"crc32"} and all(sh.sha256 for sh in manifest.shards)
    assert verify_cache(cache).ok
    fresh = CacheReader(tiny_cache)
    assert all(CacheReader(cache).read(i).equals(fresh.read(i)) for i in range(len(fresh)))
    info = manifest.shards[0]
    path = cache / info.path
    buffer = pa.py_buffer(path.read_bytes())
    lo, hi = shards.column_range(pa.ipc.open_file(buffer).get_batch(1).column("cameras"), buffer.address)
    data = bytearray(path.read_bytes())
    data[(lo + hi) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    assert verify_cache(cache).errors == [
        f"{path}: row 1, column 'cameras': CRC-32 mismatch (SHA-256 mismatch: the file is corrupt)"
    ]
    with pytest.raises(CacheError, match=r"row 1, column 'cameras' is corrupt \(CRC-32 mismatch"):
        CacheReader(cache).read(1)
