"""Hostile nuScenes input: every error names the file, the record (table + token) and the field;
paths from the tables stay inside the dataroot; nothing non-finite reaches a scene; and
``on_error="skip"`` leaves out the smallest unit (a box, an image, a sweep, a sample's boxes, a
frame) while the rest converts as before.

The fixture is a tiny ``phigenesis-synth --format nuscenes`` export: one scene of 2 keyframes
(7 frames at 12 Hz, 11 LiDAR sweeps at 20 Hz), 24 x 16 images, a 4-beam LiDAR.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from phigenesis import prep
from phigenesis.data.pipeline import PipelineSpec
from phigenesis.data.records import INVALID_POINTS, Frame, Scene
from phigenesis.data.sources.nuscenes import NuScenesConfig, NuScenesError, NuScenesSource
from phigenesis.data.sources.nuscenes.convert import DROPPED_FILES
from phigenesis.data.sources.synthetic.nuscenes_export import export_nuscenes
from phigenesis.data.sources.synthetic.rigs import LidarSpec
from phigenesis.errors import PrepError
from tests.cache_checks import non_finite_values
from tests.conftest import tiny_config
from tests.test_waymo_images import undecodable

VERSION = "v1.0-mini"
#: One scene, 2 keyframes: 7 camera steps, 11 LiDAR sweeps; tiny images and LiDAR.
TINY_NUSCENES = tiny_config(scenes=1, height=16, width=24, lidar=LidarSpec(beams=4, columns=64, sectors=4))
TINY_KEYFRAMES = 2
STEPS = 7
CAMERAS = 6
#: A pipeline that runs only the cheap stage, into a cache without depth or labels.
CHEAP_PIPELINE = PipelineSpec.from_dict(
    {
        "name": "nuscenes-cheap",
        "source": {"name": "nuscenes", "params": {}},
        "stages": [{"name": "interpolate_boxes"}],
        "output": {
            "camera_truth": [],
            "lidar": True,
            "lidar_truth": False,
            "camera_labels": False,
            "depth": False,
            "pseudo_semantics": False,
            "range_view": False,
        },
    }
)


def export_tiny_nuscenes(root: Path) -> Path:
    """Writes the tiny export under ``root`` (its dataroot) and returns ``root``."""
    export_nuscenes(TINY_NUSCENES, root, keyframes=TINY_KEYFRAMES)
    return root


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return export_tiny_nuscenes(tmp_path_factory.mktemp("nuscenes-tiny") / "data")


@pytest.fixture
def root(base: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny export to damage."""
    out = tmp_path / "data"
    shutil.copytree(base, out)
    return out.resolve()


# --------------------------------------------------------------------------------------------
# Helpers


def table_path(root: Path, table: str) -> Path:
    return root / VERSION / f"{table}.json"


def rows(root: Path, table: str) -> list[dict[str, Any]]:
    return json.loads(table_path(root, table).read_text())


def find(root: Path, table: str, pick: Callable[[dict[str, Any]], bool], nth: int = 0) -> dict[str, Any]:
    """The ``nth`` record of ``table`` for which ``pick`` holds."""
    return [r for r in rows(root, table) if pick(r)][nth]


def edit(root: Path, table: str, token: str, **values: Any) -> dict[str, Any]:
    """Sets (or, for the value ``DELETE``, removes) fields of record ``token`` of ``table``."""
    table_rows = rows(root, table)
    (record,) = [r for r in table_rows if r["token"] == token]
    for key, value in values.items():
        if value is DELETE:
            del record[key]
        else:
            record[key] = value
    table_path(root, table).write_text(json.dumps(table_rows))
    return record


DELETE = object()


def sweep(root: Path, channel: str, key: bool, nth: int = 0) -> dict[str, Any]:
    """The ``nth`` sample_data record of ``channel`` that is (or is not) a keyframe, in time order."""
    folder = "samples" if key else "sweeps"
    matches = [r for r in rows(root, "sample_data") if r["filename"].startswith(f"{folder}/{channel}/")]
    return sorted(matches, key=lambda r: r["timestamp"])[nth]


