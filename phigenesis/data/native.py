"""The data pipeline's C kernels (``csrc/*.c``), compiled on first use into one library: the Waymo
reader's range-image kernel (``range_points.c``), the shard writer's CRC-32C combination
(``crc32c_combine.c``), the pseudo labels' box rule (``box_labels.c``), depth completion's
fine pass (``complete_fine.c``), the densifier's last pass (``densify_finish.c``: support,
confidence and clean-up in one pass), the depth projection's ray-box test (``ray_box.c``: the far
side of a moving vehicle along each ray of its footprint, one pass instead of numpy's fifteen), its
first pass over the map points (``camera_points.c``: transform, cull, distort, project and test
against the ego body and vehicles in one pass) and its per-pixel plane fits (``plane_fits.c``), and
a camera's per-calibration tables (``camera_rays.c``: undistorted pixel rays, their ego-frame
directions and the range view's overlap map), and scene flow's pass over a moving box's pixels
(``scene_flow.c``).

Entry points: :func:`load_range_points`, :func:`load_crc32c_combine`, :func:`load_box_labels`,
:func:`load_complete_fine`, :func:`load_ray_box`, :func:`load_camera_rays`,
:func:`load_densify_finish`, :func:`load_camera_points`, :func:`load_plane_fits`,
:func:`load_scene_flow_pixels`.

Turning a Waymo frame's range images into points in numpy takes a mask, a gather per channel, the
ray arithmetic and the concatenation, each its own pass over every return. The kernel does it in one
pass over each image, writing every field of its returns (docs/design/waymo.md, "Range images to
points in one C pass"). It is plain C, built with the system C compiler (``cc``, or ``$CC``) into
the native cache folder (:mod:`phigenesis.native_cache`) and loaded with ctypes, so
reading data never needs torch. When it cannot be built (no compiler, a read-only cache) the reason
is one warning line, :func:`load_range_points` returns ``None`` and the reader uses its numpy path,
which the tests hold the kernel against; the shard writer reads its rows a second time to checksum
the whole file. ``PHIGENESIS_NATIVE=0`` skips them.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import sys
import threading
import uuid
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from phigenesis.native_cache import cache_root, cpu_flags, native_enabled

logger = logging.getLogger(__name__)

SOURCES = (
    Path(__file__).parent / "csrc" / "range_points.c",
    Path(__file__).parent / "csrc" / "crc32c_combine.c",
    Path(__file__).parent / "csrc" / "box_labels.c",
    Path(__file__).parent / "csrc" / "complete_fine.c",
    Path(__file__).parent / "csrc" / "ray_box.c",
    Path(__file__).parent / "csrc" / "camera_rays.c",
    Path(__file__).parent / "csrc" / "densify_finish.c",
    Path(__file__).parent / "csrc" / "camera_points.c",
    Path(__file__).parent / "csrc" / "plane_fits.c",
    Path(__file__).parent / "csrc" / "scene_flow.c",
)
LIBRARY_NAME = "libphigenesis_data"
CFLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fPIC", "-shared", "-std=c99")

#: The arrays :meth:`RangePoints.gather` writes: name -> (dtype, shape of one return's value).
OUTPUT_FIELDS: dict[str, tuple[type, tuple[int, ...]]] = {
    "points": (np.float32, (3,)),
    "origins": (np.float32, (3,)),
    "intensity": (np.float32, ()),
    "elongation": (np.float32, ()),
    "beam": (np.uint16, ()),
    "time_offset": (np.int32, ()),
}

_lock = threading.Lock()
_library: _Kernels | None = None
_failure: str | None = None


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def build_directory() -> Path:
    """Where this machine's build of the current sources lives (hash of sources, flags, CPU)."""
    digest = hashlib.sha256()
    for source in SOURCES:
        digest.update(source.read_bytes())
    digest.update(f"{CFLAGS} {sys.platform} {cpu_flags()}".encode())
    return cache_root() / f"data_kernels-{digest.hexdigest()[:16]}"


