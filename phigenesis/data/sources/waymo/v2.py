"""Waymo Open Dataset v2 (Parquet) reader, with pyarrow only (the writer: :mod:`.v2_writer`).

Layout: ``{root}/{component_tag}/{segment_context_name}.parquet``. Key columns are ``key.<field>``,
data columns ``[ComponentClass].<path>`` (the components of
https://github.com/waymo-research/waymo-open-dataset, ``src/waymo_open_dataset/v2/``). Frames read
into and write from the records of :mod:`.raw`, which keep Waymo's own frames and units: 4x4 float64
``target_from_source`` transforms, ``global`` = Waymo's world frame, ``vehicle`` = Waymo's ego
frame, metres, radians, seconds since the epoch for camera times and microseconds for frame
timestamps.

Reading is frame by frame: :class:`V2Segment` indexes the timestamp column of each component once
(which file rows hold each frame), then decodes each component a frame's rows at a time
(``ParquetFile.iter_batches``), so memory holds about one frame, not a row group (10 frames of
range images are 244 MiB in Arrow), and a pass in file order decodes each row once. Real files
differ from the declared schema; the reader accepts float32 or float64 transforms (fixed-size or
plain lists) and camera / LiDAR names stored as integer codes or as strings such as ``"FRONT"``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numpy.typing import NDArray

from phigenesis.data.records import InvalidRecord, check_transform
from phigenesis.data.sources.waymo.raw import (
    CAMERA_CODES,
    CAMERA_NAMES,
    LASER_CODES,
    LASER_NAMES,
    FrameKey,
    RawCameraCalibration,
    RawCameraImage,
    RawFrame,
    RawLabels,
    RawLaser,
    RawLaserCalibration,
    RawProjectedBoxes,
    WaymoFormatError,
)
from phigenesis.data.sources.waymo.v2_columns import (
    _column,
    _ColumnError,
    _floats,
    _ints,
    _list_values,
    _name_codes,
    _range_images,
    _transforms,
)
from phigenesis.data.sources.waymo.v2_schema import (
    _CAM,
    _INTRINSICS,
    _LASER,
    _MAPPING,
    _OBJ,
    _R,
    _READ_BUFFER_BYTES,
    _STATIC,
    _TS,
    _XYZ,
    FRAMES_PER_ROW_GROUP,  # noqa: F401  (re-exported)
    V2_COMPONENTS,
    _c,
    _read_columns,
)
from phigenesis.data.sources.waymo.v2_writer import write_v2  # noqa: F401  (re-exported)


def is_v2_root(path: Path) -> bool:
    """Whether ``path`` is a directory holding a ``vehicle_pose/`` component folder."""
    path = Path(path)
    return path.is_dir() and (path / "vehicle_pose").is_dir()


def _check_root(root: Path) -> list[str]:
    """The component tags present in ``root``; raises if the root or a required folder is missing."""
    if not root.is_dir():
        raise WaymoFormatError(f"{root}: Waymo v2 root does not exist or is not a directory")
    present = [tag for tag in V2_COMPONENTS if (root / tag).is_dir()]
    if not present:
        raise WaymoFormatError(
            f"{root}: no Waymo v2 component folders (expected some of {', '.join(V2_COMPONENTS)})"
        )
    # lidar_box too: without it a segment would convert with no boxes, silently.
    required = ["vehicle_pose", "camera_calibration", "lidar_box"]
    if "lidar" in present:
        required += ["lidar_calibration", "lidar_pose"]
    for tag in required:
        if tag not in present:
            raise WaymoFormatError(f"{root}: required component folder {tag}/ is missing")
    return present


def list_segments(root: Path) -> list[str]:
    """Sorted segment context names of a v2 root (the file stems in ``vehicle_pose/``)."""
    root = Path(root)
    _check_root(root)
    return sorted(p.stem for p in (root / "vehicle_pose").glob("*.parquet"))


class _RowStream:
    """The rows of a component file in file order from the start of one row group on, decoded
    a few at a time (``ParquetFile.iter_batches`` of ``batch_rows`` rows, one row group after the
    other), so only the batch in hand is in memory."""

    def __init__(self, file: _ComponentFile, group: int) -> None:
        self.file = file
        self.group = group
        #: File row number of the first row of ``pending``.
        self.position = int(file.group_starts[group])
        self.pending: pa.RecordBatch | None = None
        self._batches = self._decode(group)

    def _decode(self, first_group: int) -> Iterator[pa.RecordBatch]:
        f = self.file
        for group in range(first_group, f.num_row_groups):
            self.group = group
            f.reads[(f.tag, group)] += 1
            yield from f.file.iter_batches(
                batch_size=f.batch_rows, row_groups=[group], columns=f.columns, use_threads=False
            )

    def take(self, positions: NDArray[np.int64]) -> list[pa.RecordBatch]:
        """The rows at file row numbers ``positions`` (increasing, none before :attr:`position`),
        in file order; the stream moves on to the row after the last of them."""
        parts: list[pa.RecordBatch] = []
        end = int(positions[-1]) + 1
        while self.position < end:
            if self.pending is None or self.pending.num_rows == 0:
                self.pending = next(self._batches, None)
                if self.pending is None:
                    raise pa.ArrowInvalid(f"the file ends at row {self.position}, before row {end - 1}")
            stop = min(self.position + self.pending.num_rows, end)
            lo, hi = np.searchsorted(positions, [self.position, stop])
            if hi > lo:
                wanted = positions[lo:hi] - self.position
                if wanted[-1] - wanted[0] + 1 == len(wanted):  # contiguous: a slice, no copy
                    parts.append(self.pending.slice(int(wanted[0]), len(wanted)))
                else:
                    parts.append(self.pending.take(pa.array(wanted)))
            rest = self.pending.num_rows - (stop - self.position)
            # Drop a used-up batch at once: even an empty slice of it would keep its memory.
            self.pending = self.pending.slice(stop - self.position) if rest else None
            self.position = stop
        return parts


class _ComponentFile:
    """One component file of one segment: where each frame's rows are, and a stream that decodes
    the rows a frame at a time."""

    def __init__(self, tag: str, path: Path, reads: Counter[tuple[str, int]]) -> None:
        self.tag, self.path, self.reads = tag, path, reads
        try:
            # No pre-buffering and a small read buffer: a column chunk is read as it is decoded,
            # not all at once (a LiDAR row group's range images are tens of MB even compressed).
            self.file = pq.ParquetFile(path, pre_buffer=False, buffer_size=_READ_BUFFER_BYTES)
        except (pa.ArrowException, OSError) as e:
            raise WaymoFormatError(f"{path}: not a readable Parquet file ({e})") from e
        names = set(self.file.schema_arrow.names)
        required, optional = _read_columns(tag)
        missing = [c for c in required if c not in names]
        if missing:
            raise WaymoFormatError(f"{path}: {tag} is missing column(s) {', '.join(missing)}")
        self.columns = required + [c for c in optional if c in names]
        meta = self.file.metadata
        #: File row number where each row group starts, then the file's number of rows.
        self.group_starts = np.cumsum([0] + [meta.row_group(g).num_rows for g in range(meta.num_row_groups)])
        self.index: dict[int, NDArray[np.int64]] = {} if tag in _STATIC else self._index_frames()
        #: Rows per decoded batch: a frame's rows on average (5 per frame for the sensor components).
        self.batch_rows = max(1, -(-meta.num_rows // max(1, len(self.index))))
        self._stream: _RowStream | None = None

    @property
    def num_row_groups(self) -> int:
        return self.file.metadata.num_row_groups

    def _index_frames(self) -> dict[int, NDArray[np.int64]]:
        """Frame timestamp (us) -> the file row numbers of its rows, from the key column alone."""
        column = self._read(lambda: self.file.read(columns=[_TS])).column(_TS)
        if column.null_count:
            raise WaymoFormatError(f"{self.path}: column {_TS} has null entries")
        if not pa.types.is_integer(column.type):
            raise WaymoFormatError(f"{self.path}: column {_TS} is {column.type}, not integer microseconds")
        ts = column.to_numpy().astype(np.int64)
        order = np.argsort(ts, kind="stable")  # stable: each frame's row numbers stay increasing
        keys, starts = np.unique(ts[order], return_index=True)
        if not len(keys):
            return {}
        return dict(zip(keys.tolist(), np.split(order.astype(np.int64), starts[1:]), strict=True))

    def _read(self, fn: Callable[[], _R]) -> _R:
        try:
            return fn()
        except (pa.ArrowException, OSError) as e:
            raise WaymoFormatError(f"{self.path}: cannot read {self.tag} ({e})") from e

    def _group_of(self, row: int) -> int:
        return int(np.searchsorted(self.group_starts, row, side="right")) - 1

    def rows(self, timestamp: int) -> pa.Table:
        """The rows of frame ``timestamp`` (only the used columns), in file order.

        Read from the file's stream: frames asked for in file order decode each row once; a frame
        behind the stream (or row groups ahead of it) restarts it at the frame's row group.
        """
        positions = self.index.get(timestamp)
        if positions is None:
            return self.file.schema_arrow.empty_table().select(self.columns)
        first = int(positions[0])
        stream = self._stream
        if stream is None or stream.position > first or self._group_of(first) > stream.group:
            stream = self._stream = _RowStream(self, self._group_of(first))
        try:
            parts = stream.take(positions)
        except (pa.ArrowException, OSError) as e:
            self._stream = None
            raise WaymoFormatError(f"{self.path}: cannot read {self.tag} ({e})") from e
        return pa.Table.from_batches(parts)

    def all_rows(self) -> pa.Table:
        """Every row (for the per-segment components: calibrations, the vehicle poses)."""
        tables = []
        for group in range(self.num_row_groups):
            tables.append(self._read(lambda g=group: self.file.read_row_group(g, columns=self.columns)))
            self.reads[(self.tag, group)] += 1
        if not tables:
            return self.file.schema_arrow.empty_table().select(self.columns)
        return pa.concat_tables(tables)


class V2Segment:
    """One segment of a Waymo v2 root, read frame by frame.

    Construction checks the root and the segment's component files (existence, Parquet footer,
    expected columns) and indexes the frame timestamps; :meth:`frame_keys` reads every frame's
    pose (the vehicle_pose component, once) and :meth:`frame` then decodes the rows of one frame
    from each component's stream. ``row_group_reads`` counts how often each row group was started
    (read whole, or streamed from its first row), keyed by (component tag, group).

    Errors name the component file and the frame timestamp (and the row's camera, LiDAR or
    object); a value that only spoils one camera's or one LiDAR's data is put in the raw frame's
    ``invalid_sensors`` for the conversion's error policy.
    """

    def __init__(self, root: Path, segment: str) -> None:
        self.root, self.segment = Path(root), segment
        self.row_group_reads: Counter[tuple[str, int]] = Counter()
        self.files: dict[str, _ComponentFile] = {}
        for tag in _check_root(self.root):
            path = self.root / tag / f"{segment}.parquet"
            if not path.is_file():
                raise WaymoFormatError(f"segment {segment}: component {tag} has no file (expected {path})")
            self.files[tag] = _ComponentFile(tag, path, self.row_group_reads)
        self.timestamps: list[int] = sorted(self.files["vehicle_pose"].index)
        self._poses: dict[int, NDArray[np.float64]] | None = None
        self._camera_calibrations: list[RawCameraCalibration] | None = None
        self._laser_calibrations: list[RawLaserCalibration] | None = None

    def __len__(self) -> int:
        return len(self.timestamps)

    def frame_keys(self) -> list[tuple[str, FrameKey | WaymoFormatError]]:
        """(where, :class:`~.raw.FrameKey` or the error that makes the frame unusable) for every
        frame timestamp in order: a timestamp with two vehicle_pose rows, or a pose that is not a
        rigid transform, is unusable. Raises if vehicle_pose has no rows."""
        file = self.files["vehicle_pose"]
        if not self.timestamps:
            raise WaymoFormatError(f"{file.path}: vehicle_pose has no rows: the segment has no frames")
        table = file.all_rows()
        ts = table.column(_TS).to_numpy().astype(np.int64)
        poses = _transforms(table, _c("vehicle_pose", "world_from_vehicle.transform"), file.path)
        rows: dict[int, list[int]] = {}
        for row, t in enumerate(ts.tolist()):
            rows.setdefault(t, []).append(row)
        out: list[tuple[str, FrameKey | WaymoFormatError]] = []
        self._poses = {}
        for t in self.timestamps:
            where = f"{file.path} frame {t}"
            if len(rows[t]) > 1:
                out.append(
                    (where, WaymoFormatError(f"{where}: rows {rows[t]} are all this frame's vehicle pose"))
                )
                continue
            try:
                pose = check_transform("world_from_vehicle", poses[rows[t][0]])
            except InvalidRecord as e:
                out.append((where, WaymoFormatError(f"{where} (row {rows[t][0]}): {e}")))
                continue
            self._poses[t] = pose
            out.append((where, FrameKey(t, pose)))
        return out

    def frame(self, index: int) -> RawFrame:
        """Frame ``index`` (in timestamp order) with every component of the root joined on its key."""
        ts = self.timestamps[index]
        if self._poses is None:
            self.frame_keys()
        assert self._poses is not None
        if ts not in self._poses:
            raise WaymoFormatError(
                f"{self.files['vehicle_pose'].path} frame {ts}: the frame's vehicle pose is invalid"
            )
        raw = RawFrame(
            segment=self.segment,
            timestamp_micros=ts,
            global_from_vehicle=self._poses[ts],
            camera_calibrations=self.camera_calibrations(),
            laser_calibrations=self.laser_calibrations(),
            images=[],
            lasers=[],
            labels=RawLabels.empty(),
            where=f"{self.root} segment {self.segment} frame {ts}",
            part_where={
                part: f"{self.files[tag].path} frame {ts}"
                for part, tag in (("camera", "camera_image"), ("laser", "lidar"), ("labels", "lidar_box"))
                if tag in self.files
            },
        )
        _mark_repeated(
            raw, raw.camera_calibrations, "camera_calibration", self.files["camera_calibration"].path
        )
        if "lidar_calibration" in self.files:
            _mark_repeated(
                raw, raw.laser_calibrations, "laser_calibration", self.files["lidar_calibration"].path
            )
        raw.images = self._images(ts, raw)
        raw.lasers = self._lasers(ts, raw)
        raw.labels = self._labels(ts)
        raw.projected_boxes = self._projected_boxes(ts)
        raw.stats = self._stats(ts)
        return raw

    def camera_calibrations(self) -> list[RawCameraCalibration]:
        """The segment's camera calibrations, sorted by camera code (read once)."""
        if self._camera_calibrations is None:
            file = self.files["camera_calibration"]
            self._camera_calibrations = _naming(file, None, lambda: _read_camera_calibrations(file))
        return self._camera_calibrations

    def laser_calibrations(self) -> list[RawLaserCalibration]:
        """The segment's LiDAR calibrations, sorted by laser code (read once; [] if absent)."""
        if self._laser_calibrations is None:
            cal = self.files.get("lidar_calibration")
            self._laser_calibrations = (
                [] if cal is None else _naming(cal, None, lambda: _read_laser_calibrations(cal))
            )
        return self._laser_calibrations

    def _images(self, ts: int, raw: RawFrame) -> list[RawCameraImage]:
        file = self.files.get("camera_image")
        if file is None:
            return []
        images = _naming(file, ts, lambda: _read_images(file, file.rows(ts)))
        calibrated = {c.name for c in self.camera_calibrations()}
        for image in images:
            if image.name not in calibrated:
                raw.mark_invalid(
                    "camera",
                    image.name,
                    WaymoFormatError(
                        f"{file.path} frame {ts}: camera {CAMERA_NAMES.get(image.name, image.name)} of "
                        f"segment {self.segment} has an image but no camera_calibration row"
                    ),
                )
        seg = self.files.get("camera_segmentation")
        if seg is not None:
            _naming(
                seg, ts, lambda: _attach_panoptic(images, seg, seg.rows(ts), f"{seg.path} frame {ts}", raw)
            )
        return sorted(images, key=lambda im: im.name)

    def _lasers(self, ts: int, raw: RawFrame) -> list[RawLaser]:
        file = self.files.get("lidar")
        if file is None:
            return []
        lasers = _naming(file, ts, lambda: _read_lasers(file, file.rows(ts), raw))
        pose_file = self.files["lidar_pose"]
        poses = _naming(pose_file, ts, lambda: _read_pixel_poses(pose_file, pose_file.rows(ts), raw))
        for laser in lasers:
            laser.pixel_pose = poses.get(laser.name)
        return sorted(lasers, key=lambda la: la.name)

    def _labels(self, ts: int) -> RawLabels:
        file = self.files.get("lidar_box")
        return RawLabels.empty() if file is None else _naming(file, ts, lambda: _read_labels(file.rows(ts)))

    def _projected_boxes(self, ts: int) -> RawProjectedBoxes:
        file = self.files.get("projected_lidar_box")
        if file is None:
            return RawProjectedBoxes.empty()
        return _naming(file, ts, lambda: _read_projected(file, file.rows(ts)))

    def _stats(self, ts: int) -> dict[str, str]:
        file = self.files.get("stats")
        if file is None:
            return {}
        table = file.rows(ts)
        if table.num_rows == 0:
            return {}
        stats = {}
        for key in ("time_of_day", "location", "weather"):
            name = _c("stats", key)
            value = table.column(name)[0].as_py() if name in table.column_names else None
            if value is not None:
                stats[key] = str(value)
        return stats


