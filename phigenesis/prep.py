"""Build, check and look at caches: the library behind ``phigenesis-prep``.

Each function here is what the command of the same name runs::

    phigenesis-prep synthetic --out cache/ --scenes 2     ->  synthetic("cache/", scenes=2)
    phigenesis-prep waymo --input seg.tfrecord --out c/  ->  waymo("c/", input="seg.tfrecord")
    phigenesis-prep nuscenes --dataroot D --out c/    ->  nuscenes("c/", dataroot="D")
    phigenesis-prep verify cache/                         ->  verify("cache/")
    phigenesis-prep preview cache/ --frame 3 --out a.png  ->  preview("cache/", frame=3, out="a.png")
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.executors import ExecutorName
from phigenesis.data.pipeline import OnError, PipelineSpec, PrepSummary, prepare
from phigenesis.data.records import InvalidRecord
from phigenesis.data.shards import CacheReader, VerifyReport, verify_cache
from phigenesis.errors import CacheError


def synthetic(
    out: str | os.PathLike[str],
    *,
    scenes: int = 2,
    frames: int = 40,
    seed: int = 0,
    rig: str | None = None,
    height: int | None = None,
    width: int | None = None,
    preset: str | None = None,
    render_scale: int | None = None,
    pipeline: str | os.PathLike[str] | PipelineSpec = "synthetic",
    executor: ExecutorName = "local",
    workers: int = 1,
    ray_address: str | None = None,
    overwrite: bool = False,
    on_error: OnError = "raise",
    progress: bool = True,
    **source_params: Any,
) -> PrepSummary:
    """Renders ``scenes`` synthetic scenes of ``frames`` frames into a cache at ``out``.

    ``preset`` (``waymo`` or ``nuscenes``: the real rigs' image sizes and LiDARs, see
    :mod:`phigenesis.data.sources.synthetic.presets`) replaces the pipeline spec's sensors;
    ``rig``, ``height``, ``width``, ``render_scale`` and any other synthetic source parameter
    (:class:`~phigenesis.data.sources.synthetic.SyntheticConfig`) override both. See
    :func:`~phigenesis.data.pipeline.prepare` for the run options.
    """
    overrides: dict[str, Any] = {}
    if preset is not None:
        # the synthetic source (Open3D, trimesh) loads only for a synthetic preset
        from phigenesis.data.sources.synthetic.presets import preset_values

        overrides.update(preset_values(preset))
    explicit = {
        "scenes": scenes,
        "frames": frames,
        "seed": seed,
        "rig": rig,
        "height": height,
        "width": width,
        "render_scale": render_scale,
        **source_params,
    }
    overrides.update({k: v for k, v in explicit.items() if v is not None})
    return prepare(
        out,
        "synthetic",
        overrides,
        pipeline=pipeline,
        executor=executor,
        workers=workers,
        ray_address=ray_address,
        overwrite=overwrite,
        on_error=on_error,
        progress=progress,
    )


def waymo(
    out: str | os.PathLike[str],
    *,
    input: str | os.PathLike[str],
    split: str | None = None,
    segments: list[str] | tuple[str, ...] = (),
    format: str = "auto",
    check_crc: bool = True,
    pipeline: str | os.PathLike[str] | PipelineSpec = "waymo",
    executor: ExecutorName = "local",
    workers: int = 1,
    ray_address: str | None = None,
    overwrite: bool = False,
    on_error: OnError = "raise",
    progress: bool = True,
) -> PrepSummary:
    """Converts Waymo Open Dataset segments (v1 TFRecord or v2 Parquet, detected) into a cache.

    ``input`` is a ``.tfrecord`` file, a folder of them, or a v2 root; ``split`` picks a subfolder
    and ``segments`` keeps segments by name or shell pattern (see
    :class:`~phigenesis.data.sources.waymo.WaymoConfig`). An invalid record fails its segment
    with an error naming the file, the record and the field; with ``on_error="skip"`` only the
    invalid part is left out (a box, an image, a LiDAR, a frame; counted in the manifest), a
    segment that cannot be read at all is skipped, and the manifest lists it with the reason.
    """
    overrides = {
        "input": str(Path(input).expanduser().resolve()),
        "split": split,
        "segments": list(segments),
        "format": format,
        "check_crc": check_crc,
        "on_error": on_error,
    }
    return prepare(
        out,
        "waymo",
        overrides,
        pipeline=pipeline,
        executor=executor,
        workers=workers,
        ray_address=ray_address,
        overwrite=overwrite,
        on_error=on_error,
        progress=progress,
    )


def nuscenes(
    out: str | os.PathLike[str],
    *,
    dataroot: str | os.PathLike[str],
    version: str = "v1.0-mini",
    scenes: list[str] | tuple[str, ...] = (),
    pipeline: str | os.PathLike[str] | PipelineSpec = "nuscenes",
    executor: ExecutorName = "local",
    workers: int = 1,
    ray_address: str | None = None,
    overwrite: bool = False,
    on_error: OnError = "raise",
    progress: bool = True,
) -> PrepSummary:
    """Converts nuScenes scenes (the JSON tables of ``version`` under ``dataroot``) into a cache.

    ``scenes`` keeps scenes by name or shell pattern (see
    :class:`~phigenesis.data.sources.nuscenes.NuScenesConfig`). A bad record (a dangling token, a
    missing file, an unknown category) fails its scene with an error naming the table, token or
    file; with ``on_error="skip"`` the record is left out and listed in the scene's metadata
    (``skipped``), and a scene that cannot be read at all is listed in the manifest.
    """
    overrides = {
        "dataroot": str(Path(dataroot).expanduser().resolve()),
        "version": version,
        "scenes": list(scenes),
        "on_error": on_error,
    }
    return prepare(
        out,
        "nuscenes",
        overrides,
        pipeline=pipeline,
        executor=executor,
        workers=workers,
        ray_address=ray_address,
        overwrite=overwrite,
        on_error=on_error,
        progress=progress,
    )


def verify(cache_dir: str | os.PathLike[str]) -> VerifyReport:
    """Re-checks a cache against its manifest: the manifest's schema and shard paths, then every
    shard's size, SHA-256, footer, rows, columns and schema version and each row's and column's
    CRC, then whether the run that wrote it finished every scene it asked for (see
    :func:`~phigenesis.data.shards.verify_cache`). Never raises on a bad cache: each problem is a
    line of ``report.errors`` naming the shard, row and column; ``report.status`` is ``DAMAGED``,
    ``INCOMPLETE`` (``report.unfinished`` names the scenes) or ``OK``."""
    return verify_cache(cache_dir)


def preview(
    cache_dir: str | os.PathLike[str],
    frame: int = 0,
    out: str | os.PathLike[str] | None = None,
    scale: int = 2,
) -> NDArray[np.uint8]:
    """Draws global frame ``frame`` of a cache; writes a PNG to ``out`` if given. Returns RGB.

    A value of the frame that is invalid (an image that does not decode, ...) raises a
    :class:`~phigenesis.errors.CacheError` naming the shard, the row and the field."""
    # the preview's drawing (OpenCV fonts, colour maps) loads only for previews
    from phigenesis.data.preview import draw_frame

    reader = CacheReader(cache_dir)
    try:
        image = draw_frame(reader.frame(frame), scale=scale, cache_source=reader.manifest.source)
    except InvalidRecord as e:
        path, row = reader.locate(frame)
        raise CacheError(f"{path}: row {row}: {e}") from None
    if out is not None:
        out = Path(out)
        if out.parent and not out.parent.exists():
            out.parent.mkdir(parents=True)
        if not cv2.imwrite(str(out), image[..., ::-1]):
            raise OSError(f"could not write {out}")
    return image
