"""The LiDAR sweep record: points in the ego frame with their origins, times and returns.

The scene model as a whole: :mod:`phigenesis.data.records`."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.record_checks import (
    MAX_POINT_DISTANCE_M,
    InvalidRecord,
    _check_array,
    _check_micros,
    _listed,
    check_transform,
)

#: The per-point fields of :class:`LidarSweep`: (name, shape after N, dtype, optional).
_POINT_FIELDS: tuple[tuple[str, tuple[int, ...], type, bool], ...] = (
    ("points_ego", (3,), np.float32, False),
    ("intensity", (), np.float32, False),
    ("beam_index", (), np.uint16, False),
    ("origins_ego", (3,), np.float32, False),
    ("time_offset_micros", (), np.int32, False),
    ("lidar_id", (), np.uint8, False),
    ("semantic", (), np.uint8, True),
    ("instance", (), np.uint16, True),
    ("elongation", (), np.float32, True),
    ("return_index", (), np.uint8, True),
    ("flow_world_mps", (3,), np.float32, True),
)


@dataclass
class LidarSweep:
    """One sweep of the LiDAR(s), points in the ego frame at the sweep's reference time.

    Attributes (N points):
        timestamp_micros: reference time; ``points_ego`` are in the ego frame at this time
            (motion-compensated, as Waymo provides them).
        world_from_ego: (4, 4) ego pose at ``timestamp_micros``.
        points_ego: (N, 3) float32 metres.
        intensity: (N,) float32, in [0, 1] for synthetic data, raw for datasets.
        beam_index: (N,) uint16 laser row (0 = highest beam).
        origins_ego: (N, 3) float32 position of the sensor when the point was measured, in the same
            ego frame (ray origin; differs from the mount position when the ego moves).
        time_offset_micros: (N,) int32 measurement time minus ``timestamp_micros``.
        lidar_id: (N,) uint8 which sensor (0 for a single LiDAR).
        semantic: (N,) uint8 truth class per point, or None.
        instance: (N,) uint16 truth instance per point (0 = stuff), or None.
        elongation: (N,) float32 pulse elongation per point (Waymo), or None.
        return_index: (N,) uint8 0 for the strongest (first) return, 1 for the second; None =
            all first returns.
        flow_world_mps: (N, 3) float32 velocity of each point's surface at its measurement time,
            world frame, m/s (stage ``scene_flow``: its box's rigid motion, 0 for static points),
            or None.
    """

    timestamp_micros: int
    world_from_ego: NDArray[np.float64]
    points_ego: NDArray[np.float32]
    intensity: NDArray[np.float32]
    beam_index: NDArray[np.uint16]
    origins_ego: NDArray[np.float32]
    time_offset_micros: NDArray[np.int32]
    lidar_id: NDArray[np.uint8]
    semantic: NDArray[np.uint8] | None = None
    instance: NDArray[np.uint16] | None = None
    elongation: NDArray[np.float32] | None = None
    return_index: NDArray[np.uint8] | None = None
    flow_world_mps: NDArray[np.float32] | None = None

    def __post_init__(self) -> None:
        self._convert()
        bad = self._invalid_points()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidRecord(
                "lidar points_ego",
                f"has {int(bad.sum())} of {len(bad)} points with non-finite values or coordinates beyond "
                f"{MAX_POINT_DISTANCE_M:g} m (first: point {i} at {_listed(self.points_ego[i])} from "
                f"{_listed(self.origins_ego[i])}); build the sweep with "
                "LidarSweep.without_invalid_points to leave them out",
            )

    def _convert(self) -> None:
        """Checks the sweep-wide fields and every per-point array's shape, and sets the dtypes."""
        self.timestamp_micros = _check_micros("lidar timestamp_micros", self.timestamp_micros)
        self.world_from_ego = check_transform("lidar world_from_ego", self.world_from_ego)
        with np.errstate(over="ignore"):  # float64 beyond float32's range becomes inf: refused below
            self.points_ego = _check_array("lidar points_ego", self.points_ego, (None, 3), np.float32)
            n = len(self.points_ego)
            for name, shape, dtype, optional in _POINT_FIELDS[1:]:
                value = getattr(self, name)
                if value is not None or not optional:
                    setattr(self, name, _check_array(f"lidar {name}", value, (n, *shape), dtype))

    def _invalid_points(self) -> NDArray[np.bool_]:
        """(N,) which points have a non-finite value or a coordinate beyond MAX_POINT_DISTANCE_M."""
        bad = np.zeros(len(self.points_ego), bool)
        for name in ("points_ego", "origins_ego"):
            xyz = getattr(self, name)
            # One flat pass first (a NaN makes the maximum NaN, which compares False); the per-point
            # mask only when something fails.
            if not np.abs(xyz).max(initial=0.0) <= MAX_POINT_DISTANCE_M:
                bad |= ~(np.abs(xyz) <= MAX_POINT_DISTANCE_M).all(axis=1)
        for name in ("intensity", "elongation"):
            value = getattr(self, name)
            if value is not None:
                bad |= ~np.isfinite(value)
        return bad

    @classmethod
    def without_invalid_points(cls, **values: Any) -> tuple[LidarSweep, int]:
        """A sweep from the constructor's arguments with every point that has a non-finite value
        (coordinates, ray origin, intensity, elongation) or a coordinate beyond
        :data:`MAX_POINT_DISTANCE_M` left out, with all its per-point fields; and how many were
        left out (record it as ``scene.dropped.add(INVALID_POINTS, frame_index, count)``).

        Sweep-wide problems (the pose, the time, array shapes) still raise :class:`InvalidRecord`.
        """
        sweep = cls.__new__(cls)
        for f in fields(cls):
            setattr(sweep, f.name, values.get(f.name, f.default))
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"LidarSweep has no fields {unknown}")
        sweep._convert()
        bad = sweep._invalid_points()
        return sweep.select(~bad), int(bad.sum())

    def select(self, index: NDArray[np.bool_] | NDArray[np.integer]) -> LidarSweep:
        """The points given by a boolean mask or an index array, with all their per-point fields."""
        idx = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, dtype=np.int64)
        per_point = {
            name: None if getattr(self, name) is None else getattr(self, name)[idx]
            for name, *_ in _POINT_FIELDS
        }
        return LidarSweep(
            timestamp_micros=self.timestamp_micros, world_from_ego=self.world_from_ego, **per_point
        )

    def __len__(self) -> int:
        return len(self.points_ego)

    def points_world(self) -> NDArray[np.float64]:
        """(N, 3) float64 points in the world frame."""
        return geometry.transform_points(self.world_from_ego, self.points_ego)

    @classmethod
    def empty(cls, timestamp_micros: int, world_from_ego: NDArray[np.float64]) -> LidarSweep:
        """A sweep with no points (the LiDAR saw nothing or the frame has none)."""
        return cls(
            timestamp_micros=timestamp_micros,
            world_from_ego=world_from_ego,
            points_ego=np.zeros((0, 3), np.float32),
            intensity=np.zeros(0, np.float32),
            beam_index=np.zeros(0, np.uint16),
            origins_ego=np.zeros((0, 3), np.float32),
            time_offset_micros=np.zeros(0, np.int32),
            lidar_id=np.zeros(0, np.uint8),
        )
