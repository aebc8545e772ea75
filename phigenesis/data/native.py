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

from phigenesis.data.native_projection import (
    CameraPointsKernel,
    CameraRays,
    PlaneFits,
    RayBox,
    _address,
)
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
