"""The cache's Arrow schema, declared once in typed dataclasses, and frame <-> row conversion.

One row per frame. Per-camera data is a list of structs (one per camera, in rig order), the
LiDAR sweep a struct of flat arrays, the boxes a list of structs. Every field carries metadata
(``doc``, ``unit``, ``frame``) so the files describe themselves to any Arrow reader; matrices are
row-major flat lists (``world_from_ego``: 16 values), point arrays flat x, y, z triples.

Which optional columns a cache holds is chosen by :class:`CacheContents` (from the pipeline
spec): a cache holds only what its spec asks for.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np
import pyarrow as pa

from phigenesis import taxonomy as tx
from phigenesis.data import codec
from phigenesis.data.lidar_range import LidarRangeImage, with_sweep_values
from phigenesis.data.rangeview import RangeViewLayout, ViewPlacement
from phigenesis.data.records import (
    BOX_STATUSES,
    Boxes,
    CameraCalibration,
    CameraDepth,
    CameraFlow,
    CameraImage,
    CameraLabels,
    CameraSemantics,
    CameraTruth,
    Frame,
    LidarSweep,
)
from phigenesis.options import ConfigError, check_options, option

SCHEMA_VERSION = 7
TruthMap = Literal["depth", "semantic", "instance", "flow"]
TRUTH_MAPS: tuple[TruthMap, ...] = get_args(TruthMap)


@dataclass(frozen=True)
class CacheContents:
    """Which optional columns a cache holds.

    Attributes:
        camera_truth: exact per-pixel truth maps to store, any of depth, semantic, instance, flow.
        lidar: store the LiDAR sweep.
        lidar_truth: store per-point truth class and instance (sources that have them).
        camera_labels: store the dataset's human per-pixel labels (Waymo panoptic), where present.
        depth: store the depth stages' sparse and dense depth with their confidences.
        pseudo_semantics: store the ``pseudo_semantics`` stage's labels, confidences and sources.
        range_view: store the ``range_view`` stage's layout and overlap map (the pixels are the
            cameras' own columns).
        scene_flow: store the ``scene_flow`` stage's per-camera flow maps, dynamic masks and
            confidences, and (with ``lidar``) each LiDAR point's flow.
        lidar_range_image: store the ``lidar_range_image`` stage's cell -> point index map (needs
            ``lidar``: range and intensity are read from the sweep through it).
    """

    camera_truth: tuple[TruthMap, ...] = option(TRUTH_MAPS)
    lidar: bool = option(True)
    lidar_truth: bool = option(True)
    camera_labels: bool = option(True)
    depth: bool = option(False)
    pseudo_semantics: bool = option(False)
    range_view: bool = option(False)
    lidar_range_image: bool = option(False)
    scene_flow: bool = option(False)

    def __post_init__(self) -> None:
        check_options(self, "CacheContents")
        if self.lidar_range_image and not self.lidar:
            raise ConfigError(
                "CacheContents: lidar_range_image = True: needs lidar = true (the range image indexes the "
                "stored sweep)"
            )

    def includes(self, group: str | None) -> bool:
        if group is None:
            return True
        if group.startswith("truth_"):
            return group.removeprefix("truth_") in self.camera_truth
        if group == "lidar_truth":
            return self.lidar and self.lidar_truth
        if group == "camera_labels":
            return self.camera_labels
        if group == "depth":
            return self.depth
        if group == "pseudo_semantics":
            return self.pseudo_semantics
        if group == "range_view":
            return self.range_view
        if group == "lidar_range_image":
            return self.lidar_range_image
        if group == "scene_flow":
            return self.scene_flow
        if group == "lidar_scene_flow":
            return self.lidar and self.scene_flow
        raise ValueError(f"unknown column group {group!r}")


def col(
    arrow_type: pa.DataType | type,
    doc: str,
    unit: str = "",
    frame: str = "",
    group: str | None = None,
    nullable: bool = False,
    repeated: bool = False,
) -> Any:
    """Declares a cache column: its Arrow type (or a nested columns class), docs, unit and frame."""
    return field(
        default=None,
        metadata={
            "arrow": arrow_type,
            "doc": doc,
            "unit": unit,
            "frame": frame,
            "group": group,
            "nullable": nullable,
            "repeated": repeated,
        },
    )


def _f64(n: int) -> pa.DataType:
    return pa.list_(pa.float64(), n)


@dataclass
class BoxColumns:
    track_id: str = col(pa.string(), "object id, stable within the scene")
    class_id: int = col(pa.uint8(), "unified taxonomy class id")
    class_name: str = col(pa.string(), "unified taxonomy class name")
    center_world: list = col(_f64(3), "box centre", "m", "world")
    size_lwh: list = col(_f64(3), "length (along heading), width, height", "m")
    yaw_world: float = col(pa.float64(), "heading about +z in [-pi, pi)", "rad", "world")
    orientation_world: list = col(
        _f64(4),
        "w, x, y, z quaternion world<-box (yaw only unless the dataset tilts boxes)",
        "",
        "world<-box",
    )
    velocity_world: list = col(_f64(3), "velocity of the box centre", "m/s", "world")
    acceleration_world: list = col(
        _f64(3), "acceleration of the box centre, NaN if unknown", "m/s^2", "world"
    )
    status: str = col(pa.string(), "annotated, interpolated or extrapolated")
    instance_id: int = col(pa.uint16(), "id in instance maps, 0 if none")
    num_lidar_points: int = col(pa.int32(), "LiDAR points on the object in this frame's sweep, -1 if unknown")


@dataclass
class CameraColumns:
    camera_name: str = col(pa.string(), "camera name in its dataset; cameras are matched by name")
    timestamp_micros: int = col(pa.int64(), "capture time", "microseconds")
    width: int = col(pa.int32(), "image width", "px")
    height: int = col(pa.int32(), "image height", "px")
    intrinsics: list = col(_f64(9), "OpenCV camera matrix K, row-major 3x3", "px")
    distortion: list = col(_f64(5), "OpenCV distortion k1, k2, p1, p2, k3")
    ego_from_camera: list = col(_f64(16), "row-major 4x4 camera pose; camera axes OpenCV", "m", "ego<-camera")
    world_from_ego: list = col(
        _f64(16), "row-major 4x4 ego pose at this image's capture time", "m", "world<-ego"
    )
    readout_direction: str = col(
        pa.string(),
        "shutter readout: global, top_to_bottom, left_to_right, bottom_to_top, right_to_left or unknown",
    )
    trigger_micros: int = col(
        pa.int64(), "when the sensor was triggered, null if unknown", "microseconds", nullable=True
    )
    shutter_micros: float = col(pa.float64(), "exposure time of each line", "microseconds")
    readout_micros: float = col(
        pa.float64(), "time from the first to the last line's readout", "microseconds"
    )
    velocity_world_mps: list = col(
        _f64(3), "ego velocity at the capture time, null if unknown", "m/s", "world", nullable=True
    )
    angular_velocity_world_radps: list = col(
        _f64(3), "ego angular velocity at the capture time, null if unknown", "rad/s", "world", nullable=True
    )
    image_format: str = col(pa.string(), "encoding of `image`: jpeg or png", nullable=True)
    image: bytes = col(pa.binary(), "the image as stored (RGB), null if the frame has none", nullable=True)
    truth_depth_png: bytes = col(
        pa.binary(),
        "exact z-depth, 16-bit map, metres = value / 256, 0 = none",
        "m/256",
        "camera",
        "truth_depth",
        True,
    )
    truth_semantic_png: bytes = col(
        pa.binary(),
        "exact class per pixel, 8-bit map, unified taxonomy, 255 = ignore",
        "",
        "",
        "truth_semantic",
        True,
    )
    truth_instance_png: bytes = col(
        pa.binary(),
        "exact instance id per pixel (boxes' instance_id), 16-bit map, 0 = none",
        "",
        "",
        "truth_instance",
        True,
    )
    truth_flow_png: bytes = col(
        pa.binary(),
        "exact world-frame velocity of the visible surface, 16-bit 3-channel map, "
        "m/s = (value - 32768) / 256",
        "m/s",
        "world",
        "truth_flow",
        True,
    )
    label_semantic_png: bytes = col(
        pa.binary(),
        "the dataset's human class labels (unified taxonomy), 8-bit map, 255 = unlabelled; null if none",
        "",
        "",
        "camera_labels",
        True,
    )
    depth_sparse_png: bytes = col(
        pa.binary(),
        "LiDAR projected at this image's time and pose (nearest visible point per pixel), z-depth, "
        "16-bit map, metres = value / 256, 0 = unknown; null if not computed",
        "m/256",
        "camera",
        "depth",
        True,
    )
    depth_sparse_confidence_png: bytes = col(
        pa.binary(),
        "confidence of depth_sparse_png, 8-bit map, value / 255, 0 where unknown",
        "1/255",
        "",
        "depth",
        True,
    )
    depth_sparse_origin_png: bytes = col(
        pa.binary(),
        "what each sparse depth came from, 8-bit map: 0 none, 1 static map, 2 rigid object model, "
        "3 non-rigid object (own sweep), 4 single sweep",
        "",
        "",
        "depth",
        True,
    )
    depth_dense_png: bytes = col(
        pa.binary(),
        "densified depth ground truth, z-depth, 16-bit map, metres = value / 256, 0 = unknown",
        "m/256",
        "camera",
        "depth",
        True,
    )
    depth_dense_confidence_png: bytes = col(
        pa.binary(),
        "confidence of depth_dense_png, 8-bit map, value / 255, 0 where unknown",
        "1/255",
        "",
        "depth",
        True,
    )
    depth_dense_origin_png: bytes = col(
        pa.binary(),
        "what each dense depth came from, 8-bit map (records.DENSE_ORIGINS): 0 none, 1 lidar (a trusted "
        "measurement kept as measured), 2 densified, 3 plane of its image segment, 4 thin vertical "
        "structure at its base's depth (3 and 4: stage complete_depth), 5 rendered from generated Gaussians "
        "(phigenesis-generate)",
        "",
        "",
        "depth",
        True,
    )
    label_instance_png: bytes = col(
        pa.binary(),
        "the dataset's human instance labels, 16-bit map, 0 = none; null if none",
        "",
        "",
        "camera_labels",
        True,
    )
    pseudo_semantic_png: bytes = col(
        pa.binary(),
        "pseudo-semantic class per pixel (segmenter refined by geometry), 8-bit map, unified taxonomy, "
        "255 = no label; null if the stage did not run",
        "",
        "",
        "pseudo_semantics",
        True,
    )
    pseudo_semantic_confidence_png: bytes = col(
        pa.binary(),
        "confidence of pseudo_semantic_png, 8-bit map, value / 255, 0 where no label",
        "1/255",
        "",
        "pseudo_semantics",
        True,
    )
    pseudo_semantic_source_png: bytes = col(
        pa.binary(),
        "where each pseudo label came from, 8-bit map: 0 none, 1 segmenter, 2 box, 3 ground plane, "
        "4 sky rule",
        "",
        "",
        "pseudo_semantics",
        True,
    )
    flow_world_mps_png: bytes = col(
        pa.binary(),
        "scene flow from the boxes' rigid motion (stage scene_flow): world-frame velocity of the surface "
        "point each pixel's dense depth gives, at this image's capture time, 0 for static points, 16-bit "
        "3-channel map, m/s = (value - 32768) / 256; null if the stage did not run",
        "m/s",
        "world",
        "scene_flow",
        True,
    )
    flow_dynamic_png: bytes = col(
        pa.binary(),
        "1 where the pixel's dense-depth point lies inside a moving box (stage scene_flow), 0 elsewhere, "
        "8-bit map",
        "",
        "",
        "scene_flow",
        True,
    )
    flow_confidence_png: bytes = col(
        pa.binary(),
        "confidence of flow_world_mps_png, 8-bit map, value / 255: the box's motion confidence on dynamic "
        "pixels, 1 on static pixels with a depth, 0 where the depth (so the flow) is unknown",
        "1/255",
        "",
        "scene_flow",
        True,
    )
    boxes: list = col(
        BoxColumns,
        "3D boxes at this image's timestamp_micros (the interpolate_boxes stage: nuScenes' staggered "
        "cameras); null where no stage made them (use the frame's boxes)",
        nullable=True,
        repeated=True,
    )


@dataclass
class LidarColumns:
    timestamp_micros: int = col(
        pa.int64(), "sweep reference time; points are in the ego frame at this time", "microseconds"
    )
    world_from_ego: list = col(_f64(16), "row-major 4x4 ego pose at timestamp_micros", "m", "world<-ego")
    points_ego: list = col(pa.list_(pa.float32()), "flat x, y, z of N points", "m", "ego")
    intensity: list = col(pa.list_(pa.float32()), "return strength per point")
    beam_index: list = col(pa.list_(pa.uint16()), "laser row per point, 0 = highest beam")
    origins_ego: list = col(
        pa.list_(pa.float32()), "flat x, y, z of the sensor position per point (ray origin)", "m", "ego"
    )
    time_offset_micros: list = col(
        pa.list_(pa.int32()), "measurement time minus timestamp_micros", "microseconds"
    )
    lidar_id: list = col(pa.list_(pa.uint8()), "which LiDAR measured the point (0 = the first)")
    elongation: list = col(
        pa.list_(pa.float32()),
        "pulse elongation per point (Waymo), null if the source has none",
        nullable=True,
    )
    return_index: list = col(
        pa.list_(pa.uint8()), "0 = first (strongest) return, 1 = second; null = all first", nullable=True
    )
    truth_semantic: list = col(pa.list_(pa.uint8()), "exact class per point", "", "", "lidar_truth", True)
    truth_instance: list = col(
        pa.list_(pa.uint16()), "exact instance id per point, 0 = none", "", "", "lidar_truth", True
    )
    flow_world_mps: list = col(
        pa.list_(pa.float32()),
        "flat x, y, z velocity of each point's surface at its measurement time (stage scene_flow: its box's "
        "rigid motion, 0 for static points); null if the stage did not run",
        "m/s",
        "world",
        "lidar_scene_flow",
        True,
    )


@dataclass
class ViewPlacementColumns:
    camera_name: str = col(pa.string(), "the camera whose pixels these are")
    row0: int = col(pa.int32(), "range-view row of the view's pixel row 0", "px")
    col0: int = col(pa.int32(), "range-view column of the view's pixel column 0", "px")
    height: int = col(pa.int32(), "view height (its image's)", "px")
    width: int = col(pa.int32(), "view width (its image's)", "px")
    axis_azimuth_rad: float = col(pa.float64(), "optical axis azimuth, [-pi, pi), 0 = forward", "rad", "ego")
    azimuth_min_rad: float = col(pa.float64(), "least azimuth of the view's rays (unwrapped)", "rad", "ego")
    azimuth_max_rad: float = col(pa.float64(), "largest azimuth of the view's rays (unwrapped)", "rad", "ego")


@dataclass
class RangeViewColumns:
    height: int = col(pa.int32(), "range-view height: max(row0 + height) of the views", "px")
    width: int = col(pa.int32(), "range-view width: the sum of the views' widths", "px")
    views: list = col(
        ViewPlacementColumns,
        "one entry per view, left to right (optical axis azimuth decreasing); a view's pixel (v, u) is "
        "the cell (row0 + v, col0 + u)",
        repeated=True,
    )
    owner_png: bytes = col(
        pa.binary(),
        "8-bit map (height x width): index into views of the view owning the cell's direction (optical "
        "axis nearest among the views that see it), 255 = no view",
    )
    coverage_png: bytes = col(
        pa.binary(), "8-bit map (height x width): number of views that see the cell's direction, 0 = no view"
    )


@dataclass
class LidarRangeImageColumns:
    lidar_id: int = col(pa.uint8(), "which LiDAR of the sweep")
    height: int = col(pa.int32(), "rows = beams (beam_index)")
    width: int = col(
        pa.int32(), "columns = azimuth bins; column c is centred on pi (1 - (2c + 1) / width), ego frame"
    )
    point_index: list = col(
        pa.list_(pa.int32()),
        "height x width row-major: the sweep's point in each cell (the nearest), -1 = empty; "
        "range = |point - origin| of that point",
    )
    beam_inclination_rad: list = col(
        pa.list_(pa.float32()), "elevation of each row (median of its points), NaN if none", "rad", "ego"
    )
    column_origin_ego: list = col(
        pa.list_(pa.float32()), "flat x, y, z ray origin of each column (mean), NaN if none", "m", "ego"
    )
    overflow_index: list = col(pa.list_(pa.int32()), "points that lost a cell to a nearer point")
    overflow_cell: list = col(pa.list_(pa.int32()), "their cells, row * width + column")


@dataclass
class FrameColumns:
    scene_id: str = col(pa.string(), "scene identifier, unique within the cache")
    source: str = col(pa.string(), "source dataset: synthetic, waymo or nuscenes")
    frame_index: int = col(pa.int32(), "0-based position of the frame in its scene")
    frame_timestamp_micros: int = col(pa.int64(), "frame reference time (the LiDAR sweep's)", "microseconds")
    source_timestamp_micros: int = col(
        pa.int64(), "the frame's timestamp as its dataset keys it (Waymo: start of the scan)", "microseconds"
    )
    world_from_ego: list = col(
        _f64(16), "row-major 4x4 ego pose at frame_timestamp_micros", "m", "world<-ego"
    )
    cameras: list = col(CameraColumns, "one entry per camera, in rig order", repeated=True)
    lidar: dict = col(LidarColumns, "the LiDAR sweep, null if the frame has none", group=None, nullable=True)
    boxes: list = col(BoxColumns, "3D boxes at frame_timestamp_micros", repeated=True)
    range_view: dict = col(
        RangeViewColumns,
        "layout of the camera range view (views side by side, native pixels), null if not computed",
        group="range_view",
        nullable=True,
    )
    lidar_range_image: dict = col(
        LidarRangeImageColumns,
        "the sweep as a beams x azimuth image (cell -> point index), null if the frame has no sweep",
        group="lidar_range_image",
        nullable=True,
    )


def _arrow_fields(columns_cls: type, contents: CacheContents) -> list[pa.Field]:
    out = []
    for f in dataclasses.fields(columns_cls):
        meta = f.metadata
        if not contents.includes(meta["group"]):
            continue
        if f.name == "lidar" and not contents.lidar:
            continue
        t = meta["arrow"]
        if isinstance(t, type):
            t = pa.struct(_arrow_fields(t, contents))
            if meta["repeated"]:
                t = pa.list_(t)
        md = {k: str(meta[k]) for k in ("doc", "unit", "frame") if meta[k]}
        out.append(pa.field(f.name, t, nullable=meta["nullable"] or meta["repeated"], metadata=md))
    return out


def frame_schema(
    contents: CacheContents = CacheContents(), extra_metadata: dict[str, str] | None = None
) -> pa.Schema:
    """The Arrow schema of a cache holding ``contents``."""
    meta = {"phigenesis.schema_version": str(SCHEMA_VERSION), "phigenesis.format": "one row per frame"}
    meta.update(extra_metadata or {})
    return pa.schema(_arrow_fields(FrameColumns, contents), metadata=meta)


# --------------------------------------------------------------------------------------------
# Frame -> Arrow


def _array(t: pa.DataType, values: Any) -> pa.Array:
    """An Arrow array of type ``t`` from numpy-friendly values (one entry per row), or ``values``
    itself if it is already an Arrow array."""
    if isinstance(values, pa.Array):
        return values
    if pa.types.is_fixed_size_list(t):
        mask = None
        if isinstance(values, list) and any(v is None for v in values):
            mask = pa.array([v is None for v in values])
            values = [np.zeros(t.list_size) if v is None else v for v in values]
        flat = np.ascontiguousarray(values, dtype=t.value_type.to_pandas_dtype()).reshape(-1)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat, t.value_type), t.list_size, mask=mask)
    if pa.types.is_list(t) and not pa.types.is_struct(t.value_type):
        parts = [np.asarray(v, dtype=t.value_type.to_pandas_dtype()).reshape(-1) for v in values]
        offsets = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int32)
        if not parts:
            flat = np.zeros(0, t.value_type.to_pandas_dtype())
        elif len(parts) == 1:
            flat = parts[0]  # a frame's sweep, as it is: no copy (7.5 MB a Waymo frame)
        else:
            flat = np.concatenate(parts)
        return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), pa.array(flat, t.value_type))
    return pa.array(values, t)


def _struct(
    t: pa.StructType, columns: dict[str, Any], length: int, mask: np.ndarray | None = None
) -> pa.StructArray:
    arrays = []
    for f in t:
        v = columns.get(f.name)
        arrays.append(pa.nulls(length, f.type) if v is None else _array(f.type, v))
    return pa.StructArray.from_arrays(arrays, fields=list(t), mask=None if mask is None else pa.array(mask))


def _list_of_struct(t: pa.ListType, columns: dict[str, Any], length: int) -> pa.ListArray:
    child = _struct(t.value_type, columns, length)
    return pa.ListArray.from_arrays(pa.array([0, length], pa.int32()), child)


def _box_columns(b: Boxes) -> dict[str, Any]:
    """The :class:`BoxColumns` values of ``b`` (one entry per box)."""
    return {
        "track_id": b.track_id,
        "class_id": b.class_id,
        "class_name": [tx.class_name(int(c)) for c in b.class_id],
        "center_world": b.center_world,
        "size_lwh": b.size_lwh,
        "yaw_world": b.yaw_world,
        "velocity_world": b.velocity_world,
        "acceleration_world": b.acceleration_world,
        "orientation_world": b.orientation_world,
        "status": b.status_names(),
        "instance_id": b.instance_id,
        "num_lidar_points": b.num_lidar_points,
    }


def _boxes_array(t: pa.ListType, boxes: list[Boxes | None]) -> pa.ListArray:
    """A ``list<struct>`` array of boxes with one entry per element of ``boxes`` (None: null)."""
    present = [b for b in boxes if b is not None]
    every = present[0] if len(present) == 1 else Boxes.concatenate(present)
    child = _struct(t.value_type, _box_columns(every), len(every))
    sizes = [0 if b is None else len(b) for b in boxes]
    offsets = pa.array(np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32))
    mask = pa.array([b is None for b in boxes]) if any(b is None for b in boxes) else None
    return pa.ListArray.from_arrays(offsets, child, type=t, mask=mask)


def frame_to_batch(frame: Frame, source: str, schema: pa.Schema) -> pa.RecordBatch:
    """One frame as a one-row RecordBatch of ``schema`` (encodes per-pixel maps with codec.py)."""
    cams = frame.cameras
    cam_type = schema.field("cameras").type
    cam_names = {f.name for f in cam_type.value_type}

    def png(name: str, encode: Any, maps: str, attr: str) -> list[bytes | None] | None:
        """Column ``name`` (None if not in the schema): each camera's ``c.<maps>.<attr>`` encoded."""
        if name not in cam_names:
            return None
        values = [None if getattr(c, maps) is None else getattr(getattr(c, maps), attr) for c in cams]
        return [None if v is None else encode(v) for v in values]

    cameras = {
        "camera_name": [c.name for c in cams],
        "timestamp_micros": [c.timestamp_micros for c in cams],
        "width": [c.calibration.width for c in cams],
        "height": [c.calibration.height for c in cams],
        "intrinsics": np.array([c.calibration.intrinsics for c in cams]).reshape(len(cams), 9),
        "distortion": np.array([c.calibration.distortion for c in cams]).reshape(len(cams), 5),
        "ego_from_camera": np.array([c.calibration.ego_from_camera for c in cams]).reshape(len(cams), 16),
        "world_from_ego": np.array([c.world_from_ego for c in cams]).reshape(len(cams), 16),
        "readout_direction": [c.calibration.readout_direction for c in cams],
        "trigger_micros": [c.trigger_micros for c in cams],
        "shutter_micros": [c.shutter_micros for c in cams],
        "readout_micros": [c.readout_micros for c in cams],
        "velocity_world_mps": [c.velocity_world_mps for c in cams],
        "angular_velocity_world_radps": [c.angular_velocity_world_radps for c in cams],
        "image_format": [c.image_format if c.image_bytes is not None else None for c in cams],
        "image": [c.image_bytes for c in cams],
        "truth_depth_png": png("truth_depth_png", codec.encode_depth, "truth", "depth_m"),
        "truth_semantic_png": png("truth_semantic_png", codec.encode_semantic, "truth", "semantic"),
        "truth_instance_png": png("truth_instance_png", codec.encode_instance, "truth", "instance"),
        "truth_flow_png": png("truth_flow_png", codec.encode_flow, "truth", "flow_world_mps"),
        "label_semantic_png": png("label_semantic_png", codec.encode_semantic, "labels", "semantic"),
        "label_instance_png": png("label_instance_png", codec.encode_instance, "labels", "instance"),
        "depth_sparse_png": png("depth_sparse_png", codec.encode_depth, "depth", "sparse_m"),
        "depth_sparse_confidence_png": png(
            "depth_sparse_confidence_png", codec.encode_confidence, "depth", "sparse_confidence"
        ),
        "depth_sparse_origin_png": png(
            "depth_sparse_origin_png", codec.encode_semantic, "depth", "sparse_origin"
        ),
        "depth_dense_png": png("depth_dense_png", codec.encode_depth, "depth", "dense_m"),
        "depth_dense_confidence_png": png(
            "depth_dense_confidence_png", codec.encode_confidence, "depth", "dense_confidence"
        ),
        "depth_dense_origin_png": png(
            "depth_dense_origin_png", codec.encode_semantic, "depth", "dense_origin"
        ),
        "pseudo_semantic_png": png("pseudo_semantic_png", codec.encode_semantic, "pseudo", "semantic"),
        "pseudo_semantic_confidence_png": png(
            "pseudo_semantic_confidence_png", codec.encode_confidence, "pseudo", "confidence"
        ),
        "pseudo_semantic_source_png": png(
            "pseudo_semantic_source_png", codec.encode_semantic, "pseudo", "source"
        ),
        "flow_world_mps_png": png("flow_world_mps_png", codec.encode_flow, "flow", "flow_world_mps"),
        "flow_dynamic_png": png("flow_dynamic_png", _encode_mask, "flow", "dynamic"),
        "flow_confidence_png": png("flow_confidence_png", codec.encode_confidence, "flow", "confidence"),
        "boxes": _boxes_array(cam_type.value_type.field("boxes").type, [c.boxes for c in cams]),
    }
    arrays: dict[str, pa.Array] = {
        "scene_id": pa.array([frame.scene_id], pa.string()),
        "source": pa.array([source], pa.string()),
        "frame_index": pa.array([frame.frame_index], pa.int32()),
        "frame_timestamp_micros": pa.array([frame.timestamp_micros], pa.int64()),
        "source_timestamp_micros": pa.array([frame.source_timestamp_micros], pa.int64()),
        "world_from_ego": _array(schema.field("world_from_ego").type, frame.world_from_ego.reshape(1, 16)),
        "cameras": _list_of_struct(cam_type, cameras, len(cams)),
        "boxes": _boxes_array(schema.field("boxes").type, [frame.boxes]),
    }
    if "lidar" in schema.names:
        lt = schema.field("lidar").type
        s = frame.lidar
        if s is None:
            arrays["lidar"] = _struct(lt, {}, 1, mask=np.array([True]))
        else:
            lidar = {
                "timestamp_micros": [s.timestamp_micros],
                "world_from_ego": s.world_from_ego.reshape(1, 16),
                "points_ego": [s.points_ego],
                "intensity": [s.intensity],
                "beam_index": [s.beam_index],
                "origins_ego": [s.origins_ego],
                "time_offset_micros": [s.time_offset_micros],
                "lidar_id": [s.lidar_id],
                "truth_semantic": None if s.semantic is None else [s.semantic],
                "truth_instance": None if s.instance is None else [s.instance],
                "elongation": None if s.elongation is None else [s.elongation],
                "return_index": None if s.return_index is None else [s.return_index],
                "flow_world_mps": None if s.flow_world_mps is None else [s.flow_world_mps],
            }
            arrays["lidar"] = _struct(lt, lidar, 1)
    if "range_view" in schema.names:
        arrays["range_view"] = _range_view_array(schema.field("range_view").type, frame.range_view)
    if "lidar_range_image" in schema.names:
        lri_type = schema.field("lidar_range_image").type
        arrays["lidar_range_image"] = _lidar_range_array(lri_type, frame.lidar_range_image)
    return pa.RecordBatch.from_arrays([arrays[name] for name in schema.names], schema=schema)


