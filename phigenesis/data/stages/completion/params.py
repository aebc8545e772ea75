"""The completion's parameters (:class:`CompletionParams`, the ``complete_depth`` stage's YAML
keys), its result (:class:`CompletionResult`) and the constants its modules share: origin codes,
plane kinds, the label sets that decide what is filled, and the parameters' bounds.

Conventions: :mod:`phigenesis.data.stages.complete` (the algorithm, step by step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from phigenesis import taxonomy as tx
from phigenesis.data.records import DENSE_ORIGINS
from phigenesis.options import ConfigError, check_options, from_mapping, option

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
            the plane through it their label implies (complete.py's docstring, step 2).
        min_line_m: least length of such a line of ground points.
        line_confidence: confidence factor of those segments' pixels.
        crowns: fill green segments no plane explains at one depth (complete.py's docstring, 6b).
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
        conf_distance_ref_px: ``d0`` of the confidence (complete.py's docstring).
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
