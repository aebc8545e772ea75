"""Builds caches: source -> scenes -> stages -> shard writer -> manifest, resumable and parallel.

Entry point: :func:`prepare`. A run is defined by the source, its arguments and the pipeline
spec; their fingerprint is stored in the manifest, so rerunning the same command into the same
directory resumes (finished scenes are skipped), while a different command is refused unless
``overwrite`` is given. Scenes are independent and run in parallel on the chosen executor. The
lock, the fingerprint, resuming and committing scenes are :mod:`phigenesis.data.cache_run`'s, which
every command that writes a cache shares.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.resources
import json
import logging
import os
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml
from tqdm import tqdm

from phigenesis.data.cache.checksums import ShardInfo
from phigenesis.data.cache.files import DEFAULT_SHARD_MAX_BYTES, CacheWriteError
from phigenesis.data.cache.manifest import SceneEntry
from phigenesis.data.cache.writer import ShardWriter
from phigenesis.data.cache_lock import CacheLock
from phigenesis.data.cache_run import POLICY_ARGUMENTS as POLICY_ARGUMENTS  # re-exported
from phigenesis.data.cache_run import CacheRun, check_out_dir, start_run, swap_in
from phigenesis.data.cache_run import fingerprint as fingerprint  # re-exported
from phigenesis.data.coverage import SceneCoverage
from phigenesis.data.executors import ExecutorName, ProgressHandle, ProgressMessage, run_tasks
from phigenesis.data.records import Frame, LazyFrames, Scene
from phigenesis.data.schema import CacheContents, frame_schema, frame_to_batch
from phigenesis.data.sources import given, make_source, source_config
from phigenesis.data.stages import get_stage, run_stage, stage_params
from phigenesis.errors import PhiGenesisError, PrepError, describe
from phigenesis.options import ConfigError, check_options, check_values, from_mapping, option
from phigenesis.user_files import read_small_file

log = logging.getLogger("phigenesis.prep")
OnError = Literal["raise", "skip"]


# --------------------------------------------------------------------------------------------
# Pipeline specs


#: The keys of a pipeline spec, of its ``source`` and of each of its stages.
SPEC_KEYS = ("name", "source", "stages", "output")
SOURCE_KEYS = ("name", "params")
STAGE_KEYS = ("name", "params")
#: Bounds of ``output.shard_max_bytes``: a row goes into a shard whole, so a limit below a row's
#: size (1 byte, as tests use) gives each row its own shard; a TiB is past any file system's taste.
MAX_SHARD_BYTES = 2**40


@dataclass(frozen=True)
class StageSpec:
    """A stage of a spec: its registered name and its parameters as the spec gives them (the
    stage builds them into its parameter class, :func:`~phigenesis.data.stages.stage_params`)."""

    name: str = option()
    params: dict[str, Any] = option(factory=dict)

    def __post_init__(self) -> None:
        check_options(self, "StageSpec")
        try:
            stage_params(self.name, self.params)
        except KeyError as e:
            raise ConfigError(f"StageSpec: {e.args[0]}") from None


@dataclass(frozen=True)
class PipelineSpec:
    """A declarative pipeline: the source and its default parameters, the stages, the outputs."""

    name: str = option()
    source: str = option()
    source_params: dict[str, Any] = option(factory=dict)
    stages: tuple[StageSpec, ...] = option(())
    contents: CacheContents = option(factory=CacheContents)
    shard_max_bytes: int = option(DEFAULT_SHARD_MAX_BYTES, ge=1, le=MAX_SHARD_BYTES)

    def __post_init__(self) -> None:
        check_options(self, "PipelineSpec")
        try:
            config = source_config(self.source)
        except ValueError as e:
            raise ConfigError(f"PipelineSpec: {e}") from None
        check_values(config, given(self.source_params), f"PipelineSpec: source {self.source} params")

    @classmethod
    def from_dict(cls, d: Any, where: str = "pipeline spec") -> PipelineSpec:
        """The spec a mapping holds (a YAML file's, or a manifest's ``pipeline``), every value
        checked before any scene is read: the keys of the spec, its source and its stages; the
        source's parameters against its config's declared types and ranges (the command line
        completes them, so a required one may be missing here); every stage's parameters built
        into the stage's parameter class; the outputs into :class:`CacheContents`. Raises
        :class:`~phigenesis.errors.PrepError` naming ``where``, the stage (its position and name)
        and the key."""
        try:
            return cls._from_dict(d, where)
        except ConfigError as e:
            raise PrepError(str(e)) from e

    @classmethod
    def _from_dict(cls, d: Any, where: str) -> PipelineSpec:
        d = _spec_mapping(d, where, SPEC_KEYS)
        if d.get("source") is None:
            raise ConfigError(f"{where}: source is missing (a mapping with name and params)")
        src = _spec_mapping(d["source"], f"{where}: source", SOURCE_KEYS)
        source = src.get("name")
        try:
            config = source_config(source)
        except ValueError as e:
            raise ConfigError(f"{where}: source: {e}") from None
        source_params = dict(_spec_mapping(src.get("params"), f"{where}: source {source} params"))
        check_values(config, given(source_params), f"{where}: source {source} params")
        name = check_values(cls, {"name": d.get("name", source)}, where)["name"]
        stages = d.get("stages") or []
        if not isinstance(stages, list):
            raise ConfigError(f"{where}: stages must be a list of {{name, params}} mappings")
        out = dict(_spec_mapping(d.get("output"), f"{where}: output"))
        shard_max_bytes = out.pop("shard_max_bytes", DEFAULT_SHARD_MAX_BYTES)
        return cls(
            name=name,
            source=source,
            source_params=source_params,
            stages=tuple(_stage_spec(s, f"{where}: stage {i}") for i, s in enumerate(stages, 1)),
            contents=from_mapping(CacheContents, out, f"{where}: output"),
            **check_values(cls, {"shard_max_bytes": shard_max_bytes}, f"{where}: output"),
        )

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


def _spec_mapping(value: Any, where: str, keys: tuple[str, ...] | None = None) -> dict[str, Any]:
    """``value`` (None: empty) if it is a mapping with string keys among ``keys`` (None: any);
    otherwise a :class:`ConfigError` naming ``where``."""
    if value is None:
        return {}
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ConfigError(f"{where}: must be a mapping (key: value), got {type(value).__name__}")
    unknown = sorted(set(value) - set(keys or value))
    if unknown:
        raise ConfigError(f"{where}: unknown keys {unknown}; known: {list(keys or ())}")
    return value


def _stage_spec(value: Any, where: str) -> StageSpec:
    """A stage of a spec, its parameters built (and so checked) by the stage's parameter class
    first here, so that an error names the stage's position in the spec."""
    stage = _spec_mapping(value, where, STAGE_KEYS)
    name = stage.get("name")
    if not isinstance(name, str):
        raise ConfigError(f"{where}: name = {name!r}: must be the name of a registered stage")
    try:
        get_stage(name)
    except KeyError as e:
        raise ConfigError(f"{where}: {e.args[0]}") from None
    where = f"{where} ({name})"
    params = _spec_mapping(stage.get("params"), f"{where}: params")
    stage_params(name, params, where)
    return StageSpec(name, dict(params))


