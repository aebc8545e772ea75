"""What depends only on a camera's calibration, computed once and shared by every stage.

A camera's pixel rays and the depth at which they meet the ego car's own body depend on the
calibration (and the body's boxes), not on the frame: the depth projection, the pseudo labels,
the depth completion and the range view all need them for every image. They are computed here
once per calibration and shared, read-only, by every stage of every frame of the scenes that use
that calibration (at full Waymo resolution one camera's rays are tens of MB, and solving them
is a per-calibration cost no frame should pay; figures in BENCHMARKS.md, "Prep at real size").

Entry points: :func:`pixel_rays_cam`, :func:`ray_components_of`, :func:`ego_body_depth_of` and
:func:`ray_extents_of` (per row and per column, the range of the rays' normalised coordinates:
what lets a stage work only inside an object's projected footprint). Each keeps the last
:data:`MAX_CACHED_CAMERAS` calibrations (a worker converts one scene at a time, and a rig has at
most six cameras), so memory stays bounded across the scenes of a run. :data:`COMPUTED` counts
what was computed, for the tests and the benchmark to check that it happens once per calibration.

The plain per-image functions (:func:`undistorted_pixel_rays`, :func:`ego_body_depth_from_rays`)
compute what the cached ones return; :func:`undistorted_pixel_rays_reference` is the numpy and
OpenCV path the native kernel is held to (and the fallback without a C compiler).
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data import native
from phigenesis.data.records import CameraCalibration

#: How many calibrations' tables are kept (least recently used dropped first).
MAX_CACHED_CAMERAS = 12
#: What was computed, per table kind ("pixel_rays", "ray_components", "ego_body_depth"): a count per call that
#: missed the cache.
COMPUTED: Counter[str] = Counter()

#: OpenCV's undistortion iterations; pixels it leaves off by more than UNDISTORT_TOLERANCE
#: (normalised units) are solved again with the toolkit's Newton solver.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-15)
UNDISTORT_TOLERANCE = 1e-12

T = TypeVar("T")


def undistorted_pixel_rays_reference(cal: CameraCalibration) -> NDArray[np.float64]:
    """(H * W, 3) float64 camera-frame rays (z = 1) of every pixel centre, row-major: the
    reference of :func:`undistorted_pixel_rays`.

    Equal to ``geometry.unproject_pixels`` of the pixel grid to ~1e-15, several times faster:
    OpenCV's C++ fixed-point undistortion first, then every pixel whose ray does not distort back
    to it within :data:`UNDISTORT_TOLERANCE` (strong distortion, where the fixed point stalls) is
    solved again with the toolkit's Newton solver.
    """
    uv = geometry.pixel_grid(cal.width, cal.height)
    if not cal.distortion.any():
        return geometry.unproject_pixels(uv, cal.intrinsics)
    k = cal.intrinsics
    xy = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), k, cal.distortion, None, np.eye(3), np.eye(3), _UNDISTORT_CRITERIA
    ).reshape(-1, 2)
    off = undistortion_residual(cal, xy)
    redo = ~(off <= UNDISTORT_TOLERANCE)  # NaN included
    if redo.any():
        xy[redo] = geometry.unproject_pixels(uv[redo], k, cal.distortion)[:, :2]
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


def undistortion_residual(cal: CameraCalibration, xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """(H * W,) float64: how far (normalised units, max over x and y) each pixel's undistorted
    point ``xy`` ((H * W, 2), camera frame, z = 1, row-major pixels) lands from the pixel's own
    distorted point when distorted again; NaN for a NaN point. Under :data:`UNDISTORT_TOLERANCE`
    the point is a solution; where no undistorted point maps to a pixel (beyond the fold of a
    non-monotonic distortion) it stays large."""
    uv = geometry.pixel_grid(cal.width, cal.height)
    k = cal.intrinsics
    y_d = (uv[:, 1] - k[1, 2]) / k[1, 1]
    target = np.stack([(uv[:, 0] - k[0, 2] - k[0, 1] * y_d) / k[0, 0], y_d], axis=-1)
    return np.abs(geometry.distort_normalized(xy, cal.distortion) - target).max(axis=1)


def undistorted_pixel_rays(cal: CameraCalibration) -> NDArray[np.float64]:
    """(H * W, 3) float64 camera-frame rays (z = 1) of every pixel centre, row-major.

    With the native kernel (``csrc/camera_rays.c``) every pixel is solved by Newton's method
    from a prediction (the line through the solutions of the two rows above it) until it
    distorts back to the pixel within :data:`UNDISTORT_TOLERANCE`, then one step more, on the
    image's own sheet of the distortion (Jacobian determinant > 0), four pixels a vector. On the
    real Waymo calibrations it equals :func:`undistorted_pixel_rays_reference`
    to 2.8e-16 (normalised units); wherever a solution exists it is within 1e-13 of
    :func:`~phigenesis.geometry.unproject_pixels` and within 2e-12 of the reference (which takes
    OpenCV's points at a residual of 1e-12). Where none does (beyond the fold of a distortion
    that is not monotonic up to the image's corners) both give
    :func:`~phigenesis.geometry.undistort_normalized`'s last iterate, clamped to the monotonic
    radius: a ray, not a solution. Without a C compiler: the reference. Computed anew
    on every call; stages use :func:`pixel_rays_cam`.
    """
    kernel = native.load_camera_rays() if cal.distortion.any() else None
    if kernel is None:
        return undistorted_pixel_rays_reference(cal)
    rays = np.empty((cal.width * cal.height, 3), np.float64)
    r_max = geometry.max_monotonic_radius(cal.distortion)
    kernel.undistort_grid(cal.width, cal.height, cal.intrinsics, cal.distortion, r_max, rays)
    return rays


def ray_box_depths(
    rays_cam: NDArray[np.float64], camera_from_box: NDArray[np.float64], half_size: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where rays from the camera centre (z = 1, so the parameter is the z-depth) enter and leave
    a box (slab test in the box frame). Returns (P,) entry and exit depths, inf where a ray
    misses or the box is behind the camera; an entry of 0 means the camera is inside."""
    box_from_camera = geometry.invert_transform(camera_from_box)
    d = rays_cam @ box_from_camera[:3, :3].T
    o = box_from_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half_size - o) / d, (half_size - o) / d
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        # fmax/fmin skip the NaN of a ray parallel to a slab with its origin on the slab's plane.
        t_near = np.fmax(np.fmax(lo[:, 0], lo[:, 1]), lo[:, 2])
        t_far = np.fmin(np.fmin(hi[:, 0], hi[:, 1]), hi[:, 2])
    hit = np.isfinite(t_near) & np.isfinite(t_far) & (t_far >= np.maximum(t_near, 0.0))
    return np.where(hit, np.maximum(t_near, 0.0), np.inf), np.where(hit, t_far, np.inf)