# --------------------------------------------------------------------------------------------
# Arrow -> Frame


def _mat(values: pa.Array, n: int, shape: tuple[int, ...]) -> np.ndarray:
    """A fixed-size-list column of ``n`` rows as a float64 array of ``(n, *shape)``."""
    return values.flatten().to_numpy(zero_copy_only=False).reshape(n, *shape)


def _fields(struct: pa.StructArray) -> dict[str, pa.Array]:
    return {f.name: a for f, a in zip(struct.type, struct.flatten(), strict=True)}


def cameras_of(batch: pa.RecordBatch, row: int = 0) -> dict[str, pa.Array]:
    """The camera struct fields of one row, as arrays with one entry per camera."""
    return _fields(batch.column("cameras").slice(row, 1).flatten())


def row_to_frame(batch: pa.RecordBatch, row: int = 0, decode_truth: bool = True) -> Frame:
    """Rebuilds the :class:`Frame` record of one row (truth maps decoded if ``decode_truth``)."""
    scalar = {
        name: batch.column(name)[row].as_py()
        for name in ("scene_id", "frame_index", "frame_timestamp_micros", "source_timestamp_micros")
    }
    world_from_ego = _mat(batch.column("world_from_ego").slice(row, 1), 1, (4, 4))[0]
    cf = cameras_of(batch, row)
    n_cam = len(cf["camera_name"])
    intr = _mat(cf["intrinsics"], n_cam, (3, 3))
    dist = _mat(cf["distortion"], n_cam, (5,))
    e_from_c = _mat(cf["ego_from_camera"], n_cam, (4, 4))
    w_from_e = _mat(cf["world_from_ego"], n_cam, (4, 4))
    names = cf["camera_name"].to_pylist()
    widths, heights = cf["width"].to_pylist(), cf["height"].to_pylist()
    times = cf["timestamp_micros"].to_pylist()
    images = cf["image"].to_pylist()
    formats = cf["image_format"].to_pylist()
    readout = cf["readout_direction"].to_pylist()
    triggers = cf["trigger_micros"].to_pylist()
    shutters, readouts = cf["shutter_micros"].to_pylist(), cf["readout_micros"].to_pylist()
    velocities = cf["velocity_world_mps"].to_pylist()
    angular = cf["angular_velocity_world_radps"].to_pylist()
    cameras = []
    for i in range(n_cam):
        cal = CameraCalibration(names[i], widths[i], heights[i], intr[i], dist[i], e_from_c[i], readout[i])
        cameras.append(
            CameraImage(
                cal,
                times[i],
                w_from_e[i],
                images[i],
                formats[i] or "jpeg",
                truth=_camera_truth(cf, i, heights[i], widths[i]) if decode_truth else None,
                labels=_camera_labels(cf, i, (heights[i], widths[i])) if decode_truth else None,
                depth=_camera_depth(cf, i, (heights[i], widths[i])) if decode_truth else None,
                pseudo=_camera_pseudo(cf, i, (heights[i], widths[i])) if decode_truth else None,
                flow=_camera_flow(cf, i, (heights[i], widths[i])) if decode_truth else None,
                trigger_micros=triggers[i],
                shutter_micros=shutters[i],
                readout_micros=readouts[i],
                velocity_world_mps=None if velocities[i] is None else np.array(velocities[i]),
                angular_velocity_world_radps=None if angular[i] is None else np.array(angular[i]),
                boxes=_camera_boxes(cf, i),
            )
        )
    lidar = None
    if "lidar" in batch.schema.names and batch.column("lidar")[row].is_valid:
        lidar = _lidar(_fields(batch.column("lidar").slice(row, 1)))
    boxes = _boxes(_fields(batch.column("boxes").slice(row, 1).flatten()))
    return Frame(
        scene_id=scalar["scene_id"],
        frame_index=scalar["frame_index"],
        timestamp_micros=scalar["frame_timestamp_micros"],
        world_from_ego=world_from_ego,
        cameras=cameras,
        lidar=lidar,
        boxes=boxes,
        source_timestamp_micros=scalar["source_timestamp_micros"],
        range_view=range_view_of(batch, row),
        lidar_range_image=None if lidar is None else lidar_range_image_of(batch, row, lidar),
    )


