"""``phigenesis-prep preview``'s picture: the semantics row shows the best labels a frame has and says
which, depth has a colour bar and classes a legend, a depth has the same colour here as in the
Stage 1 evaluation picture, a frame without LiDAR says so (no black map, no colour bar), and a
caption's outline stays within its text."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from phigenesis import taxonomy as tx
from phigenesis.data.colormap import DEPTH_FAR_M, DEPTH_NEAR_M, depth_color
from phigenesis.data.preview import (
    EMPTY_RGB,
    NO_DEPTH_CAPTION,
    depth_caption,
    draw_frame,
    has_depth,
    preview_range_view,
    put_caption,
)
from phigenesis.data.rangeview import RangeView, pack_range_view
from phigenesis.data.records import CameraLabels, Frame
from phigenesis.data.shards import CacheReader
from phigenesis.eval.stage1 import ClipResult, Rendered, Views, save_picture


@pytest.fixture(scope="module")
def frame(tiny_cache: Path) -> Frame:
    """A synthetic frame with exact truth, dense depth and pseudo labels."""
    frame = CacheReader(tiny_cache).frame(1)
    assert all(c.truth is not None and c.pseudo is not None and c.depth is not None for c in frame.cameras)
    return frame


def truth_view(frame: Frame) -> RangeView:
    return pack_range_view(frame, depth_sources=("truth",), semantic_sources=("truth",), rgb=False)


def picture_rows(frame: Frame, picture: np.ndarray) -> list[np.ndarray]:
    """The picture's range-view rows (RGB, depth, semantics) at scale 1, without the top view."""
    layout = truth_view(frame).layout
    h, w = layout.height, layout.width
    assert h <= 320  # drawn at scale 1, unshrunk
    return [picture[k * h : (k + 1) * h, :w] for k in range(3)]


def with_cameras(frame: Frame, **changes: object) -> Frame:
    return dataclasses.replace(frame, cameras=[dataclasses.replace(c, **changes) for c in frame.cameras])


def test_semantics_row_shows_the_exact_truth_of_a_synthetic_cache_not_its_pseudo_labels(frame: Frame) -> None:
    picture = draw_frame(frame, scale=1)
    truth = truth_view(frame)
    layout = truth.layout
    above_caption = np.arange(layout.height)[:, None] < layout.height - 16  # it names the source
    semantics = picture_rows(frame, picture)[2]
    same = (semantics == tx.PALETTE_RGB[truth.semantic]).all(axis=-1)
    assert same[layout.valid() & above_caption].mean() > 0.99


def test_semantics_come_from_truth_else_the_dataset_labels_else_pseudo_labels(frame: Frame) -> None:
    assert preview_range_view(frame).semantic_source == "truth"
    labelled = with_cameras(frame, truth=None)
    labelled = dataclasses.replace(
        labelled,
        cameras=[
            dataclasses.replace(c, labels=CameraLabels(t.truth.semantic, t.truth.instance))
            for c, t in zip(labelled.cameras, frame.cameras, strict=True)
        ],
    )
    assert preview_range_view(labelled).semantic_source == "labels"
    assert preview_range_view(with_cameras(frame, truth=None)).semantic_source == "pseudo"
    assert preview_range_view(with_cameras(frame, truth=None, pseudo=None)).semantic is None


def test_picture_ends_with_a_depth_colour_bar_and_a_legend_of_the_classes_shown(frame: Frame) -> None:
    picture = draw_frame(frame, scale=1)
    truth = truth_view(frame)
    keys = picture[3 * truth.layout.height :]
    assert keys.shape[0] >= 40
    colours = {tuple(int(v) for v in c) for c in keys.reshape(-1, 3)}
    assert tuple(depth_color(DEPTH_NEAR_M)) in colours and tuple(depth_color(DEPTH_FAR_M)) in colours
    shown = np.unique(truth.semantic[truth.layout.valid()])
    assert len(shown) >= 4
    for c in shown:
        assert tuple(int(v) for v in tx.PALETTE_RGB[c]) in colours, tx.class_name(int(c))


def test_depth_colours_run_from_red_near_to_blue_far_with_unknown_black() -> None:
    near, far, unknown = depth_color(np.array([0.5, 300.0, 0.0]))
    assert near[0] > near[2] and far[2] > far[0]
    assert tuple(unknown) == (0, 0, 0) and tuple(depth_color(np.nan)) == (0, 0, 0)
    assert (depth_color(0.5) == depth_color(DEPTH_NEAR_M)).all()


