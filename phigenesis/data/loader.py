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
truth_semantic             uint8 [C, H, W]               unified classes, 255 = ignore
truth_instance             int32 [C, H, W]               instance ids, 0 = none
truth_flow                 float32 [C, 3, H, W]          surface velocity, world frame, m/s
depth_sparse               float32 [C, H, W]             projected LiDAR, metres along z, 0 = none
depth_sparse_confidence    float32 [C, H, W]             in [0, 1], 0 where depth_sparse is 0
depth_sparse_origin        uint8 [C, H, W]               records.DEPTH_ORIGINS index (0 = none)
depth_dense                float32 [C, H, W]             densified depth GT, 0 = none
depth_dense_confidence     float32 [C, H, W]             in [0, 1], 0 where depth_dense is 0
depth_dense_origin         uint8 [C, H, W]               records.DENSE_ORIGINS index (0 = none)
pseudo_semantic            uint8 [C, H, W]               pseudo labels, unified classes, 255 = none
pseudo_confidence          float32 [C, H, W]             in [0, 1], 0 where no label
pseudo_source              uint8 [C, H, W]               records.PSEUDO_SOURCES index (0 = none)
flow_world                 float32 [C, 3, H, W]          stage scene_flow: box-motion flow, world, m/s
flow_dynamic               uint8 [C, H, W]               1 inside a moving box, 0 elsewhere
flow_confidence            float32 [C, H, W]             in [0, 1], 0 where the flow is unknown
lidar_points_ego           float32 [N, 3]                LiDAR points, ego frame at frame time
lidar_intensity            float32 [N]
lidar_beam_index           int64 [N]
lidar_origins_ego          float32 [N, 3]                ray origins
lidar_truth_semantic       uint8 [N]                     (synthetic)
lidar_truth_instance       int32 [N]
lidar_flow_world_mps       float32 [N, 3]                stage scene_flow: per-point flow, world, m/s
boxes_center_world         float64 [M, 3]
boxes_size_lwh             float64 [M, 3]
boxes_yaw_world            float64 [M]
boxes_velocity_world       float64 [M, 3]
boxes_class_id             int64 [M]
boxes_instance_id          int64 [M]
boxes_track_id             list[str] (M)
=========================  ===========================  ==========================================

``depth_dense_origin`` says what each dense depth came from: 1 a LiDAR measurement, 2 the densifier, 3 a
plane of its image segment and 4 a thin vertical structure (both from ``complete_depth``, at lower
confidence), 5 the rendered depth of generated Gaussians (caches ``phigenesis-generate`` writes); weigh or
mask the depth loss by it.

Choose groups with ``fields`` ("images", "cameras", "truth", "depth", "pseudo", "flow", "lidar",
"boxes"); only
what is asked for is read, checked and decoded. Label maps stay compact (uint8 classes, int32 instances);
cast them on the device (``.long()`` for a cross-entropy target). :func:`collate_frames` stacks
fixed-size entries over the batch and keeps variable-size ones (LiDAR, boxes, per-camera lists)
as lists. The further groups ``RANGE_FIELD_GROUPS``, "range_view" (all views side by side as one
image) and "lidar_range_image" (the sweep as beams x azimuth), give the keys listed in
:mod:`phigenesis.data.loader_rangeview`.
"""

from __future__ import annotations

import math
import os
import threading
import weakref
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import torch
from torch.utils.data import Dataset

from phigenesis.data import batch_pool, codec
from phigenesis.data.cache.reader import CacheReader
from phigenesis.data.loader_rangeview import lidar_range_sample, range_view_sample
from phigenesis.data.records import decode_whole
from phigenesis.data.schema import cameras_of
from phigenesis.errors import CacheError

FIELD_GROUPS = ("images", "cameras", "truth", "depth", "pseudo", "flow", "lidar", "boxes")
#: Groups of packed views, documented in :mod:`phigenesis.data.loader_rangeview`.
RANGE_FIELD_GROUPS = ("range_view", "lidar_range_image")


def _binary_views(arr: pa.Array) -> list[np.ndarray | None]:
    """Zero-copy uint8 views of the elements of a binary array (None where null), sliced out of its
    data buffer at its offsets (a third of the cost of one Arrow scalar per element)."""
    if arr.null_count or not (pa.types.is_binary(arr.type) or pa.types.is_large_binary(arr.type)):
        return [
            np.frombuffer(arr[i].as_buffer(), dtype=np.uint8) if arr[i].is_valid else None
            for i in range(len(arr))
        ]
    _, offsets, data = arr.buffers()
    width = 8 if pa.types.is_large_binary(arr.type) else 4
    ends = np.frombuffer(offsets, f"<i{width}", len(arr) + 1, arr.offset * width).tolist()
    values = np.frombuffer(data, np.uint8) if data is not None else np.empty(0, np.uint8)
    return [values[ends[i] : ends[i + 1]] for i in range(len(arr))]


class _CameraFields(Mapping[str, pa.Array]):
    """The camera struct fields of a one-row batch, as :func:`~phigenesis.data.schema.cameras_of`
    gives them, each taken out of the struct on first use: a field group uses a few of the
    struct's fields, and flattening them all would cost every frame for nothing."""

    def __init__(self, batch: pa.RecordBatch):
        struct = batch.column("cameras")[0].values
        self._struct = struct
        self._fields: dict[str, pa.Array] = {}
        if struct is None or struct.null_count:  # null entries: cameras_of merges their validity
            self._fields = cameras_of(batch)
            self._struct = None
        self._names = dict.fromkeys(self._fields if self._struct is None else self._struct.type.names)

    def __getitem__(self, name: str) -> pa.Array:
        field = self._fields.get(name)
        if field is None:
            if self._struct is None or name not in self._names:
                raise KeyError(name)
            field = self._fields[name] = self._struct.field(name)
        return field

    def __contains__(self, name: object) -> bool:
        return name in self._names

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


