"""Scene editing: assets inserted into a scene's Gaussians (phigenesis.infer.insert; phigenesis-render
--insert)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.cli.render import main as render_main
from phigenesis.data.records import Boxes
from phigenesis.data.shards import CacheReader, verify_cache
from phigenesis.export.ply import scene_from_ply, write_ply
from phigenesis.infer.insert import (
    AssetError,
    AssetPlacement,
    asset_box,
    insert_asset,
    load_asset,
    load_path_file,
    parse_keyframe,
    parse_pose,
    placed_gaussians,
    with_inserted_box,
)
from phigenesis.models.gaussians import GaussianScene
from tests.conftest import one_scene_cache

H, W = 48, 64
#: A pinhole camera at the world origin looking along +z (OpenCV axes: x right, y down).
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
RED, BLUE = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)


@pytest.fixture(autouse=True)
def one_thread() -> None:
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def cube_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1 m cube with red faces, centred on its origin, as an OBJ."""
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.visual.face_colors = [255, 0, 0, 255]
    path = tmp_path_factory.mktemp("assets") / "cube.obj"
    cube.export(path)
    return path


@pytest.fixture(scope="module")
def cube(cube_file: Path):  # type: ignore[no-untyped-def]
    return load_asset(cube_file, class_name="car", spacing_m=0.05)


def empty_scene(k: int = tx.NUM_CLASSES) -> GaussianScene:
    z = torch.zeros
    return GaussianScene(
        z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 3), z(0, k), z(0, 3), z(0, dtype=torch.bool), z(0)
    )


def plane(
    z_m: float, half_m: float, color: tuple[float, float, float], spacing: float = 0.05
) -> GaussianScene:
    """A square of flat opaque Gaussians facing the camera at depth ``z_m`` (the scene's own)."""
    ticks = np.arange(-half_m, half_m + 1e-9, spacing)
    x, y = np.meshgrid(ticks, ticks)
    n = x.size
    means = np.stack([x.ravel(), y.ravel(), np.full(n, z_m)], 1)
    return GaussianScene(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).clone(),
        scales=torch.tensor([[0.7 * spacing, 0.7 * spacing, 1e-4]]).expand(n, 3).clone(),
        opacities=torch.full((n,), 0.99),
        colors=torch.tensor([color]).expand(n, 3).clone(),
        semantic_logits=torch.zeros(n, tx.NUM_CLASSES),
        velocity=torch.zeros(n, 3),
        dynamic=torch.zeros(n, dtype=torch.bool),
        time_s=torch.zeros(n),
    )


def render(scene: GaussianScene, t_s: float = 0.0):  # type: ignore[no-untyped-def]
    out = scene.render(torch.eye(4)[None], torch.tensor(K, dtype=torch.float32)[None], W, H, t_s)
    return out.rgb[0].numpy(), out.depth[0].numpy(), out.alpha[0].numpy()


def pose(xyz: tuple[float, float, float], yaw_deg: float = 0.0) -> np.ndarray:
    return geometry.yaw_pose_to_transform(np.array(xyz), math.radians(yaw_deg))


def project(points_world: np.ndarray) -> np.ndarray:
    """(N, 2) pixel coordinates (u, v) of world points in the camera at the origin."""
    p = points_world @ K.T
    return p[:, :2] / p[:, 2:]


def hull_margin(uv: np.ndarray) -> np.ndarray:
    """(H, W) signed distance in pixels of each pixel centre inside the convex hull of ``uv``
    (positive inside): the smallest distance to the hull's edge lines."""
    pts = sorted(map(tuple, uv))

    def turn(o: tuple, a: tuple, b: tuple) -> float:  # type: ignore[type-arg]
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def half(points: list) -> list:  # type: ignore[type-arg]
        chain: list = []  # type: ignore[type-arg]
        for p in points:
            while len(chain) >= 2 and turn(chain[-2], chain[-1], p) <= 0:
                chain.pop()
            chain.append(p)
        return chain

    hull = half(pts)[:-1] + half(pts[::-1])[:-1]  # counter-clockwise in (u, v)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    dist = np.full((H, W), np.inf)
    for a, b in zip(hull, hull[1:] + hull[:1], strict=True):
        e = np.subtract(b, a)
        n = np.array([-e[1], e[0]]) / np.linalg.norm(e)  # left normal: inside for a ccw hull
        dist = np.minimum(dist, (u - a[0]) * n[0] + (v - a[1]) * n[1])
    return dist


