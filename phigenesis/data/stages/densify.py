"""Sparse LiDAR depth -> dense per-camera depth (the ``densify_depth`` stage).

Entry point: :func:`densify` (one image). Methods live in :data:`DENSIFIERS`, registered with
:func:`register_densifier`; each is ``method(sparse_m, sparse_confidence, rgb, focal_px, **params)
-> DenseResult``. The stage ``densify_depth`` runs one on every camera that has a
:class:`CameraDepth` and fills its ``dense_m`` / ``dense_confidence``.

Conventions shared by every method:

- Depths are metres along the camera's +z, float32, 0 = unknown. A pixel is *measured* where
  ``sparse_m > 0`` and ``sparse_confidence > 0``.
- Parameters named ``*_ref_px`` are pixels of a camera with focal length
  :data:`REFERENCE_FOCAL_PX` (KITTI's, for which IP-Basic was tuned); a method scales them by
  ``focal_px / REFERENCE_FOCAL_PX``, so it looks at the same angular neighbourhood at any
  resolution.
- Only *trusted* measurements (see each method) seed the output. A pixel is filled only if it
  lies within ``max_fill_ref_px`` of one, has one in each of its four quadrants within 1.5 times
  that (or the image border there), and, unless ``extrapolate_top``, is not above the top-most one
  of its column (:func:`support_mask`): holes are interpolated, surfaces never grow into sky or
  into regions the LiDAR did not reach.
- Confidence (:func:`depth_confidence`) of an output depth ``z``::

      conf = c * exp(-d / d0) * exp(-(|z - z_ref| / (z * rel0))^2)      (0 where z == 0)

  At a measured pixel: ``c`` its input confidence, ``d = 0``, ``z_ref`` its measured depth, so a
  measurement kept as is has exactly its input confidence and one the method changed (an outlier
  it replaced) loses it. At any other pixel: ``c``, ``z_ref`` the input confidence and depth of
  the nearest trusted measurement, ``d`` the distance to it in pixels; every filled pixel is
  below 1. ``d0`` = ``conf_distance_ref_px`` (scaled), ``rel0`` = ``conf_relative_depth``.

Methods (``ipbasic`` and ``planar`` use no image):

- ``ipbasic``: IP-Basic-style morphology in inverted depth, focal-scaled kernels.
- ``planar``: local affine fit of inverse depth (exact on planes); a Gaussian-weighted mean
  where the window spans a depth edge.
- ``guided`` (:data:`DEFAULT_DENSIFIER`): RGB edge-aware normalized convolution of inverse depth
  (domain transform filter, or the fast global smoother with ``edge_filter="fgs"``).
- ``planar_guided``: ``planar``'s fit where the window holds one surface, ``guided``'s estimate
  along depth edges.

The methods live in :mod:`phigenesis.data.stages.densification` (registry and parameters,
shared support and confidence, ``ipbasic``, the inverse-depth methods, the one-map entry point).
How they compare on synthetic frames: docs/experiments.md, "Densification methods"
(``benchmarks/densify_methods.py``).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.records import (
    DENSE_ORIGINS,
    CameraImage,
    Frame,
    LazyFrames,
    Scene,
)
from phigenesis.data.stages import register_stage
from phigenesis.data.stages.densification.depth_map import (  # noqa: F401  (re-exported)
    CROP_MARGINS,
    MIN_CROP_SAVING,
    _densify_checked,
    check_depth_maps,
    check_rgb,
    crop_box,
    densify,
    densify_reference,
)
from phigenesis.data.stages.densification.inverse_depth import (  # noqa: F401  (re-exported)
    EDGE_FILTERS,
    gaussian_mean,
    guided,
    guided_mean,
    planar,
    planar_guided,
    plane_fit,
)
from phigenesis.data.stages.densification.ipbasic import ipbasic  # noqa: F401  (re-exported)
from phigenesis.data.stages.densification.registry import (  # noqa: F401  (re-exported: the stage's names)
    DEFAULT_DENSIFIER,
    DEFAULT_FALLBACK,
    DENSIFIERS,
    ENCLOSURE_FACTOR,
    F32,
    MIN_SPARSE_COVERAGE,
    REFERENCE_FOCAL_PX,
    Blur,
    DenseResult,
    Densifier,
    DensifyParams,
    EdgeFilter,
    Mask,
    check_params,
    get_densifier,
    method_params,
    needs_rgb,
    register_densifier,
)
from phigenesis.data.stages.densification.support import (  # noqa: F401  (re-exported)
    FillParams,
    depth_confidence,
    nearest_trusted,
    occluded_samples,
    scaled_px,
    support_mask,
)

log = logging.getLogger("phigenesis.prep")


def camera_focal_px(cam: CameraImage) -> float:
    """The camera's focal length in pixels (geometric mean of fx and fy)."""
    k = cam.calibration.intrinsics
    return float(np.sqrt(k[0, 0] * k[1, 1]))