def ego_body_depth_from_rays(
    cal: CameraCalibration, ego_boxes: Sequence[dict[str, Any]], rays_cam: NDArray[np.float64]
) -> NDArray[np.float32]:
    """(H, W) z-depth (m) at which each pixel's ray (``rays_cam``, (H * W, 3), camera frame,
    z = 1) enters the ego body boxes (each a ``center_ego`` and ``size_lwh``, ego frame, axis
    aligned), inf where it misses."""
    camera_from_ego = geometry.invert_transform(cal.ego_from_camera)
    entry = np.full(len(rays_cam), np.inf)
    for b in ego_boxes:
        camera_from_box = camera_from_ego @ geometry.make_transform(np.eye(3), b["center_ego"])
        t_in, _ = ray_box_depths(rays_cam, camera_from_box, 0.5 * np.asarray(b["size_lwh"], np.float64))
        np.minimum(entry, t_in, out=entry)
    return entry.reshape(cal.height, cal.width).astype(np.float32)


@dataclass(frozen=True)
class RayComponents:
    """A camera's pixel rays (camera frame, z = 1) as (H, W) float32 planes, for per-frame work
    that is linear in the ray: with ``R``, ``t`` a frame's pose, the world point of a pixel at
    z-depth ``d`` is ``t + d * R @ (x, y, 1)``, so its height above a plane, its lateral offset
    or its elevation are ``a + d * (b x + c y + e)``: a few (H, W) float32 operations instead of
    (H * W, 3) float64 points. float32 moves a point at 80 m by about 5 um.

    Attributes:
        x, y: (H, W) float32, the ray's x and y (its z is 1).
        norm: (H, W) float32, the ray's length ``sqrt(x^2 + y^2 + 1)`` (range = depth * norm).
        column_x: (2, W) float64, the least and greatest x of each column's rays.
        row_y: (2, H) float64, the least and greatest y of each row's rays.
    """

    x: NDArray[np.float32]
    y: NDArray[np.float32]
    norm: NDArray[np.float32]
    column_x: NDArray[np.float64]
    row_y: NDArray[np.float64]

    def rectangle(
        self, x_min: float, x_max: float, y_min: float, y_max: float
    ) -> tuple[int, int, int, int] | None:
        """The smallest pixel rectangle ``(v0, v1, u0, u1)`` (rows ``v0:v1``, columns ``u0:u1``)
        holding every pixel whose ray has ``x_min <= x <= x_max`` and ``y_min <= y <= y_max``
        (camera frame, z = 1); None where no pixel has. Exact under any distortion: a column is
        in it if its rays' x range meets ``[x_min, x_max]``, a row if its y range meets
        ``[y_min, y_max]``."""
        cols = np.flatnonzero((self.column_x[1] >= x_min) & (self.column_x[0] <= x_max))
        rows = np.flatnonzero((self.row_y[1] >= y_min) & (self.row_y[0] <= y_max))
        if cols.size == 0 or rows.size == 0:
            return None
        return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def ray_components_from_rays(cal: CameraCalibration, rays_cam: NDArray[np.float64]) -> RayComponents:
    """:class:`RayComponents` of (H * W, 3) z = 1 camera-frame rays (computed in float64, then
    rounded to float32): :func:`ray_components_reference`, in one pass with the native kernel
    (``csrc/camera_rays.c``) where it builds."""
    kernel = native.load_camera_rays()
    if kernel is None or not rays_cam.flags.c_contiguous:
        return ray_components_reference(cal, rays_cam)
    out = RayComponents(*kernel.ray_components(rays_cam, cal.width, cal.height))
    for a in (out.x, out.y, out.norm, out.column_x, out.row_y):
        a.setflags(write=False)
    return out


