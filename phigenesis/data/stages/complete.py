"""Geometric depth completion where the LiDAR cannot reach (the ``complete_depth`` stage).

Entry point: :func:`complete_depth_map` (one image, plain arrays). The stage ``complete_depth``
runs it on every camera that has a dense depth and an image, and extends that camera's
``dense_m`` / ``dense_confidence`` / ``dense_origin`` (:class:`~phigenesis.data.records.CameraDepth`).

The densifier leaves empty what no LiDAR point is near: upper facades above the top beam, pole
tops, tree crowns, ground between far scan lines. The paper fills them with a diffusion
inpainting model; this stage fills only what the scene's own geometry explains, image segment
by image segment. Conventions are the densifier's (``densify.py``): z-depth in metres, 0 =
unknown, ``*_ref_px`` lengths are pixels at ``REFERENCE_FOCAL_PX`` scaled to the camera.

1. **Segments** come from the image itself (:func:`segment_image`): OpenCV's graph segmentation
   (Felzenszwalb-Huttenlocher) of the blurred image, then adjacent segments of nearly the same
   mean colour across a faint boundary are merged (the graph criterion stops merging large
   uniform regions, which cut one facade into pieces, most without any depth). Pixels labelled
   sky (``pseudo_semantics``) and ``keep_out`` pixels (the ego body) are never filled; a segment
   more than ``max_sky_share`` sky has leaked into the sky and is left alone, and so is one whose
   majority label is in :data:`NEVER_FILLED_CLASSES` (people, bicycles: no plane describes them).
2. **Planes** (origin ``plane``): a segment's known pixels are back-projected with the camera's
   rays. A vertical plane is fitted by RANSAC (two-point hypotheses that contain the up
   direction), refined by least squares with its normal kept horizontal; where none passes, a
   near-horizontal one (``ground_planes``). A plane passes with ``min_inliers`` inliers (within
   ``inlier_tol_m + inlier_tol_rel * z``), an RMS residual of at most ``max_residual_rel`` of
   their depth, a free 3D fit of them tilted less than ``max_tilt_deg`` (a slanted roof or
   windscreen fails) and, if vertical, ``min_height_m`` of vertical extent, or
   ``min_height_rel`` of their depth if less (a row of ground points fails; the side of a bus two
   metres away, seen over a few decimetres between two beams, passes). A segment whose plane
   explains less than ``min_inlier_share`` of its known pixels gets a second plane from the rest
   (a corner of a building; a bus in front of a facade of the same grey); with two, each must
   explain ``min_plane_share``. A segment with fewer than ``min_inliers`` dense pixels is fitted
   to its sparse (LiDAR) depth instead, if that covers ``sparse_min_share`` of it
   (``sparse_planes``: the densifier leaves out the scan lines on a far lawn).
   **Lines** (``line_planes``): a segment whose known pixels lie along one line (a single scan
   line across a lawn or up a wall's foot) fixes no plane by itself, only the planes through
   that line; its pseudo-semantic label says which: a segment labelled ground
   (:data:`~phigenesis.taxonomy.GROUND_IDS`) takes the plane through the line that is closest
   to level (two-point hypotheses with the line's horizontal normal, least squares along the
   inliers' main axis; the line within ``max_tilt_deg`` of level and ``min_line_m`` long; the
   same for a strip of a few scan lines too narrow across to fix its tilt, whose free fit tilts
   beyond ``max_tilt_deg``: a pavement's edge 4 cm off over 20 cm of depth tilts it 11 deg), one
   labelled a standing structure (:data:`STANDING_CLASSES`) the vertical plane through it without
   the ``min_height_m`` test (a scan line on a facade has no height; a row of ground points
   labelled building would be a vertical plane at the ground, which the label rules out). Where
   the labels say neither, a line at the ground's height (within ``inlier_tol_m`` + twice
   ``inlier_tol_rel`` of its depth of the median distance below the camera of the image's own
   ground planes) lies; height alone never makes a line stand (a car's flank, a kerb's top). Their
   pixels' confidence is multiplied by ``line_confidence``.
3. **Filling**: an empty pixel of the segment takes the plane of the segment's known pixel
   nearest to it (none if that pixel is an outlier), within ``max_extrapolation_ref_px``; where
   the two planes of a segment do not meet along their seam (one stands in front of the other),
   only within ``split_extrapolation_ref_px``, except, where both planes are vertical
   (``climb_columns``: two facades of one colour), above each column's topmost inlier, which
   takes that inlier's plane however far (a facade's upper part stands above its lower part; the
   climb runs through the segment and the holes it encloses, and stops at anything else). The
   depth is where the pixel's ray meets the plane,
   kept if in ``(min_depth_m, max_depth_m]`` and if the ray meets the plane at
   ``min_incidence_deg`` or more: at grazing incidence a small tilt moves the depth by metres.
4. **Holes** of a plane's region (windows in a facade; origin ``plane``): the parts of its
   bounding box that the region encloses, and those cut by the image border that look like the
   enclosed ones, take the region's plane unless their own known pixels lie off it.
5. **Ground beyond the data**: a segment without depth entirely below the horizon takes the
   ground plane of the neighbour it shares ``min_boundary_ref_px`` of boundary with and
   resembles (mean colours within ``propagate_color_tol``).
6. **Thin vertical structures** (poles, trunks, sign posts; origin ``vertical``): a segment at
   most ``max_thin_width_ref_px`` wide on average and ``min_thin_aspect`` times taller, whose
   depths (dense, and sparse where the densifier dropped the edge pixels a thin pole is made of)
   agree and rise ``min_height_m`` vertically, with ``min_thin_trusted`` trusted pixels among
   them, is filled in the columns of that evidence with the vertical plane facing the camera
   through its base (the median depth of its lowest ``base_band_ref_px`` rows of evidence). A thin
   segment this does not fill (a strip of wall between two columns of windows, too little of it
   seen to show a pole's rise) is fitted and filled as any other segment (``thin_planes``).
6b. **Tree crowns** (``crowns``; origin ``vertical``): a green segment (excess green above
   ``upward_max_green``, or a majority label of vegetation) that no plane explains and whose
   dense depths lie within ``crown_max_spread`` of their median (interquartile range) takes the
   vertical plane facing the camera through the median of its known points, within
   ``max_extrapolation_ref_px`` of them, at ``crown_confidence`` at most: off by up to the
   crown's radius at its rim, a target to weigh low rather than none; pixels of excess blue above
   ``upward_max_blue`` and their neighbours are left out (where a crown blends into the sky, the
   blended pixels are sky). ``canopies``: a crown is
   many small green segments, most above the LiDAR's top beam; every connected region of the
   above-horizon pixels of green segments that hold no things (the sky's rim left out) is filled
   the same way, as one crown, from the depths its lower part holds, if at least
   ``canopy_min_known_share`` of its pixels hold one (a few known pixels in a large green region
   are as often a facade's that a segment took in, or depth seen through the leaves).
6c. **Vehicles** (``vehicle_max_spread``; origin ``vertical``): a segment labelled a vehicle
   (:data:`VEHICLE_CLASSES`) that no plane explains (a rounded body, a windscreen), whose known
   depths lie within ``vehicle_max_spread`` of their median, takes the camera-facing plane
   through them as a crown does: the back or the side of a car that faces the camera.
6d. **Walls above their data** (``wall_columns``; origin ``vertical``): in a segment with
   ``min_inliers`` pixels of dense depth (thin or not; any but ground, vegetation or vehicles by
   their majority label), each column's pixels
   above its topmost known pixel (not a thing's) and above the horizon take the vertical plane
   facing the camera through that pixel's point: a vertical surface holds one horizontal
   distance up a column of a level camera, whatever way it faces. A column climbs if its known
   pixels ``wall_min_height_m`` lower lie at that same horizontal distance (a rounded body is
   upright only at its widest), or, if they span less height, if most of the segment's checked
   columns do. It reaches the upper part of a facade no plane explains (the segment mixes two
   surfaces, or curves) or that lies beyond a plane's reach, at ``wall_confidence`` at most;
   pixels labelled things or of excess blue above ``upward_max_blue`` stay empty. After step 7,
   each climbed column goes on up through the segments above that step 7 could have climbed into
   (the LiDAR did not see them; no things; neither green nor blue) until the sky or anything
   else, at ``upward_confidence`` times the confidence it climbed with. Only with sky labels, as
   step 7.
7. **Facades above the data** (``propagate_up``; origin ``plane``): the upper part of a facade,
   above the LiDAR's top beam, is often a segment of its own (cut off by a ledge, a row of
   windows) without depth. A segment the LiDAR did not see (fewer than ``min_inliers`` pixels of
   dense or sparse depth), with at most ``upward_max_thing_share`` of its pixels labelled things
   (vehicles end at their box; nor does a plane climb from such a segment), not green (excess
   green ``2 g - r - b`` at most ``upward_max_green``: a crown above a roof) and not blue (excess
   blue ``2 b - r - g`` at most ``upward_max_blue``: sky the sky labels missed), takes the
   vertical plane whose region (its segment's inliers and completed pixels) runs along its lower
   boundary for ``upward_min_boundary_ref_px`` and ``upward_boundary_share`` of that whole
   boundary (a segment touching a facade's top at a corner is more often another building behind
   it than the facade's upper part); or the one whose region holds nine tenths of its whole boundary
   (windows between two such segments). Then it is part of that region, so a facade climbs
   through ``upward_steps`` segments at most. Only with sky labels (nothing else tells the sky
   above a roofline from a wall), and only from planes of dense depth (sparse depth leaks into
   the sky at silhouettes). Ground planes never climb. A climbed segment's pixels of excess blue above
   ``upward_max_blue`` stay empty (a roofline's segment takes in some sky).

Everything else stays empty (0): crowns the LiDAR saw nothing of, vehicles' curved parts, what no
LiDAR point anchors (buildings beyond the LiDAR's range or hidden behind others, unless a facade below them
is known), the sky.

Confidence of a completed pixel, never above that of the data it extends::

    conf = min(cap, c_data) * factor * share * exp(-(rms / (z * rel0))^2) * exp(-d / d0)
           * min(1, sin(incidence) / sin(30 deg))

``c_data`` the mean confidence of the plane's inliers, ``share`` the share of the segment's
known pixels its plane(s) explain, ``rms`` / ``z`` their RMS residual and mean depth,
``rel0`` = ``conf_relative_residual``, ``d`` the distance in pixels to the nearest known pixel
(rows above the evidence for thin structures), ``d0`` = ``conf_distance_ref_px``; ``cap`` is
``max_confidence`` (``vertical_confidence`` for thin structures), ``factor`` 1 for a segment's
own pixels, ``hole_confidence`` for holes and ``propagate_confidence`` for ground beyond the data,
times ``sparse_plane_confidence`` for planes of sparse depth; a facade's climb multiplies its
factor by ``upward_confidence`` per segment climbed, ``d`` then being the rows up from the
boundary it climbed over plus that boundary's own distance to the data.

Error: on an exact plane the completion is exact (the ray-plane intersection of the fitted plane;
``tests/test_complete_depth.py``). With measurement noise ``sigma`` on known pixels spanning
``h`` metres, a pixel ``H`` metres beyond them is off by about ``sigma * H / h`` along the
normal. Measured on synthetic scenes: BENCHMARKS.md, section ``completion``
(``benchmarks/completion.py``).

Large images (longer side over ``max_side_px``) are completed on a coarser grid of their own
pixels, and every empty pixel then takes its grid cell's plane, intersected with its own ray.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from phigenesis import taxonomy as tx
from phigenesis.data.records import CameraImage, Frame, LazyFrames, Scene
from phigenesis.data.stages import register_stage
from phigenesis.data.stages.aggregate import ego_boxes_of
from phigenesis.data.stages.completion.depth_map import complete_depth_map
from phigenesis.data.stages.completion.params import (  # noqa: F401  (re-exported: the stage's names)
    F32,
    F64,
    KIND_GROUND,
    KIND_NONE,
    KIND_VERTICAL,
    MAX_COLOR_DISTANCE,
    MAX_EXCESS,
    MAX_POINTS,
    MAX_REF_PX,
    MAX_REF_PX2,
    NEVER_FILLED_CLASSES,
    ORIGIN,
    STANDING_CLASSES,
    VEHICLE_CLASSES,
    CompletionParams,
    CompletionResult,
    Mask,
)
from phigenesis.data.stages.completion.planes import PlaneFits, fit_planes  # noqa: F401
from phigenesis.data.stages.completion.segments import merge_similar_segments, segment_image  # noqa: F401
from phigenesis.data.stages.densify import camera_focal_px
from phigenesis.data.stages.project import ego_body_depth, pixel_rays

log = logging.getLogger("phigenesis.prep")


@dataclass
class _CameraTables:
    """Per-calibration tables: pixel rays (z = 1, (H * W, 3)) and the ego body mask (H, W)."""

    rays: F64
    ego: Mask


def _has_evidence(dense_m: F32, sparse_m: F32 | None, sparse_confidence: F32 | None) -> bool:
    """Whether a camera's (H, W) depth maps hold anything a completion could extend: a dense pixel
    of positive depth, or a sparse one of positive confidence (the evidence of sparse planes and
    thin structures). Without either :func:`complete_depth_map` returns an all-0 map."""
    if np.any(dense_m > 0):
        return True
    return (
        sparse_m is not None
        and sparse_confidence is not None
        and bool(np.any((sparse_m > 0) & (sparse_confidence > 0)))
    )


@register_stage("complete_depth", params=CompletionParams)
def complete_depth(scene: Scene, p: CompletionParams) -> Scene:
    """Stage: extends every camera's dense depth where planes and thin vertical structures of its
    image explain it (module docstring); params: the fields of :class:`CompletionParams`.

    Runs after ``densify_depth`` (it extends ``dense_m``, and uses the sparse depth as evidence of
    thin structures) and after ``pseudo_semantics``: it never fills what that labels sky and skips
    segments labelled people or bicycles. Without pseudo labels it warns once per scene and
    relies on the image segments alone. The ego body (the scene's ``ego_boxes``) is never filled.
    Cameras without a dense depth or an image are left alone; frames are processed lazily when
    the scene's frames are a :class:`LazyFrames`.
    """
    ego_boxes = ego_boxes_of(scene)
    tables: dict[tuple, _CameraTables] = {}
    warned = False

    def camera_tables(cam: CameraImage) -> _CameraTables:
        key = cam.calibration.key()
        if key not in tables:
            tables[key] = _CameraTables(pixel_rays(cam), np.isfinite(ego_body_depth(cam, ego_boxes)))
        return tables[key]

    def complete_camera(cam: CameraImage) -> CameraImage:
        nonlocal warned
        depth = cam.depth
        if depth is None or depth.dense_m is None or cam.image_bytes is None:
            return cam
        if not _has_evidence(depth.dense_m, depth.sparse_m, depth.sparse_confidence):
            # Nothing to extend (a frame without LiDAR): the map stays empty, as the completion
            # would leave it, without segmenting the image.
            if depth.dense_confidence is None or not depth.dense_confidence.any():
                return cam
            zeros = np.zeros(depth.dense_m.shape, np.float32)
            empty = dataclasses.replace(depth, dense_confidence=zeros, dense_origin=zeros.astype(np.uint8))
            return dataclasses.replace(cam, depth=empty)
        sky = classes = None
        if cam.pseudo is not None:
            sky = cam.pseudo.semantic == tx.SKY
            classes = cam.pseudo.semantic
        elif not warned:
            log.warning(
                "complete_depth: scene %s camera %s has no pseudo-semantic labels (run pseudo_semantics "
                "before complete_depth); completing without sky labels",
                scene.scene_id,
                cam.name,
            )
            warned = True
        t = camera_tables(cam)
        try:
            result = complete_depth_map(
                depth.dense_m,
                depth.dense_confidence,
                cam.decode_image(),
                rays_cam=t.rays,
                up_cam=cam.world_from_camera[:3, :3].T @ np.array([0.0, 0.0, 1.0]),
                focal_px=camera_focal_px(cam),
                origin=depth.dense_origin,
                sparse_m=depth.sparse_m,
                sparse_confidence=depth.sparse_confidence,
                sky=sky,
                classes=classes,
                keep_out=t.ego,
                params=p,
            )
        except ValueError as e:
            raise ValueError(
                f"complete_depth: scene {scene.scene_id} camera {cam.name} at {cam.timestamp_micros}: {e}"
            ) from None
        completed = dataclasses.replace(
            depth, dense_m=result.depth_m, dense_confidence=result.confidence, dense_origin=result.origin
        )
        return dataclasses.replace(cam, depth=completed)

    def complete_frame(frame: Frame) -> Frame:
        return dataclasses.replace(frame, cameras=[complete_camera(c) for c in frame.cameras])

    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(complete_frame)
    else:
        scene.frames = [complete_frame(f) for f in scene.frames]
    return scene