@dataclass
class CameraCoverage:
    """Pixel counts of one camera over the frames of a scene seen so far."""

    pixels: int = 0
    sparse: int = 0  # pixels with a sparse depth (> 0)
    dense: int = 0  # pixels with a dense depth (> 0)

    def sparse_share(self) -> float:
        return self.sparse / max(self.pixels, 1)

    def dense_share(self) -> float:
        return self.dense / max(self.pixels, 1)


class DepthCoverage:
    """Per-camera share of pixels with a sparse and with a dense depth over a scene's frames.

    Each frame counts once however often a lazy frame is loaded (the last load wins). Once every
    frame of the scene has been seen, :meth:`add` logs the shares in one line and warns, naming the
    camera, where a camera's sparse share is below ``min_sparse_coverage``. The shares are known
    only after the frames are processed, that is while the shards are written (the scene metadata
    is fixed before), so they go to the log only.
    """

    def __init__(self, scene_id: str, frames: int, min_sparse_coverage: float = MIN_SPARSE_COVERAGE):
        self.scene_id = scene_id
        self.frames = frames
        self.min_sparse_coverage = min_sparse_coverage
        self.reported = False
        self._counts: dict[int, dict[str, CameraCoverage]] = {}

    def add(self, frame: Frame) -> None:
        """Counts the frame's cameras that have a depth; reports when the scene is complete."""
        counts = {}
        for cam in frame.cameras:
            if cam.depth is not None and cam.depth.dense_m is not None:
                counts[cam.name] = CameraCoverage(
                    int(cam.depth.sparse_m.size),
                    int(np.count_nonzero(cam.depth.sparse_m > 0)),
                    int(np.count_nonzero(cam.depth.dense_m > 0)),
                )
        self._counts[frame.frame_index] = counts
        if len(self._counts) >= self.frames:
            self.report()

    def per_camera(self) -> dict[str, CameraCoverage]:
        """The counts summed over the frames seen, by camera (in the order first seen)."""
        out: dict[str, CameraCoverage] = {}
        for counts in self._counts.values():
            for name, c in counts.items():
                total = out.setdefault(name, CameraCoverage())
                total.pixels += c.pixels
                total.sparse += c.sparse
                total.dense += c.dense
        return out

    def report(self) -> None:
        """Logs the sparse shares once (INFO), and a WARNING per camera below ``min_sparse_coverage``."""
        if self.reported:
            return
        self.reported = True
        cameras = self.per_camera()
        if not cameras:
            return
        shares = ", ".join(f"{name} {100 * c.sparse_share():.1f} %" for name, c in cameras.items())
        # The dense share is not logged here: completion fills more after this stage, and the
        # pipeline logs what the written rows hold (phigenesis.data.coverage).
        log.info(
            "scene %s: sparse depth coverage over %d frames, share of pixels with a sparse depth: %s",
            self.scene_id,
            len(self._counts),
            shares,
        )
        for name, c in cameras.items():
            if c.sparse_share() < self.min_sparse_coverage:
                log.warning(
                    "scene %s camera %s: only %.2f %% of its pixels have a sparse depth "
                    "(min_sparse_coverage %.2f %%): its depth ground truth is (nearly) empty. Does the "
                    "ego body (scene metadata ego_boxes) cover the view, or is the LiDAR missing?",
                    self.scene_id,
                    name,
                    100 * c.sparse_share(),
                    100 * self.min_sparse_coverage,
                )


_LIDAR_CODE, _DENSIFIED_CODE = DENSE_ORIGINS.index("lidar"), DENSE_ORIGINS.index("densified")