#: A decoder of one stored map that writes into the given output array.
MapDecoder = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _decode_flow_channels_first(data: np.ndarray, out: np.ndarray) -> np.ndarray:
    return codec.decode_flow(data, out, channels_first=True)


def _decode_rgb(data: np.ndarray, out: np.ndarray) -> np.ndarray:
    """JPEG/PNG bytes into ``out`` [3, H, W] RGB, de-interleaved by OpenCV (several times faster
    than a numpy transpose copy); raises :class:`~phigenesis.data.records.InvalidRecord` for bytes
    that are not a whole image (:func:`~phigenesis.data.records.decode_whole`)."""
    bgr = decode_whole(data, cv2.IMREAD_COLOR, "image")
    if bgr.shape[:2] != out.shape[1:]:
        raise ValueError(
            f"image is {bgr.shape[1]}x{bgr.shape[0]}, the calibration says {out.shape[2]}x{out.shape[1]}"
        )
    cv2.split(bgr, [out[2], out[1], out[0]])
    return out


@dataclass(frozen=True)
class _MapJob:
    """One per-camera output: its key, stored column, decoder, dtype and leading channel count."""

    key: str
    column: str
    decode: MapDecoder
    dtype: type
    channels: int | None
    required: bool = False


_IMAGE_JOB = _MapJob("images", "image", _decode_rgb, np.uint8, 3, required=True)
_TRUTH_JOBS = (
    _MapJob("truth_depth", "truth_depth_png", codec.decode_depth, np.float32, None),
    _MapJob("truth_semantic", "truth_semantic_png", codec.decode_semantic, np.uint8, None),
    _MapJob("truth_instance", "truth_instance_png", codec.decode_instance, np.int32, None),
    _MapJob("truth_flow", "truth_flow_png", _decode_flow_channels_first, np.float32, 3),
)

_DEPTH_JOBS = (
    _MapJob("depth_sparse", "depth_sparse_png", codec.decode_depth, np.float32, None),
    _MapJob(
        "depth_sparse_confidence", "depth_sparse_confidence_png", codec.decode_confidence, np.float32, None
    ),
    _MapJob("depth_sparse_origin", "depth_sparse_origin_png", codec.decode_semantic, np.uint8, None),
    _MapJob("depth_dense", "depth_dense_png", codec.decode_depth, np.float32, None),
    _MapJob(
        "depth_dense_confidence", "depth_dense_confidence_png", codec.decode_confidence, np.float32, None
    ),
    _MapJob("depth_dense_origin", "depth_dense_origin_png", codec.decode_semantic, np.uint8, None),
)
_PSEUDO_JOBS = (
    _MapJob("pseudo_semantic", "pseudo_semantic_png", codec.decode_semantic, np.uint8, None),
    _MapJob("pseudo_confidence", "pseudo_semantic_confidence_png", codec.decode_confidence, np.float32, None),
    _MapJob("pseudo_source", "pseudo_semantic_source_png", codec.decode_semantic, np.uint8, None),
)

