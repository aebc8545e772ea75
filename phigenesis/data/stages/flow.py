"""Scene flow and dynamic masks from the boxes' rigid motion: the stages ``box_tracks`` and
``scene_flow`` and the library functions under them.

Model (world frame, metres, seconds, radians): a box moves rigidly, its centre ``c`` at velocity
``v`` (``Boxes.velocity_world``) while it turns about the world's +z at its yaw rate ``omega``,
so a point ``p`` inside it moves at

    flow(p) = v + (0, 0, omega) x (p - c)          (m/s, world frame)

Points outside every moving box have zero flow. Boxes carry no yaw rate: a track's yaw rate at a
frame is the finite difference of its yaw (wrapped to the shortest arc) between the frame's
neighbours that hold the same track (central where both lie within ``max_gap_s`` of the frame,
one-sided where one does), from :class:`BoxTrackTable`; a difference faster than
``max_yaw_rate_radps`` (a label whose heading flipped by pi, a track id reused) is not a turn and
gives no yaw rate. A box is moving when its centre's
horizontal speed, or its rim's speed from turning (``|omega|`` times its half-diagonal in the
ground plane), exceeds ``moving_mps``; a slower box is static (a parked car, a label's jitter).

Confidence of a box's motion, in [0, 1], the product of:

- the yaw rate's support: 1 for a central difference, 0.75 for a one-sided one, 0.5 for none
  (a track seen in one frame only, its neighbours beyond the gap, or an implausible difference:
  omega taken as 0);
- the box's status: 1 annotated; interpolated ``1 - 0.5 min(1, d / h)`` with ``d`` the time to
  the nearest annotated keyframe and ``h`` half the median keyframe interval (a scene without
  keyframes: 1); 0.5 extrapolated.

Per camera image (:func:`camera_flow`), the dense depth (the completed one where
``complete_depth`` ran) back-projects each pixel to its surface point at the image's capture
time; a point inside a moving box (grown by ``margin_m`` per side, its bottom ``clearance_m``
left out so the road under a car stays static) takes the box's flow, the box at the image's time
(the image's own boxes where a stage made them, else the frame's moved by their motion). Only
the pixels inside each moving box's projected rectangle whose depth lies within the box's range of
camera z are back-projected (in one C pass per box where the native kernels build,
``csrc/scene_flow.c``, else :func:`_box_pixels_numpy`): the rest of an image pays only for its
maps' allocation, a depth test (the confidence map) and a finiteness check. Per LiDAR point
(:func:`points_flow`), the box is taken at the point's own measurement time.

Pipelines place ``box_tracks`` early (after the boxes exist: after ``interpolate_boxes`` for
nuScenes) so that it records every frame's boxes as the scene-wide passes (``aggregate_lidar``)
and the writer load them, and ``scene_flow`` after ``complete_depth``. Without ``box_tracks`` the
flow stage reads the neighbours' boxes from its own frames (a lazily loaded frame then runs every
stage before it again; it warns once).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.camera_tables import pixel_rays_cam
from phigenesis.data.native import load_scene_flow_pixels
from phigenesis.data.records import (
    BOX_STATUSES,
    Boxes,
    CameraFlow,
    CameraImage,
    Frame,
    LazyFrames,
    Scene,
    frame_geometry,
)
from phigenesis.data.stages import register_stage
from phigenesis.data.stages.aggregate import sweep_dt_s
from phigenesis.data.stages.semantics import box_rectangles
from phigenesis.options import check_options, option

log = logging.getLogger("phigenesis.prep")

#: Which implementation of the per-box pixel pass :func:`camera_flow` uses.
PixelBackend = Literal["auto", "numpy"]
#: ``Scene.products`` key of the :class:`BoxTrackTable` that ``box_tracks`` leaves.
TRACKS_PRODUCT = "box_tracks"
#: Confidence of a yaw rate from a central difference, a one-sided one, and none.
YAW_SUPPORT_CONFIDENCE = (1.0, 0.75, 0.5)
#: Confidence factor of an extrapolated box.
EXTRAPOLATED_CONFIDENCE = 0.5
_ANNOTATED, _INTERPOLATED, _EXTRAPOLATED = range(len(BOX_STATUSES))


@dataclass(frozen=True)
class SceneFlowParams:
    """Parameters of the ``scene_flow`` stage (lengths in metres, speeds in m/s, times in seconds).

    Attributes:
        moving_mps: a box whose centre's horizontal speed, or whose rim's turning speed, exceeds
            this is moving; slower boxes are static (zero flow, not dynamic).
        margin_m: boxes grow by this on every side when testing which points they hold.
        clearance_m: the bottom this much of a box is left out (the road under it stays static).
        max_gap_s: a neighbouring frame further than this from the frame does not give the yaw
            rate (a track lost and found again is not differenced across the gap).
        max_yaw_rate_radps: a yaw difference faster than this (rad/s) is not a turn (a heading
            flipped by pi, a reused track id): the box gets no yaw rate, at lower confidence.
        lidar: also give every LiDAR point of the frame's sweep its flow.
    """

    moving_mps: float = option(0.5, ge=0, le=100)
    margin_m: float = option(0.1, ge=0, le=10)
    clearance_m: float = option(0.1, ge=0, le=10)
    max_gap_s: float = option(0.3, gt=0, le=60)
    max_yaw_rate_radps: float = option(2.0, gt=0, le=100)
    lidar: bool = option(True)

    def __post_init__(self) -> None:
        check_options(self, "SceneFlowParams")


@dataclass(frozen=True)
class BoxTracksParams:
    """The ``box_tracks`` stage takes no parameters (an empty mapping; a key is a typo)."""

    def __post_init__(self) -> None:
        check_options(self, "BoxTracksParams")


@dataclass(frozen=True)
class BoxMotion:
    """The rigid motion of M boxes at one time.

    Attributes:
        yaw_rate_radps: (M,) float64 turn rate about the world's +z, rad/s.
        moving: (M,) bool: the box moves (see the module docstring); static boxes give no flow.
        confidence: (M,) float32 in [0, 1] (module docstring).
    """

    yaw_rate_radps: NDArray[np.float64]
    moving: NDArray[np.bool_]
    confidence: NDArray[np.float32]


# --------------------------------------------------------------------------------------------
# Rigid motion


def rigid_flow(
    points_world: NDArray[np.floating],
    center_world: NDArray[np.floating],
    velocity_world: NDArray[np.floating],
    yaw_rate_radps: float,
) -> NDArray[np.float64]:
    """(N, 3) float64 velocity, m/s, world frame, of (N, 3) points rigidly attached to a body whose
    point ``center_world`` (3,) moves at ``velocity_world`` (3,) m/s while it turns at
    ``yaw_rate_radps`` about the world's +z: ``v + (0, 0, omega) x (p - c)``."""
    p = np.asarray(points_world, np.float64).reshape(-1, 3)
    r = p - np.asarray(center_world, np.float64).reshape(3)  # [N, 3]
    w = float(yaw_rate_radps)
    out = np.empty_like(r)
    v = np.asarray(velocity_world, np.float64).reshape(3)
    out[:, 0] = v[0] - w * r[:, 1]
    out[:, 1] = v[1] + w * r[:, 0]
    out[:, 2] = v[2]
    return out