def load(root: Path, on_error: str = "raise") -> tuple[Scene, list[Frame]]:
    """The scene of ``root`` and all its frames."""
    source = NuScenesSource(NuScenesConfig(dataroot=str(root), on_error=on_error))  # type: ignore[arg-type]
    (scene_id,) = source.scene_ids()
    scene = source.load(scene_id)
    return scene, [scene.frames[i] for i in range(len(scene))]


def names_record(message: str, root: Path, table: str, token: str, field: str) -> bool:
    """Whether ``message`` starts by naming the table's file, the record and the field."""
    return message.startswith(f"{table_path(root, table)}: {table} {token!r}: {field!r}")


def camera_count(frames: list[Frame], camera: str) -> int:
    return sum(c.name == camera for f in frames for c in f.cameras)


def skipped(scene: Scene) -> list[str]:
    return [s["skipped"] for s in scene.metadata["skipped"]]


def damage_image(
    root: Path, channel: str, nth: int, damage: Callable[[bytes], bytes]
) -> tuple[dict[str, Any], Path]:
    """The ``nth`` non-keyframe sample_data of camera ``channel`` and its image file, which
    ``damage`` rewrites."""
    sd = sweep(root, channel, key=False, nth=nth)
    path = root / sd["filename"]
    path.write_bytes(damage(path.read_bytes()))
    return sd, path


def load_error(root: Path) -> str:
    """The message of the :class:`NuScenesError` that loading ``root``'s scene raises."""
    with pytest.raises(NuScenesError) as e:
        load(root)
    return str(e.value)


def annotation(root: Path, nth: int = 0) -> dict[str, Any]:
    """The ``nth`` annotation (by token) of the first sample that has a next annotation."""
    anns = sorted(rows(root, "sample_annotation"), key=lambda a: a["token"])
    return [a for a in anns if a["next"]][nth]


# --------------------------------------------------------------------------------------------
# 1. Fields of the wrong kind are errors naming the file, the record and the field


def test_is_key_frame_false_as_a_string_is_an_error_not_a_keyframe(root: Path) -> None:
    sd = sweep(root, "CAM_FRONT_LEFT", key=False, nth=1)
    edit(root, "sample_data", sd["token"], is_key_frame="false")
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert names_record(str(e.value), root, "sample_data", sd["token"], "is_key_frame")
    assert 'must be true or false, got "false"' in str(e.value)
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample_data {sd['token']}"]
    assert camera_count(frames, "CAM_FRONT_LEFT") == STEPS - 1


def test_a_missing_sample_timestamp_is_an_error_naming_sample_json(root: Path) -> None:
    sample = rows(root, "sample")[1]
    edit(root, "sample", sample["token"], timestamp=DELETE)
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert (
        str(e.value) == f"{table_path(root, 'sample')}: sample {sample['token']!r}: has no field 'timestamp'"
    )


def test_a_missing_box_size_is_an_error_naming_the_annotation(root: Path) -> None:
    ann = annotation(root)
    edit(root, "sample_annotation", ann["token"], size=DELETE)
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert str(e.value) == (
        f"{table_path(root, 'sample_annotation')}: sample_annotation {ann['token']!r}: has no field 'size'"
    )


@pytest.mark.parametrize(
    ("table", "field", "value"),
    [
        ("sample_data", "sample_token", ["x"]),  # the reverse index: was "unhashable type: 'list'"
        ("sample_annotation", "attribute_tokens", [["x"]]),  # a link: was the same TypeError
        ("sample_annotation", "instance_token", ["x"]),
    ],
)
def test_a_list_where_a_token_belongs_is_an_error_naming_the_field(
    root: Path, table: str, field: str, value: Any
) -> None:
    record = annotation(root) if table == "sample_annotation" else sweep(root, "CAM_BACK", key=False)
    edit(root, table, record["token"], **{field: value})
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert names_record(str(e.value), root, table, record["token"], field)
    assert "token string" in str(e.value)