def _mark_repeated(raw: RawFrame, calibrations: list[Any], part: str, path: Path) -> None:
    """Marks every sensor with more than one calibration row invalid in ``raw``."""
    seen: set[int] = set()
    for c in calibrations:
        if c.name in seen:
            raw.mark_invalid(
                part, c.name, WaymoFormatError(f"{path}: sensor code {c.name} has two {part} rows")
            )
        seen.add(c.name)


def _naming(file: _ComponentFile, ts: int | None, read: Callable[[], _R]) -> _R:
    """``read()``, with a column value it cannot use reported as a :class:`WaymoFormatError`
    naming the component file and the frame (``ts``; None for the per-segment components)."""
    try:
        return read()
    except _ColumnError as e:
        where = f"{file.path}" if ts is None else f"{file.path} frame {ts}"
        raise WaymoFormatError(f"{where}: {e}") from None


def _read_camera_calibrations(file: _ComponentFile) -> list[RawCameraCalibration]:
    t, tag = file.all_rows(), "camera_calibration"
    names = _name_codes(t, _CAM, CAMERA_CODES, file.path)
    intrinsics = np.stack([_floats(t, _c(tag, f"intrinsic.{k}")) for k in _INTRINSICS], axis=1)
    extrinsics = _transforms(t, _c(tag, "extrinsic.transform"), file.path)
    width, height = _ints(t, _c(tag, "width")), _ints(t, _c(tag, "height"))
    readout = _ints(t, _c(tag, "rolling_shutter_direction"), 0)
    cals = [
        RawCameraCalibration(
            int(names[i]), intrinsics[i], extrinsics[i], int(width[i]), int(height[i]), int(readout[i])
        )
        for i in range(t.num_rows)
    ]
    return sorted(cals, key=lambda c: c.name)


