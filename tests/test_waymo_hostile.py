"""Hostile Waymo input: every invalid value fails naming the file, the record and the field, or
under ``on_error="skip"`` loses only its own part (a box, a camera, a LiDAR, a frame), counted in
``Scene.dropped``; nothing a few bytes declare is allocated unchecked."""

from __future__ import annotations

import copy
import re
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from phigenesis.data.pipeline import PipelineSpec, PrepError, prepare
from phigenesis.data.records import INVALID_BOXES, INVALID_POINTS
from phigenesis.data.schema import CacheContents
from phigenesis.data.sources.synthetic import SyntheticScene
from phigenesis.data.sources.synthetic.waymo_export import raw_frame
from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource, convert, protos, tfrecord, v1, v2
from phigenesis.data.sources.waymo.raw import (
    CAMERAS_LEFT_OUT,
    FRAMES_LEFT_OUT,
    LIDARS_LEFT_OUT,
    RawFrame,
    WaymoFormatError,
)
from tests.cache_checks import non_finite_values
from tests.conftest import tiny_config
from tests.test_fuzz_waymo import zlib_bomb

CONFIG = tiny_config(scenes=1, frames=3, height=24, width=36)
SEGMENT = "hostile"
#: No stages: these tests are about what the source lets into a scene.
SPEC = PipelineSpec(
    "hostile",
    "waymo",
    {},
    (),
    CacheContents(camera_truth=(), lidar=True, lidar_truth=False, camera_labels=True),
)
FRONT_RIGHT = 3


@pytest.fixture(scope="module")
def raws() -> list[RawFrame]:
    scene = SyntheticScene(CONFIG, 0)
    return [raw_frame(scene, k) for k in range(CONFIG.frames)]


def _v1(tmp_path: Path, raws: list[RawFrame], edit: Callable[[list[RawFrame]], object] | None = None) -> Path:
    """The frames (a deep copy, changed by ``edit``) as a v1 file."""
    frames = copy.deepcopy(raws)
    if edit is not None:
        edit(frames)
    path = tmp_path / "in" / f"segment-{SEGMENT}_with_camera_labels.tfrecord"
    path.parent.mkdir(parents=True, exist_ok=True)
    tfrecord.write_records(path, [v1.serialize_frame(f) for f in frames])
    return path


def _v1_messages(tmp_path: Path, raws: list[RawFrame], edit: Callable[[list[Any]], object]) -> Path:
    """The frames as a v1 file, ``edit`` applied to the decoded Frame messages (for what the raw
    records cannot hold: corrupt range image bytes, mappings, field values)."""
    messages = []
    for raw in raws:
        message = protos.Frame()
        message.ParseFromString(v1.serialize_frame(raw))
        messages.append(message)
    edit(messages)
    path = tmp_path / "in" / f"segment-{SEGMENT}_with_camera_labels.tfrecord"
    path.parent.mkdir(parents=True, exist_ok=True)
    tfrecord.write_records(path, [m.SerializeToString() for m in messages])
    return path


def _prep(tmp_path: Path, path: Path, on_error: str = "raise") -> Any:
    return prepare(
        tmp_path / "out", "waymo", {"input": str(path), "on_error": on_error}, pipeline=SPEC, progress=False
    )


def _fails(tmp_path: Path, path: Path, record: int, words: str) -> str:
    """Converts ``path`` expecting an error that names the file, record ``record`` and ``words``."""
    offset = tfrecord.index_records(path)[record].offset
    where = re.escape(f"{path} (record {record} at byte {offset})")
    with pytest.raises(PrepError, match=rf"{where}: {words}") as err:
        _prep(tmp_path, path)
    return str(err.value)


def _skipped(path: Path) -> Any:
    """The segment read with on_error="skip", every frame loaded."""
    scene = WaymoSource(WaymoConfig(input=str(path), on_error="skip")).load(SEGMENT)
    frames = list(scene.frames)
    return scene, frames


def _image(raw: RawFrame, code: int) -> Any:
    return next(im for im in raw.images if im.name == code)