def _camera_cs(root: Path) -> dict[str, Any]:
    return find(root, "calibrated_sensor", lambda r: len(r["camera_intrinsic"]) == 3)


def _lidar_cs(root: Path) -> dict[str, Any]:
    return find(root, "calibrated_sensor", lambda r: r["camera_intrinsic"] == [])


NAN, INF = float("nan"), float("inf")


def _ego_pose(root: Path) -> dict[str, Any]:
    return rows(root, "ego_pose")[3]


def _back_sweep(root: Path) -> dict[str, Any]:
    return sweep(root, "CAM_BACK", key=False)


def _lidar_sweep(root: Path) -> dict[str, Any]:
    return sweep(root, "LIDAR_TOP", key=False)


def _first_sample(root: Path) -> dict[str, Any]:
    return rows(root, "sample")[0]


def _car_category(root: Path) -> dict[str, Any]:
    return find(root, "category", lambda c: c["name"] == "vehicle.car")


def _back_sensor(root: Path) -> dict[str, Any]:
    return find(root, "sensor", lambda s: s["channel"] == "CAM_BACK")


def _bad(
    what: str, table: str, pick: Callable[[Path], dict[str, Any]], field: str, value: Any, says: str
) -> Any:
    return pytest.param(table, pick, field, value, says, id=what)


#: (table, record picker, field, bad value, what the message says is wrong), named by the damage.
BAD_FIELDS = [
    _bad("strings for numbers", "ego_pose", _ego_pose, "translation", ["1", "2", "3"], "numbers only"),
    _bad("a 2-element centre", "sample_annotation", annotation, "translation", [1.0, 2.0], "a list of 3"),
    _bad("a NaN ego position", "ego_pose", _ego_pose, "translation", [NAN, 0, 0], "finite"),
    _bad("an Inf extrinsic", "calibrated_sensor", _lidar_cs, "translation", [INF, 0, 0], "finite"),
    _bad(
        "a non-rigid rotation", "calibrated_sensor", _camera_cs, "rotation", [1e6, 0, 0, 0], "unit quaternion"
    ),
    _bad("a NaN intrinsic", "calibrated_sensor", _camera_cs, "camera_intrinsic", [[NAN, 0, 1]] * 3, "finite"),
    _bad(
        "a zero focal length", "calibrated_sensor", _camera_cs, "camera_intrinsic", [[0, 0, 1]] * 3, "pinhole"
    ),
    _bad("a negative timestamp", "sample_data", _back_sweep, "timestamp", -5, "timestamp in microseconds"),
    _bad("a timestamp of 1e18", "sample_data", _back_sweep, "timestamp", 10**18, "before 2100"),
    _bad("a fractional timestamp", "sample", _first_sample, "timestamp", 1.5, "integer timestamp"),
    _bad("a string timestamp", "sample_data", _lidar_sweep, "timestamp", "1600000000", "integer timestamp"),
    _bad("a string width", "sample_data", _back_sweep, "width", "24", "number of pixels"),
    _bad("a huge LiDAR count", "sample_annotation", annotation, "num_lidar_pts", 10**30, "integer count"),
    _bad("a NaN box size", "sample_annotation", annotation, "size", [NAN, 1.0, 1.0], "finite"),
    _bad("a negative box size", "sample_annotation", annotation, "size", [-1.0, 1.0, 1.0], "positive"),
    _bad("a NaN box rotation", "sample_annotation", annotation, "rotation", [NAN, 0, 0, 0], "finite"),
    _bad("a number for a name", "category", _car_category, "name", 5, "must be a string"),
    _bad("an unknown modality", "sensor", _back_sensor, "modality", "Camera", "camera, lidar or radar"),
]


@pytest.mark.parametrize(("table", "pick", "field", "value", "wrong"), BAD_FIELDS)
def test_a_bad_field_is_an_error_naming_its_file_record_and_field(
    root: Path, table: str, pick: Callable[[Path], dict[str, Any]], field: str, value: Any, wrong: str
) -> None:
    record = pick(root)
    edit(root, table, record["token"], **{field: value})
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert names_record(str(e.value), root, table, record["token"], field), str(e.value)
    assert wrong in str(e.value)


