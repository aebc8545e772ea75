"""Stage 2's training data: the VAE latents of target windows and of their conditions, computed
once into a cache of their own, so that a training step does no VAE or rasterizer work.

A *window* is ``history_frames`` consecutive frames of a scene (the history) followed by
``window_frames`` frames to generate (the targets). For every window of every scene of a frame
cache, :func:`precompute_stage2` writes one row holding:

- ``z_history`` [V, C, T_h, h, w] and ``z_target`` [V, C, T, h, w]: the frozen VAE's latents
  (posterior mode) of the history's and the targets' images at the Stage 1 model's size;
- ``z_render`` [V, C, T, h, w]: the latents of the history's Gaussians (``geometry``: ``stage1``,
  ``cache`` or ``truth``, :mod:`phigenesis.rollout.conditions`) rendered at every target camera at
  its own capture time, holes black;
- ``u_<kind>`` [V, T, h, w]: each uncertainty map of :mod:`phigenesis.models.uncertainty`
  (``coverage``, ``random``, ``entropy``, ``localization_potential``; ``entropy`` only where the
  Gaussians carry a depth entropy) at image resolution, pooled to the latent grid
  (:func:`~phigenesis.models.stereo_forcing.pool_to_latent`), so that training picks the kind;
- the target and history cameras (``world_from_camera`` [F, V, 4, 4] float64, ``intrinsics``
  [V, 3, 3] at the model's size, capture times [F, V] in seconds after the window's first history
  frame).

The cache has the frame caches' layout (``manifest.json`` naming every shard with its checksums;
shards written under temporary names and renamed; one scene at a time, each committed once its
shards are complete, under the cache's lock, as every cache is written:
:mod:`phigenesis.data.cache_run`; a killed run resumes after the last finished scene), its
manifest's ``source`` is ``stage2-latents`` and its ``arguments`` say what made it;
``phigenesis-prep verify`` checks it as any cache. Latents are stored as flat float32 lists with
their shape beside them (any Arrow reader can open them).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch
from torch import Tensor
from tqdm import tqdm

from phigenesis.data.cache_run import writing_cache
from phigenesis.data.clips import Clip, Stage1Clips
from phigenesis.data.schema import SCHEMA_VERSION
from phigenesis.data.shards import (
    MANIFEST_NAME,
    CacheError,
    CacheReader,
    Manifest,
    SceneEntry,
    ShardInfo,
    ShardWriter,
)
from phigenesis.models.stage1 import Stage1Model
from phigenesis.models.stereo_forcing import pool_to_latent
from phigenesis.rollout.conditions import (
    UNCERTAINTY_KINDS,
    context_cameras,
    future_cameras,
    history_scene,
    render_condition,
    truth_maps,
    uncertainty_maps,
)
from phigenesis.rollout.config import Stage2DataConfig

log = logging.getLogger(__name__)

#: The manifest ``source`` of a Stage 2 latent cache.
LATENT_SOURCE = "stage2-latents"


@dataclass
class Stage2Sample:
    """One window's row, as tensors (shapes in the module docstring)."""

    scene_id: str
    history_indices: list[int]
    target_indices: list[int]
    time_origin_micros: int
    z_history: Tensor
    z_target: Tensor
    z_render: Tensor
    u: dict[str, Tensor]
    world_from_camera: Tensor  # [F, V, 4, 4] targets
    history_world_from_camera: Tensor  # [F_h, V, 4, 4]
    intrinsics: Tensor  # [V, 3, 3] at image_hw
    time_s: Tensor  # [F, V]
    history_time_s: Tensor  # [F_h, V]
    image_hw: tuple[int, int]
    render_coverage: float = 0.0  # mean share of target pixels the render covers
    extra: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# One window


def window_clip(data: Stage1Clips, scene_id: str, start: int, cfg: Stage2DataConfig) -> Clip:
    """The Stage 1 clip of the window whose history starts at ``start``: its context is the
    history, its targets beyond the context the frames to generate."""
    offsets = list(range(1, cfg.window_frames + 1))
    return data.clip(scene_id, start, offsets, keep_frames=cfg.geometry == "truth")