def _read_laser_calibrations(file: _ComponentFile) -> list[RawLaserCalibration]:
    t, tag = file.all_rows(), "lidar_calibration"
    names = _name_codes(t, _LASER, LASER_CODES, file.path)
    extrinsics = _transforms(t, _c(tag, "extrinsic.transform"), file.path)
    lo, hi = _floats(t, _c(tag, "beam_inclination.min")), _floats(t, _c(tag, "beam_inclination.max"))
    values = _list_values(t, _c(tag, "beam_inclination.values"), pa.float64())
    cals = [
        RawLaserCalibration(
            int(names[i]),
            extrinsics[i],
            None if v is None or v.size == 0 else v.astype(np.float64),
            float(lo[i]),
            float(hi[i]),
        )
        for i, v in enumerate(values)
    ]
    return sorted(cals, key=lambda c: c.name)


def _bytes_column(table: pa.Table, name: str) -> list[bytes | None]:
    """Binary column ``name`` as bytes per row (None for nulls)."""
    col = _column(table, name)
    if not (pa.types.is_binary(col.type) or pa.types.is_large_binary(col.type)):
        raise _ColumnError(f"column {name} is {col.type}, not binary")
    return col.to_pylist()


def _read_images(file: _ComponentFile, t: pa.Table) -> list[RawCameraImage]:
    tag = "camera_image"
    names = _name_codes(t, _CAM, CAMERA_CODES, file.path)
    jpegs = _bytes_column(t, _c(tag, "image"))
    poses = _transforms(t, _c(tag, "pose.transform"), file.path)
    lin = np.stack([_floats(t, _c(tag, f"velocity.linear_velocity.{a}")) for a in _XYZ], axis=1)
    ang = np.stack([_floats(t, _c(tag, f"velocity.angular_velocity.{a}")) for a in _XYZ], axis=1)
    pose_ts = _floats(t, _c(tag, "pose_timestamp"))
    shutter, trigger, readout = (
        _floats(t, _c(tag, f"rolling_shutter_params.{k}"))
        for k in ("shutter", "camera_trigger_time", "camera_readout_done_time")
    )
    return [
        RawCameraImage(
            name=int(names[i]),
            jpeg=jpegs[i],
            global_from_vehicle=poses[i],
            velocity_linear=lin[i],
            velocity_angular=ang[i],
            pose_timestamp=float(pose_ts[i]),
            shutter=float(shutter[i]),
            trigger_time=float(trigger[i]),
            readout_done_time=float(readout[i]),
        )
        for i in range(t.num_rows)
    ]