# --------------------------------------------------------------------------------------------
# Frame-level fields: checked for the whole segment before any frame is converted


def test_a_nan_frame_pose_names_the_file_record_and_field(tmp_path: Path, raws: list[RawFrame]) -> None:
    path = _v1(tmp_path, raws, lambda f: f[1].global_from_vehicle.__setitem__((0, 3), np.nan))
    _fails(tmp_path, path, 1, r"Frame.pose has non-finite entries \[1, .*nan")


def test_a_frame_pose_scaled_by_a_million_is_not_rigid(tmp_path: Path, raws: list[RawFrame]) -> None:
    def scale(frames: list[RawFrame]) -> None:
        frames[2].global_from_vehicle[:3, :3] *= 1e6

    path = _v1(tmp_path, raws, scale)
    _fails(tmp_path, path, 2, "Frame.pose is not a rigid transform: its rotation is not orthonormal")


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (
            lambda f: setattr(f[2], "timestamp_micros", f[1].timestamp_micros),
            "frame 2 timestamp_micros is .* the same as frame 1's",
        ),
        (
            lambda f: setattr(f[2], "timestamp_micros", f[0].timestamp_micros - 1),
            "frame 2 timestamp_micros is .* before frame 1's",
        ),
        (
            lambda f: setattr(f[0], "timestamp_micros", -60_000),
            r"frame 0 timestamp_micros is -60000 us, negative",
        ),
    ],
    ids=["duplicate", "earlier", "negative"],
)
def test_frame_times_that_do_not_strictly_increase_name_the_record(
    tmp_path: Path, raws: list[RawFrame], change: Callable, words: str
) -> None:
    path = _v1(tmp_path, raws, change)
    record = 0 if "negative" in words else 2
    _fails(tmp_path, path, record, words)
    assert not (tmp_path / "out" / "shards").exists() or not list(
        (tmp_path / "out" / "shards").glob("*.arrow")
    )


