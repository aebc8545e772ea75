"""Depth completion (stage ``complete_depth``): exact answers on synthetic planes seen by a pinhole,
what must stay empty, hostile inputs, the vectorised plane fit against a plain per-group
reference, and the stage on a small synthetic scene."""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np
import pytest

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.records import DENSE_ORIGINS, CameraDepth, InvalidRecord, Scene
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.sources.synthetic.rigs import LidarSpec
from phigenesis.data.stages import get_stage
from phigenesis.data.stages.complete import (
    KIND_GROUND,
    KIND_VERTICAL,
    CompletionParams,
    complete_depth_map,
    fit_planes,
)
from phigenesis.options import ConfigError

H, W, F = 120, 180, 150.0
PLANE, VERTICAL, DENSIFIED = (DENSE_ORIGINS.index(k) for k in ("plane", "vertical", "densified"))
UP = np.array([0.0, -1.0, 0.0])  # a level camera: OpenCV y points down
SKY_RGB = (120, 170, 230)


def rays(height: int = H, width: int = W, f: float = F) -> np.ndarray:
    """(H * W, 3) z = 1 rays of a pinhole with the principal point at the image centre."""
    k = geometry.intrinsic_matrix(f, f, (width - 1) / 2, (height - 1) / 2)
    return geometry.unproject_pixels(geometry.pixel_grid(width, height), k)


def plane_depth(r: np.ndarray, normal, offset: float, shape=(H, W)) -> np.ndarray:
    """Reference z-depth of the plane ``normal . p + offset = 0`` along each ray, a plain loop."""
    n = np.asarray(normal, np.float64)
    out = np.zeros(len(r))
    for i, ray in enumerate(r):
        out[i] = -offset / float(n @ ray)
    return out.reshape(shape)


def textured(shape, colour, seed: int) -> np.ndarray:
    """An (H, W, 3) uint8 patch of ``colour`` with a faint smooth texture and a little pixel noise
    (a rendered material)."""
    rng = np.random.default_rng(seed)
    smooth = cv2.GaussianBlur(rng.normal(0, 60, shape).astype(np.float32), (0, 0), 4)
    noise = rng.normal(0, 1, (*shape, 3))
    return np.clip(np.array(colour) + smooth[..., None] + noise, 0, 255).astype(np.uint8)


def facade_scene(windows: bool = False, noise_m: float = 0.0):
    """A facade 12 m ahead, turned 25 deg, seen by a level pinhole: rows >= ``roof`` are facade
    (its lower rows >= ``known_from`` have depth, as a LiDAR would give), the sky above."""
    normal = np.array([np.sin(np.radians(25)), 0.0, -np.cos(np.radians(25))])
    offset = 12.0 * np.cos(np.radians(25))
    r = rays()
    truth = plane_depth(r, normal, offset)
    roof, known_from = 20, 80
    rgb = textured((H, W), (200, 180, 150), 0)
    rgb[:roof] = SKY_RGB
    if windows:
        for top in (30, 55):
            for left in range(20, W - 20, 35):
                rgb[top : top + 12, left : left + 14] = (40, 50, 60)
    depth = np.zeros((H, W), np.float32)
    depth[known_from:] = truth[known_from:]
    if noise_m:
        depth[known_from:] += np.random.default_rng(1).normal(0, noise_m, depth[known_from:].shape)
    conf = (depth > 0).astype(np.float32) * 0.9
    sky = np.zeros((H, W), bool)
    sky[:roof] = True
    return depth, conf, rgb, truth.astype(np.float32), sky, roof, known_from, (normal, offset)


def complete(depth, conf, rgb, **kwargs):
    return complete_depth_map(depth, conf, rgb, rays_cam=rays(), up_cam=UP, focal_px=F, **kwargs)


# ------------------------------------------------------------------------------------------
# Exact answers