def _attach_panoptic(
    images: list[RawCameraImage], file: _ComponentFile, t: pa.Table, where: str, raw: RawFrame
) -> None:
    """Sets the panoptic label fields of ``images`` from the camera_segmentation rows ``t``; a
    camera whose label rows are inconsistent is marked invalid in ``raw``."""
    tag = "camera_segmentation"
    names = _name_codes(t, _CAM, CAMERA_CODES, file.path)
    labels = _bytes_column(t, _c(tag, "panoptic_label"))
    divisors = _ints(t, _c(tag, "panoptic_label_divisor"), 0)
    local = _list_values(t, _c(tag, f"{_MAPPING}.local_instance_ids"), pa.int64())
    glob = _list_values(t, _c(tag, f"{_MAPPING}.global_instance_ids"), pa.int64())
    rows: dict[int, list[int]] = {}
    for i, n in enumerate(names.tolist()):
        rows.setdefault(int(n), []).append(i)
    for image in images:
        found = rows.get(image.name, [])
        camera = f"{where}: camera {CAMERA_NAMES.get(image.name, image.name)} panoptic label"
        if len(found) > 1:
            raw.mark_invalid("camera", image.name, WaymoFormatError(f"{camera}: rows {found} all label it"))
            continue
        if not found:
            continue
        i = found[0]
        image.panoptic_label = labels[i]
        image.panoptic_label_divisor = int(divisors[i])
        ids_local = [] if local[i] is None else local[i].tolist()
        ids_global = [] if glob[i] is None else glob[i].tolist()
        if len(ids_local) != len(ids_global):
            error = WaymoFormatError(
                f"{camera}: {_MAPPING} has {len(ids_local)} local, {len(ids_global)} global ids"
            )
            raw.mark_invalid("camera", image.name, error)
            continue
        image.instance_to_global = dict(zip(ids_local, ids_global, strict=True))