SPEC_SUFFIXES = (".yaml", ".yml")


def bundled_pipelines() -> list[str]:
    """Names of the pipeline specs that ship with the toolkit (``pipelines/*.yaml``)."""
    root = importlib.resources.files("phigenesis.pipelines")
    return sorted(p.name[: -len(".yaml")] for p in root.iterdir() if p.name.endswith(".yaml"))


def is_spec_path(name_or_path: str | os.PathLike[str]) -> bool:
    """Whether ``name_or_path`` names a spec file rather than a bundled pipeline: it ends in
    ``.yaml``/``.yml`` or holds a path separator. A bare name is always a bundled pipeline, so a
    folder called ``waymo`` in the working directory does not shadow the bundled ``waymo``."""
    text = os.fspath(name_or_path)
    separators = [s for s in (os.sep, os.altsep, "/") if s]
    return text.lower().endswith(SPEC_SUFFIXES) or any(s in text for s in separators)


def load_pipeline(name_or_path: str | os.PathLike[str]) -> PipelineSpec:
    """A pipeline spec from a YAML file (a ``.yaml``/``.yml`` path, or any path with a separator)
    or, for a bare name, the bundled spec of that name (see :func:`is_spec_path`)."""
    if is_spec_path(name_or_path):
        path = Path(name_or_path)
        if not path.exists():
            raise PrepError(f"{path}: pipeline spec not found")
        text = read_small_file(path, "pipeline spec", PrepError)
        where = str(path)
    else:
        name = os.fspath(name_or_path)
        res = importlib.resources.files("phigenesis.pipelines") / f"{name}.yaml"
        if not name or not res.is_file():
            raise PrepError(
                f"no bundled pipeline named {name!r}; the bundled ones are "
                f"{', '.join(bundled_pipelines())} (a spec file needs a .yaml or .yml suffix, "
                "or a path such as ./my-spec)"
            )
        text = res.read_text()
        where = f"pipelines/{name}.yaml"
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
    #: The failure was in writing the cache (a full disk, ...), not in the scene: the run stops
    #: whatever the error policy, and the scene is not recorded as failed.
    error_stops_run: bool = False
    #: What the source left out of the scene as invalid, count per kind
    #: (:meth:`~phigenesis.data.records.DroppedValues.totals`), and the same as one line for the
    #: log (:meth:`~phigenesis.data.records.DroppedValues.describe`; "" if nothing).
    dropped: dict[str, int] = field(default_factory=dict)
    dropped_description: str = ""
    #: CPU seconds of the scene's parts (:meth:`StageTimings.as_dict`); empty on failure.
    timings: dict[str, Any] = field(default_factory=dict)


