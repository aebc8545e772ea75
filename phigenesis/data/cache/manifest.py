"""The cache's manifest: its scenes and shards (:class:`Manifest`, :class:`SceneEntry`), written
atomically as the commit point of each scene, and loaded as untrusted input: checked against the
cache's schema field by field (:func:`parse_manifest`), every shard path resolving inside the
cache's ``shards/`` folder (:func:`resolve_shard_path`).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from phigenesis.data.cache.checksums import CHECKSUMS, ShardInfo
from phigenesis.data.cache.files import (
    CACHE_FORMAT,
    MANIFEST_NAME,
    MAX_FILE_NAME_BYTES,
    SHARDS_DIR,
    STAGING_DIR,
    SWAP_MARKER,
    atomic_write_bytes,
    os_reason,
    scene_id_problem,
)
from phigenesis.errors import CacheError

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
