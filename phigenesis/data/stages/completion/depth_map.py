"""The completion of one depth map, plain arrays in and out (:func:`complete_depth_map`): input
checks, the completion at the image's resolution or, for a large image, on a coarser grid of its
own pixels with every empty pixel then intersected with its cell's plane (:func:`_complete_coarse`,
a C kernel with a numpy reference).

Conventions: z-depth in metres along the camera's z axis (OpenCV), 0 = unknown; rays with z = 1.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.native import load_complete_fine
from phigenesis.data.records import DENSE_ORIGINS
from phigenesis.data.stages.completion.completer import _Completer, _Inputs
from phigenesis.data.stages.completion.params import (
    F32,
    F64,
    ORIGIN,
    CompletionParams,
    CompletionResult,
    Mask,
)
from phigenesis.data.stages.completion.segments import (
    segment_image,
)
from phigenesis.data.stages.densification.depth_map import check_depth_maps, check_rgb


def complete_depth_map(
    depth_m: F32,
    confidence: F32,
    rgb: NDArray[np.uint8],
    *,
    rays_cam: F64,
    up_cam: F64,
    focal_px: float,
    origin: NDArray[np.uint8] | None = None,
    sparse_m: F32 | None = None,
    sparse_confidence: F32 | None = None,
    sky: Mask | None = None,
    classes: NDArray[np.uint8] | None = None,
    keep_out: Mask | None = None,
    params: CompletionParams | None = None,
) -> CompletionResult:
    """Completes one dense depth map from its image's segments and the depth they already hold.

    Args:
        depth_m: (H, W) float z-depth in metres (the densifier's), 0 = unknown; finite, >= 0.
        confidence: (H, W) float in [0, 1]; known pixels have ``depth_m > 0`` and
            ``confidence > 0``.
        rgb: (H, W, 3) uint8 RGB image of the same camera.
        rays_cam: (H, W, 3) or (H * W, 3) camera-frame ray (OpenCV axes) of every pixel centre
            with z = 1 and the distortion undone, so that the pixel at depth z is ``z * ray``
            (:func:`~phigenesis.data.stages.project.pixel_rays`).
        up_cam: (3,) the world's up direction in camera axes (any length but 0).
        focal_px: the camera's focal length in pixels (scales the ``*_ref_px`` parameters).
        origin: (H, W) uint8 :data:`~phigenesis.data.records.DENSE_ORIGINS` code of the input's
            known pixels (kept), or None: "densified".
        sparse_m, sparse_confidence: (H, W) the projected LiDAR depth and its confidence (both or
            neither): evidence for thin structures, which at low resolution are all depth edge
            and so mostly missing from the dense depth.
        sky: (H, W) bool, pixels that are sky: never filled.
        classes: (H, W) uint8 labels (unified taxonomy, 255 = none): segments whose majority label
            is in :data:`NEVER_FILLED_CLASSES` are not completed.
        keep_out: (H, W) bool, pixels never to fill (the ego body).
        params: :class:`CompletionParams` (None: the defaults).

    Returns:
        The completed depth, its confidence and origin codes (complete.py's docstring), and the image's
        segments. The inputs are not modified. Raises ValueError naming the argument for a wrong
        shape or dtype, NaN or infinite values, negative depths, confidences outside [0, 1], a
        zero up vector or rays without z = 1.

    Example::

        rays = pixel_rays(camera)                        # (H * W, 3)
        up = camera.world_from_camera[:3, :3].T @ [0, 0, 1]
        out = complete_depth_map(dense, conf, rgb, rays_cam=rays, up_cam=up, focal_px=f, sky=sky)
        planar = out.origin == DENSE_ORIGINS.index("plane")
    """
    p = CompletionParams() if params is None else params
    depth, conf = check_depth_maps(depth_m, confidence, ("depth_m", "confidence"))
    shape = depth.shape
    h, w = shape
    rgb = np.ascontiguousarray(check_rgb(rgb, shape, "depth_m"))
    ray_info = _ray_info(rays_cam)
    if ray_info is not None and ray_info.get("checked") == shape:
        rays = np.asarray(rays_cam).reshape(shape[0] * shape[1], 3)
    else:
        rays = _check_rays(rays_cam, shape)
        if ray_info is not None:
            ray_info["checked"] = shape
    up = _check_up(up_cam)
    focal_px = float(focal_px)
    if not np.isfinite(focal_px) or focal_px <= 0:
        raise ValueError(f"focal_px must be a positive finite number of pixels, got {focal_px}")
    origin_in = _check_labels("origin", origin, shape, len(DENSE_ORIGINS))
    if (sparse_m is None) != (sparse_confidence is None):
        raise ValueError("sparse_m and sparse_confidence come together (both or neither)")
    sparse = None
    if sparse_m is not None:
        sparse = check_depth_maps(sparse_m, sparse_confidence)
        if sparse[0].shape != shape:
            raise ValueError(f"sparse_m has shape {sparse[0].shape}, depth_m has {shape}")
    sky = _check_mask("sky", sky, shape)
    keep_out = _check_mask("keep_out", keep_out, shape)
    classes = _check_labels("classes", classes, shape, None)

    known = (depth > 0) & (conf > 0)
    out_depth = depth * known  # float32 copies, 0 where unknown
    out_conf = conf * known
    densified = np.uint8(ORIGIN["densified"])
    if origin_in is None:
        out_origin = known.astype(np.uint8) * densified
    else:
        out_origin = np.where(known, np.where(origin_in > 0, origin_in, densified), 0).astype(np.uint8)
    fillable = ~known
    for mask in (sky, keep_out):
        if mask is not None:
            fillable &= ~mask
    inputs = _Inputs(
        out_depth, out_conf, out_origin, known, fillable, rgb, rays, sky, classes, sparse, ray_info
    )
    scale = min(1.0, p.max_side_px / max(h, w))
    if scale < 1.0:
        segments = _complete_coarse(inputs, up, focal_px, p, scale)
    else:
        segments = segment_image(rgb, focal_px, p)
        if (known.any() or (p.sparse_planes and sparse is not None)) and fillable.any():
            _Completer(inputs, segments, up, focal_px, p).run()
    # Completed depths are finite and positive by construction; checked once more so that no NaN
    # or infinity can ever reach a cache (in place: NaN fails both comparisons).
    filled = (out_depth > 0) & (out_depth < np.inf)
    unfilled = ~filled
    np.copyto(out_depth, 0, where=unfilled)
    np.copyto(out_conf, 0, where=unfilled | ~(out_conf > 0))  # NaN and negatives too
    np.minimum(out_conf, np.float32(1), out=out_conf)
    np.copyto(out_origin, 0, where=unfilled)
    return CompletionResult(out_depth, out_conf, out_origin, segments)


def _ray_info(rays_cam: Any) -> dict[Any, Any] | None:
    """A dict kept with a read-only rays array across calls (the per-calibration tables of
    :mod:`~phigenesis.data.camera_tables`, passed for every frame): that it passed the checks, its
    lengths, its coarse grids. None for a writeable array (it may change between calls). Entries
    go with their array (held by a weak reference)."""
    if not isinstance(rays_cam, np.ndarray) or rays_cam.flags.writeable:
        return None
    with _RAY_INFO_LOCK:
        entry = _RAY_INFO.get(id(rays_cam))
        if entry is not None and entry[0]() is rays_cam:
            return entry[1]
        for key in [k for k, (ref, _) in _RAY_INFO.items() if ref() is None]:
            del _RAY_INFO[key]
        info: dict[Any, Any] = {}
        _RAY_INFO[id(rays_cam)] = (weakref.ref(rays_cam), info)
        return info


_RAY_INFO: dict[int, tuple[weakref.ref, dict[Any, Any]]] = {}
_RAY_INFO_LOCK = threading.Lock()


def _complete_coarse(
    inputs: _Inputs, up: F64, focal_px: float, p: CompletionParams, scale: float, native: bool = True
) -> NDArray[np.int32]:
    """Completes a large image on a grid ``scale`` times as fine (outputs updated in place);
    returns the segments, upsampled.

    Each grid cell is one of the image's own pixels (depth, rays and masks sampled, the image
    area-averaged), so the planes are the scene's; every empty pixel of the image then takes its
    cell's plane, intersected with its own ray: depths stay exact on the planes, only the segment
    boundaries are as coarse as the grid. That fine pass runs in a C kernel
    (``csrc/complete_fine.c``) where it can be built and ``native``; the numpy path is its
    reference (bit-identical, tests/test_complete_depth.py).
    """
    h, w = inputs.depth.shape
    h2, w2 = max(1, round(h * scale)), max(1, round(w * scale))
    rows = np.minimum(((np.arange(h2) + 0.5) * h / h2).astype(np.intp), h - 1)
    cols = np.minimum(((np.arange(w2) + 0.5) * w / w2).astype(np.intp), w - 1)
    grid = np.ix_(rows, cols)

    def sample(a: Any) -> Any:
        return None if a is None else np.ascontiguousarray(a[grid])

    key = ("coarse", h2, w2)
    if inputs.ray_info is not None and key in inputs.ray_info:
        small_rays, small_norm = inputs.ray_info[key]
    else:
        small_rays = inputs.rays.reshape(h, w, 3)[grid].reshape(-1, 3)
        small_norm = np.linalg.norm(small_rays, axis=1)
        if inputs.ray_info is not None:
            small_rays.setflags(write=False)
            small_norm.setflags(write=False)
            inputs.ray_info[key] = (small_rays, small_norm)

    small = _Inputs(
        *(sample(inputs.depth), sample(inputs.conf), sample(inputs.origin)),
        *(sample(inputs.known), sample(inputs.fillable)),
        cv2.resize(inputs.rgb, (w2, h2), interpolation=cv2.INTER_AREA),
        small_rays,
        *(sample(inputs.sky), sample(inputs.classes)),
        None if inputs.sparse is None else (sample(inputs.sparse[0]), sample(inputs.sparse[1])),
    )
    focal_small = focal_px * w2 / w
    segments = segment_image(small.rgb, focal_small, p)
    ry = np.minimum((np.arange(h) * h2 / h).astype(np.intp), h2 - 1)
    rx = np.minimum((np.arange(w) * w2 / w).astype(np.intp), w2 - 1)
    if (small.known.any() or (p.sparse_planes and small.sparse is not None)) and small.fillable.any():
        completer = _Completer(small, segments, up, focal_small, p, small_norm)
        completer.run()
        kernel = load_complete_fine() if native else None
        if kernel is not None:
            kernel(
                ry.astype(np.int64),
                rx.astype(np.int64),
                np.ascontiguousarray(inputs.fillable),
                np.ascontiguousarray(inputs.rays),
                completer.plane_normal,
                completer.plane_offset,
                small.conf.reshape(-1),
                small.origin.reshape(-1),
                w2,
                ORIGIN["plane"],
                (p.min_depth_m, p.max_depth_m),
                float(np.sin(np.radians(p.min_incidence_deg))),
                inputs.depth,
                inputs.conf,
                inputs.origin,
            )
        else:
            done = (small.origin >= ORIGIN["plane"])[np.ix_(ry, rx)]  # (H, W) whether the cell completed
            done &= inputs.fillable
            target = np.flatnonzero(done)
            del done
            src = ry[target // w] * w2 + rx[target % w]  # the grid cell of every target pixel
            norm = None
            if inputs.ray_info is not None:
                if "norm" not in inputs.ray_info:
                    inputs.ray_info["norm"] = np.linalg.norm(inputs.rays, axis=1)  # (H * W,) float64
                norm = inputs.ray_info["norm"]
            z, ok = completer.intersect(
                inputs.rays[target],
                completer.plane_normal[src],
                completer.plane_offset[src],
                None if norm is None else norm[target],
            )
            target, src = target[ok], src[ok]
            inputs.depth.reshape(-1)[target] = z[ok]
            inputs.conf.reshape(-1)[target] = small.conf.reshape(-1)[src]
            inputs.origin.reshape(-1)[target] = small.origin.reshape(-1)[src]
    return segments[np.ix_(ry, rx)]


def _check_rays(rays_cam: Any, shape: tuple[int, int]) -> F64:
    arr = np.asarray(rays_cam, dtype=np.float64)
    h, w = shape
    if arr.shape == (h, w, 3):
        arr = arr.reshape(h * w, 3)
    if arr.shape != (h * w, 3):
        raise ValueError(f"rays_cam must have shape {(h, w, 3)} or {(h * w, 3)}, got {np.shape(rays_cam)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("rays_cam has NaN or infinite values")
    if np.any(np.abs(arr[:, 2] - 1.0) > 1e-6):
        raise ValueError("rays_cam must have z = 1 (the pixel at depth z is z * ray)")
    return arr


def _check_up(up_cam: Any) -> F64:
    up = np.asarray(up_cam, dtype=np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)):
        raise ValueError(f"up_cam must be 3 finite numbers, got {up_cam!r}")
    norm = float(np.linalg.norm(up))
    if norm < 1e-9:
        raise ValueError("up_cam must not be the zero vector")
    return up / norm


def _check_mask(name: str, mask: Any, shape: tuple[int, int]) -> Mask | None:
    if mask is None:
        return None
    arr = np.asarray(mask)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape} (as depth_m), got {arr.shape}")
    if arr.dtype != np.bool_:
        raise ValueError(f"{name} must be a bool mask, got dtype {arr.dtype}")
    return arr


def _check_labels(
    name: str, labels: Any, shape: tuple[int, int], count: int | None
) -> NDArray[np.uint8] | None:
    if labels is None:
        return None
    arr = np.asarray(labels)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape} (as depth_m), got {arr.shape}")
    if arr.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8, got dtype {arr.dtype}")
    if count is not None and arr.size and int(arr.max()) >= count:
        raise ValueError(f"{name} holds code {int(arr.max())}; codes are 0..{count - 1}")
    return arr
