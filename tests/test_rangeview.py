"""Tests for the camera range view, the LiDAR range image, their cache columns, loader groups and preview."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import geometry, prep
from phigenesis.data import loader_rangeview
from phigenesis.data.lidar_range import (
    EMPTY,
    azimuth_columns,
    estimate_columns,
    lidar_range_image,
    range_image_points,
)
from phigenesis.data.loader import FrameDataset
from phigenesis.data.pipeline import PipelineSpec, load_pipeline
from phigenesis.data.preview import draw_frame
from phigenesis.data.rangeview import (
    NO_VIEW,
    camera_rays_ego,
    pack_range_view,
    range_view_layout,
    to_camera,
    undistorted_pixel_rays,
)
from phigenesis.data.records import Boxes, CameraCalibration, Frame, LidarSweep, Scene
from phigenesis.data.schema import CacheContents, cameras_of, frame_schema, frame_to_batch, row_to_frame
from phigenesis.data.shards import CacheReader
from phigenesis.data.sources.synthetic import synthetic_scene
from phigenesis.data.stages import get_stage
from tests.conftest import TINY_PREP_ARGS, tiny_config


def staged_frame(rig: str, uniform: bool) -> Frame:
    scene = synthetic_scene(tiny_config(rig=rig, uniform_image_size=uniform, scenes=1, frames=2), 0)
    scene = get_stage("range_view")(scene, {})
    scene = get_stage("lidar_range_image")(scene, {})
    return scene.frames[1]


@pytest.fixture(scope="module")
def waymo_frame() -> Frame:
    """Waymo-like rig with shorter side cameras (different image sizes)."""
    return staged_frame("waymo5", uniform=False)


@pytest.fixture(scope="module")
def nuscenes_frame() -> Frame:
    """nuScenes-like rig covering 360 degrees."""
    return staged_frame("nuscenes6", uniform=True)


def calibration(
    name: str, yaw_deg: float, hfov_deg: float, height: int, width: int, pitch_deg: float = 0.0
) -> CameraCalibration:
    """A pinhole camera at the ego origin looking at azimuth ``yaw_deg``, pitched down ``pitch_deg``."""
    fx = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    k = geometry.intrinsic_matrix(fx, fx, (width - 1) / 2, (height - 1) / 2)
    p = np.radians(pitch_deg)
    pitch = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    body = geometry.rotation_z(np.radians(yaw_deg)) @ pitch
    return CameraCalibration(
        name,
        width,
        height,
        k,
        np.zeros(5),
        geometry.make_transform(body @ geometry.BODY_FROM_OPENCV, [0, 0, 1.5]),
    )


# --------------------------------------------------------------------------------------------
# Camera range view


@pytest.mark.parametrize("which", ["waymo_frame", "nuscenes_frame"])
def test_pack_then_unpack_returns_every_pixel_of_every_view_unchanged(which: str, request) -> None:
    frame: Frame = request.getfixturevalue(which)
    rv = pack_range_view(frame, depth_sources=("truth",))
    layout = rv.layout
    assert rv.depth_source == "truth" and rv.semantic_source == "truth"
    cams = {c.name: c for c in frame.cameras}
    for plane, per_camera in (
        (rv.rgb, lambda c: c.decode_image()),
        (rv.depth_m, lambda c: c.truth.depth_m),
        (rv.semantic, lambda c: c.truth.semantic),
        (rv.rays_ego, camera_rays_ego),
    ):
        views = layout.unpack(plane)
        for name, view in zip(layout.camera_names, views, strict=True):
            cam = cams[name]
            expected = per_camera(cam.calibration if per_camera is camera_rays_ego else cam)
            assert view.dtype == expected.dtype and np.array_equal(view, expected), name
    assert rv.valid.sum() == sum(c.calibration.width * c.calibration.height for c in frame.cameras)
    assert sorted(layout.camera_names) == sorted(cams)


def test_views_go_left_to_right_by_decreasing_azimuth_and_tile_the_width(nuscenes_frame: Frame) -> None:
    layout = range_view_layout([c.calibration for c in nuscenes_frame.cameras])
    azimuths = [p.axis_azimuth_rad for p in layout.views]
    assert azimuths == sorted(azimuths, reverse=True)
    assert layout.camera_names[2] == "CAM_FRONT" and layout.camera_names[-1] == "CAM_BACK"
    assert [p.col0 for p in layout.views] == list(np.cumsum([0] + [p.width for p in layout.views[:-1]]))
    assert layout.width == sum(p.width for p in layout.views)
    for p in layout.views:
        assert p.azimuth_min_rad < p.axis_azimuth_rad < p.azimuth_max_rad


def test_horizon_alignment_centres_the_shorter_side_cameras(waymo_frame: Frame) -> None:
    layout = waymo_frame.range_view
    rows = {p.camera_name: (p.row0, p.height) for p in layout.views}
    assert rows["FRONT"] == (0, 60) and layout.height == 60
    side_row0, side_height = rows["SIDE_LEFT"]
    assert side_height < 60 and side_row0 == round((60 - side_height) / 2)
    assert (layout.view_index() == NO_VIEW).sum() == 2 * (60 - side_height) * 90
    top = range_view_layout([c.calibration for c in waymo_frame.cameras], align="top")
    assert all(p.row0 == 0 for p in top.views)


def brute_force_overlap(layout, cals: list[CameraCalibration]) -> tuple[np.ndarray, np.ndarray]:
    """Reference owner and coverage maps: every cell's ray projected into every camera."""
    owner = np.full((layout.height, layout.width), NO_VIEW, np.uint8)
    coverage = np.zeros_like(owner)
    for k, p in enumerate(layout.views):
        rays = camera_rays_ego(cals[k]).reshape(-1, 3).astype(np.float64)
        cos = np.full((len(cals), len(rays)), -np.inf)
        for j, cal in enumerate(cals):
            in_camera = to_camera(rays, cal)
            uv, ok = geometry.project_points(in_camera, cal.intrinsics, cal.distortion)
            seen = ok & geometry.in_image(uv, cal.width, cal.height)
            seen |= j == k
            cos[j, seen] = in_camera[seen, 2]
        owner[p.rows, p.cols] = np.argmax(cos, axis=0).reshape(p.height, p.width)  # first of equals
        coverage[p.rows, p.cols] = np.isfinite(cos).sum(axis=0).reshape(p.height, p.width)
    return owner, coverage