def _camera_boxes(cf: dict[str, pa.Array], i: int) -> Boxes | None:
    if "boxes" not in cf or not cf["boxes"][i].is_valid:
        return None
    return _boxes(_fields(cf["boxes"][i].values))


def _camera_labels(cf: dict[str, pa.Array], i: int, shape: tuple[int, int]) -> CameraLabels | None:
    if "label_semantic_png" not in cf:
        return None
    sem, inst = cf["label_semantic_png"][i].as_py(), cf["label_instance_png"][i].as_py()
    if sem is None:
        return None
    semantic = codec.decode_semantic(sem, shape=shape)
    instance = codec.decode_instance(inst, shape=shape) if inst is not None else np.zeros(shape, np.uint16)
    return CameraLabels(semantic, instance)


def _camera_depth(cf: dict[str, pa.Array], i: int, shape: tuple[int, int]) -> CameraDepth | None:
    if "depth_sparse_png" not in cf or cf["depth_sparse_png"][i].as_py() is None:
        return None

    def get(name: str, decode: Any) -> np.ndarray | None:
        data = cf[name][i].as_py()
        return None if data is None else decode(data, shape=shape)

    return CameraDepth(
        sparse_m=get("depth_sparse_png", codec.decode_depth),
        sparse_confidence=get("depth_sparse_confidence_png", codec.decode_confidence),
        sparse_origin=get("depth_sparse_origin_png", codec.decode_semantic),
        dense_m=get("depth_dense_png", codec.decode_depth),
        dense_confidence=get("depth_dense_confidence_png", codec.decode_confidence),
        dense_origin=get("depth_dense_origin_png", codec.decode_semantic),
    )


