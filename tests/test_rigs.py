"""Rigs to re-render a cache with (phigenesis.infer.rigs): the named rigs are the synthetic ones without
distortion, a YAML rig file round-trips and is refused by file, camera and field when wrong, and
random rigs stay within their ranges, upright and reproducible."""

from __future__ import annotations

import copy
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import geometry
from phigenesis.data.ego_body import WAYMO_PACIFICA_BOXES, sensor_in_box
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.sources.synthetic.rigs import RIGS, camera_calibrations
from phigenesis.data.stages.aggregate import DEFAULT_EGO_BOXES
from phigenesis.infer.rigs import (
    NAMED_RIGS,
    RandomRigRanges,
    Rig,
    RigError,
    check_rig,
    ego_from_angles,
    load_rig_file,
    named_rig,
    random_rig,
    resolve_rig,
)

H, W = 60, 90


def _write(path: Path, d: Any) -> Path:
    path.write_text(yaml.safe_dump(d))
    return path


def _optical_yaw_pitch_deg(ego_from_camera: np.ndarray) -> tuple[float, float]:
    """Azimuth (0 forward, +90 left) and downward tilt of a camera's optical axis, degrees."""
    axis = ego_from_camera[:3, 2]
    return math.degrees(math.atan2(axis[1], axis[0])), math.degrees(math.asin(-axis[2]))


# --------------------------------------------------------------------------------------------
# Named rigs


@pytest.mark.parametrize("name", NAMED_RIGS)
def test_named_rigs_are_the_synthetic_rigs_as_pinhole_cameras(name: str) -> None:
    rig = named_rig(name, H, W)
    synthetic, _ = camera_calibrations(name, H, W)
    assert rig.name == name and rig.seed is None
    assert [c.name for c in rig.cameras] == [c.name for c in synthetic]
    for ours, theirs in zip(rig.cameras, synthetic, strict=True):
        assert (ours.height, ours.width) == (H, W)
        np.testing.assert_array_equal(ours.intrinsics, theirs.intrinsics)
        np.testing.assert_array_equal(ours.ego_from_camera, theirs.ego_from_camera)
        np.testing.assert_array_equal(ours.distortion, np.zeros(5))


@pytest.mark.parametrize("name", NAMED_RIGS)
def test_named_rigs_fire_when_the_synthetic_rig_fires(name: str) -> None:
    scene = SyntheticScene(SyntheticConfig(rig=name, frames=2), 0)
    frame_micros = 1_700_000_000_000_000
    expected = [scene.camera_time_micros(frame_micros, i) - frame_micros for i in range(len(scene.specs))]
    assert list(named_rig(name, H, W).time_offsets_micros) == expected
    assert len(set(expected)) == len(expected)  # a rolling rig: no two cameras at once


def test_an_unknown_rig_name_is_refused() -> None:
    with pytest.raises(RigError, match=r"'waymo6'.*waymo5.*nuscenes6"):
        named_rig("waymo6", H, W)


# --------------------------------------------------------------------------------------------
# Dicts and YAML files


def test_to_dict_and_from_dict_round_trip_exactly_through_json() -> None:
    for rig in (named_rig("waymo5", H, W), random_rig(named_rig("nuscenes6", H, W), RandomRigRanges(), 9)):
        d = json.loads(json.dumps(rig.to_dict()))
        back = Rig.from_dict(d)
        assert back == rig and back.to_dict() == rig.to_dict() and back.seed == rig.seed
        for a, b in zip(back.cameras, rig.cameras, strict=True):
            np.testing.assert_array_equal(a.intrinsics, b.intrinsics)
            np.testing.assert_array_equal(a.ego_from_camera, b.ego_from_camera)
        assert back.time_offsets_micros == rig.time_offsets_micros


def test_a_yaml_file_written_from_to_dict_loads_back_equal(tmp_path: Path) -> None:
    rig = named_rig("nuscenes6", H, W)
    path = _write(tmp_path / "copy.yaml", rig.to_dict())
    loaded = load_rig_file(path)
    assert loaded == rig and loaded.name == "nuscenes6"
    assert loaded != named_rig("nuscenes6", H, W + 2)


