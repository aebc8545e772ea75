"""What hides points from a camera: the ego body, moving vehicles' far sides and the splat
visibility test's occluder depth.

The stage is :mod:`phigenesis.data.stages.project`."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.camera_tables import (
    ego_body_depth_from_rays,
    ego_body_depth_of,
    footprint_pixels,
    pixel_rays_cam,
)
from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported
from phigenesis.data.native import load_ray_box
from phigenesis.data.records import (
    CameraImage,
    Frame,
)
from phigenesis.data.stages.projection.params import PERSON_IDS, VEHICLE_IDS, ProjectParams


def pixel_rays(camera: CameraImage) -> NDArray[np.float64]:
    """(H * W, 3) camera-frame rays through the pixel centres with z = 1 (distortion undone),
    read-only, computed once per calibration (:func:`~phigenesis.data.camera_tables.pixel_rays_cam`)."""
    return pixel_rays_cam(camera.calibration)


def ego_body_depth(
    camera: CameraImage, ego_boxes: list[dict], rays: NDArray[np.float64] | None = None
) -> NDArray[np.float32]:
    """(H, W) z-depth at which each pixel's ray enters the ego body boxes (ego frame), inf where
    it misses: read-only and computed once per calibration and body without ``rays``
    (:func:`~phigenesis.data.camera_tables.ego_body_depth_of`), from ``rays`` otherwise."""
    if rays is None:
        return ego_body_depth_of(camera.calibration, ego_boxes)
    return ego_body_depth_from_rays(camera.calibration, ego_boxes, rays)


#: Boxes are clipped to z >= this (metres, camera frame) before their footprint is taken.
_CLIP_Z_M = 1e-6
#: The 12 edges of a box, as pairs of indices into ``geometry.BOX_CORNER_SIGNS``.
_BOX_EDGES = [
    (i, j)
    for i in range(8)
    for j in range(i + 1, 8)
    if np.sum(geometry.BOX_CORNER_SIGNS[i] != geometry.BOX_CORNER_SIGNS[j]) == 1
]


def normalized_footprint(corners_cam: NDArray[np.float64]) -> tuple[tuple[float, float], ...] | None:
    """((x0, x1), (y0, y1)): bounds of x/z and y/z over a box (its 8 corners, camera frame)
    clipped to z >= :data:`_CLIP_Z_M`, None if nothing of it lies in front of the camera. A
    convex solid's pinhole image is the hull of its vertices' images, so every ray (x, y, 1)
    that meets the clipped box lies in these bounds."""
    z = corners_cam[:, 2]
    vertices = [corners_cam[z >= _CLIP_Z_M]]
    for i, j in _BOX_EDGES:
        if (z[i] - _CLIP_Z_M) * (z[j] - _CLIP_Z_M) < 0:
            t = (_CLIP_Z_M - z[i]) / (z[j] - z[i])
            vertices.append((corners_cam[i] + t * (corners_cam[j] - corners_cam[i]))[None])
    points = np.concatenate(vertices)
    if len(points) == 0:
        return None
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    return (float(x.min()), float(x.max())), (float(y.min()), float(y.max()))


def vehicle_far_depth(
    frame: Frame,
    camera: CameraImage,
    moving_tracks: frozenset[str],
    params: ProjectParams,
    rays: NDArray[np.float64],
) -> NDArray[np.float32]:
    """(H, W) depth of the far side of the nearest moving vehicle box (shrunk, bottom raised) on
    each pixel's ray at the image's time, inf where none: nothing beyond it can be visible.

    Each box's rays are tested only over its footprint: the rows and columns whose rays' extents
    (:func:`~phigenesis.data.camera_tables.footprint_pixels`) meet the bounds of its
    :func:`normalized_footprint`, also for a box that reaches behind the camera (a car alongside),
    where :func:`vehicle_far_depth_reference` tested every pixel; in one pass per box with the
    native kernel (:func:`~phigenesis.data.native.load_ray_box`), else with numpy."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    far = np.full((h, w), np.inf, np.float32)
    boxes = frame.boxes
    dt_s = (camera.timestamp_micros - frame.timestamp_micros) * 1e-6
    camera_from_world = geometry.invert_transform(camera.world_from_camera)
    grid = rays.reshape(h, w, 3)
    for k, track in enumerate(boxes.track_id):
        cls = int(boxes.class_id[k])
        if track not in moving_tracks or cls not in VEHICLE_IDS | PERSON_IDS:
            continue
        clearance = params.occluder_clearance_m if cls in VEHICLE_IDS else 0.0
        shrink = params.occluder_shrink if cls in VEHICLE_IDS else params.person_core
        size = boxes.size_lwh[k] * np.array([shrink, shrink, 1.0])
        size[2] -= clearance
        if np.any(size <= 0):
            continue
        rotation = geometry.quaternion_to_matrix(boxes.orientation_world[k])
        centre = boxes.center_world[k] + boxes.velocity_world[k] * dt_s + rotation[:, 2] * 0.5 * clearance
        camera_from_box = camera_from_world @ geometry.make_transform(rotation, centre)
        corners = geometry.transform_points(camera_from_box, 0.5 * size * geometry.BOX_CORNER_SIGNS)
        bounds = normalized_footprint(corners)
        region = None if bounds is None else footprint_pixels(cal, *bounds)
        if region is None:
            continue
        kernel = load_ray_box() if rays.flags.c_contiguous else None
        if kernel is not None:
            kernel.far_side(rays, region, geometry.invert_transform(camera_from_box), 0.5 * size, far)
            continue
        rows, cols = region
        sub = grid[rows, cols]
        _, t_out = ray_box_depths(sub.reshape(-1, 3), camera_from_box, 0.5 * size)
        np.minimum(far[rows, cols], t_out.reshape(sub.shape[:2]), out=far[rows, cols])
    return far


