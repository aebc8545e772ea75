"""One image's projection: the candidate points through the kernel, the visibility test, the
z-buffer and the per-pixel depth, confidence and origin.

The stage is :mod:`phigenesis.data.stages.project`."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported
from phigenesis.data.native import load_camera_points
from phigenesis.data.records import (
    CameraDepth,
    CameraImage,
)
from phigenesis.data.stages.projection.candidates import CameraPoints, normalized_bounds
from phigenesis.data.stages.projection.edges import (
    CameraPixels,
    depth_edge_band,
    depth_edge_band_reference,
    silhouette_pixels,
    silhouette_pixels_reference,
)
from phigenesis.data.stages.projection.fits import (
    _centre_first,
    _pixel_index,
    fit_pixels,
    fit_pixels_reference,
)
from phigenesis.data.stages.projection.occluders import _zbuffer, occluder_depth, occluder_depth_reference
from phigenesis.data.stages.projection.params import ORIGIN_WEIGHTS, ProjectParams, _cap_of, supersample_of


def _projection_counts(projected: int, behind_ego: int, behind_vehicles: int, thinned: int) -> dict[str, int]:
    return {
        "projected": projected,
        "removed_by_visibility": 0,
        "behind_ego_body": behind_ego,
        "behind_vehicles": behind_vehicles,
        "thinned_in_pixels": thinned,
        "mixed_pixels": 0,
        "edge_pixels": 0,
    }


def _mix64(x: NDArray[np.int64]) -> NDArray[np.uint64]:
    """splitmix64's finaliser of ``x`` + its increment (uint64, wrapping): ``camera_points.c``'s
    hash of a point's index."""
    z = x.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def thin_in_pixels(
    index: NDArray[np.int64],
    z: NDArray[np.float32],
    pixel: NDArray[np.int64],
    size: int,
    max_per_pixel: int,
    params: ProjectParams,
) -> NDArray[np.bool_]:
    """(K,) True for the points (``index`` into the scene's points, camera ``z`` float32 metres,
    flat ``pixel`` of a ``size``-pixel image) that a pixel holding more than ``max_per_pixel``
    keeps: those no deeper than ``zmin * (1 + tau) + slack_m`` (its nearest point's splat bound:
    the visibility test removes the others, whatever else covers the pixel) and, where more than
    ``max_per_pixel`` lie in that band, a uniform subset of about ``max_per_pixel``: point i stays
    if ``(hash(i) >> 40) * in_band < max_per_pixel * 2^24`` (a hash of its index, so the same
    points stay whichever order they come in). Pixels with fewer points keep all.

    The numpy twin of the thinning in ``camera_points.c`` (same float32 bound, same hash)."""
    total = np.bincount(pixel, minlength=size)
    dense = total[pixel] > max_per_pixel
    zmin = np.full(size, np.inf, np.float32)
    np.minimum.at(zmin, pixel[dense], z[dense])
    band = z <= zmin[pixel] * (1 + params.tau) + params.slack_m
    in_band = np.bincount(pixel[dense & band], minlength=size)[pixel]
    draw = (_mix64(index) >> np.uint64(40)).astype(np.int64)
    return ~dense | (band & ((in_band <= max_per_pixel) | (draw * in_band < max_per_pixel << 24)))


def camera_pixels(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
) -> CameraPixels:
    """The points (world frame) that land in the image in front of the ego body and the vehicles.

    Returns ``(index, uv, z, pixel, counts)``: (K,) int64 indices into ``points``, (K, 2) float64
    pixel positions (u along the width), (K,) float32 camera z in metres, (K,) int64 flat pixel
    indices (row * W + column) and the counts ``projected`` (points in the image),
    ``behind_ego_body``, ``behind_vehicles`` and ``thinned_in_pixels`` (the per-pixel cap,
    :func:`thin_in_pixels`; the later steps' counts at 0), in the points' order.

    One pass of the native kernel (:func:`~phigenesis.data.native.load_camera_points`) over the
    points, where the numpy path (:func:`camera_pixels_reference`) makes a dozen over millions
    of map points (figures: BENCHMARKS.md, "Prep at real size"). The same arithmetic in the
    same precision, except the float32 rotation's last bit (BLAS may sum in another order): a
    point on a pixel's border or on a limit may fall the other way."""
    kernel = load_camera_points()
    world = points.points_world
    if kernel is None or len(world) == 0:
        return camera_pixels_reference(camera, points, params, ego_depth, occluder_far)
    cal = camera.calibration
    distortion = np.zeros(5) if cal.distortion is None else np.asarray(cal.distortion, np.float64)
    radius = geometry.max_monotonic_radius(distortion) if np.any(distortion != 0.0) else np.inf
    maps = [
        None if m is None else np.ascontiguousarray(m, np.float32).reshape(cal.height, cal.width)
        for m in (ego_depth, occluder_far)
    ]
    cap = _cap_of(params, cal.width)
    index, uv, z, pixel, (projected, ego, vehicles, thinned) = kernel(
        np.ascontiguousarray(world, np.float32),
        camera.world_from_camera,
        np.asarray(cal.intrinsics, np.float64),
        distortion,
        radius**2,
        (cal.width, cal.height),
        (params.min_depth_m, params.max_range_m),
        normalized_bounds(camera),
        maps[0],
        maps[1],
        params.slack_m,
        cap,
        (1 + params.tau, params.slack_m),
    )
    return index, uv, z, pixel, _projection_counts(projected, ego, vehicles, thinned)