def densified_origin(sparse_m: F32, sparse_confidence: F32, dense_m: F32) -> NDArray[np.uint8]:
    """:func:`~phigenesis.data.records.dense_origin_of` (its reference, tested equal) in uint8
    throughout: (H, W) code 1 ("lidar") where ``dense_m`` is exactly a sparse depth of positive
    confidence, 2 ("densified") at every other pixel with a depth, 0 where ``dense_m`` is 0."""
    code = (dense_m > 0).view(np.uint8) * np.uint8(_DENSIFIED_CODE)
    kept = (sparse_m > 0) & (sparse_confidence > 0) & (dense_m == sparse_m)
    code -= kept.view(np.uint8) * np.uint8(_DENSIFIED_CODE - _LIDAR_CODE)
    return code


@register_stage("densify_depth", params=DensifyParams)
def densify_depth(scene: Scene, params: DensifyParams) -> Scene:
    """Fills ``dense_m`` / ``dense_confidence`` / ``dense_origin`` (lidar or densified,
    :func:`~phigenesis.data.records.dense_origin_of`) of every camera that has a :class:`CameraDepth`.

    Params: :class:`DensifyParams`: ``method`` (default :data:`DEFAULT_DENSIFIER`), ``fallback``
    (default :data:`DEFAULT_FALLBACK`: what runs on a camera without an image when the method
    needs one; a warning is logged once per scene), ``min_confidence`` (sparse depths below it,
    such as pixels at depth edges, are not used as seeds; default
    :data:`~phigenesis.data.records.TRUSTED_DEPTH_CONFIDENCE`), ``min_sparse_coverage`` (share of
    a camera's pixels, over the scene, below which its sparse depth is warned about; default
    :data:`MIN_SPARSE_COVERAGE`), and the method's own parameters (the fallback gets those of them
    it accepts). Cameras without depth are left alone. Frames are processed lazily when the
    scene's frames are a :class:`LazyFrames`.

    Once every frame is processed, the per-camera coverage (share of pixels with a sparse and with
    a dense depth) is logged in one line per scene (:class:`DepthCoverage`): log only, as it is
    known only while the shards are written.
    """
    method, fallback = params.method, params.fallback
    method_kwargs, fallback_kwargs = params.method_kwargs(method), params.method_kwargs(fallback)
    min_confidence, min_sparse_coverage = params.min_confidence, params.min_sparse_coverage
    warned = False

    def densify_camera(cam: CameraImage) -> CameraImage:
        nonlocal warned
        if cam.depth is None:
            return cam
        name, kwargs, rgb = method, method_kwargs, None
        if needs_rgb(method):
            if cam.image_bytes is None:
                if not warned:
                    log.warning(
                        "densify_depth: scene %s camera %s has no image; %r falls back to %r",
                        scene.scene_id,
                        cam.name,
                        method,
                        fallback,
                    )
                    warned = True
                name, kwargs = fallback, fallback_kwargs
            else:
                rgb = cam.decode_image()
        depth = cam.depth
        sparse_conf = np.asarray(depth.sparse_confidence, np.float32)
        seeds = sparse_conf * (sparse_conf >= min_confidence)  # float32, 0 below min_confidence
        result = _densify_checked(depth.sparse_m, seeds, rgb, camera_focal_px(cam), name, kwargs)
        dense = dataclasses.replace(
            depth,
            dense_m=result.depth_m,
            dense_confidence=result.confidence,
            dense_origin=densified_origin(depth.sparse_m, seeds, result.depth_m),
        )
        return dataclasses.replace(cam, depth=dense)

    coverage = DepthCoverage(scene.scene_id, len(scene.frames), min_sparse_coverage)

    def densify_frame(frame: Frame) -> Frame:
        dense = dataclasses.replace(frame, cameras=[densify_camera(c) for c in frame.cameras])
        coverage.add(dense)
        return dense

    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(densify_frame)
    else:
        scene.frames = [densify_frame(f) for f in scene.frames]
        coverage.report()
    return scene


def sweep_sparse_depth(frame: Frame, cam: CameraImage) -> F32:
    """The frame's own LiDAR sweep in ``cam``: nearest point per pixel (z-buffer only)."""
    h, w = cam.calibration.height, cam.calibration.width
    p_cam = geometry.transform_points(np.linalg.inv(cam.world_from_camera), frame.lidar.points_world())
    uv, valid = geometry.project_points(p_cam, cam.calibration.intrinsics, cam.calibration.distortion)
    u, v = np.round(uv[valid]).astype(np.int64).T
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    depth = np.full(h * w, np.inf)
    np.minimum.at(depth, v[inside] * w + u[inside], p_cam[valid, 2][inside])
    return np.where(np.isfinite(depth), depth, 0).reshape(h, w).astype(np.float32)
