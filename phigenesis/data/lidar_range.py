"""LiDAR range image: a sweep laid out as rows = beams, columns = azimuth bins.

Entry points: :func:`lidar_range_image` (sweep -> image) and :func:`range_image_points` (image ->
points, within the bin quantisation). :func:`estimate_columns` guesses a spinning LiDAR's
azimuth steps from a sweep.

Geometry (ego frame, metres, radians): each point is measured along the ray from its own origin
(``LidarSweep.origins_ego``, the sensor's position when it fired), so ``d = point - origin``;
its range is ``|d|`` (computed in float64, stored as float32: exact), its azimuth
``atan2(d_y, d_x)`` and its elevation ``atan2(d_z, hypot(d_x, d_y))``.

- Row = ``beam_index`` (0 = highest beam); points of other LiDARs (``lidar_id``) or with a beam
  index beyond the image's rows are not in the image.
- Column ``c`` covers azimuths ``(pi * (1 - 2 (c + 1) / W), pi * (1 - 2 c / W)]`` around its centre
  ``pi * (1 - (2 c + 1) / W)``: column 0 just left of the rear, decreasing (clockwise seen from
  above) through the front at ``W / 2``, as Waymo's range images. ``c = floor((pi - azimuth) *
  W / (2 pi)) mod W``.
- Collisions (two points in one cell, e.g. both returns of a pulse, or ego rotation during the
  sweep): the nearest point is kept (ties: the lower point index); the others are listed in
  ``overflow_index`` with their cell in ``overflow_cell``, nearest first within a cell, so nothing is
  lost.
- Back to points: the cell's ray starts at ``column_origin_ego[c]`` (the mean origin of the
  column's points) with azimuth = the column centre and elevation = ``beam_inclination_rad[r]``
  (the median elevation of the row's points). A point comes back within half a column in azimuth
  and within its beam's spread in elevation; ``point_index`` gives the exact point.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.range_records import EMPTY, LidarRangeImage, column_azimuths_rad
from phigenesis.data.records import LidarSweep

__all__ = ["EMPTY", "LidarRangeImage", "column_azimuths_rad"]


def _rays(sweep: LidarSweep) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Range, azimuth and elevation (N,) of every point from its own origin, float64."""
    d = sweep.points_ego.astype(np.float64) - sweep.origins_ego.astype(np.float64)
    horizontal = np.hypot(d[:, 0], d[:, 1])
    return np.linalg.norm(d, axis=1), np.arctan2(d[:, 1], d[:, 0]), np.arctan2(d[:, 2], horizontal)


def azimuth_columns(azimuth_rad: NDArray[np.floating], width: int) -> NDArray[np.int64]:
    """Column (N,) of azimuths (radians) in a ``width``-column image (see the module docstring)."""
    c = np.floor((np.pi - np.asarray(azimuth_rad, np.float64)) * (width / (2.0 * np.pi))).astype(np.int64)
    return np.mod(c, width)


def lidar_range_image(sweep: LidarSweep, beams: int, columns: int, lidar_id: int = 0) -> LidarRangeImage:
    """The range image of LiDAR ``lidar_id`` in ``sweep``: ``beams`` rows by ``columns`` azimuth bins.

    Points of other LiDARs, with a beam index ``>= beams``, or with a zero or non-finite range are
    left out (count them as ``len(sweep) - valid.sum() - len(overflow_index)``). An empty sweep
    gives an empty image (all cells -1, NaN inclinations and origins).
    """
    if beams < 1 or columns < 1:
        raise ValueError(f"a range image needs beams >= 1 and columns >= 1, got {beams} x {columns}")
    rng, azimuth, elevation = _rays(sweep)
    range_all = rng.astype(np.float32)
    ok = (sweep.lidar_id == lidar_id) & (sweep.beam_index < beams) & np.isfinite(rng) & (rng > 0)
    index = np.flatnonzero(ok)
    cell = sweep.beam_index[index].astype(np.int64) * columns + azimuth_columns(azimuth[index], columns)
    # Nearest first within each cell (ties: lower point index, as `index` is ascending): a stable
    # sort by range, then a stable sort by cell (faster than lexsort).
    by_range = np.argsort(range_all[index], kind="stable")
    order = by_range[np.argsort(cell[by_range], kind="stable")]
    index, cell = index[order], cell[order]
    first = np.ones(len(cell), bool)
    first[1:] = cell[1:] != cell[:-1]
    point_index = np.full(beams * columns, EMPTY, np.int32)
    point_index[cell[first]] = index[first]
    point_index = point_index.reshape(beams, columns)
    valid = point_index != EMPTY
    kept = point_index[valid]
    rows, cols = np.nonzero(valid)
    inclination = np.full(beams, np.nan, np.float32)
    origin = np.full((columns, 3), np.nan, np.float32)
    if kept.size:
        counts = np.bincount(rows, minlength=beams)  # `rows` is ascending (row-major order)
        for r, row_elevations in enumerate(np.split(elevation[kept], np.cumsum(counts)[:-1])):
            if row_elevations.size:
                inclination[r] = np.median(row_elevations)
        col_counts = np.bincount(cols, minlength=columns)
        sums = np.stack(
            [np.bincount(cols, sweep.origins_ego[kept, k].astype(np.float64), columns) for k in range(3)], 1
        )
        filled = col_counts > 0
        origin[filled] = (sums[filled] / col_counts[filled, None]).astype(np.float32)
    return LidarRangeImage(
        range_m=_gather(range_all, point_index, 0.0),
        intensity=_gather(sweep.intensity, point_index, 0.0),
        point_index=point_index,
        beam_inclination_rad=inclination,
        column_origin_ego=origin,
        overflow_index=index[~first].astype(np.int32),
        overflow_cell=cell[~first].astype(np.int32),
        lidar_id=int(lidar_id),
    )