def test_two_sweeps_of_one_camera_at_one_time_are_an_error_and_skip_uses_neither(root: Path) -> None:
    first, second = (sweep(root, "CAM_FRONT_RIGHT", key=False, nth=n) for n in (1, 2))
    edit(root, "sample_data", second["token"], timestamp=first["timestamp"])
    with pytest.raises(NuScenesError) as e:
        load(root)
    a, b = sorted((first["token"], second["token"]))  # the first by token is named first
    assert names_record(str(e.value), root, "sample_data", a, "timestamp")
    assert f"is also the time of CAM_FRONT_RIGHT sample_data {b!r}" in str(e.value)
    scene, frames = load(root, "skip")
    assert sorted(skipped(scene)) == sorted(f"sample_data {t}" for t in (first["token"], second["token"]))
    assert camera_count(frames, "CAM_FRONT_RIGHT") == STEPS - 2
    assert [c["camera"] for c in scene.metadata["camera_gaps"]] == ["CAM_FRONT_RIGHT"] * 2


def test_a_repeated_token_is_an_error_naming_the_table_and_skip_uses_neither_record(
    base: Path, root: Path
) -> None:
    table_rows = rows(root, "sample_annotation")
    first, second = annotation(root, 0), annotation(root, 1)  # both in keyframe 0
    i, j = (next(i for i, r in enumerate(table_rows) if r["token"] == a["token"]) for a in (first, second))
    table_rows[j]["token"] = first["token"]
    table_path(root, "sample_annotation").write_text(json.dumps(table_rows))
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert str(e.value) == (  # the later of the two in the file is the repeat
        f"{table_path(root, 'sample_annotation')}: record {max(i, j)} of table 'sample_annotation' "
        f"repeats the token {first['token']!r}"
    )
    full, _ = load(base)
    scene, _ = load(root, "skip")
    kept = [set(kf.boxes.track_id) for kf in scene.keyframes]
    want = [set(kf.boxes.track_id) for kf in full.keyframes]
    assert kept == [want[0] - {first["instance_token"], second["instance_token"]}, want[1]]
    assert len(kept[0]) == len(want[0]) - 2


def test_a_sample_out_of_time_order_is_an_error_and_skip_loses_only_its_boxes(base: Path, root: Path) -> None:
    first, second = rows(root, "sample")
    edit(root, "sample", second["token"], timestamp=first["timestamp"])  # a duplicate time
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert names_record(str(e.value), root, "sample", second["token"], "timestamp")
    assert "out of time order" in str(e.value)
    full, full_frames = load(base)
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample {second['token']}"]
    assert [kf.token for kf in scene.keyframes] == [first["token"]]
    assert len(frames) == STEPS
    assert [f.timestamp_micros for f in frames] == [f.timestamp_micros for f in full_frames]
    # Keyframe 0's boxes stay; their next annotations' time is unknown, so they are not used
    # for velocities (which become 0, "annotated once").
    assert len(scene.keyframes[0].boxes) == len(full.keyframes[0].boxes) > 0
    np.testing.assert_array_equal(scene.keyframes[0].boxes.velocity_world, 0.0)


# --------------------------------------------------------------------------------------------
# 2. Paths from the tables stay inside the dataroot