@pytest.mark.parametrize("which", ["waymo_frame", "nuscenes_frame"])
def test_overlap_owner_is_the_view_whose_optical_axis_is_nearest(which: str, request) -> None:
    frame: Frame = request.getfixturevalue(which)
    layout = frame.range_view
    by_name = {c.name: c.calibration for c in frame.cameras}
    owner, coverage = brute_force_overlap(layout, [by_name[n] for n in layout.camera_names])
    assert np.array_equal(layout.owner, owner) and np.array_equal(layout.coverage, coverage)
    assert (layout.coverage >= 2).any() and layout.primary().sum() < layout.valid().sum()


@pytest.mark.parametrize(
    "distortion", [(0.035, -0.012, 0.0004, -0.0003, 0.0), (-0.45, 0.2, 0.01, -0.01, -0.05)]
)
def test_pixel_rays_match_the_toolkit_unprojection(distortion) -> None:
    cal = dataclasses.replace(calibration("D", 0.0, 100.0, 30, 40), distortion=np.array(distortion))
    reference = geometry.unproject_pixels(geometry.pixel_grid(40, 30), cal.intrinsics, cal.distortion)
    assert np.abs(undistorted_pixel_rays(cal) - reference).max() < 1e-10  # ~1e-9 px


def test_a_frame_missing_a_camera_gets_the_layout_of_the_cameras_it_has(nuscenes_frame: Frame) -> None:
    dropped = dataclasses.replace(
        nuscenes_frame, cameras=nuscenes_frame.cameras[:3] + nuscenes_frame.cameras[4:]
    )
    scene = Scene("s", "synthetic", [c.calibration for c in nuscenes_frame.cameras], [dropped])
    layout = get_stage("range_view")(scene, {}).frames[0].range_view
    assert len(layout.views) == 5 and "CAM_BACK" not in layout.camera_names
    assert pack_range_view(scene.frames[0]).valid.sum() == 5 * 60 * 90
    with pytest.raises(ValueError, match="align"):
        get_stage("range_view")(scene, {"align": "bottom"})