@pytest.mark.parametrize("with_sky_labels", [True, False])
def test_a_facade_is_completed_to_the_truth_up_to_the_roofline(with_sky_labels):
    depth, conf, rgb, truth, sky, roof, known_from, _ = facade_scene()
    out = complete(depth, conf, rgb, sky=sky if with_sky_labels else None)
    upper = slice(roof, known_from)
    assert np.all(out.origin[upper] == PLANE)
    # Exact on an exact plane (float32 depths, the fit from float32 data).
    np.testing.assert_allclose(out.depth_m[upper], truth[upper], rtol=1e-4)
    assert not np.any(out.depth_m[:roof]), "the sky stays empty"
    assert np.array_equal(out.depth_m[known_from:], depth[known_from:]), "known depths are kept"
    assert np.all(out.origin[known_from:] == DENSIFIED)
    completed = out.confidence[upper]
    assert completed.min() > 0 and completed.max() <= CompletionParams().max_confidence
    assert completed.max() < conf[known_from:].min(), "never above the data it extends"
    # Farther from the data, lower confidence.
    assert out.confidence[roof, W // 2] < out.confidence[known_from - 1, W // 2]


def test_a_noisy_facade_stays_within_the_stated_extrapolation_error():
    sigma = 0.02
    depth, conf, rgb, truth, sky, roof, known_from, (normal, _) = facade_scene(noise_m=sigma)
    out = complete(depth, conf, rgb, sky=sky)
    # The module's error model: a pixel H metres beyond data spanning h metres is off by about
    # sigma * H / h along the normal (3 sigma here), plus the in-plane noise of the fit itself.
    r = rays().reshape(H, W, 3)
    height = -(r[..., 1] * truth)  # metres above the camera (y down)
    h_data = np.ptp(height[known_from:])
    beyond = np.abs(height[roof:known_from] - height[known_from:].mean()) + 0.5 * h_data
    along_normal = np.abs(r[roof:known_from] @ normal)  # z error per metre of offset along the normal
    bound = (3 * sigma * beyond / h_data + 3 * sigma) / along_normal
    err = np.abs(out.depth_m[roof:known_from] - truth[roof:known_from])
    assert np.all(out.origin[roof:known_from] == PLANE)
    assert np.all(err <= bound), float((err - bound).max())


def test_windows_in_a_facade_take_its_plane():
    depth, conf, rgb, truth, sky, *_ = facade_scene(windows=True)
    out = complete(depth, conf, rgb, sky=sky)
    window = (slice(30, 42), slice(20, 34))
    assert np.all(out.origin[window] == PLANE)
    np.testing.assert_allclose(out.depth_m[window], truth[window], rtol=1e-4)
    # Holes get a lower confidence than the facade beside them.
    assert out.confidence[window].max() < out.confidence[30:42, 16:19].min()


def two_tone_facade(upper_rgb=(120, 100, 80), ledge: int = 50):
    """:func:`facade_scene` whose rows ``roof:ledge`` are another material (a segment of their own,
    without depth: above the LiDAR's top beam), with the sky labelled."""
    depth, conf, rgb, truth, sky, roof, known_from, _ = facade_scene()
    rgb[roof:ledge] = textured((ledge - roof, W), upper_rgb, 6)
    return depth, conf, rgb, truth, sky, roof, ledge, known_from


def test_the_upper_part_of_a_facade_takes_the_plane_below_it():
    depth, conf, rgb, truth, sky, roof, ledge, known_from = two_tone_facade()
    out = complete(depth, conf, rgb, sky=sky)
    top = slice(roof, ledge)
    assert len(np.unique(out.segments[top])) < len(np.unique(out.segments))  # its own segment(s)
    assert not np.isin(out.segments[top], out.segments[known_from:]).any()
    assert np.all(out.origin[top] == PLANE)
    np.testing.assert_allclose(out.depth_m[top], truth[top], rtol=1e-4)  # the same exact plane
    assert not np.any(out.depth_m[:roof]), "the sky above stays empty"
    # Its own, lower confidence: below the facade's own completed pixels next to it.
    p = CompletionParams()
    assert out.confidence[top].max() <= p.max_confidence * p.upward_confidence + 1e-6
    assert out.confidence[ledge - 1].max() < out.confidence[ledge].min()
    # The sky above, were it not labelled, is blue: no facade.
    unlabelled = complete(depth, conf, rgb, sky=np.zeros((H, W), bool))
    np.testing.assert_allclose(unlabelled.depth_m[top], truth[top], rtol=1e-4)
    assert not np.any(unlabelled.depth_m[:roof])
    # Switched off, or without sky labels (nothing tells a roofline then), it stays empty.
    off = complete(depth, conf, rgb, sky=sky, params=CompletionParams(propagate_up=False))
    assert not np.any(off.depth_m[top])
    assert not np.any(complete(depth, conf, rgb).depth_m[top])


def test_a_segment_touching_a_facades_top_over_a_small_share_of_its_lower_edge_is_not_climbed():
    # Rows 20:50 another building (brown, no depth); below it the facade (with depth from row 80)
    # over the first 36 columns only, and blue glass without depth over the rest (not a candidate
    # itself: too blue). Only 20 % of the brown segment's lower edge is the facade's top.
    depth, conf, rgb, truth, sky, roof, ledge, known_from = two_tone_facade()
    rgb[ledge:known_from, 36:] = textured((known_from - ledge, W - 36), (80, 110, 170), 7)
    out = complete(depth, conf, rgb, sky=sky)
    assert np.all(out.depth_m[ledge:known_from, :30] > 0), "the facade itself is completed"
    # (but for a blob of its texture that sits on the facade's top)
    assert (out.depth_m[roof:ledge] > 0).mean() < 0.1, "the building above is not the facade"
    # Half of its lower edge is enough (the whole of it is the facade's top in the test above).
    half = complete(depth, conf, rgb, sky=sky, params=CompletionParams(upward_boundary_share=0.15))
    np.testing.assert_allclose(half.depth_m[roof:ledge], truth[roof:ledge], rtol=1e-4)


def test_sky_coloured_pixels_of_a_climbed_segment_stay_empty():
    # Single sky-blue pixels inside the upper segment (a roofline's segment takes in some sky):
    # too small for segments of their own, they are the sky the labels missed.
    depth, conf, rgb, truth, sky, roof, ledge, _ = two_tone_facade()
    dots = np.zeros((H, W), bool)
    dots[roof + 4 : ledge - 4 : 7, 10:-10:9] = True
    rgb[dots] = SKY_RGB
    out = complete(depth, conf, rgb, sky=sky)
    top = np.zeros((H, W), bool)
    top[roof:ledge] = True
    assert not np.any(out.depth_m[dots]), "sky-blue pixels are not given the facade's depth"
    filled = top & ~dots & (out.depth_m > 0)
    assert filled.sum() > 0.95 * (top & ~dots).sum()
    np.testing.assert_allclose(out.depth_m[filled], truth[filled], rtol=1e-4)


def test_no_plane_climbs_from_a_segment_partly_labelled_a_vehicle():
    # A car's side in one image segment with the facade behind it (labels cover a part of it)
    # would carry the car's depth up the facade: nothing climbs from such a segment.
    depth, conf, rgb, truth, sky, roof, ledge, known_from = two_tone_facade()
    top = slice(roof, ledge)
    classes = np.full((H, W), tx.BUILDING, np.uint8)
    classes[sky] = tx.SKY
    clean = complete(depth, conf, rgb, sky=sky, classes=classes)
    np.testing.assert_allclose(clean.depth_m[top], truth[top], rtol=1e-4)  # labels alone change nothing
    car = classes.copy()
    car[known_from:, : W // 8] = tx.CAR  # an eighth of the lower segment's columns
    out = complete(depth, conf, rgb, sky=sky, classes=car)
    assert not np.any(out.depth_m[top])
    loose = CompletionParams(upward_max_thing_share=1.0)
    np.testing.assert_allclose(
        complete(depth, conf, rgb, sky=sky, classes=car, params=loose).depth_m[top], truth[top], rtol=1e-4
    )


def test_nothing_climbs_from_the_ground_or_into_a_tree():
    # A segment without depth standing on a known road (a wall beyond the LiDAR's range) stays
    # empty: the ground is no facade.
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:] = SKY_RGB
    horizon = (H - 1) // 2
    rgb[horizon - 25 : horizon + 8] = textured((33, W), (170, 150, 130), 7)  # the far wall
    rgb[horizon + 8 :] = textured((H - horizon - 8, W), (90, 90, 90), 8)  # the road
    r = rays().reshape(H, W, 3)
    road = 1.6 / np.maximum(r[..., 1], 1e-9)  # a level road 1.6 m below the camera
    depth = np.zeros((H, W), np.float32)
    depth[horizon + 20 :] = road[horizon + 20 :]
    conf = (depth > 0).astype(np.float32) * 0.9
    sky = np.zeros((H, W), bool)
    sky[: horizon - 25] = True
    out = complete(depth, conf, rgb, sky=sky)
    assert np.any(out.origin[horizon + 8 :] == PLANE)  # the road is completed ...
    assert not np.any(out.depth_m[: horizon + 8]), "... the wall on it is not"
    # A green crown above a facade's known part is not the facade.
    depth, conf, rgb, _, sky, roof, ledge, _ = two_tone_facade(upper_rgb=(50, 130, 50))
    out = complete(depth, conf, rgb, sky=sky)
    assert not np.any(out.depth_m[roof : ledge - 1])


def test_a_plane_climbs_only_into_segments_the_lidar_did_not_see():
    # Sparse depth on the upper segment (the LiDAR saw it, at another depth): no climbing.
    depth, conf, rgb, _, sky, roof, ledge, _ = two_tone_facade()
    sparse = np.zeros((H, W), np.float32)
    sparse[roof:ledge:4, ::4] = 30.0  # something far behind
    out = complete(depth, conf, rgb, sky=sky, sparse_m=sparse, sparse_confidence=(sparse > 0) * 0.9)
    # (A sliver of the texture's own segments with too few of those points may still take it.)
    assert np.mean(out.depth_m[roof:ledge] > 0) < 0.05


def lawn_scene() -> tuple[np.ndarray, int, np.ndarray]:
    """Sky above the horizon, a green lawn below, level 1.6 m under a level camera: the image, the
    horizon's row and the lawn's z-depth (0 above the horizon)."""
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:] = SKY_RGB
    horizon = (H - 1) // 2
    rgb[horizon + 1 :] = textured((H - horizon - 1, W), (100, 140, 80), 9)
    r = rays().reshape(H, W, 3)
    truth = np.where(r[..., 1] > 0.01, 1.6 / np.maximum(r[..., 1], 1e-9), 0).astype(np.float32)
    return rgb, horizon, truth


