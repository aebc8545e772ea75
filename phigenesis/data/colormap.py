"""The colours of the toolkit's pictures, shared so that a depth or a class looks the same in every one
(``phigenesis-prep preview`` and the Stage 1 evaluation picture).

- Depth: turbo over log depth, near red and far blue, from :data:`DEPTH_NEAR_M` (and nearer) to
  :data:`DEPTH_FAR_M` (and farther); unknown depth (0, negative or not finite) is black.
  :func:`depth_color_bar` draws the scale with its ticks in metres.
- Classes: the taxonomy's palette (:data:`phigenesis.taxonomy.PALETTE_RGB`);
  :func:`class_legend` draws the swatches and names of the classes a picture shows.
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from phigenesis import taxonomy as tx

#: Depths at or nearer than this take the nearest colour (metres).
DEPTH_NEAR_M = 1.0
#: Depths at or farther than this take the farthest colour (metres).
DEPTH_FAR_M = 100.0
#: Where the colour bar has ticks (metres).
DEPTH_TICKS_M: tuple[float, ...] = (1, 2, 5, 10, 20, 50, 100)
#: The stretch of the turbo map used, far to near: its darkest ends are left out so that far is
#: not mistaken for unknown (black).
_TURBO_FAR, _TURBO_NEAR = 20, 240
#: (256, 3) uint8 RGB turbo map.
_TURBO_RGB = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1].copy()

FONT = cv2.FONT_HERSHEY_SIMPLEX
TEXT_RGB = (230, 230, 230)
PANEL_RGB = (24, 24, 24)


def depth_position(depth_m: ArrayLike) -> NDArray[np.float64]:
    """Where each depth sits on the colour scale: 0 at :data:`DEPTH_NEAR_M` and nearer, 1 at
    :data:`DEPTH_FAR_M` and farther, log-spaced between (NaN where the depth is unknown)."""
    d = np.asarray(depth_m, dtype=np.float64)
    known = np.isfinite(d) & (d > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.log(np.where(known, d, 1.0) / DEPTH_NEAR_M) / np.log(DEPTH_FAR_M / DEPTH_NEAR_M)
    return np.where(known, np.clip(u, 0.0, 1.0), np.nan)


def depth_color(depth_m: ArrayLike) -> NDArray[np.uint8]:
    """(..., 3) uint8 RGB of depths (..., metres): near red, far blue, unknown black (see the module
    docstring)."""
    u = depth_position(depth_m)
    known = np.isfinite(u)
    index = np.round(_TURBO_NEAR - np.where(known, u, 0.0) * (_TURBO_NEAR - _TURBO_FAR)).astype(np.intp)
    rgb = np.take(_TURBO_RGB, index, axis=0)  # a copy even for a scalar (indexing gives a view)
    rgb[~known] = 0
    return rgb


def _put_text(img: NDArray[np.uint8], text: str, x: int, y: int, scale: float) -> None:
    cv2.putText(img, text, (x, y), FONT, scale, TEXT_RGB, 1, cv2.LINE_AA)


def _text_width(text: str, scale: float) -> int:
    return cv2.getTextSize(text, FONT, scale, 1)[0][0]


def depth_color_bar(width: int, title: str = "depth", text_scale: float = 1.0) -> NDArray[np.uint8]:
    """An (H, width, 3) uint8 RGB strip: ``title``, the depth colours from near to far with ticks
    labelled in metres (:data:`DEPTH_TICKS_M`), and the colour of unknown depth. ``text_scale``
    magnifies the text and the strip (1: 0.35 OpenCV font scale, 30 pixels high)."""
    scale, pad = 0.35 * text_scale, round(8 * text_scale)
    height, label_h = round(30 * text_scale), round(12 * text_scale)
    swatch = round(12 * text_scale)
    img = np.full((height, width, 3), PANEL_RGB, np.uint8)
    bar_top, bar_bottom = round(3 * text_scale), height - label_h - round(2 * text_scale)
    x0 = pad + _text_width(title, scale) + pad
    x1 = width - pad - _text_width("unknown", scale) - swatch - 2 * pad
    _put_text(img, title, pad, bar_bottom - 1, scale)
    if x1 - x0 >= 40:
        depths = DEPTH_NEAR_M * (DEPTH_FAR_M / DEPTH_NEAR_M) ** np.linspace(0.0, 1.0, x1 - x0)
        img[bar_top:bar_bottom, x0:x1] = depth_color(depths)[None]
        for tick in DEPTH_TICKS_M:
            x = x0 + round(float(depth_position(tick)) * (x1 - x0 - 1))
            img[bar_bottom : bar_bottom + round(3 * text_scale), x] = TEXT_RGB
            label = f"{tick:g} m" if tick in (DEPTH_TICKS_M[0], DEPTH_TICKS_M[-1]) else f"{tick:g}"
            lx = min(max(x - _text_width(label, scale) // 2, 0), width - _text_width(label, scale))
            _put_text(img, label, lx, height - round(2 * text_scale), scale)
    sx = max(x1, x0) + pad
    img[bar_top:bar_bottom, sx : sx + swatch] = 0
    cv2.rectangle(img, (sx, bar_top), (sx + swatch - 1, bar_bottom - 1), (90, 90, 90), 1)
    _put_text(img, "unknown", sx + swatch + round(4 * text_scale), bar_bottom - 1, scale)
    return img


def classes_present(semantic: ArrayLike) -> list[int]:
    """The class ids that occur in a label map, in taxonomy order (255 = no label last)."""
    return sorted(int(c) for c in np.unique(np.asarray(semantic)))


def class_legend(
    class_ids: Iterable[int], width: int, title: str = "classes", text_scale: float = 1.0
) -> NDArray[np.uint8]:
    """An (H, width, 3) uint8 RGB panel: ``title``, then a palette swatch and the name of each
    class in ``class_ids`` (255 as "no label"), wrapped over as many lines as the width needs.
    ``text_scale`` magnifies the text (1: 0.35 OpenCV font scale, 16-pixel lines)."""
    scale, line_h, swatch = 0.35 * text_scale, round(16 * text_scale), round(10 * text_scale)
    entries = [(title, None)] + [
        ("no label" if c == tx.IGNORE_ID else tx.class_name(c), int(c)) for c in class_ids
    ]
    lines: list[list[tuple[int, str, int | None]]] = [[]]
    pad, gap = round(8 * text_scale), round(4 * text_scale)
    x = pad
    for text, c in entries:
        w = _text_width(text, scale) + (swatch + gap if c is not None else 0) + 3 * gap
        if x + w > width and lines[-1]:
            lines.append([])
            x = pad
        lines[-1].append((x, text, c))
        x += w
    img = np.full((line_h * len(lines) + gap, width, 3), PANEL_RGB, np.uint8)
    for row, line in enumerate(lines):
        y = line_h * row + gap // 2
        for x, text, c in line:
            if c is not None:
                top = y + (line_h - swatch) // 2
                img[top : top + swatch, x : x + swatch] = tx.PALETTE_RGB[c]
                cv2.rectangle(img, (x, top), (x + swatch - 1, top + swatch - 1), (90, 90, 90), 1)
                x += swatch + gap
            _put_text(img, text, x, y + round(11 * text_scale), scale)
    return img
