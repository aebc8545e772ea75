"""The 3-D box record of a frame: centres, sizes and orientations (world frame), velocities, classes
and tracks.

The scene model as a whole: :mod:`phigenesis.data.records`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.record_checks import (
    BOX_STATUSES,
    MAX_BOX_SIZE_M,
    MAX_COORDINATE_M,
    BoxStatus,
    InvalidRecord,
    _check_array,
    _listed,
)


@dataclass
class Boxes:
    """The 3D boxes of one timestamp, as parallel arrays (M boxes), in the world frame.

    Attributes:
        track_id: M strings, stable for an object within its scene.
        class_id: (M,) uint8 unified-taxonomy class.
        center_world: (M, 3) float64 box centre, metres.
        size_lwh: (M, 3) float64 length (along heading), width, height, metres.
        yaw_world: (M,) float64 heading about +z, radians in [-pi, pi).
        velocity_world: (M, 3) float64 velocity of the centre, m/s; NaN where unknown (keyframe
            annotations, which ``interpolate_boxes`` fills; sources build their boxes with
            :meth:`without_invalid`, which refuses NaN by default, so caches hold known ones).
        status: (M,) uint8 index into :data:`BOX_STATUSES` (annotated, interpolated, extrapolated).
        instance_id: (M,) uint16 id used in instance maps, 0 if the source has none.
        num_lidar_points: (M,) int32 LiDAR points inside the box in its frame's sweep, -1 if unknown.
        acceleration_world: (M, 3) float64 acceleration of the centre, m/s^2; NaN where unknown
            (None on construction means unknown for all).
        orientation_world: (M, 4) float64 wxyz quaternion world <- box. Boxes are upright in the
            world unless a dataset tilts them (Waymo labels are upright in the tilted ego frame);
            None on construction means upright at ``yaw_world``. ``yaw_world`` is the heading of
            the box's +x axis in the ground plane either way.
    """

    track_id: list[str]
    class_id: NDArray[np.uint8]
    center_world: NDArray[np.float64]
    size_lwh: NDArray[np.float64]
    yaw_world: NDArray[np.float64]
    velocity_world: NDArray[np.float64]
    status: NDArray[np.uint8]
    instance_id: NDArray[np.uint16]
    num_lidar_points: NDArray[np.int32]
    acceleration_world: NDArray[np.float64] | None = None
    orientation_world: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        self._convert()
        problems = self._problems(velocity_known=False)
        if problems:
            raise problems[0]
        self.yaw_world = geometry.wrap_angle(self.yaw_world)
        self.orientation_world = geometry.quaternion_normalize(self.orientation_world)

    def _convert(self) -> None:
        """Checks every array's shape against the track ids, sets the dtypes, fills the defaults."""
        self.track_id = [str(t) for t in self.track_id]
        m = len(self.track_id)
        self.class_id = _check_array("boxes class_id", self.class_id, (m,), np.uint8)
        self.center_world = _check_array("boxes center_world", self.center_world, (m, 3), np.float64)
        self.size_lwh = _check_array("boxes size_lwh", self.size_lwh, (m, 3), np.float64)
        self.yaw_world = _check_array("boxes yaw_world", self.yaw_world, (m,), np.float64)
        self.velocity_world = _check_array("boxes velocity_world", self.velocity_world, (m, 3), np.float64)
        self.status = _check_array("boxes status", self.status, (m,), np.uint8)
        self.instance_id = _check_array("boxes instance_id", self.instance_id, (m,), np.uint16)
        self.num_lidar_points = _check_array("boxes num_lidar_points", self.num_lidar_points, (m,), np.int32)
        if self.acceleration_world is None:
            self.acceleration_world = np.full((m, 3), np.nan)
        self.acceleration_world = _check_array(
            "boxes acceleration_world", self.acceleration_world, (m, 3), np.float64
        )
        if self.orientation_world is None:
            self.orientation_world = geometry.yaw_to_quaternion(self.yaw_world).reshape(m, 4)
        self.orientation_world = _check_array(
            "boxes orientation_world", self.orientation_world, (m, 4), np.float64
        )
        if np.any(self.status >= len(BOX_STATUSES)):
            raise InvalidRecord(
                "boxes status", f"codes must be < {len(BOX_STATUSES)}, got {np.unique(self.status).tolist()}"
            )

    def _problems(self, velocity_known: bool) -> list[InvalidRecord]:
        """One error per invalid box (its first invalid field), naming the box by its track id:
        centre finite within MAX_COORDINATE_M, size finite in (0, MAX_BOX_SIZE_M], yaw and
        orientation (non-zero) finite, velocity finite (or NaN = unknown unless
        ``velocity_known``), acceleration finite or NaN (unknown)."""
        with np.errstate(invalid="ignore", over="ignore"):
            norms = np.linalg.norm(self.orientation_world, axis=1)
            checks = (
                (
                    "center_world",
                    ~(np.abs(self.center_world) <= MAX_COORDINATE_M).all(axis=1),
                    f"must be finite and within {MAX_COORDINATE_M:g} m",
                ),
                (
                    "size_lwh",
                    ~((self.size_lwh > 0) & (self.size_lwh <= MAX_BOX_SIZE_M)).all(axis=1),
                    f"must be finite and in (0, {MAX_BOX_SIZE_M:g}] m",
                ),
                ("yaw_world", ~np.isfinite(self.yaw_world), "must be finite"),
                (
                    "orientation_world",
                    ~(np.isfinite(norms) & (norms > geometry.QUATERNION_ZERO_NORM)),
                    "must be a finite, non-zero quaternion",
                ),
                (
                    "velocity_world",
                    ~np.isfinite(self.velocity_world).all(axis=1)
                    if velocity_known
                    else np.isinf(self.velocity_world).any(axis=1),
                    "must be finite" if velocity_known else "must be finite (or NaN where unknown)",
                ),
                (
                    "acceleration_world",
                    np.isinf(self.acceleration_world).any(axis=1),
                    "must be finite (or NaN where unknown)",
                ),
            )
        problems: dict[int, InvalidRecord] = {}
        for name, bad, rule in checks:
            for i in np.flatnonzero(bad).tolist():
                if i not in problems:
                    value = getattr(self, name)[i]
                    problems[i] = InvalidRecord(
                        f"box {self.track_id[i]!r}", f"{name} {_listed(value)} {rule}", index=i
                    )
        return [problems[i] for i in sorted(problems)]

    @classmethod
    def without_invalid(
        cls, *, velocity_known: bool = True, **values: Any
    ) -> tuple[Boxes, list[InvalidRecord]]:
        """Boxes from the constructor's arguments with every invalid box left out, and one
        :class:`InvalidRecord` per box left out (naming its track id and field; ``index`` is its
        position in the arguments). Sources raise the first under ``--on-error raise``, and
        under ``skip`` log them and count them as :data:`INVALID_BOXES`.

        ``velocity_known``: a NaN velocity is invalid (the boxes of a frame, which the cache
        stores), or, if False, unknown (keyframe annotations that ``interpolate_boxes`` fills).
        Problems of the arrays as a whole (shapes, status codes) still raise.
        """
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"Boxes has no fields {unknown}")
        boxes = cls.__new__(cls)
        for f in fields(cls):
            setattr(boxes, f.name, values.get(f.name, f.default))
        boxes._convert()
        problems = boxes._problems(velocity_known)
        keep = np.ones(len(boxes.track_id), bool)
        keep[[p.index for p in problems]] = False
        return boxes.select(keep), problems

    def __len__(self) -> int:
        return len(self.track_id)

    @classmethod
    def empty(cls) -> Boxes:
        return cls(
            track_id=[],
            class_id=np.zeros(0, np.uint8),
            center_world=np.zeros((0, 3)),
            size_lwh=np.zeros((0, 3)),
            yaw_world=np.zeros(0),
            velocity_world=np.zeros((0, 3)),
            status=np.zeros(0, np.uint8),
            instance_id=np.zeros(0, np.uint16),
            num_lidar_points=np.zeros(0, np.int32),
        )

    @classmethod
    def concatenate(cls, parts: Sequence[Boxes]) -> Boxes:
        """All boxes of ``parts`` in order as one :class:`Boxes` (empty if there are none)."""
        if not parts:
            return cls.empty()
        arrays = [f.name for f in fields(cls) if f.name != "track_id"]
        return cls(
            track_id=[t for b in parts for t in b.track_id],
            **{name: np.concatenate([getattr(b, name) for b in parts]) for name in arrays},
        )

    def select(self, index: NDArray[np.bool_] | NDArray[np.integer]) -> Boxes:
        """The subset of boxes given by a boolean mask or an index array."""
        idx = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, dtype=np.int64)
        return Boxes(
            track_id=[self.track_id[i] for i in idx],
            class_id=self.class_id[idx],
            center_world=self.center_world[idx],
            size_lwh=self.size_lwh[idx],
            yaw_world=self.yaw_world[idx],
            velocity_world=self.velocity_world[idx],
            status=self.status[idx],
            instance_id=self.instance_id[idx],
            num_lidar_points=self.num_lidar_points[idx],
            acceleration_world=self.acceleration_world[idx],
            orientation_world=self.orientation_world[idx],
        )

    def corners_world(self) -> NDArray[np.float64]:
        """(M, 8, 3) corners in the world frame (Waymo corner order), tilt included."""
        rotation = geometry.quaternion_to_matrix(self.orientation_world)
        return geometry.rotated_box_corners(self.center_world, self.size_lwh, rotation)

    def status_names(self) -> list[BoxStatus]:
        return [BOX_STATUSES[s] for s in self.status]