def _by_laser(
    file: _ComponentFile, t: pa.Table, columns: list[list[Any]], raw: RawFrame
) -> dict[int, list[Any]]:
    """Per laser code, its row's values of ``columns`` (one list per column, one value per row);
    a laser with two rows, or a value that is an error, marks that laser invalid in ``raw``."""
    names = _name_codes(t, _LASER, LASER_CODES, file.path)
    out: dict[int, list[Any]] = {}
    for row, code in enumerate(names.tolist()):
        values = [col[row] for col in columns]
        if code in out:
            error = WaymoFormatError(
                f"{file.path} frame {raw.timestamp_micros}: LiDAR {LASER_NAMES.get(code, code)} has two rows"
            )
            raw.mark_invalid("laser", code, error)
            continue
        errors = [v for v in values if isinstance(v, WaymoFormatError)]
        if errors:
            raw.mark_invalid("laser", code, errors[0])
            values = [None if isinstance(v, WaymoFormatError) else v for v in values]
        out[code] = values
    return out


def _read_lasers(file: _ComponentFile, t: pa.Table, raw: RawFrame) -> list[RawLaser]:
    r1 = _range_images(t, "lidar", 1, 4, file.path)
    r2 = _range_images(t, "lidar", 2, 4, file.path)
    return [RawLaser(code, a, b) for code, (a, b) in _by_laser(file, t, [r1, r2], raw).items()]


