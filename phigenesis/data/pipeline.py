"""Builds caches: source -> scenes -> stages -> shard writer -> manifest, resumable and parallel.

Entry point: :func:`prepare`. A run is defined by the source, its arguments and the pipeline
spec; their fingerprint is stored in the manifest, so rerunning the same command into the same
directory resumes (finished scenes are skipped), while a different command is refused unless
``overwrite`` is given. Scenes are independent and run in parallel on the chosen executor.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.resources
import json
import logging
import os
import time
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from phigenesis import __version__
from phigenesis.data.executors import ExecutorName, ProgressHandle, ProgressMessage, run_tasks
from phigenesis.data.schema import SCHEMA_VERSION, CacheContents, frame_schema, frame_to_batch
from phigenesis.data.shards import (
    DEFAULT_SHARD_MAX_BYTES,
    MANIFEST_NAME,
    SHARDS_DIR,
    TMP_MARKER,
    CacheError,
    Manifest,
    SceneEntry,
    ShardInfo,
    ShardWriter,
)
from phigenesis.data.sources import make_source
from phigenesis.data.stages import get_stage
from phigenesis.errors import PhiGenesisError, PrepError, describe

log = logging.getLogger("phigenesis.prep")
OnError = Literal["raise", "skip"]


# --------------------------------------------------------------------------------------------
# Pipeline specs


@dataclass(frozen=True)
class StageSpec:
    name: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PipelineSpec:
    """A declarative pipeline: the source and its default parameters, the stages, the outputs."""

    name: str
    source: str
    source_params: dict[str, Any]
    stages: tuple[StageSpec, ...] = ()
    contents: CacheContents = CacheContents()
    shard_max_bytes: int = DEFAULT_SHARD_MAX_BYTES

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "pipeline spec") -> PipelineSpec:
        try:
            src = d["source"]
            out = dict(d.get("output") or {})
            shard_max = int(out.pop("shard_max_bytes", DEFAULT_SHARD_MAX_BYTES))
            stages = tuple(StageSpec(s["name"], dict(s.get("params") or {})) for s in d.get("stages") or [])
            for st in stages:
                get_stage(st.name)
            return cls(
                name=str(d.get("name", src["name"])),
                source=str(src["name"]),
                source_params=dict(src.get("params") or {}),
                stages=stages,
                contents=CacheContents(**out),
                shard_max_bytes=shard_max,
            )
        except (KeyError, TypeError, ValueError) as e:
            raise PrepError(f"{where}: invalid pipeline spec ({type(e).__name__}: {e})") from e

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "source": {"name": self.source, "params": self.source_params},
            "stages": [{"name": s.name, "params": s.params} for s in self.stages],
            "output": {
                **dataclasses.asdict(self.contents),
                "camera_truth": list(self.contents.camera_truth),
                "shard_max_bytes": self.shard_max_bytes,
            },
        }


def load_pipeline(name_or_path: str | os.PathLike[str]) -> PipelineSpec:
    """A pipeline spec from a YAML file path, or by name from the bundled ``pipelines/``."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or path.exists():
        if not path.is_file():
            raise PrepError(f"{path}: pipeline spec not found")
        text = path.read_text()
        where = str(path)
    else:
        res = importlib.resources.files("phigenesis.pipelines") / f"{name_or_path}.yaml"
        if not res.is_file():
            raise PrepError(f"no bundled pipeline named {name_or_path!r}")
        text = res.read_text()
        where = f"pipelines/{name_or_path}.yaml"
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise PrepError(f"{where}: not valid YAML ({e})") from e
    if not isinstance(d, dict):
        raise PrepError(f"{where}: a pipeline spec must be a mapping")
    return PipelineSpec.from_dict(d, where)


