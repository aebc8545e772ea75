"""Camera range view: all camera views of a frame side by side in azimuth order, at their native pixels.

Entry points: :func:`range_view_layout` (where each view goes, and the overlap map) and
:func:`pack_range_view` (a frame's RGB, depth, semantics and rays as one image each);
:meth:`RangeViewLayout.pack` / :meth:`RangeViewLayout.unpack` move any per-view plane in and out.

Layout rule (also in docs/design/rangeview.md):

- **Order.** Views go left to right by the azimuth of their optical axis in the ego frame, decreasing
  (as seen from the driver's seat: left side, front, right side), the panorama cut at the rear
  (azimuth ``-pi``, where a 360-degree rig's rear camera lands at the right end). Equal azimuths keep
  the frame's camera order.
- **Placement.** A view keeps its native pixels: its pixel ``(v, u)`` is the cell
  ``(row0 + v, col0 + u)``. ``col0`` is the sum of the widths of the views before it (no gap
  columns: a gap between fields of view shows in the views' azimuth ranges, not as empty columns).
  With ``align="horizon"`` (default) ``row0`` lines up the views' horizons (the row where the
  horizontal ray at the view's axis azimuth lands), so views of different heights (Waymo's side
  cameras) stay level; the smallest ``row0`` is 0. ``align="top"`` puts every view at row 0. The
  range view is ``max(row0 + height)`` by ``sum(width)`` cells; cells no view covers are empty
  (view index 255, not valid).
- **Overlap.** Every cell keeps its own view's pixel: nothing is resampled or dropped, so unpacking
  returns each view exactly. Where fields of view overlap, ``owner`` names the view that owns the
  cell's viewing direction (among the views whose image contains it, the one whose optical axis is
  nearest in angle; ties go to the lower index) and ``coverage`` counts the views that see it.
  Cells whose owner is their own view form a panorama with each direction once. Directions are
  compared from each camera's own centre (exact at infinity; a 0.5 m baseline shifts a surface 10 m
  away by about 3 degrees).

Arrays: a range view of ``H x W`` cells; planes are ``(H, W, ...)`` with the per-view trailing
shape; ``view_index`` and ``owner`` index :attr:`RangeViewLayout.views` (range-view order, not
the frame's camera order).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.camera_tables import pixel_rays_cam
from phigenesis.data.camera_tables import undistorted_pixel_rays as undistorted_pixel_rays  # re-exported
from phigenesis.data.native import load_camera_rays
from phigenesis.data.range_records import NO_VIEW, RangeViewLayout, ViewPlacement
from phigenesis.data.records import CameraCalibration, CameraImage, Frame

__all__ = ["NO_VIEW", "RangeViewLayout", "ViewPlacement"]

Align = Literal["horizon", "top"]
DepthSource = Literal["dense", "sparse", "truth"]
SemanticSource = Literal["pseudo", "truth", "labels"]
#: Depth sources tried in order by default: densified, then projected LiDAR.
DEFAULT_DEPTH_SOURCES: tuple[DepthSource, ...] = ("dense", "sparse")
#: Semantic sources tried in order by default: pseudo-labels, exact truth, human labels.
DEFAULT_SEMANTIC_SOURCES: tuple[SemanticSource, ...] = ("pseudo", "truth", "labels")


# --------------------------------------------------------------------------------------------
# Rays and layout (cached per calibration: a rig's layout is computed once per scene)


class _Key:
    """Hashable wrapper of calibrations for the caches (CameraCalibration holds arrays)."""

    def __init__(self, cals: Sequence[CameraCalibration], *extra: object):
        self.cals = tuple(cals)
        self.key = (tuple(c.key() for c in cals), *extra)

    def __hash__(self) -> int:
        return hash(self.key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Key) and self.key == other.key


def camera_rays_ego(cal: CameraCalibration) -> NDArray[np.float32]:
    """(H, W, 3) float32 unit viewing directions of a camera's pixel centres, ego axes.

    The pixel ray :func:`~phigenesis.geometry.unproject_pixels` gives (distortion removed),
    rotated by ``ego_from_camera`` and normalised; read-only (cached per calibration).
    """
    return _rays(_Key([cal]))


@functools.lru_cache(maxsize=16)
def _rays(key: _Key) -> NDArray[np.float32]:
    (cal,) = key.cals
    kernel = load_camera_rays()
    if kernel is None:
        out = camera_rays_ego_reference(cal)
    else:
        out = kernel.rays_ego(pixel_rays_cam(cal), cal.ego_from_camera[:3, :3])
        out = out.reshape(cal.height, cal.width, 3)
    out.setflags(write=False)
    return out


def camera_rays_ego_reference(cal: CameraCalibration) -> NDArray[np.float32]:
    """:func:`camera_rays_ego` in numpy ((H, W, 3) float32: a (H * W, 3) float64 matrix product, norm
    and division over every pixel); the native kernel
    (``csrc/camera_rays.c``) equals it to one float32 rounding."""
    rays = pixel_rays_cam(cal) @ cal.ego_from_camera[:3, :3].T  # (H*W, 3) ego axes
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return rays.astype(np.float32).reshape(cal.height, cal.width, 3)


def _axis_azimuth(cal: CameraCalibration) -> float:
    axis = cal.ego_from_camera[:3, 2]
    return float(geometry.wrap_angle(np.arctan2(axis[1], axis[0])))


def _horizon_row(cal: CameraCalibration, azimuth: float) -> float:
    """Image row where the horizontal ego ray at ``azimuth`` lands (the principal point's row if
    that ray is behind the camera or outside the distortion model)."""
    direction = np.array([[np.cos(azimuth), np.sin(azimuth), 0.0]])
    uv, ok = geometry.project_points(direction @ cal.ego_from_camera[:3, :3], cal.intrinsics, cal.distortion)
    return float(uv[0, 1]) if ok[0] else float(cal.intrinsics[1, 2])


def _azimuth_span(cal: CameraCalibration, axis_azimuth: float) -> tuple[float, float]:
    """Azimuth range of a view's field: over the outer edge of its pixels' footprints, sampled every
    half pixel (azimuth has no extremum inside an image, unless a pole is in view: then the whole
    circle, ``axis -+ pi``)."""
    poles = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]) @ cal.ego_from_camera[:3, :3]
    uv, ok = geometry.project_points(poles, cal.intrinsics, cal.distortion)
    if np.any(ok & geometry.in_image(uv, cal.width, cal.height)):
        return axis_azimuth - np.pi, axis_azimuth + np.pi
    us = np.linspace(-0.5, cal.width - 0.5, 2 * cal.width + 1)
    vs = np.linspace(-0.5, cal.height - 0.5, 2 * cal.height + 1)
    edge = np.concatenate(
        [
            np.stack([us, np.full_like(us, vs[0])], 1),
            np.stack([us, np.full_like(us, vs[-1])], 1),
            np.stack([np.full_like(vs, us[0]), vs], 1),
            np.stack([np.full_like(vs, us[-1]), vs], 1),
        ]
    )
    rays = unproject_points(edge, cal) @ cal.ego_from_camera[:3, :3].T
    relative = geometry.wrap_angle(np.arctan2(rays[:, 1], rays[:, 0]) - axis_azimuth)
    return axis_azimuth + float(relative.min()), axis_azimuth + float(relative.max())


def unproject_points(uv: NDArray[np.float64], cal: CameraCalibration) -> NDArray[np.float64]:
    """Pixels ``uv`` ((N, 2) float64, u along the width) to (N, 3) camera-frame rays (z = 1):
    :func:`~phigenesis.geometry.unproject_pixels`, with the native Newton solver
    (``csrc/camera_rays.c``, equal to it to ~1e-15 wherever a ray exists) where it builds."""
    kernel = load_camera_rays() if cal.distortion.any() else None
    if kernel is None:
        return geometry.unproject_pixels(uv, cal.intrinsics, cal.distortion)
    k = cal.intrinsics
    y_d = (uv[:, 1] - k[1, 2]) / k[1, 1]
    x_d = (uv[:, 0] - k[0, 2] - k[0, 1] * y_d) / k[0, 0]
    r_max = geometry.max_monotonic_radius(cal.distortion)
    xy = kernel.undistort_points(np.stack([x_d, y_d], axis=-1), cal.distortion, r_max)
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


def range_view_layout(calibrations: Sequence[CameraCalibration], align: Align = "horizon") -> RangeViewLayout:
    """The range-view layout of cameras ``calibrations`` (any order), following the module's rules.

    Cached per set of calibrations (the result is read-only); computing the overlap map costs one
    projection of every pixel ray into every other camera.
    """
    if not calibrations:
        raise ValueError("a range view needs at least one camera")
    return _layout(_Key(calibrations, align))


@functools.lru_cache(maxsize=16)
def _layout(key: _Key) -> RangeViewLayout:
    cals, align = key.cals, key.key[1]
    azimuths = [_axis_azimuth(c) for c in cals]
    order = sorted(range(len(cals)), key=lambda i: (-azimuths[i], i))
    cals = [cals[i] for i in order]
    azimuths = [azimuths[i] for i in order]
    if align == "horizon":
        horizon = [_horizon_row(c, a) for c, a in zip(cals, azimuths, strict=True)]
        top = max(horizon)
        rows0 = [round(top - h) for h in horizon]
    elif align == "top":
        rows0 = [0] * len(cals)
    else:
        raise ValueError(f"unknown range view alignment {align!r}; choose 'horizon' or 'top'")
    rows0 = [r - min(rows0) for r in rows0]
    cols0 = np.concatenate([[0], np.cumsum([c.width for c in cals])]).astype(int)
    views = []
    for c, a, r0, c0 in zip(cals, azimuths, rows0, cols0[:-1], strict=True):
        lo, hi = _azimuth_span(c, a)
        views.append(ViewPlacement(c.name, int(r0), int(c0), c.height, c.width, a, lo, hi))
    height = max(p.row0 + p.height for p in views)
    owner = np.full((height, int(cols0[-1])), NO_VIEW, np.uint8)
    coverage = np.zeros_like(owner)
    for k, (p, cal) in enumerate(zip(views, cals, strict=True)):
        # With the kernel the directions are made from the camera-frame rays on the way: the
        # layout leaves camera_rays_ego's 30 MB per 1920 x 1280 view to packing, which uses it.
        kernel = load_camera_rays()
        rays = pixel_rays_cam(cal) if kernel is not None else camera_rays_ego(cal).reshape(-1, 3)
        own, count = _overlap(k, rays, cals, views)
        owner[p.rows, p.cols] = own.reshape(p.height, p.width)
        coverage[p.rows, p.cols] = count.reshape(p.height, p.width)
    for arr in (owner, coverage):
        arr.setflags(write=False)
    return RangeViewLayout(height, int(cols0[-1]), tuple(views), owner, coverage)


def to_camera(directions_ego: NDArray[np.float64], cal: CameraCalibration) -> NDArray[np.float64]:
    """Directions (N, 3) from ego to camera axes, element by element: each row's result does not
    depend on the other rows (a matrix product's rounding can), so equal directions of two views
    compare equal."""
    r = cal.ego_from_camera[:3, :3]
    d = directions_ego
    return np.stack([d[:, 0] * r[0, i] + d[:, 1] * r[1, i] + d[:, 2] * r[2, i] for i in range(3)], axis=1)


#: Slack of the azimuth pre-test of the overlap map (radians; covers float32 rays).
_AZIMUTH_SLACK = 1e-4


def _overlap(
    k: int,
    rays: NDArray[np.float32] | NDArray[np.float64],
    cals: Sequence[CameraCalibration],
    views: Sequence[ViewPlacement],
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Owner and coverage ((N,) uint8) of view ``k``'s rays ``(N, 3)``: float32 unit directions
    in ego axes (:func:`camera_rays_ego`), or float64 camera-frame rays, z = 1
    (:func:`~phigenesis.data.camera_tables.pixel_rays_cam`, made into those directions on the
    way), among all views ``cals``: :func:`_overlap_reference`, with the native kernel
    (``csrc/camera_rays.c``: one pass, the same arithmetic) where it builds."""
    kernel = load_camera_rays()
    if kernel is None or len(cals) > NO_VIEW:
        if rays.dtype != np.float32:
            rays = camera_rays_ego(cals[k]).reshape(-1, 3)
        return _overlap_reference(k, rays, cals, views)
    r_max2 = [
        geometry.max_monotonic_radius(c.distortion) ** 2 if c.distortion.any() else np.inf for c in cals
    ]
    azimuth = [
        (
            0.5 * (v.azimuth_min_rad + v.azimuth_max_rad),
            0.5 * (v.azimuth_max_rad - v.azimuth_min_rad) + _AZIMUTH_SLACK,
        )
        for v in views
    ]
    return kernel.overlap(
        np.ascontiguousarray(rays) if rays.dtype == np.float64 else np.ascontiguousarray(rays, np.float32),
        k,
        np.ascontiguousarray([c.ego_from_camera[:3, :3] for c in cals], np.float64),
        np.ascontiguousarray([c.intrinsics for c in cals], np.float64),
        np.ascontiguousarray([np.asarray(c.distortion, np.float64).reshape(5) for c in cals]),
        np.asarray(r_max2, np.float64),
        np.asarray([(c.width, c.height) for c in cals], np.int64),
        np.asarray(azimuth, np.float64),
    )


def _overlap_reference(
    k: int, rays: NDArray[np.float32], cals: Sequence[CameraCalibration], views: Sequence[ViewPlacement]
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Owner and coverage of view ``k``'s rays ``(N, 3)`` (ego axes) among all views ``cals``, in
    numpy (the reference of :func:`_overlap`).

    Only rays within another view's azimuth range (plus a small slack) can be in its image, so
    only those are projected into it.
    """
    rays = rays.astype(np.float64)
    azimuth = np.arctan2(rays[:, 1], rays[:, 0])
    best_cos = to_camera(rays, cals[k])[:, 2]  # cosine to the own optical axis
    owner = np.full(len(rays), k, np.uint8)
    count = np.ones(len(rays), np.uint8)
    for j, (cal, view) in enumerate(zip(cals, views, strict=True)):
        if j == k:
            continue
        middle = 0.5 * (view.azimuth_min_rad + view.azimuth_max_rad)
        half = 0.5 * (view.azimuth_max_rad - view.azimuth_min_rad) + _AZIMUTH_SLACK
        near = np.flatnonzero(np.abs(geometry.wrap_angle(azimuth - middle)) <= half)
        in_camera = to_camera(rays[near], cal)
        uv, ok = geometry.project_points(in_camera, cal.intrinsics, cal.distortion)
        seen = ok & geometry.in_image(uv, cal.width, cal.height)
        index, cos = near[seen], in_camera[seen, 2]
        count[index] += 1
        # Strictly nearer wins; on a tie the lower index wins.
        better = (cos > best_cos[index]) | ((cos == best_cos[index]) & (j < owner[index]))
        owner[index[better]] = j
        best_cos[index[better]] = cos[better]
    return owner, count


def range_view_rays(
    layout: RangeViewLayout, calibrations: Sequence[CameraCalibration], channels_first: bool = False
) -> NDArray[np.float32]:
    """Unit ray direction of every cell in the ego frame, 0 in empty cells: float32 (H, W, 3), or
    (3, H, W) with ``channels_first``; read-only (cached per layout and calibrations)."""
    by_name = {c.name: c for c in calibrations}
    cals = [by_name[name] for name in layout.camera_names]
    return _packed_rays(_Key(cals, layout.height, layout.width, layout.views, channels_first))


@functools.lru_cache(maxsize=16)
def _packed_rays(key: _Key) -> NDArray[np.float32]:
    height, width, views, channels_first = key.key[1:]
    out = np.zeros((3, height, width) if channels_first else (height, width, 3), np.float32)
    for p, cal in zip(views, key.cals, strict=True):
        rays = camera_rays_ego(cal)
        if channels_first:
            out[:, p.rows, p.cols] = rays.transpose(2, 0, 1)
        else:
            out[p.rows, p.cols] = rays
    out.setflags(write=False)
    return out


# --------------------------------------------------------------------------------------------
# Packing a frame


@dataclass
class RangeView:
    """A frame's views packed into one range view (all planes ``(H, W, ...)`` of ``layout``).

    Attributes:
        layout: the placement of the views and the overlap map.
        rgb: (H, W, 3) uint8 RGB, 0 in empty cells and in views without an image; None if no
            view has an image.
        depth_m: (H, W) float32 z-depth of each cell's own camera in metres, 0 = unknown; None
            if no view has the chosen source.
        depth_source: which depth this is ("dense", "sparse", "truth") or None.
        semantic: (H, W) uint8 unified class per cell, 255 = ignore/unknown; None if none.
        semantic_source: which semantics ("pseudo", "truth", "labels") or None.
        rays_ego: (H, W, 3) float32 unit viewing direction of each cell in the ego frame, 0 in
            empty cells (read-only: shared by every frame of a rig).
    """

    layout: RangeViewLayout
    rgb: NDArray[np.uint8] | None
    depth_m: NDArray[np.float32] | None
    depth_source: DepthSource | None
    semantic: NDArray[np.uint8] | None
    semantic_source: SemanticSource | None
    rays_ego: NDArray[np.float32]

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(H, W) True where a view's pixel is."""
        return self.layout.valid()

    @property
    def view_index(self) -> NDArray[np.uint8]:
        """(H, W) uint8 index into ``layout.views``, 255 where empty."""
        return self.layout.view_index()


#: Where each depth source's map is on a CameraImage: (record attribute, field).
DEPTH_MAPS: dict[str, tuple[str, str]] = {
    "dense": ("depth", "dense_m"),
    "sparse": ("depth", "sparse_m"),
    "truth": ("truth", "depth_m"),
}
#: Where each semantic source's map is on a CameraImage: (record attribute, field).
SEMANTIC_MAPS: dict[str, tuple[str, str]] = {
    "pseudo": ("pseudo", "semantic"),
    "truth": ("truth", "semantic"),
    "labels": ("labels", "semantic"),
}


def camera_map(cam: CameraImage, where: tuple[str, str]) -> NDArray | None:
    """The (H, W) map ``cam.<record>.<field>`` (e.g. ``DEPTH_MAPS["dense"]``), None if absent."""
    record = getattr(cam, where[0])
    return None if record is None else getattr(record, where[1])


def _first_source(cams: list[CameraImage], sources: Sequence[str], maps: dict[str, tuple[str, str]]) -> tuple:
    """The first of ``sources`` that any view has, with every view's map of it (None where a view
    lacks it); (None, []) if none has any."""
    for source in sources:
        if source not in maps:
            raise ValueError(f"unknown map source {source!r}; choose from {sorted(maps)}")
        planes = [camera_map(c, maps[source]) for c in cams]
        if any(m is not None for m in planes):
            return source, planes
    return None, []


def frame_layout(frame: Frame, align: Align = "horizon") -> RangeViewLayout:
    """The frame's stored layout (``frame.range_view``) if it matches its cameras, else a new one."""
    stored = frame.range_view
    if stored is not None:
        sizes = {c.name: (c.calibration.height, c.calibration.width) for c in frame.cameras}
        if sorted(stored.camera_names) == sorted(sizes) and all(
            sizes[p.camera_name] == (p.height, p.width) for p in stored.views
        ):
            return stored
    return range_view_layout([c.calibration for c in frame.cameras], align)


def pack_range_view(
    frame: Frame,
    layout: RangeViewLayout | None = None,
    depth_sources: Sequence[DepthSource] = DEFAULT_DEPTH_SOURCES,
    semantic_sources: Sequence[SemanticSource] = DEFAULT_SEMANTIC_SOURCES,
    rgb: bool = True,
) -> RangeView:
    """Packs a frame's images and maps into one range view.

    Args:
        frame: the frame; each camera's pixels go to its view's cells unchanged.
        layout: the layout to use (default :func:`frame_layout`: the frame's own, else computed).
        depth_sources: depth kinds tried in order; the first that any view has is used (views
            without it get 0 = unknown).
        semantic_sources: semantic kinds tried in order, likewise (views without it get 255).
        rgb: decode and pack the images (False skips the JPEG decoding).

    Returns:
        A :class:`RangeView`.
    """
    layout = frame_layout(frame) if layout is None else layout
    by_name = {c.name: c for c in frame.cameras}
    missing = [n for n in layout.camera_names if n not in by_name]
    if missing:
        raise ValueError(f"frame {frame.scene_id}/{frame.frame_index} has no camera {missing} of the layout")
    cams = [by_name[n] for n in layout.camera_names]
    images = [c.decode_image() if rgb and c.image_bytes is not None else None for c in cams]
    depth_source, depths = _first_source(cams, depth_sources, DEPTH_MAPS)
    semantic_source, semantics = _first_source(cams, semantic_sources, SEMANTIC_MAPS)
    return RangeView(
        layout=layout,
        rgb=layout.pack(images) if any(i is not None for i in images) else None,
        depth_m=layout.pack(depths) if depth_source is not None else None,
        depth_source=depth_source,  # type: ignore[arg-type]
        semantic=layout.pack(semantics, fill=tx.IGNORE_ID) if semantic_source is not None else None,
        semantic_source=semantic_source,  # type: ignore[arg-type]
        rays_ego=range_view_rays(layout, [c.calibration for c in cams]),
    )