@pytest.mark.parametrize("how", ["dot-dot", "absolute", "symlink"])
def test_a_filename_leading_outside_the_dataroot_is_an_error_and_the_file_is_not_used(
    root: Path, how: str
) -> None:
    sd = sweep(root, "LIDAR_TOP", key=False, nth=2)
    outside = root.parent / "outside.pcd.bin"
    shutil.copy(root / sd["filename"], outside)
    if how == "dot-dot":
        filename = "../outside.pcd.bin"
    elif how == "absolute":
        filename = str(outside)
    else:
        filename = "sweeps/LIDAR_TOP/link.pcd.bin"
        os.symlink(outside, root / filename)
    edit(root, "sample_data", sd["token"], filename=filename)
    with pytest.raises(NuScenesError) as e:
        load(root)
    message = str(e.value)
    assert names_record(message, root, "sample_data", sd["token"], "filename")
    assert f"{filename!r} leads outside the dataroot {root}" in message
    if how == "symlink":
        assert f"(to {outside})" in message
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample_data {sd['token']}"]
    assert sd["timestamp"] not in [f.lidar.timestamp_micros for f in frames if f.lidar is not None]
    with pytest.raises(
        PrepError, match=rf"sample_data '{sd['token']}': 'filename' '{filename}' leads outside"
    ):
        prep.nuscenes(root.parent / "cache", dataroot=root, pipeline=CHEAP_PIPELINE, progress=False)


# --------------------------------------------------------------------------------------------
# 3. Nothing non-finite reaches a scene or a cache


def _key_lidar_of_frame_0(root: Path) -> Path:
    return root / sweep(root, "LIDAR_TOP", key=True, nth=0)["filename"]


def test_non_finite_lidar_points_are_dropped_and_counted(base: Path, root: Path) -> None:
    path = _key_lidar_of_frame_0(root)
    points = np.fromfile(path, "<f4").reshape(-1, 5)
    points[[3, 10, 11], 0] = np.nan
    points[[20, 21], 1] = np.inf
    points[30, 2] = -np.inf
    points[40, 3] = np.nan  # intensity
    points[50, 0] = 1e30  # finite, but no LiDAR measures 1e30 m
    points.tofile(path)
    _, full_frames = load(base)
    scene, frames = load(root)
    lidar = frames[0].lidar
    assert lidar is not None and len(lidar) == len(full_frames[0].lidar) - 8
    assert np.isfinite(lidar.points_ego).all() and np.isfinite(lidar.intensity).all()
    assert scene.dropped.totals() == {INVALID_POINTS: 8}
    assert scene.dropped.describe() == f"8 {INVALID_POINTS} (1 frames)"
    cache = root.parent / "cache"
    prep.nuscenes(cache, dataroot=root, pipeline=CHEAP_PIPELINE, progress=False)
    assert non_finite_values(cache) == []
    (entry,) = json.loads((cache / "manifest.json").read_text())["scenes"]
    assert entry["dropped"] == {INVALID_POINTS: 8}


@pytest.mark.parametrize(
    ("field", "value"),
    [("translation", [NAN, 0.0, 0.0]), ("size", [2.0, NAN, 1.5]), ("rotation", [1.0, 0.0, 0.0, INF])],
)
def test_a_non_finite_box_field_is_rejected_at_the_source_and_never_reaches_the_cache(
    base: Path, root: Path, field: str, value: list[float]
) -> None:
    ann = annotation(root)
    edit(root, "sample_annotation", ann["token"], **{field: value})
    with pytest.raises(PrepError) as e:
        prep.nuscenes(root.parent / "stop", dataroot=root, pipeline=CHEAP_PIPELINE, progress=False)
    where = f"{table_path(root, 'sample_annotation')}: sample_annotation {ann['token']!r}: {field!r}"
    assert where in str(e.value) and "finite" in str(e.value)
    cache = root.parent / "cache"
    summary = prep.nuscenes(cache, dataroot=root, pipeline=CHEAP_PIPELINE, on_error="skip", progress=False)
    assert summary.frames_written == STEPS and not summary.scenes_skipped
    assert non_finite_values(cache) == []
    # Only that one box is gone: the instance keeps its other keyframe.
    scene, _ = load(root, "skip")
    full, _ = load(base)
    assert skipped(scene) == [f"sample_annotation {ann['token']}"]
    assert len(scene.keyframes[0].boxes) == len(full.keyframes[0].boxes) - 1
    assert ann["instance_token"] not in scene.keyframes[0].boxes.track_id
    assert ann["instance_token"] in scene.keyframes[1].boxes.track_id