def _check_boxes(boxes: Boxes, where: str) -> None:
    """Raises ValueError naming ``where`` and the track unless every velocity is finite."""
    bad = ~np.isfinite(boxes.velocity_world).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"scene_flow: {where}: box {boxes.track_id[k]!r} has velocity_world "
            f"{boxes.velocity_world[k].tolist()} m/s; scene flow needs a finite velocity for every box "
            "(run interpolate_boxes on keyframe annotations, or leave the box out at the source)"
        )


def _rotation_z(angle_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 3, 3) rotations about +z."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out = np.zeros((len(c), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1], out[:, 2, 2] = c, -s, s, c, 1.0
    return out


def boxes_moved(boxes: Boxes, yaw_rate_radps: NDArray[np.float64], dt_s: float) -> Boxes:
    """The boxes ``dt_s`` seconds later under their rigid motion: centre + v dt (first order),
    orientation and velocity turned by ``omega dt`` about +z (status and the rest kept)."""
    if dt_s == 0 or len(boxes) == 0:
        return boxes
    turn = _rotation_z(yaw_rate_radps * dt_s)  # [M, 3, 3]
    turn_q = geometry.yaw_to_quaternion(yaw_rate_radps * dt_s)  # [M, 4]
    return dataclasses.replace(
        boxes,
        center_world=boxes.center_world + boxes.velocity_world * dt_s,
        yaw_world=geometry.wrap_angle(boxes.yaw_world + yaw_rate_radps * dt_s),
        orientation_world=geometry.quaternion_multiply(turn_q, boxes.orientation_world),
        velocity_world=np.einsum("mij,mj->mi", turn, boxes.velocity_world),
    )


