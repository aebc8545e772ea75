"""Pictures of a frame: cameras as a panorama with boxes, depth and semantics, and a bird's-eye view."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data import taxonomy as tx
from phigenesis.data.records import CameraImage, Frame

BEV_RANGE_M = 60.0
#: Camera images taller than this are drawn shrunk to it (real datasets' 1280-pixel images).
MAX_CAMERA_HEIGHT_PX = 320


def draw_frame(frame: Frame, scale: int = 2) -> NDArray[np.uint8]:
    """An RGB picture of a frame: rows of camera images (left to right as seen from the car) with
    projected boxes, then truth depth and semantics (or the dataset's labels) where the frame has
    them, and a bird's-eye view of the LiDAR and boxes on the right."""
    cams = sorted(frame.cameras, key=lambda c: -_camera_yaw(c))
    factor = min(1.0, MAX_CAMERA_HEIGHT_PX / max(c.calibration.height for c in cams))

    def shrink(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        if factor == 1.0:
            return img
        size = (round(img.shape[1] * factor), round(img.shape[0] * factor))
        return cv2.resize(img, size, interpolation=cv2.INTER_NEAREST)

    height = max(round(c.calibration.height * factor) for c in cams)
    rows = [[_with_boxes(c, frame, factor) for c in cams]]
    if all(c.truth is not None for c in cams):
        rows.append([shrink(_depth_color(c.truth.depth_m)) for c in cams])
        rows.append([shrink(tx.PALETTE_RGB[c.truth.semantic]) for c in cams])
    elif any(c.labels is not None for c in cams):
        rows.append(
            [
                shrink(tx.PALETTE_RGB[c.labels.semantic])
                if c.labels is not None
                else np.zeros(
                    (round(c.calibration.height * factor), round(c.calibration.width * factor), 3), np.uint8
                )
                for c in cams
            ]
        )
    mosaic = np.concatenate([np.concatenate([_pad(p, height) for p in row], axis=1) for row in rows], axis=0)
    mosaic = cv2.resize(mosaic, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    bev = _bev(frame, mosaic.shape[0])
    return np.concatenate([mosaic, bev], axis=1)


def _camera_yaw(cam: CameraImage) -> float:
    axis = cam.calibration.ego_from_camera[:3, 2]
    return float(np.arctan2(axis[1], axis[0]))


def _pad(img: NDArray[np.uint8], height: int) -> NDArray[np.uint8]:
    if img.shape[0] == height:
        return img
    out = np.zeros((height, *img.shape[1:]), np.uint8)
    out[: img.shape[0]] = img
    return out


def _depth_color(depth_m: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Turbo colour map of inverse depth (near = red); unknown depth is black."""
    valid = depth_m > 0
    inv = np.where(valid, 1.0 / np.maximum(depth_m, 1e-3), 0.0)
    u8 = np.clip(inv / 0.5 * 255.0, 0, 255).astype(np.uint8)  # 2 m and nearer saturate
    rgb = cv2.applyColorMap(u8, cv2.COLORMAP_TURBO)[..., ::-1]
    rgb[~valid] = 0
    return rgb


def _box_color(class_id: int) -> tuple[int, int, int]:
    c = tx.PALETTE_RGB[class_id]
    return (255, 255, 0) if class_id == tx.CAR else tuple(int(x) for x in np.clip(c.astype(int) + 60, 0, 255))


def _with_boxes(cam: CameraImage, frame: Frame, factor: float = 1.0) -> NDArray[np.uint8]:
    """The image shrunk by ``factor`` with the frame's boxes drawn at the image's capture time."""
    cal = cam.calibration
    width, height = round(cal.width * factor), round(cal.height * factor)
    if cam.image_bytes is None:
        img = np.zeros((height, width, 3), np.uint8)
    else:
        img = cam.decode_image()
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA) if factor != 1.0 else img.copy()
    b = frame.boxes
    if len(b) == 0:
        return img
    # Move boxes to the image's capture time with their velocity, then into the camera.
    dt = (cam.timestamp_micros - frame.timestamp_micros) * 1e-6
    corners = b.corners_world() + (b.velocity_world * dt)[:, None, :]
    camera_from_world = geometry.invert_transform(cam.world_from_camera)
    # Pixel centres stay centres when shrinking: u' = (u + 0.5) * factor - 0.5.
    shrink = np.array([[factor, 0, 0.5 * factor - 0.5], [0, factor, 0.5 * factor - 0.5], [0, 0, 1]])
    intrinsics = shrink @ cal.intrinsics
    for i in range(len(b)):
        pts = geometry.transform_points(camera_from_world, corners[i])
        uv, valid = geometry.project_points(pts, intrinsics, cal.distortion)
        if valid.sum() < 8 or not np.any(geometry.in_image(uv, width, height)):
            continue
        for a, c in geometry.BOX_EDGES:
            p, q = np.round(uv[a]).astype(int), np.round(uv[c]).astype(int)
            cv2.line(img, tuple(p), tuple(q), _box_color(int(b.class_id[i])), 1, cv2.LINE_AA)
    return img


def _bev(frame: Frame, size: int) -> NDArray[np.uint8]:
    """Top view around the ego (x up, y left), LiDAR coloured by height, boxes as outlines."""
    img = np.full((size, size, 3), 20, np.uint8)
    px_per_m = size / (2 * BEV_RANGE_M)

    def to_px(xy_ego: NDArray[np.float64]) -> NDArray[np.int64]:
        col = size / 2 - xy_ego[..., 1] * px_per_m
        row = size / 2 - xy_ego[..., 0] * px_per_m
        return np.stack([col, row], axis=-1).round().astype(np.int64)

    if frame.lidar is not None and len(frame.lidar):
        p = frame.lidar.points_ego.astype(np.float64)
        px = to_px(p[:, :2])
        ok = (px >= 0).all(1) & (px < size).all(1)
        z = np.clip(64 + p[ok, 2] / 5.0 * 191, 64, 255).astype(np.uint8)  # ground dim, tall bright
        img[px[ok, 1], px[ok, 0]] = cv2.applyColorMap(z[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    ego_from_world = geometry.invert_transform(frame.world_from_ego)
    b = frame.boxes
    if len(b):
        corners = geometry.transform_points(ego_from_world, b.corners_world().reshape(-1, 3)).reshape(
            -1, 8, 3
        )
        for i in range(len(b)):
            poly = to_px(corners[i, :4, :2])
            cv2.polylines(img, [poly.astype(np.int32)], True, _box_color(int(b.class_id[i])), 1, cv2.LINE_AA)
    ego = to_px(np.array([[4.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [4.0, -1.0]]))
    cv2.polylines(img, [ego.astype(np.int32)], True, (255, 255, 255), 1, cv2.LINE_AA)
    return img