def test_a_lawn_known_only_from_sparse_scan_lines_takes_their_ground_plane():
    rgb, horizon, truth = lawn_scene()
    sparse = np.zeros((H, W), np.float32)
    sparse[horizon + 6 :: 2] = truth[horizon + 6 :: 2]  # scan lines on every other row
    zeros = np.zeros((H, W), np.float32)
    sky = np.zeros((H, W), bool)
    sky[:horizon] = True
    out = complete(zeros, zeros, rgb, sky=sky, sparse_m=sparse, sparse_confidence=(sparse > 0) * 0.9)
    lawn = out.origin == PLANE
    assert lawn[horizon + 6 :].mean() > 0.8 and lawn[H - 30 :].mean() > 0.95
    np.testing.assert_allclose(out.depth_m[lawn], truth[lawn], rtol=1e-4)
    p = CompletionParams()
    assert out.confidence[lawn].max() <= p.max_confidence * p.sparse_plane_confidence + 1e-6
    off = complete(
        zeros,
        zeros,
        rgb,
        sky=sky,
        sparse_m=sparse,
        sparse_confidence=(sparse > 0) * 0.9,
        params=CompletionParams(sparse_planes=False),
    )
    assert not np.any(off.origin == PLANE)


def test_a_near_wall_seen_over_a_few_decimetres_is_a_vertical_plane():
    # The side of a bus 2 m away: 0.2 m of it between two beams, 2 m long.
    up = np.array([0.0, -1.0, 0.0])
    u, v = np.meshgrid(np.linspace(-1, 1, 40), np.linspace(0, 0.2, 8))
    band = np.stack([u.ravel(), -v.ravel(), np.full(u.size, 2.0)], axis=1)
    p = CompletionParams()
    fits, _ = fit_planes(
        np.zeros(len(band), np.intp), band, np.ones(len(band)), 1, up, p, np.random.default_rng(0)
    )
    assert fits.kind[0] == KIND_VERTICAL
    fits, _ = fit_planes(
        np.zeros(len(band), np.intp),
        band,
        np.ones(len(band)),
        1,
        up,
        CompletionParams(min_height_rel=1.0),
        np.random.default_rng(0),
    )
    assert fits.kind[0] != KIND_VERTICAL  # min_height_m alone


def test_a_pole_is_filled_up_at_its_base_depth_and_nothing_else():
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:] = SKY_RGB
    rgb[100:] = textured((H - 100, W), (90, 90, 90), 2)  # road
    z_pole, cols = 8.0, slice(88, 93)
    rgb[15:100, cols] = (60, 60, 60)
    depth = np.zeros((H, W), np.float32)
    depth[100:] = 15.0  # something at the bottom: the road, roughly
    depth[75:100, cols] = z_pole  # the LiDAR reaches the pole's foot only
    conf = (depth > 0).astype(np.float32)
    out = complete(depth, conf, rgb, sky=np.zeros((H, W), bool))
    assert np.all(out.origin[15:75, cols] == VERTICAL)
    # A flat strip facing the camera: exact.
    np.testing.assert_allclose(out.depth_m[15:75, cols], z_pole, rtol=1e-4)
    assert out.confidence[15:75, cols].max() <= CompletionParams().vertical_confidence
    assert not np.any(out.depth_m[:100, : cols.start - 1]) and not np.any(out.depth_m[:100, cols.stop + 1 :])


def test_a_thin_strip_of_wall_seen_too_little_for_a_pole_takes_its_plane():
    # A dark strip 5 pixels wide down the facade (a wall between two columns of windows), its own
    # segment, with depth on its lowest 20 rows only: too little of it for a thin structure's
    # evidence (min_thin_evidence), enough for a plane.
    depth, conf, rgb, truth, sky, roof, _, _ = facade_scene()
    strip = np.zeros((H, W), bool)
    strip[roof:, 88:93] = True
    rgb[strip] = textured((H, W), (110, 40, 40), 8)[strip]
    depth = np.where(strip & (np.arange(H)[:, None] < 100), 0, depth).astype(np.float32)
    conf = (depth > 0).astype(np.float32) * 0.9
    upper = strip & (np.arange(H)[:, None] < 100)
    out = complete(depth, conf, rgb, sky=sky)
    assert np.all(out.depth_m[upper] > 0) and np.all(out.origin[upper] == PLANE)
    np.testing.assert_allclose(out.depth_m[upper], truth[upper], rtol=1e-4)
    off = complete(depth, conf, rgb, sky=sky, params=CompletionParams(thin_planes=False, wall_columns=False))
    assert (off.depth_m[upper] > 0).mean() < 0.5