def _inside(
    local: NDArray[np.float64], half: NDArray[np.float64], margin_m: float, clearance_m: float
) -> NDArray[np.bool_]:
    """(P,) which box-frame points (P, 3) lie in the box of half sizes ``half`` grown by
    ``margin_m``, its bottom ``clearance_m`` left out."""
    return (
        (np.abs(local[:, 0]) <= half[0] + margin_m)
        & (np.abs(local[:, 1]) <= half[1] + margin_m)
        & (local[:, 2] <= half[2] + margin_m)
        & (local[:, 2] >= -half[2] + clearance_m)
    )


# --------------------------------------------------------------------------------------------
# Yaw rates and confidences


class BoxTrackTable:
    """Every frame's boxes of a scene, by frame index, as the frames pass ``box_tracks`` (or as
    :meth:`at` loads them from ``frames``): what the yaw rates are differenced from.

    Holds per frame its time and, per track, the box's yaw (a few dozen bytes a box)."""

    def __init__(self, frames: Sequence[Frame]):
        self.frames = frames
        self._frames: dict[int, tuple[int, dict[str, float]]] = {}

    def record(self, frame: Frame) -> Frame:
        """Keeps ``frame``'s time and its boxes' yaws; returns the frame unchanged."""
        b = frame.boxes
        self._frames[frame.frame_index] = (
            frame.timestamp_micros,
            dict(zip(b.track_id, b.yaw_world.tolist(), strict=True)),
        )
        return frame

    def at(self, index: int) -> tuple[int, dict[str, float]] | None:
        """(time, track -> yaw) of frame ``index`` (loaded as geometry if not yet recorded), None
        outside the scene."""
        if not 0 <= index < len(self.frames):
            return None
        if index not in self._frames:
            self.record(frame_geometry(self.frames, index))
        return self._frames[index]