_FLOW_JOBS = (
    _MapJob("flow_world", "flow_world_mps_png", _decode_flow_channels_first, np.float32, 3),
    _MapJob("flow_dynamic", "flow_dynamic_png", codec.decode_semantic, np.uint8, None),
    _MapJob("flow_confidence", "flow_confidence_png", codec.decode_confidence, np.float32, None),
)


class _Arenas:
    """The allocations a dataset decodes frames' maps into, each reused once every tensor carved
    out of it has been freed.

    malloc alone recycles one frame's allocation when frames come one at a time, but a worker
    collating a batch frees several at once, and glibc then hands the memory back to the kernel
    and takes it again, page by page, each page zeroed by the kernel (BENCHMARKS.md, "Image-only
    loading"). At most ``keep`` allocations are kept; beyond that they are malloc's.
    """

    def __init__(self, keep: int = 8):
        self.keep = keep
        self._arenas: list[np.ndarray] = []
        self._busy: set[int] = set()

    def __reduce__(self) -> tuple[Any, ...]:
        return (_Arenas, (self.keep,))  # another process starts with none

    def take(self, nbytes: int) -> torch.Tensor:
        """A uint8 tensor of ``nbytes``; its memory is reused only once it and all tensors and
        arrays viewing it are freed."""
        free = [i for i in range(len(self._arenas)) if i not in self._busy]
        fits = [i for i in free if self._arenas[i].nbytes >= nbytes]
        if fits:
            index = min(fits, key=lambda i: self._arenas[i].nbytes)
        elif len(self._arenas) < self.keep:
            index = len(self._arenas)
            self._arenas.append(np.empty(nbytes, np.uint8))
        elif free:  # all kept ones too small: replace one
            index = free[0]
            self._arenas[index] = np.empty(nbytes, np.uint8)
        else:
            return torch.from_numpy(np.empty(nbytes, np.uint8))
        self._busy.add(index)
        use = self._arenas[index][:nbytes]  # torch holds this very array: its death frees the arena
        weakref.finalize(use, self._busy.discard, index).atexit = False
        return torch.from_numpy(use)


#: Most threads a frame's maps are decoded on in one process (more gave nothing on 2-8 cores).
MAX_DECODE_THREADS = 4
#: Frames with fewer decoded pixels than this decode on one thread (below it, handing maps to
#: another thread costs more than decoding them).
MIN_THREADED_PIXELS = 50_000