def window_starts(length: int, cfg: Stage2DataConfig) -> list[int]:
    """History starts of the windows of a scene of ``length`` frames (each window lies inside it)."""
    last = length - cfg.history_frames - cfg.window_frames
    return list(range(0, last + 1, cfg.stride)) if last >= 0 else []


def _encode(model: Stage1Model, images: Tensor) -> Tensor:
    """[V, C, T_z, h, w] latents of [F, V, 3, H, W] images in [0, 1]."""
    return model.encode(images[None])[0]


def window_sample(
    model: Stage1Model, data: Stage1Clips, scene_id: str, start: int, cfg: Stage2DataConfig
) -> Stage2Sample:
    """The row of one window (see the module docstring)."""
    clip = window_clip(data, scene_id, start, cfg)
    t_h = len(clip.frame_indices)
    truth: dict[str, Any] = {}
    if cfg.geometry == "truth":
        depth, sem, flow = truth_maps(clip)
        truth = {"truth_depth_m": depth, "truth_semantic": sem, "truth_flow_mps": flow}
    scene = history_scene(cfg.geometry, clip, model, **truth)
    targets, history = future_cameras(clip), context_cameras(clip)
    cond = render_condition(scene, targets)
    hist_render = render_condition(scene, history)
    images = clip.targets.images
    with torch.no_grad():
        z_target = _encode(model, images[t_h:])
        z_history = _encode(model, images[:t_h])
        z_render = _encode(model, cond.rgb.permute(0, 1, 4, 2, 3))
    generator = torch.Generator().manual_seed(hash_text(f"{cfg.seed}/{scene_id}/{start}"))
    bins = int(model.config.adapter_config.depth_bins)
    maps = uncertainty_maps(
        cond, targets, history, hist_render.depth, bins, generator, cfg.random_patch_px, lp_trust=cfg.lp_trust
    )
    latent_hw = tuple(z_target.shape[-2:])
    tc = int(model.vae.config.temporal_compression)
    u = {k: pool_to_latent(m.permute(1, 0, 2, 3), latent_hw, tc) for k, m in maps.items()}  # [V, T_z, h, w]
    return Stage2Sample(
        scene_id=scene_id,
        history_indices=list(clip.frame_indices),
        target_indices=list(clip.target_indices[t_h:]),
        time_origin_micros=int(clip.time_origin_micros),
        z_history=z_history.float(),
        z_target=z_target.float(),
        z_render=z_render.float(),
        u=u,
        world_from_camera=targets.world_from_camera.double(),
        history_world_from_camera=history.world_from_camera.double(),
        intrinsics=clip.intrinsics.float(),
        time_s=targets.time_s.double(),
        history_time_s=history.time_s.double(),
        image_hw=targets.size_hw,
        render_coverage=float((cond.alpha >= 0.5).float().mean()),
    )


def hash_text(text: str) -> int:
    """A stable 63-bit integer of ``text`` (Python's ``hash`` of strings changes per process)."""
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") >> 1


# --------------------------------------------------------------------------------------------
# Rows


def _tensor_fields(name: str, dtype: pa.DataType, unit: str) -> list[pa.Field]:
    """A flat list column ``name`` and its shape column ``name_shape``."""
    return [
        pa.field(
            name, pa.list_(dtype), metadata={"unit": unit, "layout": f"row-major, shape in {name}_shape"}
        ),
        pa.field(f"{name}_shape", pa.list_(pa.int32())),
    ]


#: (column, Arrow value type, unit) of every tensor of a row.
TENSOR_COLUMNS: tuple[tuple[str, pa.DataType, str], ...] = (
    ("z_history", pa.float32(), "VAE latent [V, C, T_h, h, w]"),
    ("z_target", pa.float32(), "VAE latent [V, C, T, h, w]"),
    ("z_render", pa.float32(), "VAE latent [V, C, T, h, w]"),
    *((f"u_{k}", pa.float32(), "trust in [0, 1], [V, T, h, w]") for k in UNCERTAINTY_KINDS),
    ("world_from_camera", pa.float64(), "4x4 transforms [F, V, 4, 4], metres, OpenCV camera axes"),
    ("history_world_from_camera", pa.float64(), "4x4 transforms [F_h, V, 4, 4]"),
    ("intrinsics", pa.float32(), "pinhole [V, 3, 3] at image_hw, pixels"),
    ("time_s", pa.float64(), "capture times [F, V], seconds after time_origin_micros"),
    ("history_time_s", pa.float64(), "capture times [F_h, V], seconds after time_origin_micros"),
)