def _two_depth_frame(frame: Frame, near_m: float, far_m: float) -> Frame:
    """``frame`` with only truth depth: ``near_m`` in the left half of every image, ``far_m`` right."""

    def split(depth: np.ndarray) -> np.ndarray:
        out = np.full(depth.shape, far_m, np.float32)
        out[:, : depth.shape[1] // 2] = near_m
        return out

    cameras = [
        dataclasses.replace(c, depth=None, truth=dataclasses.replace(c.truth, depth_m=split(c.truth.depth_m)))
        for c in frame.cameras
    ]
    return dataclasses.replace(frame, cameras=cameras)


def _two_depth_clip(near_m: float, far_m: float) -> ClipResult:
    """One view whose truth and rendered depth are ``near_m`` on the left half, ``far_m`` right."""
    h, w = 24, 36
    depth = torch.full((1, h, w), far_m)
    depth[..., : w // 2] = near_m
    road = torch.full((1, h, w), tx.ROAD, dtype=torch.uint8)
    views = Views(
        images=torch.full((1, h, w, 3), 0.5),
        world_from_camera=torch.eye(4, dtype=torch.float64)[None],
        intrinsics=torch.eye(3)[None],
        time_s=torch.zeros(1, dtype=torch.float64),
        depth=depth,
        semantic=road,
    )
    rendered = Rendered(rgb=views.images, depth=depth, alpha=torch.ones(1, h, w), semantic=road)
    return ClipResult("scene", 0, {"input": views}, {"input": rendered}, {})


def test_a_depth_has_the_same_colour_in_preview_and_in_the_stage1_evaluation_picture(
    frame: Frame, tmp_path: Path
) -> None:
    near_m, far_m = 1.5, 40.0
    shown = _two_depth_frame(frame, near_m, far_m)
    rv = preview_range_view(shown)
    assert rv.depth_source == "truth"
    depth_row = picture_rows(shown, draw_frame(shown, scale=1))[1]
    top = np.arange(rv.layout.height)[:, None] < rv.layout.height // 2  # away from the caption
    preview_colour = {}
    for d in (near_m, far_m):
        cells = depth_row[(rv.depth_m == d) & rv.layout.valid() & top]
        values, counts = np.unique(cells, axis=0, return_counts=True)
        preview_colour[d] = values[counts.argmax()]
    assert not (preview_colour[near_m] == preview_colour[far_m]).all()

    path = save_picture(_two_depth_clip(near_m, far_m), tmp_path / "eval.png")
    evaluation = cv2.imread(str(path))[..., ::-1]
    for d, colour in preview_colour.items():
        pixels = (evaluation == colour).all(axis=-1).sum()
        assert pixels >= 24 * 36, f"{d} m: {colour} covers {pixels} pixels of the evaluation picture"


def _without_lidar(frame: Frame) -> Frame:
    """``frame`` as a converted frame without LiDAR: no points, every depth map 0, no truth."""
    cameras = [
        dataclasses.replace(
            c,
            truth=None,
            depth=dataclasses.replace(
                c.depth,
                sparse_m=np.zeros_like(c.depth.sparse_m),
                sparse_confidence=np.zeros_like(c.depth.sparse_confidence),
                dense_m=np.zeros_like(c.depth.dense_m),
                dense_confidence=np.zeros_like(c.depth.dense_confidence),
                dense_origin=None,
            ),
        )
        for c in frame.cameras
    ]
    return dataclasses.replace(frame, cameras=cameras, lidar=None)


def test_a_frame_without_lidar_says_so_instead_of_a_black_dense_depth_with_a_colour_bar(frame: Frame) -> None:
    bare = _without_lidar(frame)
    rv = preview_range_view(bare)
    assert rv.depth_source == "dense" and not has_depth(rv.depth_m)
    assert depth_caption(bare, rv) == NO_DEPTH_CAPTION == "no depth (no LiDAR in this frame)"
    with_depth = draw_frame(frame, scale=1)
    picture = draw_frame(bare, scale=1)
    layout = rv.layout
    depth_row = picture[layout.height : 2 * layout.height, : layout.width]
    above_caption = np.arange(layout.height) < layout.height - 16
    assert (depth_row[above_caption] == EMPTY_RGB).all()  # grey, not a black "unknown" map
    keys = picture[3 * layout.height :]
    colours = {tuple(int(v) for v in c) for c in keys.reshape(-1, 3)}
    assert (
        tuple(depth_color(10.0)) not in colours and tuple(depth_color(DEPTH_FAR_M)) not in colours
    )  # no bar
    assert picture.shape[0] < with_depth.shape[0]


def test_a_frame_without_lidar_but_with_exact_depth_shows_the_exact_depth(frame: Frame) -> None:
    bare = _without_lidar(frame)
    truthful = dataclasses.replace(
        bare,
        cameras=[
            dataclasses.replace(c, truth=t.truth) for c, t in zip(bare.cameras, frame.cameras, strict=True)
        ],
    )
    rv = preview_range_view(truthful)
    assert rv.depth_source == "truth" and has_depth(rv.depth_m)
    assert depth_caption(truthful, rv) == "depth: exact truth"


@pytest.mark.parametrize(
    "text", ["semantics: dataset labels", "depth: dense (LiDAR, densified)", "FRONT_LEFT"]
)
@pytest.mark.parametrize("font_scale", [0.4, 0.5, 0.7])
def test_a_caption_outline_stays_within_one_pixel_of_its_text(text: str, font_scale: float) -> None:
    img = np.full((40, 400, 3), 128, np.uint8)
    put_caption(img, text, (5, 30), font_scale)
    (width, height), baseline = cv2.getTextSize(text, 0, font_scale, 1)
    changed = (img != 128).any(axis=-1)
    rows, cols = np.nonzero(changed)
    white = (img > 200).all(axis=-1)
    _, white_cols = np.nonzero(white)
    assert cols.max() <= white_cols.max() + 2  # the outline ends where the text ends
    assert cols.min() >= 5 - 2 and cols.max() <= 5 + width + 2
    assert rows.min() >= 30 - height - 2 and rows.max() <= 30 + baseline + 2


def test_colouring_an_unknown_scalar_depth_leaves_the_colour_map_intact() -> None:
    from phigenesis.data.colormap import DEPTH_NEAR_M, depth_color

    near = depth_color(DEPTH_NEAR_M).copy()
    assert depth_color(np.nan).tolist() == [0, 0, 0]
    assert depth_color(DEPTH_NEAR_M).tolist() == near.tolist() != [0, 0, 0]


def test_the_dense_depth_caption_says_what_its_pixels_are_made_of(frame: Frame) -> None:
    """LiDAR-derived: the shares of each origin, which add up to 100 %; rendered: by what."""
    from phigenesis.data.records import DENSE_ORIGINS

    rv = preview_range_view(frame)
    assert rv.depth_source == "dense"
    caption = depth_caption(frame, rv)
    assert caption is not None and caption.startswith("depth: dense (LiDAR ")
    shares = [float(part.split()[-2]) for part in caption[len("depth: dense (") : -1].split(", ")]
    assert abs(sum(shares) - 100) <= len(shares) / 2  # each rounded to a whole per cent
    origins = np.concatenate([c.depth.dense_origin.ravel() for c in frame.cameras])
    lidar = np.mean(origins[origins > 0] == DENSE_ORIGINS.index("lidar"))
    assert f"LiDAR {100 * lidar:.0f} %" in caption

    rendered = DENSE_ORIGINS.index("rendered")

    def all_rendered(c):
        origin = np.where(c.depth.dense_m > 0, rendered, 0).astype(np.uint8)
        return dataclasses.replace(c, depth=dataclasses.replace(c.depth, dense_origin=origin))

    drawn = dataclasses.replace(frame, cameras=[all_rendered(c) for c in frame.cameras])
    rv = preview_range_view(drawn)
    assert depth_caption(drawn, rv, "rendered") == "depth: rendered from phigenesis-render's Gaussians"
    assert (
        depth_caption(drawn, rv, "generated")
        == "depth: rendered from the rollout's Gaussians (phigenesis-generate)"
    )
    assert depth_caption(drawn, rv) == "depth: rendered from Gaussians"
    assert draw_frame(drawn, scale=1, cache_source="generated").shape[0] > 0
