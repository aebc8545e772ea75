"""``phigenesis-export ply``: the Gaussians a trained Stage 1 model predicts for one frame of a cache."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from phigenesis.data.clips import Stage1Clips, clip_inputs
from phigenesis.export.ply import write_ply
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.loading import load_stage1

log = logging.getLogger(__name__)


def predict_frame(
    checkpoint: str | os.PathLike[str],
    shards: str | os.PathLike[str],
    frame: int,
    scene_id: str | None = None,
) -> GaussianScene:
    """The Gaussian scene (inference rules: no sky, only moving things move) of the clip starting
    at ``frame`` (a scene's frame index with ``scene_id``, else a global index into the cache).
    Its time origin is that frame's timestamp."""
    model = load_stage1(checkpoint)
    data = Stage1Clips(shards, model.config.image_size, model.config.frames)
    if scene_id is None:
        scenes = list(data.scenes.items())
        for sid, rows in scenes:
            if frame in rows:
                scene_id, frame = sid, rows.index(frame)
                break
        else:
            raise ValueError(f"{shards}: no frame {frame} (the cache has {len(data.reader)} frames)")
    if scene_id not in data.scenes:
        raise ValueError(f"{shards}: no scene {scene_id!r}")
    if not 0 <= frame <= data.scene_length(scene_id) - model.config.frames:
        raise ValueError(f"{shards}: scene {scene_id} has no clip starting at frame {frame}")
    clip = data.clip(scene_id, frame, [])
    return model.predict(*clip_inputs([clip]), time_origin_micros=clip.time_origin_micros)


def export_ply(
    checkpoint: str | os.PathLike[str],
    shards: str | os.PathLike[str],
    out: str | os.PathLike[str],
    frame: int,
    *,
    scene_id: str | None = None,
    t_s: float | None = None,
    sh_degree: int = 3,
) -> Path:
    """Writes the Gaussians of :func:`predict_frame` as a 3DGS PLY (see :mod:`phigenesis.export.ply`);
    ``t_s`` (seconds after the frame) places moving Gaussians at that time."""
    scene = predict_frame(checkpoint, shards, frame, scene_id)
    log.info("%d Gaussians (%d dynamic)", len(scene), int(scene.dynamic.sum()))
    return write_ply(scene, out, t_s=t_s, sh_degree=sh_degree)