def _read_pixel_poses(
    file: _ComponentFile, t: pa.Table, raw: RawFrame
) -> dict[int, NDArray[np.float32] | None]:
    poses = _range_images(t, "lidar_pose", 1, 6, file.path)
    return {code: p for code, (p,) in _by_laser(file, t, [poses], raw).items()}


def _read_labels(t: pa.Table) -> RawLabels:
    tag = "lidar_box"
    box = np.stack(
        [_floats(t, _c(tag, f"box.center.{a}")) for a in _XYZ]
        + [_floats(t, _c(tag, f"box.size.{a}")) for a in _XYZ]
        + [_floats(t, _c(tag, "box.heading"))],
        axis=1,
    ).reshape(-1, 7)
    speed = np.stack([_floats(t, _c(tag, f"speed.{a}"), 0.0) for a in _XYZ], axis=1).reshape(-1, 3)
    accel = np.stack([_floats(t, _c(tag, f"acceleration.{a}"), 0.0) for a in _XYZ], axis=1).reshape(-1, 3)
    return RawLabels(
        ids=[str(x) for x in _column(t, _OBJ).to_pylist()],
        types=_ints(t, _c(tag, "type"), 0).astype(np.int32),
        box=box,
        speed=speed,
        accel=accel,
        num_lidar_points=_ints(t, _c(tag, "num_lidar_points_in_box")).astype(np.int32),
        num_top_lidar_points=_ints(t, _c(tag, "num_top_lidar_points_in_box")).astype(np.int32),
    )


def _read_projected(file: _ComponentFile, t: pa.Table) -> RawProjectedBoxes:
    tag = "projected_lidar_box"
    box = np.stack(
        [_floats(t, _c(tag, f"box.{p}.{a}")) for p in ("center", "size") for a in ("x", "y")], axis=1
    ).reshape(-1, 4)
    return RawProjectedBoxes(
        camera=_name_codes(t, _CAM, CAMERA_CODES, file.path),
        ids=[str(x) for x in _column(t, _OBJ).to_pylist()],
        box=box,
        types=_ints(t, _c(tag, "type"), 0).astype(np.int32),
    )
