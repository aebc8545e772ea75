"""Per-pixel depth from the visible points: the sub-pixel plane fits and the nearest-centre
choice, with the numpy references the native kernel is tested against.

The stage is :mod:`phigenesis.data.stages.project`."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported
from phigenesis.data.native import load_plane_fits
from phigenesis.data.stages.projection.params import ProjectParams


def _pixel_index(uv: NDArray[np.float64], scale: int, width: int, height: int) -> NDArray[np.int64]:
    """Flat index of the pixel holding each (u, v) on a grid ``scale`` times finer than the image."""
    col = np.clip(np.rint((uv[:, 0] + 0.5) * scale - 0.5), 0, width - 1).astype(np.int64)
    row = np.clip(np.rint((uv[:, 1] + 0.5) * scale - 0.5), 0, height - 1).astype(np.int64)
    return row * width + col


def _centre_first(fine_depth: NDArray[np.float32], max_offset_px: float = 1.0) -> NDArray[np.int64]:
    """For (H, s, W, s) sub-pixel depths (inf = empty), the (H, W) flat fine index of the filled
    sub-pixel nearest each pixel's centre (no farther than ``max_offset_px`` pixels from it),
    -1 where there is none."""
    h, ss, w, _ = fine_depth.shape
    centre = (ss - 1) / 2
    offsets = [
        (i, j)
        for i in range(ss)
        for j in range(ss)
        if np.hypot(i - centre, j - centre) <= max_offset_px * ss + 1e-9
    ]
    offsets.sort(key=lambda o: (o[0] - centre) ** 2 + (o[1] - centre) ** 2)
    rows = np.arange(h)[:, None] * ss
    cols = np.arange(w)[None, :] * ss
    chosen = np.full((h, w), -1, np.int64)
    for i, j in offsets:
        take = (chosen < 0) & np.isfinite(fine_depth[:, i, :, j])
        chosen[take] = ((rows + i) * (w * ss) + cols + j)[take]
    return chosen


@dataclass
class PixelFit:
    """Per-pixel result of :func:`fit_pixels` (flat arrays over the image's pixels).

    Attributes:
        depth_m: (P,) float64 depth at the pixel centre from a plane fit, NaN where none fits.
        count: (P,) int64 visible points in the pixel itself.
        mixed: (P,) bool: the pixel's own points do not lie on one surface.
    """

    depth_m: NDArray[np.float64]
    count: NDArray[np.int64]
    mixed: NDArray[np.bool_]


#: Moments of a pixel's points: n, sums of du, dv, du², dv², du dv, y, du y, dv y, y².
MOMENT_NAMES = ("n", "u", "v", "uu", "vv", "uv", "y", "uy", "vy", "yy")


def moments(
    pixel: NDArray[np.int64],
    du: NDArray[np.float64],
    dv: NDArray[np.float64],
    y: NDArray[np.float64],
    size: int,
) -> dict[str, NDArray[np.float64]]:
    """Per-pixel sums (:data:`MOMENT_NAMES`) over points in pixel ``pixel`` (flat index, ``size``
    pixels) at offsets ``du``, ``dv`` from its centre (pixels) with inverse depth ``y`` (1/m)."""
    values = {
        "n": None,
        "u": du,
        "v": dv,
        "uu": du * du,
        "vv": dv * dv,
        "uv": du * dv,
        "y": y,
        "uy": du * y,
        "vy": dv * y,
        "yy": y * y,
    }
    return {k: np.bincount(pixel, weights=v, minlength=size).astype(np.float64) for k, v in values.items()}


def window_moments(m: dict[str, NDArray[np.float64]], shape: tuple[int, int], radius: int) -> dict:
    """Moments of the points in each pixel's (2r+1)^2 window, offsets taken from that pixel's
    centre. A neighbour at offset (dx, dy) contributes its moments shifted by it (du -> du + dx,
    ...), so each window moment is a sum of separable correlations of the per-pixel moments."""
    h, w = shape
    ones = np.ones(2 * radius + 1)
    ramp = np.arange(-radius, radius + 1, dtype=np.float64)

    def corr(name: str, kx: NDArray[np.float64], ky: NDArray[np.float64]) -> NDArray[np.float64]:
        src = m[name].reshape(h, w)
        return cv2.sepFilter2D(src, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT).reshape(-1)

    box = {k: corr(k, ones, ones) for k in MOMENT_NAMES}
    return {
        "n": box["n"],
        "u": box["u"] + corr("n", ramp, ones),
        "v": box["v"] + corr("n", ones, ramp),
        "uu": box["uu"] + 2 * corr("u", ramp, ones) + corr("n", ramp**2, ones),
        "vv": box["vv"] + 2 * corr("v", ones, ramp) + corr("n", ones, ramp**2),
        "uv": box["uv"] + corr("v", ramp, ones) + corr("u", ones, ramp) + corr("n", ramp, ramp),
        "y": box["y"],
        "uy": box["uy"] + corr("y", ramp, ones),
        "vy": box["vy"] + corr("y", ones, ramp),
        "yy": box["yy"],
    }


def _plane_at_centre(m: dict, min_points: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Least-squares ``y = a + b du + c dv`` from moments: (a, b, c, rms residual of y); a is NaN
    where there are too few points or they are not spread in both directions."""
    with np.errstate(divide="ignore", invalid="ignore"):
        n = m["n"]
        mu, mv, my = m["u"] / n, m["v"] / n, m["y"] / n
        cuu = m["uu"] / n - mu * mu
        cvv = m["vv"] / n - mv * mv
        cuv = m["uv"] / n - mu * mv
        cuy = m["uy"] / n - mu * my
        cvy = m["vy"] / n - mv * my
        cyy = m["yy"] / n - my * my
        det = cuu * cvv - cuv * cuv
        # Points spread over at least ~a fifth of a pixel in both directions.
        ok = (n >= min_points) & (det > 1.6e-5)
        b = np.where(ok, (cvv * cuy - cuv * cvy) / det, 0.0)
        c = np.where(ok, (cuu * cvy - cuv * cuy) / det, 0.0)
        a = np.where(ok, my - b * mu - c * mv, np.nan)
        rms = np.sqrt(np.maximum(cyy - b * cuy - c * cvy, 0.0))
    return a, b, c, rms


def occupied_window_moments(
    occupied: NDArray[np.int64], own: NDArray[np.float64], shape: tuple[int, int], radius: int
) -> NDArray[np.float64]:
    """(K, 10) moments (:data:`MOMENT_NAMES` order) of the ``(2r+1)^2`` window of each occupied
    pixel, offsets taken from that pixel's centre: :func:`window_moments` evaluated only at the
    ``occupied`` pixels (sorted flat indices; ``own`` their (K, 10) per-pixel moments).

    Only occupied pixels contribute to a window and only their windows are used, so this is the
    same sum over at most (2r+1)^2 neighbours per occupied pixel (found by binary search), not
    ten whole-image filters: about 1 % of a full-size image's pixels hold a point."""
    h, w = shape
    k = len(occupied)
    out = np.zeros((k, len(MOMENT_NAMES)))
    if k == 0:
        return out
    row, col = occupied // w, occupied % w
    n, u, v, uu, vv, uv, y, uy, vy, yy = own.T
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            inside = (col + dx >= 0) & (col + dx < w) & (row + dy >= 0) & (row + dy < h)
            target = occupied + dy * w + dx
            j = np.minimum(np.searchsorted(occupied, target), k - 1)
            at = np.flatnonzero(inside & (occupied[j] == target))
            if at.size == 0:
                continue
            nb = j[at]
            # A neighbour at (dx, dy) has offsets du + dx, dv + dy from this pixel's centre.
            out[at] += np.stack(
                [
                    n[nb],
                    u[nb] + dx * n[nb],
                    v[nb] + dy * n[nb],
                    uu[nb] + 2 * dx * u[nb] + dx * dx * n[nb],
                    vv[nb] + 2 * dy * v[nb] + dy * dy * n[nb],
                    uv[nb] + dx * v[nb] + dy * u[nb] + dx * dy * n[nb],
                    y[nb],
                    uy[nb] + dx * y[nb],
                    vy[nb] + dy * y[nb],
                    yy[nb],
                ],
                axis=1,
            )
    return out


def fit_pixels(
    pixel: NDArray[np.int64],
    uv: NDArray[np.float64],
    z: NDArray[np.floating],
    shape: tuple[int, int],
    reference_m: NDArray[np.floating],
    params: ProjectParams,
) -> PixelFit:
    """Depth at each pixel centre from the visible points (image pixel ``pixel``, position
    ``uv``, depth ``z``): ``1/z = a + b du + c dv`` (du, dv: offset from the centre, pixels)
    fitted to the points of the pixel's ``(2 fit_window_px + 1)^2`` window where they lie on
    one plane (RMS residual within ``fit_tolerance``/2), else to the pixel's own points. The
    pixel is mixed if one of its own points lies farther than the tolerance from its own
    fit or, with too few points for one, from ``reference_m`` (the point nearest its centre).

    The moments and fits are computed for the occupied pixels only, by the native kernel
    (:func:`~phigenesis.data.native.load_plane_fits`: the same arithmetic in the same order, so
    the same doubles, in a few passes) where it is built, else with numpy
    (:func:`fit_occupied_numpy`); :func:`fit_pixels_reference` is the same on whole-image maps
    (equal to rounding: the sums are taken in another order)."""
    h, w = shape
    size = h * w
    kernel = load_plane_fits()
    if kernel is not None and len(pixel):
        occupied, depth, count_k, mixed = kernel(
            pixel,
            uv,
            np.asarray(z, np.float32),
            shape,
            np.asarray(reference_m, np.float32),
            params.plane_min_points,
            (params.fit_tolerance_m, params.fit_tolerance_rel),
            params.fit_window_px,
            (params.window_tolerance_m, params.window_tolerance_rel),
        )
    else:
        occupied, depth, count_k, mixed = fit_occupied_numpy(pixel, uv, z, shape, reference_m, params)
    depth_full = np.full(size, np.nan)
    depth_full[occupied] = depth
    count_full = np.zeros(size, np.int64)
    count_full[occupied] = count_k
    mixed_full = np.zeros(size, bool)
    mixed_full[occupied] = mixed
    return PixelFit(depth_full, count_full, mixed_full)


def fit_occupied_numpy(
    pixel: NDArray[np.int64],
    uv: NDArray[np.float64],
    z: NDArray[np.floating],
    shape: tuple[int, int],
    reference_m: NDArray[np.floating],
    params: ProjectParams,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_]]:
    """:func:`fit_pixels` on the occupied pixels with numpy (the native kernel's fallback and
    reference): their sorted flat indices (K,), depth at the centre (K,) float64 (NaN: no fit),
    point count (K,) int64 and mixed flag (K,) bool."""
    w = shape[1]
    z = np.asarray(z, np.float64)
    du = uv[:, 0] - pixel % w
    dv = uv[:, 1] - pixel // w
    y = 1.0 / z
    occupied, inverse = np.unique(pixel, return_inverse=True)
    k = len(occupied)
    values = (None, du, dv, du * du, dv * dv, du * dv, y, du * y, dv * y, y * y)
    sums = [np.bincount(inverse, weights=v, minlength=k) for v in values]
    own_k = np.stack(sums, axis=1).astype(np.float64)
    own = dict(zip(MOMENT_NAMES, own_k.T, strict=True))
    count_k = own["n"].astype(np.int64)
    a, b, c, _ = _plane_at_centre(own, params.plane_min_points)
    zmin = np.full(k, np.inf)
    zmax = np.zeros(k)
    np.minimum.at(zmin, inverse, z)
    np.maximum.at(zmax, inverse, z)
    reference = np.asarray(reference_m)[occupied]
    with np.errstate(divide="ignore", invalid="ignore"):
        # As in fit_pixels_reference: the centre's depth stays within the pixel's own depth range
        # widened by its span, and at least half the nearest point's depth.
        span = zmax - zmin
        depth = np.where(a > 0, np.clip(1.0 / a, np.maximum(zmin - span, 0.5 * zmin), zmax + span), np.nan)
        fitted = np.isfinite(a)[inverse]
        plane_z = 1.0 / (a[inverse] + b[inverse] * du + c[inverse] * dv)
        expected = np.where(fitted, plane_z, reference[inverse])
        deviation = np.nan_to_num(np.abs(z - expected), nan=np.inf)
    worst = np.zeros(k)
    np.maximum.at(worst, inverse, deviation)
    base = np.where(np.isfinite(depth), depth, reference)
    tolerance = params.fit_tolerance_m + params.fit_tolerance_rel * base
    mixed = worst > tolerance
    if params.fit_window_px > 0 and k:
        window = occupied_window_moments(occupied, own_k, shape, params.fit_window_px)
        window_fit = dict(zip(MOMENT_NAMES, window.T, strict=True))
        wa, _, _, rms = _plane_at_centre(window_fit, params.plane_min_points)
        with np.errstate(divide="ignore", invalid="ignore"):
            window_z = 1.0 / wa
            window_tolerance = params.window_tolerance_m + params.window_tolerance_rel * window_z
            good = np.isfinite(window_z) & (window_z > 0) & (rms * window_z**2 <= window_tolerance)
            good &= np.abs(window_z - base) <= tolerance
        depth = np.where(good, window_z, depth)
    return occupied, depth, count_k, mixed