@pytest.mark.parametrize("name", NAMED_RIGS)
def test_a_yaml_with_position_yaw_and_pitch_reproduces_the_synthetic_mounting(
    name: str, tmp_path: Path
) -> None:
    synthetic, specs = camera_calibrations(name, H, W)
    cameras = [
        {
            "name": s.name,
            "width": W,
            "height": H,
            "fx": float(c.intrinsics[0, 0]),
            "fy": float(c.intrinsics[1, 1]),
            "cx": float(c.intrinsics[0, 2]),
            "cy": float(c.intrinsics[1, 2]),
            "position_m": list(s.position_m),
            "yaw_deg": s.yaw_deg,
            "pitch_deg": s.pitch_deg,
        }
        for c, s in zip(synthetic, specs, strict=True)
    ]
    rig = load_rig_file(_write(tmp_path / "by_angles.yaml", {"cameras": cameras}))
    assert rig.name == "by_angles" and rig.time_offsets_micros == (0,) * len(specs)
    for ours, theirs in zip(rig.cameras, synthetic, strict=True):
        np.testing.assert_allclose(ours.ego_from_camera, theirs.ego_from_camera, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(ours.intrinsics, theirs.intrinsics)


def test_roll_turns_the_image_top_to_the_right() -> None:
    t = ego_from_angles([1.0, 2.0, 3.0], yaw_deg=0.0, roll_deg=90.0)
    up_in_ego = t[:3, :3] @ np.array([0.0, -1.0, 0.0])  # camera -y is the image's top
    np.testing.assert_allclose(up_in_ego, [0.0, -1.0, 0.0], atol=1e-15)  # ego -y: right
    np.testing.assert_allclose(t[:3, 2], [1.0, 0.0, 0.0], atol=1e-15)  # still looking forward
    np.testing.assert_array_equal(t[:3, 3], [1.0, 2.0, 3.0])


def _nan_intrinsic(d: dict) -> None:
    d["cameras"][1]["intrinsics"][0][0] = float("nan")


def _scaled_rotation(d: dict) -> None:
    m = np.array(d["cameras"][1]["ego_from_camera"])
    m[:3, :3] *= 1.1
    d["cameras"][1]["ego_from_camera"] = m.tolist()


def _set(camera: int, key: str, value: Any):  # type: ignore[no-untyped-def]
    def mutate(d: dict) -> None:
        d["cameras"][camera][key] = value

    return mutate


def _drop(camera: int, key: str):  # type: ignore[no-untyped-def]
    def mutate(d: dict) -> None:
        del d["cameras"][camera][key]

    return mutate


REFUSALS = {
    "nan intrinsic": (_nan_intrinsic, r"camera 1 \(FRONT_LEFT\) intrinsics must be finite"),
    "scaled rotation": (_scaled_rotation, r"camera 1 \(FRONT_LEFT\).*ego_from_camera is not a rigid"),
    "inf translation": (
        _set(2, "ego_from_camera", [[0, 0, 1, float("inf")], [-1, 0, 0, 0], [0, -1, 0, 2], [0, 0, 0, 1]]),
        r"camera 2 \(FRONT_RIGHT\) ego_from_camera must be finite",
    ),
    "unknown key": (_set(0, "hfov_deg", 50.0), r"camera 0 \(FRONT\): unknown field hfov_deg"),
    "missing width": (_drop(3, "width"), r"camera 3 \(SIDE_LEFT\): missing field width"),
    "missing extrinsics": (_drop(0, "ego_from_camera"), r"camera 0 \(FRONT\): missing field ego_from_camera"),
    "negative focal length": (
        _set(4, "intrinsics", [[-50.0, 0, 44.5], [0, 50.0, 29.5], [0, 0, 1]]),
        r"camera 4 \(SIDE_RIGHT\) intrinsics: focal lengths must be positive",
    ),
    "width too small": (_set(0, "width", 4), r"camera 0 \(FRONT\) width is 4 pixels"),
    "height not an integer": (_set(0, "height", "60"), r"camera 0 \(FRONT\) height must be an integer"),
    "bad distortion": (_set(1, "distortion", [0.1, 0.0]), r"camera 1 \(FRONT_LEFT\) distortion must be 5"),
    "offset beyond 1 s": (
        _set(2, "time_offset_micros", 1_000_001),
        r"camera 2 \(FRONT_RIGHT\) time_offset_micros: 1000001",
    ),
    "duplicate names": (_set(3, "name", "FRONT"), r"camera 3 \(FRONT\) name: duplicate, camera 0"),
    "both intrinsics forms": (_set(0, "fx", 50.0), r"camera 0 \(FRONT\): give intrinsics or fx"),
}


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_a_bad_rig_file_is_refused_naming_the_file_the_camera_and_the_field(
    case: str, tmp_path: Path
) -> None:
    mutate, message = REFUSALS[case]
    d = copy.deepcopy(named_rig("waymo5", H, W).to_dict())
    mutate(d)
    path = _write(tmp_path / "bad_rig.yaml", d)
    with pytest.raises(RigError, match=rf"^{re.escape(str(path))}: {message}"):
        load_rig_file(path)
    with pytest.raises(RigError, match=message):  # from_dict refuses the same dict the same way
        Rig.from_dict(d)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("- FRONT\n- BACK\n", "must hold a mapping"),
        ("name: empty\ncameras: []\n", "cameras must be a list of 1 to 32 cameras, got 0 cameras"),
        ("name: x\ncamera: []\n", "unknown field camera"),
        ("cameras: [\n", "not a YAML rig file"),
    ],
)
def test_a_rig_file_that_is_no_rig_is_refused(text: str, message: str, tmp_path: Path) -> None:
    path = tmp_path / "not_a_rig.yaml"
    path.write_text(text)
    with pytest.raises(RigError, match=rf"^{re.escape(str(path))}: .*{message}"):
        load_rig_file(path)


