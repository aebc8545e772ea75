"""The records of the range views: where each camera view sits in a frame's camera range view
(:class:`RangeViewLayout`) and a LiDAR sweep as a beams x azimuth image (:class:`LidarRangeImage`).

They are part of the scene model (``Frame.range_view``, ``Frame.lidar_range_image``) but depend on
nothing of it, so the scene model (:mod:`phigenesis.data.records`) imports them and the modules
that build them (:mod:`phigenesis.data.rangeview`, :mod:`phigenesis.data.lidar_range`) import both
without an import circle.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: View index / owner of a cell that no view covers.
NO_VIEW = 255


@dataclass(frozen=True)
class ViewPlacement:
    """Where one camera view sits in the range view.

    Attributes:
        camera_name: the camera (matched by name).
        row0, col0: range-view cell of the view's pixel (0, 0).
        height, width: the view's size in pixels (= its cells).
        axis_azimuth_rad: azimuth of the optical axis in the ego frame, [-pi, pi) (0 = forward,
            +pi/2 = left).
        azimuth_min_rad, azimuth_max_rad: azimuth range of the view's field in the ego frame (the
            outer edge of its pixels), ``min <= axis <= max``, not wrapped: a view across the rear
            may reach below -pi; a view with a pole in sight spans ``axis -+ pi``.
    """

    camera_name: str
    row0: int
    col0: int
    height: int
    width: int
    axis_azimuth_rad: float
    azimuth_min_rad: float
    azimuth_max_rad: float

    @property
    def rows(self) -> slice:
        return slice(self.row0, self.row0 + self.height)

    @property
    def cols(self) -> slice:
        return slice(self.col0, self.col0 + self.width)


@dataclass(frozen=True, eq=False)
class RangeViewLayout:
    """The placement of a frame's views in its range view, and the overlap map.

    Attributes:
        height, width: range-view size in cells.
        views: placements in range-view order (left to right).
        owner: (H, W) uint8 index into ``views`` of the view owning the cell's direction (see the
            module docstring), 255 where no view covers the cell.
        coverage: (H, W) uint8 number of views whose image contains the cell's direction (0 where
            no view covers the cell; >= 2 in overlaps).
    """

    height: int
    width: int
    views: tuple[ViewPlacement, ...]
    owner: NDArray[np.uint8]
    coverage: NDArray[np.uint8]

    def __post_init__(self) -> None:
        for name in ("owner", "coverage"):
            arr = getattr(self, name)
            if arr.shape != (self.height, self.width) or arr.dtype != np.uint8:
                raise ValueError(
                    f"range view {name}: want {(self.height, self.width)} uint8, got {arr.shape} {arr.dtype}"
                )
        for p in self.views:
            if p.row0 < 0 or p.col0 < 0 or p.row0 + p.height > self.height or p.col0 + p.width > self.width:
                raise ValueError(
                    f"view {p.camera_name} does not fit in the {self.height}x{self.width} range view"
                )

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, RangeViewLayout)
            and (self.height, self.width, self.views) == (other.height, other.width, other.views)
            and np.array_equal(self.owner, other.owner)
            and np.array_equal(self.coverage, other.coverage)
        )

    __hash__ = object.__hash__

    @property
    def camera_names(self) -> list[str]:
        return [p.camera_name for p in self.views]

    def view_index(self) -> NDArray[np.uint8]:
        """(H, W) uint8 index into ``views`` of each cell's view, 255 where empty."""
        out = np.full((self.height, self.width), NO_VIEW, np.uint8)
        for k, p in enumerate(self.views):
            out[p.rows, p.cols] = k
        return out

    def valid(self) -> NDArray[np.bool_]:
        """(H, W) True where a view's pixel is."""
        return self.view_index() != NO_VIEW

    def primary(self) -> NDArray[np.bool_]:
        """(H, W) True where the cell's own view owns its direction (each direction once)."""
        index = self.view_index()
        return (self.owner == index) & (index != NO_VIEW)

    def pack(self, planes: Sequence[NDArray | None], fill: float | int = 0) -> NDArray:
        """One ``(H, W, ...)`` plane from per-view planes ``(h_k, w_k, ...)`` in range-view order.

        All planes share dtype and trailing shape; a None plane leaves its view's cells at ``fill``
        (as do empty cells). Raises ValueError naming the view on a size mismatch.
        """
        if len(planes) != len(self.views):
            raise ValueError(f"{len(planes)} planes for {len(self.views)} views")
        first = next((p for p in planes if p is not None), None)
        if first is None:
            raise ValueError("pack needs at least one plane")
        out = np.full((self.height, self.width, *first.shape[2:]), fill, first.dtype)
        for p, plane in zip(self.views, planes, strict=True):
            if plane is None:
                continue
            if plane.shape != (p.height, p.width, *first.shape[2:]):
                raise ValueError(
                    f"view {p.camera_name}: plane is {plane.shape}, the layout says {(p.height, p.width)}"
                )
            out[p.rows, p.cols] = plane
        return out

    def unpack(self, plane: NDArray) -> list[NDArray]:
        """The per-view planes ``(h_k, w_k, ...)`` (copies) of an ``(H, W, ...)`` plane."""
        if plane.shape[:2] != (self.height, self.width):
            raise ValueError(f"plane is {plane.shape}, the range view is {(self.height, self.width)}")
        return [plane[p.rows, p.cols].copy() for p in self.views]