def _camera_pseudo(cf: dict[str, pa.Array], i: int, shape: tuple[int, int]) -> CameraSemantics | None:
    if "pseudo_semantic_png" not in cf or cf["pseudo_semantic_png"][i].as_py() is None:
        return None
    return CameraSemantics(
        semantic=codec.decode_semantic(cf["pseudo_semantic_png"][i].as_py(), shape=shape),
        confidence=codec.decode_confidence(cf["pseudo_semantic_confidence_png"][i].as_py(), shape=shape),
        source=codec.decode_semantic(cf["pseudo_semantic_source_png"][i].as_py(), shape=shape),
    )


def _encode_mask(mask: np.ndarray) -> bytes:
    return codec.encode_semantic(np.asarray(mask, np.uint8))


def _camera_flow(cf: dict[str, pa.Array], i: int, shape: tuple[int, int]) -> CameraFlow | None:
    """The ``scene_flow`` stage's maps of camera ``i``, or None where the cache (a cache written
    before the stage existed) or the camera has none."""
    if "flow_world_mps_png" not in cf or cf["flow_world_mps_png"][i].as_py() is None:
        return None
    return CameraFlow(
        flow_world_mps=codec.decode_flow(cf["flow_world_mps_png"][i].as_py(), shape=shape),
        dynamic=codec.decode_semantic(cf["flow_dynamic_png"][i].as_py(), shape=shape) > 0,
        confidence=codec.decode_confidence(cf["flow_confidence_png"][i].as_py(), shape=shape),
    )