def latent_schema(metadata: dict[str, str]) -> pa.Schema:
    """The schema of a latent cache's rows (one row per window)."""
    fields = [
        pa.field("scene_id", pa.string()),
        pa.field("history_indices", pa.list_(pa.int32())),
        pa.field("target_indices", pa.list_(pa.int32())),
        pa.field("time_origin_micros", pa.int64()),
        pa.field("image_hw", pa.list_(pa.int32())),
        pa.field("render_coverage", pa.float32()),
    ]
    for name, dtype, unit in TENSOR_COLUMNS:
        fields += _tensor_fields(name, dtype, unit)
    meta = {
        "phigenesis.schema_version": str(SCHEMA_VERSION),
        "phigenesis.format": "one row per Stage 2 window",
    }
    return pa.schema(fields, metadata=meta | metadata)


def _tensors_of(sample: Stage2Sample) -> dict[str, Tensor | None]:
    return {
        "z_history": sample.z_history,
        "z_target": sample.z_target,
        "z_render": sample.z_render,
        **{f"u_{k}": sample.u.get(k) for k in UNCERTAINTY_KINDS},
        "world_from_camera": sample.world_from_camera,
        "history_world_from_camera": sample.history_world_from_camera,
        "intrinsics": sample.intrinsics,
        "time_s": sample.time_s,
        "history_time_s": sample.history_time_s,
    }


def sample_to_batch(sample: Stage2Sample, schema: pa.Schema) -> pa.RecordBatch:
    """The one-row batch of ``sample``; refuses a sample with NaN or Inf (nothing invalid enters)."""
    columns: dict[str, list[Any]] = {
        "scene_id": [sample.scene_id],
        "history_indices": [sample.history_indices],
        "target_indices": [sample.target_indices],
        "time_origin_micros": [sample.time_origin_micros],
        "image_hw": [list(sample.image_hw)],
        "render_coverage": [sample.render_coverage],
    }
    for (name, dtype, _), value in zip(TENSOR_COLUMNS, _tensors_of(sample).values(), strict=True):
        if value is None:
            columns[name], columns[f"{name}_shape"] = [None], [None]
            continue
        array = value.detach().cpu().numpy().astype(dtype.to_pandas_dtype())
        if not np.isfinite(array).all():
            raise ValueError(
                f"scene {sample.scene_id}, window {sample.history_indices[0]}: {name} holds NaN or Inf"
            )
        columns[name] = [pa.array(array.reshape(-1), dtype)]
        columns[f"{name}_shape"] = [list(array.shape)]
    arrays = []
    for f in schema:
        value = columns[f.name]
        if isinstance(value[0], pa.Array):
            arrays.append(pa.ListArray.from_arrays(pa.array([0, len(value[0])], pa.int32()), value[0]))
        else:
            arrays.append(pa.array(value, f.type))
    return pa.RecordBatch.from_arrays(arrays, schema=schema)


def _tensor(batch: pa.RecordBatch, name: str, where: str) -> Tensor | None:
    """Column ``name`` of a one-row batch as a tensor of its stored shape, checked."""
    values, shape = batch.column(name)[0], batch.column(f"{name}_shape")[0]
    if not values.is_valid:
        return None
    dims = [int(d) for d in shape.values.to_numpy(zero_copy_only=False)] if shape.is_valid else None
    flat = values.values.to_numpy(zero_copy_only=False)
    if dims is None or any(d < 0 for d in dims) or int(np.prod(dims)) != len(flat):
        raise CacheError(f"{where}: {name} holds {len(flat)} values, its shape says {dims}")
    if not np.isfinite(flat).all():
        raise CacheError(f"{where}: {name} holds NaN or Inf")
    return torch.from_numpy(flat.reshape(dims).copy())


