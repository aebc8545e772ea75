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
   (:data:`~phigenesis.data.taxonomy.GROUND_IDS`) takes the plane through the line that is closest
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
import functools
import logging
import threading
import weakref
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data import taxonomy as tx
from phigenesis.data.native import load_complete_fine
from phigenesis.data.records import DENSE_ORIGINS, CameraImage, Frame, LazyFrames, Scene
from phigenesis.data.stages import register_stage
from phigenesis.data.stages.aggregate import ego_boxes_of
from phigenesis.data.stages.densify import REFERENCE_FOCAL_PX, camera_focal_px, check_depth_maps, check_rgb
from phigenesis.data.stages.project import ego_body_depth, pixel_rays
from phigenesis.options import ConfigError, check_options, from_mapping, option

log = logging.getLogger("phigenesis.prep")

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]

ORIGIN = {name: i for i, name in enumerate(DENSE_ORIGINS)}
#: Classes (of ``classes``, e.g. pseudo labels) whose segments are never completed: no plane
#: describes them.
NEVER_FILLED_CLASSES = frozenset({tx.SKY, tx.PERSON, tx.RIDER, tx.BICYCLE, tx.MOTORCYCLE})
_SIN_GOOD_INCIDENCE = float(np.sin(np.radians(30.0)))
KIND_NONE, KIND_VERTICAL, KIND_GROUND = 0, 1, 2
#: The RANSAC and refinement mode of a ground plane through a line of points (its fits are
#: ``KIND_GROUND``).
_MODE_GROUND_LINE = 3
#: Labels of structures that stand (their planes are vertical); see ``line_planes``.
STANDING_CLASSES = frozenset({tx.BUILDING, tx.WALL, tx.FENCE})
#: Bounds of the parameters (:class:`CompletionParams`): lengths in reference pixels, areas in
#: reference pixels squared, and counts of points (a 10^5-pixel image side at most, as every stage).
MAX_REF_PX = 1e5
MAX_REF_PX2 = 1e10
MAX_POINTS = 10**8
#: The largest distance between two 0-255 RGB colours (255 sqrt 3, rounded up), and the largest
#: excess green or blue (2 g - r - b).
MAX_COLOR_DISTANCE = 442.0
MAX_EXCESS = 510.0
#: Vehicles: a segment of one no plane explains, of one depth (``vehicle_max_spread``), is the side
#: or back that faces the camera.
VEHICLE_CLASSES = frozenset({tx.CAR, tx.TRUCK, tx.BUS, tx.TRAIN})


@dataclass(frozen=True)
class CompletionParams:
    """Parameters of :func:`complete_depth_map` and of the ``complete_depth`` stage.

    Lengths named ``*_ref_px`` are pixels at ``densify.REFERENCE_FOCAL_PX`` (scaled by
    ``focal_px / REFERENCE_FOCAL_PX``); ``*_ref_px2`` areas scale with its square. Colours are
    0-255 RGB, distances between them Euclidean.

    Attributes:
        segment_sigma_ref_px: Gaussian blur of the image before segmentation.
        segment_k_ref_px2: graph segmentation's scale ``k`` (larger: larger segments).
        segment_min_size_ref_px2: graph segmentation's minimum segment size.
        merge_color_tol: adjacent segments whose mean colours differ by less are merged (0: no
            merging) ...
        merge_edge_tol: ... if the colour difference across their boundary averages less.
        max_sky_share: a segment with more sky pixels than this share is not completed.
        min_inliers: least inliers of a plane.
        min_inlier_share: least share of a segment's known pixels its plane(s) explain.
        min_plane_share: least share of a segment's known pixels each of its two planes explains.
        inlier_tol_m, inlier_tol_rel: a point is an inlier within ``tol_m + tol_rel * z`` metres.
        max_residual_rel: largest RMS residual of the inliers, relative to their mean depth.
        min_height_m: least vertical extent of a vertical plane's inliers (and of a thin
            structure's evidence) ...
        min_height_rel: ... or, if less, this share of their mean depth (the side of a bus a
            metre or two away shows a few decimetres of it between the LiDAR's beams).
        max_tilt_deg: largest tilt from vertical of a free fit to a vertical plane's inliers, and
            of a ground plane's normal from up.
        ground_planes: also fit near-horizontal planes (roads, terrain).
        sparse_planes: a segment with fewer than ``min_inliers`` dense pixels is fitted to its
            sparse (LiDAR) depth if that has as many ...
        sparse_min_share: ... on at least this share of its pixels (a lawn's scan lines, not the
            few depths that leak across a silhouette).
        sparse_plane_confidence: confidence factor of such a segment's pixels.
        line_planes: segments labelled ground or standing whose known pixels form a line take
            the plane through it their label implies (module docstring, step 2).
        min_line_m: least length of such a line of ground points.
        line_confidence: confidence factor of those segments' pixels.
        crowns: fill green segments no plane explains at one depth (module docstring, 6b).
        crown_max_spread: largest interquartile range of such a segment's known depths, relative
            to their median.
        crown_confidence: cap of their pixels' confidence.
        thin_planes: a thin segment step 6 did not fill is fitted as any other (6).
        canopies: fill each connected green region above the horizon as one crown (6b) ...
        canopy_min_known_share: ... if this share of its pixels has depth.
        vehicle_max_spread: largest interquartile range of a vehicle segment's known depths,
            relative to their median, for the camera-facing plane (6c; 0: never).
        climb_columns: a segment's two vertical planes that do not meet climb their columns (3).
        wall_columns: each column of a seen segment climbs from its topmost known pixel (6d).
        wall_confidence: cap of the confidences of those pixels.
        wall_min_height_m: a column climbs if its known pixels this far below its topmost one
            lie at that one's horizontal distance (6d).
        ransac_iterations: hypotheses per fit.
        ransac_points: points of a segment each hypothesis is scored on.
        fit_points: known pixels per segment a fit uses (at random); all are scored at the end.
        min_incidence_deg: rays meeting the plane at a smaller angle are not filled.
        min_depth_m, max_depth_m: completed depths lie in ``(min_depth_m, max_depth_m]``.
        max_extrapolation_ref_px: pixels farther from the segment's nearest known pixel stay empty.
        split_extrapolation_ref_px: the same for segments with two planes that do not meet.
        hole_confidence: confidence factor of holes of a plane's region.
        propagate_ground: fill segments without depth below the horizon from a ground neighbour.
        min_boundary_ref_px: least boundary such a segment shares with that neighbour.
        propagate_color_tol: largest difference of their mean colours.
        propagate_confidence: confidence factor of such pixels.
        propagate_up: fill segments without depth above a vertical plane's region from that plane.
        upward_steps: how many segments such a plane may climb, one above the other.
        upward_boundary_share: least share of such a segment's lower boundary (with segments
            other than the sky) along the top of that plane's region ...
        upward_min_boundary_ref_px: ... and least length of it.
        upward_max_green: a segment whose mean colour has a larger excess green (``2 g - r - b``,
            a vegetation index) is not climbed into (a tree's crown above a roof) ...
        upward_max_blue: ... nor one with a larger excess blue (``2 b - r - g``): the sky above a
            roofline that the sky labels missed (the geometric ones cannot label the sky above a
            facade taller than the LiDAR's field).
        upward_confidence: confidence factor of such pixels, once per segment climbed.
        upward_max_thing_share: no plane climbs from, or into, a segment with a larger share of
            pixels labelled things (vehicles, people): a car's side in one segment with the facade
            behind it would carry the car's depth up the facade.
        max_thin_width_ref_px: widest mean width of a thin vertical segment.
        min_thin_aspect: least height / mean width of a thin vertical segment.
        min_thin_height_ref_px: least height of a thin vertical segment.
        min_thin_known: least pixels with a depth (dense or sparse) of a thin segment ...
        min_thin_evidence: ... and least share of its pixels (a sliver of sky between two
            facades holds a few of their silhouettes' sparse depths) ...
        min_thin_trusted: ... of which at least this many dense ones at the base's depth.
        base_band_ref_px: a thin segment's base: its evidence this close to the lowest.
        max_confidence: cap of plane confidences.
        vertical_confidence: cap of thin structures' confidences.
        conf_distance_ref_px: ``d0`` of the confidence (module docstring).
        conf_relative_residual: ``rel0`` of the confidence.
        max_side_px: images with a longer side are completed on a coarser grid with this one.
        seed: seed of the RANSAC sampling (results are deterministic).
    """

    segment_sigma_ref_px: float = option(1.5, ge=0, le=MAX_REF_PX)
    segment_k_ref_px2: float = option(2400.0, gt=0, le=MAX_REF_PX2)
    segment_min_size_ref_px2: float = option(160.0, gt=0, le=MAX_REF_PX2)
    merge_color_tol: float = option(12.0, ge=0, le=MAX_COLOR_DISTANCE)
    merge_edge_tol: float = option(8.0, ge=0, le=MAX_COLOR_DISTANCE)
    max_sky_share: float = option(0.05, ge=0, le=1)
    min_inliers: int = option(12, ge=3, le=MAX_POINTS)
    min_inlier_share: float = option(0.7, ge=0, le=1)
    min_plane_share: float = option(0.25, ge=0, le=1)
    inlier_tol_m: float = option(0.05, gt=0, le=100)
    inlier_tol_rel: float = option(0.01, ge=0, le=10)
    max_residual_rel: float = option(0.01, gt=0, le=10)
    min_height_m: float = option(0.3, ge=0, le=1000)
    min_height_rel: float = option(0.05, ge=0, le=100)
    max_tilt_deg: float = option(8.0, ge=0, lt=45)
    ground_planes: bool = option(True)
    sparse_planes: bool = option(True)
    sparse_min_share: float = option(0.5, ge=0, le=1)
    sparse_plane_confidence: float = option(0.7, ge=0, le=1)
    line_planes: bool = option(True)
    climb_columns: bool = option(True)
    wall_columns: bool = option(True)
    wall_confidence: float = option(0.2, ge=0, le=1)
    wall_min_height_m: float = option(1.0, gt=0, le=1000)
    min_line_m: float = option(1.0, gt=0, le=1000)
    crowns: bool = option(True)
    canopies: bool = option(True)
    thin_planes: bool = option(True)
    canopy_min_known_share: float = option(0.02, ge=0, le=1)
    vehicle_max_spread: float = option(0.05, ge=0, le=10)
    crown_max_spread: float = option(0.15, gt=0, le=10)
    crown_confidence: float = option(0.2, ge=0, le=1)
    line_confidence: float = option(0.5, ge=0, le=1)
    ransac_iterations: int = option(32, ge=1, le=100_000)
    ransac_points: int = option(64, ge=3, le=MAX_POINTS)
    fit_points: int = option(256, ge=3, le=MAX_POINTS)
    min_incidence_deg: float = option(2.0, ge=0, lt=90)
    min_depth_m: float = option(0.5, ge=0, le=1000)
    max_depth_m: float = option(150.0, gt=0, le=1000)
    max_extrapolation_ref_px: float = option(600.0, gt=0, le=MAX_REF_PX)
    split_extrapolation_ref_px: float = option(30.0, gt=0, le=MAX_REF_PX)
    hole_confidence: float = option(0.7, ge=0, le=1)
    propagate_ground: bool = option(True)
    min_boundary_ref_px: float = option(20.0, ge=0, le=MAX_REF_PX)
    propagate_color_tol: float = option(24.0, ge=0, le=MAX_COLOR_DISTANCE)
    propagate_confidence: float = option(0.5, ge=0, le=1)
    propagate_up: bool = option(True)
    upward_steps: int = option(6, ge=0, le=1000)
    upward_boundary_share: float = option(0.3, ge=0, le=1)
    upward_min_boundary_ref_px: float = option(3.0, ge=0, le=MAX_REF_PX)
    upward_confidence: float = option(0.6, ge=0, le=1)
    upward_max_green: float = option(20.0, ge=-MAX_EXCESS, le=MAX_EXCESS)
    upward_max_blue: float = option(40.0, ge=-MAX_EXCESS, le=MAX_EXCESS)
    upward_max_thing_share: float = option(0.02, ge=0, le=1)
    max_thin_width_ref_px: float = option(30.0, gt=0, le=MAX_REF_PX)
    min_thin_aspect: float = option(4.0, gt=0, le=1000)
    min_thin_height_ref_px: float = option(40.0, ge=0, le=MAX_REF_PX)
    min_thin_known: int = option(6, ge=1, le=MAX_POINTS)
    min_thin_evidence: float = option(0.25, ge=0, le=1)
    min_thin_trusted: int = option(1, ge=0, le=MAX_POINTS)
    base_band_ref_px: float = option(20.0, gt=0, le=MAX_REF_PX)
    max_confidence: float = option(0.45, ge=0, le=1)
    vertical_confidence: float = option(0.3, ge=0, le=1)
    conf_distance_ref_px: float = option(400.0, gt=0, le=MAX_REF_PX)
    conf_relative_residual: float = option(0.01, gt=0, le=10)
    max_side_px: int = option(640, ge=16, le=100_000)
    seed: int = option(0, ge=0, le=2**32 - 1)

    def __post_init__(self) -> None:
        check_options(self, "CompletionParams")
        if self.min_depth_m >= self.max_depth_m:
            raise ConfigError(
                f"CompletionParams: min_depth_m = {self.min_depth_m}: must be below max_depth_m "
                f"({self.max_depth_m})"
            )

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> CompletionParams:
        return from_mapping(cls, values, "complete_depth")


