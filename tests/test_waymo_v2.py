"""Waymo v2 Parquet: write_v2 -> V2Segment round trips, real-file quirks, errors and row-group reads."""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from phigenesis.data.sources.waymo.raw import (
    RawCameraCalibration,
    RawCameraImage,
    RawFrame,
    RawLabels,
    RawLaser,
    RawLaserCalibration,
    RawProjectedBoxes,
    WaymoFormatError,
)
from phigenesis.data.sources.waymo.v2 import V2Segment, is_v2_root, list_segments, write_v2

SEGMENTS = ("1005081002024129653_5313_150_5333_150", "10023947602400723454_1120_000_1140_000")
T0 = 1550083467346370
PER_FRAME = ("vehicle_pose", "camera_image", "camera_segmentation", "lidar", "lidar_pose", "lidar_box")


def _transform(rng: np.random.Generator, offset: float = 0.0) -> np.ndarray:
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    t = np.eye(4)
    t[:3, :3] = q
    t[:3, 3] = rng.standard_normal(3) * 10 + offset
    return t


def _png(rng: np.random.Generator) -> bytes:
    ok, buf = cv2.imencode(".png", rng.integers(0, 30000, (6, 8)).astype(np.uint16))
    assert ok
    return buf.tobytes()


def _calibrations(rng: np.random.Generator) -> tuple[list[RawCameraCalibration], list[RawLaserCalibration]]:
    cams = [
        RawCameraCalibration(
            name=c,
            intrinsic=np.concatenate([[2000 + c, 2001 + c, 960.5, 640.25], rng.standard_normal(5) * 0.01]),
            vehicle_from_camera=_transform(rng),
            width=1920,
            height=1280 if c <= 3 else 886,
            rolling_shutter_direction=c % 5,
        )
        for c in range(1, 6)
    ]
    lasers = [
        RawLaserCalibration(1, _transform(rng), np.sort(rng.uniform(-0.3, 0.04, 4)), -0.3, 0.04),
        RawLaserCalibration(2, _transform(rng), None, -1.57, 0.52),
    ]
    return cams, lasers


def _image(rng: np.random.Generator, cam: int, ts: int, labelled: bool) -> RawCameraImage:
    t = ts * 1e-6
    return RawCameraImage(
        name=cam,
        jpeg=b"\xff\xd8fake" + bytes([cam]) + rng.bytes(5),
        global_from_vehicle=_transform(rng, 1e4),
        velocity_linear=rng.standard_normal(3).astype(np.float32).astype(np.float64),
        velocity_angular=rng.standard_normal(3),
        pose_timestamp=t + 0.01 * cam,
        shutter=0.004 + 1e-4 * cam,
        trigger_time=t + 0.02 * cam,
        readout_done_time=t + 0.02 * cam + 0.03,
        panoptic_label=_png(rng) if labelled else None,
        panoptic_label_divisor=1000 if labelled else 0,
        instance_to_global={1: 17, 2: 4, 5: 33} if labelled else {},
    )


def _labels(rng: np.random.Generator, n: int) -> RawLabels:
    accel = rng.standard_normal((n, 3))
    accel[0, 2] = np.nan
    return RawLabels(
        ids=[f"obj{rng.integers(1 << 30)}_{i}" for i in range(n)],
        types=rng.integers(1, 5, n).astype(np.int32),
        box=rng.standard_normal((n, 7)),
        speed=rng.standard_normal((n, 3)),
        accel=accel,
        num_lidar_points=rng.integers(0, 500, n).astype(np.int32),
        num_top_lidar_points=np.array([-1, *rng.integers(0, 400, n - 1)], np.int32),
    )


def _projected(rng: np.random.Generator, labels: RawLabels) -> RawProjectedBoxes:
    return RawProjectedBoxes(
        camera=np.array([1, 3, 1], np.int32),
        ids=labels.ids[:3],
        box=rng.uniform(0, 1000, (3, 4)),
        types=labels.types[:3].copy(),
    )