def vehicle_far_depth_reference(
    frame: Frame,
    camera: CameraImage,
    moving_tracks: frozenset[str],
    params: ProjectParams,
    rays: NDArray[np.float64],
) -> NDArray[np.float32]:
    """The reference :func:`vehicle_far_depth`: each box's rays over the bounding box of its
    projected corners, or over the whole image when a corner lies nearer than ``min_depth_m``.
    Kept for the tests.

    (H, W) depth of the far side of the nearest moving vehicle box (shrunk, bottom raised) on
    each pixel's ray at the image's time, inf where none: nothing beyond it can be visible."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    far = np.full(h * w, np.inf)
    boxes = frame.boxes
    dt_s = (camera.timestamp_micros - frame.timestamp_micros) * 1e-6
    camera_from_world = geometry.invert_transform(camera.world_from_camera)
    for k, track in enumerate(boxes.track_id):
        cls = int(boxes.class_id[k])
        if track not in moving_tracks or cls not in VEHICLE_IDS | PERSON_IDS:
            continue
        clearance = params.occluder_clearance_m if cls in VEHICLE_IDS else 0.0
        shrink = params.occluder_shrink if cls in VEHICLE_IDS else params.person_core
        size = boxes.size_lwh[k] * np.array([shrink, shrink, 1.0])
        size[2] -= clearance
        if np.any(size <= 0):
            continue
        rotation = geometry.quaternion_to_matrix(boxes.orientation_world[k])
        centre = boxes.center_world[k] + boxes.velocity_world[k] * dt_s + rotation[:, 2] * 0.5 * clearance
        camera_from_box = camera_from_world @ geometry.make_transform(rotation, centre)
        corners = geometry.transform_points(camera_from_box, 0.5 * size * geometry.BOX_CORNER_SIGNS)
        if np.all(corners[:, 2] <= 0):
            continue
        region = np.arange(h * w)
        if np.all(corners[:, 2] > params.min_depth_m):
            uv, ok = geometry.project_points(corners, cal.intrinsics, cal.distortion)
            if ok.all():
                u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 1
                u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 1
                u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w - 1), min(v1, h - 1)
                if u0 > u1 or v0 > v1:
                    continue
                vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
                region = (vv * w + uu).ravel()
        _, t_out = ray_box_depths(rays[region], camera_from_box, 0.5 * size)
        far[region] = np.minimum(far[region], t_out)
    return far.reshape(h, w).astype(np.float32)


def _disc(radius: int) -> NDArray[np.uint8]:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _zbuffer(pixel: NDArray[np.int64], z: NDArray[np.float32], size: int) -> NDArray[np.float32]:
    buf = np.full(size, np.inf, np.float32)
    np.minimum.at(buf, pixel, z)
    return buf


def occluder_depth(
    pixel: NDArray[np.int64], z: NDArray[np.float32], radius_px: NDArray[np.int64], shape: tuple[int, int]
) -> NDArray[np.float32]:
    """(H, W) nearest depth of any point whose disc of ``radius_px`` covers each pixel (inf: none).

    Each radius's z-buffer and erosion cover only the rectangle around that radius's points
    that their discs reach (the LiDAR fills a band of rows, the sky and the cameras' edges
    nothing): the same values as over the whole image (:func:`occluder_depth_reference`)."""
    h, w = shape
    occ = np.full((h, w), np.inf, np.float32)
    for r in np.unique(radius_px):
        sel = pixel[radius_px == r]
        zs = z[radius_px == r]
        rows, cols = sel // w, sel % w
        r0, r1 = max(int(rows.min()) - r, 0), min(int(rows.max()) + r + 1, h)
        c0, c1 = max(int(cols.min()) - r, 0), min(int(cols.max()) + r + 1, w)
        cw = c1 - c0
        buf = _zbuffer((rows - r0) * cw + (cols - c0), zs, (r1 - r0) * cw).reshape(r1 - r0, cw)
        if r > 0:
            buf = cv2.erode(buf, _disc(int(r)), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        np.minimum(occ[r0:r1, c0:c1], buf, out=occ[r0:r1, c0:c1])
    return occ


def occluder_depth_reference(
    pixel: NDArray[np.int64], z: NDArray[np.float32], radius_px: NDArray[np.int64], shape: tuple[int, int]
) -> NDArray[np.float32]:
    """The reference :func:`occluder_depth`: every radius's z-buffer and erosion over the whole
    image. Kept for the tests."""
    h, w = shape
    occ = np.full((h, w), np.inf, np.float32)
    for r in np.unique(radius_px):
        sel = radius_px == r
        buf = _zbuffer(pixel[sel], z[sel], h * w).reshape(h, w)
        if r > 0:
            buf = cv2.erode(buf, _disc(int(r)), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        np.minimum(occ, buf, out=occ)
    return occ