def cube_corners(world_from_asset: np.ndarray, side: float = 1.0) -> np.ndarray:
    return geometry.transform_points(world_from_asset, 0.5 * side * geometry.BOX_CORNER_SIGNS)


def is_red(rgb: np.ndarray) -> np.ndarray:
    return (rgb[..., 0] > 0.8) & (rgb[..., 1] < 0.1) & (rgb[..., 2] < 0.1)


# --------------------------------------------------------------------------------------------
# Meshes become surface Gaussians


def test_a_mesh_becomes_solid_red_surface_discs_with_its_box(cube) -> None:  # type: ignore[no-untyped-def]
    g = cube.gaussians
    assert cube.kind == "mesh" and cube.class_id == tx.CAR and cube.spacing_m == 0.05
    assert len(g) == 2400  # 6 m^2 at 5 cm: one disc per 25 cm^2
    np.testing.assert_allclose(cube.box_size_lwh, [1, 1, 1])
    np.testing.assert_allclose(cube.box_center_local, [0, 0, 0], atol=1e-12)
    # Every disc lies on the cube's surface, flat in its face: its thin axis along the face normal.
    means = g.means.double().numpy()
    assert np.allclose(np.abs(means).max(axis=1), 0.5, atol=1e-6)
    normals = geometry.quaternion_to_matrix(g.quats.double().numpy())[:, :, 2]
    on_face = np.argmax(np.abs(means), axis=1)
    np.testing.assert_allclose(np.abs(normals[np.arange(len(g)), on_face]), 1.0, atol=1e-6)
    np.testing.assert_allclose(g.scales[:, :2].numpy(), 0.035, rtol=1e-6)
    assert (g.scales[:, 2] < 1e-3).all() and (g.opacities > 0.98).all()
    np.testing.assert_array_equal(g.colors.numpy(), np.tile(RED, (len(g), 1)))
    assert (g.semantic_logits.argmax(1) == tx.CAR).all()
    # The same file gives the same Gaussians.
    again = load_asset(cube.path, class_name="car", spacing_m=0.05)
    assert torch.equal(again.gaussians.means, g.means) and torch.equal(again.gaussians.quats, g.quats)


def test_the_default_spacing_is_a_hundredth_of_the_diagonal_and_the_count_is_capped(
    cube_file: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from phigenesis.infer import insert

    monkeypatch.setattr(insert, "MAX_MESH_GAUSSIANS", 3000)
    with caplog.at_level("INFO", logger="phigenesis.infer.insert"):
        asset = load_asset(cube_file, class_name="car")
    # sqrt(3) / 100 m would make 20,000 discs: the spacing widens to sqrt(6 / 3000) m.
    assert len(asset.gaussians) == 3000
    assert asset.spacing_m == pytest.approx(math.sqrt(6 / 3000))
    assert "spacing widened" in caplog.text


def test_a_glb_scene_joins_its_meshes_with_their_transforms_and_colours(tmp_path: Path) -> None:
    a = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    a.visual.face_colors = [0, 255, 0, 255]
    b = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    b.visual.vertex_colors = [0, 0, 255, 255]
    scene = trimesh.Scene()
    scene.add_geometry(a, node_name="a")
    scene.add_geometry(b, node_name="b", transform=geometry.yaw_pose_to_transform([3.0, 0, 0], 0.0))
    path = tmp_path / "two.glb"
    scene.export(path)
    asset = load_asset(path, class_name="truck", spacing_m=0.1)
    np.testing.assert_allclose(asset.box_size_lwh, [4, 1, 1], atol=1e-6)
    np.testing.assert_allclose(asset.box_center_local, [1.5, 0, 0], atol=1e-6)
    x = asset.gaussians.means[:, 0].numpy()
    colors = asset.gaussians.colors.numpy()
    np.testing.assert_allclose(colors[x < 1], np.tile([0, 1, 0], ((x < 1).sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(colors[x > 2], np.tile([0, 0, 1], ((x > 2).sum(), 1)), atol=1e-6)
    # Y-up (glTF's convention): the file's +Y becomes the asset's +z.
    upright = load_asset(path, class_name="truck", spacing_m=0.1, up="y")
    np.testing.assert_allclose(upright.box_size_lwh, [1, 4, 1], atol=1e-6)


def test_a_textured_quad_takes_its_colours_from_the_texture_and_has_a_thin_box(tmp_path: Path) -> None:
    from PIL import Image

    vertices = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], np.float64)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    image = Image.fromarray(np.array([[[255, 0, 0], [0, 255, 0]]], np.uint8))  # left red, right green
    visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    quad = trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], visual=visual, process=False)
    path = tmp_path / "sign.glb"
    quad.export(path)
    asset = load_asset(path, class_name="traffic_sign", spacing_m=0.1)
    x, colors = asset.gaussians.means[:, 0].numpy(), asset.gaussians.colors.numpy()
    assert len(x) == 200
    np.testing.assert_array_equal(colors[x < 0.9], np.tile(RED, ((x < 0.9).sum(), 1)))
    np.testing.assert_array_equal(colors[x > 1.1], np.tile([0, 1, 0], ((x > 1.1).sum(), 1)))
    # A flat mesh still has a valid box: its zero side becomes MIN_BOX_SIDE_M.
    np.testing.assert_allclose(asset.box_size_lwh, [2, 1, 0.01])