def yaw_rates(
    boxes: Boxes,
    time_micros: int,
    before: tuple[int, dict[str, float]] | None,
    after: tuple[int, dict[str, float]] | None,
    max_gap_s: float,
    max_yaw_rate_radps: float = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
    """(M,) yaw rates (rad/s) of ``boxes`` at ``time_micros`` from the yaws of the same tracks in
    the neighbouring frames ``before`` and ``after`` (each (time, track -> yaw) or None), and
    (M,) the support's confidence (:data:`YAW_SUPPORT_CONFIDENCE`). Differences are wrapped to
    the shortest arc; a neighbour further than ``max_gap_s`` is not used, and a rate beyond
    ``max_yaw_rate_radps`` is dropped (0, support as for none)."""
    m = len(boxes)
    rate = np.zeros(m)
    support = np.full(m, YAW_SUPPORT_CONFIDENCE[2], np.float32)
    near = [
        n if n is not None and 0 < abs(n[0] - time_micros) * 1e-6 <= max_gap_s else None
        for n in (before, after)
    ]
    for k, track in enumerate(boxes.track_id):
        ends = [(n[0], n[1][track]) for n in near if n is not None and track in n[1]]
        if len(ends) == 2:
            (t0, y0), (t1, y1) = ends
            support[k] = YAW_SUPPORT_CONFIDENCE[0]
        elif len(ends) == 1:
            (t0, y0), (t1, y1) = sorted([ends[0], (time_micros, float(boxes.yaw_world[k]))])
            support[k] = YAW_SUPPORT_CONFIDENCE[1]
        else:
            continue
        rate[k] = float(geometry.angle_difference(y1, y0)) / ((t1 - t0) * 1e-6)
        if abs(rate[k]) > max_yaw_rate_radps:
            rate[k], support[k] = 0.0, YAW_SUPPORT_CONFIDENCE[2]
    return rate, support


def status_confidence(
    boxes: Boxes, time_micros: int, keyframe_micros: NDArray[np.int64]
) -> NDArray[np.float32]:
    """(M,) confidence factor of each box's status (module docstring); ``keyframe_micros`` the
    scene's annotated keyframe times (empty: none)."""
    out = np.ones(len(boxes), np.float32)
    out[boxes.status == _EXTRAPOLATED] = EXTRAPOLATED_CONFIDENCE
    interpolated = boxes.status == _INTERPOLATED
    if interpolated.any() and len(keyframe_micros) >= 2:
        half_s = 0.5 * float(np.median(np.diff(keyframe_micros))) * 1e-6
        d_s = float(np.min(np.abs(keyframe_micros - time_micros))) * 1e-6
        out[interpolated] = 1.0 - 0.5 * min(1.0, d_s / half_s)
    return out


def box_motion(
    boxes: Boxes,
    yaw_rate_radps: NDArray[np.float64],
    support: NDArray[np.float32],
    status: NDArray[np.float32],
    moving_mps: float,
) -> BoxMotion:
    """The :class:`BoxMotion` of ``boxes``: moving where the centre's horizontal speed or the rim's
    turning speed exceeds ``moving_mps``; confidence = support x status."""
    speed = np.linalg.norm(boxes.velocity_world[:, :2], axis=1)
    rim = np.abs(yaw_rate_radps) * 0.5 * np.linalg.norm(boxes.size_lwh[:, :2], axis=1)
    moving = (speed > moving_mps) | (rim > moving_mps)
    return BoxMotion(yaw_rate_radps, moving, (support * status).astype(np.float32))


# --------------------------------------------------------------------------------------------
# Cameras and points


def camera_flow(
    camera: CameraImage,
    boxes: Boxes,
    motion: BoxMotion,
    depth_m: NDArray[np.float32],
    params: SceneFlowParams,
    backend: PixelBackend = "auto",
) -> CameraFlow:
    """The flow map, dynamic mask and confidence of one image (:class:`CameraFlow`).

    Args:
        camera: the image (its calibration and pose at its capture time).
        boxes: M boxes at the image's capture time, world frame.
        motion: their :class:`BoxMotion`.
        depth_m: (H, W) float32 z-depth, metres, 0 where unknown.
        params: margin, clearance.
        backend: "auto" (the native pixel pass where it builds, else numpy) or "numpy" (the plain
            reference, :func:`_box_pixels_numpy`).

    Only the pixels inside the projected rectangle of a moving box are back-projected; where boxes
    overlap, the one whose centre is nearest the point wins.
    """
    cal = camera.calibration
    h, w = cal.height, cal.width
    depth_m = np.asarray(depth_m)
    if depth_m.shape != (h, w):
        raise ValueError(f"scene_flow: camera {cal.name}: depth is {depth_m.shape}, the image {(h, w)}")
    if not np.isfinite(depth_m.sum(dtype=np.float64)):  # one pass: any NaN or inf makes the sum so
        where = f"camera {cal.name} at {camera.timestamp_micros}"
        raise ValueError(f"scene_flow: {where}: the depth map holds non-finite values")
    flow = np.zeros((h, w, 3), np.float32)
    dynamic = np.zeros((h, w), bool)
    confidence = (depth_m > 0).astype(np.float32)
    moving = np.flatnonzero(motion.moving)
    if moving.size == 0:
        return CameraFlow(flow, dynamic, confidence)
    mb = boxes.select(moving)
    rects = box_rectangles(camera, mb, params.margin_m)
    world_from_camera = camera.world_from_camera
    world_rotation = world_from_camera[:3, :3]
    # Each box in the camera frame, so a pixel's point is tested without a transform to the world.
    center_cam = (mb.center_world - world_from_camera[:3, 3]) @ world_rotation  # [M, 3]: R^T (c - t)
    camera_from_box = world_rotation.T @ geometry.quaternion_to_matrix(mb.orientation_world).reshape(-1, 3, 3)
    # The z range of each grown box's corners: a point inside the (convex) box has its z in it, so
    # only the pixels of its rectangle whose depth lies in that range are back-projected.
    grown = 0.5 * mb.size_lwh + params.margin_m  # [M, 3]
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)  # [8, 3]
    corner_z = center_cam[:, None, 2] + np.einsum("mk,ck,mk->mc", camera_from_box[:, 2, :], signs, grown)
    best = np.zeros((h, w), np.float32)  # squared distance to the winning centre + 1; 0 = none
    kernel = load_scene_flow_pixels() if backend == "auto" else None
    box_pass = _box_pixels_numpy if kernel is None else kernel
    depth32 = np.ascontiguousarray(depth_m, np.float32)
    rays_flat = pixel_rays_cam(cal)
    rows_xy = np.ascontiguousarray(world_rotation[:2])
    for j, rect in enumerate(rects):
        if rect is None:
            continue
        half = 0.5 * mb.size_lwh[j]
        limits = np.array([half[0] + params.margin_m, half[1] + params.margin_m, half[2] + params.margin_m,
                           -half[2] + params.clearance_m])  # fmt: skip
        k = moving[j]
        box_pass(
            depth32, rays_flat, rect, (max(float(corner_z[j].min()), 0.0), float(corner_z[j].max())),
            center_cam[j], camera_from_box[j], limits, rows_xy, mb.velocity_world[j],
            float(motion.yaw_rate_radps[k]), float(motion.confidence[k]), best, flow, dynamic, confidence,
        )  # fmt: skip
    return CameraFlow(flow, dynamic, confidence)