def batch_to_sample(batch: pa.RecordBatch, where: str) -> Stage2Sample:
    """The :class:`Stage2Sample` of a row read from a latent cache; :class:`CacheError` naming
    ``where`` (shard and row) and the column when a value is missing, misshapen, non-finite or
    inconsistent with the others (a crafted or damaged cache)."""
    missing = [n for n in latent_schema({}).names if n not in batch.schema.names]
    if missing:
        raise CacheError(f"{where}: not a Stage 2 latent row (missing {', '.join(missing)})")
    t = {name: _tensor(batch, name, where) for name, _, _ in TENSOR_COLUMNS}
    for name in (
        "z_history",
        "z_target",
        "z_render",
        "u_coverage",
        "world_from_camera",
        "intrinsics",
        "time_s",
    ):
        if t[name] is None:
            raise CacheError(f"{where}: {name} is null")
    z = t["z_target"]
    assert z is not None
    if z.ndim != 5 or t["z_render"].shape != z.shape:  # type: ignore[union-attr]
        raise CacheError(
            f"{where}: z_target {tuple(z.shape)} and z_render {tuple(t['z_render'].shape)} differ"
        )  # type: ignore[union-attr]
    v, c, tz, h, w = z.shape
    zh = t["z_history"]
    if zh.ndim != 5 or zh.shape[:2] != (v, c) or zh.shape[3:] != (h, w):  # type: ignore[union-attr]
        raise CacheError(f"{where}: z_history {tuple(zh.shape)} does not fit z_target {tuple(z.shape)}")  # type: ignore[union-attr]
    u = {}
    for kind in UNCERTAINTY_KINDS:
        m = t[f"u_{kind}"]
        if m is None:
            continue
        if m.shape != (v, tz, h, w):
            raise CacheError(f"{where}: u_{kind} is {tuple(m.shape)}, expected {(v, tz, h, w)}")
        if m.min() < 0 or m.max() > 1:
            raise CacheError(f"{where}: u_{kind} leaves [0, 1]")
        u[kind] = m
    wfc = t["world_from_camera"]
    if wfc.ndim != 4 or wfc.shape[1:] != (v, 4, 4):  # type: ignore[union-attr]
        raise CacheError(f"{where}: world_from_camera is {tuple(wfc.shape)}, expected [F, {v}, 4, 4]")  # type: ignore[union-attr]
    if t["intrinsics"].shape != (v, 3, 3):  # type: ignore[union-attr]
        raise CacheError(f"{where}: intrinsics is {tuple(t['intrinsics'].shape)}, expected {(v, 3, 3)}")  # type: ignore[union-attr]
    hw = [int(x) for x in batch.column("image_hw")[0].values.to_numpy(zero_copy_only=False)]
    if len(hw) != 2 or min(hw) < 1:
        raise CacheError(f"{where}: image_hw {hw} is not two positive sizes")
    return Stage2Sample(
        scene_id=str(batch.column("scene_id")[0].as_py()),
        history_indices=list(batch.column("history_indices")[0].as_py()),
        target_indices=list(batch.column("target_indices")[0].as_py()),
        time_origin_micros=int(batch.column("time_origin_micros")[0].as_py()),
        z_history=zh,  # type: ignore[arg-type]
        z_target=z,
        z_render=t["z_render"],  # type: ignore[arg-type]
        u=u,
        world_from_camera=wfc,  # type: ignore[arg-type]
        history_world_from_camera=t["history_world_from_camera"],  # type: ignore[arg-type]
        intrinsics=t["intrinsics"],  # type: ignore[arg-type]
        time_s=t["time_s"],  # type: ignore[arg-type]
        history_time_s=t["history_time_s"],  # type: ignore[arg-type]
        image_hw=(hw[0], hw[1]),
        render_coverage=float(batch.column("render_coverage")[0].as_py() or 0.0),
    )