def _merge(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in overrides.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        elif v is not None:
            out[k] = v
    return out


def fingerprint(source: str, arguments: dict[str, Any], pipeline: dict[str, Any]) -> str:
    """Hash of everything that determines a cache's rows."""
    blob = json.dumps(
        {"source": source, "arguments": arguments, "pipeline": pipeline, "schema_version": SCHEMA_VERSION},
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(blob.encode()).hexdigest()


# --------------------------------------------------------------------------------------------
# One scene (runs in a worker)


@dataclass
class SceneTask:
    cache_dir: str
    source: str
    arguments: dict[str, Any]
    pipeline: dict[str, Any]
    scene_id: str


@dataclass
class SceneResult:
    scene_id: str
    source: str
    frames: int = 0
    shards: list[ShardInfo] = field(default_factory=list)
    error: str | None = None
    seconds: float = 0.0
    #: The failure was an input problem (a :class:`~phigenesis.errors.PhiGenesisError`, whose
    #: message names the file and record); False for anything else, which is a toolkit bug.
    error_is_input: bool = True


def process_scene(task: SceneTask, progress: ProgressHandle | None = None) -> SceneResult:
    """Loads one scene, runs the pipeline's stages and writes its shards. Never raises: a failure
    comes back as ``SceneResult.error`` (with nothing of the scene left on disk under final names
    that the manifest would list)."""
    t0 = time.perf_counter()
    try:
        spec = PipelineSpec.from_dict(task.pipeline)
        source = make_source(task.source, task.arguments)
        scene = source.load(task.scene_id)
        for st in spec.stages:
            scene = get_stage(st.name)(scene, st.params)
        schema = frame_schema(
            spec.contents,
            {"phigenesis.source": scene.source, "phigenesis.scene_metadata": json.dumps(scene.metadata)},
        )
        total = len(scene.frames)
        with ShardWriter(Path(task.cache_dir), scene.scene_id, schema, spec.shard_max_bytes) as writer:
            for i, frame in enumerate(scene.frames):
                writer.write(frame_to_batch(frame, scene.source, schema))
                if progress is not None:
                    progress.put((task.scene_id, i + 1, total))
        return SceneResult(task.scene_id, scene.source, total, writer.shards, None, time.perf_counter() - t0)
    except Exception as e:  # reported per scene; the coordinator applies the error policy
        log.debug("scene %s failed:\n%s", task.scene_id, traceback.format_exc())
        return SceneResult(
            task.scene_id,
            task.source,
            error=describe(e),
            seconds=time.perf_counter() - t0,
            error_is_input=isinstance(e, PhiGenesisError),
        )


# --------------------------------------------------------------------------------------------
# A whole run


@dataclass
class PrepSummary:
    """What a prep run did."""

    cache_dir: str
    scenes_written: list[str] = field(default_factory=list)
    scenes_already_complete: list[str] = field(default_factory=list)
    scenes_skipped: dict[str, str] = field(default_factory=dict)
    frames_written: int = 0
    bytes_written: int = 0
    seconds: float = 0.0

    def describe(self) -> str:
        lines = [
            f"{self.cache_dir}: wrote {len(self.scenes_written)} scenes ({self.frames_written} frames, "
            f"{self.bytes_written / 1e6:.1f} MB) in {self.seconds:.1f} s"
            + (f" ({self.seconds / self.frames_written:.2f} s/frame)" if self.frames_written else "")
        ]
        if self.scenes_already_complete:
            lines.append(
                f"  {len(self.scenes_already_complete)} scenes were already complete and were skipped"
            )
        for sid, why in self.scenes_skipped.items():
            lines.append(f"  skipped scene {sid}: {why}")
        return "\n".join(lines)


def _check_out_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise PrepError(f"--out {out} is a file, not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise PrepError(f"--out {out} cannot be created: {e.strerror or e}") from e
    probe = out / f".write-probe{TMP_MARKER}{uuid.uuid4().hex[:8]}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise PrepError(f"--out {out} is not writable: {e.strerror or e}") from e


def _describe_difference(
    old: Manifest, source: str, arguments: dict[str, Any], pipeline: dict[str, Any]
) -> str:
    # Compare as the manifest stores them (JSON: tuples become lists), like the fingerprint does.
    arguments, pipeline = json.loads(json.dumps([arguments, pipeline], default=str))
    diffs = []
    if old.source != source:
        diffs.append(f"source {old.source} -> {source}")
    for k in sorted(set(old.arguments) | set(arguments)):
        if old.arguments.get(k) != arguments.get(k):
            diffs.append(f"{k} {old.arguments.get(k)!r} -> {arguments.get(k)!r}")
    if old.pipeline != pipeline:
        diffs.append("pipeline spec differs")
    if old.schema_version != SCHEMA_VERSION:
        diffs.append(f"schema version {old.schema_version} -> {SCHEMA_VERSION}")
    return ", ".join(diffs) or "fingerprint differs"


def _remove_cache_files(out: Path, manifest: Manifest | None) -> None:
    """Removes what a cache consists of (its listed shards, our shard files, the manifest)."""
    if manifest is not None:
        for sh in manifest.shards:
            (out / sh.path).unlink(missing_ok=True)
    shard_dir = out / SHARDS_DIR
    if shard_dir.is_dir():
        for p in shard_dir.iterdir():
            if p.suffix == ".arrow" or TMP_MARKER in p.name:
                p.unlink()
    (out / MANIFEST_NAME).unlink(missing_ok=True)


def _clean_unfinished(out: Path, manifest: Manifest) -> list[str]:
    """Removes temporary files and shards no manifest entry lists (left by a killed run)."""
    listed = {sh.path for sh in manifest.shards}
    removed = []
    shard_dir = out / SHARDS_DIR
    if shard_dir.is_dir():
        for p in shard_dir.iterdir():
            rel = p.relative_to(out).as_posix()
            if TMP_MARKER in p.name or (p.suffix == ".arrow" and rel not in listed):
                p.unlink()
                removed.append(rel)
    for p in out.glob(f"{MANIFEST_NAME}{TMP_MARKER}*"):
        p.unlink()
        removed.append(p.name)
    return removed


def _is_foreign(out: Path) -> bool:
    """True if ``out`` (which has no manifest) holds anything but the temporary files of a run
    killed before its first manifest write. Our runs write the manifest before any shard, so
    shard files without a manifest are someone else's and are never deleted."""
    for p in out.iterdir():
        if p.name == SHARDS_DIR and p.is_dir():
            if any(TMP_MARKER not in q.name for q in p.iterdir()):
                return True
        elif not p.name.startswith(f"{MANIFEST_NAME}{TMP_MARKER}"):
            return True
    return False


def prepare(
    out: str | os.PathLike[str],
    source: str,
    source_overrides: dict[str, Any] | None = None,
    pipeline: str | os.PathLike[str] | PipelineSpec = "synthetic",
    executor: ExecutorName = "local",
    workers: int = 1,
    ray_address: str | None = None,
    overwrite: bool = False,
    on_error: OnError = "raise",
    progress: bool = True,
) -> PrepSummary:
    """Builds (or resumes) the cache in ``out``.

    Args:
        out: cache directory (created if missing).
        source: source name, e.g. "synthetic".
        source_overrides: source parameters that override the pipeline spec's defaults.
        pipeline: a spec, a bundled pipeline name or a YAML path.
        executor: "local" (process pool; inline if ``workers <= 1``) or "ray".
        workers: parallel scenes.
        ray_address: Ray cluster address for ``executor="ray"`` (None starts a local Ray).
        overwrite: replace a cache made with other arguments, or with an unreadable manifest.
        on_error: "raise" stops at the first failed scene (finished scenes stay recorded);
            "skip" records the failure in the manifest and goes on.
        progress: show a progress bar per scene.

    Returns:
        A :class:`PrepSummary`. Raises :class:`PrepError` when the run cannot start or a scene
        fails with ``on_error="raise"``.
    """
    t0 = time.perf_counter()
    out = Path(out)
    spec = pipeline if isinstance(pipeline, PipelineSpec) else load_pipeline(pipeline)
    if spec.source != source:
        raise PrepError(f"pipeline {spec.name!r} is for source {spec.source!r}, not {source!r}")
    try:
        src = make_source(source, _merge(spec.source_params, source_overrides or {}))
    except (TypeError, ValueError) as e:
        raise PrepError(f"invalid {source} arguments: {e}") from e
    try:
        scene_ids = src.scene_ids()  # before anything is written: a bad input leaves no trace
    except (ValueError, OSError) as e:
        raise PrepError(f"cannot list the {source} scenes: {e}") from e
    arguments = src.arguments()
    pipeline_dict = spec.to_dict()
    fp = fingerprint(source, arguments, pipeline_dict)
    _check_out_dir(out)

    manifest: Manifest | None = None
    if (out / MANIFEST_NAME).exists():
        try:
            manifest = Manifest.load(out)
        except CacheError as e:
            if not overwrite:
                raise PrepError(f"{e}. Rerun with --overwrite to rebuild the cache from scratch.") from e
            log.warning("replacing the cache in %s: %s", out, e)
            _remove_cache_files(out, None)
        else:
            if manifest.fingerprint != fp:
                if not overwrite:
                    raise PrepError(
                        f"{out} holds a cache made with other arguments "
                        f"({_describe_difference(manifest, source, arguments, pipeline_dict)}); "
                        "use --overwrite to replace it or choose another --out"
                    )
                log.warning("replacing the cache in %s made with other arguments", out)
                _remove_cache_files(out, manifest)
                manifest = None
    elif _is_foreign(out):
        raise PrepError(
            f"--out {out} is not empty and holds no phigenesis cache; choose a new or empty directory"
        )

    if manifest is None:
        manifest = Manifest(
            schema_version=SCHEMA_VERSION,
            source=source,
            arguments=arguments,
            pipeline=pipeline_dict,
            fingerprint=fp,
            phigenesis_version=__version__,
        )
    removed = _clean_unfinished(out, manifest)
    if removed:
        log.info(
            "removed %d unfinished files left by an interrupted run: %s", len(removed), ", ".join(removed)
        )
    manifest.save(out)

    order = {sid: i for i, sid in enumerate(scene_ids)}
    summary = PrepSummary(str(out))
    pending = []
    for sid in order:
        entry = manifest.scene(sid)
        if entry is not None and entry.status == "complete":
            summary.scenes_already_complete.append(sid)
        else:
            pending.append(SceneTask(str(out), source, arguments, pipeline_dict, sid))
    if summary.scenes_already_complete:
        log.info(
            "%d of %d scenes already complete; skipping them",
            len(summary.scenes_already_complete),
            len(order),
        )

    bars = _ProgressBars(enabled=progress)
    try:
        for result in run_tasks(process_scene, pending, executor, workers, ray_address, bars.update):
            bars.finish(result.scene_id)
            if result.error is None:
                entry = SceneEntry(
                    result.scene_id, result.source, result.frames, "complete", [s.path for s in result.shards]
                )
                manifest.record_scene(entry, result.shards)
                summary.scenes_written.append(result.scene_id)
                summary.frames_written += result.frames
                summary.bytes_written += sum(s.bytes for s in result.shards)
            else:
                status = "skipped" if on_error == "skip" else "failed"
                manifest.record_scene(
                    SceneEntry(result.scene_id, result.source, 0, status, [], result.error), []
                )
                summary.scenes_skipped[result.scene_id] = result.error
            manifest.scenes.sort(key=lambda s: order.get(s.id, len(order)))
            manifest.save(out)
            if result.error is not None:
                if on_error == "raise":
                    raise PrepError(
                        f"scene {result.scene_id} failed: {result.error} "
                        f"(finished scenes are kept in {out}; --on-error skip converts the rest)"
                    )
                log.warning("skipped scene %s: %s", result.scene_id, result.error)
    finally:
        bars.close()
    summary.seconds = time.perf_counter() - t0
    return summary


class _ProgressBars:
    """One tqdm bar per running scene, fed by progress messages."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.bars: dict[str, Any] = {}

    def update(self, msg: ProgressMessage) -> None:
        if not self.enabled:
            return
        from tqdm import tqdm

        key, done, total = msg
        bar = self.bars.get(key)
        if bar is None:
            bar = self.bars[key] = tqdm(total=total, desc=key, unit="frame", leave=True, dynamic_ncols=True)
        bar.update(done - bar.n)

    def finish(self, key: str) -> None:
        bar = self.bars.pop(key, None)
        if bar is not None:
            bar.close()

    def close(self) -> None:
        for key in list(self.bars):
            self.finish(key)
