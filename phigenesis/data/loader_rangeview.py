"""The loader's range-view field groups: a frame's range view and LiDAR range image as tensors.

``range_view`` (``Hr x Wr`` cells, the layout stored by the ``range_view`` stage, or computed from
the row's calibrations when the cache has none):

===========================  =====================  ================================================
key                          tensor                 meaning
===========================  =====================  ================================================
range_view_rgb               uint8 [3, Hr, Wr]      RGB, 0 where empty (present if any image)
range_view_depth             float32 [Hr, Wr]       z-depth of the cell's camera, m, 0 = unknown
range_view_depth_source      str                    "dense" or "sparse" (key absent without depth)
range_view_semantic          uint8 [Hr, Wr]         unified classes, 255 = ignore/none
range_view_semantic_source   str                    "pseudo", "truth" or "labels" (absent without)
range_view_valid             bool [Hr, Wr]          a view's pixel is there
range_view_view_index        uint8 [Hr, Wr]         index into range_view_cameras, 255 = empty
range_view_owner             uint8 [Hr, Wr]         view owning the cell's direction (overlap rule)
range_view_rays_ego          float32 [3, Hr, Wr]    unit ray direction, ego frame, 0 where empty
range_view_cameras           list[str]              camera of each view, left to right
===========================  =====================  ================================================

``lidar_range_image`` (``B x A``: beams x azimuth bins; needs the ``lidar_range_image`` column):

===========================  =====================  ================================================
key                          tensor                 meaning
===========================  =====================  ================================================
lidar_range                  float32 [B, A]         range from the point's ray origin, m, 0 = empty
lidar_range_intensity        float32 [B, A]         intensity of the kept point, 0 = empty
lidar_range_index            int32 [B, A]           index into lidar_points_ego, -1 = empty
lidar_range_inclination      float32 [B]            elevation of each row, rad (NaN: no points)
lidar_range_column_origin    float32 [A, 3]         ray origin of each column, ego frame, m
===========================  =====================  ================================================
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import torch

from phigenesis.data import codec
from phigenesis.data.rangeview import (
    DEFAULT_DEPTH_SOURCES,
    DEFAULT_SEMANTIC_SOURCES,
    NO_VIEW,
    range_view_layout,
    range_view_rays,
)
from phigenesis.data.records import CameraCalibration, decode_whole
from phigenesis.data.schema import lidar_of, lidar_range_image_of, range_view_of

#: The camera column holding each depth / semantic source of :mod:`phigenesis.data.rangeview`.
DEPTH_COLUMNS = {"dense": "depth_dense_png", "sparse": "depth_sparse_png", "truth": "truth_depth_png"}
SEMANTIC_COLUMNS = {
    "pseudo": "pseudo_semantic_png",
    "truth": "truth_semantic_png",
    "labels": "label_semantic_png",
}


def _calibrations(cf: dict[str, pa.Array]) -> list[CameraCalibration]:
    n = len(cf["camera_name"])

    def mat(name: str, shape: tuple[int, ...]) -> np.ndarray:
        return cf[name].flatten().to_numpy(zero_copy_only=False).reshape(n, *shape)

    intrinsics, distortion, ego_from_camera = (
        mat("intrinsics", (3, 3)),
        mat("distortion", (5,)),
        mat("ego_from_camera", (4, 4)),
    )
    return [
        CameraCalibration(name, w, h, intrinsics[i], distortion[i], ego_from_camera[i])
        for i, (name, w, h) in enumerate(
            zip(cf["camera_name"].to_pylist(), cf["width"].to_pylist(), cf["height"].to_pylist(), strict=True)
        )
    ]


def _first_column(
    cf: dict[str, pa.Array], sources: tuple[str, ...], columns: dict[str, str]
) -> tuple[str, str]:
    """The first source whose column any camera fills, and that column ("", "" if none)."""
    for source in sources:
        name = columns[source]
        if name in cf and cf[name].null_count < len(cf[name]):
            return source, name
    return "", ""


#: The loader key that already holds a camera column's decoded maps, when its group was asked for.
DECODED_KEYS = {
    "image": "images",
    "depth_dense_png": "depth_dense",
    "depth_sparse_png": "depth_sparse",
    "truth_depth_png": "truth_depth",
    "truth_semantic_png": "truth_semantic",
    "pseudo_semantic_png": "pseudo_semantic",
}


def _camera_planes(
    cf: dict[str, pa.Array], column: str, index: list[int], decoded: dict[str, Any], decode: Any
) -> list[np.ndarray | None]:
    """Each view's map of a camera column: reused from ``decoded`` (the sample's per-camera
    tensors) where the loader already decoded it, else decoded here."""
    have = decoded.get(DECODED_KEYS.get(column, ""))
    if have is not None:
        return [have[i].numpy() for i in index]
    return [None if not cf[column][i].is_valid else _decode_camera(cf, column, i, decode) for i in index]


def _decode_camera(cf: dict[str, pa.Array], column: str, i: int, decode: Any) -> np.ndarray:
    """``decode`` of camera ``i``'s ``column``; a ValueError names the camera."""
    try:
        return decode(cf[column][i].as_py())
    except ValueError as e:
        raise ValueError(f"camera {cf['camera_name'][i].as_py()}: {e}") from e