def test_a_yaml_python_object_tag_is_refused_and_runs_nothing(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    path = tmp_path / "evil.yaml"
    path.write_text(f'cameras: !!python/object/apply:os.system ["touch {marker}"]\n')
    with pytest.raises(RigError, match=rf"^{re.escape(str(path))}: not a YAML rig file"):
        load_rig_file(path)
    assert not marker.exists()


def test_too_many_cameras_and_too_large_files_are_refused(tmp_path: Path) -> None:
    d = named_rig("waymo5", H, W).to_dict()
    camera = d["cameras"][0]
    d["cameras"] = [{**camera, "name": f"CAM_{i}"} for i in range(33)]
    with pytest.raises(RigError, match=r"many.yaml: cameras must be a list of 1 to 32 cameras, got 33"):
        load_rig_file(_write(tmp_path / "many.yaml", d))
    d["cameras"] = d["cameras"][:32]
    assert len(load_rig_file(_write(tmp_path / "many.yaml", d)).cameras) == 32
    big = tmp_path / "big.yaml"
    big.write_text(yaml.safe_dump(named_rig("waymo5", H, W).to_dict()) + "#" * (1 << 20) + "\n")
    with pytest.raises(RigError, match=r"big.yaml: larger than 1048576 bytes"):
        load_rig_file(big)


def test_a_camera_inside_the_ego_body_is_refused_naming_the_camera_and_the_box(tmp_path: Path) -> None:
    d = named_rig("waymo5", H, W).to_dict()
    d["cameras"][0]["ego_from_camera"][2][3] = 0.8  # FRONT lowered into the default body (z 0 .. 1 m)
    path = _write(tmp_path / "in_body.yaml", d)
    rig = load_rig_file(path)  # no body given: fine
    where = re.escape(str(path))
    message = r"camera 0 \(FRONT\) ego_from_camera: its centre \(1.550, 0.000, 0.800\) m \(ego frame\)"
    with pytest.raises(RigError, match=rf"^{where}: {message} lies inside ego body box 0"):
        resolve_rig(str(path), base=rig, height=H, width=W, ego_boxes=DEFAULT_EGO_BOXES)
    assert check_rig(named_rig("waymo5", H, W), DEFAULT_EGO_BOXES).name == "waymo5"
    assert check_rig(named_rig("waymo5", H, W), WAYMO_PACIFICA_BOXES).name == "waymo5"


def test_check_rig_refuses_a_rig_without_cameras_or_with_offsets_missing() -> None:
    rig = named_rig("waymo5", H, W)
    with pytest.raises(RigError, match=r"^mine: cameras: the rig has no camera"):
        check_rig(Rig("empty", (), ()), where="mine")
    with pytest.raises(RigError, match=r"^rig: time_offsets_micros: 4 offsets for 5 cameras"):
        check_rig(Rig("short", rig.cameras, rig.time_offsets_micros[:4]))


# --------------------------------------------------------------------------------------------
# Random rigs

BASES = {name: named_rig(name, H, W) for name in NAMED_RIGS}


def test_random_rigs_are_reproducible_per_seed_and_differ_across_seeds() -> None:
    base, ranges = BASES["waymo5"], RandomRigRanges()
    a, b, c = random_rig(base, ranges, 5), random_rig(base, ranges, 5), random_rig(base, ranges, 6)
    assert a == b and a != c
    assert a.name == "random" and a.seed == 5 and c.seed == 6
    assert [x.name for x in a.cameras] == [x.name for x in base.cameras]
    assert a.time_offsets_micros == base.time_offsets_micros


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), base_name=st.sampled_from(NAMED_RIGS))
def test_random_rigs_stay_within_their_ranges_and_upright(seed: int, base_name: str) -> None:
    base, r = BASES[base_name], RandomRigRanges()
    rig = random_rig(base, r, seed)
    sizes = {(c.height, c.width) for c in rig.cameras}
    assert len(sizes) == 1 and sizes <= set(r.sizes_hw)
    for cal, old in zip(rig.cameras, base.cameras, strict=True):
        k, h, w = cal.intrinsics, cal.height, cal.width
        assert k[0, 0] == k[1, 1] and (k[0, 2], k[1, 2]) == ((w - 1) / 2, (h - 1) / 2)
        hfov = math.degrees(2 * math.atan(0.5 * w / k[0, 0]))
        assert r.hfov_deg[0] - 1e-9 <= hfov <= r.hfov_deg[1] + 1e-9
        np.testing.assert_array_equal(cal.distortion, np.zeros(5))
        rot, centre = cal.ego_from_camera[:3, :3], cal.ego_from_camera[:3, 3]
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)
        assert abs(rot[2, 0]) < 1e-15  # the image x axis is horizontal: no roll
        assert r.height_m[0] <= centre[2] <= r.height_m[1]
        assert centre[0] == old.ego_from_camera[0, 3]
        dy = centre[1] - old.ego_from_camera[1, 3]
        assert r.lateral_offset_m[0] - 1e-12 <= dy <= r.lateral_offset_m[1] + 1e-12
        yaw, pitch = _optical_yaw_pitch_deg(cal.ego_from_camera)
        base_yaw, _ = _optical_yaw_pitch_deg(old.ego_from_camera)
        jitter = math.degrees(geometry.angle_difference(math.radians(yaw), math.radians(base_yaw)))
        assert r.yaw_jitter_deg[0] - 1e-9 <= jitter <= r.yaw_jitter_deg[1] + 1e-9
        assert r.pitch_deg[0] - 1e-9 <= pitch <= r.pitch_deg[1] + 1e-9