def _frame(rng: np.random.Generator, segment: str, k: int, calibrations: tuple, rich: bool) -> RawFrame:
    ts = T0 + k * 100_000 + 7 * SEGMENTS.index(segment)
    cams, laser_cals = calibrations
    labels = _labels(rng, 4 + k)
    lasers = [
        RawLaser(
            1,
            rng.standard_normal((4, 16, 4)).astype(np.float32),
            rng.standard_normal((4, 16, 4)).astype(np.float32),
            rng.standard_normal((4, 16, 6)).astype(np.float32),
        ),
        RawLaser(2, rng.standard_normal((3, 8, 4)).astype(np.float32), None, None),
    ]
    return RawFrame(
        segment=segment,
        timestamp_micros=ts,
        global_from_vehicle=_transform(rng, 1e4),
        camera_calibrations=cams,
        laser_calibrations=laser_cals,
        images=[_image(rng, c, ts, labelled=k != 1 and c in (1, 3)) for c in range(1, 6)],
        lasers=lasers,
        labels=labels,
        projected_boxes=_projected(rng, labels) if rich else RawProjectedBoxes.empty(),
        stats={"time_of_day": "Day", "location": "location_sf", "weather": "sunny"} if rich else {},
    )


@pytest.fixture(scope="module")
def frames() -> list[RawFrame]:
    """2 segments x 3 frames; the first segment has projected boxes and stats, the second none."""
    rng = np.random.default_rng(11)
    out = []
    for s, segment in enumerate(SEGMENTS):
        cals = _calibrations(rng)
        out += [_frame(rng, segment, k, cals, rich=s == 0) for k in range(3)]
    return out


def _assert_same(got: Any, want: Any, where: str, transform_rtol: float = 0.0) -> None:
    """Recursive equality: arrays must match in dtype and shape and exactly in value (NaN == NaN),
    except 4x4 transforms which may differ by ``transform_rtol``."""
    if dataclasses.is_dataclass(want):
        assert type(got) is type(want), where
        for f in dataclasses.fields(want):
            if f.name not in ("where", "part_where"):
                _assert_same(getattr(got, f.name), getattr(want, f.name), f"{where}.{f.name}", transform_rtol)
    elif isinstance(want, np.ndarray):
        assert isinstance(got, np.ndarray), where
        assert got.dtype == want.dtype and got.shape == want.shape, (where, got.dtype, got.shape)
        if want.shape == (4, 4) and transform_rtol:
            np.testing.assert_allclose(got, want, rtol=transform_rtol, atol=0, err_msg=where)
        else:
            np.testing.assert_array_equal(got, want, err_msg=where)
    elif isinstance(want, (list, tuple)):
        assert len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            _assert_same(g, w, f"{where}[{i}]", transform_rtol)
    elif isinstance(want, dict):
        assert list(got) == list(want), where
        for key in want:
            _assert_same(got[key], want[key], f"{where}[{key!r}]", transform_rtol)
    else:
        assert type(got) is type(want) and got == want, (where, got, want)


def _read_all(root: Path, segment: str) -> list[RawFrame]:
    seg = V2Segment(root, segment)
    return [seg.frame(i) for i in range(len(seg))]


def _by_segment(frames: list[RawFrame], segment: str) -> list[RawFrame]:
    return sorted((f for f in frames if f.segment == segment), key=lambda f: f.timestamp_micros)


def test_round_trip_is_exact(tmp_path: Path, frames: list[RawFrame]) -> None:
    paths = write_v2(tmp_path, frames, frames_per_row_group=2)
    assert {p.parent.name for p in paths} == {
        *PER_FRAME,
        "camera_calibration",
        "lidar_calibration",
        "projected_lidar_box",
        "stats",
    }
    assert len(paths) == 10 * len(SEGMENTS) and all(p.is_file() for p in paths)
    assert not list(tmp_path.rglob("*.tmp"))
    for segment in SEGMENTS:
        want = _by_segment(frames, segment)
        seg = V2Segment(tmp_path, segment)
        assert seg.segment == segment and len(seg) == 3
        assert seg.timestamps == [f.timestamp_micros for f in want]
        got = [seg.frame(i) for i in range(len(seg))]
        _assert_same(got, want, segment)
        assert got[1].where == f"{tmp_path} segment {segment} frame {want[1].timestamp_micros}"
    first = V2Segment(tmp_path, SEGMENTS[0]).frame(0)
    assert first.stats == {"time_of_day": "Day", "location": "location_sf", "weather": "sunny"}
    assert first.lasers[1].return2 is None and first.laser_calibrations[1].beam_inclinations is None
    assert first.labels.num_top_lidar_points[0] == -1 and np.isnan(first.labels.accel[0, 2])
    assert [im.panoptic_label is not None for im in first.images] == [True, False, True, False, False]