# --------------------------------------------------------------------------------------------
# LiDAR range image

#: ``point_index`` of an empty cell.
EMPTY = -1


@dataclass
class LidarRangeImage:
    """One LiDAR's sweep as an ``H x W`` (beams x azimuth bins) image.

    Attributes:
        range_m: (H, W) float32 distance from the point's ray origin, metres; 0 = empty.
        intensity: (H, W) float32 return strength of the kept point; 0 = empty.
        point_index: (H, W) int32 index into the sweep's points of the kept point; -1 = empty.
        beam_inclination_rad: (H,) float32 elevation of each row's rays (median of its points),
            NaN for a row without points.
        column_origin_ego: (W, 3) float32 ray origin of each column in the ego frame (mean of its
            points' origins), NaN for a column without points.
        overflow_index: (K,) int32 points that lost a collision (farther than the kept one).
        overflow_cell: (K,) int32 their cells, ``row * W + column``.
        lidar_id: which LiDAR of the sweep this is.
    """

    range_m: NDArray[np.float32]
    intensity: NDArray[np.float32]
    point_index: NDArray[np.int32]
    beam_inclination_rad: NDArray[np.float32]
    column_origin_ego: NDArray[np.float32]
    overflow_index: NDArray[np.int32]
    overflow_cell: NDArray[np.int32]
    lidar_id: int = 0

    def __post_init__(self) -> None:
        h, w = self.point_index.shape
        for name, shape, dtype in (
            ("range_m", (h, w), np.float32),
            ("intensity", (h, w), np.float32),
            ("point_index", (h, w), np.int32),
            ("beam_inclination_rad", (h,), np.float32),
            ("column_origin_ego", (w, 3), np.float32),
            ("overflow_index", self.overflow_index.shape[:1], np.int32),
            ("overflow_cell", self.overflow_index.shape[:1], np.int32),
        ):
            arr = getattr(self, name)
            if arr.shape != shape or arr.dtype != dtype:
                raise ValueError(
                    f"{name} must be {shape} {np.dtype(dtype).name}, got {arr.shape} {arr.dtype}"
                )

    @property
    def height(self) -> int:
        return self.point_index.shape[0]

    @property
    def width(self) -> int:
        return self.point_index.shape[1]

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(H, W) True where a point is."""
        return self.point_index != EMPTY

    def column_azimuths_rad(self) -> NDArray[np.float64]:
        """(W,) azimuth of each column's centre, ego frame."""
        return column_azimuths_rad(self.width)


def column_azimuths_rad(width: int) -> NDArray[np.float64]:
    """(W,) centre azimuths of ``width`` columns, from just left of the rear, clockwise."""
    return np.pi * (1.0 - (2.0 * np.arange(width) + 1.0) / width)