def test_a_3dgs_ply_round_trips_through_load_asset(tmp_path: Path) -> None:
    g = torch.Generator().manual_seed(0)
    n = 50
    scene = GaussianScene(
        means=torch.randn(n, 3, generator=g),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        scales=torch.rand(n, 3, generator=g) * 0.1 + 0.01,
        opacities=torch.rand(n, generator=g) * 0.8 + 0.15,
        colors=torch.rand(n, 3, generator=g),
        semantic_logits=torch.zeros(n, 0),
        velocity=torch.zeros(n, 3),
        dynamic=torch.zeros(n, dtype=torch.bool),
        time_s=torch.zeros(n),
    )
    path = write_ply(scene, tmp_path / "splat.ply")
    asset = load_asset(path, class_name="person", scale=2.0)
    assert asset.kind == "gaussians" and asset.spacing_m is None and len(asset.gaussians) == n
    back = asset.gaussians
    np.testing.assert_allclose(back.means.numpy(), 2 * scene.means.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(back.scales.numpy(), 2 * scene.scales.numpy(), rtol=1e-5)
    np.testing.assert_allclose(back.colors.numpy(), scene.colors.numpy(), atol=1e-6)
    np.testing.assert_allclose(back.opacities.numpy(), scene.opacities.numpy(), atol=1e-6)
    sign = np.sign((back.quats * scene.quats).sum(1, keepdim=True).numpy())
    np.testing.assert_allclose(back.quats.numpy() * sign, scene.quats.numpy(), atol=1e-6)
    assert (back.semantic_logits.argmax(1) == tx.PERSON).all()
    means = 2 * scene.means.double().numpy()
    np.testing.assert_allclose(asset.box_size_lwh, means.max(0) - means.min(0), rtol=1e-5)


# --------------------------------------------------------------------------------------------
# Rendering: where the projection says, occluding and occluded


def test_an_inserted_cube_renders_red_inside_the_projection_of_its_corners(cube) -> None:  # type: ignore[no-untyped-def]
    where = pose((0.4, -0.2, 4.0), yaw_deg=30.0)
    edited = insert_asset(empty_scene(), cube, AssetPlacement.still(where), 0)
    assert len(edited) == len(cube.gaussians)
    rgb, _, alpha = render(edited)
    margin = hull_margin(project(cube_corners(where)))
    # Splats blur an edge by a pixel or two (the discs' size and the rasterizer's 0.3 px^2 low-pass).
    inside, outside = margin > 1.5, margin < -2.5
    assert inside.sum() > 150 and outside.sum() > 2000
    assert is_red(rgb)[inside].mean() > 0.95
    assert alpha[outside].max() < 0.02


def test_the_cube_hides_the_plane_behind_it_and_leaves_the_rest_as_it_was(cube) -> None:  # type: ignore[no-untyped-def]
    background = plane(8.0, 5.0, BLUE)
    where = pose((0.0, 0.0, 5.0))
    rgb0, depth0, _ = render(background)
    rgb, depth, _ = render(insert_asset(background, cube, AssetPlacement.still(where), 0))
    margin = hull_margin(project(cube_corners(where)))
    inside, outside = margin > 1.5, margin < -2.5
    assert is_red(rgb)[inside].mean() > 0.95
    # What the camera sees there is the cube's front face, 4.5 m away (its sides are behind it from
    # the camera on its axis), not the plane at 8 m.
    np.testing.assert_allclose(depth[inside], 4.5, atol=0.03)
    np.testing.assert_allclose(rgb[outside], rgb0[outside], atol=1e-5)
    np.testing.assert_allclose(depth[outside], depth0[outside], atol=1e-4)
    assert np.allclose(depth0[outside], 8.0, atol=0.01)


def test_a_plane_in_front_of_the_cube_hides_it(cube) -> None:  # type: ignore[no-untyped-def]
    where = pose((0.0, 0.0, 5.0))
    occluder = plane(3.0, 2.0, BLUE)
    rgb, depth, _ = render(insert_asset(occluder, cube, AssetPlacement.still(where), 0))
    inside = hull_margin(project(cube_corners(where))) > 1.5
    assert not is_red(rgb)[inside].any()
    assert rgb[inside][:, 2].min() > 0.9
    np.testing.assert_allclose(depth[inside], 3.0, atol=0.02)


def test_a_moving_cube_is_at_the_interpolated_position_and_moves_at_the_path_velocity(cube) -> None:  # type: ignore[no-untyped-def]
    path = AssetPlacement(
        np.array([1_000_000, 2_000_000]), np.stack([pose((-1.5, 0.0, 6.0)), pose((1.5, 0.0, 6.0))])
    )
    scene = empty_scene()
    scene = GaussianScene(**{**scene.__dict__, "time_origin_micros": 1_000_000})
    at_mid = insert_asset(scene, cube, path, 1_500_000)
    g = at_mid
    assert g.dynamic.all() and torch.allclose(g.velocity, torch.tensor([3.0, 0, 0]), atol=1e-4)
    assert torch.allclose(g.time_s, torch.tensor(0.5))

    def red_centroid(rgb: np.ndarray) -> np.ndarray:
        v, u = np.nonzero(is_red(rgb))
        return np.array([u.mean(), v.mean()])

    # Rendered at its own time it is at the middle of the path; 0.1 s later, 0.3 m further along.
    for t_s, x in ((0.5, 0.0), (0.6, 0.3)):
        rgb, _, _ = render(at_mid, t_s)
        expected = project(np.array([[x, 0.0, 6.0]]))[0]
        np.testing.assert_allclose(red_centroid(rgb), expected, atol=0.3)
    # Held outside the path: waiting at its first pose, then staying at its last, not moving.
    np.testing.assert_array_equal(path.pose_at(0), pose((-1.5, 0.0, 6.0)))
    np.testing.assert_array_equal(path.pose_at(9_000_000), pose((1.5, 0.0, 6.0)))
    np.testing.assert_array_equal(path.velocity_at(0), [0, 0, 0])
    np.testing.assert_array_equal(path.velocity_at(2_000_000), [0, 0, 0])
    still = placed_gaussians(cube, AssetPlacement.still(pose((0, 0, 6.0))), 1_200_000, scene)
    assert not still.dynamic.any() and not still.velocity.any()


def test_slerp_halfway_between_yaw_0_and_90_degrees_is_45() -> None:
    path = AssetPlacement(np.array([0, 1000]), np.stack([pose((0, 0, 0), 0.0), pose((2, 4, 0), 90.0)]))
    mid = path.pose_at(500)
    np.testing.assert_allclose(mid, pose((1, 2, 0), 45.0), atol=1e-12)
    assert math.degrees(geometry.matrix_yaw(mid[:3, :3])) == pytest.approx(45.0)


def test_the_box_matches_the_cube_and_joins_the_frames_boxes(cube) -> None:  # type: ignore[no-untyped-def]
    where = pose((10.0, -3.0, 0.5), yaw_deg=30.0)
    box = asset_box(cube, AssetPlacement.still(where), 123, track_id="inserted-0")
    assert len(box) == 1 and box.track_id == ["inserted-0"] and box.class_id[0] == tx.CAR
    assert box.status_names() == ["annotated"] and box.num_lidar_points[0] == -1
    assert box.yaw_world[0] == pytest.approx(math.radians(30))
    np.testing.assert_array_equal(box.velocity_world, [[0, 0, 0]])
    mesh = trimesh.load(cube.path, process=False)
    expected = geometry.transform_points(where, mesh.vertices)
    got = box.corners_world()[0]
    # The same 8 points (each corner of one set is a corner of the other).
    dist = np.linalg.norm(got[:, None] - expected[None], axis=2)
    assert dist.min(axis=1).max() < 1e-9 and dist.min(axis=0).max() < 1e-9
    # A moving box has the path's velocity.
    moving = AssetPlacement(np.array([0, 2_000_000]), np.stack([where, where @ pose((4.0, 0, 0))]))
    v = asset_box(cube, moving, 1_000_000).velocity_world[0]
    np.testing.assert_allclose(
        v, [2 * math.cos(math.radians(30)), 2 * math.sin(math.radians(30)), 0], atol=1e-9
    )
    frame_boxes = with_inserted_box(Boxes.empty(), box)
    other = asset_box(cube, AssetPlacement.still(where), 123, track_id="inserted-1")
    joined = with_inserted_box(frame_boxes, other)
    assert joined.track_id == ["inserted-0", "inserted-1"]
    with pytest.raises(AssetError, match=r"inserted-0.*already"):
        with_inserted_box(joined, box)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(1, 5_000_000),  # time step, us
            st.tuples(*[st.floats(-100, 100)] * 3),  # position, m
            st.tuples(st.floats(-math.pi, math.pi), st.floats(-1.5, 1.5), st.floats(-math.pi, math.pi)),
        ),
        min_size=1,
        max_size=5,
    ),
    st.floats(0, 1),
)
def test_pose_at_gives_each_keyframe_its_pose_and_is_always_rigid(keys, fraction) -> None:  # type: ignore[no-untyped-def]
    times = np.cumsum([k[0] for k in keys])
    poses = np.stack([geometry.make_transform(geometry.euler_zyx_to_matrix(*k[2]), k[1]) for k in keys])
    path = AssetPlacement(times, poses)
    for t, p in zip(times, poses, strict=True):
        np.testing.assert_allclose(path.pose_at(int(t)), p, atol=1e-12)
    t = int(times[0] - 1000 + fraction * (times[-1] - times[0] + 2000))
    r = path.pose_at(t)[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-9)
    assert np.isfinite(path.velocity_at(t)).all()


