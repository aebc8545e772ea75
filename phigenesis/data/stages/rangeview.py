"""Stages ``range_view`` and ``lidar_range_image``: attach each frame's range-view layout and its
LiDAR range image (see :mod:`phigenesis.data.rangeview` and :mod:`phigenesis.data.lidar_range`).

Both work frame by frame, lazily. ``range_view`` stores only the layout and the overlap map on
``Frame.range_view`` (the pixels are the cameras' own, packed by ``pack_range_view`` when read),
so it may run before or after the stages that make depth and semantics.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from phigenesis.data.lidar_range import estimate_columns, lidar_range_image
from phigenesis.data.rangeview import Align, range_view_layout
from phigenesis.data.records import Frame, LazyFrames, Scene, frame_geometry
from phigenesis.data.stages import register_stage
from phigenesis.options import check_options, option


@dataclass(frozen=True)
class RangeViewParams:
    """Parameters of the camera range view.

    Attributes:
        align: "horizon" (views' horizons on one row) or "top" (all views at row 0).
    """

    align: Align = option("horizon")

    def __post_init__(self) -> None:
        check_options(self, "RangeViewParams")


@dataclass(frozen=True)
class LidarRangeParams:
    """Parameters of the LiDAR range image.

    Attributes:
        beams: rows (laser count); None = the highest beam index of the scene's first sweep + 1
            (a top beam that hits nothing in that sweep is then cut: set it when known).
        columns: azimuth bins per revolution; None = estimated from the scene's first sweep
            (:func:`~phigenesis.data.lidar_range.estimate_columns`). Set both for real sensors
            (Waymo TOP: 64 x 2650) so every scene has the same shape.
        lidar_id: which LiDAR of the sweep (0 = the first; Waymo's TOP).
    """

    beams: int | None = option(None, ge=1, le=10_000)
    columns: int | None = option(None, ge=1, le=100_000)
    lidar_id: int = option(0, ge=0, le=255)

    def __post_init__(self) -> None:
        check_options(self, "LidarRangeParams")


def _map_frames(scene: Scene, fn: Callable[[Frame], Frame]) -> Scene:
    scene.frames = (
        scene.frames.map(fn) if isinstance(scene.frames, LazyFrames) else [fn(f) for f in scene.frames]
    )
    return scene


def _layout_once(scene: Scene, p: RangeViewParams) -> None:
    """Per-scene setup: the layout of the rig's cameras (cached per calibrations), so no frame
    pays for it."""
    if scene.calibrations:
        range_view_layout(scene.calibrations, p.align)


@register_stage("range_view", params=RangeViewParams, setup=_layout_once)
def range_view(scene: Scene, p: RangeViewParams) -> Scene:
    """Sets ``Frame.range_view`` (the layout of the frame's cameras) on every frame.

    Params: :class:`RangeViewParams`. A frame missing a camera (nuScenes' dropped sweeps) gets the
    layout of the cameras it has.
    """

    def attach(frame: Frame) -> Frame:
        if not frame.cameras:
            return frame
        layout = range_view_layout([c.calibration for c in frame.cameras], p.align)
        return dataclasses.replace(frame, range_view=layout)

    return _map_frames(scene, attach)


@register_stage("lidar_range_image", params=LidarRangeParams)
def lidar_range_image_stage(scene: Scene, p: LidarRangeParams) -> Scene:
    """Sets ``Frame.lidar_range_image`` on every frame with a sweep.

    Params: :class:`LidarRangeParams`; the shape left open is taken from the first frame's sweep
    (read once, geometry only), so every frame of a scene has the same shape.
    """
    if not len(scene.frames):
        return scene
    beams, columns = p.beams, p.columns
    if beams is None or columns is None:
        first = frame_geometry(scene.frames, 0).lidar
        mine = np.zeros(0) if first is None else first.beam_index[first.lidar_id == p.lidar_id]
        if mine.size:
            beams = int(mine.max()) + 1 if beams is None else beams
            columns = estimate_columns(first, p.lidar_id) if columns is None else columns
    if beams is None or columns is None:
        raise ValueError(
            f"lidar_range_image: scene {scene.scene_id}'s first frame has no points of lidar {p.lidar_id}; "
            "give beams and columns"
        )

    def attach(frame: Frame) -> Frame:
        if frame.lidar is None:
            return frame
        image = lidar_range_image(frame.lidar, beams, columns, p.lidar_id)
        return dataclasses.replace(frame, lidar_range_image=image)

    return _map_frames(scene, attach)
