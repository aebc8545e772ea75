"""A run that writes a cache: one lock, one fingerprint and one commit protocol for every writer.

Prep (:func:`phigenesis.data.pipeline.prepare`), ``phigenesis-render``, ``phigenesis-generate`` and
Stage 2's latent cache all write their caches through this module:

1. the output folder is checked (a folder, writable) and the cache's lock
   (:class:`~phigenesis.data.cache_lock.CacheLock`) taken: a second writer is refused with a message
   naming the run that holds it;
2. :func:`start_run` finishes an overwrite that was stopped while swapping in its new version, then
   decides what the folder holds: this run's cache to resume (same :func:`fingerprint`: source,
   arguments, pipeline, schema version), a cache made otherwise (refused; prep's ``--overwrite``
   rebuilds it beside the old one in a staging folder), someone else's files (refused) or nothing.
   It removes what a killed run left unfinished and saves the manifest, recording which scenes the
   run asks for (``scenes_expected``), before any scene is written;
3. each scene's shards are written under temporary names and renamed once complete
   (:class:`~phigenesis.data.shards.ShardWriter`); then :meth:`CacheRun.commit` records the scene in
   the manifest, saved atomically. The manifest is the commit point: a killed run (or one stopped by
   a full disk) loses nothing it committed, and a rerun of the same command skips it;
4. on an error or an interrupt the unfinished files are removed; the lock is released however the
   run ends (the kernel releases a killed run's).

:func:`writing_cache` is steps 1-4 as one context manager, for writers without an overwrite mode.
``phigenesis-prep verify`` compares the scenes a manifest lists as finished with ``scenes_expected``
to tell an incomplete cache from a complete one (:func:`phigenesis.data.shards.verify_cache`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from phigenesis.data.cache.checksums import ShardInfo
from phigenesis.data.cache.files import (
    MANIFEST_NAME,
    SHARDS_DIR,
    STAGING_DIR,
    SWAP_MARKER,
    TMP_MARKER,
    CacheWriteError,
    atomic_write_bytes,
    fsync_dir,
    scene_id_problem,
)
from phigenesis.data.cache.manifest import Manifest, SceneEntry
from phigenesis.data.cache_lock import LOCK_NAME, CacheLock
from phigenesis.data.schema import SCHEMA_VERSION
from phigenesis.errors import CacheError, PrepError, argument
from phigenesis.version import __version__

#: The output folder and the overwrite switch, as a message names them (Python or command line).
OUT = argument("out", "--out")
OVERWRITE = argument("overwrite=True", "--overwrite")

log = logging.getLogger("phigenesis.prep")

#: Source arguments that do not make a cache another cache: the error policy. A scene that
#: completes under ``raise`` had nothing to leave out, so it is the scene ``skip`` makes, and a
#: rerun with ``--on-error skip`` after a failed scene resumes instead of being refused.
POLICY_ARGUMENTS = frozenset({"on_error"})


def fingerprint(source: str, arguments: dict[str, Any], pipeline: dict[str, Any]) -> str:
    """Hash of everything that determines a cache's rows (the arguments but the error policy,
    :data:`POLICY_ARGUMENTS`)."""
    arguments = {k: v for k, v in arguments.items() if k not in POLICY_ARGUMENTS}
    blob = json.dumps(
        {"source": source, "arguments": arguments, "pipeline": pipeline, "schema_version": SCHEMA_VERSION},
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(blob.encode()).hexdigest()


# --------------------------------------------------------------------------------------------
# The run


@dataclass
class CacheRun:
    """Where a run writes and what it has committed: ``target`` is the cache directory ``out``,
    or for an overwrite of an existing cache the staging folder inside it."""

    out: Path
    target: Path
    manifest: Manifest

    @property
    def staged(self) -> bool:
        return self.target != self.out

    def complete_scenes(self) -> list[SceneEntry]:
        return [s for s in self.manifest.scenes if s.status == "complete"]

    def is_complete(self, scene_id: str) -> bool:
        """Whether ``scene_id`` is committed complete (a rerun skips it)."""
        entry = self.manifest.scene(scene_id)
        return entry is not None and entry.status == "complete"

    def commit(self, entry: SceneEntry, shards: Sequence[ShardInfo] = ()) -> None:
        """Records a scene whose shard files are all complete under their final names (or a scene
        skipped or failed, without shards) and saves the manifest atomically: the commit point.
        Scenes are kept in the order of ``scenes_expected``."""
        self.manifest.record_scene(entry, list(shards))
        order = {sid: i for i, sid in enumerate(self.manifest.scenes_expected or [])}
        self.manifest.scenes.sort(key=lambda s: order.get(s.id, len(order)))
        self.manifest.save(self.target)

    def what_is_kept(self, advice: str) -> str:
        """What a run that stops now leaves, and ``advice`` where something was kept, for its error."""
        if not self.staged:
            return f"finished scenes are kept in {self.out}; {advice}"
        kept = len(self.complete_scenes())
        if not kept:
            return f"the cache in {self.out} is unchanged"
        return (
            f"the cache in {self.out} is unchanged; the {kept} finished scenes of its new version are kept "
            f"in {self.target} for a rerun; {advice}"
        )

    def tidy_after_stop(self) -> None:
        """After a run stopped early: removes its unfinished files, and an overwrite's staging
        folder if it holds no complete scene. Never raises (the error that stopped the run matters)."""
        try:
            if self.staged and not self.complete_scenes():
                clear_staging(self.target)
            else:
                clean_unfinished(self.target, self.manifest)
        except OSError as e:
            log.warning("could not remove the unfinished files in %s: %s", self.target, e)


# --------------------------------------------------------------------------------------------
# The output folder


def check_out_dir(out: Path) -> None:
    """Creates ``out`` if missing; PrepError if it is a file, cannot be created or is not writable."""
    if out.exists() and not out.is_dir():
        raise PrepError(f"{OUT} {out} is a file, not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise PrepError(f"{OUT} {out} cannot be created: {e.strerror or e}") from e
    probe = out / f".write-probe{TMP_MARKER}{uuid.uuid4().hex[:8]}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise PrepError(f"{OUT} {out} is not writable: {e.strerror or e}") from e


def refuse_links(cache_dir: Path) -> None:
    """Refuses a cache whose ``shards/`` (or staging folder) or manifest is a symbolic link:
    clean-up deletes files in them and the run rewrites the manifest, and neither may follow a link
    out of the cache."""
    for name in (SHARDS_DIR, STAGING_DIR, f"{STAGING_DIR}/{SHARDS_DIR}"):
        if (cache_dir / name).is_symlink():
            raise PrepError(
                f"{cache_dir / name} is a symbolic link; a cache's {name}/ must be a folder inside it"
            )
    for name in (MANIFEST_NAME, f"{STAGING_DIR}/{MANIFEST_NAME}"):
        if (cache_dir / name).is_symlink():
            raise PrepError(
                f"{cache_dir / name} is a symbolic link; a cache's {MANIFEST_NAME} must be a file inside it"
            )


def _describe_difference(
    old: Manifest, source: str, arguments: dict[str, Any], pipeline: dict[str, Any]
) -> str:
    # Compare as the manifest stores them (JSON: tuples become lists), like the fingerprint does.
    arguments, pipeline = json.loads(json.dumps([arguments, pipeline], default=str))
    diffs = []
    if old.source != source:
        diffs.append(f"source {old.source} -> {source}")
    for k in sorted((set(old.arguments) | set(arguments)) - POLICY_ARGUMENTS):
        if old.arguments.get(k) != arguments.get(k):
            diffs.append(f"{k} {old.arguments.get(k)!r} -> {arguments.get(k)!r}")
    if old.pipeline != pipeline:
        diffs.append("pipeline spec differs")
    if old.schema_version != SCHEMA_VERSION:
        diffs.append(f"schema version {old.schema_version} -> {SCHEMA_VERSION}")
    return ", ".join(diffs) or "fingerprint differs"


def _is_ours(path: Path) -> bool:
    """Whether a file in a ``shards/`` folder is one the toolkit writes (a shard or a temporary)."""
    return path.suffix == ".arrow" or TMP_MARKER in path.name


def remove_unlisted(cache_dir: Path, listed: set[str]) -> list[str]:
    """Removes the toolkit's files in ``cache_dir/shards/`` that ``listed`` (shard file names) does
    not name, and manifest temporaries; returns them relative to ``cache_dir``."""
    removed = []
    shard_dir = cache_dir / SHARDS_DIR
    if shard_dir.is_dir():
        for p in sorted(shard_dir.iterdir()):
            if _is_ours(p) and (TMP_MARKER in p.name or p.name not in listed):
                p.unlink(missing_ok=True)
                removed.append(p.relative_to(cache_dir).as_posix())
    for p in sorted(cache_dir.glob(f"{MANIFEST_NAME}{TMP_MARKER}*")):
        p.unlink(missing_ok=True)
        removed.append(p.name)
    return removed


def clean_unfinished(out: Path, manifest: Manifest) -> list[str]:
    """Removes temporary files and shards no manifest entry lists (left by a killed run)."""
    return remove_unlisted(out, {Path(sh.path).name for sh in manifest.shards})


def clear_staging(staging: Path) -> None:
    """Removes an overwrite's staging folder: its manifest, marker and shard files (anything else
    in it is not ours and stays, and so does the folder then)."""
    if not staging.is_dir():
        return
    remove_unlisted(staging, set())
    for name in (MANIFEST_NAME, SWAP_MARKER):
        (staging / name).unlink(missing_ok=True)
    for folder in (staging / SHARDS_DIR, staging):
        with contextlib.suppress(OSError):  # not empty: it holds files that are not ours
            folder.rmdir()


def _is_foreign(out: Path) -> bool:
    """True if ``out`` (which has no manifest) holds anything but the temporary files of a run
    killed before its first manifest write, a lock file or a staging folder. Our runs write the
    manifest before any shard, so shard files without a manifest are someone else's and are never
    deleted."""
    for p in out.iterdir():
        if p.name == SHARDS_DIR and p.is_dir() and not p.is_symlink():
            if any(TMP_MARKER not in q.name for q in p.iterdir()):
                return True
        elif p.name in (LOCK_NAME, STAGING_DIR):
            continue
        elif not p.name.startswith(f"{MANIFEST_NAME}{TMP_MARKER}"):
            return True
    return False


# --------------------------------------------------------------------------------------------
# Overwrites: a new version built in a staging folder and swapped in once complete


def swap_in(out: Path, staging: Path) -> None:
    """Replaces the cache in ``out`` by the complete new version in ``staging``.

    The swap is journaled: a marker in ``staging`` says it has begun, before anything of the old
    cache is touched; a run killed part-way is finished by the next run on ``out``
    (:func:`finish_swap`)."""
    atomic_write_bytes(staging / SWAP_MARKER, b"")
    finish_swap(out, staging)


def finish_swap(out: Path, staging: Path) -> None:
    """Completes a begun swap (idempotent): removes the old manifest, moves the new shards over the
    old ones, removes the old cache's other shard files, renames the new manifest into place and
    removes the staging folder. Between the first step and the rename ``out`` has no manifest, so
    a reader then fails with a clear error, never with a mix of the two versions."""
    new_manifest = staging / MANIFEST_NAME
    if new_manifest.is_file():  # else the rename was done: only the folder is left to remove
        new = Manifest.load(staging)
        (out / MANIFEST_NAME).unlink(missing_ok=True)
        fsync_dir(out)
        (out / SHARDS_DIR).mkdir(exist_ok=True)
        for sh in new.shards:
            moved = staging / sh.path
            if moved.exists():
                os.replace(moved, out / sh.path)
        remove_unlisted(out, {Path(sh.path).name for sh in new.shards})
        fsync_dir(out / SHARDS_DIR)
        os.replace(new_manifest, out / MANIFEST_NAME)
        fsync_dir(out)
    clear_staging(staging)


# --------------------------------------------------------------------------------------------
# Starting a run


def _open_existing(
    out: Path,
    source: str,
    arguments: dict[str, Any],
    pipeline: dict[str, Any],
    fp: str,
    overwrite: bool | None,
) -> tuple[Manifest | None, bool]:
    """The cache already in ``out``: (its manifest if this run resumes it, whether this run
    replaces it). Refuses a cache made otherwise (unless ``overwrite``; ``None``: the command has no
    overwrite mode) and a foreign folder."""
    if not (out / MANIFEST_NAME).exists():
        if _is_foreign(out):
            raise PrepError(
                f"{OUT} {out} is not empty and holds no phigenesis cache; choose a new or empty directory"
            )
        return None, False
    try:
        manifest = Manifest.load(out)
    except CacheError as e:
        if not overwrite:
            advice = f"Choose another {OUT}"
            if overwrite is False:
                advice = f"Rerun with {OVERWRITE} to rebuild the cache from scratch"
            raise PrepError(f"{e}. {advice}.") from e
        log.warning("replacing the cache in %s: %s", out, e)
        return None, True
    if manifest.fingerprint == fp:
        return manifest, False
    if not overwrite:
        advice = f"choose another {OUT}"
        if overwrite is False:
            advice = f"use {OVERWRITE} to replace it or {advice}"
        raise PrepError(
            f"{out} holds a cache made with other arguments "
            f"({_describe_difference(manifest, source, arguments, pipeline)}); {advice}"
        )
    log.warning("replacing the cache in %s made with other arguments", out)
    return None, True


def _open_staging(staging: Path, fp: str) -> Manifest | None:
    """The manifest of an interrupted overwrite with fingerprint ``fp`` staged in ``staging``
    (this run resumes it); otherwise clears whatever an other overwrite left there."""
    try:
        manifest = Manifest.load(staging) if (staging / MANIFEST_NAME).is_file() else None
    except CacheError as e:
        log.warning("discarding the unreadable staged cache in %s: %s", staging, e)
        manifest = None
    if manifest is not None and manifest.fingerprint == fp:
        return manifest
    clear_staging(staging)
    return None


def check_scene_ids(source: str, scenes: Sequence[str]) -> None:
    """PrepError naming the first scene id a cache cannot hold (see
    :func:`~phigenesis.data.shards.scene_id_problem`), before anything is written."""
    for scene_id in scenes:
        problem = scene_id_problem(scene_id)
        if problem:
            shown = scene_id if len(scene_id) <= 60 else scene_id[:57] + "..."
            raise PrepError(f"{source}: scene id {shown!r} {problem}; nothing was written")


def start_run(
    out: Path,
    source: str,
    arguments: dict[str, Any],
    pipeline: dict[str, Any],
    scenes: Sequence[str],
    overwrite: bool | None = None,
) -> CacheRun:
    """Decides where a run writes (``out``, or a staging folder when it replaces a cache), with
    the manifest it resumes or a new one, after clearing what killed runs left unfinished; records
    ``scenes`` (the scene ids the run's arguments ask for, in order) as the manifest's
    ``scenes_expected`` and saves it before any scene is written. The caller holds ``out``'s lock.

    ``overwrite``: replace a cache made with other arguments (prep's ``--overwrite``); False
    refuses it, suggesting ``--overwrite``; None (a command without an overwrite mode) refuses it."""
    check_scene_ids(source, scenes)
    fp = fingerprint(source, arguments, pipeline)
    refuse_links(out)
    staging = out / STAGING_DIR
    if (staging / SWAP_MARKER).exists():
        log.warning("%s: finishing the overwrite that was stopped while swapping in its new version", out)
        finish_swap(out, staging)
    manifest, replace = _open_existing(out, source, arguments, pipeline, fp, overwrite)
    target = out
    if replace:
        target = staging
        manifest = _open_staging(staging, fp)
        log.info(
            "building the new cache in %s; the cache in %s stays readable until the new one is complete",
            staging,
            out,
        )
    elif staging.is_dir():
        log.info("removing %s, left by an overwrite that did not finish", staging)
        clear_staging(staging)
    if manifest is None:
        manifest = Manifest(
            schema_version=SCHEMA_VERSION,
            source=source,
            arguments=arguments,
            pipeline=pipeline,
            fingerprint=fp,
            phigenesis_version=__version__,
        )
    manifest.scenes_expected = list(scenes)
    target.mkdir(exist_ok=True)
    removed = clean_unfinished(target, manifest)
    if removed:
        log.info(
            "removed %d unfinished files left by an interrupted run: %s", len(removed), ", ".join(removed)
        )
    manifest.save(target)
    return CacheRun(out, target, manifest)


@contextlib.contextmanager
def writing_cache(
    out: str | os.PathLike[str],
    source: str,
    arguments: dict[str, Any],
    pipeline: dict[str, Any],
    scenes: Sequence[str],
    command: str,
) -> Iterator[CacheRun]:
    """Holds ``out``'s lock for a run of ``command`` ("render", "generate", ...) that writes the
    scenes ``scenes`` of a cache of ``source`` made with ``arguments`` and ``pipeline``, and yields
    the :class:`CacheRun` to commit them to (see the module docstring). A rerun of the same command
    resumes; a folder holding a cache made otherwise, or anything else, is refused with a
    PrepError; whatever ends the run early, its unfinished files are removed, and a
    CacheWriteError (a full disk) says what was kept and that a rerun resumes.

    Example::

        with writing_cache(out, "rendered", arguments, pipeline, scene_ids, "render") as run:
            for scene_id in scene_ids:
                if not run.is_complete(scene_id):
                    with ShardWriter(run.target, scene_id, schema) as writer:
                        ...
                    run.commit(SceneEntry(scene_id, "rendered", n, "complete", paths), writer.shards)
    """
    out = Path(out)
    check_out_dir(out)
    with CacheLock(out, command):
        run = start_run(out, source, arguments, pipeline, scenes)
        try:
            yield run
        except CacheWriteError as e:  # a full disk: say what is kept, as prep does
            run.tidy_after_stop()
            raise CacheWriteError(f"{e} ({run.what_is_kept('rerun the same command to resume')})") from e
        except BaseException:
            run.tidy_after_stop()
            raise