def process_scene(task: SceneTask, progress: ProgressHandle | None = None) -> SceneResult:
    """Loads one scene, runs the pipeline's stages and writes its shards. Never raises: a failure
    comes back as ``SceneResult.error`` (with nothing of the scene left on disk under final names
    that the manifest would list). The CPU time of each part (the stages' per-scene work, each
    stage's per-frame work, the read and the write) comes back in ``SceneResult.timings`` and goes
    to the log at INFO, with what the written rows hold (:class:`~phigenesis.data.coverage.SceneCoverage`)."""
    t0 = time.perf_counter()
    try:
        spec = PipelineSpec.from_dict(task.pipeline)
        source = make_source(task.source, task.arguments)
        timings = StageTimings()
        scene = timings.scene_work("load", lambda: source.load(task.scene_id))
        scene.frames = timings.marked(scene.frames, "read")
        total = len(scene.frames)
        for st in spec.stages:
            if progress is not None:  # the bar runs from here, so its rate counts the scene's setup
                progress.put((task.scene_id, 0, total, f"{st.name} (per scene)"))
            scene = timings.scene_work(
                st.name, lambda st=st, scene=scene: run_stage(st.name, scene, st.params)
            )
            scene.frames = timings.marked(scene.frames, st.name)
        schema = frame_schema(
            spec.contents,
            {"phigenesis.source": scene.source, "phigenesis.scene_metadata": json.dumps(scene.metadata)},
        )
        coverage = SceneCoverage(scene.scene_id)
        with ShardWriter(Path(task.cache_dir), scene.scene_id, schema, spec.shard_max_bytes) as writer:
            for i, frame in enumerate(timings.frames(scene.frames)):
                writer.write(frame_to_batch(frame, scene.source, schema))
                coverage.add(frame)
                timings.written()
                if progress is not None:
                    progress.put((task.scene_id, i + 1, total, ""))
        coverage.report()
        log.info("scene %s: %s", scene.scene_id, timings.describe())
        return SceneResult(
            task.scene_id,
            scene.source,
            total,
            writer.shards,
            None,
            time.perf_counter() - t0,
            dropped=scene.dropped.totals(),
            dropped_description=scene.dropped.describe(),
            timings=timings.as_dict(),
        )
    except Exception as e:  # reported per scene; the coordinator applies the error policy
        log.debug("scene %s failed:\n%s", task.scene_id, traceback.format_exc())
        return SceneResult(
            task.scene_id,
            task.source,
            error=describe(e),
            seconds=time.perf_counter() - t0,
            error_is_input=isinstance(e, PhiGenesisError),
            error_stops_run=isinstance(e, CacheWriteError),
        )


