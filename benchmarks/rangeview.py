"""Range-view speed and size: layout, pack/unpack of the camera range view, the LiDAR range image.

Frames are built from the synthetic rigs' calibrations with stand-in content (smooth noise
images stored as JPEG at quality 95, random depth and classes, a 64 x 1024 sweep with 10 %
dropouts whose origin moves 1.5 m during the revolution): packing costs do not depend on what the
pixels show, and rendering 480 x 720 scenes would take minutes. Run:
``.venv/bin/python benchmarks/rangeview.py`` (``--update`` writes the ``rangeview`` section of BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag

from phigenesis.data import rangeview as rvm
from phigenesis.data.lidar_range import lidar_range_image
from phigenesis.data.records import Boxes, CameraImage, CameraTruth, Frame, LidarSweep, encode_rgb
from phigenesis.data.schema import CacheContents, frame_schema, frame_to_batch, row_to_frame
from phigenesis.data.sources.synthetic.rigs import LidarSpec, camera_calibrations

SIZES = ((160, 240), (480, 720))
RIGS = (("waymo5", False), ("nuscenes6", True))


def stand_in_frame(rig: str, height: int, width: int, uniform: bool, seed: int = 0) -> Frame:
    """A frame of the rig with stand-in images, truth maps and a 64 x 1024 sweep."""
    rng = np.random.default_rng(seed)
    cals, _ = camera_calibrations(rig, height, width, uniform)
    cams = []
    for cal in cals:
        noise = rng.integers(0, 255, (cal.height // 8 + 1, cal.width // 8 + 1, 3), dtype=np.uint8)
        rgb = cv2.resize(noise, (cal.width, cal.height), interpolation=cv2.INTER_CUBIC)
        shape = (cal.height, cal.width)
        truth = CameraTruth(
            rng.uniform(1, 80, shape).astype(np.float32),
            rng.integers(0, 19, shape, dtype=np.uint8),
            np.zeros(shape, np.uint16),
            np.zeros((*shape, 3), np.float32),
        )
        cams.append(CameraImage(cal, 0, np.eye(4), encode_rgb(rgb), truth=truth))
    return Frame("bench", 0, 0, np.eye(4), cams, stand_in_sweep(rng), Boxes.empty())


def stand_in_sweep(rng: np.random.Generator) -> LidarSweep:
    spec = LidarSpec()
    incl, az = spec.inclinations_rad(), spec.column_azimuths_rad()
    beams, cols = np.meshgrid(np.arange(spec.beams), np.arange(spec.columns), indexing="ij")
    d = np.stack(
        [np.cos(incl)[beams] * np.cos(az)[cols], np.cos(incl)[beams] * np.sin(az)[cols], np.sin(incl)[beams]],
        -1,
    ).reshape(-1, 3)
    origins = np.zeros_like(d)
    origins[:, 0] = 1.5 * (cols.reshape(-1) / spec.columns - 0.5)
    origins[:, 2] = spec.position_m[2]
    keep = rng.uniform(size=len(d)) > 0.1
    points = origins + d * rng.uniform(2, 75, (len(d), 1))
    n = int(keep.sum())
    return LidarSweep(
        0,
        np.eye(4),
        points[keep].astype(np.float32),
        rng.uniform(0, 1, n).astype(np.float32),
        beams.reshape(-1)[keep].astype(np.uint16),
        origins[keep].astype(np.float32),
        np.zeros(n, np.int32),
        np.zeros(n, np.uint8),
    )


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * float(np.median(times))


def measure(rig: str, height: int, width: int, uniform: bool, repeats: int) -> dict[str, float]:
    """Milliseconds per frame of each step, and stored bytes per frame."""
    frame = stand_in_frame(rig, height, width, uniform)
    cals = [c.calibration for c in frame.cameras]
    t0 = time.perf_counter()
    layout = rvm.range_view_layout(cals)  # first call: rays, overlap map (once per scene)
    out = {"layout_ms": 1000 * (time.perf_counter() - t0)}
    frame.range_view = layout
    out["pack_maps_ms"] = median_ms(
        lambda: rvm.pack_range_view(frame, layout, ("truth",), ("truth",), rgb=False), repeats
    )
    out["decode_jpeg_ms"] = median_ms(lambda: [c.decode_image() for c in frame.cameras], repeats)
    rv = rvm.pack_range_view(frame, layout, ("truth",), ("truth",))
    out["pack_all_ms"] = median_ms(
        lambda: rvm.pack_range_view(frame, layout, ("truth",), ("truth",)), repeats
    )
    out["unpack_ms"] = median_ms(
        lambda: [layout.unpack(p) for p in (rv.rgb, rv.depth_m, rv.semantic, rv.rays_ego)], repeats
    )
    out["lidar_ms"] = median_ms(lambda: lidar_range_image(frame.lidar, 64, 1024), repeats)
    frame.lidar_range_image = lidar_range_image(frame.lidar, 64, 1024)
    schema = frame_schema(CacheContents(range_view=True, lidar_range_image=True))
    batch = frame_to_batch(frame, "synthetic", schema)
    out["read_back_ms"] = median_ms(lambda: row_to_frame(batch, decode_truth=False), repeats)
    out["range_view_bytes"] = batch.column("range_view").nbytes
    out["lidar_range_bytes"] = batch.column("lidar_range_image").nbytes
    out["lidar_bytes"] = batch.column("lidar").nbytes
    out["rgb_png_bytes"] = len(cv2.imencode(".png", rv.rgb)[1])
    out["cells"] = layout.height * layout.width
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=20)
    add_update_flag(parser)
    args = parser.parse_args(argv)
    report = Report("rangeview", "Range views: speed and size", __doc__.split("\n\n", 1)[1])
    rows, sizes = [], []
    for rig, uniform in RIGS:
        for h, w in SIZES:
            m = measure(rig, h, w, uniform, args.repeats)
            label = f"{rig} {h}x{w}"
            rows.append(
                [
                    label,
                    m["cells"],
                    *(
                        f"{m[k]:.2f}"
                        for k in (
                            "layout_ms",
                            "pack_maps_ms",
                            "decode_jpeg_ms",
                            "pack_all_ms",
                            "unpack_ms",
                            "lidar_ms",
                        )
                    ),
                ]
            )
            sizes.append(
                [label, m["range_view_bytes"], m["rgb_png_bytes"], m["lidar_range_bytes"], m["lidar_bytes"]]
            )
    report.table(
        "Milliseconds per frame (one process)",
        [
            "rig, image size",
            "cells",
            "layout (once)",
            "pack maps",
            "JPEG decode",
            "pack all",
            "unpack",
            "LiDAR 64x1024",
        ],
        rows,
        "`layout (once)`: rays of every pixel and the overlap map, computed once per rig and cached; "
        "`pack maps`: depth, semantics and rays; `pack all`: the same plus decoding and placing the "
        "images (the JPEG decode alone is the column before); `unpack`: RGB, depth, semantics and rays "
        "back to per-view arrays.",
    )
    report.table(
        "Bytes per frame in the cache",
        ["rig, image size", "range_view column", "(RGB range view as PNG)", "lidar_range_image", "lidar"],
        sizes,
        "The range view stores the layout and the overlap map only; storing its RGB losslessly as well "
        "would cost the PNG size in brackets (the images are already stored as JPEG).",
    )
    report.write(update=args.update)


if __name__ == "__main__":
    main()