def test_a_single_camera_owns_all_its_cells() -> None:
    layout = range_view_layout([calibration("ONLY", 30.0, 60.0, 12, 20)])
    assert (layout.height, layout.width) == (12, 20)
    assert (layout.owner == 0).all() and (layout.coverage == 1).all() and layout.primary().all()
    plane = np.arange(12 * 20, dtype=np.int32).reshape(12, 20)
    assert np.array_equal(layout.unpack(layout.pack([plane]))[0], plane)


def test_a_gap_between_views_shows_in_their_azimuth_ranges_not_as_overlap() -> None:
    layout = range_view_layout(
        [calibration("LEFT", 90.0, 50.0, 10, 16), calibration("RIGHT", -90.0, 50.0, 10, 16)]
    )
    left, right = layout.views
    assert left.camera_name == "LEFT" and right.col0 == 16
    assert right.azimuth_max_rad < left.azimuth_min_rad - np.radians(60)
    assert (layout.coverage == 1).all() and layout.primary().all()


def test_pack_names_the_view_of_a_plane_with_the_wrong_size() -> None:
    layout = range_view_layout([calibration("A", 0.0, 60.0, 10, 16)])
    with pytest.raises(ValueError, match="view A"):
        layout.pack([np.zeros((10, 15), np.uint8)])


@settings(max_examples=30, deadline=None)
@given(
    cameras=st.lists(
        st.tuples(
            st.floats(-179.0, 179.0),  # yaw
            st.floats(20.0, 120.0),  # horizontal field of view
            st.integers(2, 16),  # height
            st.integers(2, 24),  # width
            st.floats(-60.0, 60.0),  # pitch (steep ones see a pole)
        ),
        min_size=1,
        max_size=5,
    ),
    align=st.sampled_from(["horizon", "top"]),
)
def test_any_rig_packs_and_unpacks_exactly(cameras, align) -> None:
    cals = [calibration(f"C{i}", *spec) for i, spec in enumerate(cameras)]
    layout = range_view_layout(cals, align)
    rng = np.random.default_rng(len(cals))
    by_name = {c.name: c for c in cals}
    planes = [
        rng.integers(0, 255, (by_name[n].height, by_name[n].width, 3), dtype=np.uint8)
        for n in layout.camera_names
    ]
    packed = layout.pack(planes, fill=7)
    for a, b in zip(layout.unpack(packed), planes, strict=True):
        assert np.array_equal(a, b)
    valid = layout.valid()
    assert valid.sum() == sum(c.width * c.height for c in cals)  # views never overlap in cells
    assert (packed[~valid] == 7).all()
    assert ((layout.owner == NO_VIEW) == ~valid).all() and ((layout.coverage == 0) == ~valid).all()
    assert min(p.row0 for p in layout.views) == 0
    owner, coverage = brute_force_overlap(layout, [by_name[n] for n in layout.camera_names])
    assert np.array_equal(layout.owner, owner) and np.array_equal(layout.coverage, coverage)


# --------------------------------------------------------------------------------------------
# LiDAR range image


def sweep_of(points: np.ndarray, beams: np.ndarray, origins: np.ndarray | None = None) -> LidarSweep:
    n = len(points)
    return LidarSweep(
        timestamp_micros=0,
        world_from_ego=np.eye(4),
        points_ego=points.astype(np.float32),
        intensity=np.linspace(0, 1, n, dtype=np.float32),
        beam_index=beams.astype(np.uint16),
        origins_ego=np.zeros((n, 3), np.float32) if origins is None else origins.astype(np.float32),
        time_offset_micros=np.zeros(n, np.int32),
        lidar_id=np.zeros(n, np.uint8),
    )