class StageTimings:
    """CPU seconds (this process, all threads: ``time.process_time``) of each part of a scene's
    conversion: the per-scene work of the source and of each stage (its setup and whatever it does
    when called, such as the LiDAR aggregation reading every frame's geometry), and per frame the
    read, each stage and the write of the row.

    Stages wrap the frames lazily, one layer each, so loading a frame runs the read, then each
    stage in order; a marker layer after each records the clock as the frame leaves it, and the
    time between two markers is that stage's. Markers count only while the rows are written
    (:meth:`frames`), not in the scene-wide passes of stages like ``aggregate_lidar``. A stage
    that works eagerly on a list of frames counts as per-scene work.
    """

    def __init__(self) -> None:
        self.scene_s: dict[str, float] = {}
        self.frame_s: dict[str, float] = {}
        self.frame_count = 0
        self._writing = False
        self._last = 0.0

    def scene_work(self, name: str, work: Callable[[], Scene]) -> Scene:
        start = time.process_time()
        result = work()
        self.scene_s[name] = self.scene_s.get(name, 0.0) + time.process_time() - start
        return result

    def marked(self, frames: Sequence[Frame], name: str) -> Sequence[Frame]:
        """``frames`` with a marker layer after the part ``name`` (lazy frames only)."""
        if not isinstance(frames, LazyFrames):
            return frames
        self.frame_s.setdefault(name, 0.0)

        def mark(frame: Frame) -> Frame:
            if self._writing:
                now = time.process_time()
                self.frame_s[name] += now - self._last
                self._last = now
            return frame

        return frames.map(mark)

    def frames(self, frames: Sequence[Frame]) -> Iterator[Frame]:
        """Iterates ``frames`` for writing, the clock started before each frame is loaded."""
        self._writing = True
        self._last = time.process_time()
        try:
            yield from frames
        finally:
            self._writing = False

    def written(self) -> None:
        """Marks a row written: the time since the last stage's marker is the write's."""
        now = time.process_time()
        self.frame_s["write"] = self.frame_s.get("write", 0.0) + now - self._last
        self._last = now
        self.frame_count += 1

    def as_dict(self) -> dict[str, Any]:
        return {"frames": self.frame_count, "scene_s": dict(self.scene_s), "frame_s": dict(self.frame_s)}

    def describe(self) -> str:
        n = max(self.frame_count, 1)
        per_frame = ", ".join(f"{k} {v / n:.2f}" for k, v in self.frame_s.items())
        per_scene = ", ".join(f"{k} {v:.2f}" for k, v in self.scene_s.items())
        total = (sum(self.frame_s.values()) + sum(self.scene_s.values())) / n
        return (
            f"{total:.2f} CPU-s per frame over {self.frame_count} frames; per frame: {per_frame}; "
            f"per scene: {per_scene}"
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
    #: CPU seconds of each written scene's parts, by scene id (:meth:`StageTimings.as_dict`).
    timings: dict[str, dict[str, Any]] = field(default_factory=dict)

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


class PrepInterrupted(KeyboardInterrupt):
    """The interrupt (Ctrl-C) that stopped :func:`prepare`, raised once the cache is consistent:
    every scene recorded complete is in the manifest, worker processes are stopped, unfinished
    files are removed and the lock is released. ``str()`` is one line saying what was kept and how
    to resume.

    Attributes:
        cache_dir: the cache directory of the run.
        scenes_complete: complete scenes of the cache the run was building.
        scenes_total: the scenes of the run.
        frames_complete: frames of the complete scenes.
        staging_dir: where an overwrite keeps the complete scenes of the new version for a rerun
            (the cache in ``cache_dir`` is unchanged); None for a run that was not an overwrite,
            or when nothing of the new version was kept.
    """

    def __init__(
        self,
        message: str,
        cache_dir: str,
        scenes_complete: int,
        scenes_total: int,
        frames_complete: int,
        staging_dir: str | None = None,
    ):
        super().__init__(message)
        self.cache_dir = cache_dir
        self.scenes_complete = scenes_complete
        self.scenes_total = scenes_total
        self.frames_complete = frames_complete
        self.staging_dir = staging_dir

    def __str__(self) -> str:
        return str(self.args[0])


def _open_source(
    source: str, source_overrides: dict[str, Any] | None, pipeline: str | os.PathLike[str] | PipelineSpec
) -> tuple[PipelineSpec, dict[str, Any], list[str]]:
    """The spec, the source's resolved arguments and its scene ids: everything is checked and the
    source opened before the cache directory is touched, so a bad input changes nothing."""
    spec = pipeline if isinstance(pipeline, PipelineSpec) else load_pipeline(pipeline)
    if spec.source != source:
        raise PrepError(f"pipeline {spec.name!r} is for source {spec.source!r}, not {source!r}")
    try:
        src = make_source(source, _merge(spec.source_params, source_overrides or {}))
    except ConfigError as e:  # names the source, the key, the value and what it allows
        raise PrepError(str(e)) from e
    except (TypeError, ValueError) as e:
        raise PrepError(f"invalid {source} arguments: {e}") from e
    try:
        scene_ids = list(dict.fromkeys(src.scene_ids()))
    except (ValueError, OSError) as e:
        raise PrepError(f"cannot list the {source} scenes: {e}") from e
    return spec, src.arguments(), scene_ids


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
        overwrite: replace a cache made with other arguments, or with an unreadable manifest. The
            new cache is built in ``out/.phigenesis-staging/`` and swapped in once complete, so
            until then the old one stays readable, and a failed or killed overwrite leaves it as
            it was (a rerun of the same overwrite resumes the staged scenes).
        on_error: "raise" stops at the first failed scene (finished scenes stay recorded);
            "skip" records the failure in the manifest and goes on.
        progress: show a progress bar per scene.

    Returns:
        A :class:`PrepSummary`. Raises :class:`PrepError` when the run cannot start (another run
        holds ``out``'s lock, the inputs are bad, ``out`` holds something else) or a scene fails
        with ``on_error="raise"``; :class:`~phigenesis.data.shards.CacheWriteError` (whatever
        ``on_error``) when a cache file cannot be written; :class:`PrepInterrupted` on Ctrl-C.
        In every case the cache is left consistent and the lock released.
    """
    t0 = time.perf_counter()
    out = Path(out)
    spec, arguments, scene_ids = _open_source(source, source_overrides, pipeline)
    pipeline_dict = spec.to_dict()
    check_out_dir(out)
    with CacheLock(out, "prep"):
        run = start_run(out, source, arguments, pipeline_dict, scene_ids, overwrite)
        summary = PrepSummary(str(out))
        tasks = _pending_tasks(run, scene_ids, source, arguments, pipeline_dict, summary)
        _run_scenes(run, tasks, scene_ids, summary, executor, workers, ray_address, on_error, progress)
        if run.staged:
            _swap_staged(run, len(scene_ids))
    summary.seconds = time.perf_counter() - t0
    return summary


def _pending_tasks(
    run: CacheRun,
    scene_ids: list[str],
    source: str,
    arguments: dict[str, Any],
    pipeline_dict: dict[str, Any],
    summary: PrepSummary,
) -> list[SceneTask]:
    """The scenes left to do (those not complete in the run's manifest), as tasks writing into
    the run's target; the complete ones go into ``summary``."""
    tasks = []
    for sid in scene_ids:
        entry = run.manifest.scene(sid)
        if entry is not None and entry.status == "complete":
            summary.scenes_already_complete.append(sid)
        else:
            tasks.append(SceneTask(str(run.target), source, arguments, pipeline_dict, sid))
    if summary.scenes_already_complete:
        log.info(
            "%d of %d scenes already complete; skipping them",
            len(summary.scenes_already_complete),
            len(scene_ids),
        )
    return tasks


def _run_scenes(
    run: CacheRun,
    tasks: list[SceneTask],
    scene_ids: list[str],
    summary: PrepSummary,
    executor: ExecutorName,
    workers: int,
    ray_address: str | None,
    on_error: OnError,
    progress: bool,
) -> None:
    """Runs the scene tasks and records each result in the manifest as it comes.

    However the loop ends early (a failed scene under ``on_error="raise"``, a write error, an
    interrupt), the workers are stopped before anything else, then the unfinished files are
    removed; an interrupt comes out as :class:`PrepInterrupted`."""
    bars = _ProgressBars(enabled=progress)
    results = run_tasks(process_scene, tasks, executor, workers, ray_address, bars.update)
    try:
        with contextlib.closing(results):  # closing stops the workers
            for result in results:
                bars.finish(result.scene_id)
                _record(run, result, summary, on_error)
    except KeyboardInterrupt as e:
        raise _interrupted(run, len(scene_ids)) from e
    except BaseException:
        run.tidy_after_stop()
        raise
    finally:
        bars.close()


def _record(run: CacheRun, result: SceneResult, summary: PrepSummary, on_error: OnError) -> None:
    """Commits one scene's result to the manifest (saved at once) and applies the error policy."""
    if result.error is not None and result.error_stops_run:
        raise CacheWriteError(f"{result.error} ({run.what_is_kept('rerun the same command to resume')})")
    if result.error is None:
        entry = SceneEntry(
            result.scene_id,
            result.source,
            result.frames,
            "complete",
            [s.path for s in result.shards],
            dropped=result.dropped,
        )
        run.commit(entry, result.shards)
        summary.scenes_written.append(result.scene_id)
        summary.frames_written += result.frames
        summary.bytes_written += sum(s.bytes for s in result.shards)
        summary.timings[result.scene_id] = result.timings
        if result.dropped_description:
            log.warning("scene %s: the source left out %s", result.scene_id, result.dropped_description)
    else:
        status = "skipped" if on_error == "skip" else "failed"
        run.commit(SceneEntry(result.scene_id, result.source, 0, status, [], result.error))
        summary.scenes_skipped[result.scene_id] = result.error
    if result.error is None:
        return
    if on_error == "raise":
        kept = run.what_is_kept("--on-error skip converts the rest")
        raise PrepError(f"scene {result.scene_id} failed: {result.error} ({kept})")
    log.warning("skipped scene %s: %s", result.scene_id, result.error)


def _interrupted(run: CacheRun, scenes_total: int) -> PrepInterrupted:
    """Leaves an interrupted run's cache consistent and says what was kept."""
    with contextlib.suppress(OSError):  # the scene recorded last may not have been saved yet
        run.manifest.save(run.target)
    run.tidy_after_stop()
    complete = run.complete_scenes()
    frames = sum(s.frames for s in complete)
    args = (str(run.out), len(complete), scenes_total, frames)
    if not run.staged:
        return PrepInterrupted(
            f"interrupted: {len(complete)} of {scenes_total} scenes ({frames} frames) are complete in "
            f"{run.out}; rerun the same command to resume",
            *args,
        )
    if not complete:
        return PrepInterrupted(
            f"interrupted: the cache in {run.out} is unchanged; no scene of its new version was complete",
            *args,
        )
    return PrepInterrupted(
        f"interrupted: the cache in {run.out} is unchanged; {len(complete)} of {scenes_total} scenes of "
        f"its new version are kept in {run.target}; rerun the same command to resume",
        *args,
        staging_dir=str(run.target),
    )


def _swap_staged(run: CacheRun, scenes_total: int) -> None:
    """Swaps a complete overwrite into place; an interrupt during the swap is PrepInterrupted."""
    try:
        swap_in(run.out, run.target)
    except KeyboardInterrupt as e:
        complete = run.complete_scenes()
        raise PrepInterrupted(
            f"interrupted while swapping the new version of the cache into {run.out}; rerun the same "
            "command to finish",
            str(run.out),
            len(complete),
            scenes_total,
            sum(s.frames for s in complete),
        ) from e


class _ProgressBars:
    """One tqdm bar per running scene, fed by progress messages: it starts when the scene's stages
    start (so its rate and ETA include the per-scene work) and names the per-scene step running."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.bars: dict[str, Any] = {}

    def update(self, msg: ProgressMessage) -> None:
        if not self.enabled:
            return

        key, done, total, phase = msg
        bar = self.bars.get(key)
        if bar is None:
            # smoothing 0: the rate is the scene's average since its start (setup included), as
            # the summary's s/frame is, not the last frames' write rate.
            bar = self.bars[key] = tqdm(
                total=total, desc=key, unit="frame", leave=True, dynamic_ncols=True, smoothing=0
            )
        bar.set_postfix_str(phase, refresh=False)
        bar.update(done - bar.n)
        if done == bar.n and phase:
            bar.refresh()

    def finish(self, key: str) -> None:
        bar = self.bars.pop(key, None)
        if bar is not None:
            bar.close()

    def close(self) -> None:
        for key in list(self.bars):
            self.finish(key)