@dataclass
class CompletionResult:
    """A completed depth map, all (H, W).

    Attributes:
        depth_m: float32 z-depth in metres, 0 where unknown; the input's where it was known.
        confidence: float32 in [0, 1], 0 exactly where ``depth_m`` is 0; the input's where known.
        origin: uint8 :data:`~phigenesis.data.records.DENSE_ORIGINS` code, 0 exactly where
            ``depth_m`` is 0; the input's where known.
        segments: int32 image segment of each pixel (:func:`segment_image`).
    """

    depth_m: F32
    confidence: F32
    origin: NDArray[np.uint8]
    segments: NDArray[np.int32]


# --------------------------------------------------------------------------------------------
# Entry point


def complete_depth_map(
    depth_m: F32,
    confidence: F32,
    rgb: NDArray[np.uint8],
    *,
    rays_cam: F64,
    up_cam: F64,
    focal_px: float,
    origin: NDArray[np.uint8] | None = None,
    sparse_m: F32 | None = None,
    sparse_confidence: F32 | None = None,
    sky: Mask | None = None,
    classes: NDArray[np.uint8] | None = None,
    keep_out: Mask | None = None,
    params: CompletionParams | None = None,
) -> CompletionResult:
    """Completes one dense depth map from its image's segments and the depth they already hold.

    Args:
        depth_m: (H, W) float z-depth in metres (the densifier's), 0 = unknown; finite, >= 0.
        confidence: (H, W) float in [0, 1]; known pixels have ``depth_m > 0`` and
            ``confidence > 0``.
        rgb: (H, W, 3) uint8 RGB image of the same camera.
        rays_cam: (H, W, 3) or (H * W, 3) camera-frame ray (OpenCV axes) of every pixel centre
            with z = 1 and the distortion undone, so that the pixel at depth z is ``z * ray``
            (:func:`~phigenesis.data.stages.project.pixel_rays`).
        up_cam: (3,) the world's up direction in camera axes (any length but 0).
        focal_px: the camera's focal length in pixels (scales the ``*_ref_px`` parameters).
        origin: (H, W) uint8 :data:`~phigenesis.data.records.DENSE_ORIGINS` code of the input's
            known pixels (kept), or None: "densified".
        sparse_m, sparse_confidence: (H, W) the projected LiDAR depth and its confidence (both or
            neither): evidence for thin structures, which at low resolution are all depth edge
            and so mostly missing from the dense depth.
        sky: (H, W) bool, pixels that are sky: never filled.
        classes: (H, W) uint8 labels (unified taxonomy, 255 = none): segments whose majority label
            is in :data:`NEVER_FILLED_CLASSES` are not completed.
        keep_out: (H, W) bool, pixels never to fill (the ego body).
        params: :class:`CompletionParams` (None: the defaults).

    Returns:
        The completed depth, its confidence and origin codes (module docstring), and the image's
        segments. The inputs are not modified. Raises ValueError naming the argument for a wrong
        shape or dtype, NaN or infinite values, negative depths, confidences outside [0, 1], a
        zero up vector or rays without z = 1.

    Example::

        rays = pixel_rays(camera)                        # (H * W, 3)
        up = camera.world_from_camera[:3, :3].T @ [0, 0, 1]
        out = complete_depth_map(dense, conf, rgb, rays_cam=rays, up_cam=up, focal_px=f, sky=sky)
        planar = out.origin == DENSE_ORIGINS.index("plane")
    """
    p = CompletionParams() if params is None else params
    depth, conf = check_depth_maps(depth_m, confidence, ("depth_m", "confidence"))
    shape = depth.shape
    h, w = shape
    rgb = np.ascontiguousarray(check_rgb(rgb, shape, "depth_m"))
    ray_info = _ray_info(rays_cam)
    if ray_info is not None and ray_info.get("checked") == shape:
        rays = np.asarray(rays_cam).reshape(shape[0] * shape[1], 3)
    else:
        rays = _check_rays(rays_cam, shape)
        if ray_info is not None:
            ray_info["checked"] = shape
    up = _check_up(up_cam)
    focal_px = float(focal_px)
    if not np.isfinite(focal_px) or focal_px <= 0:
        raise ValueError(f"focal_px must be a positive finite number of pixels, got {focal_px}")
    origin_in = _check_labels("origin", origin, shape, len(DENSE_ORIGINS))
    if (sparse_m is None) != (sparse_confidence is None):
        raise ValueError("sparse_m and sparse_confidence come together (both or neither)")
    sparse = None
    if sparse_m is not None:
        sparse = check_depth_maps(sparse_m, sparse_confidence)
        if sparse[0].shape != shape:
            raise ValueError(f"sparse_m has shape {sparse[0].shape}, depth_m has {shape}")
    sky = _check_mask("sky", sky, shape)
    keep_out = _check_mask("keep_out", keep_out, shape)
    classes = _check_labels("classes", classes, shape, None)

    known = (depth > 0) & (conf > 0)
    out_depth = depth * known  # float32 copies, 0 where unknown
    out_conf = conf * known
    densified = np.uint8(ORIGIN["densified"])
    if origin_in is None:
        out_origin = known.astype(np.uint8) * densified
    else:
        out_origin = np.where(known, np.where(origin_in > 0, origin_in, densified), 0).astype(np.uint8)
    fillable = ~known
    for mask in (sky, keep_out):
        if mask is not None:
            fillable &= ~mask
    inputs = _Inputs(
        out_depth, out_conf, out_origin, known, fillable, rgb, rays, sky, classes, sparse, ray_info
    )
    scale = min(1.0, p.max_side_px / max(h, w))
    if scale < 1.0:
        segments = _complete_coarse(inputs, up, focal_px, p, scale)
    else:
        segments = segment_image(rgb, focal_px, p)
        if (known.any() or (p.sparse_planes and sparse is not None)) and fillable.any():
            _Completer(inputs, segments, up, focal_px, p).run()
    # Completed depths are finite and positive by construction; checked once more so that no NaN
    # or infinity can ever reach a cache (in place: NaN fails both comparisons).
    filled = (out_depth > 0) & (out_depth < np.inf)
    unfilled = ~filled
    np.copyto(out_depth, 0, where=unfilled)
    np.copyto(out_conf, 0, where=unfilled | ~(out_conf > 0))  # NaN and negatives too
    np.minimum(out_conf, np.float32(1), out=out_conf)
    np.copyto(out_origin, 0, where=unfilled)
    return CompletionResult(out_depth, out_conf, out_origin, segments)


@dataclass
class _Inputs:
    """The arrays of one completion, all (H, W) (``rays`` (H * W, 3)); ``depth``, ``conf`` and
    ``origin`` are the outputs, updated in place."""

    depth: F32
    conf: F32
    origin: NDArray[np.uint8]
    known: Mask
    fillable: Mask
    rgb: NDArray[np.uint8]
    rays: F64
    sky: Mask | None
    classes: NDArray[np.uint8] | None
    sparse: tuple[F32, F32] | None
    #: What is known of ``rays`` across calls (:func:`_ray_info`): its lengths, its coarse grids.
    ray_info: dict[Any, Any] | None = None


def _ray_info(rays_cam: Any) -> dict[Any, Any] | None:
    """A dict kept with a read-only rays array across calls (the per-calibration tables of
    :mod:`~phigenesis.data.camera_tables`, passed for every frame): that it passed the checks, its
    lengths, its coarse grids. None for a writeable array (it may change between calls). Entries
    go with their array (held by a weak reference)."""
    if not isinstance(rays_cam, np.ndarray) or rays_cam.flags.writeable:
        return None
    with _RAY_INFO_LOCK:
        entry = _RAY_INFO.get(id(rays_cam))
        if entry is not None and entry[0]() is rays_cam:
            return entry[1]
        for key in [k for k, (ref, _) in _RAY_INFO.items() if ref() is None]:
            del _RAY_INFO[key]
        info: dict[Any, Any] = {}
        _RAY_INFO[id(rays_cam)] = (weakref.ref(rays_cam), info)
        return info


_RAY_INFO: dict[int, tuple[weakref.ref, dict[Any, Any]]] = {}
_RAY_INFO_LOCK = threading.Lock()