def camera_pixels_reference(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
) -> CameraPixels:
    """The numpy :func:`camera_pixels` (its fallback where no C compiler is present, and the
    reference of the tests)."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    # float32 relative to the camera centre: millions of map points, and world coordinates of a
    # scene (up to a few km) keep ~0.1 mm precision once the centre is subtracted.
    centre = camera.world_from_camera[:3, 3]
    rotation = camera.world_from_camera[:3, :3].astype(np.float32)
    p_cam = (np.asarray(points.points_world, np.float32) - centre.astype(np.float32)) @ rotation
    z_all = p_cam[:, 2]
    near = (z_all > params.min_depth_m) & (np.einsum("ij,ij->i", p_cam, p_cam) <= params.max_range_m**2)
    # A cheap test on the undistorted view directions before the exact projection.
    (x0, x1), (y0, y1) = normalized_bounds(camera)
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = p_cam[:, 0] / z_all, p_cam[:, 1] / z_all
    near &= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    p_cam = p_cam[near]
    uv, valid = geometry.project_points(p_cam, cal.intrinsics, cal.distortion, params.min_depth_m)
    valid &= geometry.in_image(uv, w, h)
    idx = np.flatnonzero(near)[valid]
    z = p_cam[valid, 2].astype(np.float32)
    uv = uv[valid]
    pixel = _pixel_index(uv, 1, w, h)
    counts = _projection_counts(len(z), 0, 0, 0)
    for name, limit, slack in (
        ("behind_ego_body", ego_depth, 0.0),
        ("behind_vehicles", occluder_far, params.slack_m),
    ):
        if limit is not None:
            front = z < limit.reshape(-1)[pixel] + slack
            counts[name] = int(np.sum(~front))
            pixel, z, idx, uv = pixel[front], z[front], idx[front], uv[front]
    cap = _cap_of(params, w)
    if cap > 0 and len(z):
        keep = thin_in_pixels(idx, z, pixel, h * w, cap, params)
        counts["thinned_in_pixels"] = int(np.sum(~keep))
        pixel, z, idx, uv = pixel[keep], z[keep], idx[keep], uv[keep]
    return idx, uv, z, pixel, counts


def project_camera(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
    sweep_step_rad: float = float(np.radians(0.5)),
) -> tuple[CameraDepth, dict[str, int]]:
    """Projects world points into one image with occlusion handling.

    Args:
        camera: the image (its calibration, capture time pose).
        points: world points with their origins and footprints.
        ego_depth: (H, W) depth where each pixel's ray enters the ego body (inf: misses); pixels
            on the body get no depth, points behind it are dropped.
        occluder_far: (H, W) depth beyond which nothing is visible (moving vehicles' far sides).
        sweep_step_rad: angular footprint of points measured by a single sweep (NaN spacing).

    Returns the image's :class:`CameraDepth` (sparse only) and counts: ``projected`` (points in
    the image), ``removed_by_visibility``, ``behind_ego_body`` and ``behind_vehicles``.
    """
    cal = camera.calibration
    h, w = cal.height, cal.width
    idx, uv, z, pixel, counts = camera_pixels(camera, points, params, ego_depth, occluder_far)
    origin = points.origin[idx]
    # Visibility and the z-buffer work on a grid `s` times finer than the image, so a point
    # occludes (and fills) only the part of a pixel it covers; each pixel then takes the visible
    # point nearest its centre, not the nearest in depth, so edge pixels keep the surface at
    # their centre.
    ss = supersample_of(params, w)
    hf, wf = h * ss, w * ss
    fine = _pixel_index(uv, ss, wf, hf)
    keep = np.ones(len(z), bool)
    if params.visibility == "splat" and len(z):
        focal = float(cal.intrinsics[0, 0]) * ss
        spacing = points.spacing_m[idx]
        footprint = np.where(np.isnan(spacing), z * sweep_step_rad, spacing)
        radius = np.rint(params.splat_scale * focal * footprint / z)
        radius = np.clip(radius, 0, params.max_splat_px * ss).astype(np.int64)
        occ = occluder_depth(fine, z, radius, (hf, wf)).reshape(-1)
        keep = z <= occ[fine] * (1 + params.tau) + params.slack_m
    elif params.visibility == "local_min" and len(z):
        buf = _zbuffer(pixel, z, h * w).reshape(h, w)
        kernel = np.ones((params.window, params.window), np.uint8)
        local = cv2.erode(buf, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf).reshape(-1)
        keep = z <= local[pixel] * (1 + params.tau)
    counts["removed_by_visibility"] = int(np.sum(~keep))
    pixel, fine, z, origin = pixel[keep], fine[keep], z[keep], origin[keep]
    fine_depth = _zbuffer(fine, z, hf * wf)
    fine_origin = np.zeros(hf * wf, np.uint8)
    nearest = np.flatnonzero(z == fine_depth[fine])
    fine_origin[fine[nearest]] = origin[nearest]
    # Every per-pixel value below is computed on the pixels that take a point (``known``, about
    # 1 % of a full-size image), then scattered into the (H, W) maps.
    if ss == 1:
        known = np.flatnonzero(np.isfinite(fine_depth))  # _centre_first on a 1 x 1 grid
        chosen = known
    else:
        chosen = _centre_first(fine_depth.reshape(h, ss, w, ss), params.max_offset_px).reshape(-1)
        known = np.flatnonzero(chosen >= 0)
        chosen = chosen[known]
    sparse_k = fine_depth[chosen]
    origin_k = fine_origin[chosen]
    if params.estimator == "plane":
        sparse = np.full(h * w, np.inf, np.float32)
        sparse[known] = sparse_k
        fit = fit_pixels(pixel, uv[keep], z, (h, w), sparse, params)
        fit_depth, fit_count, mixed = fit.depth_m[known], fit.count[known], fit.mixed[known]
        plane = np.isfinite(fit_depth) & ~mixed
        sparse_k = np.where(plane, fit_depth, sparse_k)
        support = np.where(plane, 2, np.minimum(fit_count, 1))
    else:
        # Support: points in the pixel agreeing with its depth within tau.
        sparse = np.full(h * w, np.inf, np.float32)
        sparse[known] = sparse_k
        agree = np.abs(z - sparse[pixel]) <= sparse[pixel] * params.tau
        support = np.bincount(pixel[agree], minlength=h * w)[known]
        mixed = np.zeros(len(known), bool)
    confidence_k = ORIGIN_WEIGHTS[origin_k] * np.where(support >= 2, 1.0, 0.75)
    confidence_k = np.where(mixed, 0.5 * confidence_k, confidence_k)
    counts["mixed_pixels"] = int(mixed.sum())
    if params.mixed_pixels == "drop":
        kept = ~mixed
        known, sparse_k, confidence_k, origin_k = (
            known[kept],
            sparse_k[kept],
            confidence_k[kept],
            origin_k[kept],
        )
    depth = np.zeros(h * w, np.float32)
    depth[known] = sparse_k
    confidence = np.zeros(h * w, np.float32)
    confidence[known] = confidence_k
    origin_map = np.zeros(h * w, np.uint8)
    origin_map[known] = origin_k
    edge = depth_edge_band(
        depth.reshape(h, w),
        params.edge_band_px,
        params.edge_tolerance_rel,
        params.edge_tolerance_m,
        params.edge_min_share,
        params.edge_near_band_px,
    ).reshape(-1)
    if params.image_edge_threshold is not None and camera.image_bytes is not None:
        edge |= silhouette_pixels(
            camera.decode_image(), depth.reshape(h, w), params.image_edge_threshold
        ).reshape(-1)
    counts["edge_pixels"] = int(edge.sum())
    confidence[edge] *= params.edge_confidence
    if ego_depth is not None:
        body = np.isfinite(ego_depth.reshape(-1))
        depth[body], confidence[body], origin_map[body] = 0.0, 0.0, 0
    return (
        CameraDepth(depth.reshape(h, w), confidence.reshape(h, w), origin_map.reshape(h, w)),
        counts,
    )


def project_camera_reference(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
    sweep_step_rad: float = float(np.radians(0.5)),
) -> tuple[CameraDepth, dict[str, int]]:
    """The reference :func:`project_camera`: the same steps with the plain reference functions
    (:func:`occluder_depth_reference`, :func:`fit_pixels_reference`,
    :func:`depth_edge_band_reference`, :func:`silhouette_pixels_reference`) and every per-pixel
    value computed over the whole image. Kept for the tests."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    idx, uv, z, pixel, counts = camera_pixels_reference(camera, points, params, ego_depth, occluder_far)
    origin = points.origin[idx]
    # Visibility and the z-buffer work on a grid `s` times finer than the image, so a point
    # occludes (and fills) only the part of a pixel it covers; each pixel then takes the visible
    # point nearest its centre, not the nearest in depth, so edge pixels keep the surface at
    # their centre.
    ss = supersample_of(params, w)
    hf, wf = h * ss, w * ss
    fine = _pixel_index(uv, ss, wf, hf)
    keep = np.ones(len(z), bool)
    if params.visibility == "splat" and len(z):
        focal = float(cal.intrinsics[0, 0]) * ss
        spacing = points.spacing_m[idx]
        footprint = np.where(np.isnan(spacing), z * sweep_step_rad, spacing)
        radius = np.rint(params.splat_scale * focal * footprint / z)
        radius = np.clip(radius, 0, params.max_splat_px * ss).astype(np.int64)
        occ = occluder_depth_reference(fine, z, radius, (hf, wf)).reshape(-1)
        keep = z <= occ[fine] * (1 + params.tau) + params.slack_m
    elif params.visibility == "local_min" and len(z):
        buf = _zbuffer(pixel, z, h * w).reshape(h, w)
        kernel = np.ones((params.window, params.window), np.uint8)
        local = cv2.erode(buf, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf).reshape(-1)
        keep = z <= local[pixel] * (1 + params.tau)
    counts["removed_by_visibility"] = int(np.sum(~keep))
    pixel, fine, z, origin = pixel[keep], fine[keep], z[keep], origin[keep]
    fine_depth = _zbuffer(fine, z, hf * wf)
    fine_origin = np.zeros(hf * wf, np.uint8)
    nearest = np.flatnonzero(z == fine_depth[fine])
    fine_origin[fine[nearest]] = origin[nearest]
    chosen = _centre_first(fine_depth.reshape(h, ss, w, ss), params.max_offset_px).reshape(-1)
    hit = chosen >= 0
    sparse = np.where(hit, fine_depth[np.maximum(chosen, 0)], np.inf)
    origin_map = np.where(hit, fine_origin[np.maximum(chosen, 0)], 0).astype(np.uint8)
    if params.estimator == "plane":
        fit = fit_pixels_reference(pixel, uv[keep], z, (h, w), sparse, params)
        plane = np.isfinite(fit.depth_m) & hit & ~fit.mixed
        sparse = np.where(plane, fit.depth_m, sparse)
        support = np.where(plane, 2, np.minimum(fit.count, 1))
        mixed = fit.mixed & hit
    else:
        # Support: points in the pixel agreeing with its depth within tau.
        agree = np.abs(z - sparse[pixel]) <= sparse[pixel] * params.tau
        support = np.bincount(pixel[agree], minlength=h * w)
        mixed = np.zeros(h * w, bool)
    confidence = ORIGIN_WEIGHTS[origin_map] * np.where(support >= 2, 1.0, 0.75)
    confidence = np.where(mixed, 0.5 * confidence, confidence)
    if params.mixed_pixels == "drop":
        hit &= ~mixed
    counts["mixed_pixels"] = int(mixed.sum())
    confidence = np.where(hit, confidence, 0.0).astype(np.float32)
    origin_map = np.where(hit, origin_map, 0).astype(np.uint8)
    depth = np.where(hit, sparse, 0.0).astype(np.float32)
    edge = depth_edge_band_reference(
        depth.reshape(h, w),
        params.edge_band_px,
        params.edge_tolerance_rel,
        params.edge_tolerance_m,
        params.edge_min_share,
        params.edge_near_band_px,
    ).reshape(-1)
    if params.image_edge_threshold is not None and camera.image_bytes is not None:
        edge |= silhouette_pixels_reference(
            camera.decode_image(), depth.reshape(h, w), params.image_edge_threshold
        ).reshape(-1)
    counts["edge_pixels"] = int(edge.sum())
    confidence[edge] *= params.edge_confidence
    if ego_depth is not None:
        body = np.isfinite(ego_depth.reshape(-1))
        depth[body], confidence[body], origin_map[body] = 0.0, 0.0, 0
    return (
        CameraDepth(depth.reshape(h, w), confidence.reshape(h, w), origin_map.reshape(h, w)),
        counts,
    )