def test_lidar_range_image_round_trips_the_points_within_the_bin(waymo_frame: Frame) -> None:
    sweep, image = waymo_frame.lidar, waymo_frame.lidar_range_image
    assert (image.height, image.width) == (16, 256)  # TINY_LIDAR, estimated by the stage
    kept = image.point_index[image.valid]
    d = sweep.points_ego[kept].astype(np.float64) - sweep.origins_ego[kept]
    assert np.array_equal(image.range_m[image.valid], np.linalg.norm(d, axis=1).astype(np.float32))
    assert np.array_equal(image.intensity[image.valid], sweep.intensity[kept])
    points, rows, cols = range_image_points(image)
    assert np.array_equal(image.point_index[rows, cols], kept)
    azimuth_error = geometry.angle_difference(np.arctan2(d[:, 1], d[:, 0]), image.column_azimuths_rad()[cols])
    assert np.abs(azimuth_error).max() <= np.pi / image.width + 1e-9
    elevation = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    assert np.abs(elevation - image.beam_inclination_rad[rows]).max() < 1e-4  # synthetic beams are exact
    rng = np.linalg.norm(d, axis=1)
    bound = rng * (np.pi / image.width + 1e-4) + np.linalg.norm(
        image.column_origin_ego[cols] - sweep.origins_ego[kept], axis=1
    )
    assert (np.linalg.norm(points - sweep.points_ego[kept], axis=1) <= bound + 1e-4).all()
    assert image.valid.sum() + len(image.overflow_index) == len(sweep)


def test_a_collision_keeps_the_nearest_point_and_lists_the_others() -> None:
    direction = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    points = np.stack([12.0 * direction, 5.0 * direction, 9.0 * direction, -3.0 * direction])
    image = lidar_range_image(sweep_of(points, np.array([1, 1, 1, 0])), beams=2, columns=64)
    cell = 1 * 64 + azimuth_columns(np.array([0.3]), 64)[0]
    assert image.point_index.reshape(-1)[cell] == 1  # the 5 m point
    assert image.range_m.reshape(-1)[cell] == np.float32(5.0)
    assert list(image.overflow_index) == [2, 0] and list(image.overflow_cell) == [cell, cell]  # nearest first
    assert image.valid.sum() == 2


def test_an_empty_sweep_gives_an_empty_image() -> None:
    image = lidar_range_image(LidarSweep.empty(0, np.eye(4)), beams=4, columns=32)
    assert (image.point_index == EMPTY).all() and (image.range_m == 0).all()
    assert np.isnan(image.beam_inclination_rad).all() and np.isnan(image.column_origin_ego).all()
    assert len(image.overflow_index) == 0 and range_image_points(image)[0].shape == (0, 3)


def test_column_zero_starts_just_left_of_the_rear_and_the_front_is_in_the_middle() -> None:
    assert azimuth_columns(np.array([np.pi - 1e-6, 1e-6, -1e-6, -np.pi + 1e-6]), 8).tolist() == [0, 3, 4, 7]