def _camera_truth(cf: dict[str, pa.Array], i: int, h: int, w: int) -> CameraTruth | None:
    def get(name: str) -> bytes | None:
        return cf[name][i].as_py() if name in cf else None

    depth, sem, inst, flow = (get(f"truth_{m}_png") for m in TRUTH_MAPS)
    if depth is None and sem is None and inst is None and flow is None:
        return None
    shape = (h, w)
    return CameraTruth(
        depth_m=np.zeros(shape, np.float32) if depth is None else codec.decode_depth(depth, shape=shape),
        semantic=np.full(shape, tx.IGNORE_ID, np.uint8)
        if sem is None
        else codec.decode_semantic(sem, shape=shape),
        instance=np.zeros(shape, np.uint16) if inst is None else codec.decode_instance(inst, shape=shape),
        flow_world_mps=np.zeros((h, w, 3), np.float32)
        if flow is None
        else codec.decode_flow(flow, shape=shape),
    )


def _flat(arr: pa.Array, dtype: type) -> np.ndarray:
    return arr.flatten().to_numpy(zero_copy_only=False).astype(dtype, copy=False)


def _lidar(lf: dict[str, pa.Array]) -> LidarSweep:
    sem = lf.get("truth_semantic")
    inst = lf.get("truth_instance")
    elong, ret = lf["elongation"], lf["return_index"]
    flow = lf.get("flow_world_mps")
    return LidarSweep(
        timestamp_micros=lf["timestamp_micros"][0].as_py(),
        world_from_ego=_mat(lf["world_from_ego"], 1, (4, 4))[0],
        points_ego=_flat(lf["points_ego"], np.float32).reshape(-1, 3),
        intensity=_flat(lf["intensity"], np.float32),
        beam_index=_flat(lf["beam_index"], np.uint16),
        origins_ego=_flat(lf["origins_ego"], np.float32).reshape(-1, 3),
        time_offset_micros=_flat(lf["time_offset_micros"], np.int32),
        lidar_id=_flat(lf["lidar_id"], np.uint8),
        semantic=None if sem is None or sem.null_count else _flat(sem, np.uint8),
        instance=None if inst is None or inst.null_count else _flat(inst, np.uint16),
        elongation=None if elong.null_count else _flat(elong, np.float32),
        return_index=None if ret.null_count else _flat(ret, np.uint8),
        flow_world_mps=None if flow is None or flow.null_count else _flat(flow, np.float32).reshape(-1, 3),
    )