def range32_of(sweep: LidarSweep) -> NDArray[np.float32]:
    """(N,) float32 range of every point from its own origin (the range image's ``range_m``)."""
    return _rays(sweep)[0].astype(np.float32)


def _gather(values: NDArray, point_index: NDArray[np.int32], fill: float) -> NDArray[np.float32]:
    """``values[point_index]`` as float32 with ``fill`` in empty cells."""
    out = np.full(point_index.shape, fill, np.float32)
    valid = point_index != EMPTY
    out[valid] = values[point_index[valid]]
    return out


def with_sweep_values(
    sweep: LidarSweep,
    point_index: NDArray[np.int32],
    beam_inclination_rad: NDArray[np.float32],
    column_origin_ego: NDArray[np.float32],
    overflow_index: NDArray[np.int32],
    overflow_cell: NDArray[np.int32],
    lidar_id: int,
) -> LidarRangeImage:
    """A range image rebuilt from its stored parts: range and intensity gathered from ``sweep``
    through ``point_index`` (what the cache reader does; equal to :func:`lidar_range_image`'s)."""
    if len(sweep) and point_index.size and point_index.max() >= len(sweep):
        raise ValueError(
            f"range image point_index {point_index.max()} beyond the sweep's {len(sweep)} points"
        )
    return LidarRangeImage(
        range_m=_gather(range32_of(sweep), point_index, 0.0),
        intensity=_gather(sweep.intensity, point_index, 0.0),
        point_index=point_index,
        beam_inclination_rad=beam_inclination_rad,
        column_origin_ego=column_origin_ego,
        overflow_index=overflow_index,
        overflow_cell=overflow_cell,
        lidar_id=lidar_id,
    )


def range_image_points(
    image: LidarRangeImage,
) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.int64]]:
    """Points (M, 3) float32 (ego frame) of the image's non-empty cells, with their rows and columns
    (M,), row-major: ``origin[c] + range * direction(column centre azimuth, row inclination)``."""
    rows, cols = np.nonzero(image.valid)
    azimuth = image.column_azimuths_rad()[cols]
    inclination = image.beam_inclination_rad[rows].astype(np.float64)
    direction = np.stack(
        [np.cos(inclination) * np.cos(azimuth), np.cos(inclination) * np.sin(azimuth), np.sin(inclination)], 1
    )
    points = image.column_origin_ego[cols].astype(np.float64) + image.range_m[rows, cols, None] * direction
    return points.astype(np.float32), rows, cols


def estimate_columns(sweep: LidarSweep, lidar_id: int = 0) -> int:
    """Azimuth steps per revolution of a spinning LiDAR: ``2 pi`` over the median azimuth step
    between neighbouring returns of its fullest beam (dropouts and gaps do not move a median).
    Raises ValueError if the sweep has too few points of that LiDAR."""
    _, azimuth, _ = _rays(sweep)
    mine = sweep.lidar_id == lidar_id
    beams = sweep.beam_index[mine]
    if beams.size < 16:
        raise ValueError(f"cannot estimate LiDAR columns from {beams.size} points of lidar {lidar_id}")
    fullest = np.bincount(beams).argmax()
    steps = np.diff(np.sort(azimuth[mine][beams == fullest]))
    steps = steps[steps > 1e-9]  # both returns of a pulse share an azimuth
    if steps.size < 8:
        raise ValueError(
            f"cannot estimate LiDAR columns: beam {fullest} has {steps.size + 1} distinct azimuths"
        )
    return round(2.0 * np.pi / float(np.median(steps)))