def test_a_run_stopped_by_a_bad_record_resumes_into_the_same_cache_with_on_error_skip(root: Path) -> None:
    ann = annotation(root)
    edit(root, "sample_annotation", ann["token"], size=[1.0, NAN, 1.5])
    cache = root.parent / "cache"
    with pytest.raises(PrepError, match="--on-error skip converts the rest"):
        prep.nuscenes(cache, dataroot=root, pipeline=CHEAP_PIPELINE, progress=False)
    # The error policy is not part of what a cache is: the advice works in the same --out.
    summary = prep.nuscenes(cache, dataroot=root, pipeline=CHEAP_PIPELINE, on_error="skip", progress=False)
    assert summary.frames_written == STEPS and not summary.scenes_skipped
    assert non_finite_values(cache) == []


# --------------------------------------------------------------------------------------------
# 4. --on-error skip leaves out the smallest unit


def test_a_bad_camera_sweep_leaves_only_that_image_out_of_its_frame(base: Path, root: Path) -> None:
    sd = sweep(root, "CAM_BACK", key=False, nth=2)
    edit(root, "ego_pose", sd["ego_pose_token"], rotation=[0.5, 0.5, 0.5, NAN])
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert names_record(str(e.value), root, "ego_pose", sd["ego_pose_token"], "rotation")
    _, full_frames = load(base)
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample_data {sd['token']}"]
    lacking = [i for i, f in enumerate(frames) if len(f.cameras) < CAMERAS]
    assert len(lacking) == 1 and "CAM_BACK" not in [c.name for c in frames[lacking[0]].cameras]
    assert [len(f.cameras) for f in full_frames] == [CAMERAS] * STEPS
    assert [f.timestamp_micros for f in frames] == [f.timestamp_micros for f in full_frames]


def test_a_bad_lidar_sweep_leaves_only_that_sweep_out(base: Path, root: Path) -> None:
    sd = sweep(root, "LIDAR_TOP", key=False, nth=3)
    edit(root, "sample_data", sd["token"], timestamp=str(sd["timestamp"]))
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert names_record(str(e.value), root, "sample_data", sd["token"], "timestamp")
    _, full_frames = load(base)
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample_data {sd['token']}"]
    full_lidar = [f.lidar.timestamp_micros if f.lidar else None for f in full_frames]
    lidar = [f.lidar.timestamp_micros if f.lidar else None for f in frames]
    changed = [k for k in range(STEPS) if lidar[k] != full_lidar[k]]
    assert len(changed) == 1 and full_lidar[changed[0]] == sd["timestamp"]
    assert sd["timestamp"] not in lidar


def test_a_frame_whose_time_is_out_of_order_is_left_out(base: Path, root: Path) -> None:
    # Lead image 3 one microsecond after lead image 2: the two frames' times (their LiDAR
    # sweeps', or their own) cannot both be in order, and the most that are in order are kept.
    lead_2, lead_3 = (sweep(root, "CAM_FRONT", key=False, nth=n) for n in (1, 2))
    edit(root, "sample_data", lead_3["token"], timestamp=lead_2["timestamp"] + 1)
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert "out of order with the frames around it" in str(e.value)
    assert str(e.value).startswith(f"{table_path(root, 'sample_data')}: sample_data ")
    scene, frames = load(root, "skip")
    times = [f.timestamp_micros for f in frames]
    assert len(frames) == STEPS - 1 and np.all(np.diff(times) > 0)
    assert [s.split()[:3] for s in skipped(scene)] == [["frame", "of", "sample_data"]]