def test_a_grazing_plane_is_not_extended_into_huge_depths():
    # A wall along the line of sight (x = 1 m, to the right), seen almost edge-on by the centre
    # columns: the ray meets it at less than min_incidence_deg there.
    normal = np.array([1.0, 0.0, 0.0])
    r = rays()
    with np.errstate(divide="ignore"):
        truth = np.where(r[:, 0] > 0.02, 1.0 / np.maximum(r[:, 0], 1e-9), 0.0).reshape(H, W)
    rgb = textured((H, W), (180, 160, 140), 3)
    rgb[:, : W // 2 + 2] = textured((H, W // 2 + 2), (60, 120, 60), 4)
    depth = np.where(truth < 12.0, truth, 0).astype(np.float32)  # data only where the wall is near
    depth[:, : W // 2 + 2] = 0
    conf = (depth > 0).astype(np.float32)
    p = CompletionParams(max_depth_m=1000.0)
    out = complete(depth, conf, rgb, params=p)
    filled = out.origin == PLANE
    assert filled.any()
    sin_incidence = np.abs(r @ normal) / np.linalg.norm(r, axis=1)
    assert np.all(sin_incidence.reshape(H, W)[filled] >= np.sin(np.radians(p.min_incidence_deg)) - 1e-9)
    np.testing.assert_allclose(out.depth_m[filled], truth[filled], rtol=1e-4)
    assert out.depth_m.max() <= 1.0 / np.sin(np.radians(p.min_incidence_deg)) + 1e-3
    assert np.all(np.isfinite(out.depth_m))


def test_empty_and_sky_regions_stay_empty():
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:] = SKY_RGB
    zeros = np.zeros((H, W), np.float32)
    out = complete(zeros, zeros, rgb)
    assert not out.depth_m.any() and not out.confidence.any() and not out.origin.any()
    # A textured region with no depth anywhere near it stays empty too.
    depth, conf, rgb, _, sky, *_ = facade_scene()
    rgb[:, : W // 3] = textured((H, W // 3), (30, 140, 40), 5)
    depth[:, : W // 3] = 0
    conf[:, : W // 3] = 0
    out = complete(depth, conf, rgb, sky=sky)
    assert not np.any(out.origin[:, : W // 3 - 1] >= PLANE)


def test_a_large_image_is_completed_on_a_coarse_grid_with_exact_depths():
    depth, conf, rgb, truth, sky, roof, known_from, _ = facade_scene()
    big = CompletionParams(max_side_px=90)  # the 180-pixel image runs on a 90 x 60 grid
    out = complete(depth, conf, rgb, sky=sky, params=big)
    upper = (slice(roof + 2, known_from), slice(2, W - 2))
    assert np.mean(out.origin[upper] == PLANE) > 0.97
    done = out.origin == PLANE
    np.testing.assert_allclose(out.depth_m[done], truth[done], rtol=1e-4)
    assert not np.any(out.depth_m[:roof])


def test_segments_labelled_people_are_not_completed():
    depth, conf, rgb, _, sky, roof, known_from, _ = facade_scene()
    classes = np.full((H, W), tx.IGNORE_ID, np.uint8)
    classes[known_from:] = tx.PERSON
    out = complete(depth, conf, rgb, sky=sky, classes=classes)
    assert not np.any(out.origin >= PLANE)
    keep_out = np.zeros((H, W), bool)
    keep_out[roof : roof + 10] = True
    out = complete(depth, conf, rgb, sky=sky, keep_out=keep_out)
    assert not out.depth_m[roof : roof + 10].any() and out.depth_m[roof + 10 : known_from].all()


# ------------------------------------------------------------------------------------------
# Hostile inputs


def test_hostile_inputs_are_refused_with_a_clear_message():
    depth, conf, rgb, *_ = facade_scene()
    bad = depth.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="depth_m has 1 NaN or infinite"):
        complete(bad, conf, rgb)
    bad[0, 0] = np.inf
    with pytest.raises(ValueError, match="depth_m has 1 NaN or infinite"):
        complete(bad, conf, rgb)
    with pytest.raises(ValueError, match=r"confidence has shape \(120, 179\), depth_m has \(120, 180\)"):
        complete(depth, conf[:, 1:], rgb)
    with pytest.raises(ValueError, match=r"rgb must have shape \(120, 180, 3\)"):
        complete(depth, conf, rgb[1:])
    with pytest.raises(ValueError, match="negative depths"):
        complete(-depth, conf, rgb)
    with pytest.raises(ValueError, match=r"confidence must lie in \[0, 1\]"):
        complete(depth, conf * 2, rgb)
    with pytest.raises(ValueError, match="floating-point"):
        complete(depth.astype(np.int32), conf, rgb)
    with pytest.raises(ValueError, match="rays_cam must have shape"):
        complete_depth_map(depth, conf, rgb, rays_cam=rays()[1:], up_cam=UP, focal_px=F)
    with pytest.raises(ValueError, match="rays_cam must have z = 1"):
        complete_depth_map(depth, conf, rgb, rays_cam=2 * rays(), up_cam=UP, focal_px=F)
    with pytest.raises(ValueError, match="up_cam must not be the zero vector"):
        complete_depth_map(depth, conf, rgb, rays_cam=rays(), up_cam=np.zeros(3), focal_px=F)
    with pytest.raises(ValueError, match="focal_px must be a positive"):
        complete_depth_map(depth, conf, rgb, rays_cam=rays(), up_cam=UP, focal_px=float("nan"))
    with pytest.raises(ValueError, match="sky must be a bool mask"):
        complete(depth, conf, rgb, sky=np.zeros((H, W), np.uint8))
    with pytest.raises(ValueError, match=r"keep_out must have shape \(120, 180\)"):
        complete(depth, conf, rgb, keep_out=np.zeros((H, W + 1), bool))
    with pytest.raises(ValueError, match="sparse_m and sparse_confidence come together"):
        complete(depth, conf, rgb, sparse_m=depth)
    sparse = depth.copy()
    sparse[5, 5] = np.nan
    with pytest.raises(ValueError, match="sparse_m has 1 NaN"):
        complete(depth, conf, rgb, sparse_m=sparse, sparse_confidence=conf)
    with pytest.raises(ValueError, match="origin holds code 9"):
        complete(depth, conf, rgb, origin=np.full((H, W), 9, np.uint8))


def test_bad_parameters_name_the_stage():
    with pytest.raises(ConfigError, match=r"^stage complete_depth: unknown keys \['max_depht_m'\]"):
        get_stage("complete_depth")(Scene("s", "x", [], []), {"max_depht_m": 10})
    for values, message in (
        ({"max_sky_share": 2.0}, "max_sky_share = 2.0: must be a number in [0, 1] (finite)"),
        ({"min_depth_m": 200.0}, "min_depth_m = 200.0: must be below max_depth_m (150.0)"),
        ({"min_inliers": 2.5}, "min_inliers = 2.5: must be an integer in [3, 100000000]"),
        ({"inlier_tol_m": float("nan")}, "inlier_tol_m = nan: must be a number in (0, 100] (finite)"),
    ):
        with pytest.raises(ConfigError) as e:
            CompletionParams(**values)
        assert str(e.value) == f"CompletionParams: {message}"


def test_dense_origin_must_match_the_dense_depth():
    zeros = np.zeros((4, 5), np.float32)
    dense = zeros.copy()
    dense[0, 0] = 3.0
    with pytest.raises(InvalidRecord, match="dense_origin"):
        CameraDepth(zeros, zeros, zeros.astype(np.uint8), dense, dense / 3, np.zeros((4, 5), np.uint8))
    with pytest.raises(InvalidRecord, match="holds code 7"):
        CameraDepth(zeros, zeros, zeros.astype(np.uint8), dense, dense / 3, (dense > 0).astype(np.uint8) * 7)
    with pytest.raises(InvalidRecord, match="without dense_m"):
        CameraDepth(zeros, zeros, zeros.astype(np.uint8), dense_origin=np.zeros((4, 5), np.uint8))
    # Derived when not given: the measured pixel is "lidar", the rest "densified".
    sparse = dense.copy()
    dense[1, 1] = 4.0
    derived = CameraDepth(sparse, (sparse > 0).astype(np.float32), zeros.astype(np.uint8), dense, dense / 4)
    assert derived.dense_origin[0, 0] == DENSE_ORIGINS.index("lidar")
    assert derived.dense_origin[1, 1] == DENSIFIED
    assert np.count_nonzero(derived.dense_origin) == 2


# ------------------------------------------------------------------------------------------
# The vectorised fit against a plain per-group reference


def _reference_plane(points: np.ndarray) -> np.ndarray:
    """The least-squares plane of (N, 3) points, a plain SVD: its unit normal."""
    centred = points - points.mean(axis=0)
    return np.linalg.svd(centred)[2][-1]


def test_fit_planes_agrees_with_a_plain_per_group_fit():
    rng = np.random.default_rng(0)
    up = np.array([0.0, -1.0, 0.0])
    groups, points, truths, kinds, clean = [], [], [], [], []
    for g in range(6):
        vertical = g % 2 == 0
        a, b = rng.uniform(-8, 8, 200), rng.uniform(-1.5, 3.0, 200)
        if vertical:  # a facade: normal horizontal
            yaw = rng.uniform(-0.6, 0.6)
            n = np.array([np.sin(yaw), 0.0, -np.cos(yaw)])
            along = np.array([np.cos(yaw), 0.0, np.sin(yaw)])
            pts = 15.0 * -n + a[:, None] * along + b[:, None] * np.array([0.0, -1.0, 0.0])
        else:  # the ground 1.6 m below the camera
            pts = np.stack([a, np.full(200, 1.6), 10 + 2 * np.abs(b) * 4], axis=1)
            n = np.array([0.0, -1.0, 0.0])
        pts = pts + rng.normal(0, 0.005, pts.shape)
        outliers = rng.random(200) < 0.15
        pts[outliers] += rng.uniform(-3, 3, (outliers.sum(), 3))
        groups.append(np.full(200, g))
        points.append(pts)
        truths.append(n)
        kinds.append(KIND_VERTICAL if vertical else KIND_GROUND)
        clean.append(1 - outliers.mean())
    groups, points = np.concatenate(groups), np.concatenate(points)
    p = CompletionParams()
    fits, inlier = fit_planes(groups, points, np.ones(len(points)), 6, up, p, np.random.default_rng(1))
    for g in range(6):
        assert fits.kind[g] == kinds[g]
        mine = groups == g
        reference = _reference_plane(points[mine & inlier])
        assert abs(abs(fits.normal[g] @ reference) - 1) < 1e-4  # the same plane as the plain fit
        assert abs(abs(fits.normal[g] @ truths[g]) - 1) < 1e-3
        assert clean[g] - 0.01 <= fits.share[g] <= clean[g] + 0.03  # outliers rarely land on it
    # A row of ground points is no facade, and two points no plane at all.
    row = np.stack([np.linspace(-5, 5, 50), np.full(50, 1.6), np.full(50, 10.0)], axis=1)
    fits, _ = fit_planes(np.zeros(50, np.intp), row, np.ones(50), 1, up, p, np.random.default_rng(2))
    assert fits.kind[0] == 0


def test_a_line_of_points_fixes_a_plane_only_with_a_label_that_says_which():
    up = np.array([0.0, -1.0, 0.0])
    p, rng = CompletionParams(), np.random.default_rng(3)
    ones, group = np.ones(50), np.zeros(50, np.intp)
    # One scan line across a level lawn 1.6 m below the camera, seen obliquely (x and z vary).
    line = np.stack([np.linspace(-5, 5, 50), np.full(50, 1.6), np.linspace(8, 12, 50)], axis=1)
    fits, inlier = fit_planes(group, line, ones, 1, up, p, rng, lies=np.ones(1, bool))
    assert fits.kind[0] == KIND_GROUND and fits.from_line[0] and inlier.all()
    # The plane through the line closest to level: the lawn itself.
    assert abs(fits.normal[0] @ up) > 1 - 1e-9 and abs(abs(fits.offset[0]) - 1.6) < 1e-9
    assert fit_planes(group, line, ones, 1, up, p, rng, lies=np.zeros(1, bool))[0].kind[0] == 0
    assert (
        fit_planes(group, line, ones, 1, up, CompletionParams(line_planes=False), rng, lies=np.ones(1, bool))[
            0
        ].kind[0]
        == 0
    )
    # A line rising 20 degrees is no ground, whatever the label (it rises enough for a wall).
    steep = line.copy()
    steep[:, 1] = 1.6 - np.tan(np.radians(20)) * np.hypot(steep[:, 0] + 5, steep[:, 2] - 8)
    fits, _ = fit_planes(group, steep, ones, 1, up, p, rng, lies=np.ones(1, bool))
    assert fits.kind[0] != KIND_GROUND and not fits.from_line[0]
    # The same line labelled a standing structure: the vertical plane through it (a scan line at a
    # wall's foot), which the height test alone refuses.
    fits, _ = fit_planes(group, line, ones, 1, up, p, rng, stands=np.ones(1, bool))
    assert fits.kind[0] == KIND_VERTICAL and fits.from_line[0]
    direction = (line[-1] - line[0]) / np.linalg.norm(line[-1] - line[0])
    assert abs(fits.normal[0] @ direction) < 1e-9 and abs(fits.normal[0] @ up) < 1e-9
    assert fit_planes(group, line, ones, 1, up, p, rng)[0].kind[0] == 0


def test_a_narrow_strip_of_ground_too_short_across_to_fix_its_tilt_takes_the_level_plane():
    up = np.array([0.0, -1.0, 0.0])
    p, rng = CompletionParams(), np.random.default_rng(3)
    # Two scan lines 0.2 m apart on a level pavement 1.6 m below the camera, the nearer one 4 cm
    # higher (a kerb's edge): the free fit tilts 11 degrees, beyond max_tilt_deg.
    x = np.linspace(-5, 5, 40)
    near = np.stack([x, np.full(40, 1.56), np.full(40, 9.0)], axis=1)
    far = np.stack([x, np.full(40, 1.6), np.full(40, 9.2)], axis=1)
    strip = np.concatenate([near, far])
    ones, group = np.ones(80), np.zeros(80, np.intp)
    assert fit_planes(group, strip, ones, 1, up, p, rng)[0].kind[0] == 0, "no label: no plane"
    fits, inlier = fit_planes(group, strip, ones, 1, up, p, rng, lies=np.ones(1, bool))
    assert fits.kind[0] == KIND_GROUND and fits.from_line[0] and inlier.all()
    assert fits.normal[0] @ up > np.cos(np.radians(1.0))
    assert abs(abs(fits.offset[0]) - 1.58) < 0.03


def test_without_labels_a_line_of_points_at_the_grounds_height_lies():
    # A road in full depth (its plane gives the camera's height, 1.6 m) beside a lawn of another
    # colour seen by one scan line; no pseudo labels beyond the sky.
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:] = SKY_RGB
    horizon = (H - 1) // 2
    rgb[horizon + 1 :, : W // 2] = textured((H - horizon - 1, W // 2), (90, 90, 90), 8)
    rgb[horizon + 1 :, W // 2 :] = textured((H - horizon - 1, W - W // 2), (100, 140, 80), 9)
    r = rays().reshape(H, W, 3)
    truth = np.where(r[..., 1] > 0.01, 1.6 / np.maximum(r[..., 1], 1e-9), 0).astype(np.float32)
    depth = np.zeros((H, W), np.float32)
    depth[horizon + 20 :, : W // 2] = truth[horizon + 20 :, : W // 2]
    depth[horizon + 30, W // 2 :] = truth[horizon + 30, W // 2 :]
    conf = (depth > 0).astype(np.float32) * 0.9
    sky = np.zeros((H, W), bool)
    sky[: horizon + 1] = True
    out = complete(depth, conf, rgb, sky=sky, classes=np.where(sky, tx.SKY, tx.IGNORE_ID).astype(np.uint8))
    lawn = out.origin[:, W // 2 + 2 :] == PLANE
    assert lawn[horizon + 8 :].mean() > 0.9
    np.testing.assert_allclose(out.depth_m[:, W // 2 + 2 :][lawn], truth[:, W // 2 + 2 :][lawn], rtol=1e-4)
    # Without the road nothing tells the lawn's line from a kerb's top: it stays a line.
    depth[:, : W // 2] = 0
    conf = (depth > 0).astype(np.float32) * 0.9
    assert not np.any(complete(depth, conf, rgb, sky=sky).origin[:, W // 2 + 2 :] == PLANE)


def crown_scene(colour=(40, 130, 45), radius_m: float = 2.0, z_m: float = 10.0):
    """A tree crown: a sphere of ``radius_m`` whose centre is ``z_m`` ahead, seen by a level
    pinhole; the LiDAR saw its lower half. Returns depth, confidence, rgb, truth and its disc."""
    r = rays().reshape(H, W, 3)
    centre = np.array([0.0, -1.0, z_m])
    # Nearest intersection of each ray with the sphere: |t r - c|^2 = R^2.
    a = np.sum(r * r, axis=-1)
    b = -2 * r @ centre
    disc = b * b - 4 * a * (centre @ centre - radius_m**2)
    inside = disc > 0
    truth = np.where(inside, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0).astype(np.float32)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:] = SKY_RGB
    rgb[inside] = textured((H, W), colour, 4)[inside]
    rows = np.nonzero(inside.any(axis=1))[0]
    lower = np.zeros((H, W), bool)
    lower[(rows[0] + rows[-1]) // 2 :] = True
    depth = np.where(inside & lower, truth, 0).astype(np.float32)
    return depth, (depth > 0).astype(np.float32) * 0.9, rgb, truth, inside


def off_rim(inside: np.ndarray) -> np.ndarray:
    """``inside`` less its pixels next to the sky: a crown's rim, which blends into the sky in a
    real image and is never filled."""
    return inside & ~cv2.dilate((~inside).view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def test_a_tree_crown_takes_the_camera_facing_plane_through_its_known_depths():
    depth, conf, rgb, truth, inside = crown_scene()
    sky = ~inside
    out = complete(depth, conf, rgb, sky=sky)
    crown = inside & (depth == 0)
    filled = crown & (out.origin == VERTICAL)
    assert filled.sum() > 0.9 * crown.sum()
    # Off by at most the crown's radius, and far less on most of it.
    err = np.abs(out.depth_m[filled] - truth[filled])
    assert err.max() <= 2.0 and np.median(err / truth[filled]) < 0.1
    assert out.confidence[filled].max() <= CompletionParams().crown_confidence
    # Not green: no crown (and no plane fits a sphere).
    grey = complete(depth, conf, crown_scene(colour=(120, 120, 120))[2], sky=sky)
    assert not np.any(grey.depth_m[crown])
    assert not np.any(
        complete(depth, conf, rgb, sky=sky, params=CompletionParams(crowns=False)).depth_m[crown]
    )
    # Known depths spread over more than crown_max_spread of their median: not one crown.
    spread = depth.copy()
    spread[::2] *= 1.5
    assert not np.any(complete(spread, conf, rgb, sky=sky).depth_m[crown])


def test_a_crown_of_many_segments_is_filled_as_one_from_its_lower_part():
    depth, conf, rgb, truth, inside = crown_scene()
    # Bands of two greens across the crown: each band a segment of its own, only the lower ones
    # with depth.
    rows = np.arange(H)[:, None] // 6 % 2 == 1
    rgb = np.where((inside & rows)[..., None], textured((H, W), (15, 80, 20), 5), rgb)
    sky = ~inside
    upper = off_rim(inside) & (depth == 0)
    out = complete(depth, conf, rgb, sky=sky)
    filled = upper & (out.origin == VERTICAL)
    assert filled.sum() > 0.9 * upper.sum()
    err = np.abs(out.depth_m[filled] - truth[filled])
    assert err.max() <= 2.0 and np.median(err / truth[filled]) < 0.1
    assert out.confidence[filled].max() <= CompletionParams().crown_confidence
    alone = complete(depth, conf, rgb, sky=sky, params=CompletionParams(canopies=False))
    assert (alone.depth_m[upper] > 0).mean() < 0.5, "the bands without depth stay empty without it"
    # A few known pixels in a large green region: not enough to say the crown's depth.
    few = np.zeros_like(depth)
    top = np.flatnonzero(depth.any(axis=1))[0]
    cols = np.flatnonzero(depth[top])[:20]  # 20 pixels of its highest known row
    few[top, cols] = depth[top, cols]
    sparse_conf = (few > 0).astype(np.float32) * 0.9
    assert not np.any(complete(few, sparse_conf, rgb, sky=sky).depth_m[upper])
    any_share = CompletionParams(canopy_min_known_share=0.0)
    assert np.all(complete(few, sparse_conf, rgb, sky=sky, params=any_share).depth_m[upper] > 0)
    labelled = np.where(inside, tx.CAR, tx.SKY).astype(np.uint8)
    car = complete(depth, conf, rgb, sky=sky, classes=labelled)
    assert not np.any(car.depth_m[upper] > 0), "not a crown where the labels say it is a thing"


def test_a_vehicle_no_plane_explains_takes_the_camera_facing_plane_if_of_one_depth():
    # A rounded grey body (a sphere of 1 m, 12 m ahead) labelled car; the LiDAR saw its lower half.
    depth, conf, _, truth, inside = crown_scene(radius_m=1.0, z_m=12.0)
    rgb = np.where(inside[..., None], textured((H, W), (120, 120, 125), 6), SKY_RGB).astype(np.uint8)
    sky = ~inside
    classes = np.where(inside, tx.CAR, tx.SKY).astype(np.uint8)
    upper = off_rim(inside) & (depth == 0)
    out = complete(depth, conf, rgb, sky=sky, classes=classes)
    filled = upper & (out.origin == VERTICAL)
    assert filled.sum() > 0.9 * upper.sum()
    assert np.abs(out.depth_m[filled] - truth[filled]).max() <= 1.0
    assert out.confidence[filled].max() <= CompletionParams().crown_confidence
    # Not without the label, nor with vehicle_max_spread 0.
    assert not np.any(complete(depth, conf, rgb, sky=sky).depth_m[upper])
    off = CompletionParams(vehicle_max_spread=0.0)
    assert not np.any(complete(depth, conf, rgb, sky=sky, classes=classes, params=off).depth_m[upper])


def two_facades(gap_m: float = 18.0):
    """Two facades of one colour side by side, 12 m ahead (left half) and ``12 + gap_m`` m ahead
    (right half), both facing the camera; the LiDAR saw rows >= 80, the sky is above row 20."""
    r = rays()
    near = plane_depth(r, (0.0, 0.0, -1.0), 12.0)
    far = plane_depth(r, (0.0, 0.0, -1.0), 12.0 + gap_m)
    truth = np.where(np.arange(W)[None, :] < W // 2, near, far).astype(np.float32)
    rgb = textured((H, W), (200, 180, 150), 0)
    rgb[:20] = SKY_RGB
    depth = np.zeros((H, W), np.float32)
    depth[80:] = truth[80:]
    sky = np.zeros((H, W), bool)
    sky[:20] = True
    return depth, (depth > 0).astype(np.float32) * 0.9, rgb, truth, sky


def test_two_facades_of_one_segment_climb_their_own_columns():
    depth, conf, rgb, truth, sky = two_facades()
    out = complete(depth, conf, rgb, sky=sky)
    assert np.bincount(out.segments[20:].ravel()).max() > 0.9 * (H - 20) * W, "one segment for both"
    upper = np.zeros((H, W), bool)
    upper[20:80] = True
    filled = upper & (out.depth_m > 0)
    assert filled.sum() > 0.95 * upper.sum()
    np.testing.assert_allclose(out.depth_m[filled], truth[filled], rtol=1e-4)
    # Without the climb the two planes, apart, reach only split_extrapolation_ref_px.
    alone = complete(
        depth, conf, rgb, sky=sky, params=CompletionParams(climb_columns=False, wall_columns=False)
    )
    assert not np.any(alone.depth_m[20:40] > 0)


def round_tower(radius_m: float = 3.0, centre_z_m: float = 12.0, known_from: int = 50):
    """A round tower (a vertical cylinder of ``radius_m`` whose axis is ``centre_z_m`` ahead) of one
    colour, seen by a level pinhole: no plane explains it. The LiDAR saw rows >= ``known_from``
    (above the horizon, row 59.5); the sky is above row 20 and beside the tower."""
    r = rays().reshape(H, W, 3)
    a = r[..., 0] ** 2 + 1.0  # |(x, z)| of the ray per unit depth, squared
    disc = centre_z_m**2 - a * (centre_z_m**2 - radius_m**2)
    hit = disc >= 0
    truth = np.where(hit, (centre_z_m - np.sqrt(np.maximum(disc, 0))) / a, 0).astype(np.float32)
    sky = ~hit
    sky[:20] = True
    truth[sky] = 0
    rgb = np.where(sky[..., None], SKY_RGB, textured((H, W), (200, 180, 150), 7)).astype(np.uint8)
    depth = np.zeros((H, W), np.float32)
    depth[known_from:] = truth[known_from:]
    return depth, (depth > 0).astype(np.float32) * 0.9, rgb, truth, sky


def test_each_column_of_a_wall_no_plane_explains_climbs_from_its_topmost_known_pixel():
    depth, conf, rgb, truth, sky = round_tower()
    upper = (truth > 0) & (depth == 0)
    upper[:, :1] = upper[:, -1:] = False
    alone = complete(depth, conf, rgb, sky=sky, params=CompletionParams(wall_columns=False))
    assert not np.any(alone.depth_m[upper] > 0), "no plane explains a round tower"
    out = complete(depth, conf, rgb, sky=sky)
    filled = upper & (out.depth_m > 0)
    assert filled.sum() > 0.95 * upper.sum()
    # A vertical surface keeps its horizontal distance up a column of a level camera: exact.
    np.testing.assert_allclose(out.depth_m[filled], truth[filled], rtol=1e-4)
    assert np.all(out.origin[filled] == VERTICAL)
    assert out.confidence[filled].max() <= CompletionParams().wall_confidence
    assert out.confidence[20, W // 2] < out.confidence[49, W // 2], "lower farther from the data"
    assert not np.any(out.depth_m[sky]), "the sky stays empty"
    # Not without sky labels (nothing tells the sky above a roofline from a wall), nor for a
    # segment labelled ground, nor from a thing's known pixels.
    assert not np.any(complete(depth, conf, rgb).depth_m[upper] > 0)
    road = np.where(sky, tx.SKY, tx.ROAD).astype(np.uint8)
    assert not np.any(complete(depth, conf, rgb, sky=sky, classes=road).origin[upper] == VERTICAL)
    car_base = np.where(sky, tx.SKY, 255).astype(np.uint8)
    car_base[50:53] = np.where(sky[50:53], tx.SKY, tx.CAR)  # a car's roof seen just below the wall
    out = complete(depth, conf, rgb, sky=sky, classes=car_base)
    climbed = upper & (out.origin == VERTICAL)
    assert climbed.any()
    np.testing.assert_allclose(out.depth_m[climbed], truth[climbed], rtol=1e-4)
    assert not np.any(out.depth_m[50:53][depth[50:53] == 0] > 0)


def test_a_climbed_column_goes_on_up_through_a_segment_the_lidar_did_not_see():
    depth, conf, rgb, truth, sky = round_tower()
    # The tower's top, rows 20-34, a darker band: a segment of its own, without depth.
    band = np.zeros((H, W), bool)
    band[20:35] = True
    band &= ~sky
    rgb[band] = textured((H, W), (90, 70, 60), 9)[band]
    inner = band & ~cv2.dilate((~band).view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    inner[:, :2] = inner[:, -2:] = False
    out = complete(depth, conf, rgb, sky=sky)
    assert out.segments[inner].min() == out.segments[inner].max(), "the band is one segment"
    assert out.segments[inner][0] not in set(out.segments[40:50][~sky[40:50]].ravel()), "not the tower's"
    filled = inner & (out.depth_m > 0)
    assert filled.sum() > 0.9 * inner.sum()
    np.testing.assert_allclose(out.depth_m[filled], truth[filled], rtol=1e-4)
    assert np.all(out.origin[filled] == VERTICAL)
    params = CompletionParams()
    assert out.confidence[filled].max() <= params.wall_confidence * params.upward_confidence
    off = complete(depth, conf, rgb, sky=sky, params=CompletionParams(wall_columns=False))
    assert not np.any(off.depth_m[inner] > 0)
    # A band labelled a thing (a truck's top in front of the tower) is not climbed into.
    labels = np.where(sky, tx.SKY, 255).astype(np.uint8)
    labels[band] = tx.TRUCK
    assert not np.any(complete(depth, conf, rgb, sky=sky, classes=labels).depth_m[inner] > 0)


def _one_scan_line(truth: np.ndarray, row: int) -> tuple[np.ndarray, np.ndarray]:
    depth = np.zeros((H, W), np.float32)
    depth[row] = truth[row]
    return depth, (depth > 0).astype(np.float32) * 0.9


def test_a_lawn_seen_by_one_scan_line_is_completed_only_if_labelled_ground():
    rgb, horizon, truth = lawn_scene()
    depth, conf = _one_scan_line(truth, horizon + 30)
    sky = np.zeros((H, W), bool)
    sky[: horizon + 1] = True
    classes = np.where(sky, tx.SKY, tx.TERRAIN).astype(np.uint8)
    out = complete(depth, conf, rgb, sky=sky, classes=classes)
    lawn = out.origin == PLANE
    assert lawn[horizon + 8 :].mean() > 0.95
    np.testing.assert_allclose(out.depth_m[lawn], truth[lawn], rtol=1e-4)
    p = CompletionParams()
    assert out.confidence[lawn].max() <= p.max_confidence * p.line_confidence + 1e-6
    assert not np.any(complete(depth, conf, rgb, sky=sky).origin == PLANE), "no label, no plane"
    unlabelled = np.where(sky, tx.SKY, tx.IGNORE_ID).astype(np.uint8)
    assert not np.any(complete(depth, conf, rgb, sky=sky, classes=unlabelled).origin == PLANE)


def test_a_facade_seen_by_one_scan_line_is_completed_if_labelled_a_building():
    _, _, rgb, truth, sky, roof, _, _ = facade_scene()
    # At the camera's height: a level line in 3D (lower rows of a turned facade rise with depth).
    depth, conf = _one_scan_line(truth, (H - 1) // 2)
    classes = np.where(sky, tx.SKY, tx.BUILDING).astype(np.uint8)
    out = complete(depth, conf, rgb, sky=sky, classes=classes)
    assert np.all(out.origin[roof:][depth[roof:] == 0] == PLANE)
    np.testing.assert_allclose(out.depth_m[roof:], truth[roof:], rtol=1e-4)
    assert not np.any(out.depth_m[:roof])
    assert not np.any(complete(depth, conf, rgb, sky=sky).origin == PLANE)


# ------------------------------------------------------------------------------------------
# The stage on a small synthetic scene


@pytest.fixture(scope="module")
def completed_scene() -> tuple[Scene, Scene]:
    cfg = SyntheticConfig(
        scenes=1, frames=4, seed=5, height=72, width=108, lidar=LidarSpec(beams=32, columns=512, sectors=8)
    )
    scene = SyntheticScene(cfg, 0).scene()
    for name in ("aggregate_lidar", "project_depth", "densify_depth", "pseudo_semantics"):
        scene = get_stage(name)(scene, {})
    before = [f for f in scene.frames]
    after = get_stage("complete_depth")(Scene(scene.scene_id, scene.source, scene.calibrations, before), {})
    return Scene(scene.scene_id, scene.source, scene.calibrations, before), after


def test_the_stage_adds_completed_pixels_with_their_own_codes(completed_scene):
    before, after = completed_scene
    gained, errors = 0, []
    for fb, fa in zip(before.frames, after.frames, strict=True):
        for cb, ca in zip(fb.cameras, fa.cameras, strict=True):
            db, da = cb.depth, ca.depth
            assert set(np.unique(db.dense_origin)) <= {0, 1, 2}
            assert np.array_equal(da.dense_m[db.dense_m > 0], db.dense_m[db.dense_m > 0])
            assert np.array_equal((da.dense_origin > 0), da.dense_m > 0)
            new = da.dense_origin >= PLANE
            assert not np.any(db.dense_m[new])
            assert np.all(da.dense_confidence[new] <= CompletionParams().max_confidence)
            truth = ca.truth.depth_m
            gained += int(np.count_nonzero(new & (truth > 0)))
            assert np.count_nonzero(new & (ca.truth.semantic == tx.SKY)) <= 0.01 * max(new.sum(), 1) + 3
            ok = new & (truth > 0)
            errors.append(np.abs(da.dense_m[ok] - truth[ok]) / truth[ok])
            assert np.all(np.isfinite(da.dense_m))
    assert gained > 0
    assert np.mean(np.concatenate(errors)) < 0.05


def test_the_origin_map_round_trips_through_the_cache_schema(completed_scene):
    from phigenesis.data.schema import CacheContents, frame_schema, frame_to_batch, row_to_frame

    _, after = completed_scene
    frame = after.frames[1]
    schema = frame_schema(CacheContents(camera_truth=(), depth=True))
    assert "depth_dense_origin_png" in {f.name for f in schema.field("cameras").type.value_type}
    back = row_to_frame(frame_to_batch(frame, "synthetic", schema))
    for a, b in zip(frame.cameras, back.cameras, strict=True):
        assert np.array_equal(a.depth.dense_origin, b.depth.dense_origin)


def test_the_stage_without_pseudo_labels_warns_once(caplog):
    cfg = SyntheticConfig(
        scenes=1, frames=2, seed=2, height=36, width=54, lidar=LidarSpec(beams=16, columns=256)
    )
    scene = SyntheticScene(cfg, 0).scene()
    for name in ("project_depth", "densify_depth"):
        scene = get_stage(name)(scene, {})
    with caplog.at_level(logging.WARNING, logger="phigenesis.prep"):
        out = get_stage("complete_depth")(scene, {})
        frames = list(out.frames)
    warnings = [r for r in caplog.records if "no pseudo-semantic labels" in r.getMessage()]
    assert len(warnings) == 1
    assert all(c.depth.dense_origin is not None for f in frames for c in f.cameras)


def test_a_read_only_rays_table_gives_the_same_completion_as_fresh_rays_every_call():
    """complete_depth_map keeps the checks, lengths and coarse grid of a read-only rays array (a
    per-calibration table) across calls; the answer is bit-identical to fresh writeable rays."""
    depth, conf, rgb, _, sky, *_ = facade_scene(windows=True, noise_m=0.01)
    table = rays()
    table.setflags(write=False)
    for params in (CompletionParams(), CompletionParams(max_side_px=90)):  # full grid, coarse grid
        fresh = complete(depth, conf, rgb, sky=sky, params=params)
        for _ in range(2):  # the second call reuses what the first one kept
            cached = complete_depth_map(
                depth, conf, rgb, rays_cam=table, up_cam=UP, focal_px=F, sky=sky, params=params
            )
            for name in ("depth_m", "confidence", "origin", "segments"):
                assert np.array_equal(getattr(cached, name), getattr(fresh, name)), name
        assert np.sum(fresh.origin == PLANE) > 2000


def test_the_fine_pass_kernel_equals_its_numpy_reference(monkeypatch):
    """The coarse grid's fine pass (every fillable pixel of a completed cell takes the cell's
    plane) in C (csrc/complete_fine.c) is bit-identical to the numpy path it replaces."""
    from phigenesis.data import native
    from phigenesis.data.stages.completion import depth_map as complete_module

    assert native.load_complete_fine() is not None, native.failure_reason()  # a C compiler here
    depth, conf, rgb, truth, sky, *_ = facade_scene(windows=True, noise_m=0.01)
    params = CompletionParams(max_side_px=90)
    kernel = complete(depth, conf, rgb, sky=sky, params=params)
    monkeypatch.setattr(complete_module, "load_complete_fine", lambda: None)
    plain = complete(depth, conf, rgb, sky=sky, params=params)
    for name in ("depth_m", "confidence", "origin", "segments"):
        assert np.array_equal(getattr(kernel, name), getattr(plain, name)), name
    done = kernel.origin == PLANE
    assert done.sum() > 2000
    np.testing.assert_allclose(kernel.depth_m[done], truth[done], atol=0.5)


def test_a_camera_without_depth_is_left_empty_without_segmenting_its_image(completed_scene, monkeypatch):
    """A frame without LiDAR (every map 0) costs next to nothing: the stage neither segments the
    image nor fits anything, and the map stays all 0, exactly what the full completion returns."""
    import phigenesis.data.stages.completion.depth_map as complete_module
    from phigenesis.data.stages.project import pixel_rays

    before, _ = completed_scene
    frame = before.frames[0]
    cam = frame.cameras[0]
    h, w = cam.calibration.height, cam.calibration.width
    zeros = np.zeros((h, w), np.float32)
    # What densify_depth leaves on a camera no LiDAR point reached: all-0 maps.
    no_depth = dataclasses.replace(
        CameraDepth.empty(h, w), dense_m=zeros, dense_confidence=zeros, dense_origin=zeros.astype(np.uint8)
    )
    empty_cam = dataclasses.replace(cam, depth=no_depth)
    full = complete_depth_map(
        empty_cam.depth.dense_m,
        empty_cam.depth.dense_confidence,
        cam.decode_image(),
        rays_cam=pixel_rays(cam),
        up_cam=np.array([0.0, -1.0, 0.0]),
        focal_px=100.0,
        sparse_m=empty_cam.depth.sparse_m,
        sparse_confidence=empty_cam.depth.sparse_confidence,
    )
    assert not full.depth_m.any() and not full.confidence.any() and not full.origin.any()

    def refuse(*args, **kwargs):
        raise AssertionError("segment_image called for a camera without depth")

    monkeypatch.setattr(complete_module, "segment_image", refuse)
    scene = Scene(
        before.scene_id, before.source, before.calibrations, [dataclasses.replace(frame, cameras=[empty_cam])]
    )
    out = get_stage("complete_depth")(scene, {}).frames[0].cameras[0].depth
    assert not out.dense_m.any() and not out.dense_confidence.any() and not out.dense_origin.any()