def test_written_files_use_the_declared_schema(tmp_path: Path, frames: list[RawFrame]) -> None:
    write_v2(tmp_path, frames)
    image = pq.read_schema(tmp_path / "camera_image" / f"{SEGMENTS[0]}.parquet")
    assert image.field("key.camera_name").type == pa.int8()
    assert image.field("[CameraImageComponent].pose.transform").type == pa.list_(pa.float64(), 16)
    assert image.field("[CameraImageComponent].velocity.linear_velocity.x").type == pa.float32()
    lidar = pq.read_schema(tmp_path / "lidar" / f"{SEGMENTS[0]}.parquet")
    assert lidar.field("key.laser_name").type == pa.int8()
    assert lidar.field("[LiDARComponent].range_image_return1.shape").type == pa.list_(pa.int32(), 3)
    seg = pq.read_table(tmp_path / "camera_segmentation" / f"{SEGMENTS[0]}.parquet")
    assert seg.num_rows == 4  # cameras 1 and 3 in frames 0 and 2
    prefix = "[CameraSegmentationLabelComponent].instance_id_to_global_id_mapping"
    assert seg.column(f"{prefix}.global_instance_ids")[0].as_py() == [17, 4, 33]
    pf = pq.ParquetFile(tmp_path / "camera_image" / f"{SEGMENTS[0]}.parquet")
    assert pf.metadata.num_row_groups == 1 and pf.metadata.num_rows == 15


@pytest.mark.parametrize(("as_strings", "as_float32"), [(True, False), (False, True), (True, True)])
def test_real_file_quirks_read_back(
    tmp_path: Path, frames: list[RawFrame], as_strings: bool, as_float32: bool
) -> None:
    write_v2(tmp_path, frames, camera_names_as_strings=as_strings, transforms_float32=as_float32)
    image = pq.read_schema(tmp_path / "camera_image" / f"{SEGMENTS[1]}.parquet")
    assert image.field("key.camera_name").type == (pa.string() if as_strings else pa.int8())
    want_value = pa.float32() if as_float32 else pa.float64()
    assert image.field("[CameraImageComponent].pose.transform").type.value_type == want_value
    if as_strings:
        names = pq.read_table(tmp_path / "lidar" / f"{SEGMENTS[1]}.parquet").column("key.laser_name")
        assert names.to_pylist()[:2] == ["TOP", "FRONT"]
    for segment in SEGMENTS:
        got = _read_all(tmp_path, segment)
        _assert_same(got, _by_segment(frames, segment), segment, transform_rtol=1e-6 if as_float32 else 0.0)
        if as_float32:
            assert not np.array_equal(
                got[0].global_from_vehicle, _by_segment(frames, segment)[0].global_from_vehicle
            )


def test_plain_list_transforms_are_accepted(tmp_path: Path, frames: list[RawFrame]) -> None:
    write_v2(tmp_path, frames)
    path = tmp_path / "vehicle_pose" / f"{SEGMENTS[0]}.parquet"
    table = pq.read_table(path)
    name = "[VehiclePoseComponent].world_from_vehicle.transform"
    plain = table.set_column(
        table.schema.get_field_index(name), name, table.column(name).cast(pa.list_(pa.float64()))
    )
    pq.write_table(plain, path)
    got = _read_all(tmp_path, SEGMENTS[0])
    for g, w in zip(got, _by_segment(frames, SEGMENTS[0]), strict=True):
        np.testing.assert_array_equal(g.global_from_vehicle, w.global_from_vehicle)


def test_frames_come_back_in_timestamp_order(tmp_path: Path, frames: list[RawFrame]) -> None:
    shuffled = list(frames)
    random.Random(3).shuffle(shuffled)
    assert [f.timestamp_micros for f in shuffled] != sorted(f.timestamp_micros for f in shuffled)
    write_v2(tmp_path, shuffled, frames_per_row_group=1)
    for segment in SEGMENTS:
        got = _read_all(tmp_path, segment)
        assert [f.timestamp_micros for f in got] == sorted(f.timestamp_micros for f in got)
        _assert_same(got, _by_segment(frames, segment), segment)