def _boxes(bf: dict[str, pa.Array]) -> Boxes:
    m = len(bf["track_id"])
    status_index = {s: i for i, s in enumerate(BOX_STATUSES)}
    return Boxes(
        track_id=bf["track_id"].to_pylist(),
        class_id=bf["class_id"].to_numpy(zero_copy_only=False).astype(np.uint8),
        center_world=_mat(bf["center_world"], m, (3,)),
        size_lwh=_mat(bf["size_lwh"], m, (3,)),
        yaw_world=bf["yaw_world"].to_numpy(zero_copy_only=False).astype(np.float64),
        velocity_world=_mat(bf["velocity_world"], m, (3,)),
        acceleration_world=_mat(bf["acceleration_world"], m, (3,)),
        orientation_world=_mat(bf["orientation_world"], m, (4,)),
        status=np.array([status_index[s] for s in bf["status"].to_pylist()], np.uint8),
        instance_id=bf["instance_id"].to_numpy(zero_copy_only=False).astype(np.uint16),
        num_lidar_points=bf["num_lidar_points"].to_numpy(zero_copy_only=False).astype(np.int32),
    )


# --------------------------------------------------------------------------------------------
# Range views (RangeViewColumns, LidarRangeImageColumns)

_PLACEMENT_FIELDS = [f.name for f in dataclasses.fields(ViewPlacement)]


