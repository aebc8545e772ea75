"""Torch access to caches: a map-style Dataset of frames and a collate function.

A sample is a dict. With C cameras of H x W pixels (``cameras_*`` entries are stacked over
cameras when all images share a size, and lists of per-camera tensors otherwise):

=========================  ===========================  ==========================================
key                        tensor                        meaning
=========================  ===========================  ==========================================
scene_id, frame_index      str, int                      which frame
frame_timestamp_micros     int                           frame reference time
world_from_ego             float64 [4, 4]                ego pose at the frame time
camera_names               list[str] (C)                 rig order
images                     uint8 [C, 3, H, W]            RGB
intrinsics                 float32 [C, 3, 3]             OpenCV K
distortion                 float32 [C, 5]                k1, k2, p1, p2, k3
ego_from_camera            float64 [C, 4, 4]             camera axes OpenCV
camera_world_from_ego      float64 [C, 4, 4]             ego pose at each image's capture time
camera_timestamp_micros    int64 [C]                     capture times
truth_depth                float32 [C, H, W]             metres along camera z, 0 = none
truth_semantic             int64 [C, H, W]               unified classes, 255 = ignore
truth_instance             int64 [C, H, W]               instance ids, 0 = none
truth_flow                 float32 [C, 3, H, W]          surface velocity, world frame, m/s
lidar_points_ego           float32 [N, 3]                LiDAR points, ego frame at frame time
lidar_intensity            float32 [N]
lidar_beam_index           int64 [N]
lidar_origins_ego          float32 [N, 3]                ray origins
lidar_truth_semantic       int64 [N]                     (synthetic)
lidar_truth_instance       int64 [N]
boxes_center_world         float64 [M, 3]
boxes_size_lwh             float64 [M, 3]
boxes_yaw_world            float64 [M]
boxes_velocity_world       float64 [M, 3]
boxes_class_id             int64 [M]
boxes_instance_id          int64 [M]
boxes_track_id             list[str] (M)
=========================  ===========================  ==========================================

Choose groups with ``fields`` ("images", "cameras", "truth", "lidar", "boxes"); only what is
asked for is decoded. :func:`collate_frames` stacks fixed-size entries over the batch and keeps
variable-size ones (LiDAR, boxes, per-camera lists) as lists.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import torch
from torch.utils.data import Dataset

from phigenesis.data import codec
from phigenesis.data.schema import cameras_of
from phigenesis.data.shards import CacheError, CacheReader

FIELD_GROUPS = ("images", "cameras", "truth", "lidar", "boxes")


def _bytes_view(arr: pa.BinaryArray, i: int) -> np.ndarray | None:
    """Zero-copy uint8 view of element ``i`` of a binary array (None if null)."""
    if not arr[i].is_valid:
        return None
    return np.frombuffer(arr[i].as_buffer(), dtype=np.uint8)


def _stack_or_list(items: list[torch.Tensor]) -> torch.Tensor | list[torch.Tensor]:
    if items and all(t.shape == items[0].shape for t in items):
        return torch.stack(items)
    return items


def _flat(arr: pa.Array) -> np.ndarray:
    return arr.flatten().to_numpy(zero_copy_only=False)


class FrameDataset(Dataset):
    """Random access to a cache's frames as dicts of tensors (see the module docstring).

    Works with any number of DataLoader workers (each opens the memory-mapped shards itself).
    """

    def __init__(
        self,
        cache_dir: str | os.PathLike[str],
        fields: Sequence[str] = ("images", "cameras", "truth", "boxes"),
        check_crc: bool = True,
    ):
        unknown = set(fields) - set(FIELD_GROUPS)
        if unknown:
            raise ValueError(f"unknown field groups {sorted(unknown)}; choose from {FIELD_GROUPS}")
        self.reader = CacheReader(cache_dir, check_crc=check_crc)
        self.fields = tuple(fields)

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, index: int) -> dict[str, Any]:
        batch = self.reader.read(index)
        try:
            return self._convert(batch)
        except ValueError as e:
            shard, row = self.reader._index[index]
            raise CacheError(
                f"{self.reader.cache_dir / self.reader.shards[shard].path}: row {row}: {e}"
            ) from e

    def _convert(self, batch: pa.RecordBatch) -> dict[str, Any]:
        out: dict[str, Any] = {
            "scene_id": batch.column("scene_id")[0].as_py(),
            "frame_index": batch.column("frame_index")[0].as_py(),
            "frame_timestamp_micros": batch.column("frame_timestamp_micros")[0].as_py(),
            "world_from_ego": torch.from_numpy(_flat(batch.column("world_from_ego")).reshape(4, 4).copy()),
        }
        cf = cameras_of(batch)
        n_cam = len(cf["camera_name"])
        out["camera_names"] = cf["camera_name"].to_pylist()
        if "images" in self.fields:
            imgs = []
            for i in range(n_cam):
                data = _bytes_view(cf["image"], i)
                if data is None:
                    raise ValueError(f"camera {out['camera_names'][i]} has no image")
                bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
                if bgr is None:
                    raise ValueError(f"camera {out['camera_names'][i]}: image does not decode")
                imgs.append(torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1].transpose(2, 0, 1))))
            out["images"] = _stack_or_list(imgs)
        if "cameras" in self.fields:
            out["intrinsics"] = torch.from_numpy(
                _flat(cf["intrinsics"]).reshape(n_cam, 3, 3).astype(np.float32)
            )
            out["distortion"] = torch.from_numpy(_flat(cf["distortion"]).reshape(n_cam, 5).astype(np.float32))
            out["ego_from_camera"] = torch.from_numpy(
                _flat(cf["ego_from_camera"]).reshape(n_cam, 4, 4).copy()
            )
            out["camera_world_from_ego"] = torch.from_numpy(
                _flat(cf["world_from_ego"]).reshape(n_cam, 4, 4).copy()
            )
            out["camera_timestamp_micros"] = torch.from_numpy(cf["timestamp_micros"].to_numpy().copy())
        if "truth" in self.fields:
            decoders = {
                "truth_depth": ("truth_depth_png", codec.decode_depth, None),
                "truth_semantic": ("truth_semantic_png", codec.decode_semantic, np.int64),
                "truth_instance": ("truth_instance_png", codec.decode_instance, np.int64),
                "truth_flow": ("truth_flow_png", codec.decode_flow, None),
            }
            for key, (column, decode, dtype) in decoders.items():
                if column not in cf:
                    continue
                maps = []
                for i in range(n_cam):
                    data = _bytes_view(cf[column], i)
                    if data is None:
                        break
                    m = decode(data)
                    m = m.transpose(2, 0, 1) if m.ndim == 3 else m
                    maps.append(
                        torch.from_numpy(np.ascontiguousarray(m if dtype is None else m.astype(dtype)))
                    )
                else:
                    out[key] = _stack_or_list(maps)
        if "lidar" in self.fields and "lidar" in batch.schema.names and batch.column("lidar")[0].is_valid:
            lf = {
                f.name: a
                for f, a in zip(
                    batch.schema.field("lidar").type, batch.column("lidar").flatten(), strict=True
                )
            }
            out["lidar_points_ego"] = torch.from_numpy(_flat(lf["points_ego"]).reshape(-1, 3).copy())
            out["lidar_intensity"] = torch.from_numpy(_flat(lf["intensity"]).copy())
            out["lidar_beam_index"] = torch.from_numpy(_flat(lf["beam_index"]).astype(np.int64))
            out["lidar_origins_ego"] = torch.from_numpy(_flat(lf["origins_ego"]).reshape(-1, 3).copy())
            for name in ("truth_semantic", "truth_instance"):
                if name in lf and lf[name][0].is_valid:
                    out[f"lidar_{name}"] = torch.from_numpy(_flat(lf[name]).astype(np.int64))
        if "boxes" in self.fields:
            bx = batch.column("boxes").flatten()
            bf = {f.name: a for f, a in zip(bx.type, bx.flatten(), strict=True)}
            m = len(bx)
            out["boxes_center_world"] = torch.from_numpy(_flat(bf["center_world"]).reshape(m, 3).copy())
            out["boxes_size_lwh"] = torch.from_numpy(_flat(bf["size_lwh"]).reshape(m, 3).copy())
            out["boxes_yaw_world"] = torch.from_numpy(bf["yaw_world"].to_numpy(zero_copy_only=False).copy())
            out["boxes_velocity_world"] = torch.from_numpy(_flat(bf["velocity_world"]).reshape(m, 3).copy())
            out["boxes_class_id"] = torch.from_numpy(
                bf["class_id"].to_numpy(zero_copy_only=False).astype(np.int64)
            )
            out["boxes_instance_id"] = torch.from_numpy(
                bf["instance_id"].to_numpy(zero_copy_only=False).astype(np.int64)
            )
            out["boxes_track_id"] = bf["track_id"].to_pylist()
        return out


def collate_frames(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Batches samples: tensors of equal shape are stacked (new dim 0), everything else is a list."""
    out: dict[str, Any] = {}
    for key in samples[0]:
        values = [s[key] for s in samples]
        if all(isinstance(v, torch.Tensor) for v in values) and all(
            v.shape == values[0].shape for v in values
        ):
            out[key] = torch.stack(values)
        elif all(isinstance(v, (int, float)) for v in values):
            out[key] = torch.tensor(values)
        else:
            out[key] = values
    return out