def test_random_rigs_without_extrinsics_keep_the_base_mountings() -> None:
    base = BASES["nuscenes6"]
    ranges = RandomRigRanges(hfov_deg=(30.0, 31.0), extrinsics=False, sizes_hw=((100, 200),))
    rig = random_rig(base, ranges, 11)
    for cal, old in zip(rig.cameras, base.cameras, strict=True):
        np.testing.assert_array_equal(cal.ego_from_camera, old.ego_from_camera)
        assert (cal.height, cal.width) == (100, 200) != (old.height, old.width)
        assert not np.array_equal(cal.intrinsics, old.intrinsics)
        assert 0.5 * 200 / math.tan(math.radians(31.0 / 2)) <= cal.intrinsics[0, 0]
        assert cal.intrinsics[0, 0] <= 0.5 * 200 / math.tan(math.radians(30.0 / 2))


def test_random_rigs_given_a_body_redraw_the_cameras_it_would_hold() -> None:
    base = BASES["waymo5"]
    ranges = RandomRigRanges(height_m=(1.0, 2.2))  # the van's cabin reaches 1.777 m
    inside = 0
    for seed in range(20):
        free = random_rig(base, ranges, seed)
        inside += sum(
            any(sensor_in_box(c.ego_from_camera[:3, 3], b) for b in WAYMO_PACIFICA_BOXES)
            for c in free.cameras
        )
        rig = resolve_rig(
            "random", base=base, height=H, width=W, seed=seed, ranges=ranges, ego_boxes=WAYMO_PACIFICA_BOXES
        )
        for cal in rig.cameras:
            assert not any(sensor_in_box(cal.ego_from_camera[:3, 3], b) for b in WAYMO_PACIFICA_BOXES)
    assert inside > 10  # without the body, the draws do land in it
    with pytest.raises(
        RigError, match=r"camera 0 \(FRONT\) ego_from_camera: 100 draws .* inside the ego body"
    ):
        random_rig(base, RandomRigRanges(height_m=(1.1, 1.7)), 0, ego_boxes=WAYMO_PACIFICA_BOXES)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"hfov_deg": (80.0, 60.0)}, "hfov_deg: must be finite with lo <= hi"),
        ({"hfov_deg": (0.5, 60.0)}, r"hfov_deg: \(0.5, 60.0\) must lie within \(1, 170\)"),
        ({"hfov_deg": (60.0, 175.0)}, r"hfov_deg: .* must lie within \(1, 170\)"),
        ({"pitch_deg": (float("nan"), 1.0)}, "pitch_deg: must be finite"),
        ({"sizes_hw": ((4, 100),)}, r"sizes_hw: .* must be \(height, width\) in \[8, 4096\]"),
        ({"sizes_hw": ()}, "sizes_hw"),
    ],
)
def test_random_rig_ranges_are_checked(kwargs: dict, message: str) -> None:
    with pytest.raises(RigError, match=message):
        RandomRigRanges(**kwargs)