def _range_view_array(t: pa.StructType, layout: RangeViewLayout | None) -> pa.StructArray:
    if layout is None:
        return _struct(t, {}, 1, mask=np.array([True]))
    placements = {name: [getattr(p, name) for p in layout.views] for name in _PLACEMENT_FIELDS}
    columns = {
        "height": [layout.height],
        "width": [layout.width],
        "views": _list_of_struct(t.field("views").type, placements, len(layout.views)),
        "owner_png": [codec.encode_semantic(layout.owner)],
        "coverage_png": [codec.encode_semantic(layout.coverage)],
    }
    return _struct(t, columns, 1)


def range_view_of(batch: pa.RecordBatch, row: int = 0) -> RangeViewLayout | None:
    """The range-view layout of one row, or None if the cache or the row has none."""
    if "range_view" not in batch.schema.names or not batch.column("range_view")[row].is_valid:
        return None
    rf = _fields(batch.column("range_view").slice(row, 1))
    vf = _fields(rf["views"].flatten())
    views = tuple(
        ViewPlacement(**dict(zip(_PLACEMENT_FIELDS, values, strict=True)))
        for values in zip(*(vf[name].to_pylist() for name in _PLACEMENT_FIELDS), strict=True)
    )
    height, width = rf["height"][0].as_py(), rf["width"][0].as_py()
    return RangeViewLayout(
        height=height,
        width=width,
        views=views,
        owner=codec.decode_semantic(rf["owner_png"][0].as_py(), shape=(height, width)),
        coverage=codec.decode_semantic(rf["coverage_png"][0].as_py(), shape=(height, width)),
    )