def _complete_coarse(
    inputs: _Inputs, up: F64, focal_px: float, p: CompletionParams, scale: float, native: bool = True
) -> NDArray[np.int32]:
    """Completes a large image on a grid ``scale`` times as fine (outputs updated in place);
    returns the segments, upsampled.

    Each grid cell is one of the image's own pixels (depth, rays and masks sampled, the image
    area-averaged), so the planes are the scene's; every empty pixel of the image then takes its
    cell's plane, intersected with its own ray: depths stay exact on the planes, only the segment
    boundaries are as coarse as the grid. That fine pass runs in a C kernel
    (``csrc/complete_fine.c``) where it can be built and ``native``; the numpy path is its
    reference (bit-identical, tests/test_complete_depth.py).
    """
    h, w = inputs.depth.shape
    h2, w2 = max(1, round(h * scale)), max(1, round(w * scale))
    rows = np.minimum(((np.arange(h2) + 0.5) * h / h2).astype(np.intp), h - 1)
    cols = np.minimum(((np.arange(w2) + 0.5) * w / w2).astype(np.intp), w - 1)
    grid = np.ix_(rows, cols)

    def sample(a: Any) -> Any:
        return None if a is None else np.ascontiguousarray(a[grid])

    key = ("coarse", h2, w2)
    if inputs.ray_info is not None and key in inputs.ray_info:
        small_rays, small_norm = inputs.ray_info[key]
    else:
        small_rays = inputs.rays.reshape(h, w, 3)[grid].reshape(-1, 3)
        small_norm = np.linalg.norm(small_rays, axis=1)
        if inputs.ray_info is not None:
            small_rays.setflags(write=False)
            small_norm.setflags(write=False)
            inputs.ray_info[key] = (small_rays, small_norm)

    small = _Inputs(
        *(sample(inputs.depth), sample(inputs.conf), sample(inputs.origin)),
        *(sample(inputs.known), sample(inputs.fillable)),
        cv2.resize(inputs.rgb, (w2, h2), interpolation=cv2.INTER_AREA),
        small_rays,
        *(sample(inputs.sky), sample(inputs.classes)),
        None if inputs.sparse is None else (sample(inputs.sparse[0]), sample(inputs.sparse[1])),
    )
    focal_small = focal_px * w2 / w
    segments = segment_image(small.rgb, focal_small, p)
    ry = np.minimum((np.arange(h) * h2 / h).astype(np.intp), h2 - 1)
    rx = np.minimum((np.arange(w) * w2 / w).astype(np.intp), w2 - 1)
    if (small.known.any() or (p.sparse_planes and small.sparse is not None)) and small.fillable.any():
        completer = _Completer(small, segments, up, focal_small, p, small_norm)
        completer.run()
        kernel = load_complete_fine() if native else None
        if kernel is not None:
            kernel(
                ry.astype(np.int64),
                rx.astype(np.int64),
                np.ascontiguousarray(inputs.fillable),
                np.ascontiguousarray(inputs.rays),
                completer.plane_normal,
                completer.plane_offset,
                small.conf.reshape(-1),
                small.origin.reshape(-1),
                w2,
                ORIGIN["plane"],
                (p.min_depth_m, p.max_depth_m),
                float(np.sin(np.radians(p.min_incidence_deg))),
                inputs.depth,
                inputs.conf,
                inputs.origin,
            )
        else:
            done = (small.origin >= ORIGIN["plane"])[np.ix_(ry, rx)]  # (H, W) whether the cell completed
            done &= inputs.fillable
            target = np.flatnonzero(done)
            del done
            src = ry[target // w] * w2 + rx[target % w]  # the grid cell of every target pixel
            norm = None
            if inputs.ray_info is not None:
                if "norm" not in inputs.ray_info:
                    inputs.ray_info["norm"] = np.linalg.norm(inputs.rays, axis=1)  # (H * W,) float64
                norm = inputs.ray_info["norm"]
            z, ok = completer.intersect(
                inputs.rays[target],
                completer.plane_normal[src],
                completer.plane_offset[src],
                None if norm is None else norm[target],
            )
            target, src = target[ok], src[ok]
            inputs.depth.reshape(-1)[target] = z[ok]
            inputs.conf.reshape(-1)[target] = small.conf.reshape(-1)[src]
            inputs.origin.reshape(-1)[target] = small.origin.reshape(-1)[src]
    return segments[np.ix_(ry, rx)]


# --------------------------------------------------------------------------------------------
# Input checks


def _check_rays(rays_cam: Any, shape: tuple[int, int]) -> F64:
    arr = np.asarray(rays_cam, dtype=np.float64)
    h, w = shape
    if arr.shape == (h, w, 3):
        arr = arr.reshape(h * w, 3)
    if arr.shape != (h * w, 3):
        raise ValueError(f"rays_cam must have shape {(h, w, 3)} or {(h * w, 3)}, got {np.shape(rays_cam)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("rays_cam has NaN or infinite values")
    if np.any(np.abs(arr[:, 2] - 1.0) > 1e-6):
        raise ValueError("rays_cam must have z = 1 (the pixel at depth z is z * ray)")
    return arr


def _check_up(up_cam: Any) -> F64:
    up = np.asarray(up_cam, dtype=np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)):
        raise ValueError(f"up_cam must be 3 finite numbers, got {up_cam!r}")
    norm = float(np.linalg.norm(up))
    if norm < 1e-9:
        raise ValueError("up_cam must not be the zero vector")
    return up / norm


def _check_mask(name: str, mask: Any, shape: tuple[int, int]) -> Mask | None:
    if mask is None:
        return None
    arr = np.asarray(mask)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape} (as depth_m), got {arr.shape}")
    if arr.dtype != np.bool_:
        raise ValueError(f"{name} must be a bool mask, got dtype {arr.dtype}")
    return arr


def _check_labels(
    name: str, labels: Any, shape: tuple[int, int], count: int | None
) -> NDArray[np.uint8] | None:
    if labels is None:
        return None
    arr = np.asarray(labels)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape} (as depth_m), got {arr.shape}")
    if arr.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8, got dtype {arr.dtype}")
    if count is not None and arr.size and int(arr.max()) >= count:
        raise ValueError(f"{name} holds code {int(arr.max())}; codes are 0..{count - 1}")
    return arr


# --------------------------------------------------------------------------------------------
# Segmentation


@functools.lru_cache(maxsize=8)
def _graph_segmentation(k: float, min_size: int) -> Any:
    return cv2.ximgproc.segmentation.createGraphSegmentation(0.0, k, min_size)


def segment_image(rgb: NDArray[np.uint8], focal_px: float, params: CompletionParams) -> NDArray[np.int32]:
    """(H, W) int32 segment labels 0..S-1 of an (H, W, 3) uint8 image.

    Graph segmentation (``cv2.ximgproc``, Felzenszwalb-Huttenlocher) of the image blurred with a
    Gaussian of ``segment_sigma_ref_px``, scale ``segment_k_ref_px2`` and minimum size
    ``segment_min_size_ref_px2`` (focal-scaled), then :func:`merge_similar_segments`.
    """
    scale = focal_px / REFERENCE_FOCAL_PX
    sigma = params.segment_sigma_ref_px * scale
    image = cv2.GaussianBlur(rgb, (0, 0), sigma) if sigma >= 0.2 else rgb
    k = params.segment_k_ref_px2 * scale**2
    min_size = max(1, round(params.segment_min_size_ref_px2 * scale**2))
    labels = _graph_segmentation(float(k), int(min_size)).processImage(np.ascontiguousarray(image))
    if params.merge_color_tol > 0:
        labels = merge_similar_segments(labels, image, params.merge_color_tol, params.merge_edge_tol)
    return labels