def test_a_random_rig_needs_a_non_negative_integer_seed() -> None:
    with pytest.raises(RigError, match="seed must be a non-negative integer, got -1"):
        random_rig(BASES["waymo5"], RandomRigRanges(), -1)


# --------------------------------------------------------------------------------------------
# resolve_rig


def test_resolve_rig_takes_names_random_and_files(tmp_path: Path) -> None:
    base = BASES["waymo5"]
    for name in NAMED_RIGS:
        assert resolve_rig(name, base=base, height=H, width=W) == named_rig(name, H, W)
    assert resolve_rig("random", base=base, height=H, width=W, seed=3) == random_rig(
        base, RandomRigRanges(), 3
    )
    narrow = RandomRigRanges(hfov_deg=(45.0, 45.0))
    assert resolve_rig("random", base=base, height=H, width=W, seed=3, ranges=narrow) == random_rig(
        base, narrow, 3
    )
    d = named_rig("nuscenes6", 48, 72).to_dict() | {"name": "file_rig"}
    path = _write(tmp_path / "mine.yaml", d)
    rig = resolve_rig(str(path), base=base, height=H, width=W, ego_boxes=DEFAULT_EGO_BOXES)
    assert rig.name == "file_rig" and rig == load_rig_file(path)
    assert set(RIGS) == set(NAMED_RIGS)


def test_resolve_rig_refuses_an_unknown_name_naming_the_choices(tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    for spec in ("waymo6", str(missing)):
        choices = "waymo5, nuscenes6, random or a YAML rig file"
        with pytest.raises(RigError, match=rf"^rig '{re.escape(spec)}': no such rig file.*{choices}"):
            resolve_rig(spec, base=BASES["waymo5"], height=H, width=W)