def fit_pixels_reference(
    pixel: NDArray[np.int64],
    uv: NDArray[np.float64],
    z: NDArray[np.floating],
    shape: tuple[int, int],
    reference_m: NDArray[np.floating],
    params: ProjectParams,
) -> PixelFit:
    """The reference :func:`fit_pixels`: the same arithmetic on whole-image moment maps (ten
    (H * W) float64 maps, filtered over every row that holds a point). Kept for the tests.

    Depth at each pixel centre from the visible points (image pixel ``pixel``, position
    ``uv``, depth ``z``): ``1/z = a + b du + c dv`` (du, dv: offset from the centre, pixels)
    fitted to the points of the pixel's ``(2 fit_window_px + 1)^2`` window where they lie on
    one plane (RMS residual within ``fit_tolerance``/2), else to the pixel's own points. The
    pixel is mixed if one of its own points lies farther than the tolerance from its own
    fit or, with too few points for one, from ``reference_m`` (the point nearest its centre)."""
    h, w = shape
    size = h * w
    z = np.asarray(z, np.float64)
    du = uv[:, 0] - pixel % w
    dv = uv[:, 1] - pixel // w
    y = 1.0 / z
    own = moments(pixel, du, dv, y, size)
    count = own["n"].astype(np.int64)
    a, b, c, _ = _plane_at_centre(own, params.plane_min_points)
    zmin = np.full(size, np.inf)
    zmax = np.zeros(size)
    np.minimum.at(zmin, pixel, z)
    np.maximum.at(zmax, pixel, z)
    with np.errstate(divide="ignore", invalid="ignore"):
        # The extrapolation to the centre stays within the pixel's own depth range widened by its
        # span on either side (points in one corner of a planar pixel need up to that).
        # Half the nearest point's depth at least: a steep fit can extrapolate to a negative inverse
        # depth (points near 1 m and 100 m in one pixel), which is no depth at all.
        span = zmax - zmin
        depth = np.where(a > 0, np.clip(1.0 / a, np.maximum(zmin - span, 0.5 * zmin), zmax + span), np.nan)
        fitted = np.isfinite(a)[pixel]
        plane_z = 1.0 / (a[pixel] + b[pixel] * du + c[pixel] * dv)
        expected = np.where(fitted, plane_z, reference_m[pixel])
        deviation = np.nan_to_num(np.abs(z - expected), nan=np.inf)
    worst = np.zeros(size)
    np.maximum.at(worst, pixel, deviation)
    base = np.where(np.isfinite(depth), depth, reference_m)
    tolerance = params.fit_tolerance_m + params.fit_tolerance_rel * base
    mixed = (worst > tolerance) & (count > 0)
    if params.fit_window_px > 0 and len(pixel):
        # Only the rows that hold points (and the window's reach around them) are filtered: the
        # sky and whatever lies above the LiDAR's field stay out of the work.
        r = params.fit_window_px
        rows = pixel // w
        r0, r1 = max(int(rows.min()) - r, 0), min(int(rows.max()) + r + 1, h)
        band = {k: v[r0 * w : r1 * w] for k, v in own.items()}
        wa_band, _, _, rms_band = _plane_at_centre(
            window_moments(band, (r1 - r0, w), r), params.plane_min_points
        )
        wa, rms = np.full(size, np.nan), np.zeros(size)
        wa[r0 * w : r1 * w], rms[r0 * w : r1 * w] = wa_band, rms_band
        with np.errstate(divide="ignore", invalid="ignore"):
            window_z = 1.0 / wa
            window_tolerance = params.window_tolerance_m + params.window_tolerance_rel * window_z
            good = np.isfinite(window_z) & (window_z > 0) & (rms * window_z**2 <= window_tolerance)
            good &= count > 0
            good &= np.abs(window_z - np.where(np.isfinite(depth), depth, reference_m)) <= tolerance
        depth = np.where(good, window_z, depth)
    return PixelFit(depth, count, mixed)