def test_list_segments_and_is_v2_root(tmp_path: Path, frames: list[RawFrame]) -> None:
    assert not is_v2_root(tmp_path)
    write_v2(tmp_path / "v2", frames)
    assert is_v2_root(tmp_path / "v2")
    assert not is_v2_root(tmp_path)
    assert list_segments(tmp_path / "v2") == sorted(SEGMENTS)


def test_sequential_reading_reads_each_row_group_once(tmp_path: Path, frames: list[RawFrame]) -> None:
    write_v2(tmp_path, frames, frames_per_row_group=1)
    seg = V2Segment(tmp_path, SEGMENTS[0])
    assert not seg.row_group_reads
    for i in range(len(seg)):
        seg.frame(i)
    for tag in PER_FRAME:
        groups = pq.ParquetFile(tmp_path / tag / f"{SEGMENTS[0]}.parquet").metadata.num_row_groups
        reads = {g: n for (t, g), n in seg.row_group_reads.items() if t == tag}
        assert groups == (2 if tag == "camera_segmentation" else 3), tag  # frame 1 has no panoptic label
        assert reads == dict.fromkeys(range(groups), 1), (tag, reads)
    assert seg.row_group_reads[("camera_calibration", 0)] == 1
    seg.frame(0)  # the poses come from the index (read once); the images' group 0 is read again
    assert seg.row_group_reads[("vehicle_pose", 0)] == 1
    assert seg.row_group_reads[("camera_image", 0)] == 2
    assert seg.row_group_reads[("camera_image", 2)] == 1


@pytest.fixture
def root(tmp_path: Path, frames: list[RawFrame]) -> Path:
    write_v2(tmp_path / "v2", frames)
    return tmp_path / "v2"


def _rmtree(path: Path) -> None:
    for p in path.iterdir():
        p.unlink()
    path.rmdir()


def test_missing_root_and_empty_root(tmp_path: Path) -> None:
    with pytest.raises(WaymoFormatError, match="does not exist"):
        list_segments(tmp_path / "nope")
    with pytest.raises(WaymoFormatError, match="does not exist"):
        V2Segment(tmp_path / "nope", SEGMENTS[0])
    (tmp_path / "other").mkdir()
    with pytest.raises(WaymoFormatError, match="no Waymo v2 component folders") as err:
        list_segments(tmp_path)
    assert str(tmp_path) in str(err.value)


@pytest.mark.parametrize("tag", ["vehicle_pose", "camera_calibration", "lidar_calibration", "lidar_pose"])
def test_missing_required_component_folder(root: Path, tag: str) -> None:
    _rmtree(root / tag)
    with pytest.raises(WaymoFormatError, match=f"required component folder {tag}/"):
        V2Segment(root, SEGMENTS[0])


def test_lidar_components_optional_without_lidar(root: Path, frames: list[RawFrame]) -> None:
    for tag in ("lidar", "lidar_pose"):
        _rmtree(root / tag)
    got = V2Segment(root, SEGMENTS[0]).frame(0)
    assert got.lasers == [] and len(got.laser_calibrations) == 2
    _assert_same(got.images, _by_segment(frames, SEGMENTS[0])[0].images, "images")


def test_segment_without_file_in_a_component(root: Path) -> None:
    missing = root / "camera_image" / f"{SEGMENTS[1]}.parquet"
    missing.unlink()
    V2Segment(root, SEGMENTS[0])
    with pytest.raises(WaymoFormatError, match="component camera_image") as err:
        V2Segment(root, SEGMENTS[1])
    assert str(missing) in str(err.value)


def test_unparsable_parquet(root: Path) -> None:
    path = root / "lidar_box" / f"{SEGMENTS[0]}.parquet"
    path.write_bytes(b"PAR1 this is not parquet")
    with pytest.raises(WaymoFormatError, match="not a readable Parquet file") as err:
        V2Segment(root, SEGMENTS[0])
    assert str(path) in str(err.value)