def ray_components_reference(cal: CameraCalibration, rays_cam: NDArray[np.float64]) -> RayComponents:
    """:func:`ray_components_from_rays` in numpy (the native kernel equals it exactly)."""
    h, w = cal.height, cal.width
    x = rays_cam[:, 0].reshape(h, w)
    y = rays_cam[:, 1].reshape(h, w)
    norm = np.sqrt(x * x + y * y + 1.0)
    out = RayComponents(
        x.astype(np.float32),
        y.astype(np.float32),
        norm.astype(np.float32),
        np.stack([x.min(axis=0), x.max(axis=0)]),
        np.stack([y.min(axis=1), y.max(axis=1)]),
    )
    for a in (out.x, out.y, out.norm, out.column_x, out.row_y):
        a.setflags(write=False)
    return out


def ego_body_depth_native(
    cal: CameraCalibration, ego_boxes: Sequence[dict[str, Any]], rays_cam: NDArray[np.float64]
) -> NDArray[np.float32] | None:
    """:func:`ego_body_depth_from_rays` with the native kernel (``csrc/camera_rays.c``: every box
    in one vectorised pass, instead of numpy's many passes over (H * W, 3) float64
    temporaries); None where the kernel cannot be
    built here. Equal to the reference to float32 rounding."""
    kernel = native.load_camera_rays()
    if kernel is None or not rays_cam.flags.c_contiguous:
        return None
    camera_from_ego = geometry.invert_transform(cal.ego_from_camera)
    entry = np.full((cal.height, cal.width), np.inf, np.float32)
    if not ego_boxes:
        return entry
    box_from_camera = [
        geometry.invert_transform(camera_from_ego @ geometry.make_transform(np.eye(3), b["center_ego"]))
        for b in ego_boxes
    ]
    half = [0.5 * np.asarray(b["size_lwh"], np.float64) for b in ego_boxes]
    kernel.boxes_near(rays_cam, np.stack(box_from_camera), np.stack(half), entry)
    return entry


class _Tables:
    """A small least-recently-used map from keys to read-only arrays, safe across threads (the
    depth projection works on a frame's cameras in threads)."""

    def __init__(self, kind: str, size: int):
        self.kind = kind
        self.size = size
        self.items: OrderedDict[Any, Any] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: Any, compute: Callable[[], T]) -> T:
        with self.lock:  # held while computing: two threads never compute the same table
            if key in self.items:
                self.items.move_to_end(key)
                return self.items[key]
            value = compute()
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            COMPUTED[self.kind] += 1
            self.items[key] = value
            while len(self.items) > self.size:
                self.items.popitem(last=False)
            return value

    def clear(self) -> None:
        with self.lock:
            self.items.clear()


_RAYS = _Tables("pixel_rays", MAX_CACHED_CAMERAS)
_EGO_DEPTH = _Tables("ego_body_depth", MAX_CACHED_CAMERAS)
_RAY_COMPONENTS = _Tables("ray_components", MAX_CACHED_CAMERAS)
_EXTENTS = _Tables("ray_extents", MAX_CACHED_CAMERAS)


def pixel_rays_cam(cal: CameraCalibration) -> NDArray[np.float64]:
    """(H * W, 3) float64 camera-frame rays (z = 1) of every pixel centre, row-major, read-only:
    :func:`undistorted_pixel_rays`, computed once per calibration."""
    return _RAYS.get(cal.key(), lambda: undistorted_pixel_rays(cal))