_pools: dict[tuple[int, int], ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()


def _forget_pools() -> None:
    """In a forked child: the parent's threads do not exist there."""
    _pools.clear()


os.register_at_fork(after_in_child=_forget_pools)


def _decode_pool(threads: int) -> ThreadPoolExecutor:
    """This process's pool of ``threads`` decode threads (made on first use)."""
    key = (os.getpid(), threads)
    with _pools_lock:
        pool = _pools.get(key)
        if pool is None:
            pool = _pools[key] = ThreadPoolExecutor(threads, thread_name_prefix="phigenesis-decode")
        return pool


def usable_cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def auto_decode_threads(num_workers: int | None = None) -> int:
    """Threads to decode a frame on: the usable cores (at most :data:`MAX_DECODE_THREADS`), shared
    out among ``num_workers`` DataLoader workers (default: this process's DataLoader's, if it is
    a worker, else none)."""
    if num_workers is None:
        info = torch.utils.data.get_worker_info()
        num_workers = info.num_workers if info is not None else 0
    return max(1, min(MAX_DECODE_THREADS, usable_cores() // max(1, num_workers)))


def _decode_maps(
    cf: Mapping[str, pa.Array], names: list[str], jobs: list[_MapJob], arenas: _Arenas, threads: int = 1
) -> dict[str, Any]:
    """Decodes every job's map of every camera straight into its output, on ``threads`` threads
    (OpenCV's decoders and numpy's conversions release the GIL, so the cameras decode in parallel).

    When all cameras share a size, each job's maps form one [C, (channels,) H, W] tensor and all
    jobs' tensors are carved out of a single allocation, taken from ``arenas``: separate arrays
    made the kernel zero fresh pages for every frame (measured: a third of the loader's time).
    Cameras of different sizes give lists of tensors.
    """
    sizes = list(zip(cf["height"].to_pylist(), cf["width"].to_pylist(), strict=True))
    uniform = all(size == sizes[0] for size in sizes)
    jobs = [j for j in jobs if j.column in cf]

    def lead(job: _MapJob) -> tuple[int, ...]:
        return () if job.channels is None else (job.channels,)

    if uniform:
        shapes = [(len(names), *lead(j), *sizes[0]) for j in jobs]
        dtypes = [_TORCH_DTYPES[np.dtype(j.dtype)] for j in jobs]
        nbytes = [math.prod(shape) * dt.itemsize for shape, dt in zip(shapes, dtypes, strict=True)]
        offsets = [0]
        for n in nbytes:
            offsets.append(offsets[-1] + (n + 63) // 64 * 64)
        arena = arenas.take(offsets[-1])
    out: dict[str, Any] = {}
    tasks: list[tuple[MapDecoder, str, np.ndarray, np.ndarray]] = []
    for k, job in enumerate(jobs):
        views = _binary_views(cf[job.column])
        if any(v is None for v in views):
            if job.required:
                raise ValueError(f"camera {names[views.index(None)]} has no {job.column}")
            continue
        if uniform:
            # torch views keep the arena's storage, and numpy views of them the tensor, alive
            stacked = arena[offsets[k] : offsets[k] + nbytes[k]].view(dtypes[k]).view(shapes[k])
            outputs = list(stacked.numpy())
        else:
            outputs = [np.empty((*lead(job), *size), job.dtype) for size in sizes]
        tasks += [
            (job.decode, name, data, target) for name, data, target in zip(names, views, outputs, strict=True)
        ]
        out[job.key] = stacked if uniform else [torch.from_numpy(o) for o in outputs]
    pixels = sum(h * w for h, w in sizes) * len(jobs)
    threads = min(threads, len(tasks)) if pixels >= MIN_THREADED_PIXELS else 1
    # One share per thread, this thread taking the first: one handoff per helper thread, not one
    # per map (a handoff through the executor costs about as much as decoding a 160x240 JPEG).
    shares = [tasks[i::threads] for i in range(threads)]
    helpers = [_decode_pool(threads - 1).submit(_decode_all, share) for share in shares[1:]]
    errors = _decode_all(shares[0]) + [e for future in helpers for e in future.result()]
    if errors:
        raise errors[0]
    return out


def _decode_all(tasks: list[tuple[MapDecoder, str, np.ndarray, np.ndarray]]) -> list[ValueError]:
    """Runs each decode; a wrong size or type comes back as an error naming the camera."""
    errors = []
    for decode, name, data, target in tasks:
        try:
            decode(data, target)
        except ValueError as e:
            error = ValueError(f"camera {name}: {e}")
            error.__cause__ = e
            errors.append(error)
    return errors


_TORCH_DTYPES = {
    np.dtype(np.uint8): torch.uint8,
    np.dtype(np.int32): torch.int32,
    np.dtype(np.float32): torch.float32,
}


def _flat(arr: pa.Array) -> np.ndarray:
    return arr.flatten().to_numpy(zero_copy_only=False)


class FrameDataset(Dataset):
    """Random access to a cache's frames as dicts of tensors (see the module docstring).

    Works with any number of DataLoader workers (each opens the memory-mapped shards itself).
    A frame's images and maps decode on ``decode_threads`` threads; the default (None) is
    :func:`auto_decode_threads` in each process: the usable cores in the main process (at most
    :data:`MAX_DECODE_THREADS`), the cores per worker in a DataLoader worker (1 for 2 workers on
    2 cores). Results do not depend on it.
    """

    def __init__(
        self,
        cache_dir: str | os.PathLike[str],
        fields: Sequence[str] = ("images", "cameras", "truth", "boxes"),
        check_crc: bool = True,
        decode_threads: int | None = None,
    ):
        groups = FIELD_GROUPS + RANGE_FIELD_GROUPS
        unknown = set(fields) - set(groups)
        if unknown:
            raise ValueError(f"unknown field groups {sorted(unknown)}; choose from {groups}")
        self.reader = CacheReader(cache_dir, check_crc=check_crc)
        self.fields = tuple(fields)
        self._map_jobs = (
            ([_IMAGE_JOB] if "images" in self.fields else [])
            + (list(_TRUTH_JOBS) if "truth" in self.fields else [])
            + (list(_DEPTH_JOBS) if "depth" in self.fields else [])
            + (list(_PSEUDO_JOBS) if "pseudo" in self.fields else [])
            + (list(_FLOW_JOBS) if "flow" in self.fields else [])
        )
        self._arenas = _Arenas()
        if decode_threads is not None and decode_threads < 1:
            raise ValueError(f"decode_threads must be >= 1 or None (auto), got {decode_threads}")
        #: Threads a frame's maps are decoded on; None: :func:`auto_decode_threads` in each process.
        self.decode_threads = decode_threads
        self._auto_threads = (-1, 1)  # (pid, threads): auto_decode_threads once per process

    def __len__(self) -> int:
        return len(self.reader)

    def _threads(self) -> int:
        """This process's decode threads (a DataLoader worker is a process of its own)."""
        if self.decode_threads is not None:
            return self.decode_threads
        if self._auto_threads[0] != os.getpid():
            self._auto_threads = (os.getpid(), auto_decode_threads())
        return self._auto_threads[1]

    def __getitem__(self, index: int) -> dict[str, Any]:
        batch = self.reader.read(index, self._columns(index))
        try:
            return self._convert(batch)
        except ValueError as e:
            path, row = self.reader.locate(index)
            raise CacheError(f"{path}: row {row}: {e}") from e

    def _columns(self, index: int) -> list[str]:
        """The columns this dataset's fields need (only these are read and CRC-checked)."""
        available = self.reader.columns_of(index)
        cols = ["scene_id", "frame_index", "frame_timestamp_micros", "world_from_ego", "cameras"]
        wanted = set(self.fields)
        if "lidar_range_image" in wanted:
            wanted.add("lidar")  # range and intensity come from the sweep
        names = ("lidar", "boxes", "range_view", "lidar_range_image")
        return cols + [c for c in names if c in wanted and c in available]

    def _convert(self, batch: pa.RecordBatch) -> dict[str, Any]:
        out: dict[str, Any] = {
            "scene_id": batch.column("scene_id")[0].as_py(),
            "frame_index": batch.column("frame_index")[0].as_py(),
            "frame_timestamp_micros": batch.column("frame_timestamp_micros")[0].as_py(),
            "world_from_ego": torch.from_numpy(_flat(batch.column("world_from_ego")).reshape(4, 4).copy()),
        }
        cf = _CameraFields(batch)
        n_cam = len(cf["camera_name"])
        names = cf["camera_name"].to_pylist()
        out["camera_names"] = names
        out.update(_decode_maps(cf, names, self._map_jobs, self._arenas, self._threads()))
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
            if "truth_semantic" in lf and lf["truth_semantic"][0].is_valid:
                out["lidar_truth_semantic"] = torch.from_numpy(_flat(lf["truth_semantic"]).copy())
            if "truth_instance" in lf and lf["truth_instance"][0].is_valid:
                out["lidar_truth_instance"] = torch.from_numpy(_flat(lf["truth_instance"]).astype(np.int32))
            if "flow_world_mps" in lf and lf["flow_world_mps"][0].is_valid:
                flow = _flat(lf["flow_world_mps"]).reshape(-1, 3)
                out["lidar_flow_world_mps"] = torch.from_numpy(flow.copy())
        if "range_view" in self.fields:
            out.update(range_view_sample(batch, cameras_of(batch), out))
        if "lidar_range_image" in self.fields:
            out.update(lidar_range_sample(batch))
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


def collate_frames(samples: list[dict[str, Any]]) -> FrameBatch:
    """Batches samples: tensors of equal shape are stacked (new dim 0), numbers become tensors,
    everything else (variable-size LiDAR and boxes, per-camera lists, strings) is a list.

    In a DataLoader worker every tensor of the batch is built straight in a pooled shared-memory
    segment, which then travels to the main process without a copy (see :class:`FrameBatch`)."""
    plan: list[tuple[str, str, Any]] = []
    for key in samples[0]:
        values = [s[key] for s in samples]
        if all(isinstance(v, torch.Tensor) for v in values) and all(
            v.shape == values[0].shape and v.dtype == values[0].dtype for v in values
        ):
            plan.append((key, "stack", values))
        elif all(type(v) is int for v in values) and all(-(2**63) <= v < 2**63 for v in values):
            plan.append((key, "tensor", torch.from_numpy(np.array(values, np.int64))))  # torch.tensor's 1/3
        elif all(isinstance(v, (int, float)) for v in values):
            plan.append((key, "tensor", torch.tensor(values)))
        elif all(isinstance(v, torch.Tensor) for v in values) and all(
            v.shape == values[0].shape for v in values
        ):
            plan.append((key, "tensor", torch.stack(values)))  # mixed dtypes: torch promotes
        else:
            plan.append((key, "list", values))
    buffer = None
    if batch_pool.worker_pool() is not None:
        shapes: list[tuple[tuple[int, ...], torch.dtype]] = []
        for _, kind, value in plan:
            if kind == "stack":
                shapes.append(((len(value), *value[0].shape), value[0].dtype))
            elif kind == "tensor":
                shapes.append((tuple(value.shape), value.dtype))
            else:
                shapes += [(tuple(t.shape), t.dtype) for t in _tensors_in(value)]
        specs, total = batch_pool.layout(shapes)
        buffer = batch_pool.allocate(total)
    out = FrameBatch()
    if buffer is None:
        for key, kind, value in plan:
            if kind == "stack":
                out[key] = value[0].unsqueeze(0) if len(value) == 1 else torch.stack(value)
            else:
                out[key] = value
        return out
    views = iter(batch_pool.views(buffer, specs))
    for key, kind, value in plan:
        if kind == "stack":
            out[key] = torch.stack(value, out=next(views))
        elif kind == "tensor":
            out[key] = next(views).copy_(value)
        else:
            out[key] = _copied_into(value, views)
    return out


def _tensors_in(obj: Any) -> list[torch.Tensor]:
    """The tensors inside nested lists and dicts, in the order :func:`_replace_tensors` meets them."""
    if isinstance(obj, torch.Tensor):
        return [obj]
    if isinstance(obj, (list, dict)):
        return [t for v in (obj.values() if isinstance(obj, dict) else obj) for t in _tensors_in(v)]
    return []


def _copied_into(obj: Any, views: Iterator[torch.Tensor]) -> Any:
    """``obj`` (nested lists and dicts) with each tensor replaced by a copy in the next of ``views``."""
    if isinstance(obj, torch.Tensor):
        return next(views).copy_(obj)
    if isinstance(obj, dict):
        return {k: _copied_into(v, views) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_copied_into(v, views) for v in obj]
    return obj


class FrameBatch(dict):
    """A batch from :func:`collate_frames`: a plain dict in use.

    When a DataLoader worker sends it to the main process, all its tensors travel packed in one
    shared-memory buffer and come back as views of it: torch otherwise shares every tensor through
    its own segment and file descriptor, which costs more than decoding a frame's images. The
    buffer is one of a few segments each worker reuses (:mod:`phigenesis.data.batch_pool`); the
    segment goes back to its worker only once every tensor of the batch has been freed, so a batch
    may be held as long as wanted.
    """

    def __reduce__(self) -> tuple[Any, ...]:
        tensors: list[torch.Tensor] = []
        skeleton = _replace_tensors(dict(self), tensors)
        rebuild, args = batch_pool.pack(tensors)
        return (_rebuild_batch, (skeleton, rebuild, args))

    def __copy__(self) -> FrameBatch:
        return FrameBatch(self)  # what pin_memory copies: the same tensors, not a repacked buffer


class _Slot(int):
    """Placeholder for the i-th packed tensor inside a batch skeleton."""


def _replace_tensors(obj: Any, tensors: list[torch.Tensor]) -> Any:
    if isinstance(obj, torch.Tensor):
        tensors.append(obj)
        return _Slot(len(tensors) - 1)
    if isinstance(obj, dict):
        return {k: _replace_tensors(v, tensors) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_replace_tensors(v, tensors) for v in obj]
    return obj


def _fill_tensors(obj: Any, views: list[torch.Tensor]) -> Any:
    if isinstance(obj, _Slot):
        return views[obj]
    if isinstance(obj, dict):
        return {k: _fill_tensors(v, views) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_fill_tensors(v, views) for v in obj]
    return obj


def _rebuild_batch(skeleton: dict, rebuild: Callable[..., list[torch.Tensor]], args: tuple) -> FrameBatch:
    return FrameBatch(_fill_tensors(skeleton, rebuild(*args)))