def _decode_rgb_chw(data: bytes) -> np.ndarray:
    """JPEG/PNG bytes as a [3, H, W] RGB view (copied once, where it is placed); raises
    :class:`~phigenesis.data.records.InvalidRecord` for bytes that are not a whole image."""
    return decode_whole(data, cv2.IMREAD_COLOR, "image").transpose(2, 0, 1)[::-1]


def range_view_sample(
    batch: pa.RecordBatch, cf: dict[str, pa.Array], decoded: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The ``range_view`` keys (module docstring) of a one-row batch whose cameras are ``cf``;
    ``decoded`` (the sample so far) lends images and maps its other groups already decoded."""
    decoded = decoded or {}
    cals = _calibrations(cf)
    layout = range_view_of(batch) or range_view_layout(cals)
    names = cf["camera_name"].to_pylist()
    index = [names.index(n) for n in layout.camera_names]
    out: dict[str, Any] = {"range_view_cameras": layout.camera_names}
    if cf["image"].null_count < len(cf["image"]):
        rgb = np.zeros((3, layout.height, layout.width), np.uint8)
        for p, plane in zip(
            layout.views, _camera_planes(cf, "image", index, decoded, _decode_rgb_chw), strict=True
        ):
            if plane is not None:
                rgb[:, p.rows, p.cols] = plane
        out["range_view_rgb"] = torch.from_numpy(rgb)
    for key, sources, columns, decode, fill in (
        ("depth", DEFAULT_DEPTH_SOURCES, DEPTH_COLUMNS, codec.decode_depth, 0),
        ("semantic", DEFAULT_SEMANTIC_SOURCES, SEMANTIC_COLUMNS, codec.decode_semantic, 255),
    ):
        source, column = _first_column(cf, sources, columns)
        if source:
            planes = _camera_planes(cf, column, index, decoded, decode)
            out[f"range_view_{key}"] = torch.from_numpy(layout.pack(planes, fill=fill))
            out[f"range_view_{key}_source"] = source
    view_index = layout.view_index()
    out["range_view_valid"] = torch.from_numpy(view_index != NO_VIEW)
    out["range_view_view_index"] = torch.from_numpy(view_index)
    out["range_view_owner"] = torch.from_numpy(layout.owner.copy())
    out["range_view_rays_ego"] = torch.from_numpy(range_view_rays(layout, cals, channels_first=True).copy())
    return out


def lidar_range_sample(batch: pa.RecordBatch) -> dict[str, Any]:
    """The ``lidar_range_image`` keys (module docstring) of a one-row batch (empty if none)."""
    sweep = lidar_of(batch)
    image = None if sweep is None else lidar_range_image_of(batch, 0, sweep)
    if image is None:
        return {}
    return {
        "lidar_range": torch.from_numpy(image.range_m),
        "lidar_range_intensity": torch.from_numpy(image.intensity),
        # The stored parts are read-only views of the memory-mapped shard.
        "lidar_range_index": torch.from_numpy(image.point_index.copy()),
        "lidar_range_inclination": torch.from_numpy(image.beam_inclination_rad.copy()),
        "lidar_range_column_origin": torch.from_numpy(image.column_origin_ego.copy()),
    }
