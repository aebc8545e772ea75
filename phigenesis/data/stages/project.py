"""Occlusion-aware projection of LiDAR into every camera: sparse depth and its confidence.

Entry point: :func:`project_camera` (one image); the stage ``project_depth`` runs it for every
camera of every frame, lazily, and stores a :class:`CameraDepth` on each image.

What is projected into an image, all at that image's own capture time and pose:

- with an aggregated map (stage ``aggregate_lidar`` ran first): the static map's points near the
  camera, each rigid moving object's model at its box pose moved to the image's time (constant
  velocity from the frame's box), and each non-rigid moving object's points from the frame's own
  sweep, moved the same way;
- without one: the frame's own sweep (``single_sweep``).

Occlusion: a min-depth z-buffer keeps the nearest point per pixel, but sparse foreground points
leave gaps through which background points show ("see-through"). The visibility test removes
them; ``visibility`` picks one of:

- ``splat`` (default): each point occludes a disc of radius ``splat_scale * f * spacing / z`` pixels
  (its footprint: a map voxel, or the LiDAR's angular step for sweep points); a point survives if
  it is no deeper than ``(1 + tau) * z_occluder + slack_m`` for every disc covering its pixel.
- ``local_min``: a point survives if it is within ``(1 + tau)`` of the minimum depth in a
  ``window x window`` neighbourhood (the classic test; it also removes slanted ground far away).
- ``none``: the z-buffer only.

The ego car's body (boxes in the ego frame, :func:`aggregate.ego_boxes_of`) is an occluder too:
pixels whose ray meets it get no depth (confidence 0), and nothing behind it is projected. A box
holding a camera centre or a LiDAR origin is an error naming the scene, the sensor and the box
(:func:`phigenesis.data.ego_body.check_sensors_outside`): it would blank the camera's depth.

Cost: the first pass over the points (transform, cull, distort, project, the ego-body and
vehicle tests) and the per-pixel plane fits run in C (``csrc/camera_points.c``,
``csrc/plane_fits.c``, :mod:`phigenesis.data.native`), with their numpy twins as the fallback
where no compiler is present (:func:`camera_pixels_reference`, :func:`fit_occupied_numpy`). A
long segment's map saturates its 2 cm voxels: a pixel holding more than
``max_points_per_pixel`` points keeps its front band thinned to about that many
(:func:`thin_in_pixels`), so the work after the first pass is bounded by the image.

Confidence of a sparse pixel: the origin's weight (static map or own sweep 1.0, non-rigid own
points 0.9, rigid object models 0.8: their pose is extrapolated to the image time) times 0.75 if
a single point supports the pixel, 1.0 if two or more agree within ``tau``.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.camera_tables import (
    ego_body_depth_of,
)
from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported
from phigenesis.data.ego_body import camera_centres, check_sensors_outside
from phigenesis.data.records import (
    CameraImage,
    Frame,
    LazyFrames,
    Scene,
)
from phigenesis.data.stages import register_stage
from phigenesis.data.stages.aggregate import (
    LidarMap,
    LidarOriginCheck,
    checked_ego_boxes,
    ego_boxes_from,
    lidar_angular_step,
)
from phigenesis.data.stages.projection.camera import (  # noqa: F401 (re-exported)
    _mix64,
    _projection_counts,
    camera_pixels,
    camera_pixels_reference,
    project_camera,
    project_camera_reference,
    thin_in_pixels,
)
from phigenesis.data.stages.projection.candidates import (  # noqa: F401 (re-exported)
    CameraPoints,
    NonRigidPoints,
    _border_rays,
    _normalized_bounds,
    _points,
    camera_wedge,
    footprint_budgets,
    non_rigid_points,
    normalized_bounds,
    scene_points,
    seen_past_lidar_top,
    static_points_per_camera,
    sweep_points,
    thinning_strides,
    tiles_in_view,
    tiles_reaching,
)
from phigenesis.data.stages.projection.edges import (  # noqa: F401 (re-exported)
    CameraPixels,
    _known_box,
    depth_edge_band,
    depth_edge_band_reference,
    silhouette_pixels,
    silhouette_pixels_reference,
)
from phigenesis.data.stages.projection.fits import (  # noqa: F401 (re-exported)
    MOMENT_NAMES,
    PixelFit,
    _centre_first,
    _pixel_index,
    _plane_at_centre,
    fit_occupied_numpy,
    fit_pixels,
    fit_pixels_reference,
    moments,
    occupied_window_moments,
    window_moments,
)
from phigenesis.data.stages.projection.occluders import (  # noqa: F401 (re-exported)
    _BOX_EDGES,
    _CLIP_Z_M,
    _disc,
    _zbuffer,
    ego_body_depth,
    normalized_footprint,
    occluder_depth,
    occluder_depth_reference,
    pixel_rays,
    vehicle_far_depth,
    vehicle_far_depth_reference,
)
from phigenesis.data.stages.projection.params import (  # noqa: F401 (re-exported)
    ORIGIN_CODE,
    ORIGIN_WEIGHT,
    ORIGIN_WEIGHTS,
    PERSON_IDS,
    VEHICLE_IDS,
    Estimator,
    MixedPixels,
    ProjectParams,
    Visibility,
    _cap_of,
    supersample_of,
)

log = logging.getLogger("phigenesis.prep")


class _Projector:
    """Runs :func:`project_camera` over a scene's frames, caching per-camera rays and ego body."""

    def __init__(self, scene: Scene, params: ProjectParams):
        self.scene_id = scene.scene_id
        self.params = params
        self.lidar_map: LidarMap | None = scene.products.get("lidar_map") if params.use_map else None
        # The aggregation checked the body against the cameras and LiDARs already.
        self.ego_boxes = self.lidar_map.ego_boxes if self.lidar_map is not None else checked_ego_boxes(scene)
        self.boxes_from = ego_boxes_from(scene)
        self.check_lidar = None if self.lidar_map is not None else LidarOriginCheck(scene, self.ego_boxes)
        self._rays: dict[tuple, tuple[NDArray[np.float64], NDArray[np.float32]]] = {}
        self._warned = False

    def rays_and_ego_depth(self, camera: CameraImage) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
        """The camera's pixel rays and ego body depth, computed once per calibration (a new
        calibration is checked against the body first: PrepError if a box holds its centre)."""
        key = camera.calibration.key()
        if key not in self._rays:
            sensors = camera_centres([camera.calibration])
            check_sensors_outside(self.scene_id, self.ego_boxes, sensors, self.boxes_from)
            self._rays[key] = (pixel_rays(camera), ego_body_depth(camera, self.ego_boxes))
        return self._rays[key]

    def sweep_step(self, frame: Frame) -> float:
        if self.params.sweep_spacing_rad is not None:
            return self.params.sweep_spacing_rad
        if self.lidar_map is not None:
            return self.lidar_map.angular_step_rad
        return lidar_angular_step(frame.lidar) if frame.lidar is not None else float(np.radians(0.5))

    def __call__(self, frame: Frame) -> Frame:
        has_sweep = frame.lidar is not None and len(frame.lidar) > 0
        if self.check_lidar is not None and has_sweep:
            self.check_lidar(frame.lidar)
        if self.lidar_map is None and not has_sweep and not self._warned:
            log.warning(
                "scene %s frame %d: no LiDAR; its depth maps are empty", self.scene_id, frame.frame_index
            )
            self._warned = True
        step = self.sweep_step(frame)
        static = people = None
        if self.lidar_map is not None:
            static = static_points_per_camera(frame, self.lidar_map, self.params)
            people = non_rigid_points(frame, self.lidar_map)
        for camera in frame.cameras:  # the per-scene tables, filled before any thread runs
            self.rays_and_ego_depth(camera)

        def one_camera(k: int) -> None:
            camera = frame.cameras[k]
            rays, ego_depth = self.rays_and_ego_depth(camera)
            occluders = None
            if self.lidar_map is not None:
                pts = scene_points(frame, camera, self.lidar_map, self.params, static[k], people)
                if self.params.vehicle_occluders:
                    occluders = vehicle_far_depth(
                        frame, camera, self.lidar_map.moving_tracks, self.params, rays
                    )
            else:
                pts = sweep_points(frame)
            camera.depth, _ = project_camera(camera, pts, self.params, ego_depth, occluders, step)

        if self.params.threads > 1 and len(frame.cameras) > 1:
            # Cameras are independent and numpy/OpenCV release the GIL on large arrays.
            with ThreadPoolExecutor(max_workers=self.params.threads) as pool:
                list(pool.map(one_camera, range(len(frame.cameras))))
        else:
            for k in range(len(frame.cameras)):
                one_camera(k)
        return frame


def _camera_tables_once(scene: Scene, params: ProjectParams) -> None:
    """Per-scene setup: every camera's pixel rays and ego-body depth
    (:mod:`~phigenesis.data.camera_tables`), so no frame pays for them."""
    lidar_map = scene.products.get("lidar_map") if params.use_map else None
    ego_boxes = lidar_map.ego_boxes if lidar_map is not None else checked_ego_boxes(scene)
    for cal in scene.calibrations:
        ego_body_depth_of(cal, ego_boxes)


@register_stage("project_depth", params=ProjectParams, setup=_camera_tables_once)
def project_depth(scene: Scene, params: ProjectParams) -> Scene:
    """Stage: sparse depth and confidence for every image (see the module docstring); uses the
    aggregated map from ``aggregate_lidar`` when it ran, else each frame's own sweep."""
    projector = _Projector(scene, params)
    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(projector)
    else:
        scene.frames = [projector(f) for f in scene.frames]
    return scene