def _box_pixels_numpy(
    depth: NDArray[np.float32],
    rays: NDArray[np.float64],
    rect: tuple[int, int, int, int],
    z_range: tuple[float, float],
    center_cam: NDArray[np.float64],
    camera_from_box: NDArray[np.float64],
    limits: NDArray[np.float64],
    world_rotation_xy: NDArray[np.float64],
    velocity: NDArray[np.float64],
    yaw_rate_radps: float,
    box_confidence: float,
    best: NDArray[np.float32],
    flow: NDArray[np.float32],
    dynamic: NDArray[np.bool_],
    confidence: NDArray[np.float32],
) -> int:
    """The plain numpy twin of the native pixel pass (``csrc/scene_flow.c``,
    :class:`~phigenesis.data.native.SceneFlowPixels`, same arguments): the pixels of ``rect`` =
    (v0, v1, u0, u1) whose depth lies in ``z_range`` = (exclusive, inclusive) and whose point lies
    inside the box (camera-frame centre ``center_cam``, rotation ``camera_from_box``, box-frame
    ``limits`` |x|, |y| <= limits[0:2], limits[3] <= z <= limits[2]) take its rigid flow where its
    centre is nearer than ``best`` (|o|^2 + 1, 0 = none). Writes in place; returns how many took it."""
    h, w = depth.shape
    v0, v1, u0, u1 = rect
    d = depth[v0:v1, u0:u1]
    known = (d > z_range[0]) & (d <= z_range[1])
    z = d[known].astype(np.float64)
    if z.size == 0:
        return 0
    offset = rays.reshape(h, w, 3)[v0:v1, u0:u1][known] * z[:, None] - center_cam  # [P, 3] camera frame
    local = offset @ camera_from_box  # [P, 3] box frame
    inside = (
        (np.abs(local[:, 0]) <= limits[0])
        & (np.abs(local[:, 1]) <= limits[1])
        & (local[:, 2] <= limits[2])
        & (local[:, 2] >= limits[3])
    )
    within = np.flatnonzero(known.ravel())[inside]  # positions in the rectangle, row-major
    index = (within // (u1 - u0) + v0) * w + within % (u1 - u0) + u0  # [P'] flat pixel index
    offset = offset[inside]
    dist = (np.einsum("ij,ij->i", offset, offset) + 1.0).astype(np.float32)
    flat_best = best.reshape(-1)
    win = (flat_best[index] == 0) | (dist < flat_best[index])
    index = index[win]
    flat_best[index] = dist[win]
    q = offset[win] @ world_rotation_xy.T  # [P', 2] world x, y of point - centre
    flat_flow = flow.reshape(-1, 3)
    flat_flow[index, 0] = velocity[0] - yaw_rate_radps * q[:, 1]
    flat_flow[index, 1] = velocity[1] + yaw_rate_radps * q[:, 0]
    flat_flow[index, 2] = velocity[2]
    dynamic.reshape(-1)[index] = True
    confidence.reshape(-1)[index] = box_confidence
    return int(index.size)


def points_flow(
    points_world: NDArray[np.floating],
    dt_s: NDArray[np.floating],
    boxes: Boxes,
    motion: BoxMotion,
    params: SceneFlowParams,
) -> NDArray[np.float32]:
    """(N, 3) float32 flow, m/s, world frame, of (N, 3) world points measured ``dt_s`` (N,)
    seconds after the boxes' time: each point inside a moving box at its own time (the box moved
    by its rigid motion over ``dt_s``) takes the box's rigid flow there; 0 elsewhere. Where boxes
    overlap, the one whose centre is nearest wins."""
    p_all = np.asarray(points_world, np.float64).reshape(-1, 3)
    dt = np.asarray(dt_s, np.float64).reshape(-1)
    if len(dt) != len(p_all):
        raise ValueError(f"scene_flow: {len(p_all)} points but {len(dt)} time offsets")
    out = np.zeros((len(p_all), 3), np.float32)
    best = np.full(len(p_all), np.inf)
    reach = float(np.abs(dt).max(initial=0.0))
    rotations = geometry.quaternion_to_matrix(boxes.orientation_world).reshape(-1, 3, 3)
    movers = np.flatnonzero(motion.moving).tolist()
    # The points by world x: a box's candidates are the run within its reach in x (bisection), not
    # a pass over every point per box.
    by_x = np.argsort(p_all[:, 0], kind="stable") if movers else np.zeros(0, np.int64)
    xs = p_all[by_x, 0]
    for k in movers:
        c, v, omega = boxes.center_world[k], boxes.velocity_world[k], float(motion.yaw_rate_radps[k])
        half = 0.5 * boxes.size_lwh[k]
        radius = float(np.linalg.norm(half + params.margin_m)) + float(np.linalg.norm(v)) * reach + 1e-6
        run = by_x[np.searchsorted(xs, c[0] - radius) : np.searchsorted(xs, c[0] + radius, "right")]
        near = run[np.sum((p_all[run, :2] - c[:2]) ** 2, axis=1) <= radius**2]
        if near.size == 0:
            continue
        t = dt[near]
        turn = _rotation_z(omega * t)  # [P, 3, 3]
        c_t = c + v * t[:, None]  # [P, 3] centre at each point's time
        offset = p_all[near] - c_t
        local = np.einsum("pji,pj->pi", turn @ rotations[k], offset)  # box frame: (T R)^T (p - c_t)
        inside = _inside(local, half, params.margin_m, params.clearance_m)
        dist = np.einsum("ij,ij->i", offset, offset)
        win = inside & (dist < best[near])
        idx = near[win]
        best[idx] = dist[win]
        v_t = turn[win] @ v  # [P', 3]
        r = offset[win]
        out[idx, 0] = v_t[:, 0] - omega * r[:, 1]
        out[idx, 1] = v_t[:, 1] + omega * r[:, 0]
        out[idx, 2] = v_t[:, 2]
    return out


# --------------------------------------------------------------------------------------------
# The stages


@register_stage("box_tracks", params=BoxTracksParams)
def box_tracks(scene: Scene, p: BoxTracksParams) -> Scene:
    """Stage: records every frame's boxes as frames pass (a :class:`BoxTrackTable` in
    ``scene.products["box_tracks"]``) for ``scene_flow``'s yaw rates; frames pass unchanged.
    Place it where frames are cheap to load again (before the depth stages)."""
    table = BoxTrackTable(scene.frames)
    scene.products[TRACKS_PRODUCT] = table
    scene.frames = scene.frames.map(table.record) if isinstance(scene.frames, LazyFrames) else scene.frames
    if not isinstance(scene.frames, LazyFrames):
        for frame in scene.frames:
            table.record(frame)
    return scene


def frame_motion(
    frame: Frame,
    boxes: Boxes,
    time_micros: int,
    table: BoxTrackTable,
    keyframe_micros: NDArray[np.int64],
    params: SceneFlowParams,
    where: str,
) -> BoxMotion:
    """The :class:`BoxMotion` of ``boxes`` at ``time_micros`` (the frame's boxes, or an image's at
    its own time) from the frame's neighbours in ``table``."""
    _check_boxes(boxes, where)
    i = frame.frame_index
    before, after = table.at(i - 1), table.at(i + 1)
    rate, support = yaw_rates(boxes, time_micros, before, after, params.max_gap_s, params.max_yaw_rate_radps)
    status = status_confidence(boxes, time_micros, keyframe_micros)
    return box_motion(boxes, rate, support, status, params.moving_mps)


def flow_frame(
    frame: Frame, table: BoxTrackTable, keyframe_micros: NDArray[np.int64], p: SceneFlowParams
) -> Frame:
    """``frame`` with every camera's :class:`CameraFlow` (cameras without depth get none) and,
    with ``p.lidar``, its sweep's per-point flow."""
    where = f"scene {frame.scene_id} frame {frame.frame_index}"
    motion = frame_motion(frame, frame.boxes, frame.timestamp_micros, table, keyframe_micros, p, where)
    cameras = []
    for cam in frame.cameras:
        if cam.depth is None:
            cameras.append(cam)
            continue
        depth = cam.depth.dense_m if cam.depth.dense_m is not None else cam.depth.sparse_m
        if cam.boxes is not None:  # the image's own boxes (interpolate_boxes), same tracks
            boxes = cam.boxes
            cam_where = f"{where} camera {cam.name}"
            cam_motion = frame_motion(
                frame, boxes, cam.timestamp_micros, table, keyframe_micros, p, cam_where
            )
        else:
            dt_s = (cam.timestamp_micros - frame.timestamp_micros) * 1e-6
            boxes, cam_motion = boxes_moved(frame.boxes, motion.yaw_rate_radps, dt_s), motion
        cameras.append(dataclasses.replace(cam, flow=camera_flow(cam, boxes, cam_motion, depth, p)))
    lidar = frame.lidar
    if p.lidar and lidar is not None:
        flow = points_flow(
            lidar.points_world(), sweep_dt_s(lidar, frame.timestamp_micros), frame.boxes, motion, p
        )
        lidar = dataclasses.replace(lidar, flow_world_mps=flow)
    return dataclasses.replace(frame, cameras=cameras, lidar=lidar)


@register_stage("scene_flow", params=SceneFlowParams)
def scene_flow(scene: Scene, p: SceneFlowParams) -> Scene:
    """Stage: every camera's flow map, dynamic mask and confidence (``CameraImage.flow``) and,
    with ``p.lidar``, every LiDAR point's flow (``LidarSweep.flow_world_mps``): the module
    docstring. Runs after ``complete_depth`` (it back-projects the dense depth); yaw rates come
    from ``box_tracks``' table where that ran. Lazy per frame."""
    table = scene.products.get(TRACKS_PRODUCT)
    if table is None:
        if isinstance(scene.frames, LazyFrames):
            log.warning(
                "scene_flow: scene %s: no box_tracks stage before it; the yaw rates load neighbouring frames "
                "through every stage again (put box_tracks early in the pipeline)",
                scene.scene_id,
            )
        table = BoxTrackTable(scene.frames)
    keyframe_micros = np.array([k.timestamp_micros for k in scene.keyframes], np.int64)

    def run(frame: Frame) -> Frame:
        return flow_frame(frame, table, keyframe_micros, p)

    scene.frames = (
        scene.frames.map(run) if isinstance(scene.frames, LazyFrames) else [run(f) for f in scene.frames]
    )
    return scene
