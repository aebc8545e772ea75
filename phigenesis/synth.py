"""Synthetic scenes written in a dataset's own format: the library behind ``phigenesis-synth``.

::

    phigenesis-synth --format waymo-v1 --out dir/   ->  synth("waymo-v1", "dir/")
    phigenesis-synth --format waymo-v2 --preset waymo --render-scale 4 --out dir/
        ->  synth("waymo-v2", "dir/", preset="waymo", render_scale=4)

The files are what the dataset's readers are tested against: reading them back must give the
synthetic truth (see :mod:`phigenesis.data.sources.synthetic.waymo_export`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from phigenesis.data.sources.synthetic import SyntheticConfig
from phigenesis.options import ConfigError

#: The formats ``phigenesis-synth`` writes.
SYNTH_FORMATS = ("waymo-v1", "waymo-v2", "nuscenes")


#: The rig each format writes.
FORMAT_RIGS = {"waymo-v1": "waymo5", "waymo-v2": "waymo5", "nuscenes": "nuscenes6"}


def synth(
    format: str,
    out: str | os.PathLike[str],
    *,
    scenes: int = 1,
    frames: int = 10,
    seed: int = 0,
    height: int | None = None,
    width: int | None = None,
    preset: str | None = None,
    render_scale: int = 1,
    keyframes: int = 3,
    version: str = "v1.0-mini",
    dropped: list[tuple[str, int]] | tuple[tuple[str, int], ...] = (),
    **params: Any,
) -> list[Path]:
    """Renders synthetic scenes and writes them under ``out`` in ``format``; returns the files.

    ``preset`` (``waymo`` for the Waymo formats, ``nuscenes`` for nuscenes; see
    :mod:`phigenesis.data.sources.synthetic.presets`) gives the real dataset's sensor sizes:
    image sizes, LiDARs, rates. ``height`` and ``width`` (pixels) override the preset's; without
    a preset they default to 160 x 240. ``render_scale`` casts the images at 1/render_scale of
    their size and resizes them (see :class:`~phigenesis.data.sources.synthetic.SyntheticConfig`).
    ``params`` are further ``SyntheticConfig`` fields (``lidar``, ``uniform_image_size``, ...).
    Waymo formats use the waymo5 rig and ``frames``.
    ``nuscenes`` uses the nuscenes6 rig and ``keyframes`` 2 Hz samples per scene (``frames`` is
    not used: the 12 Hz camera and 20 Hz LiDAR sweeps follow from them), writes the tables as
    ``version`` and leaves out the ``dropped`` (camera, 12 Hz step) sweeps (see
    :func:`~phigenesis.data.sources.synthetic.nuscenes_export.export_nuscenes`).
    """
    if format not in SYNTH_FORMATS:
        raise ValueError(f"unknown format {format!r}; choose one of {', '.join(SYNTH_FORMATS)}")
    values: dict[str, Any] = {
        "scenes": scenes,
        "frames": frames,
        "seed": seed,
        "rig": FORMAT_RIGS[format],
        "render_scale": render_scale,
        **({"height": height} if height is not None else {}),
        **({"width": width} if width is not None else {}),
        **params,
    }
    if preset is not None:
        # each exporter and the presets load only for the format asked for
        from phigenesis.data.sources.synthetic.presets import PRESETS

        if preset in PRESETS and PRESETS[preset]["rig"] != FORMAT_RIGS[format]:
            fits = [f for f in SYNTH_FORMATS if FORMAT_RIGS[f] == PRESETS[preset]["rig"]]
            raise ConfigError(
                f"preset {preset!r} does not match format {format!r}: "
                f"preset {preset!r} writes {' or '.join(fits)}"
            )
        config = SyntheticConfig.from_preset(preset, **values)
    else:
        config = SyntheticConfig.from_dict({"height": 160, "width": 240, **values})
    if format == "nuscenes":
        # each exporter and the presets load only for the format asked for
        from phigenesis.data.sources.synthetic.nuscenes_export import export_nuscenes

        return export_nuscenes(config, out, keyframes=keyframes, version=version, dropped=dropped)
    # each exporter and the presets load only for the format asked for
    from phigenesis.data.sources.synthetic.waymo_export import export_waymo

    return export_waymo(config, out, "v1" if format == "waymo-v1" else "v2")