def test_an_image_that_cannot_be_read_when_its_frame_loads_is_counted_under_skip(root: Path) -> None:
    sd = sweep(root, "CAM_FRONT_LEFT", key=False, nth=0)
    for on_error in ("raise", "skip"):
        source = NuScenesSource(NuScenesConfig(dataroot=str(root), on_error=on_error))  # type: ignore[arg-type]
        scene = source.load(source.scene_ids()[0])
        (root / sd["filename"]).rename(root / "moved.jpg")
        try:
            if on_error == "raise":
                with pytest.raises(NuScenesError, match=rf"{root / sd['filename']}: cannot read the image"):
                    [scene.frames[i] for i in range(STEPS)]
            else:
                frames = [scene.frames[i] for i in range(STEPS)]
                assert camera_count(frames, "CAM_FRONT_LEFT") == STEPS - 1
                assert scene.dropped.totals() == {DROPPED_FILES: 1}
        finally:
            (root / "moved.jpg").rename(root / sd["filename"])


def test_an_image_whose_size_differs_from_its_record_is_an_error_and_skip_leaves_it_out(root: Path) -> None:
    sd = sweep(root, "CAM_FRONT_RIGHT", key=False, nth=3)
    edit(root, "sample_data", sd["token"], width=48)
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert names_record(str(e.value), root, "sample_data", sd["token"], "width")
    assert f"is 48x16, but its image {root / sd['filename']} is 24x16" in str(e.value)
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample_data {sd['token']}"]
    assert camera_count(frames, "CAM_FRONT_RIGHT") == STEPS - 1


@pytest.mark.parametrize(
    ("cut", "problem"),
    [
        (slice(None, 40), "a truncated segment"),
        (slice(None, -10), "it ends without the end-of-image marker FF D9: cut short"),  # the header reads
    ],
)
def test_a_truncated_image_is_an_error_naming_it_and_skip_leaves_it_out(
    root: Path, cut: slice, problem: str
) -> None:
    sd, path = damage_image(root, "CAM_BACK_RIGHT", 2, lambda data: data[cut])
    assert load_error(root) == (
        f"{path}: not a readable JPEG ({problem}) "
        f"(named by sample_data {sd['token']!r} 'filename' in {table_path(root, 'sample_data')})"
    )
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample_data {sd['token']}"]
    assert camera_count(frames, "CAM_BACK_RIGHT") == STEPS - 1


def test_an_image_that_does_not_decode_is_an_error_when_its_frame_loads_and_skip_leaves_it_out(
    root: Path,
) -> None:
    sd, path = damage_image(root, "CAM_FRONT_LEFT", 1, undecodable)  # header and end marker intact
    assert load_error(root) == (
        f"{table_path(root, 'sample_data')}: sample_data {sd['token']!r}: as an image ({path}): "
        f"camera CAM_FRONT_LEFT image_bytes holds {path.stat().st_size} bytes that do not decode"
    )
    scene, frames = load(root, "skip")
    assert camera_count(frames, "CAM_FRONT_LEFT") == STEPS - 1
    assert scene.dropped.totals() == {DROPPED_FILES: 1}


def test_a_camera_sweep_with_another_calibration_than_its_camera_is_left_out(root: Path) -> None:
    sd = sweep(root, "CAM_BACK_LEFT", key=False, nth=1)
    cs = next(r for r in rows(root, "calibrated_sensor") if r["token"] == sd["calibrated_sensor_token"])
    copy = {**cs, "token": "c" * 32, "translation": [9.0, 9.0, 9.0]}
    table_path(root, "calibrated_sensor").write_text(json.dumps([*rows(root, "calibrated_sensor"), copy]))
    edit(root, "sample_data", sd["token"], calibrated_sensor_token=copy["token"])
    with pytest.raises(NuScenesError) as e:
        load(root)
    assert str(e.value).startswith(f"{table_path(root, 'sample_data')}: sample_data {sd['token']!r}: ")
    assert f"its calibrated sensor {copy['token']!r}" in str(e.value)
    scene, frames = load(root, "skip")
    assert skipped(scene) == [f"sample_data {sd['token']}"]
    assert camera_count(frames, "CAM_BACK_LEFT") == STEPS - 1
    np.testing.assert_allclose(scene.calibration("CAM_BACK_LEFT").ego_from_camera[:3, 3], cs["translation"])