# --------------------------------------------------------------------------------------------
# Poses and refusals


def test_poses_and_path_files_parse(tmp_path: Path) -> None:
    np.testing.assert_allclose(parse_pose("1,2,3"), pose((1, 2, 3)))
    np.testing.assert_allclose(parse_pose(" 1.5, -2e1 ,0 , 90"), pose((1.5, -20, 0), 90))
    key = parse_keyframe("1,2,3,45@2.5")
    assert key.t_s == 2.5
    np.testing.assert_allclose(key.matrix, pose((1, 2, 3), 45))
    path = tmp_path / "path.yaml"
    path.write_text(
        "keyframes:\n"
        "  - {t_s: 0, xyz: [0, 0, 0]}\n"
        "  - {t_s: 2, xyz: [4, 0, 0], yaw_deg: 90}\n"
        "  - {t_s: 3, world_from_asset: [[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}\n"
    )
    keys = load_path_file(path)
    placement = AssetPlacement.from_keyframes(keys, 1_000_000)
    np.testing.assert_array_equal(placement.times_micros, [1_000_000, 3_000_000, 4_000_000])
    np.testing.assert_allclose(placement.pose_at(2_000_000)[:3, 3], [2, 0, 0])
    # In the first frame's ego frame: composed with its pose.
    ego = pose((100, 50, 0), 90)
    in_ego = AssetPlacement.from_keyframes([parse_keyframe("10,0,0")], 7, ego)
    np.testing.assert_allclose(in_ego.pose_at(7)[:3, 3], [100, 60, 0], atol=1e-12)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("case", "match"),
    [
        ("nan_path", r"nan\.json: keyframe 1: xyz must be a finite number"),
        ("backwards_path", r"back\.json: keyframe 2: time 1\.0 is not after keyframe 1's 2\.0"),
        ("scaled_path", r"scaled\.json: keyframe 0: world_from_asset is not a rigid transform"),
        ("mirrored_pose", r"keyframe 0: world_from_asset is not a rigid transform: .*reflection"),
        ("backwards_placement", r"keyframe 1: time 0 us is not after keyframe 0's 5 us"),
        ("unknown_class", r"unknown asset class 'spaceship'"),
        ("missing_file", r"nowhere\.obj: no such asset file"),
        ("not_a_mesh", r"notes\.obj: no triangle faces"),
        ("unknown_format", r"notes\.xyz123: not an asset format; assets are \.obj"),
        ("unreadable", r"notes\.off: not a mesh trimesh can read"),
        ("nan_vertex", r"nanvert\.obj: 1 vertices have non-finite coordinates"),
        ("flat_point", r"point\.obj: the mesh has zero surface area"),
        ("bad_pose_text", r"pose 'one,two,3': expected x,y,z"),
        ("bad_scale", r"cube\.obj: scale must be a positive number"),
    ],
)
def test_hostile_inputs_are_refused_naming_what_is_wrong(  # type: ignore[no-untyped-def]
    case: str, match: str, tmp_path: Path, cube_file: Path
) -> None:
    with pytest.raises(AssetError, match=match):
        if case == "nan_path":
            load_path_file(
                _write(tmp_path, "nan.json", '[{"t_s": 0, "xyz": [0,0,0]}, {"t_s": 1, "xyz": [NaN,0,0]}]')
            )
        elif case == "backwards_path":
            text = json.dumps([{"t_s": t, "xyz": [t, 0, 0]} for t in (0.0, 2.0, 1.0)])
            load_path_file(_write(tmp_path, "back.json", text))
        elif case == "scaled_path":
            m = (2 * np.eye(4)).tolist()
            m[3][3] = 1.0
            load_path_file(_write(tmp_path, "scaled.json", json.dumps([{"t_s": 0, "world_from_asset": m}])))
        elif case == "mirrored_pose":
            AssetPlacement.still(np.diag([1.0, 1.0, -1.0, 1.0]))
        elif case == "backwards_placement":
            AssetPlacement(np.array([5, 0]), np.stack([np.eye(4), np.eye(4)]))
        elif case == "unknown_class":
            load_asset(cube_file, class_name="spaceship")
        elif case == "missing_file":
            load_asset(tmp_path / "nowhere.obj", class_name="car")
        elif case == "not_a_mesh":
            load_asset(_write(tmp_path, "notes.obj", "just some words\n"), class_name="car")
        elif case == "unknown_format":
            load_asset(_write(tmp_path, "notes.xyz123", "just some words\n"), class_name="car")
        elif case == "unreadable":
            load_asset(_write(tmp_path, "notes.off", "OFF\nsome words\n"), class_name="car")
        elif case == "nan_vertex":
            text = "v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n"
            load_asset(_write(tmp_path, "nanvert.obj", text), class_name="car")
        elif case == "flat_point":
            load_asset(
                _write(tmp_path, "point.obj", "v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n"), class_name="car"
            )
        elif case == "bad_pose_text":
            parse_keyframe("one,two,3")
        elif case == "bad_scale":
            load_asset(cube_file, class_name="car", scale=0.0)


