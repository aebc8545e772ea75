"""Parameters of the depth projection and the constants its steps share.

The stage is :mod:`phigenesis.data.stages.project`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from phigenesis import taxonomy as tx
from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported
from phigenesis.data.records import (
    DEPTH_ORIGINS,
)
from phigenesis.options import ConfigError, check_options, from_mapping, option

Visibility = Literal["splat", "local_min", "none"]
Estimator = Literal["plane", "nearest_centre"]
MixedPixels = Literal["drop", "keep"]
ORIGIN_WEIGHT = {"static_map": 1.0, "single_sweep": 1.0, "non_rigid_object": 0.9, "rigid_object": 0.8}
ORIGIN_CODE = {name: i for i, name in enumerate(DEPTH_ORIGINS)}
#: ORIGIN_WEIGHT indexed by origin code (0 for "none").
ORIGIN_WEIGHTS = np.array([ORIGIN_WEIGHT.get(name, 0.0) for name in DEPTH_ORIGINS], np.float32)
#: Classes whose boxes are solid enough to hide what lies behind them.
VEHICLE_IDS = frozenset({tx.CAR, tx.TRUCK, tx.BUS, tx.TRAIN})
#: People are far from box-shaped: only their core (this share of length and width) occludes.
PERSON_IDS = frozenset({tx.PERSON, tx.RIDER})


@dataclass(frozen=True)
class ProjectParams:
    """Parameters of the projection (lengths in metres).

    Attributes:
        visibility: "splat", "local_min" or "none" (see the module docstring).
        tau: relative depth tolerance of the visibility test and of agreeing points.
        slack_m: absolute depth tolerance of the splat test.
        window: neighbourhood size of ``local_min`` (pixels, odd).
        splat_scale: a point's disc has radius ``splat_scale * f * spacing / z`` pixels: 0.5
            would make touching discs on a square grid, which leaves gaps at the corners;
            0.75 covers a grid of voxel centroids.
        max_splat_px: cap on a splat's radius in pixels.
        max_range_m: points farther than this from the camera are not projected.
        min_depth_m: points nearer than this (z) are not projected.
        sweep_spacing_rad: angular footprint of a single sweep's points; None: the LiDAR's
            measured angular step (:func:`aggregate.lidar_angular_step`).
        object_spacing_m: footprint of object model points.
        elevation_margin_deg: map points up to this much above the LiDAR's highest return
            elevation (seen from the current sensor position) count as inside its field.
        top_band_deg, top_bin_deg: the band below that limit whose surfaces decide, per azimuth
            bin of this width, which map points above the field are kept (:func:`seen_past_lidar_top`).
        vehicle_occluders: moving vehicles' boxes (shrunk by ``occluder_shrink``, their bottom
            raised by ``occluder_clearance_m``) and moving people's box cores (``person_core``
            of their length and width) hide whatever lies beyond their far side.
        supersample: the visibility test and z-buffer run on a grid this many times finer than
            the image (odd; 1 = the image's own pixels); None: 3 for images up to 640 pixels
            wide, where a pixel holds several map points, else 1.
        max_offset_px: a pixel takes the depth of a visible point at most this far from its
            centre (in pixels, on the fine grid; 0.71 reaches the corners).
        estimator: how a pixel's depth comes from the visible points that fall in it:
            "plane" fits inverse depth as an affine function of the sub-pixel position (exact for
            a planar surface under a pinhole) to pixels holding at least ``plane_min_points``
            spread-out points and evaluates it at the pixel centre, averaging the LiDAR's range
            noise; other pixels, and every pixel with "nearest_centre", take the visible point
            nearest the centre (``max_offset_px``).
        fit_window_px: the plane is fitted to the points of the pixel's ``(2 r + 1)^2`` window
            where they lie on one plane (more points average more noise; 0: the pixel's own).
        fit_tolerance_m, fit_tolerance_rel: a pixel is mixed (it straddles a depth edge: a pole's
            side, a roof line) if one of its points lies farther than ``fit_tolerance_m +
            fit_tolerance_rel * z`` from the fitted plane, or, with too few points for a fit,
            from the nearest one.
        mixed_pixels: "drop" leaves mixed pixels unknown (the densifier fills them from the
            image's edges); "keep" gives them the point nearest the centre at half confidence.
        edge_band_px, edge_confidence: pixels this close (Chebyshev distance) to a depth edge of
            the sparse map (a neighbour nearer or farther by more than ``edge_tolerance_rel * z +
            edge_tolerance_m``) keep their depth at ``edge_confidence`` times their confidence,
            below ``records.TRUSTED_DEPTH_CONFIDENCE``: a silhouette's pixel centres fall on
            either surface, and whether a point landing near one belongs to it is a guess (most
            are right, but they hold most of the large errors; a thin pole is all edge). 0: no
            band. The near side of an edge counts only where at least ``edge_min_share`` of the
            known pixels around are on its far side (:func:`depth_edge_band`), so a lone
            background leak does not mark the surface around it; ``edge_near_band_px`` (default
            ``edge_band_px``) is the near side's band.
        image_edge_threshold: pixels on the rim of the known region that sit on a strong image
            edge (:func:`silhouette_pixels`) get ``edge_confidence`` too; None turns it off.
        thin, thin_points_per_cell: far map tiles contribute a uniform subset of their points,
            about this many per cell of the visibility grid (:func:`thinning_strides`; the plane
            fits need several per pixel).
        max_points_per_pixel: on the image's own grid (``supersample`` 1), a pixel holding more
            points keeps those in its front band (the splat test's bound over its nearest point,
            which no other could pass) and, of these, a uniform subset of about this many
            (:func:`thin_in_pixels`): a long segment's map saturates its 2 cm voxels, and at a
            grazing angle a far pixel of road holds hundreds. 0: no cap.
        threads: cameras projected in parallel threads (1: one after the other).
        use_map: project the aggregated map when the scene has one (False: own sweep only).
    """

    visibility: Visibility = option("splat")
    tau: float = option(0.05, ge=0, le=10)
    slack_m: float = option(0.1, ge=0, le=100)
    window: int = option(7, ge=1, le=255)
    splat_scale: float = option(0.75, ge=0, le=100)
    max_splat_px: int = option(12, ge=0, le=10_000)
    max_range_m: float = option(120.0, gt=0, le=1000)
    min_depth_m: float = option(0.5, ge=0, le=1000)
    sweep_spacing_rad: float | None = option(None, gt=0, le=1)
    object_spacing_m: float = option(0.02, ge=0, le=10)
    elevation_margin_deg: float = option(0.5, ge=-90, le=90)
    top_band_deg: float = option(1.5, ge=0, le=90)
    top_bin_deg: float = option(0.5, gt=0, le=90)
    vehicle_occluders: bool = option(True)
    occluder_shrink: float = option(0.9, gt=0, le=10)
    occluder_clearance_m: float = option(0.35, ge=0, le=100)
    person_core: float = option(0.8, ge=0, le=1)
    supersample: int | None = option(None, ge=1, le=15)
    max_offset_px: float = option(1.0, ge=0, le=100)
    estimator: Estimator = option("plane")
    plane_min_points: int = option(4, ge=3, le=10_000)
    fit_window_px: int = option(2, ge=0, le=100)
    window_tolerance_m: float = option(0.05, ge=0, le=100)
    window_tolerance_rel: float = option(0.005, ge=0, le=10)
    fit_tolerance_m: float = option(0.1, ge=0, le=100)
    fit_tolerance_rel: float = option(0.01, ge=0, le=10)
    mixed_pixels: MixedPixels = option("drop")
    edge_band_px: int = option(4, ge=0, le=1000)
    edge_tolerance_rel: float = option(0.1, ge=0, le=10)
    edge_tolerance_m: float = option(0.3, ge=0, le=100)
    edge_min_share: float = option(0.05, ge=0, le=1)
    edge_near_band_px: int | None = option(None, ge=0, le=1000)
    edge_confidence: float = option(0.25, ge=0, le=1)
    image_edge_threshold: float | None = option(150.0, ge=0, le=10_000)
    thin: bool = option(True)
    threads: int = option(2, ge=1, le=256)
    thin_points_per_cell: float = option(9.0, gt=0, le=10_000)
    max_points_per_pixel: int = option(8, ge=0, le=1_000_000)
    use_map: bool = option(True)

    def __post_init__(self) -> None:
        check_options(self, "ProjectParams")
        if self.supersample is not None and self.supersample % 2 == 0:
            raise ConfigError(f"ProjectParams: supersample = {self.supersample}: must be odd")
        if self.window % 2 == 0:
            raise ConfigError(f"ProjectParams: window = {self.window}: must be odd")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ProjectParams:
        return from_mapping(cls, values, "project_depth")


def supersample_of(params: ProjectParams, width: int) -> int:
    """The visibility grid's refinement for an image ``width`` pixels wide."""
    return params.supersample or (3 if width <= 640 else 1)


def _cap_of(params: ProjectParams, width: int) -> int:
    """The per-pixel cap in force (0: none): only on the image's own grid."""
    return params.max_points_per_pixel if supersample_of(params, width) == 1 else 0