def test_under_skip_records_with_a_bad_pose_or_time_are_left_out_and_the_rest_converts(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    def edit(frames: list[RawFrame]) -> None:
        frames[1].global_from_vehicle[2, 2] = np.inf
        frames[2].timestamp_micros = frames[0].timestamp_micros

    scene, frames = _skipped(_v1(tmp_path, raws, edit))
    assert [f.source_timestamp_micros for f in frames] == [raws[0].timestamp_micros]
    assert scene.dropped.totals() == {FRAMES_LEFT_OUT: 2}


# --------------------------------------------------------------------------------------------
# Cameras


def test_a_nan_camera_time_names_the_camera_not_a_float_conversion(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    path = _v1(tmp_path, raws, lambda f: setattr(_image(f[1], FRONT_RIGHT), "pose_timestamp", float("nan")))
    _fails(tmp_path, path, 1, "camera FRONT_RIGHT pose_timestamp is nan s, not a time")


def test_a_camera_time_of_1e18_micros_is_refused_as_far_from_its_frame(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    path = _v1(tmp_path, raws, lambda f: setattr(_image(f[1], FRONT_RIGHT), "pose_timestamp", 1e12))
    _fails(
        tmp_path,
        path,
        1,
        r"camera FRONT_RIGHT pose_timestamp is 1000000000000000000 us, \+9\.984e\+11 s from",
    )


def test_a_nan_focal_length_names_the_camera_calibration(tmp_path: Path, raws: list[RawFrame]) -> None:
    def edit(frames: list[RawFrame]) -> None:
        for f in frames:
            f.camera_calibrations[0].intrinsic[0] = np.nan

    _fails(tmp_path, _v1(tmp_path, raws, edit), 0, r"camera FRONT intrinsics has non-finite entries \[nan")


def test_a_jpeg_of_another_size_than_its_calibration_names_the_camera(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    other = cv2.imencode(".jpg", np.zeros((30, 40, 3), np.uint8))[1].tobytes()
    path = _v1(tmp_path, raws, lambda f: setattr(_image(f[1], FRONT_RIGHT), "jpeg", other))
    _fails(tmp_path, path, 1, "camera FRONT_RIGHT image_bytes is a 40x30 JPEG, the calibration says 36x24")


def test_under_skip_a_bad_image_leaves_out_that_camera_of_that_frame(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    def edit(frames: list[RawFrame]) -> None:
        _image(frames[1], FRONT_RIGHT).global_from_vehicle[0, 0] = 7.0  # not a rotation

    scene, frames = _skipped(_v1(tmp_path, raws, edit))
    assert [len(f.cameras) for f in frames] == [5, 4, 5]
    assert "FRONT_RIGHT" not in [c.name for c in frames[1].cameras]
    assert scene.dropped.totals() == {CAMERAS_LEFT_OUT: 1}


# --------------------------------------------------------------------------------------------
# Boxes


def test_a_nan_box_size_names_the_box_id_and_field(tmp_path: Path, raws: list[RawFrame]) -> None:
    path = _v1(tmp_path, raws, lambda f: f[1].labels.box.__setitem__((0, 4), np.nan))
    box = raws[1].labels.ids[0]
    _fails(tmp_path, path, 1, rf"laser label 0: box '{box}' size_lwh \[\S+, nan, \S+\] must be finite")


def test_under_skip_a_bad_box_is_left_out_and_counted_and_the_cache_is_finite(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    def edit(frames: list[RawFrame]) -> None:
        frames[1].labels.box[0, 3] = -1.0  # a negative length
        frames[2].labels.speed[1, 0] = np.inf

    path = _v1(tmp_path, raws, edit)
    scene, frames = _skipped(path)
    assert [len(f.boxes) for f in frames] == [len(r.labels) for r in raws[:1]] + [
        len(r.labels) - 1 for r in raws[1:]
    ]
    assert raws[1].labels.ids[0] not in frames[1].boxes.track_id
    assert scene.dropped.totals() == {INVALID_BOXES: 2}
    summary = _prep(tmp_path, path, "skip")
    assert summary.frames_written == 3 and non_finite_values(tmp_path / "out") == []


def test_two_labels_with_one_id_name_the_repeated_one(tmp_path: Path, raws: list[RawFrame]) -> None:
    path = _v1(tmp_path, raws, lambda f: f[1].labels.ids.__setitem__(1, f[1].labels.ids[0]))
    _fails(
        tmp_path, path, 1, rf"laser label 1: box '{raws[1].labels.ids[0]}' repeats the id of laser label 0"
    )


# --------------------------------------------------------------------------------------------
# LiDAR


def _top_return(raw: RawFrame) -> np.ndarray:
    return raw.lasers[0].return1  # type: ignore[return-value]


def test_inf_and_nan_ranges_drop_only_their_points_and_are_counted(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    image = _top_return(raws[1])
    rows, cols = np.nonzero(image[..., 0] > 0)
    inf_pixels, nan_pixels = (rows[:5], cols[:5]), (rows[5:8], cols[5:8])

    def edit(frames: list[RawFrame]) -> None:
        _top_return(frames[1])[(*inf_pixels, 0)] = np.inf
        _top_return(frames[1])[(*nan_pixels, 0)] = np.nan
        _top_return(frames[1])[0, 0, 0] = np.nan  # a NaN where there was no return is dropped too

    path = _v1(tmp_path, raws, edit)
    scene, frames = _skipped(path)
    clean = WaymoSource(WaymoConfig(input=str(_v1(tmp_path / "clean", raws)))).load(SEGMENT).frames[1]
    lidar = frames[1].lidar
    assert lidar is not None and np.isfinite(lidar.points_ego).all()
    assert len(lidar) == len(clean.lidar) - 8  # type: ignore[arg-type]
    assert scene.dropped.totals() == {INVALID_POINTS: 9}
    # Under raise too: points are left out and counted, never an error.
    assert _prep(tmp_path, path).frames_written == 3 and non_finite_values(tmp_path / "out") == []


def test_nan_pixel_poses_drop_only_the_points_of_those_pixels(tmp_path: Path, raws: list[RawFrame]) -> None:
    image = _top_return(raws[1])
    column = int(np.nonzero(image[..., 0] > 0)[1][0])
    lost = int((image[:, column, 0] > 0).sum())

    def edit(frames: list[RawFrame]) -> None:
        pose = frames[1].lasers[0].pixel_pose.copy()  # type: ignore[union-attr]
        pose[:, column, 4] = np.nan
        frames[1].lasers[0].pixel_pose = pose

    scene, frames = _skipped(_v1(tmp_path, raws, edit))
    assert np.isfinite(frames[1].lidar.origins_ego).all()  # type: ignore[union-attr]
    assert scene.dropped.totals() == {INVALID_POINTS: lost}


def test_a_nan_beam_inclination_names_the_lidar_and_field_and_skip_leaves_the_lidar_out(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    def edit(frames: list[RawFrame]) -> None:
        for f in frames:
            f.laser_calibrations[0].beam_inclinations[2] = np.nan  # type: ignore[index]

    path = _v1(tmp_path, raws, edit)
    _fails(tmp_path, path, 0, r"LiDAR TOP: beam_inclinations gives row \d+ the inclination nan rad")
    scene, frames = _skipped(path)
    assert all(f.lidar is not None and len(f.lidar) == 0 for f in frames)
    assert scene.dropped.totals() == {LIDARS_LEFT_OUT: 3}


def test_a_lidar_name_code_waymo_does_not_have_is_refused(tmp_path: Path, raws: list[RawFrame]) -> None:
    def edit(frames: list[RawFrame]) -> None:
        for f in frames:
            f.lasers[0].name = 0
            f.laser_calibrations[0].name = 0

    _fails(tmp_path, _v1(tmp_path, raws, edit), 0, r"LiDAR name code 0 is not one of \[1, 2, 3, 4, 5\]")


# --------------------------------------------------------------------------------------------
# Allocations bounded by what the input declares


def _peak_bytes(fn: Callable[[], object]) -> int:
    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def test_a_panoptic_instance_id_of_2_31_needs_no_table_that_large(raws: list[RawFrame]) -> None:
    image = copy.deepcopy(_image(raws[0], FRONT_RIGHT))
    image.instance_to_global = {**image.instance_to_global, 2**31 - 1: 5}
    peak = _peak_bytes(lambda: convert.camera_labels(image, CONFIG.height, CONFIG.width, "w"))
    assert peak < 16 << 20, peak
    labels = convert.camera_labels(image, CONFIG.height, CONFIG.width, "w")
    want = convert.camera_labels(_image(raws[0], FRONT_RIGHT), CONFIG.height, CONFIG.width, "w")
    np.testing.assert_array_equal(labels.instance, want.instance)  # type: ignore[union-attr]


def test_a_panoptic_png_declaring_a_huge_image_is_refused_before_decoding(raws: list[RawFrame]) -> None:
    image = copy.deepcopy(_image(raws[0], FRONT_RIGHT))
    png = bytearray(image.panoptic_label)  # type: ignore[arg-type]
    png[16:24] = (50000).to_bytes(4, "big") + (50000).to_bytes(4, "big")
    image.panoptic_label = bytes(png)
    with pytest.raises(WaymoFormatError, match=r"w: panoptic label of the image is shape \(50000, 50000\)"):
        convert.camera_labels(image, CONFIG.height, CONFIG.width, "w")


@pytest.mark.parametrize("adler32", [True, False])
def test_a_zlib_bomb_range_image_is_refused_having_inflated_only_the_cap(adler32: bool) -> None:
    bomb = zlib_bomb(256)  # 256 MiB from 264 KB
    with pytest.raises(
        WaymoFormatError, match=r"^m: range image inflates beyond 16777216 bytes from \d+ compressed"
    ):
        v1.inflate_matrix(bomb, "m", adler32)

    def inflate() -> None:
        with pytest.raises(WaymoFormatError):
            v1.inflate_matrix(bomb, "m", adler32)

    peak = _peak_bytes(inflate)
    assert peak < 40 << 20, peak


@pytest.mark.parametrize("adler32", [True, False])
def test_a_matrix_declaring_more_data_than_the_cap_is_refused_before_inflating(adler32: bool) -> None:
    import zlib

    declared = b"\x0a\x80\x80\x80\x80\x08"  # field 1, 2 GiB of packed floats follow (they do not)
    with pytest.raises(WaymoFormatError, match="declares 2147483648 bytes of data"):
        v1.inflate_matrix(zlib.compress(declared + bytes(100)), "m", adler32)


def test_inflating_without_the_adler32_gives_the_same_bytes_and_still_checks_the_framing() -> None:
    import zlib

    payload = np.random.default_rng(0).standard_normal(50_000).astype(np.float32).tobytes()
    stream = zlib.compress(payload, 6)
    assert v1.inflate_matrix(stream, "m", adler32=False) == payload == v1.inflate_matrix(stream, "m")
    wrong_sum = stream[:-4] + bytes(4)
    # The checksum is the one thing skipped: the record's CRC-32C covers these bytes.
    assert v1.inflate_matrix(wrong_sum, "m", adler32=False) == payload
    with pytest.raises(WaymoFormatError, match=r"^m: range image does not decompress .*incorrect data check"):
        v1.inflate_matrix(wrong_sum, "m")
    for bad, why in [
        (stream[:-2], "the zlib stream is truncated"),
        (stream[: len(stream) // 2], "the zlib stream is truncated"),
        (b"\x79" + stream[1:], "names no deflate stream"),
        (stream[:1] + bytes([stream[1] ^ 1]) + stream[2:], "check bits are wrong"),
        (b"\x78\xbb" + stream[2:], "needs a preset dictionary"),
        (stream[:5], "5 bytes are too few"),
    ]:
        with pytest.raises(WaymoFormatError, match=f"^m: range image does not decompress .*{why}"):
            v1.inflate_matrix(bad, "m", adler32=False)


def test_a_v1_record_with_a_bad_adler32_is_refused_only_when_its_crc_is_not_checked(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    def edit(messages: list[Any]) -> None:
        blob = messages[0].lasers[0].ri_return1.range_image_compressed
        messages[0].lasers[0].ri_return1.range_image_compressed = blob[:-4] + bytes(4)

    path = _v1_messages(tmp_path, raws, edit)
    # The record's CRC-32C is of the edited bytes, so the checked path takes the stream as written.
    checked = v1.V1File(path).frame(0)
    assert not checked.invalid_sensors and checked.lasers[0].return1 is not None
    unchecked = v1.V1File(path, check_crc=False).frame(0)
    assert "incorrect data check" in str(unchecked.invalid_sensors)


def test_a_zlib_bomb_in_a_record_names_the_file_record_and_lidar(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    def edit(messages: list[Any]) -> None:
        messages[1].lasers[0].ri_return1.range_image_compressed = zlib_bomb(64)

    path = _v1_messages(tmp_path, raws, edit)
    _fails(tmp_path, path, 1, "LiDAR TOP return 1: range image inflates beyond 16777216 bytes")
    scene, frames = _skipped(path)
    assert len(frames[1].lidar) == 0 and scene.dropped.totals() == {LIDARS_LEFT_OUT: 1}  # type: ignore[arg-type]


def test_a_varint_longer_than_64_bits_is_refused_at_once() -> None:
    with pytest.raises(ValueError, match="longer than 10 bytes"):
        protos.read_varint(b"\xff" * 11 + b"\x01", 0)
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="not a valid matrix message"):
        protos.decode_matrix(b"\x0a" + b"\xff" * 20_000, np.float32, "m")
    assert time.perf_counter() - t0 < 0.5


# --------------------------------------------------------------------------------------------
# Waymo v2


@pytest.fixture
def v2_root(tmp_path: Path, raws: list[RawFrame]) -> Path:
    root = tmp_path / "v2"
    v2.write_v2(root, raws)
    return root


def _rewrite(path: Path, change: Callable[[pa.Table], pa.Table]) -> None:
    pq.write_table(change(pq.read_table(path)), path)


def _set_column(table: pa.Table, name: str, values: list, type_: pa.DataType) -> pa.Table:
    return table.set_column(table.schema.get_field_index(name), name, pa.array(values, type_))


def test_v2_a_string_in_a_number_column_names_the_file_frame_object_and_column(
    tmp_path: Path, v2_root: Path, raws: list[RawFrame]
) -> None:
    path = v2_root / "lidar_box" / f"{SEGMENT_V2(raws)}.parquet"
    column = "[LiDARBoxComponent].box.center.x"

    def change(table: pa.Table) -> pa.Table:
        values = [str(v) for v in table.column(column).to_pylist()]
        values[0] = "abc"
        return _set_column(table, column, values, pa.string())

    _rewrite(path, change)
    ts, obj = raws[0].timestamp_micros, raws[0].labels.ids[0]
    where = re.escape(f"{path} frame {ts}: column {column} row 0 (object '{obj}') holds 'abc', not a double")
    with pytest.raises(PrepError, match=where):
        _prep(tmp_path, v2_root)


def SEGMENT_V2(raws: list[RawFrame]) -> str:
    return raws[0].segment


def test_v2_an_empty_vehicle_pose_names_the_file(tmp_path: Path, v2_root: Path, raws: list[RawFrame]) -> None:
    path = v2_root / "vehicle_pose" / f"{SEGMENT_V2(raws)}.parquet"
    _rewrite(path, lambda t: t.slice(0, 0))
    with pytest.raises(
        PrepError, match=re.escape(f"{path}: vehicle_pose has no rows: the segment has no frames")
    ):
        _prep(tmp_path, v2_root)


def test_v2_a_root_without_lidar_box_is_refused_naming_the_folder(tmp_path: Path, v2_root: Path) -> None:
    for p in (v2_root / "lidar_box").iterdir():
        p.unlink()
    (v2_root / "lidar_box").rmdir()
    with pytest.raises(
        PrepError, match=re.escape(f"{v2_root}: required component folder lidar_box/ is missing")
    ):
        _prep(tmp_path, v2_root)


def test_v2_two_vehicle_poses_for_one_frame_name_the_frame_and_skip_leaves_it_out(
    tmp_path: Path, v2_root: Path, raws: list[RawFrame]
) -> None:
    path = v2_root / "vehicle_pose" / f"{SEGMENT_V2(raws)}.parquet"
    _rewrite(path, lambda t: pa.concat_tables([t, t.slice(1, 1)]))
    ts = raws[1].timestamp_micros
    with pytest.raises(
        PrepError, match=re.escape(f"{path} frame {ts}: rows [1, 3] are all this frame's vehicle pose")
    ):
        _prep(tmp_path, v2_root)
    scene = WaymoSource(WaymoConfig(input=str(v2_root), on_error="skip")).load(SEGMENT_V2(raws))
    assert [f.source_timestamp_micros for f in scene.frames] == [
        raws[0].timestamp_micros,
        raws[2].timestamp_micros,
    ]
    assert scene.dropped.totals() == {FRAMES_LEFT_OUT: 1}


def test_v2_a_nan_box_size_names_the_lidar_box_file_and_object(
    tmp_path: Path, v2_root: Path, raws: list[RawFrame]
) -> None:
    path = v2_root / "lidar_box" / f"{SEGMENT_V2(raws)}.parquet"
    column = "[LiDARBoxComponent].box.size.y"

    def change(table: pa.Table) -> pa.Table:
        values = table.column(column).to_pylist()
        values[0] = float("nan")
        return _set_column(table, column, values, pa.float64())

    _rewrite(path, change)
    ts, obj = raws[0].timestamp_micros, raws[0].labels.ids[0]
    with pytest.raises(PrepError, match=re.escape(f"{path} frame {ts}: laser label 0: box '{obj}' size_lwh")):
        _prep(tmp_path, v2_root)