def test_missing_column(root: Path) -> None:
    path = root / "lidar_box" / f"{SEGMENTS[0]}.parquet"
    column = "[LiDARBoxComponent].box.heading"
    pq.write_table(pq.read_table(path).drop_columns([column]), path)
    with pytest.raises(WaymoFormatError, match="missing column") as err:
        V2Segment(root, SEGMENTS[0])
    assert column in str(err.value) and str(path) in str(err.value)


def test_image_without_camera_calibration(root: Path) -> None:
    path = root / "camera_calibration" / f"{SEGMENTS[0]}.parquet"
    table = pq.read_table(path)
    pq.write_table(table.filter(pa.compute.not_equal(table.column("key.camera_name"), 4)), path)
    seg = V2Segment(root, SEGMENTS[0])
    raw = seg.frame(0)  # the reader marks the camera; the conversion's error policy decides
    message = str(raw.invalid_sensors[("camera", 4)])
    assert "camera SIDE_LEFT" in message and "no camera_calibration row" in message
    assert SEGMENTS[0] in message and str(root / "camera_image" / f"{SEGMENTS[0]}.parquet") in message


def test_a_frame_is_decoded_alone_not_with_the_rest_of_its_row_group(
    tmp_path: Path, frames: list[RawFrame]
) -> None:
    write_v2(tmp_path, frames)  # one row group holds all 3 frames of a segment
    seg = V2Segment(tmp_path, SEGMENTS[0])
    lidar = seg.files["lidar"]
    assert lidar.num_row_groups == 1 and lidar.batch_rows == 2  # two lasers per frame
    for i in range(len(seg)):
        seg.frame(i)
        stream = lidar._stream
        assert stream is not None and stream.position == 2 * (i + 1)  # decoded up to this frame's rows
        assert stream.pending is None or stream.pending.num_rows <= lidar.batch_rows


def test_frames_read_in_any_order_come_back_whole(tmp_path: Path, frames: list[RawFrame]) -> None:
    write_v2(tmp_path, frames, frames_per_row_group=2)
    want = _by_segment(frames, SEGMENTS[0])
    seg = V2Segment(tmp_path, SEGMENTS[0])
    for i in (2, 0, 1, 1, 0, 2):  # backwards (the stream restarts), repeated, across row groups
        _assert_same(seg.frame(i), want[i], f"frame {i}")


def test_a_file_whose_frames_interleave_row_by_row_still_reads_each_frame(
    tmp_path: Path, frames: list[RawFrame]
) -> None:
    write_v2(tmp_path, frames)
    path = tmp_path / "lidar_box" / f"{SEGMENTS[0]}.parquet"
    table = pq.read_table(path)
    order = np.argsort(np.arange(table.num_rows) % 3, kind="stable")  # row k of each frame together
    shuffled = table.take(pa.array(order))
    assert shuffled.column("key.frame_timestamp_micros") != table.column("key.frame_timestamp_micros")
    pq.write_table(shuffled, path, row_group_size=4)
    want = _by_segment(frames, SEGMENTS[0])
    seg = V2Segment(tmp_path, SEGMENTS[0])
    for i in range(len(seg)):
        got = seg.frame(i).labels
        positions = np.flatnonzero(
            shuffled.column("key.frame_timestamp_micros").to_numpy() == want[i].timestamp_micros
        )
        rows = shuffled.take(pa.array(positions))
        assert got.ids == rows.column("key.laser_object_id").to_pylist()
        assert sorted(got.ids) == sorted(want[i].labels.ids)


def test_list_values_of_a_sliced_column_with_null_rows() -> None:
    from phigenesis.data.sources.waymo import v2

    column = pa.array([[9.0], [1.0, 2.0], None, [], [3.0, None, 4.0], [8.0]], pa.list_(pa.float32()))
    table = pa.table({"values": column}).slice(1, 4)  # the offsets index a child shared with row 0
    got = v2._list_values(table, "values")
    assert [None if g is None else g.tolist() for g in got[:3]] == [[1.0, 2.0], None, []]
    assert np.array_equal(got[3], [3.0, np.nan, 4.0], equal_nan=True)
    assert v2._floats(pa.table({"x": pa.array([1.5, None])}), "x", fill=-1.0).tolist() == [1.5, -1.0]
    assert v2._ints(pa.table({"x": pa.array([2, None], pa.int32())}), "x").tolist() == [2, -1]