class Stage2Latents:
    """The windows of a latent cache: ``len``, ``[i]`` -> :class:`Stage2Sample`, ``arguments``
    (what made it). Raises :class:`CacheError` for a cache that is not a Stage 2 latent cache."""

    def __init__(self, cache_dir: str | os.PathLike[str], check_crc: bool = True):
        self.cache_dir = Path(cache_dir)
        self.reader = CacheReader(self.cache_dir, check_crc=check_crc)
        manifest = self.reader.manifest
        if manifest.source != LATENT_SOURCE:
            raise CacheError(
                f"{self.cache_dir / MANIFEST_NAME}: a cache of source {manifest.source!r}, not a Stage 2 "
                f"latent cache ({LATENT_SOURCE!r}); make one with phigenesis-train stage2 --precompute"
            )
        self.arguments = dict(manifest.arguments)
        if len(self.reader) == 0:
            raise CacheError(f"{self.cache_dir}: the latent cache holds no windows")

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, index: int) -> Stage2Sample:
        path, row = self.reader.locate(index)
        return batch_to_sample(self.reader.read(index), f"{path}: row {row}")


# --------------------------------------------------------------------------------------------
# The cache


def _latent_scene(
    model: Stage1Model,
    data: Stage1Clips,
    scene_id: str,
    config: Stage2DataConfig,
    schema: pa.Schema,
    target: Path,
) -> tuple[SceneEntry, list[ShardInfo]]:
    """Writes the rows of every window of one scene into complete shards in ``target``: (its
    manifest entry, its shards), for the caller to commit. A scene too short for a window is
    ``skipped``, without shards."""
    starts = window_starts(data.scene_length(scene_id), config)
    if not starts:
        need = config.history_frames + config.window_frames
        log.info(
            "scene %s: skipped (%d frames, a window needs %d)", scene_id, data.scene_length(scene_id), need
        )
        return SceneEntry(scene_id, LATENT_SOURCE, 0, "skipped", [], "too short"), []
    with ShardWriter(target, scene_id, schema) as writer:
        for start in starts:
            writer.write(sample_to_batch(window_sample(model, data, scene_id, start, config), schema))
        written = writer.close()
    return SceneEntry(scene_id, LATENT_SOURCE, len(starts), "complete", [s.path for s in written]), written


def precompute_stage2(
    shards: str | os.PathLike[str],
    out: str | os.PathLike[str],
    model: Stage1Model,
    config: Stage2DataConfig,
    *,
    stage1_checkpoint: str = "",
    progress: bool = False,
) -> Path:
    """Writes the latent cache of every window of the frame cache at ``shards`` into ``out`` (see
    the module docstring), with ``model`` (the trained Stage 1 model: its frozen VAE encodes, its
    adapter predicts ``geometry: stage1``). Written as every cache is
    (:mod:`phigenesis.data.cache_run`): under ``out``'s lock (PrepError while another run writes
    it), each scene committed once its shards are complete, so a rerun into ``out`` with the same
    inputs resumes after a kill or a full disk, skipping the scenes already finished; a folder
    holding a cache made from other inputs, or anything else, is refused (PrepError). Returns
    ``out``."""
    out = Path(out)
    data = Stage1Clips(shards, model.config.image_size, config.history_frames, "auto")
    if config.history_frames % int(model.config.frames):
        raise ValueError(
            f"history_frames {config.history_frames} must be a multiple of the Stage 1 model's frames "
            f"({model.config.frames})"
        )
    tc = int(model.vae.config.temporal_compression)
    if (config.window_frames - 1) % tc or (config.history_frames > 1 and (config.history_frames - 1) % tc):
        raise ValueError(
            f"window_frames {config.window_frames} and history_frames {config.history_frames} must be "
            f"1 + a multiple of the VAE's temporal compression ({tc})"
        )
    source_manifest = Manifest.load(shards)
    arguments = {
        **asdict(config),
        "frame_cache": str(Path(shards).resolve()),
        "frame_cache_fingerprint": source_manifest.fingerprint,
        "stage1_checkpoint": stage1_checkpoint,
        "model": model.name,
        "image_hw": list(model.config.image_size),
    }
    schema = latent_schema({"phigenesis.arguments": json.dumps(arguments, default=str)})
    scenes = data.reader.scene_ids()
    with writing_cache(out, LATENT_SOURCE, arguments, {}, scenes, LATENT_SOURCE) as run:
        todo = [s for s in scenes if not run.is_complete(s)]
        log.info("stage2 latents: %d scene(s), %d to do, into %s", len(scenes), len(todo), out)
        for scene_id in tqdm(todo, unit="scene", desc="stage2 latents", disable=not progress):
            run.commit(*_latent_scene(model, data, scene_id, config, schema, run.target))
    return out