def _adjacent_pixels(shape: tuple[int, int]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Flat indices of every pair of horizontally or vertically adjacent pixels."""
    h, w = shape
    index = np.arange(h * w).reshape(h, w)
    first = np.concatenate([index[:, :-1].reshape(-1), index[:-1, :].reshape(-1)])
    second = np.concatenate([index[:, 1:].reshape(-1), index[1:, :].reshape(-1)])
    return first, second


def merge_similar_segments(
    labels: NDArray[np.int32], rgb: NDArray[np.uint8], tol: float, edge_tol: float
) -> NDArray[np.int32]:
    """Merges adjacent segments whose mean colours differ by less than ``tol`` across a faint
    boundary (the colour difference of the pixel pairs across it averages less than
    ``edge_tol``), most similar first; two groups join only while their merged means stay within
    ``tol``, so that a slow gradient cannot chain unlike regions together. Returns labels 0..S'-1.
    """
    n = int(labels.max()) + 1
    flat = labels.reshape(-1)
    count = np.bincount(flat, minlength=n).astype(np.float64)
    colour = rgb.reshape(-1, 3).astype(np.float32)
    sums = np.stack([np.bincount(flat, colour[:, c], n) for c in range(3)], axis=1)
    i, j = _adjacent_pixels(labels.shape)
    cut = flat[i] != flat[j]
    i, j = i[cut], j[cut]
    la, lb = flat[i].astype(np.int64), flat[j].astype(np.int64)
    pairs, inverse = np.unique(np.minimum(la, lb) * n + np.maximum(la, lb), return_inverse=True)
    edge = np.bincount(inverse, np.linalg.norm(colour[i] - colour[j], axis=1)) / np.bincount(inverse)
    lo, hi = np.divmod(pairs, n)
    mean = sums / np.maximum(count, 1)[:, None]
    dist = np.linalg.norm(mean[lo] - mean[hi], axis=1)
    close = np.flatnonzero((dist < tol) & (edge < edge_tol))
    if len(close) == 0:
        return labels
    parent = np.arange(n)

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for e in close[np.argsort(dist[close], kind="stable")].tolist():
        ra, rb = root(int(lo[e])), root(int(hi[e]))
        if ra == rb:
            continue
        diff = sums[ra] / count[ra] - sums[rb] / count[rb]
        if float(diff @ diff) >= tol * tol:
            continue
        parent[rb] = ra
        sums[ra] += sums[rb]
        count[ra] += count[rb]
    _, compact = np.unique([root(k) for k in range(n)], return_inverse=True)
    return compact.astype(np.int32)[labels]


# --------------------------------------------------------------------------------------------
# Plane fits, all segments at once


@dataclass
class PlaneFits:
    """Planes ``normal . p + offset = 0`` (camera axes, unit ``normal``) of G groups of points.

    Attributes:
        normal: (G, 3) float64.
        offset: (G,) float64, metres.
        kind: (G,) int8: 0 no plane passed the tests, 1 vertical, 2 ground.
        rms_m: (G,) RMS distance of the inliers to the plane.
        share: (G,) share of the group's points the plane (or the group's planes) explain.
        depth_m: (G,) mean z of the inliers.
        confidence: (G,) mean confidence of the inliers.
        from_line: (G,) bool, the plane was fixed by a line of points and the group's label
            (``line_planes``).
    """

    normal: F64
    offset: F64
    kind: NDArray[np.int8]
    rms_m: F64
    share: F64
    depth_m: F64
    confidence: F64
    from_line: Mask

    @classmethod
    def empty(cls, n: int) -> PlaneFits:
        """G = n groups without a plane."""
        return cls(
            np.zeros((n, 3)),
            np.zeros(n),
            np.zeros(n, np.int8),
            *(np.zeros(n) for _ in range(4)),
            np.zeros(n, bool),
        )

    def scattered(self, groups: NDArray[np.intp], n: int) -> PlaneFits:
        """These fits (of groups 0..len(groups)-1) placed at ``groups`` among n."""
        out = PlaneFits.empty(n)
        for f in dataclasses.fields(PlaneFits):
            getattr(out, f.name)[groups] = getattr(self, f.name)
        return out


@dataclass(frozen=True)
class _Groups:
    """Points sorted by group: group g holds points ``start[g] : start[g] + count[g]``."""

    index: NDArray[np.intp]  # (N,) group of each point, non-decreasing
    count: NDArray[np.intp]  # (G,)
    start: NDArray[np.intp]  # (G,)

    @classmethod
    def of(cls, index: NDArray[np.intp], n: int) -> _Groups:
        count = np.bincount(index, minlength=n)
        return cls(index, count, np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.intp))

    def sums(self, values: F64) -> F64:
        """(G, k) sums of the (N, k) ``values`` over each group (0 for empty groups)."""
        out = np.zeros((len(self.count), values.shape[1]))
        full = self.count > 0
        if full.any():
            out[full] = np.add.reduceat(values, self.start[full], axis=0)
        return out

    def moments(self, weight: F64, points: F64) -> tuple[F64, F64, F64]:
        """Total weight (G,), weighted mean (G, 3) and covariance (G, 3, 3) of each group."""
        x, y, z = points.T
        cols = np.stack([np.ones_like(x), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z], axis=1)
        s = self.sums(cols * weight[:, None])
        total = s[:, 0]
        inv = 1.0 / np.maximum(total, 1e-12)
        mean = s[:, 1:4] * inv[:, None]
        second = np.empty((len(total), 3, 3))
        for (i, j), k in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), range(4, 10), strict=True):
            second[:, i, j] = second[:, j, i] = s[:, k] * inv
        return total, mean, second - mean[:, :, None] * mean[:, None, :]


def _horizontal_basis(up: F64) -> F64:
    """(2, 3) orthonormal basis of the plane perpendicular to the unit vector ``up``."""
    e1 = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.5:
        e1 = np.cross(up, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)])


def fit_planes(
    groups: NDArray[np.intp],
    points: F64,
    confidence: F64,
    n_groups: int,
    up: F64,
    p: CompletionParams,
    rng: np.random.Generator,
    lies: Mask | None = None,
    stands: Mask | None = None,
) -> tuple[PlaneFits, Mask]:
    """A robust plane for each group of camera-frame points (the tests of the module docstring),
    all groups at once.

    Args:
        groups: (N,) group of each point in 0..G-1, non-decreasing (points sorted by group).
        points: (N, 3) camera-frame points, metres.
        confidence: (N,) their confidences.
        n_groups: G.
        up: (3,) unit up vector in camera axes.
        p: the tests' parameters (``min_inlier_share`` is the share each plane needs).
        rng: draws the RANSAC samples.
        lies, stands: (G,) bool or None, groups labelled ground / a standing structure: with
            ``line_planes``, a line of their points fixes their plane (module docstring, step 2).

    Returns:
        The planes (``share``: each plane's own inlier share) and each point's inlier flag.
        Vertical planes first (RANSAC over two-point hypotheses that contain ``up``, least squares
        with the normal kept horizontal); where none passes and ``ground_planes``, near-horizontal
        ones (three-point hypotheses, free least squares); then, for groups that ``lies`` marks,
        ground planes through a line of points.
    """
    assert points.shape == (len(groups), 3), (points.shape, len(groups))
    assert np.all(np.diff(groups) >= 0), "points must be sorted by group"
    g = _Groups.of(groups, n_groups)
    fits = PlaneFits.empty(n_groups)
    inlier = np.zeros(len(points), bool)
    tol = p.inlier_tol_m + p.inlier_tol_rel * points[:, 2]
    todo = np.flatnonzero(g.count >= p.min_inliers)
    lines = p.line_planes and lies is not None
    stands = stands if p.line_planes and stands is not None else np.zeros(n_groups, bool)
    for mode in (KIND_VERTICAL, KIND_GROUND, _MODE_GROUND_LINE):
        if mode == KIND_GROUND and not p.ground_planes:
            continue
        if mode == _MODE_GROUND_LINE and lines:
            todo = todo[lies[todo]]  # type: ignore[index]
        if len(todo) == 0 or (mode == _MODE_GROUND_LINE and not lines):
            break
        normal, offset = _ransac(mode, g, points, tol, todo, up, p, rng)
        on, ok, line = _refine_and_accept(mode, g, points, tol, todo, normal, offset, up, p, stands)
        won = todo[ok[todo]]
        kind = KIND_GROUND if mode == _MODE_GROUND_LINE else mode
        fits.normal[won], fits.offset[won], fits.kind[won] = normal[won], offset[won], kind
        fits.from_line[won] = line[won]
        take = ok[groups]
        inlier[take] = on[take]
        todo = todo[~ok[todo]]
    w = inlier.astype(np.float64)
    res = np.einsum("ij,ij->i", points, fits.normal[groups]) + fits.offset[groups]
    s = g.sums(np.stack([w, w * res * res, w * points[:, 2], w * confidence], axis=1))
    inv = 1.0 / np.maximum(s[:, 0], 1.0)
    fits.share = s[:, 0] / np.maximum(g.count, 1)
    fits.rms_m = np.sqrt(s[:, 1] * inv)
    fits.depth_m = s[:, 2] * inv
    fits.confidence = s[:, 3] * inv
    return fits, inlier


def _ransac(
    kind: int,
    g: _Groups,
    points: F64,
    tol: F64,
    todo: NDArray[np.intp],
    up: F64,
    p: CompletionParams,
    rng: np.random.Generator,
) -> tuple[F64, F64]:
    """The best hypothesis (most inliers among ``ransac_points`` points) of every group in
    ``todo``: (G, 3) normals and (G,) offsets (zeros elsewhere). ``kind``: ``KIND_VERTICAL``,
    ``KIND_GROUND`` or ``_MODE_GROUND_LINE``."""
    a, r, m = len(todo), p.ransac_points, p.ransac_iterations
    pick = g.start[todo, None] + (rng.random((a, r)) * g.count[todo, None]).astype(np.intp)  # [A, R]
    pts, tol_s = points[pick], tol[pick]  # [A, R, 3], [A, R]
    h = rng.integers(0, r, (3, a, m))
    rows = np.arange(a)[:, None]
    p0 = pts[rows, h[0]]  # [A, M, 3]
    d1 = pts[rows, h[1]] - p0
    # A vertical plane holds the up direction; a ground plane a third point; a ground plane
    # through a line the horizontal direction across it (the plane through it closest to level).
    if kind == KIND_VERTICAL:
        d2 = np.broadcast_to(up, d1.shape)
    elif kind == _MODE_GROUND_LINE:
        d2 = np.cross(np.broadcast_to(up, d1.shape), d1)
    else:
        d2 = pts[rows, h[2]] - p0
    cand = np.stack(
        [
            d1[..., 1] * d2[..., 2] - d1[..., 2] * d2[..., 1],
            d1[..., 2] * d2[..., 0] - d1[..., 0] * d2[..., 2],
            d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0],
        ],
        axis=-1,
    )
    length = np.sqrt(np.sum(cand * cand, axis=-1))
    cand = cand / np.maximum(length, 1e-12)[..., None]
    off = -np.sum(cand * p0, axis=-1)
    dist = np.abs(np.matmul(cand, pts.transpose(0, 2, 1)) + off[..., None])  # [A, M, R]
    score = np.count_nonzero(dist <= tol_s[:, None, :], axis=2)
    bad = length <= 1e-9
    if kind != KIND_VERTICAL:
        bad |= np.abs(cand @ up) < np.cos(np.radians(p.max_tilt_deg))
    score[bad] = -1
    best = np.argmax(score, axis=1)
    normal, offset = np.zeros((len(g.count), 3)), np.zeros(len(g.count))
    normal[todo], offset[todo] = cand[np.arange(a), best], off[np.arange(a), best]
    return normal, offset


def _refine_and_accept(
    kind: int,
    g: _Groups,
    points: F64,
    tol: F64,
    todo: NDArray[np.intp],
    normal: F64,
    offset: F64,
    up: F64,
    p: CompletionParams,
    stands: Mask,
    rounds: int = 2,
) -> tuple[Mask, Mask, Mask]:
    """Refines the planes of ``todo`` in place by least squares on their inliers (``rounds`` times:
    inliers, then the fit to them); returns each point's final inlier flag, whether each
    group's plane passes the tests of the module docstring, and whether it passes only as a plane
    through a line (``_MODE_GROUND_LINE``, or a vertical plane of a group ``stands`` marks
    without the height test)."""
    member = np.zeros(len(g.count), bool)
    member[todo] = True
    basis = _horizontal_basis(up)
    for step in range(rounds + 1):
        res = np.einsum("ij,ij->i", points, normal[g.index]) + offset[g.index]
        inlier = member[g.index] & (np.abs(res) <= tol)
        w = inlier.astype(np.float64)
        total, mean, cov = g.moments(w, points)
        if step == rounds:
            break
        if kind == KIND_VERTICAL:  # the smaller axis of the horizontal coordinates' spread
            new_normal = np.linalg.eigh(basis @ cov @ basis.T)[1][:, :, 0] @ basis
        elif kind == _MODE_GROUND_LINE:  # up, less its part along the inliers' main axis
            along = np.linalg.eigh(cov)[1][:, :, 2]
            new_normal = up - (along @ up)[:, None] * along
            new_normal /= np.maximum(np.linalg.norm(new_normal, axis=1), 1e-12)[:, None]
        else:
            new_normal = np.linalg.eigh(cov)[1][:, :, 0]
        new_normal *= np.where(new_normal @ up < 0, -1.0, 1.0)[:, None]
        enough = total >= 3
        normal[enough] = new_normal[enough]
        offset[enough] = -np.einsum("ij,ij->i", new_normal, mean)[enough]
    rms = np.sqrt(g.sums((w * res * res)[:, None])[:, 0] / np.maximum(total, 1))
    ok = member & (total >= p.min_inliers) & (total >= p.min_inlier_share * g.count)
    ok &= rms <= p.max_residual_rel * mean[:, 2]
    val, vec = np.linalg.eigh(cov)  # ascending
    free = vec[:, :, 0]
    surface = val[:, 1] > 0.01 * np.maximum(val[:, 2], 1e-12)  # spread over an area, not a line
    line = np.zeros_like(ok)
    if kind == KIND_VERTICAL:
        height_var = np.einsum("i,gij,j->g", up, cov, up)
        least = np.minimum(p.min_height_m, p.min_height_rel * mean[:, 2])
        tall = np.sqrt(12.0 * np.maximum(height_var, 0.0)) >= least  # extent, if uniform
        ok &= ~(surface & (np.abs(free @ up) > np.sin(np.radians(p.max_tilt_deg))))
        line = ok & ~tall & stands
        ok &= tall | stands
    elif kind == _MODE_GROUND_LINE:
        length = np.sqrt(12.0 * np.maximum(val[:, 2], 0.0))
        ok &= (length >= p.min_line_m) & (normal @ up >= np.cos(np.radians(p.max_tilt_deg)))
        line = ok
    else:
        ok &= surface & (np.abs(free @ up) >= np.cos(np.radians(p.max_tilt_deg)))
    return inlier, ok, line


# --------------------------------------------------------------------------------------------
# The completion of one image


class _Completer:
    """Completion state of one image; :meth:`run` updates the outputs of ``inputs`` in place."""

    def __init__(
        self,
        inputs: _Inputs,
        segments: NDArray[np.int32],
        up: F64,
        focal_px: float,
        p: CompletionParams,
        ray_norm: F64 | None = None,
    ):
        self.shape = inputs.depth.shape
        self.depth, self.conf = inputs.depth.reshape(-1), inputs.conf.reshape(-1)
        self.origin = inputs.origin.reshape(-1)
        self.known, self.fillable = inputs.known.reshape(-1), inputs.fillable.reshape(-1)
        self.image, self.rays, self.up, self.p = inputs.rgb, inputs.rays, up, p
        self.segments = segments
        self._segment_colours: F64 | None = None
        self._boundary_pairs: tuple[NDArray[np.intp], NDArray[np.intp]] | None = None
        self.scale = focal_px / REFERENCE_FOCAL_PX
        self.rng = np.random.default_rng(p.seed)
        self.ray_norm = np.linalg.norm(self.rays, axis=1) if ray_norm is None else ray_norm
        # The plane each completed pixel took (to complete a finer grid from this one).
        self.plane_normal = np.zeros((self.depth.size, 3), np.float32)
        self.plane_offset = np.zeros(self.depth.size, np.float32)
        # Each completed pixel's distance to the data its plane was fitted to (pixels).
        self.fill_dist = np.zeros(self.depth.size, np.float32)
        # The vertical plane each pixel lies on (its segment's inliers and completed pixels), an
        # index into ``facades`` ((fits, segment of fits, confidence factor, family)); -1 none. Planes
        # climb from these into the segments above (step 7).
        self.facade_of = np.full(self.depth.size, -1, np.int32)
        self.facades: list[tuple[PlaneFits, int, float, int]] = []  # (..., family: the first's index)
        self.sky = None if inputs.sky is None else inputs.sky.reshape(-1)
        # Thin structures' evidence: the dense depth, and the sparse depth where it has none.
        self.thin_depth, self.thin_conf = self.depth.copy(), self.conf.copy()
        if inputs.sparse is not None:
            sparse, sparse_conf = (a.reshape(-1) for a in inputs.sparse)
            extra = (self.thin_depth == 0) & (sparse > 0) & (sparse_conf > 0)
            self.thin_depth[extra], self.thin_conf[extra] = sparse[extra], sparse_conf[extra]
        # Segment tables: pixels sorted by segment, sizes, bounding boxes, counts.
        w = self.shape[1]
        flat = self.flat = segments.reshape(-1)
        n = self.count = int(flat.max()) + 1
        self.order = np.argsort(flat, kind="stable")
        self.sizes = np.bincount(flat, minlength=n)
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)])
        rows, cols = np.divmod(self.order, w)
        first = self.starts[:-1][self.sizes > 0]
        self.r0, self.r1, self.c0, self.c1 = (np.zeros(n, np.intp) for _ in range(4))
        full = self.sizes > 0
        self.r0[full], self.r1[full] = np.minimum.reduceat(rows, first), np.maximum.reduceat(rows, first) + 1
        self.c0[full], self.c1[full] = np.minimum.reduceat(cols, first), np.maximum.reduceat(cols, first) + 1
        self.n_dense = np.bincount(flat, weights=self.known, minlength=n)
        # Anchors, the pixels planes are fitted to: the dense depth, and in segments with fewer than
        # ``min_inliers`` of it, the sparse depth (the densifier leaves out the scan lines on a far
        # lawn) if it has that many.
        self.anchor, self.anchor_depth, self.anchor_conf = self.known, self.depth, self.conf
        self.seg_factor = np.ones(n)
        self.sparse_seg = np.zeros(n, bool)
        if p.sparse_planes and inputs.sparse is not None:
            extra = (self.n_dense < p.min_inliers)[flat] & (self.thin_depth > 0) & ~self.known
            n_sparse = np.bincount(flat, weights=extra, minlength=n)
            sparse_seg = (n_sparse >= p.min_inliers) & (n_sparse >= p.sparse_min_share * self.sizes)
            extra &= sparse_seg[flat]
            if extra.any():
                self.anchor = self.known | extra
                self.anchor_depth = np.where(extra, self.thin_depth, self.depth)
                self.anchor_conf = np.where(extra, self.thin_conf, self.conf)
                self.seg_factor[sparse_seg] = p.sparse_plane_confidence
                self.sparse_seg = sparse_seg
        self.n_known = np.bincount(flat, weights=self.anchor, minlength=n)
        self.n_fill = np.bincount(flat, weights=self.fillable, minlength=n)
        self.skip = np.zeros(n, bool)
        if inputs.sky is not None:
            self.skip |= (
                np.bincount(flat, weights=inputs.sky.reshape(-1), minlength=n) > p.max_sky_share * self.sizes
            )
        if inputs.classes is not None:
            self.skip |= _majority_never_filled(flat, inputs.classes.reshape(-1), n)
        # Segments with more than a few pixels labelled things (vehicles, people;
        # ``upward_max_thing_share``): things end where their box does, so no plane climbs from or
        # into them; a car's side merged with the facade behind it would carry the car's depth up
        # the facade.
        self.thing_touched = np.zeros(n, bool)
        # What a segment's label says of its plane, for a line of known points (``line_planes``).
        self.lies = self.stands = None
        if inputs.classes is not None and p.line_planes:
            labels = inputs.classes.reshape(-1)
            self.lies = _majority_in(flat, labels, n, tx.GROUND_IDS)
            self.stands = _majority_in(flat, labels, n, STANDING_CLASSES)
        # Pixels of excess blue (2 b - r - g) above ``upward_max_blue``: sky the labels missed; with
        # their 8 neighbours, the rim where a crown blends into it (blended pixels are sky).
        blue = inputs.rgb.reshape(-1, 3).astype(np.float64) @ np.array([-1.0, -1.0, 2.0])
        self.sky_like = blue > p.upward_max_blue
        rim = cv2.dilate(self.sky_like.reshape(self.shape).view(np.uint8), np.ones((3, 3), np.uint8))
        self.sky_rim = rim.astype(bool).reshape(-1)
        self.vegetation = np.zeros(n, bool)
        self.vehicle = np.zeros(n, bool)
        self.ground = np.zeros(n, bool)
        self.things = np.zeros(self.depth.size, bool)
        if inputs.classes is not None:
            labels = inputs.classes.reshape(-1)
            self.vegetation = _majority_in(flat, labels, n, frozenset({tx.VEGETATION}))
            self.vehicle = _majority_in(flat, labels, n, VEHICLE_CLASSES)
            self.ground = _majority_in(flat, labels, n, tx.GROUND_IDS)
            self.things = np.isin(labels, list(tx.THING_IDS))
            share = np.bincount(flat, weights=self.things, minlength=n) / np.maximum(self.sizes, 1)
            self.thing_touched = share > p.upward_max_thing_share

    def horizontal(self, points: F64) -> F64:
        """The part of (..., 3) camera-frame points across ``up``: the horizontal direction to them."""
        return points - (points @ self.up)[..., None] * self.up

    def pixels(self, s: int) -> NDArray[np.intp]:
        """Flat indices of the pixels of segment ``s``."""
        return self.order[self.starts[s] : self.starts[s + 1]]

    def crop(self, s: int) -> tuple[slice, slice]:
        """The bounding box of segment ``s``."""
        return slice(self.r0[s], self.r1[s]), slice(self.c0[s], self.c1[s])

    def run(self) -> None:
        p = self.p
        height = self.r1 - self.r0
        mean_width = self.sizes / np.maximum(height, 1)
        thin = (
            (mean_width <= p.max_thin_width_ref_px * self.scale)
            & (height >= p.min_thin_aspect * mean_width)
            & (height >= p.min_thin_height_ref_px * self.scale)
        )
        todo = (self.n_fill > 0) & ~self.skip
        planar = np.flatnonzero(todo & ~thin & (self.n_known >= p.min_inliers))
        planes, plane_px = self.fit_segments(planar)
        # A hole needs a few pixels of the segment's box that are not the segment's.
        room = (self.r1 - self.r0) * (self.c1 - self.c0) - self.sizes >= 4
        for s in planar[planes[0].kind[planar] != KIND_NONE].tolist():
            filled = self.fill_segment(s, planes, plane_px)
            if filled is not None and room[s]:
                self.fill_holes(s, planes, *filled)
        if p.crowns:
            green = self.segment_colours() @ np.array([-1.0, 2.0, -1.0]) > p.upward_max_green
            green |= self.vegetation
            blobs = planar[
                (planes[0].kind[planar] == KIND_NONE) & green[planar] & ~self.thing_touched[planar]
            ]
            for s in blobs.tolist():
                self.fill_crown(s)
            if p.vehicle_max_spread > 0:
                for s in planar[(planes[0].kind[planar] == KIND_NONE) & self.vehicle[planar]].tolist():
                    self.fill_crown(s, p.vehicle_max_spread)
            if p.canopies:
                self.fill_canopies(~self.skip & green & ~self.thing_touched)
        if p.propagate_ground:
            below = np.bincount(self.flat, weights=(self.rays @ self.up) > 0, minlength=self.count) == 0
            completed = np.bincount(self.flat, (self.depth > 0) & ~self.known, self.count)
            empty = todo & ~thin & (self.n_dense < p.min_inliers) & (completed == 0) & below
            self.propagate(np.flatnonzero(empty), planes[0], planes[0].kind == KIND_GROUND)
        evidence = np.bincount(self.flat, weights=self.thin_depth > 0, minlength=self.count)
        enough = evidence >= np.maximum(p.min_thin_known, p.min_thin_evidence * self.sizes)
        for s in np.flatnonzero(todo & thin & enough & (self.n_dense >= p.min_thin_trusted)).tolist():
            self.fill_thin(s)
        if p.thin_planes:
            # A thin segment the step above did not fill (a strip of wall between two columns of
            # windows, a kerb, seen too little to show a pole's rise) is fitted like any other.
            completed = np.bincount(self.flat, (self.depth > 0) & ~self.known, self.count)
            rest = np.flatnonzero(todo & thin & (completed == 0) & (self.n_known >= p.min_inliers))
            if len(rest):
                thin_fits, thin_px = self.fit_segments(rest)
                for s in rest[thin_fits[0].kind[rest] != KIND_NONE].tolist():
                    self.fill_segment(s, thin_fits, thin_px)
        # Only with sky labels: nothing else tells the sky above a roofline from a wall.
        walled: Mask | None = None
        if p.wall_columns and self.sky is not None:
            walls = todo & (self.n_dense >= p.min_inliers) & ~(self.ground | self.vegetation | self.vehicle)
            open_above = self.fillable & (self.depth == 0) & ((self.rays @ self.up) > 0)
            walls &= np.bincount(self.flat, open_above & ~self.things & ~self.sky_like, self.count) > 0
            before = self.depth > 0
            for s in np.flatnonzero(walls).tolist():
                self.climb_walls(s)
            walled = (self.depth > 0) & ~before
        # Thin ones too (the wall between two columns of windows).
        if p.propagate_up and self.sky is not None:
            self.propagate_up(todo)
        if walled is not None:
            self.climb_through(walled, todo)  # after step 7, which climbs whole segments first

    # -- planes ------------------------------------------------------------------------------

    def fit_segments(self, segs: NDArray[np.intp]) -> tuple[list[PlaneFits], NDArray[np.int8]]:
        """Up to two planes per segment of ``segs`` (module docstring, step 2), and per pixel the
        plane (1, 2) it is an inlier of (0: none)."""
        p = self.p
        each = dataclasses.replace(p, min_inlier_share=p.min_plane_share)
        chosen = np.zeros(self.count, bool)
        chosen[segs] = True
        kn = self.order[self.anchor[self.order] & chosen[self.flat[self.order]]]  # sorted by segment
        groups = self.flat[kn]
        first = self._fit(kn, segs, each)
        if p.line_planes:
            self._fit_lines_by_height(kn, segs, first, each)
        on_first = self._on_plane(kn, first)
        n_first = np.bincount(groups, on_first, self.count)
        share = n_first / np.maximum(self.n_known, 1)
        split = segs[(first.kind[segs] != KIND_NONE) & (share[segs] < p.min_inlier_share)]
        second = PlaneFits.empty(self.count)
        on_second = np.zeros(len(kn), bool)
        if len(split):
            is_split = np.zeros(self.count, bool)
            is_split[split] = True
            rest = ~on_first & is_split[groups]
            second = self._fit(kn[rest], split, each)
            second.kind[~is_split] = KIND_NONE
            on_second[rest] = self._on_plane(kn[rest], second)
            n_second = np.bincount(groups, on_second, self.count)
            share = (n_first + n_second) / np.maximum(self.n_known, 1)
            bad = is_split & ((share < p.min_inlier_share) | (n_second < p.min_plane_share * self.n_known))
            first.kind[bad] = second.kind[bad] = KIND_NONE
        first.share = second.share = share
        plane_px = np.zeros(self.flat.shape, np.int8)
        plane_px[kn[on_first & (first.kind[groups] != KIND_NONE)]] = 1
        plane_px[kn[on_second & (second.kind[groups] != KIND_NONE)]] = 2
        return [first, second], plane_px

    def _fit_lines_by_height(
        self, kn: NDArray[np.intp], segs: NDArray[np.intp], fits: PlaneFits, p: CompletionParams
    ) -> None:
        """Where the labels do not say, a line of points at the ground's height (the image's own
        ground planes: their median distance below the camera) lies: refits the segments of
        ``segs`` without a plane and without a ground or standing label, in place."""
        ground = segs[fits.kind[segs] == KIND_GROUND]
        failed = segs[fits.kind[segs] == KIND_NONE]
        if self.lies is not None and self.stands is not None:
            failed = failed[~(self.lies[failed] | self.stands[failed])]
        if len(ground) == 0 or len(failed) == 0:
            return
        camera_height_m = float(np.median(fits.offset[ground]))
        groups = self.flat[kn]
        points = self.rays[kn] * self.anchor_depth[kn, None]
        count = np.maximum(np.bincount(groups, minlength=self.count), 1)
        height = np.bincount(groups, points @ self.up, self.count) / count + camera_height_m
        depth = np.bincount(groups, points[:, 2], self.count) / count
        # Only lying lines: a line of points above the ground is as often a car's flank or a
        # kerb-top row as a wall's foot (measured: standing lines by height alone were wrong).
        lies = np.abs(height) <= p.inlier_tol_m + 2 * p.inlier_tol_rel * depth
        chosen = np.zeros(self.count, bool)
        chosen[failed] = True
        refit = self._fit(kn[chosen[groups]], failed, p, labels=(lies, None))
        won = failed[refit.kind[failed] != KIND_NONE]
        for f in dataclasses.fields(PlaneFits):
            getattr(fits, f.name)[won] = getattr(refit, f.name)[won]

    def _fit(
        self,
        kn: NDArray[np.intp],
        segs: NDArray[np.intp],
        p: CompletionParams,
        labels: tuple[Mask | None, Mask | None] | None = None,
    ) -> PlaneFits:
        """Planes of ``segs`` from about ``fit_points`` random pixels per segment of the known
        pixels ``kn`` (sorted by segment); ``labels``: the (S,) lies / stands flags of the segments
        (default: what their labels say)."""
        groups = self.flat[kn]
        count = np.bincount(groups, minlength=self.count)
        sub = kn[self.rng.random(len(kn)) < (p.fit_points / np.maximum(count, 1))[groups]]
        compact = np.full(self.count, -1, np.intp)
        compact[segs] = np.arange(len(segs))
        points = self.rays[sub] * self.anchor_depth[sub, None]
        conf = self.anchor_conf[sub].astype(np.float64)
        lies, stands = (None if a is None else a[segs] for a in (labels or (self.lies, self.stands)))
        fits, _ = fit_planes(
            compact[self.flat[sub]], points, conf, len(segs), self.up, p, self.rng, lies, stands
        )
        return fits.scattered(segs, self.count)

    def _on_plane(self, kn: NDArray[np.intp], fits: PlaneFits) -> Mask:
        """Whether each known pixel of ``kn`` lies on its segment's plane of ``fits``."""
        g = self.flat[kn]
        res = np.einsum("ij,ij->i", self.rays[kn], fits.normal[g]) * self.anchor_depth[kn] + fits.offset[g]
        tol = self.p.inlier_tol_m + self.p.inlier_tol_rel * self.anchor_depth[kn]
        return (fits.kind[g] != KIND_NONE) & (np.abs(res) <= tol)

    def fill_segment(
        self, s: int, planes: list[PlaneFits], plane_px: NDArray[np.int8]
    ) -> tuple[NDArray[np.int8], F32] | None:
        """Fills the segment's empty pixels from the plane of its nearest known pixel (step 3).
        Returns, for every pixel of its crop, that plane (1, 2; 0 none) and the distance to that
        pixel; None where the two planes do not meet (:meth:`planes_meet`: then no holes are
        filled either)."""
        rs, cs = self.crop(s)
        w = self.shape[1]
        seg = self.segments[rs, cs] == s
        dist, nearest = _nearest_pixel(seg & self.anchor.reshape(self.shape)[rs, cs])
        nr, nc = np.divmod(nearest, cs.stop - cs.start)
        which = plane_px[(nr + rs.start) * w + (nc + cs.start)]
        apart = planes[1].kind[s] != KIND_NONE and not self.planes_meet(s, planes, which, seg, rs, cs)
        reach = self.p.split_extrapolation_ref_px if apart else self.p.max_extrapolation_ref_px
        which[dist > reach * self.scale] = 0
        climbed = (
            apart
            and self.p.climb_columns
            and self.climb_columns(s, planes, plane_px, seg, rs, cs, which, dist)
        )
        empty = self.fillable.reshape(self.shape)[rs, cs] & (self.depth.reshape(self.shape)[rs, cs] == 0)
        for k, fits in enumerate(planes, start=1):
            tr, tc = np.nonzero(seg & empty & (which == k))
            self._fill(
                (tr + rs.start) * w + (tc + cs.start),
                fits,
                s,
                dist[tr, tc],
                self.seg_factor[s] * (self.p.line_confidence if fits.from_line[s] else 1.0),
                ORIGIN["plane"],
            )
            # Planes of the sparse depth alone do not climb: it leaks at silhouettes, most of all
            # into the sky beside a roofline.
            if fits.kind[s] == KIND_VERTICAL and not self.thing_touched[s] and not self.sparse_seg[s]:
                # The plane's region: its inliers and the pixels it completed.
                idx = self.pixels(s)
                mine = plane_px[idx] == k
                tr, tc = np.nonzero(seg & empty & (which == k))
                done = (tr + rs.start) * w + (tc + cs.start)
                done = done[self.depth[done] > 0]
                self.facade_of[idx[mine]] = self.facade_of[done] = len(self.facades)
                self.facades.append((fits, s, float(self.seg_factor[s]), len(self.facades)))
        return None if apart and not climbed else (which, dist)

    def climb_columns(
        self,
        s: int,
        planes: list[PlaneFits],
        plane_px: NDArray[np.int8],
        seg: Mask,
        rs: slice,
        cs: slice,
        which: NDArray[np.int8],
        dist: F32,
    ) -> bool:
        """A segment with two vertical planes that do not meet (two facades of one colour) fills
        its pixels above each column's topmost inlier with that inlier's plane: a facade's upper
        part lies above its lower part, however far it is from the data. The climb runs through
        the segment and its holes (windows) and stops at anything else. Updates ``which`` and
        ``dist`` (rows up from that inlier) of the crop in place; whether it climbed."""
        if self.thing_touched[s] or not (
            planes[0].kind[s] == KIND_VERTICAL and planes[1].kind[s] == KIND_VERTICAL
        ):
            return False
        h = seg.shape[0]
        inlier = seg & (plane_px.reshape(self.shape)[rs, cs] > 0) & self.anchor.reshape(self.shape)[rs, cs]
        rows = np.arange(h)[:, None]
        top = np.where(inlier, rows, h).min(axis=0)
        _, comp = cv2.connectedComponents((~seg).view(np.uint8), connectivity=4)
        edge = np.unique(np.concatenate([comp[0], comp[-1], comp[:, 0], comp[:, -1]]))
        passable = seg | ~np.isin(comp, edge[edge > 0])
        blocked = np.where(~passable & (rows < top), rows, -1).max(axis=0)
        climb = seg & (rows < top) & (rows > blocked) & (which == 0) & (top < h)
        cr, cc = np.nonzero(climb)
        which[cr, cc] = plane_px.reshape(self.shape)[rs, cs][top[cc], cc]
        dist[cr, cc] = (top[cc] - cr).astype(np.float32)
        return True

    def planes_meet(
        self, s: int, planes: list[PlaneFits], which: NDArray[np.int8], seg: Mask, rs: slice, cs: slice
    ) -> bool:
        """Whether a segment's two planes give the same depth (within the inlier tolerance) along
        the seam where their parts of the segment touch: a building's corner, not a bus standing
        in front of a facade, where a pixel far from both could belong to either."""
        inside = seg & (which > 0)
        seam = np.zeros(seg.shape, bool)
        seam[:, 1:] |= inside[:, 1:] & inside[:, :-1] & (which[:, 1:] != which[:, :-1])
        seam[1:, :] |= inside[1:, :] & inside[:-1, :] & (which[1:, :] != which[:-1, :])
        sr, sc = np.nonzero(seam)
        if len(sr) < 3:
            return False
        rays = self.rays[(sr + rs.start) * self.shape[1] + (sc + cs.start)]
        with np.errstate(divide="ignore", invalid="ignore"):
            z1 = -planes[0].offset[s] / (rays @ planes[0].normal[s])
            z2 = -planes[1].offset[s] / (rays @ planes[1].normal[s])
        gap = np.abs(z1 - z2) - (self.p.inlier_tol_m + self.p.inlier_tol_rel * np.abs(z1))
        return bool(np.all(np.isfinite(gap)) and np.median(gap) <= 0)

    def fill_holes(self, s: int, planes: list[PlaneFits], which: NDArray[np.int8], data_dist: F32) -> None:
        """Fills the holes of the segment's region with depth (step 4).

        A hole is a component of the rest of the region's bounding box that does not reach the
        box's border; one that reaches it only where that border is the image's (a window cut by
        the image's top edge) counts if it looks like an enclosed one (mean colours within
        ``merge_color_tol``, at most 1.5 times its area): facades repeat their windows, and a
        patch of sky beside a facade does not look like them. A hole takes the plane of the
        region pixel nearest to it (``which``: per pixel of the crop, :meth:`fill_segment`),
        unless its own known pixels lie off that plane; ``data_dist``: each crop pixel's
        distance to the segment's known pixels.
        """
        rs, cs = self.crop(s)
        h, w = self.shape
        region = (self.segments[rs, cs] == s) & (self.depth.reshape(self.shape)[rs, cs] > 0)
        if region.sum() < 4:
            return
        count, comp, stats, _ = cv2.connectedComponentsWithStats((~region).view(np.uint8), connectivity=4)
        if count <= 1:
            return
        inner, outer = np.zeros(count, bool), np.zeros(count, bool)
        for line, image_edge in (
            (comp[0], rs.start == 0),
            (comp[-1], rs.stop == h),
            (comp[:, 0], cs.start == 0),
            (comp[:, -1], cs.stop == w),
        ):
            (outer if image_edge else inner)[line] = True
        inner[0] = True  # the region itself
        hole = ~inner & ~outer
        cut = np.flatnonzero(~inner & outer)
        if len(cut) and hole.any():
            colour = self.image[rs, cs].reshape(-1, 3).astype(np.float64)
            area = np.maximum(stats[:, cv2.CC_STAT_AREA], 1)
            sums = np.stack([np.bincount(comp.reshape(-1), colour[:, c], count) for c in range(3)], axis=1)
            mean = sums / area[:, None]
            ref = np.flatnonzero(hole)
            for k in cut.tolist():
                alike = np.linalg.norm(mean[ref] - mean[k], axis=1) < self.p.merge_color_tol
                hole[k] = bool(np.any(alike & (area[k] <= 1.5 * area[ref])))
        if not hole.any():
            return
        _, nearest = _nearest_pixel(region)
        k_of = which.reshape(-1)[nearest]
        hr, hc = np.nonzero(hole[comp])
        pixels = (hr + rs.start) * w + (hc + cs.start)
        k_of = k_of[hr, hc]
        known = self.known[pixels]
        if known.any():  # a hole whose known pixels lie off its plane is something else
            kp, kk = pixels[known], np.maximum(k_of[known], 1) - 1
            normal = np.stack([f.normal[s] for f in planes])[kk]
            offset = np.array([f.offset[s] for f in planes])[kk]
            res = np.abs(np.einsum("ij,ij->i", self.rays[kp], normal) * self.depth[kp] + offset)
            off = (res > self.p.inlier_tol_m + self.p.inlier_tol_rel * self.depth[kp]) | (k_of[known] == 0)
            bad = np.bincount(comp[hr[known], hc[known]], off, count) > 0
            keep = ~bad[comp[hr, hc]]
            pixels, hr, hc, k_of = pixels[keep], hr[keep], hc[keep], k_of[keep]
        empty = self.fillable[pixels] & (self.depth[pixels] == 0)
        for k, fits in enumerate(planes, start=1):
            sel = empty & (k_of == k)
            dist = data_dist[hr[sel], hc[sel]]
            self._fill(
                pixels[sel], fits, s, dist, self.p.hole_confidence * self.seg_factor[s], ORIGIN["plane"]
            )

    def propagate(self, segs: NDArray[np.intp], fits: PlaneFits, source: Mask) -> None:
        """Fills each segment of ``segs`` (without depth) with the plane of the ``source`` segment
        it shares the longest boundary with, of at least ``min_boundary_ref_px``, if their mean
        colours are within ``propagate_color_tol`` (step 5)."""
        if len(segs) == 0 or not source.any():
            return
        i, j = self.boundary_pairs()
        a, b = self.flat[i].astype(np.int64), self.flat[j].astype(np.int64)
        keys, length = np.unique(np.concatenate([a * self.count + b, b * self.count + a]), return_counts=True)
        seg, nb = np.divmod(keys, self.count)
        want = np.zeros(self.count, bool)
        want[segs] = True
        mean = self.segment_colours()
        ok = want[seg] & source[nb] & (length >= self.p.min_boundary_ref_px * self.scale)
        ok &= np.linalg.norm(mean[seg] - mean[nb], axis=1) < self.p.propagate_color_tol
        seg, nb, length = seg[ok], nb[ok], length[ok]
        order = np.lexsort((-length, seg))  # by segment, longest boundary first
        seg, nb = seg[order], nb[order]
        first = np.concatenate([[True], seg[1:] != seg[:-1]]) if len(seg) else np.zeros(0, bool)
        w = self.shape[1]
        for s, src in zip(seg[first].tolist(), nb[first].tolist(), strict=True):
            idx = self.pixels(s)
            empty = idx[self.fillable[idx] & (self.depth[idx] == 0)]
            dist = np.abs(empty // w - (self.r0[src] + self.r1[src]) / 2).astype(np.float32)
            self._fill(empty, fits, src, dist, self.p.propagate_confidence, ORIGIN["plane"])

    def boundary_pairs(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Flat indices of every pair of horizontally or vertically adjacent pixels of different
        segments (first, second; computed once per completion)."""
        if self._boundary_pairs is None:
            i, j = _adjacent_pixels(self.shape)
            cut = self.flat[i] != self.flat[j]
            self._boundary_pairs = (i[cut], j[cut])
        return self._boundary_pairs

    def segment_colours(self) -> F64:
        """(S, 3) mean colour of each segment (computed once: the image and its segments do not
        change during a completion; a read-only array)."""
        if self._segment_colours is None:
            colour = self.image.reshape(-1, 3).astype(np.float64)
            sums = np.stack([np.bincount(self.flat, colour[:, c], self.count) for c in range(3)], axis=1)
            self._segment_colours = sums / np.maximum(self.sizes, 1)[:, None]
            self._segment_colours.setflags(write=False)
        return self._segment_colours

    def unseen_facade_parts(self, todo: Mask) -> Mask:
        """The segments of ``todo`` a facade may climb into (step 7): fewer than ``min_inliers``
        pixels of depth (dense or sparse: the LiDAR did not see them), at most
        ``upward_max_thing_share`` of their pixels labelled things, neither green nor blue."""
        p = self.p
        mean = self.segment_colours()
        green, blue = mean @ np.array([-1.0, 2.0, -1.0]), mean @ np.array([-1.0, -1.0, 2.0])
        evidence = np.bincount(self.flat, self.thin_depth > 0, self.count)
        todo = todo & ~self.thing_touched & (self.n_known < p.min_inliers) & (evidence < p.min_inliers)
        # Excess green (2 g - r - b), a vegetation index: a tree's crown above a roof is not the
        # facade; nor is the sky above it that the labels missed, blue (2 b - r - g).
        return todo & (green <= p.upward_max_green) & (blue <= p.upward_max_blue)

    def propagate_up(self, todo: Mask) -> None:
        """Vertical planes climb into the segments above them (step 7): the upper part of a
        facade, beyond the LiDAR's top beam, is often a segment of its own (cut off by a ledge, a
        row of windows), without depth.

        A candidate is a segment of ``todo`` with at most ``upward_max_thing_share`` of its pixels
        labelled things, neither green nor blue
        (``upward_max_green``, ``upward_max_blue``),
        with fewer than ``min_inliers`` pixels of depth (dense or sparse: the LiDAR did not see it)
        and none completed. It takes the vertical plane whose region (:attr:`facade_of`: one plane
        and the segments it climbed into) runs along its lower boundary for at least
        ``upward_min_boundary_ref_px`` and ``upward_boundary_share`` of that whole boundary; or the
        plane whose region holds all but a tenth of its whole boundary (the windows
        between two of those segments). Then it is that plane's region too, for the segments above
        it: ``upward_steps`` rounds. Its pixels' distance to the data: the rows up from that
        boundary, plus the boundary's own. Sky pixels are left out of every boundary.
        """
        p = self.p
        h, w = self.shape
        if h < 2 or not self.facades:
            return
        todo = self.unseen_facade_parts(todo)
        i, j = self.boundary_pairs()
        # Every boundary pair both ways: (pixel of the candidate, its neighbour, neighbour below).
        a, b = np.concatenate([i, j]), np.concatenate([j, i])
        below = b - a == w
        if self.sky is not None:
            keep = ~self.sky[b]
            a, b, below = a[keep], b[keep], below[keep]
        seg_a = self.flat[a].astype(np.int64)
        least = max(p.upward_min_boundary_ref_px * self.scale, 1.0)
        done = np.zeros(self.count, bool)
        for _ in range(p.upward_steps):
            completed = np.bincount(self.flat, (self.depth > 0) & ~self.known, self.count)
            cand = todo & ~done & (completed == 0)
            on = cand[seg_a]
            if not on.any():
                return
            sa, bb, down = seg_a[on], b[on], below[on]
            fid = self.facade_of[bb]
            family = np.array([f[3] for f in self.facades] + [-1], np.int64)[fid]  # -1: none
            n_f = len(self.facades) + 1
            # Below: support of each (segment, family), and the whole boundary below.
            lower = np.bincount(sa[down], minlength=self.count)
            keys, support = np.unique(
                sa[down & (fid >= 0)] * n_f + family[down & (fid >= 0)], return_counts=True
            )
            seg, fam = np.divmod(keys, n_f)
            ok = (support >= least) & (support >= p.upward_boundary_share * lower[seg])
            # All around: enclosed by one plane's region.
            total = np.bincount(sa, minlength=self.count)
            keys2, around = np.unique(sa[fid >= 0] * n_f + family[fid >= 0], return_counts=True)
            seg2, fam2 = np.divmod(keys2, n_f)
            enclosed = around >= 0.9 * total[seg2]
            seg = np.concatenate([seg[ok], seg2[enclosed]])
            fam = np.concatenate([fam[ok], fam2[enclosed]])
            length = np.concatenate([support[ok], around[enclosed]])
            if len(seg) == 0:
                return
            order = np.lexsort((-length, seg))  # by segment, longest boundary first
            seg, fam = seg[order], fam[order]
            first = np.concatenate([[True], seg[1:] != seg[:-1]])
            for s, q in zip(seg[first].tolist(), fam[first].tolist(), strict=True):
                done[s] = True
                mine = (sa == s) & (family == q)
                ref = bb[mine & down] if np.any(mine & down) else bb[mine]
                k = int(np.bincount(fid[mine]).argmax())  # the region's part it touches most
                fits, t, factor, _ = self.facades[k]
                idx = self.pixels(s)
                empty = idx[self.fillable[idx] & (self.depth[idx] == 0)]
                empty = empty[~self.sky_like[empty]]  # a roofline's segment takes in some sky
                rows = np.maximum(float(np.mean(ref // w)) - empty // w, 0)
                dist = (rows + float(np.mean(self.fill_dist[ref]))).astype(np.float32)
                factor *= p.upward_confidence
                self._fill(empty, fits, t, dist, factor, ORIGIN["plane"])
                filled = empty[self.depth[empty] > 0]
                if len(filled):
                    self.facade_of[filled] = len(self.facades)
                    self.facades.append((fits, t, factor, q))

    def climb_walls(self, s: int) -> None:
        """Each column of segment ``s`` climbs from its topmost known pixel (step 6d): its empty
        pixels above that one and above the horizon take the vertical plane facing the camera
        through that pixel's point (each column its own plane), at ``wall_confidence`` at most,
        the distance to the data being the rows up from that pixel."""
        p = self.p
        h, w = self.shape
        idx = self.pixels(s)
        rows, cols = np.divmod(idx, w)
        ref_ok = self.known[idx] & ~self.things[idx]
        top = np.full(w, h, np.intp)
        np.minimum.at(top, cols[ref_ok], rows[ref_ok])
        top[~self._column_is_vertical(s, top)] = h
        above = (top[cols] < h) & (rows < top[cols]) & ((self.rays[idx] @ self.up) > 0)
        empty = above & self.fillable[idx] & (self.depth[idx] == 0) & ~self.things[idx] & ~self.sky_like[idx]
        if not empty.any():
            return
        px, col = idx[empty], cols[empty]
        ref = top[col] * w + col
        point = self.rays[ref] * self.depth[ref, None]
        normal = self.horizontal(point)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
        offset = -np.einsum("ij,ij->i", normal, point)
        z, ok = self.intersect(self.rays[px], normal, offset, self.ray_norm[px])
        px, ref, z, normal, offset = px[ok], ref[ok], z[ok], normal[ok], offset[ok]
        dist = (ref // w - px // w).astype(np.float32)
        conf = np.minimum(p.wall_confidence, self.conf[ref]) * np.exp(
            -dist / (p.conf_distance_ref_px * self.scale)
        )
        self.depth[px], self.conf[px], self.origin[px] = z, conf, ORIGIN["vertical"]
        self.plane_normal[px], self.plane_offset[px], self.fill_dist[px] = normal, offset, dist

    def climb_through(self, walled: Mask, todo: Mask) -> None:
        """The columns step 6d climbed go on up (after step 7): from each pixel of ``walled``, the
        empty pixels straight above it take its plane while they belong to segments step 7 could
        climb into (of ``todo``, not seen by the LiDAR, without things, neither green nor blue, not
        ground or vegetation), lie above the horizon and are not sky; the first pixel that is not
        ends the column's climb. Confidence: the walled pixel's times ``upward_confidence``, and
        ``exp(-d / d0)`` of the rows climbed beyond it."""
        p = self.p
        h, w = self.shape
        assert self.sky is not None  # the wall step runs only with sky labels
        unseen = self.unseen_facade_parts(todo) & ~(self.ground | self.vegetation)
        open_px = (
            unseen[self.flat] & self.fillable & (self.depth == 0) & ~self.sky & ~self.things & ~self.sky_like
        )
        open_px = (open_px & ((self.rays @ self.up) > 0)).reshape(h, w)
        walled = walled.reshape(h, w)
        # Row by row upward, each column carrying the plane, distance and confidence it climbs with.
        per_row = np.float32(np.exp(-1.0 / (p.conf_distance_ref_px * self.scale)))
        active = np.zeros(w, bool)
        normal, offset = np.zeros((w, 3), np.float32), np.zeros(w, np.float32)
        dist, conf = np.zeros(w, np.float32), np.zeros(w, np.float32)
        taken: list[tuple[NDArray[np.intp], NDArray[np.float32], NDArray[np.float32], F32, F32]] = []
        for r in range(h - 1, -1, -1):
            here = np.arange(r * w, (r + 1) * w)
            start = walled[r]
            normal[start], offset[start] = self.plane_normal[here[start]], self.plane_offset[here[start]]
            dist[start], conf[start] = (
                self.fill_dist[here[start]],
                self.conf[here[start]] * p.upward_confidence,
            )
            go_on = active & ~start & open_px[r]
            if go_on.any():
                cols = np.flatnonzero(go_on)
                dist[cols] += 1
                conf[cols] *= per_row
                taken.append(
                    (
                        r * w + cols,
                        normal[cols].copy(),
                        offset[cols].copy(),
                        dist[cols].copy(),
                        conf[cols].copy(),
                    )
                )
            active = start | go_on
        if not taken:
            return
        px, n, o, d, c = (np.concatenate(parts) for parts in zip(*taken, strict=True))
        z, ok = self.intersect(self.rays[px], n.astype(np.float64), o.astype(np.float64), self.ray_norm[px])
        px, z, n, o, d, c = px[ok], z[ok], n[ok], o[ok], d[ok], c[ok]
        self.depth[px], self.conf[px], self.origin[px] = z, c, ORIGIN["vertical"]
        self.plane_normal[px], self.plane_offset[px], self.fill_dist[px] = n, o, d

    def _column_is_vertical(self, s: int, top: NDArray[np.intp]) -> Mask:
        """(W,) whether the known pixels of segment ``s`` in each column stand upright below its
        topmost one ``top`` (``h``: none): the known pixel ``wall_min_height_m`` lower (the first
        at or below the row that height takes at its depth) lies at the same horizontal distance
        within ``inlier_tol_m + inlier_tol_rel * z`` (a rounded body is upright at its widest
        only). A column whose known pixels span less height stands if most of the segment's
        columns that could be checked do."""
        p = self.p
        h, w = self.shape
        out = np.zeros(w, bool)
        cols = np.flatnonzero(top < h)
        if len(cols) == 0:
            return out
        # The first known pixel at or below each probe row: a search over (column, row) keys.
        idx = self.pixels(s)
        idx = idx[self.known[idx] & ~self.things[idx]]
        keys = np.sort((idx % w) * h + idx // w)
        ref = top[cols] * w + cols
        z_ref = self.depth[ref]
        step = np.ceil(p.wall_min_height_m * self.scale * REFERENCE_FOCAL_PX / z_ref).astype(np.intp)
        at = np.searchsorted(keys, cols * h + top[cols] + np.maximum(step, 1))
        found = keys[np.minimum(at, len(keys) - 1)]
        has = (at < len(keys)) & (found // h == cols)
        probe_px = (found % h) * w + cols

        def distance(px: NDArray[np.intp]) -> F64:
            return np.linalg.norm(self.horizontal(self.rays[px] * self.depth[px, None]), axis=1)

        tol = p.inlier_tol_m + p.inlier_tol_rel * z_ref
        upright = np.abs(distance(ref) - distance(probe_px)) <= tol
        # A column too short to check stands if most of the segment's checked columns do.
        wall = bool(has.any()) and float(upright[has].mean()) >= 0.5
        out[cols] = np.where(has, upright, wall)
        return out

    # -- thin vertical structures ------------------------------------------------------------

    def fill_thin(self, s: int) -> None:
        """A thin vertical segment: the vertical plane facing the camera through its base (step 6),
        if its evidence shows an upright structure (depths that agree and rise ``min_height_m``; a
        strip of ground does neither)."""
        p = self.p
        idx = self.pixels(s)
        kn = idx[self.thin_depth[idx] > 0]
        empty = idx[self.fillable[idx] & (self.depth[idx] == 0)]
        if len(empty) == 0:
            return
        w = self.shape[1]
        z = self.thin_depth[kn]
        tol = p.inlier_tol_m + p.inlier_tol_rel * float(np.median(z))
        if float(np.median(np.abs(z - np.median(z)))) > tol:
            return
        height = np.sort((self.rays[kn] * z[:, None]) @ self.up)
        if height[-1 - len(height) // 20] - height[len(height) // 20] < p.min_height_m:  # 95th - 5th
            return
        rows = kn // w
        base = kn[rows >= rows.max() - p.base_band_ref_px * self.scale]
        z_base = float(np.median(self.thin_depth[base]))
        spread = float(np.median(np.abs(self.thin_depth[base] - z_base)))
        point = self.rays[base].mean(axis=0) * z_base
        facing = self.horizontal(point)  # horizontal direction to the base
        norm = float(np.linalg.norm(facing))
        on = np.abs(z - z_base) <= tol
        # The low-confidence sparse depths alone, where foreground and background leak, do not do.
        if norm < 1e-6 or spread > tol or np.count_nonzero(on & self.known[kn]) < p.min_thin_trusted:
            return
        n = facing / norm
        fits = PlaneFits(
            *(n[None], np.array([-float(n @ point)]), np.ones(1, np.int8), np.array([spread])),
            *(np.ones(1), np.array([z_base]), np.array([float(np.mean(self.thin_conf[base]))])),
            np.zeros(1, bool),
        )
        # Only the columns that hold the structure: those of its evidence (+-1 pixel).
        allowed = np.zeros(w + 2, bool)
        cols = kn[on] % w + 1
        allowed[cols - 1] = allowed[cols] = allowed[cols + 1] = True
        empty = empty[allowed[empty % w + 1]]
        dist = np.maximum(rows[on].min() - empty // w, 0).astype(np.float32)  # rows above the evidence
        self._fill(empty, fits, 0, dist, 1.0, ORIGIN["vertical"], cap=p.vertical_confidence)

    def fill_crown(self, s: int, max_spread: float | None = None) -> None:
        """A green segment no plane explains (a tree's crown) with enough dense depth of about one
        depth (``crown_max_spread``: the spread of its known depths relative to their median)
        takes the vertical plane facing the camera through its known points' median, at
        ``crown_confidence`` at most (origin ``vertical``); with ``max_spread``, a vehicle's
        segment (6c)."""
        rs, cs = self.crop(s)
        self.fill_facing(self.pixels(s), rs, cs, self.segments[rs, cs] == s, max_spread)

    def fill_canopies(self, segs: Mask) -> None:
        """A tree's crown is many small green segments, most above the LiDAR's top beam: each
        connected region of the pixels above the horizon (and not blue) of the segments ``segs``
        (green, without things) is filled as one crown (:meth:`fill_facing`) from the depths its
        lower part holds."""
        # Not the sky a segment took in at the crown's rim: no pixel of excess blue, nor its
        # neighbours.
        mask = segs[self.flat] & ((self.rays @ self.up) > 0) & ~self.sky_rim
        count, comp = cv2.connectedComponents(mask.reshape(self.shape).view(np.uint8), connectivity=4)
        if count <= 1:
            return
        flat = comp.reshape(-1)
        order = np.argsort(flat, kind="stable")
        starts = np.searchsorted(flat[order], np.arange(count + 1))
        w = self.shape[1]
        for c in range(1, count):
            px = order[starts[c] : starts[c + 1]]
            if not np.any(self.fillable[px] & (self.depth[px] == 0)):
                continue
            r, q = np.divmod(px, w)
            rs, cs = slice(int(r.min()), int(r.max()) + 1), slice(int(q.min()), int(q.max()) + 1)
            # A few known pixels in a large region are as often a facade's a segment took in, or
            # depth seen through the leaves, as the crown's.
            if np.count_nonzero(self.known[px]) >= self.p.canopy_min_known_share * len(px):
                self.fill_facing(px, rs, cs, comp[rs, cs] == c)

    def fill_facing(
        self, px: NDArray[np.intp], rs: slice, cs: slice, member: Mask, max_spread: float | None = None
    ) -> None:
        """Fills the empty pixels ``px`` (flat indices; ``member``: the same within the crop
        ``rs, cs``) with the vertical plane facing the camera through the median of their known
        points, if they are enough (``min_inliers``) and of about one depth (``max_spread``, by
        default ``crown_max_spread``), at ``crown_confidence`` at most (origin ``vertical``)."""
        p = self.p
        kn = px[self.known[px]]
        if len(kn) < p.min_inliers:
            return
        z = self.depth[kn]
        z_mid = float(np.median(z))
        q25, q75 = np.percentile(z, [25, 75])
        if (q75 - q25) > (p.crown_max_spread if max_spread is None else max_spread) * z_mid:
            return
        point = np.median(self.rays[kn] * z[:, None], axis=0)
        facing = self.horizontal(point)
        norm = float(np.linalg.norm(facing))
        if norm < 1e-6:
            return
        n = facing / norm
        spread = float(q75 - q25)
        fits = PlaneFits(
            *(n[None], np.array([-float(n @ point)]), np.ones(1, np.int8), np.array([spread])),
            *(np.ones(1), np.array([z_mid]), np.array([float(np.mean(self.conf[kn]))])),
            np.zeros(1, bool),
        )
        empty = px[self.fillable[px] & (self.depth[px] == 0) & ~self.sky_rim[px]]
        w = self.shape[1]
        dist_map, _ = _nearest_pixel(self.known.reshape(self.shape)[rs, cs] & member)
        er, ec = np.divmod(empty, w)
        dist = dist_map[er - rs.start, ec - cs.start]
        keep = dist <= p.max_extrapolation_ref_px * self.scale
        self._fill(empty[keep], fits, 0, dist[keep], 1.0, ORIGIN["vertical"], cap=p.crown_confidence)

    # -- shared ------------------------------------------------------------------------------

    def intersect(self, rays: F64, normal: F64, offset: F64, ray_norm: F64 | None = None) -> tuple[F64, Mask]:
        """Depths where (P, 3) rays (z = 1) meet planes (P, 3) / (P,) or one plane (3,) / (), and
        whether each is valid: finite, in ``(min_depth_m, max_depth_m]`` and at an incidence of at
        least ``min_incidence_deg``. ``ray_norm``: the rays' (P,) lengths, if known."""
        denom = rays @ normal if normal.ndim == 1 else np.einsum("ij,ij->i", rays, normal)
        if ray_norm is None:
            ray_norm = np.linalg.norm(rays, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = -offset / denom
            sin_incidence = np.abs(denom) / ray_norm
        ok = np.isfinite(z) & (z > self.p.min_depth_m) & (z <= self.p.max_depth_m)
        ok &= sin_incidence >= np.sin(np.radians(self.p.min_incidence_deg))
        return z, ok

    def _fill(
        self,
        pixels: NDArray[np.intp],
        fits: PlaneFits,
        s: int,
        dist: F32,
        factor: float,
        code: int,
        cap: float | None = None,
    ) -> None:
        """Fills ``pixels`` with plane ``s`` of ``fits`` (where valid), with the confidence of the
        module docstring (``dist``: each pixel's distance to the data)."""
        if len(pixels) == 0:
            return
        normal, offset = fits.normal[s], float(fits.offset[s])
        z, ok = self.intersect(self.rays[pixels], normal, offset, self.ray_norm[pixels])
        if not ok.any():
            return
        pixels, z, dist = pixels[ok], z[ok], dist[ok]
        sin_incidence = np.abs(self.rays[pixels] @ normal) / self.ray_norm[pixels]
        rel = fits.rms_m[s] / (max(fits.depth_m[s], 1e-6) * self.p.conf_relative_residual)
        cap = self.p.max_confidence if cap is None else cap
        conf = (
            min(cap, fits.confidence[s])
            * factor
            * fits.share[s]
            * np.exp(-(rel**2))
            * np.exp(-dist / (self.p.conf_distance_ref_px * self.scale))
            * np.minimum(1.0, sin_incidence / _SIN_GOOD_INCIDENCE)
        )
        self.depth[pixels] = z
        self.conf[pixels] = conf
        self.origin[pixels] = code
        self.plane_normal[pixels] = normal
        self.plane_offset[pixels] = offset
        self.fill_dist[pixels] = dist


def _nearest_pixel(sources: Mask) -> tuple[F32, NDArray[np.intp]]:
    """Distance (pixels) to, and flat index of, the nearest ``True`` pixel of the (h, w)
    ``sources`` from every pixel (approximate Euclidean, 3x3 mask); none: infinity."""
    if not sources.any():
        return np.full(sources.shape, np.inf, np.float32), np.zeros(sources.shape, np.intp)
    dist, labels = cv2.distanceTransformWithLabels(
        (~sources).view(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    lut = np.zeros(int(labels.max()) + 1, np.intp)
    lut[labels[sources]] = np.flatnonzero(sources)
    return dist, lut[labels]


def _majority_never_filled(flat: NDArray[np.int32], classes: NDArray[np.uint8], count: int) -> Mask:
    """(S,) whether the most frequent label of each segment (among its labelled pixels) is in
    :data:`NEVER_FILLED_CLASSES`."""
    return _majority_in(flat, classes, count, NEVER_FILLED_CLASSES)


def _majority_in(
    flat: NDArray[np.int32], classes: NDArray[np.uint8], count: int, ids: frozenset[int]
) -> Mask:
    """(S,) whether the most frequent label of each segment (among its labelled pixels) is in
    ``ids`` and labels at least a quarter of its pixels (the few labelled pixels of a facade that a
    person in front of it has merged into its segment do not make it a person)."""
    labelled = classes != tx.IGNORE_ID
    if not labelled.any():
        return np.zeros(count, bool)
    votes = np.zeros((count, 256), np.int64)
    np.add.at(votes, (flat[labelled], classes[labelled]), 1)
    sizes = np.bincount(flat, minlength=count)
    return np.isin(votes.argmax(axis=1), list(ids)) & (votes.max(axis=1) >= 0.25 * np.maximum(sizes, 1))


# --------------------------------------------------------------------------------------------
# The stage


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