def _address(a: NDArray) -> int:
    """The address of ``a``'s data (ctypes passes an int to a ``c_void_p`` argument as is; cheaper
    than ``data_as``, which builds a ctypes object per call)."""
    return a.__array_interface__["data"][0]


class RangePoints:
    """The loaded kernel: :meth:`gather` (see ``csrc/range_points.c``)."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr = ctypes.c_int64, ctypes.c_void_p
        self._gather = library.phigenesis_gather_returns
        self._gather.argtypes = [ptr, i64, i64, i64] + [ptr] * 12 + [i64]
        self._gather.restype = i64

    def gather(
        self,
        image: NDArray[np.float32],
        cos_incl: NDArray[np.float32],
        sin_incl: NDArray[np.float32],
        along: NDArray[np.float32],
        up: NDArray[np.float32],
        origin: NDArray[np.float32],
        time_offsets: NDArray[np.int32],
    ) -> dict[str, NDArray]:
        """The returns of the float32 (H, W, C) C-order range image, in one pass, row by row: a
        dict of :data:`OUTPUT_FIELDS` (``points``, ``origins`` (N, 3) float32; ``intensity``,
        ``elongation`` float32; ``beam`` uint16; ``time_offset`` int32).

        ``cos_incl``, ``sin_incl`` (H,), ``along``, ``up``, ``origin`` (3, W) float32 and
        ``time_offsets`` (W,) int32, all C order: the ray geometry (``convert._RayGeometry``).

        The arrays are views of the first N rows of arrays of H * W rows (a pixel holds at most
        one return): one pass over the image instead of a count, then a gather, each of which read
        all of it. They are meant to be copied into the sweep."""
        h, w, c = image.shape
        if (cos_incl.shape, sin_incl.shape, time_offsets.shape) != ((h,), (h,), (w,)) or any(
            a.shape != (3, w) for a in (along, up, origin)
        ):
            raise ValueError(f"range points: ray geometry does not fit a {h} x {w} range image")
        inputs = [image, cos_incl, sin_incl, along, up, origin]
        if any(a.dtype != np.float32 or not a.flags.c_contiguous for a in inputs):
            raise ValueError("range points: inputs must be C-order float32 arrays")
        if time_offsets.dtype != np.int32 or not time_offsets.flags.c_contiguous:
            raise ValueError("range points: time offsets must be a C-order int32 array")
        capacity = h * w
        out = {name: np.empty((capacity, *shape), dtype) for name, (dtype, shape) in OUTPUT_FIELDS.items()}
        written = self._gather(
            _address(image),
            h,
            w,
            c,
            *(_address(a) for a in inputs[1:]),
            _address(time_offsets),
            *(_address(a) for a in out.values()),
            capacity,
        )
        if written < 0:  # cannot happen: one return per pixel at most
            raise RuntimeError("range points: the kernel wrote past its outputs")
        return {name: a[:written] for name, a in out.items()}


def _build(build_dir: Path) -> Path:
    """Compiles the kernels into ``build_dir`` (atomically: a temporary name, then a rename)."""
    library = build_dir / f"{LIBRARY_NAME}.so"
    if library.is_file():
        return library
    compiler = _compiler()
    if compiler is None:
        raise OSError("no C compiler (cc, gcc or clang) on PATH")
    build_dir.mkdir(parents=True, exist_ok=True)
    tmp = build_dir / f".{LIBRARY_NAME}-{uuid.uuid4().hex[:8]}.so"
    try:
        result = subprocess.run(
            [compiler, *CFLAGS, *map(str, SOURCES), "-o", str(tmp)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        if result.returncode != 0:
            lines = [line for line in result.stderr.splitlines() if "error" in line.lower()]
            raise OSError(f"{compiler} failed: {(lines or result.stderr.splitlines() or ['?'])[0][:300]}")
        os.replace(tmp, library)
    finally:
        tmp.unlink(missing_ok=True)
    return library


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


class _Kernels(NamedTuple):
    range_points: RangePoints
    crc32c_combine: Crc32cCombine
    box_labels: BoxLabels
    complete_fine: CompleteFine
    ray_box: RayBox
    camera_rays: CameraRays
    densify_finish: DensifyFinish
    camera_points: CameraPointsKernel
    plane_fits: PlaneFits
    scene_flow_pixels: SceneFlowPixels


def _load_library() -> _Kernels | None:
    """The compiled library's kernels, built on first call, or ``None`` if it cannot be built here; the
    reason is logged once and kept in :func:`failure_reason`."""
    global _library, _failure
    with _lock:
        if _library is not None or _failure is not None:
            return _library
        if not native_enabled():
            _failure = "disabled by PHIGENESIS_NATIVE=0"
            return None
        try:
            library = ctypes.CDLL(str(_build(build_directory())))
            _library = _Kernels(
                RangePoints(library),
                Crc32cCombine(library),
                BoxLabels(library),
                CompleteFine(library),
                RayBox(library),
                CameraRays(library),
                DensifyFinish(library),
                CameraPointsKernel(library),
                PlaneFits(library),
                SceneFlowPixels(library),
            )
        except (OSError, subprocess.SubprocessError, AttributeError) as error:
            _failure = str(error).splitlines()[0][:300] if str(error) else type(error).__name__
            logger.warning(
                "native data kernels not available: %s; converting range images and testing rays "
                "against boxes with numpy, and checksumming shard rows twice",
                _failure,
            )
        return _library


def load_range_points() -> RangePoints | None:
    """The range-image kernel, or ``None`` where the library cannot be built (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.range_points


class Crc32cCombine:
    """The loaded ``phigenesis_crc32c_combine`` (see ``csrc/crc32c_combine.c``)."""

    def __init__(self, library: ctypes.CDLL):
        self._combine = library.phigenesis_crc32c_combine
        self._combine.argtypes = [ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint64]
        self._combine.restype = ctypes.c_uint32

    def __call__(self, crc_a: int, crc_b: int, length_b: int) -> int:
        """The CRC-32C of bytes A then B from ``crc_a`` = CRC-32C(A), ``crc_b`` = CRC-32C(B) and
        B's length in bytes, in time independent of the lengths."""
        if length_b < 0:
            raise ValueError(f"crc32c combine: negative length {length_b}")
        return int(self._combine(crc_a, crc_b, length_b))


def load_crc32c_combine() -> Crc32cCombine | None:
    """The CRC-32C combination, or ``None`` where the library cannot be built (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.crc32c_combine


class BoxLabels:
    """The loaded ``phigenesis_box_labels`` (see ``csrc/box_labels.c``): the pseudo labels' box
    rule over one box's rectangle of pixels."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
        self._labels = library.phigenesis_box_labels
        self._labels.argtypes = [ptr, ptr, i64, i64, i64, i64, i64, f64, f64] + [ptr] * 5 + [i64, ptr, ptr]
        self._labels.restype = i64

    def __call__(
        self,
        depth: NDArray[np.float32],
        rays: NDArray[np.float64],
        rect: tuple[int, int, int, int],
        z_range: tuple[float, float],
        world_from_camera: NDArray[np.float64],
        center: NDArray[np.float64],
        world_from_box: NDArray[np.float64],
        limits: NDArray[np.float64],
        cls: int,
        labels: NDArray[np.uint8],
        best: NDArray[np.float64],
    ) -> int:
        """Labels the pixels of ``rect`` = (v0, v1, u0, u1) of the (H, W) float32 z-depth
        ``depth`` (metres) whose point lies in the box (centre ``center``, rotation
        ``world_from_box`` (3, 3), world frame; ``limits``: the box-frame bounds |x| <= l0,
        |y| <= l1, l3 <= z <= l2) and is nearer its centre than ``best`` (both (H * W,), updated
        in place with ``labels``); only depths in ``z_range`` are tested. ``rays``: (H * W, 3)
        camera-frame rays, z = 1. Returns how many pixels lie in the box."""
        h, w = depth.shape
        v0, v1, u0, u1 = rect
        if not (0 <= v0 <= v1 <= h and 0 <= u0 <= u1 <= w):
            raise ValueError(f"box labels: rectangle {rect} outside a {h} x {w} image")
        if rays.shape != (h * w, 3) or labels.shape != (h * w,) or best.shape != (h * w,):
            raise ValueError("box labels: rays, labels and best must cover the image")
        arrays = (depth, rays, labels, best)
        dtypes = (np.float32, np.float64, np.uint8, np.float64)
        if any(a.dtype != dt or not a.flags.c_contiguous for a, dt in zip(arrays, dtypes, strict=True)):
            raise ValueError(
                "box labels: depth, rays, labels and best must be C-order float32, float64, uint8, float64"
            )
        if not (labels.flags.writeable and best.flags.writeable):
            raise ValueError("box labels: labels and best must be writeable")
        small = [
            np.ascontiguousarray(a, np.float64)
            for a in (world_from_camera[:3, :3], world_from_camera[:3, 3], center, world_from_box, limits)
        ]
        return int(
            self._labels(
                _address(depth),
                _address(rays),
                w,
                v0,
                v1,
                u0,
                u1,
                float(z_range[0]),
                float(z_range[1]),
                *(_address(a) for a in small),
                int(cls),
                _address(labels),
                _address(best),
            )
        )


class SceneFlowPixels:
    """The loaded ``phigenesis_scene_flow_pixels`` (see ``csrc/scene_flow.c``): scene flow's pass over
    one moving box's rectangle."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
        self._pass = library.phigenesis_scene_flow_pixels
        self._pass.argtypes = (
            [ptr, ptr, i64, i64, i64, i64, i64, f64, f64] + [ptr] * 5 + [f64, ctypes.c_float]
        )
        self._pass.argtypes += [ptr] * 4
        self._pass.restype = i64

    def __call__(
        self,
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
        """Writes (in place) ``best``, ``flow``, ``dynamic``, ``confidence`` of the pixels of
        ``rect`` = (v0, v1, u0, u1) that take the box (``csrc/scene_flow.c``); returns how many.
        ``depth`` (H, W) float32 and ``rays`` (H * W, 3) float64 (z = 1) C order; ``best``,
        ``dynamic`` (bool), ``confidence`` (H, W) and ``flow`` (H, W, 3) float32, C order."""
        h, w = depth.shape
        v0, v1, u0, u1 = (int(x) for x in rect)
        if not (0 <= v0 <= v1 <= h and 0 <= u0 <= u1 <= w):
            raise ValueError(f"scene flow pixels: rectangle {rect} outside a {w}x{h} image")
        checks = (
            (depth, np.float32, (h, w)),
            (rays, np.float64, (h * w, 3)),
            (best, np.float32, (h, w)),
            (flow, np.float32, (h, w, 3)),
            (dynamic, np.bool_, (h, w)),
            (confidence, np.float32, (h, w)),
        )
        for a, dtype, shape in checks:
            if a.dtype != dtype or a.shape != shape or not a.flags.c_contiguous:
                raise ValueError(
                    f"scene flow pixels: expected C-order {np.dtype(dtype).name} {shape}, "
                    f"got {a.dtype} {a.shape}"
                )
        small = [
            np.ascontiguousarray(x, np.float64).reshape(-1)
            for x in (center_cam, camera_from_box, limits, world_rotation_xy, velocity)
        ]
        if [len(x) for x in small] != [3, 9, 4, 6, 3]:
            raise ValueError(
                "scene flow pixels: box centre (3), rotation (3x3), limits (4), rows (2x3), velocity (3)"
            )
        return int(
            self._pass(
                _address(depth), _address(rays), w, v0, v1, u0, u1, float(z_range[0]), float(z_range[1]),
                *(_address(x) for x in small), float(yaw_rate_radps), float(box_confidence),
                _address(best), _address(flow), _address(dynamic), _address(confidence),
            )
        )  # fmt: skip


def load_scene_flow_pixels() -> SceneFlowPixels | None:
    """Scene flow's pixel pass, or ``None`` where the library cannot be built (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.scene_flow_pixels


def load_box_labels() -> BoxLabels | None:
    """The box rule's kernel, or ``None`` where the library cannot be built (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.box_labels


class CompleteFine:
    """The loaded ``phigenesis_complete_fine`` (see ``csrc/complete_fine.c``): depth completion's
    fine pass over a large image from its coarse grid's planes."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
        self._fine = library.phigenesis_complete_fine
        self._fine.argtypes = [i64, i64, i64] + [ptr] * 8 + [i64, f64, f64, f64] + [ptr] * 3
        self._fine.restype = i64

    def __call__(
        self,
        ry: NDArray[np.int64],
        rx: NDArray[np.int64],
        fillable: NDArray[np.bool_],
        rays: NDArray[np.float64],
        normal_small: NDArray[np.float32],
        offset_small: NDArray[np.float32],
        conf_small: NDArray[np.float32],
        origin_small: NDArray[np.uint8],
        grid_width: int,
        min_code: int,
        depth_range: tuple[float, float],
        sin_min: float,
        depth: NDArray[np.float32],
        conf: NDArray[np.float32],
        origin: NDArray[np.uint8],
    ) -> int:
        """Fills (in place) ``depth``, ``conf``, ``origin`` (H, W) at every ``fillable`` pixel
        whose grid cell (``ry`` (H,), ``rx`` (W,) int64 cell row and column of each image row and
        column; ``grid_width`` = W2) has an origin of at least ``min_code``: the cell's plane
        (``normal_small`` (H2 * W2, 3), ``offset_small`` (H2 * W2,)) met by the pixel's ray
        (``rays`` (H * W, 3), z = 1), where the depth is in ``depth_range`` =
        (exclusive, inclusive) metres and the sine of the incidence at least ``sin_min``. Returns
        how many it filled."""
        h, w = depth.shape
        cells = len(origin_small)
        w2 = grid_width
        if w2 < 1 or cells % w2 or (h and not 0 <= ry.min() <= ry.max() < cells // w2):
            raise ValueError("complete fine: ry outside the coarse grid")
        if w and not 0 <= rx.min() <= rx.max() < w2:
            raise ValueError("complete fine: rx outside the coarse grid")
        checks = [
            (ry, np.int64, (h,)),
            (rx, np.int64, (w,)),
            (fillable, np.bool_, (h, w)),
            (rays, np.float64, (h * w, 3)),
            (normal_small, np.float32, (cells, 3)),
            (offset_small, np.float32, (cells,)),
            (conf_small, np.float32, (cells,)),
            (origin_small, np.uint8, (cells,)),
            (depth, np.float32, (h, w)),
            (conf, np.float32, (h, w)),
            (origin, np.uint8, (h, w)),
        ]
        for a, dtype, shape in checks:
            if a.dtype != dtype or a.shape != shape or not a.flags.c_contiguous:
                raise ValueError(
                    f"complete fine: expected a C-order {np.dtype(dtype)} array of shape {shape}"
                )
        if not all(a.flags.writeable for a in (depth, conf, origin)):
            raise ValueError("complete fine: depth, conf and origin must be writeable")
        return int(
            self._fine(
                h,
                w,
                w2,
                *(_address(a) for a, _, _ in checks[:8]),
                int(min_code),
                float(depth_range[0]),
                float(depth_range[1]),
                float(sin_min),
                *(_address(a) for a in (depth, conf, origin)),
            )
        )


def load_complete_fine() -> CompleteFine | None:
    """Depth completion's fine-pass kernel, or ``None`` where the library cannot be built
    (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.complete_fine


class DensifyFinish:
    """The loaded ``phigenesis_densify_finish`` (see ``csrc/densify_finish.c``): the densifier's
    support mask, confidence and clean-up in one pass over the image."""

    def __init__(self, library: ctypes.CDLL):
        i64, ptr, f32 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_float
        self._finish = library.phigenesis_densify_finish
        self._finish.argtypes = [i64] + [ptr] * 7 + [f32, f32] + [ptr] * 2
        self._finish.restype = None

    def __call__(
        self,
        dense: NDArray[np.float32],
        support: NDArray[np.bool_],
        sparse: NDArray[np.float32],
        conf: NDArray[np.float32],
        labels: NDArray[np.int32],
        lut: NDArray[np.int32],
        dist: NDArray[np.float32],
        distance_scale_px: float,
        relative_depth_scale: float,
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(depth, confidence), both (H, W) float32: ``dense`` (H, W) metres where ``support`` and
        positive, else 0, and its confidence (``densify.depth_confidence``, clipped to [0, 1]) from
        ``sparse`` / ``conf`` (H, W), the nearest trusted pixel ``lut[labels]`` (``labels`` (H, W)
        int32 of OpenCV's distance transform, ``lut`` int32 flat pixel index per label) at
        ``dist`` (H, W) pixels, ``d0`` = ``distance_scale_px``, ``rel0`` = ``relative_depth_scale``."""
        shape = dense.shape
        checks = [
            (dense, np.float32, shape),
            (support, np.bool_, shape),
            (sparse, np.float32, shape),
            (conf, np.float32, shape),
            (labels, np.int32, shape),
            (lut, np.int32, lut.shape),
            (dist, np.float32, shape),
        ]
        for a, dtype, want in checks:
            if a.dtype != dtype or a.shape != want or not a.flags.c_contiguous:
                raise ValueError(
                    f"densify finish: expected a C-order {np.dtype(dtype)} array of shape {want}"
                )
        size = dense.size
        if size and (
            int(labels.min()) < 0 or int(labels.max()) >= len(lut) or not 0 <= lut.min() <= lut.max() < size
        ):
            raise ValueError("densify finish: labels or lut out of range")
        depth, confidence = np.empty(shape, np.float32), np.empty(shape, np.float32)
        self._finish(
            size,
            *(_address(a) for a, _, _ in checks),
            np.float32(-1.0 / distance_scale_px),
            np.float32(relative_depth_scale),
            _address(depth),
            _address(confidence),
        )
        return depth, confidence


def load_densify_finish() -> DensifyFinish | None:
    """The densifier's last-pass kernel, or ``None`` where the library cannot be built
    (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.densify_finish


def load_ray_box() -> RayBox | None:
    """The ray-box kernel, or ``None`` where the library cannot be built (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.ray_box


def load_camera_rays() -> CameraRays | None:
    """The camera-table kernels, or ``None`` where the library cannot be built (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.camera_rays


def load_camera_points() -> CameraPointsKernel | None:
    """The projection's first-pass kernel, or ``None`` where the library cannot be built
    (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.camera_points


def load_plane_fits() -> PlaneFits | None:
    """The projection's plane-fit kernel, or ``None`` where the library cannot be built
    (:func:`_load_library`)."""
    kernels = _load_library()
    return None if kernels is None else kernels.plane_fits


def failure_reason() -> str | None:
    """Why the kernels are not available (after a loader returned ``None``)."""
    return _failure


__all__ = [
    "BoxLabels",
    "CameraPointsKernel",
    "CameraRays",
    "CompleteFine",
    "Crc32cCombine",
    "DensifyFinish",
    "PlaneFits",
    "RangePoints",
    "RayBox",
    "build_directory",
    "failure_reason",
    "load_box_labels",
    "load_camera_points",
    "load_camera_rays",
    "load_complete_fine",
    "load_crc32c_combine",
    "load_densify_finish",
    "load_plane_fits",
    "load_range_points",
    "load_ray_box",
    "load_scene_flow_pixels",
]
