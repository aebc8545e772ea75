"""Pictures of a frame: its camera range view (RGB with boxes, depth, semantics) and a bird's-eye view.

Entry point: :func:`draw_frame`. The range view is the frame's views side by side in azimuth order
(:mod:`phigenesis.data.rangeview`); each row of the picture is that range view:

1. RGB, each camera's name in its top-left corner, views separated by a thin line, the frame's
   boxes drawn with their projected edges in every view that sees them (at the image's own time),
   and cells whose direction a neighbouring view owns (the overlap rule) dimmed;
2. depth (:data:`DEPTH_SOURCES`: the pipeline's dense depth, else its sparse depth, else exact
   truth) in the toolkit's depth colours (:func:`phigenesis.data.colormap.depth_color`: near red,
   far blue, unknown black);
3. semantics from the best source the frame has (:data:`SEMANTIC_SOURCES`: exact truth, else the
   dataset's human labels, else pseudo labels) in the taxonomy's palette.

Each of rows 2 and 3 names its source in its bottom-left corner; the dense depth's caption says what
its pixels are made of, from their origins (:func:`dense_caption`: the LiDAR's share, the
densifier's and the completion's, or the Gaussians a render or a rollout drew it from). Rows without
data are left out; cells no view covers are dark grey. A depth source with no known depth anywhere
(a frame without LiDAR: its depth maps are all 0) is not passed off as a black map: the next source
with depth is shown (exact truth, synthetic data), else the row is dark grey and captioned
:data:`NO_DEPTH_CAPTION` (or :data:`EMPTY_DEPTH_CAPTION` where the frame has LiDAR that reached no
image), without a colour bar. A top view of the LiDAR (greys by height) and the boxes, as tall as
the rows, is on the right, captioned. Below, the depth colour bar (in metres) and the legend of the
classes shown, each titled with its source. Captions are white text outlined in black by the same
glyphs shifted one pixel, so the outline stays within the text's own box (a thicker stroke advances
further and trails past the text).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.colormap import class_legend, classes_present, depth_color, depth_color_bar
from phigenesis.data.rangeview import (
    DepthSource,
    RangeView,
    SemanticSource,
    ViewPlacement,
    pack_range_view,
)
from phigenesis.data.records import DENSE_ORIGINS, Boxes, CameraImage, Frame

BEV_RANGE_M = 60.0
#: Range views taller than this are drawn shrunk to it (real datasets' 1280-pixel images).
MAX_CAMERA_HEIGHT_PX = 320
#: Colour of cells no view covers.
EMPTY_RGB = (48, 48, 48)
#: Brightness of cells whose direction another view owns.
OVERLAP_DIM = 0.6
#: Box edges are clipped to this depth in front of the camera (metres) before projection.
NEAR_M = 0.1

#: Depth maps the depth row shows, the first the frame has: what training uses, else exact truth.
DEPTH_SOURCES: tuple[DepthSource, ...] = ("dense", "sparse", "truth")
#: Label maps the semantics row shows, best first: exact truth (synthetic), the dataset's human
#: labels, the pipeline's pseudo labels (segmenter and geometry).
SEMANTIC_SOURCES: tuple[SemanticSource, ...] = ("truth", "labels", "pseudo")
#: How the picture names each source.
DEPTH_SOURCE_NAMES: dict[str, str] = {
    "dense": "depth: dense (LiDAR, densified)",
    "sparse": "depth: sparse (projected LiDAR)",
    "truth": "depth: exact truth",
}
#: The depth row's caption where no depth source has any depth and the frame has no LiDAR.
NO_DEPTH_CAPTION = "no depth (no LiDAR in this frame)"
#: ... and where the frame has LiDAR but no point reached an image.
EMPTY_DEPTH_CAPTION = "no depth (no LiDAR point in the images)"
#: Offsets (pixels) of the black copies of a caption that outline its white glyphs.
_OUTLINE = tuple((dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy)
SEMANTIC_SOURCE_NAMES: dict[str, str] = {
    "truth": "semantics: exact truth",
    "labels": "semantics: dataset labels",
    "pseudo": "semantics: pseudo labels",
}


def preview_range_view(frame: Frame) -> RangeView:
    """The frame's range view as :func:`draw_frame` draws it: depth from the first of
    :data:`DEPTH_SOURCES` that the frame has with some known depth (else the first it has at
    all, all unknown) and semantics from the first of :data:`SEMANTIC_SOURCES` that it has
    (``depth_source`` and ``semantic_source`` say which)."""
    rv = pack_range_view(frame, depth_sources=DEPTH_SOURCES, semantic_sources=SEMANTIC_SOURCES)
    if rv.depth_source is None or has_depth(rv.depth_m):
        return rv
    rest = DEPTH_SOURCES[DEPTH_SOURCES.index(rv.depth_source) + 1 :]
    for source in rest:
        other = pack_range_view(frame, rv.layout, depth_sources=(source,), semantic_sources=(), rgb=False)
        if other.depth_source is not None and has_depth(other.depth_m):
            return dataclasses.replace(rv, depth_m=other.depth_m, depth_source=other.depth_source)
    return rv


def has_depth(depth_m: NDArray[np.float32] | None) -> bool:
    """Whether a depth map (metres, 0 = unknown) has any known (positive, finite) depth."""
    return depth_m is not None and bool(np.any(np.isfinite(depth_m) & (depth_m > 0)))


#: What drew a cache's rendered depth, by the cache's source (its manifest's ``source``).
RENDERED_BY: dict[str, str] = {
    "rendered": "phigenesis-render's Gaussians",
    "generated": "the rollout's Gaussians (phigenesis-generate)",
}
#: How the dense depth's caption groups its pixels' origins (:data:`DENSE_ORIGINS`).
_ORIGIN_GROUPS = {"lidar": "LiDAR", "densified": "densified", "plane": "completed", "vertical": "completed"}


def dense_caption(frame: Frame, cache_source: str | None = None) -> str:
    """The caption of a dense depth, from its pixels' origins over the frame's cameras: rendered
    (by what, from ``cache_source``: :data:`RENDERED_BY`) where every pixel is, else the shares of
    the LiDAR's measurements, the densifier's fill and the completion (plane and vertical fits)."""
    counts = np.zeros(len(DENSE_ORIGINS), np.int64)
    for cam in frame.cameras:
        if cam.depth is not None and cam.depth.dense_origin is not None:
            counts += np.bincount(cam.depth.dense_origin.ravel(), minlength=len(DENSE_ORIGINS))[: len(counts)]
    counts[0] = 0  # "none": no depth
    total = int(counts.sum())
    if total == 0:
        return DEPTH_SOURCE_NAMES["dense"]
    rendered = counts[DENSE_ORIGINS.index("rendered")]
    if rendered == total:
        return f"depth: rendered from {RENDERED_BY.get(cache_source or '', 'Gaussians')}"
    shares: dict[str, int] = {}
    for k, name in enumerate(DENSE_ORIGINS):
        group = _ORIGIN_GROUPS.get(name, name)
        if counts[k] and name != "none":
            shares[group] = shares.get(group, 0) + int(counts[k])
    parts = ", ".join(f"{name} {100 * n / total:.0f} %" for name, n in shares.items())
    return f"depth: dense ({parts})"


def depth_caption(frame: Frame, rv: RangeView, cache_source: str | None = None) -> str | None:
    """The depth row's caption: its source's name (:data:`DEPTH_SOURCE_NAMES`; the dense depth's
    origins, :func:`dense_caption`), or why there is no depth (:data:`NO_DEPTH_CAPTION`,
    :data:`EMPTY_DEPTH_CAPTION`); None without a depth row. ``cache_source``: the cache's source
    (``"rendered"``, ``"generated"``, a dataset), which names what drew a rendered depth."""
    if rv.depth_source is None:
        return None
    if has_depth(rv.depth_m):
        if rv.depth_source == "dense":
            return dense_caption(frame, cache_source)
        return DEPTH_SOURCE_NAMES[rv.depth_source]
    return EMPTY_DEPTH_CAPTION if frame.lidar is not None and len(frame.lidar) else NO_DEPTH_CAPTION


def draw_frame(frame: Frame, scale: int = 2, cache_source: str | None = None) -> NDArray[np.uint8]:
    """An (H, W, 3) uint8 RGB picture of a frame (see the module docstring); ``cache_source``, the
    source of the cache it comes from, names what drew a rendered depth.

    ``scale`` magnifies the range view (after range views taller than
    :data:`MAX_CAMERA_HEIGHT_PX` are shrunk to it); each row is ``round(Hr * zoom)`` pixels high,
    row 0 at the top of the picture.
    """
    rv = preview_range_view(frame)
    layout = rv.layout
    zoom = min(1.0, MAX_CAMERA_HEIGHT_PX / layout.height) * scale
    size = (round(layout.width * zoom), round(layout.height * zoom))
    empty = _resize(~layout.valid(), size, cv2.INTER_NEAREST)
    font = caption_font(size[1], zoom)
    text_scale = max(1.0, font / 0.35)
    rows = [_rgb_row(rv, frame, size, zoom, font)]
    depth_name = depth_caption(frame, rv, cache_source)
    depth_known = has_depth(rv.depth_m)
    if rv.depth_m is not None and depth_name is not None:
        depth_rgb = (
            depth_color(rv.depth_m) if depth_known else np.full((*rv.depth_m.shape, 3), EMPTY_RGB, np.uint8)
        )
        rows.append(_map_row(depth_rgb, size, empty, depth_name, font))
    if rv.semantic is not None:
        semantic_name = SEMANTIC_SOURCE_NAMES[rv.semantic_source]
        rows.append(_map_row(tx.PALETTE_RGB[rv.semantic], size, empty, semantic_name, font))
    mosaic = np.concatenate(rows, axis=0)
    picture = [np.concatenate([mosaic, _bev(frame, mosaic.shape[0], font)], axis=1)]
    width = picture[0].shape[1]
    if depth_known and depth_name is not None:
        picture.append(depth_color_bar(width, depth_name, text_scale))
    if rv.semantic is not None:
        shown = classes_present(rv.semantic[layout.valid()])
        picture.append(class_legend(shown, width, semantic_name, text_scale))
    return np.concatenate(picture, axis=0)


def _map_row(
    rgb: NDArray[np.uint8], size: tuple[int, int], empty: NDArray[np.bool_], caption: str, font: float
) -> NDArray[np.uint8]:
    """A map row: ``rgb`` (layout-sized) at the picture's size, uncovered cells dark grey, and
    ``caption`` (the map's source) in its bottom-left corner at font scale ``font``."""
    row = _resize(rgb, size, cv2.INTER_NEAREST)
    row[empty] = EMPTY_RGB
    put_caption(row, caption, (3, row.shape[0] - round(8 * font)), font)
    return row


def put_caption(img: NDArray[np.uint8], text: str, origin: tuple[int, int], font_scale: float) -> None:
    """Draws ``text`` (OpenCV font 0, ``font_scale``) in white outlined in black into ``img``
    (H, W, 3 uint8, in place), its baseline starting at ``origin`` (x, y pixels). The outline is
    the 1-pixel glyphs drawn black at the 8 neighbouring offsets, so it never reaches more than
    one pixel past the white text (a thick stroke advances further per glyph and trails past it)."""
    x, y = origin
    for dx, dy in _OUTLINE:
        cv2.putText(img, text, (x + dx, y + dy), 0, font_scale, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, text, (x, y), 0, font_scale, (255, 255, 255), 1, cv2.LINE_AA)


def _resize(plane: NDArray, size: tuple[int, int], interpolation: int) -> NDArray:
    if (plane.shape[1], plane.shape[0]) == size:
        return plane.copy()
    as_u8 = plane.dtype == bool
    out = cv2.resize(plane.astype(np.uint8) if as_u8 else plane, size, interpolation=interpolation)
    return out.astype(bool) if as_u8 else out


def _rgb_row(
    rv: RangeView, frame: Frame, size: tuple[int, int], zoom: float, font: float
) -> NDArray[np.uint8]:
    """The RGB row: images (dimmed where another view owns the direction), boxes, names, borders."""
    layout = rv.layout
    rgb = np.zeros((layout.height, layout.width, 3), np.uint8) if rv.rgb is None else rv.rgb.copy()
    shared = layout.valid() & ~layout.primary()
    rgb[shared] = (rgb[shared] * OVERLAP_DIM).astype(np.uint8)
    rgb[~layout.valid()] = EMPTY_RGB
    img = _resize(rgb, size, cv2.INTER_AREA if zoom < 1 else cv2.INTER_NEAREST)
    cams = {c.name: c for c in frame.cameras}
    for p in layout.views:
        x0, x1 = round(p.col0 * zoom), round((p.col0 + p.width) * zoom)
        y0, y1 = round(p.row0 * zoom), round((p.row0 + p.height) * zoom)
        view = img[y0:y1, x0:x1]  # drawing here clips to the view
        _draw_boxes(view, cams[p.camera_name], frame, p, zoom)
        if x0 > 0:
            img[:, x0] = (255, 255, 255)
        name = p.camera_name
        while len(name) > 1 and cv2.getTextSize(name, 0, font, 1)[0][0] > x1 - x0 - 6:
            name = name[:-1]  # a narrow view shows as much of its name as fits
        put_caption(img, name, (x0 + 3, y0 + round(24 * font)), font)
    return img


def _camera_boxes(cam: CameraImage, frame: Frame) -> NDArray[np.float64]:
    """(M, 8, 3) world corners of the boxes at the image's capture time (its own boxes, else the
    frame's moved with their velocity)."""
    if cam.boxes is not None:
        return cam.boxes.corners_world()
    b: Boxes = frame.boxes
    dt = (cam.timestamp_micros - frame.timestamp_micros) * 1e-6
    return b.corners_world() + (b.velocity_world * dt)[:, None, :]


def _draw_boxes(
    view: NDArray[np.uint8], cam: CameraImage, frame: Frame, p: ViewPlacement, zoom: float
) -> None:
    """Draws the box edges seen by ``cam`` into ``view`` (its cells of the picture, in place)."""
    boxes = cam.boxes if cam.boxes is not None else frame.boxes
    if len(boxes) == 0:
        return
    corners = _camera_boxes(cam, frame)
    camera_from_world = geometry.invert_transform(cam.world_from_camera)
    cal = cam.calibration
    # Picture pixel of image pixel (u, v): centres stay centres, u' = (u + 0.5) * zoom - 0.5, then
    # relative to the view's corner in the picture.
    x0, y0 = round(p.col0 * zoom), round(p.row0 * zoom)
    ox, oy = (p.col0 + 0.5) * zoom - 0.5 - x0, (p.row0 + 0.5) * zoom - 0.5 - y0
    intrinsics = np.array([[zoom, 0, ox], [0, zoom, oy], [0, 0, 1]]) @ cal.intrinsics
    edges = np.array(geometry.BOX_EDGES)
    for i in range(len(boxes)):
        pts = geometry.transform_points(camera_from_world, corners[i])
        a, b = pts[edges[:, 0]], pts[edges[:, 1]]
        a, b, keep = _clip_near(a, b)
        if not keep.any():
            continue
        uv_a, ok_a = geometry.project_points(a[keep], intrinsics, cal.distortion)
        uv_b, ok_b = geometry.project_points(b[keep], intrinsics, cal.distortion)
        colour = _box_color(int(boxes.class_id[i]))
        for s, t in zip(uv_a[ok_a & ok_b], uv_b[ok_a & ok_b], strict=True):
            if np.abs(np.concatenate([s, t])).max() < 1e5:
                cv2.line(
                    view,
                    tuple(np.round(s).astype(int)),
                    tuple(np.round(t).astype(int)),
                    colour,
                    1,
                    cv2.LINE_AA,
                )


def _clip_near(
    a: NDArray[np.float64], b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Segments (E, 3) a-b in camera axes cut to ``z >= NEAR_M``; ``keep`` is False where wholly behind."""
    keep = (a[:, 2] >= NEAR_M) | (b[:, 2] >= NEAR_M)
    a, b = a.copy(), b.copy()
    for p, q in ((a, b), (b, a)):
        cut = keep & (p[:, 2] < NEAR_M)
        f = (NEAR_M - p[cut, 2]) / (q[cut, 2] - p[cut, 2])
        p[cut] = p[cut] + f[:, None] * (q[cut] - p[cut])
    return a, b, keep


def _box_color(class_id: int) -> tuple[int, int, int]:
    c = tx.PALETTE_RGB[class_id]
    return (255, 255, 0) if class_id == tx.CAR else tuple(int(x) for x in np.clip(c.astype(int) + 60, 0, 255))


#: Heights (metres above the ego frame's origin) the top view's LiDAR greys run between.
BEV_HEIGHT_M = (0.0, 5.0)
#: Caption font scale per pixel of a picture row: text about 3.5 % of a row's height, so a 6,500-pixel
#: real-rig preview is readable (at least the scale small previews have always used).
FONT_PER_ROW_PX = 0.0014


def caption_font(row_height_px: int, zoom: float) -> float:
    """OpenCV font scale of the picture's captions for rows ``row_height_px`` high."""
    return max(0.3 + 0.1 * zoom, FONT_PER_ROW_PX * row_height_px)


def _bev(frame: Frame, size: int, font: float) -> NDArray[np.uint8]:
    """Top view around the ego (x up, y left): LiDAR in greys by height (:data:`BEV_HEIGHT_M`, dark
    low, bright high: not the depth colours), boxes as outlines in their class colours, and a
    caption saying so."""
    img = np.full((size, size, 3), 20, np.uint8)
    px_per_m = size / (2 * BEV_RANGE_M)

    def to_px(xy_ego: NDArray[np.float64]) -> NDArray[np.int64]:
        col = size / 2 - xy_ego[..., 1] * px_per_m
        row = size / 2 - xy_ego[..., 0] * px_per_m
        return np.stack([col, row], axis=-1).round().astype(np.int64)

    if frame.lidar is not None and len(frame.lidar):
        p = frame.lidar.points_ego.astype(np.float64)
        px = to_px(p[:, :2])
        ok = (px >= 0).all(1) & (px < size).all(1)
        lo, hi = BEV_HEIGHT_M
        grey = np.clip(64 + (p[ok, 2] - lo) / (hi - lo) * 191, 64, 255).astype(np.uint8)
        img[px[ok, 1], px[ok, 0]] = grey[:, None]
    ego_from_world = geometry.invert_transform(frame.world_from_ego)
    b = frame.boxes
    if len(b):
        corners = geometry.transform_points(ego_from_world, b.corners_world().reshape(-1, 3)).reshape(
            -1, 8, 3
        )
        for i in range(len(b)):
            poly = to_px(corners[i, :4, :2])
            cv2.polylines(img, [poly.astype(np.int32)], True, _box_color(int(b.class_id[i])), 1, cv2.LINE_AA)
    ego = to_px(np.array([[4.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [4.0, -1.0]]))
    cv2.polylines(img, [ego.astype(np.int32)], True, (255, 255, 255), 1, cv2.LINE_AA)
    span = f"{2 * BEV_RANGE_M:.0f} m"
    caption = (
        f"top view {span}: LiDAR grey by height {BEV_HEIGHT_M[0]:g}-{BEV_HEIGHT_M[1]:g} m, boxes by class"
    )
    while caption and cv2.getTextSize(caption, 0, font, 1)[0][0] > size - 6:
        font *= 0.9  # the view is narrower than the rows: the caption shrinks to fit
    put_caption(img, caption, (3, size - 4), font)
    return img