def ray_components_of(cal: CameraCalibration) -> RayComponents:
    """The calibration's :class:`RayComponents` (read-only, about 30 MB for a 1920 x 1280
    camera), computed once per calibration from :func:`pixel_rays_cam`."""
    return _RAY_COMPONENTS.get(cal.key(), lambda: ray_components_from_rays(cal, pixel_rays_cam(cal)))


def ego_body_depth_of(cal: CameraCalibration, ego_boxes: Sequence[dict[str, Any]]) -> NDArray[np.float32]:
    """(H, W) float32 z-depth (m) at which each pixel's ray enters the ego body boxes, inf where
    it misses, read-only: :func:`ego_body_depth_from_rays` (with the native kernel where it
    builds, :func:`ego_body_depth_native`), computed once per calibration and body."""
    body = tuple(
        (tuple(float(x) for x in b["center_ego"]), tuple(float(x) for x in b["size_lwh"])) for b in ego_boxes
    )

    def compute() -> NDArray[np.float32]:
        rays = pixel_rays_cam(cal)
        native = ego_body_depth_native(cal, ego_boxes, rays)
        return ego_body_depth_from_rays(cal, ego_boxes, rays) if native is None else native

    return _EGO_DEPTH.get((cal.key(), body), compute)


def ray_extents(cal: CameraCalibration, rays_cam: NDArray[np.float64]) -> NDArray[np.float64]:
    """The extents of the pixel rays' normalised coordinates (x/z, y/z, camera frame): an
    (H + W, 2) array whose first H rows are each image row's (min, max) of y/z and whose last W
    rows are each column's (min, max) of x/z.

    A ray (x, y, 1) can only belong to a pixel of a row whose y-range holds y and of a column
    whose x-range holds x: the pixels whose rays may meet a region bounded by [x0, x1] x
    [y0, y1] lie in the rows and columns whose ranges meet it (:func:`footprint_pixels`)."""
    xy = rays_cam[:, :2].reshape(cal.height, cal.width, 2)
    # fmin/fmax skip NaN rays (they meet nothing); an all-NaN row or column stays NaN and is
    # never selected.
    x, y = xy[:, :, 0], xy[:, :, 1]
    rows = np.stack([np.fmin.reduce(y, axis=1), np.fmax.reduce(y, axis=1)], axis=1)
    cols = np.stack([np.fmin.reduce(x, axis=0), np.fmax.reduce(x, axis=0)], axis=1)
    return np.concatenate([rows, cols])


def ray_extents_of(cal: CameraCalibration) -> NDArray[np.float64]:
    """:func:`ray_extents` of the calibration's pixel rays, computed once per calibration,
    read-only ((H + W, 2), 20 KB at 1920x1280)."""
    return _EXTENTS.get(cal.key(), lambda: ray_extents(cal, pixel_rays_cam(cal)))


def footprint_pixels(
    cal: CameraCalibration, x_range: tuple[float, float], y_range: tuple[float, float]
) -> tuple[slice, slice] | None:
    """(rows, columns) slices of the image holding every pixel whose ray's normalised
    coordinates (x/z, y/z) may lie in ``x_range`` x ``y_range`` (a superset, from
    :func:`ray_extents_of`); None if no pixel can."""
    extents = ray_extents_of(cal)
    rows, cols = extents[: cal.height], extents[cal.height :]
    row_hit = np.flatnonzero((rows[:, 1] >= y_range[0]) & (rows[:, 0] <= y_range[1]))
    col_hit = np.flatnonzero((cols[:, 1] >= x_range[0]) & (cols[:, 0] <= x_range[1]))
    if row_hit.size == 0 or col_hit.size == 0:
        return None
    return slice(int(row_hit[0]), int(row_hit[-1]) + 1), slice(int(col_hit[0]), int(col_hit[-1]) + 1)


_SMALL: dict[str, _Tables] = {}
_SMALL_LOCK = threading.Lock()


def per_calibration(kind: str, cal: CameraCalibration, compute: Callable[[], T]) -> T:
    """``compute()`` once per calibration for a small table of the given ``kind`` (a stage's
    border rays, image bounds), kept like the others and counted in :data:`COMPUTED` by kind."""
    with _SMALL_LOCK:
        tables = _SMALL.setdefault(kind, _Tables(kind, MAX_CACHED_CAMERAS))
    return tables.get(cal.key(), compute)


def clear() -> None:
    """Drops every cached table (tests; a worker between unrelated runs)."""
    _RAYS.clear()
    _EGO_DEPTH.clear()
    _RAY_COMPONENTS.clear()
    _EXTENTS.clear()
    for tables in _SMALL.values():
        tables.clear()