def test_columns_are_estimated_from_the_sweep(nuscenes_frame: Frame) -> None:
    assert estimate_columns(nuscenes_frame.lidar) == 256


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 200),
    columns=st.integers(1, 64),
    seed=st.integers(0, 2**16),
)
def test_every_point_is_kept_or_listed_and_kept_points_are_the_nearest(
    n: int, columns: int, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    points = rng.normal(0, 10, (n, 3))
    origins = rng.normal(0, 0.5, (n, 3))
    beams = rng.integers(0, 5, n)
    image = lidar_range_image(sweep_of(points, beams, origins), beams=4, columns=columns)
    kept = image.point_index[image.valid]
    in_image = np.flatnonzero(beams < 4)
    assert sorted(np.concatenate([kept, image.overflow_index]).tolist()) == in_image.tolist()
    ranges = np.linalg.norm(points.astype(np.float32).astype(np.float64) - origins.astype(np.float32), axis=1)
    flat = image.point_index.reshape(-1)
    for i, cell in zip(image.overflow_index, image.overflow_cell, strict=True):
        assert np.float32(ranges[flat[cell]]) <= np.float32(ranges[i])


# --------------------------------------------------------------------------------------------
# Cache columns, loader groups, pipeline


def test_schema_round_trip_keeps_layout_and_range_image(waymo_frame: Frame) -> None:
    schema = frame_schema(CacheContents(range_view=True, lidar_range_image=True))
    back = row_to_frame(frame_to_batch(waymo_frame, "synthetic", schema))
    assert back.range_view == waymo_frame.range_view
    for f in dataclasses.fields(back.lidar_range_image):
        a, b = getattr(back.lidar_range_image, f.name), getattr(waymo_frame.lidar_range_image, f.name)
        assert np.array_equal(a, b, equal_nan=True), f.name
    plain = frame_schema(CacheContents())
    assert "range_view" not in plain.names and "lidar_range_image" not in plain.names
    unstaged = dataclasses.replace(waymo_frame, range_view=None, lidar_range_image=None)
    back = row_to_frame(frame_to_batch(unstaged, "synthetic", schema))
    assert back.range_view is None and back.lidar_range_image is None


def test_a_range_image_without_the_sweep_is_refused() -> None:
    with pytest.raises(ValueError, match="needs lidar"):
        CacheContents(lidar=False, lidar_range_image=True)


def documented_keys() -> dict[str, str]:
    """key -> type from the tables in loader_rangeview's docstring."""
    entries = {}
    for line in (loader_rangeview.__doc__ or "").splitlines():
        m = re.match(r"^((?:range_view|lidar_range)\w*)\s+(\w+(?:\[\w+\])?(?: \[[^\]]*\])?)", line)
        if m:
            entries[m.group(1)] = m.group(2)
    return entries


@pytest.fixture(scope="module")
def range_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One scene of 2 frames with the range-view stages and columns (no depth stages: fast)."""
    spec = load_pipeline("synthetic").to_dict()
    spec["stages"] = [{"name": "range_view", "params": {}}, {"name": "lidar_range_image", "params": {}}]
    spec["output"].update(depth=False, range_view=True, lidar_range_image=True)
    out = tmp_path_factory.mktemp("range_cache")
    args = {**TINY_PREP_ARGS, "scenes": 1, "frames": 2}
    prep.synthetic(out, pipeline=PipelineSpec.from_dict(spec), progress=False, **args)  # type: ignore[arg-type]
    return out


def test_loader_groups_hold_the_documented_keys_and_match_the_records(range_cache: Path) -> None:
    ds = FrameDataset(range_cache, fields=("range_view", "lidar_range_image"))
    sample, frame = ds[1], CacheReader(range_cache).frame(1)
    entries = documented_keys()
    assert set(sample) - {
        "scene_id",
        "frame_index",
        "frame_timestamp_micros",
        "world_from_ego",
        "camera_names",
    } == set(entries) - {"range_view_depth", "range_view_depth_source"}  # this cache has no depth
    for key, spec in entries.items():
        if key in sample and isinstance(sample[key], torch.Tensor):
            assert str(sample[key].dtype).removeprefix("torch.") == spec.split(" ")[0], key
    rv = pack_range_view(frame)
    assert frame.range_view is not None and rv.layout == frame.range_view
    assert np.array_equal(sample["range_view_rgb"].permute(1, 2, 0).numpy(), rv.rgb)
    assert np.array_equal(sample["range_view_semantic"].numpy(), rv.semantic)
    assert np.array_equal(sample["range_view_rays_ego"].permute(1, 2, 0).numpy(), rv.rays_ego)
    assert np.array_equal(sample["range_view_view_index"].numpy(), rv.view_index)
    assert sample["range_view_cameras"] == rv.layout.camera_names
    image = frame.lidar_range_image
    assert np.array_equal(sample["lidar_range"].numpy(), image.range_m)
    assert np.array_equal(sample["lidar_range_index"].numpy(), image.point_index)


def test_the_range_view_reuses_maps_other_groups_decoded_without_changing_them(tiny_cache: Path) -> None:
    alone = FrameDataset(tiny_cache, fields=("range_view",))[2]
    shared = FrameDataset(tiny_cache, fields=("images", "truth", "depth", "pseudo", "range_view"))[2]
    for key, value in alone.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, shared[key]), key
        else:
            assert value == shared[key], key


def test_a_row_without_the_layout_column_still_gives_a_range_view(tiny_cache: Path) -> None:
    reader = CacheReader(tiny_cache)
    batch = reader.read(0, ["scene_id", "cameras"])  # as a cache made without the range_view stage
    sample = loader_rangeview.range_view_sample(batch, cameras_of(batch))
    frame = reader.frame(0)
    rv = pack_range_view(frame)
    assert np.array_equal(sample["range_view_rgb"].permute(1, 2, 0).numpy(), rv.rgb)
    assert np.array_equal(sample["range_view_owner"].numpy(), rv.layout.owner)
    assert sample["range_view_depth_source"] == rv.depth_source == "dense"
    assert np.array_equal(sample["range_view_depth"].numpy(), rv.depth_m)


# --------------------------------------------------------------------------------------------
# Preview


def test_preview_draws_one_row_per_map_and_the_boxes(waymo_frame: Frame) -> None:
    layout = waymo_frame.range_view
    image = draw_frame(waymo_frame, scale=1)
    rows = 3  # RGB, truth depth, truth semantics; below them the depth colour bar and class legend
    assert image.shape[1:] == (layout.width + rows * layout.height, 3)
    assert image.shape[0] > rows * layout.height
    plain = draw_frame(dataclasses.replace(waymo_frame, boxes=Boxes.empty()), scale=1)
    changed = np.any(image[: layout.height, : layout.width] != plain[: layout.height, : layout.width], axis=2)
    # Every box corner in front of the FRONT camera and inside its image has a drawn edge within 2 px.
    cam = waymo_frame.camera("FRONT")
    p = next(v for v in layout.views if v.camera_name == "FRONT")
    corners = (
        waymo_frame.boxes.corners_world()
        + (waymo_frame.boxes.velocity_world * (cam.timestamp_micros - waymo_frame.timestamp_micros) * 1e-6)[
            :, None
        ]
    )
    pts = geometry.transform_points(geometry.invert_transform(cam.world_from_camera), corners.reshape(-1, 3))
    uv, ok = geometry.project_points(pts, cam.calibration.intrinsics, cam.calibration.distortion)
    inside = ok & geometry.in_image(uv, p.width - 2, p.height - 2) & (uv >= 2).all(1)
    assert inside.sum() >= 4
    for u, v in np.round(uv[inside]).astype(int):
        assert changed[p.row0 + v - 2 : p.row0 + v + 3, p.col0 + u - 2 : p.col0 + u + 3].any()
    assert not changed[: layout.height, layout.width :].any()  # boxes stay inside the range view


def test_preview_of_a_frame_without_maps_draws_the_rgb_row_only(nuscenes_frame: Frame) -> None:
    bare = dataclasses.replace(
        nuscenes_frame,
        cameras=[dataclasses.replace(c, truth=None, depth=None) for c in nuscenes_frame.cameras],
    )
    layout = nuscenes_frame.range_view
    image = draw_frame(bare, scale=2)
    assert image.shape == (2 * layout.height, 2 * layout.width + 2 * layout.height, 3)
    assert image[:, : 2 * layout.width].std() > 10


def test_preview_command_writes_the_range_view_png(range_cache: Path, tmp_path: Path) -> None:
    from phigenesis.cli.prep import main

    out = tmp_path / "p.png"
    assert main(["preview", str(range_cache), "--frame", "1", "--out", str(out), "--scale", "1"]) == 0
    image = cv2.imread(str(out), cv2.IMREAD_COLOR)
    layout = CacheReader(range_cache).frame(1).range_view
    rows = 3  # RGB, depth (no depth stage ran: exact truth depth), truth semantics; then bar and legend
    assert image.shape[1:] == (layout.width + rows * layout.height, 3)
    assert image.shape[0] > rows * layout.height