def _lidar_range_array(t: pa.StructType, image: LidarRangeImage | None) -> pa.StructArray:
    if image is None:
        return _struct(t, {}, 1, mask=np.array([True]))
    columns = {
        "lidar_id": [image.lidar_id],
        "height": [image.height],
        "width": [image.width],
        "point_index": [image.point_index],
        "beam_inclination_rad": [image.beam_inclination_rad],
        "column_origin_ego": [image.column_origin_ego],
        "overflow_index": [image.overflow_index],
        "overflow_cell": [image.overflow_cell],
    }
    return _struct(t, columns, 1)


def lidar_range_image_of(batch: pa.RecordBatch, row: int, sweep: LidarSweep) -> LidarRangeImage | None:
    """The LiDAR range image of one row (range and intensity read from ``sweep``, the row's own
    sweep), or None if the cache or the row has none."""
    if "lidar_range_image" not in batch.schema.names or not batch.column("lidar_range_image")[row].is_valid:
        return None
    lf = _fields(batch.column("lidar_range_image").slice(row, 1))
    h, w = lf["height"][0].as_py(), lf["width"][0].as_py()
    return with_sweep_values(
        sweep,
        point_index=_flat(lf["point_index"], np.int32).reshape(h, w),
        beam_inclination_rad=_flat(lf["beam_inclination_rad"], np.float32),
        column_origin_ego=_flat(lf["column_origin_ego"], np.float32).reshape(w, 3),
        overflow_index=_flat(lf["overflow_index"], np.int32),
        overflow_cell=_flat(lf["overflow_cell"], np.int32),
        lidar_id=lf["lidar_id"][0].as_py(),
    )


def lidar_of(batch: pa.RecordBatch, row: int = 0) -> LidarSweep | None:
    """The LiDAR sweep of one row, or None if the cache or the row has none."""
    if "lidar" not in batch.schema.names or not batch.column("lidar")[row].is_valid:
        return None
    return _lidar(_fields(batch.column("lidar").slice(row, 1)))