# --------------------------------------------------------------------------------------------
# phigenesis-render --insert


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return one_scene_cache(tmp_path_factory, "insert_cache", 2, (48, 72))


def test_render_inserts_a_cube_in_front_of_the_camera_labels_it_and_exports_the_edit(
    cache: Path, cube_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = CacheReader(cache).frame(0, decode_truth=False)
    front = src.cameras[0]
    world_from_camera = front.world_from_ego @ front.calibration.ego_from_camera
    center = geometry.transform_points(world_from_camera, np.array([[0.0, 0.0, 4.0]]))[0]
    heading = math.degrees(geometry.matrix_yaw(src.world_from_ego[:3, :3]))
    pose_text = ",".join(f"{v:.6f}" for v in (*center, heading))
    out, ply_dir = tmp_path / "edited", tmp_path / "ply"
    code = render_main(
        ["--shards", str(cache), "--rig", "waymo5", "--geometry", "truth", "--out", str(out),
         "--max-frames", "1", "--no-progress", "--threads", "1",
         "--insert", str(cube_file), "--insert-pose", pose_text, "--insert-class", "car",
         "--insert-spacing", "0.05", "--export-ply", str(ply_dir)]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    assert verify_cache(out).ok
    manifest = json.loads((out / "manifest.json").read_text())
    (recorded,) = manifest["arguments"]["insert"]
    assert recorded["class_name"] == "car" and len(recorded["asset_sha256"]) == 64
    frame = CacheReader(out).frame(0)
    # The cube's box joins the frame's own boxes.
    assert frame.boxes.track_id[:-1] == src.boxes.track_id and frame.boxes.track_id[-1] == "inserted-0"
    assert frame.boxes.class_id[-1] == tx.CAR
    np.testing.assert_allclose(frame.boxes.center_world[-1], center, atol=1e-6)
    np.testing.assert_allclose(frame.boxes.size_lwh[-1], [1, 1, 1])
    # The front camera sees it red, its depth and pseudo label where it projects.
    cam = frame.cameras[0]
    cal = cam.calibration
    camera_from_world = geometry.invert_transform(cam.world_from_ego @ cal.ego_from_camera)
    corners = geometry.transform_points(camera_from_world, frame.boxes.corners_world()[-1])
    uv = corners @ cal.intrinsics.T
    uv = uv[:, :2] / uv[:, 2:]
    lo, hi = uv.min(0), uv.max(0)
    u0, v0 = np.ceil(lo + 0.25 * (hi - lo)).astype(int)
    u1, v1 = np.floor(hi - 0.25 * (hi - lo)).astype(int)
    assert u1 - u0 >= 4 and v1 - v0 >= 4
    patch = cam.decode_image()[v0 : v1 + 1, u0 : u1 + 1].astype(int)
    assert (patch[..., 0] > 180).all() and (patch[..., 1:] < 70).all()
    assert cam.pseudo is not None and (cam.pseudo.semantic[v0 : v1 + 1, u0 : u1 + 1] == tx.CAR).all()
    assert cam.depth is not None and cam.depth.dense_m is not None
    near = corners[:, 2].min()
    assert np.abs(cam.depth.dense_m[v0 : v1 + 1, u0 : u1 + 1] - near).max() < 0.15
    # No LiDAR point behind the cube stays in that camera's sparse depth.
    sparse = cam.depth.sparse_m[v0 : v1 + 1, u0 : u1 + 1]
    assert not (sparse > near + 0.2).any()
    # The edited Gaussians of the first frame, as a 3DGS PLY.
    exported = scene_from_ply(ply_dir / f"{src.scene_id}.ply")
    reds = (exported.colors[:, 0] > 0.99) & (exported.colors[:, 1:] < 0.01).all(1)
    assert int(reds.sum()) >= 2400
    red_means = exported.means[reds].double().numpy()
    np.testing.assert_allclose(red_means.mean(0), center, atol=0.05)


def test_render_refuses_an_insert_without_its_pose_or_class(
    cache: Path, cube_file: Path, tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    base = ["--shards", str(cache), "--rig", "waymo5", "--geometry", "truth", "--out", str(tmp_path / "o")]
    assert render_main([*base, "--insert", str(cube_file), "--insert-class", "car"]) != 0
    assert "--insert-pose" in capsys.readouterr().err
    assert render_main([*base, "--insert", str(cube_file), "--insert-pose", "1,2,3"]) != 0
    assert "--insert-class" in capsys.readouterr().err
    assert (
        render_main([*base, "--insert", str(cube_file), "--insert-pose", "1,2,3", "--insert-class", "ufo"])
        != 0
    )
    err = capsys.readouterr().err
    assert "ufo" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_gltf_reading_a_buffer_outside_its_folder_is_refused(tmp_path: Path) -> None:
    files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(trimesh.creation.box(extents=(1, 1, 1))))
    (name,) = [k for k in files if k.endswith(".gltf")]
    buffers = [k for k in files if k.endswith(".bin")]
    doc = json.loads(files[name])
    folder = tmp_path / "asset"
    folder.mkdir()
    for b in buffers:  # files beside the asset's folder, not in it
        (tmp_path / b).write_bytes(files[b])
    for entry in doc["buffers"]:
        entry["uri"] = f"../{entry['uri']}"
    (folder / name).write_text(json.dumps(doc))
    with pytest.raises(
        AssetError, match=r"buffers\[0\]\.uri '\.\./gltf_buffer_0\.bin': leaves the asset's folder"
    ):
        load_asset(folder / name, class_name="car")
    for b in buffers:  # the same files inside the folder read
        (folder / b).write_bytes(files[b])
    for entry in doc["buffers"]:
        entry["uri"] = entry["uri"][3:]
    (folder / name).write_text(json.dumps(doc))
    assert len(load_asset(folder / name, class_name="car").gaussians) > 0
