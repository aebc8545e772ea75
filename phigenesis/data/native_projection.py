"""ctypes wrappers of the depth projection's C kernels (``csrc/ray_box.c``, ``camera_rays.c``,
``camera_points.c``, ``plane_fits.c``): argument checks, output arrays and the call. The library is
built and loaded by :mod:`phigenesis.data.native`, which hands these classes the loaded library."""

from __future__ import annotations

import ctypes

import numpy as np
from numpy.typing import NDArray


def _address(a: NDArray) -> int:
    """The address of ``a``'s data (ctypes passes an int to a ``c_void_p`` argument as is; cheaper
    than ``data_as``, which builds a ctypes object per call)."""
    return a.__array_interface__["data"][0]


class RayBox:
    """The loaded ``phigenesis_ray_box_far`` (see ``csrc/ray_box.c``)."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr = ctypes.c_int64, ctypes.c_void_p
        self._far = library.phigenesis_ray_box_far
        self._far.argtypes = [ptr, i64, i64, i64, i64, i64, ptr, ptr, ptr]
        self._far.restype = i64
        self._near = library.phigenesis_ray_box_near
        self._near.argtypes = [ptr, i64, ptr, ptr, ptr]
        self._near.restype = i64

    def near_side(
        self,
        rays: NDArray[np.float64],
        box_from_camera: NDArray[np.float64],
        half_size: NDArray[np.float64],
        near: NDArray[np.float32],
    ) -> int:
        """Lowers ``near`` ((N,) or (H, W) float32, C order, modified in place) to the depth at
        which each ray of ``rays`` ((N, 3) float64, C order, z = 1) enters the box (0 from inside),
        where it meets it: :func:`~phigenesis.data.camera_tables.ray_box_depths`'s entry depth,
        rounded to float32. Returns how many rays met the box."""
        n = near.size
        if rays.shape != (n, 3) or rays.dtype != np.float64 or not rays.flags.c_contiguous:
            raise ValueError(f"ray box: rays must be a C-order ({n}, 3) float64 array")
        if near.dtype != np.float32 or not near.flags.c_contiguous or not near.flags.writeable:
            raise ValueError("ray box: near must be a writable C-order float32 array")
        matrix = np.ascontiguousarray(box_from_camera[:3, :4], np.float64)
        half = np.ascontiguousarray(half_size, np.float64)
        if half.shape != (3,):
            raise ValueError(f"ray box: half_size must have 3 values, got {half.shape}")
        return int(self._near(_address(rays), n, _address(matrix), _address(half), _address(near)))

    def far_side(
        self,
        rays: NDArray[np.float64],
        region: tuple[slice, slice],
        box_from_camera: NDArray[np.float64],
        half_size: NDArray[np.float64],
        far: NDArray[np.float32],
    ) -> int:
        """Lowers ``far`` ((H, W) float32, C order, modified in place) to the depth at which each
        ray of ``region`` (rows, columns slices of the image) leaves the box, where it meets it:
        :func:`~phigenesis.data.camera_tables.ray_box_depths`'s exit depth, rounded to float32.
        ``rays``: (H * W, 3) float64 C-order camera-frame rays (z = 1); ``box_from_camera``
        (4, 4); ``half_size`` (3,) metres. Returns how many rays met the box."""
        h, w = far.shape
        if rays.shape != (h * w, 3) or rays.dtype != np.float64 or not rays.flags.c_contiguous:
            raise ValueError(f"ray box: rays must be a C-order ({h * w}, 3) float64 array")
        if far.dtype != np.float32 or not far.flags.c_contiguous or not far.flags.writeable:
            raise ValueError("ray box: far must be a writable C-order float32 array")
        rows, cols = (range(h)[region[0]], range(w)[region[1]])
        if rows.step != 1 or cols.step != 1:
            raise ValueError("ray box: the region's slices must have step 1")
        matrix = np.ascontiguousarray(box_from_camera[:3, :4], np.float64)
        half = np.ascontiguousarray(half_size, np.float64)
        if half.shape != (3,):
            raise ValueError(f"ray box: half_size must have 3 values, got {half.shape}")
        return int(
            self._far(
                _address(rays),
                w,
                rows.start,
                max(rows.stop, rows.start),
                cols.start,
                max(cols.stop, cols.start),
                _address(matrix),
                _address(half),
                _address(far),
            )
        )


class CameraRays:
    """The loaded ``camera_rays.c``: a camera's undistorted pixel rays, their ego-frame unit
    directions and the range view's overlap map, each one pass over the image."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
        self._undistort = library.phigenesis_undistort_grid
        self._undistort.argtypes = [i64, i64, ptr, ptr, f64, ptr, ptr]
        self._undistort.restype = i64
        self._rays_ego = library.phigenesis_rays_ego
        self._rays_ego.argtypes = [ptr, i64, ptr, ptr]
        self._rays_ego.restype = None
        self._overlap = library.phigenesis_overlap
        self._overlap.argtypes = [ptr, i64, i64, i64] + [ptr] * 8
        self._overlap.restype = None
        self._overlap_camera_rays = library.phigenesis_overlap_camera_rays
        self._overlap_camera_rays.argtypes = [ptr, i64, i64, i64] + [ptr] * 8
        self._overlap_camera_rays.restype = None
        self._points = library.phigenesis_undistort_points
        self._points.argtypes = [ptr, i64, ptr, f64, ptr]
        self._points.restype = i64
        self._components = library.phigenesis_ray_components
        self._components.argtypes = [ptr, i64, i64] + [ptr] * 5
        self._components.restype = None
        self._boxes_near = library.phigenesis_ray_boxes_near
        self._boxes_near.argtypes = [ptr, i64, i64, ptr, ptr, ptr]
        self._boxes_near.restype = None

    def boxes_near(
        self,
        rays: NDArray[np.float64],
        box_from_camera: NDArray[np.float64],
        half_sizes: NDArray[np.float64],
        near: NDArray[np.float32],
    ) -> None:
        """Lowers ``near`` ((N,) or (H, W) float32, C order, in place) to the least depth at which
        each ray of ``rays`` ((N, 3) float64, C order, camera frame, z = 1) enters one of B boxes
        (0 from inside), rounded to float32: :meth:`RayBox.near_side` of every box in one pass.
        ``box_from_camera``: (B, 4, 4) transforms; ``half_sizes``: (B, 3) metres."""
        n = near.size
        if rays.shape != (n, 3) or rays.dtype != np.float64 or not rays.flags.c_contiguous:
            raise ValueError(f"camera rays: rays must be a C-order ({n}, 3) float64 array")
        if near.dtype != np.float32 or not near.flags.c_contiguous or not near.flags.writeable:
            raise ValueError("camera rays: near must be a writable C-order float32 array")
        b = len(box_from_camera)
        matrices = np.ascontiguousarray(np.asarray(box_from_camera, np.float64).reshape(b, 4, 4)[:, :3, :4])
        half = np.ascontiguousarray(half_sizes, np.float64)
        if half.shape != (b, 3):
            raise ValueError(f"camera rays: want ({b}, 3) half sizes, got {half.shape}")
        self._boxes_near(_address(rays), n, b, _address(matrices), _address(half), _address(near))

    def undistort_grid(
        self,
        width: int,
        height: int,
        intrinsics: NDArray[np.float64],
        distortion: NDArray[np.float64],
        r_max: float,
        rays: NDArray[np.float64],
    ) -> int:
        """Fills ``rays`` ((H * W, 3) float64, C order, row-major pixels) with the camera-frame ray
        (z = 1) of every pixel centre, distortion undone by Newton's method
        (:func:`~phigenesis.geometry.undistort_normalized`'s step, clamped to ``r_max`` =
        :func:`~phigenesis.geometry.max_monotonic_radius`); ``intrinsics`` (3, 3), ``distortion``
        (5,). Returns how many pixels no undistorted point maps to (they get the reference's last
        iterate: 20 steps from the distorted point)."""
        if rays.shape != (height * width, 3) or rays.dtype != np.float64 or not rays.flags.c_contiguous:
            raise ValueError(f"camera rays: rays must be a C-order ({height * width}, 3) float64 array")
        if not rays.flags.writeable:
            raise ValueError("camera rays: rays must be writeable")
        k = np.ascontiguousarray(intrinsics, np.float64)
        d = np.ascontiguousarray(distortion, np.float64).reshape(-1)
        if k.shape != (3, 3) or d.shape != (5,):
            raise ValueError(
                f"camera rays: want a (3, 3) camera matrix and 5 coefficients, got {k.shape}, {d.shape}"
            )
        scratch = np.empty(6 * width + width // 8 + 1, np.float64)
        return int(
            self._undistort(
                width, height, _address(k), _address(d), float(r_max), _address(rays), _address(scratch)
            )
        )

    def undistort_points(
        self, points: NDArray[np.float64], distortion: NDArray[np.float64], r_max: float
    ) -> NDArray[np.float64]:
        """(N, 2) float64 undistorted normalised coordinates of ``points`` ((N, 2) distorted ones,
        camera frame, z = 1): :func:`~phigenesis.geometry.undistort_normalized` by Newton's
        method (to rounding level where a solution exists, its last iterate where none does),
        ``r_max`` = :func:`~phigenesis.geometry.max_monotonic_radius` of ``distortion`` (5,)."""
        xy = np.ascontiguousarray(points, np.float64)
        d = np.ascontiguousarray(distortion, np.float64).reshape(-1)
        if xy.ndim != 2 or xy.shape[1] != 2 or d.shape != (5,):
            raise ValueError(f"camera rays: want (N, 2) points and 5 coefficients, got {xy.shape}, {d.shape}")
        out = np.empty_like(xy)
        self._points(_address(xy), len(xy), _address(d), float(r_max), _address(out))
        return out

    def ray_components(
        self, rays: NDArray[np.float64], width: int, height: int
    ) -> tuple[
        NDArray[np.float32],
        NDArray[np.float32],
        NDArray[np.float32],
        NDArray[np.float64],
        NDArray[np.float64],
    ]:
        """From (H * W, 3) float64 C-order rays (camera frame, z = 1, row-major pixels): the
        (H, W) float32 planes x, y and ``sqrt(x^2 + y^2 + 1)``, each column's least and greatest
        x ((2, W) float64) and each row's least and greatest y ((2, H)), in one pass."""
        if rays.shape != (height * width, 3) or rays.dtype != np.float64 or not rays.flags.c_contiguous:
            raise ValueError(f"camera rays: rays must be a C-order ({height * width}, 3) float64 array")
        planes = [np.empty((height, width), np.float32) for _ in range(3)]
        column_x, row_y = np.empty((2, width)), np.empty((2, height))
        outputs = (*planes, column_x, row_y)
        self._components(_address(rays), width, height, *(_address(a) for a in outputs))
        return planes[0], planes[1], planes[2], column_x, row_y

    def rays_ego(self, rays: NDArray[np.float64], rotation: NDArray[np.float64]) -> NDArray[np.float32]:
        """(N, 3) float32 unit directions, ego axes, of ``rays`` ((N, 3) float64 camera frame):
        ``rotation`` (3, 3, ego_from_camera) applied, divided by the length, rounded."""
        n = len(rays)
        if rays.shape != (n, 3) or rays.dtype != np.float64 or not rays.flags.c_contiguous:
            raise ValueError("camera rays: rays must be a C-order (N, 3) float64 array")
        r = np.ascontiguousarray(rotation, np.float64)
        if r.shape != (3, 3):
            raise ValueError(f"camera rays: rotation must be (3, 3), got {r.shape}")
        out = np.empty((n, 3), np.float32)
        self._rays_ego(_address(rays), n, _address(r), _address(out))
        return out

    def overlap(
        self,
        rays: NDArray[np.float32] | NDArray[np.float64],
        view: int,
        rotations: NDArray[np.float64],
        intrinsics: NDArray[np.float64],
        distortions: NDArray[np.float64],
        r_max2: NDArray[np.float64],
        sizes: NDArray[np.int64],
        azimuth: NDArray[np.float64],
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """Owner and coverage ((N,) uint8) of view ``view``'s rays among V views: ``rays`` (N, 3)
        float32 unit directions in ego axes, or the view's (N, 3) float64 camera-frame rays
        (z = 1), turned into those on the way (:meth:`rays_ego`'s arithmetic, without an (N, 3)
        array of them); ``rotations`` (V, 3, 3) ego_from_camera,
        ``intrinsics`` (V, 3, 3), ``distortions`` (V, 5), ``r_max2`` (V,) squared monotonic radius
        (inf where a view has no distortion), ``sizes`` (V, 2) int64 width and height,
        ``azimuth`` (V, 2) middle and half-width (radians) of the azimuth range a ray must be in
        to be tested against the view."""
        n, v = len(rays), len(rotations)
        if rays.shape != (n, 3) or rays.dtype not in (np.float32, np.float64) or not rays.flags.c_contiguous:
            raise ValueError("camera rays: overlap rays must be a C-order (N, 3) float32 or float64 array")
        if not 0 <= view < v or v > 255:
            raise ValueError(f"camera rays: view {view} of {v} views")
        checks = [
            (rotations, np.float64, (v, 3, 3)),
            (intrinsics, np.float64, (v, 3, 3)),
            (distortions, np.float64, (v, 5)),
            (r_max2, np.float64, (v,)),
            (sizes, np.int64, (v, 2)),
            (azimuth, np.float64, (v, 2)),
        ]
        for a, dtype, shape in checks:
            if a.dtype != dtype or a.shape != shape or not a.flags.c_contiguous:
                raise ValueError(f"camera rays: expected a C-order {np.dtype(dtype)} array of shape {shape}")
        owner = np.empty(n, np.uint8)
        count = np.empty(n, np.uint8)
        kernel = self._overlap if rays.dtype == np.float32 else self._overlap_camera_rays
        kernel(
            _address(rays), n, view, v, *(_address(a) for a, _, _ in checks), _address(owner), _address(count)
        )
        return owner, count


class CameraPointsKernel:
    """The loaded ``phigenesis_camera_points`` (see ``csrc/camera_points.c``)."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr, f32, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_float, ctypes.c_double
        self._run = library.phigenesis_camera_points
        self._run.argtypes = [i64, ptr, ptr, ptr, f32, f32, ptr, f64, f64, ptr, i64, ptr, i64, i64]
        self._run.argtypes += [ptr, ptr, f32, i64, f32, f32, ptr, ptr, ptr, ptr, ptr]
        self._run.restype = i64

    def __call__(
        self,
        points_world: NDArray[np.float32],
        world_from_camera: NDArray[np.float64],
        intrinsics: NDArray[np.float64],
        distortion: NDArray[np.float64],
        max_radius2: float,
        size_wh: tuple[int, int],
        depth_range_m: tuple[float, float],
        bounds: tuple[tuple[float, float], tuple[float, float]],
        ego_depth: NDArray[np.float32] | None,
        occluder_far: NDArray[np.float32] | None,
        slack_m: float,
        max_per_pixel: int = 0,
        band: tuple[float, float] = (1.0, 0.0),
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float32], NDArray[np.int64], list[int]]:
        """The points of ``points_world`` ((N, 3) float32 C order, world frame) that land in the
        image and lie in front of the ego body and the vehicles: their indices (K,) int64, pixel
        positions (K, 2) float64 (u along the width), camera z (K,) float32 metres and flat pixel
        indices (K,) int64, and the counts [projected, behind the ego body, behind vehicles,
        thinned].

        ``world_from_camera`` (4, 4); ``intrinsics`` (3, 3); ``distortion`` (5,) OpenCV k1, k2, p1,
        p2, k3 and ``max_radius2`` its monotonic radius squared (normalised units);
        ``size_wh`` the image's (W, H); ``depth_range_m`` (min z, max range); ``bounds`` the
        normalised view bounds ((x0, x1), (y0, y1)); ``ego_depth`` and ``occluder_far`` (H, W)
        float32 maps or None; ``slack_m`` added to ``occluder_far``; ``max_per_pixel`` (0: off)
        and ``band`` (scale, slack in metres) the per-pixel thinning, whose drops are the fourth
        count. See ``csrc/camera_points.c``."""
        w, h = size_wh
        n = len(points_world)
        if points_world.shape != (n, 3) or points_world.dtype != np.float32:
            raise ValueError(f"camera points: points must be (N, 3) float32, got {points_world.shape}")
        if not points_world.flags.c_contiguous:
            raise ValueError("camera points: points must be a C-order array")
        for name, m in (("ego_depth", ego_depth), ("occluder_far", occluder_far)):
            if m is not None and (m.shape != (h, w) or m.dtype != np.float32 or not m.flags.c_contiguous):
                raise ValueError(f"camera points: {name} must be a C-order ({h}, {w}) float32 array")
        centre = np.ascontiguousarray(world_from_camera[:3, 3], np.float32)
        rotation = np.ascontiguousarray(world_from_camera[:3, :3], np.float32)
        bounds_f = np.array([*bounds[0], *bounds[1]], np.float32)
        dist = np.ascontiguousarray(distortion, np.float64).reshape(5)
        k = np.asarray(intrinsics, np.float64)[[0, 0, 0, 1, 1], [0, 1, 2, 1, 2]].copy()
        index = np.empty(n, np.int64)
        uv = np.empty((n, 2), np.float64)
        z = np.empty(n, np.float32)
        pixel = np.empty(n, np.int64)
        counts = np.zeros(4, np.int64)
        min_depth, max_range = depth_range_m
        kept = self._run(
            n,
            _address(points_world),
            _address(centre),
            _address(rotation),
            min_depth,
            max_range**2,
            _address(bounds_f),
            min_depth,
            max_radius2,
            _address(dist),
            int(bool(np.any(dist != 0.0))),
            _address(k),
            w,
            h,
            None if ego_depth is None else _address(ego_depth),
            None if occluder_far is None else _address(occluder_far),
            slack_m,
            max_per_pixel,
            band[0],
            band[1],
            _address(index),
            _address(uv),
            _address(z),
            _address(pixel),
            _address(counts),
        )
        if kept < 0:
            raise MemoryError("camera points: no memory for the per-pixel thinning")
        return index[:kept], uv[:kept], z[:kept], pixel[:kept], [int(c) for c in counts]


class PlaneFits:
    """The loaded ``phigenesis_plane_fits`` (see ``csrc/plane_fits.c``)."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
        self._run = library.phigenesis_plane_fits
        self._run.argtypes = [
            i64,
            ptr,
            ptr,
            ptr,
            i64,
            i64,
            ptr,
            i64,
            f64,
            f64,
            i64,
            f64,
            f64,
            ptr,
            ptr,
            ptr,
            ptr,
        ]
        self._run.restype = i64

    def __call__(
        self,
        pixel: NDArray[np.int64],
        uv: NDArray[np.float64],
        z: NDArray[np.float32],
        shape: tuple[int, int],
        reference_m: NDArray[np.float32],
        min_points: int,
        fit_tolerance: tuple[float, float],
        window_px: int,
        window_tolerance: tuple[float, float],
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_]]:
        """Plane fits of the occupied pixels of an (H, W) ``shape`` image: their sorted flat
        indices (K,) int64, depth at the centre (K,) float64 (NaN: none), point count (K,) int64
        and mixed flag (K,) bool. ``pixel`` (N,) int64 flat pixel of each point, ``uv`` (N, 2)
        float64 its position, ``z`` (N,) float32 its depth (m); ``reference_m`` (H * W,) float32
        the depth of the point nearest each centre; ``fit_tolerance`` and ``window_tolerance``
        (metres, relative). See ``csrc/plane_fits.c``."""
        h, w = shape
        n = len(pixel)
        pixel = np.ascontiguousarray(pixel, np.int64)
        uv = np.ascontiguousarray(uv, np.float64)
        z = np.ascontiguousarray(z, np.float32)
        reference = np.ascontiguousarray(reference_m, np.float32).reshape(-1)
        if uv.shape != (n, 2) or z.shape != (n,) or reference.shape != (h * w,):
            raise ValueError(f"plane fits: shapes {pixel.shape}, {uv.shape}, {z.shape}, {reference.shape}")
        if n and (pixel.min() < 0 or pixel.max() >= h * w):
            raise ValueError(f"plane fits: a pixel index lies outside the {h} x {w} image")
        capacity = min(n, h * w)
        occupied = np.empty(capacity, np.int64)
        depth = np.empty(capacity, np.float64)
        count = np.empty(capacity, np.int64)
        mixed = np.empty(capacity, np.uint8)
        k = self._run(
            n,
            _address(pixel),
            _address(uv),
            _address(z),
            h,
            w,
            _address(reference),
            min_points,
            *fit_tolerance,
            window_px,
            *window_tolerance,
            *(_address(a) for a in (occupied, depth, count, mixed)),
        )
        if k < 0:
            raise MemoryError("plane fits: no memory for the pixel map")
        return occupied[:k], depth[:k], count[:k], mixed[:k].astype(bool)
