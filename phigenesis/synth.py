"""Synthetic scenes written in a dataset's own format: the library behind ``phigenesis-synth``.

::

    phigenesis-synth --format waymo-v1 --out dir/   ->  synth("waymo-v1", "dir/")

The files are what the dataset's readers are tested against: reading them back must give the
synthetic truth (see :mod:`phigenesis.data.sources.synthetic.waymo_export`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from phigenesis.data.sources.synthetic import SyntheticConfig

#: The formats ``phigenesis-synth`` writes.
SYNTH_FORMATS = ("waymo-v1", "waymo-v2", "nuscenes")


def synth(
    format: str,
    out: str | os.PathLike[str],
    *,
    scenes: int = 1,
    frames: int = 10,
    seed: int = 0,
    height: int = 160,
    width: int = 240,
    keyframes: int = 3,
    version: str = "v1.0-mini",
    dropped: list[tuple[str, int]] | tuple[tuple[str, int], ...] = (),
    **params: Any,
) -> list[Path]:
    """Renders synthetic scenes and writes them under ``out`` in ``format``; returns the files.

    ``params`` are further :class:`~phigenesis.data.sources.synthetic.SyntheticConfig` fields
    (``lidar``, ``uniform_image_size``, ...). Waymo formats use the waymo5 rig and ``frames``.
    ``nuscenes`` uses the nuscenes6 rig and ``keyframes`` 2 Hz samples per scene (``frames`` is
    not used: the 12 Hz camera and 20 Hz LiDAR sweeps follow from them), writes the tables as
    ``version`` and leaves out the ``dropped`` (camera, 12 Hz step) sweeps (see
    :func:`~phigenesis.data.sources.synthetic.nuscenes_export.export_nuscenes`).
    """
    if format not in SYNTH_FORMATS:
        raise ValueError(f"unknown format {format!r}; choose one of {', '.join(SYNTH_FORMATS)}")
    config = SyntheticConfig.from_dict(
        {
            "scenes": scenes,
            "frames": frames,
            "seed": seed,
            "height": height,
            "width": width,
            "rig": "nuscenes6" if format == "nuscenes" else "waymo5",
            **params,
        }
    )
    if format == "nuscenes":
        from phigenesis.data.sources.synthetic.nuscenes_export import export_nuscenes

        return export_nuscenes(config, out, keyframes=keyframes, version=version, dropped=dropped)
    from phigenesis.data.sources.synthetic.waymo_export import export_waymo

    return export_waymo(config, out, "v1" if format == "waymo-v1" else "v2")
