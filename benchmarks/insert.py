"""Benchmark of scene editing (``phigenesis-render --insert``): a box-shaped car driven through a synthetic
scene, scored against an exact ray-cast of the same mesh at every camera's pose and time.

    python benchmarks/insert.py [--work /tmp/insert-bench] [--frames 8] [--spacing 0.05 0.1 0.2]

1. A synthetic `waymo5` cache (seed 100, 1 scene x ``--frames`` at 160 x 240).
2. The asset: a 4.5 x 1.9 x 1.6 m box (yellow faces), a PLY mesh, driven in the first frame's ego frame
   from 30 m ahead and 3 m right (behind a parked car) to 34 m ahead and 3.5 m left, turning 40
   degrees, over 0.7 s.
3. ``render`` with ``--geometry truth`` and ``--rig waymo5``, with and without the asset, for each
   surface-Gaussian spacing; per camera image:
   - the asset alone (its Gaussians rendered by the same camera) against the exact ray-cast of the mesh at
     that camera's pose and time: IoU of the silhouettes (alpha >= 0.5 against hit) and depth AbsRel on the
     pixels both cover;
   - the written image's depth against what is truly in front: on pixels where the mesh is nearer than the
     scene's exact depth, the share whose written depth is the mesh's (within 5 %; the asset shows), and on
     pixels where the scene's exact depth is nearer than the mesh by more than 10 %, the share whose written
     depth is not the mesh's (the scene hides it).
4. Time per frame with and without the asset, and the asset's Gaussian count and loading time.

Written to BENCHMARKS.md (section ``insert``), with a picture (docs/images/insert_asset.png).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag, output_path

from phigenesis import geometry, prep
from phigenesis._open3d import open3d
from phigenesis.data.shards import CacheReader
from phigenesis.data.stages.project import pixel_rays
from phigenesis.eval.stage1 import SyntheticTruth
from phigenesis.infer.insert import InsertSpec, load_asset, parse_keyframe, placed_gaussians
from phigenesis.infer.rig_render import render, render_camera

PICTURE = "docs/images/insert_asset.png"
BOX_LWH = (4.5, 1.9, 1.6)
KEYFRAMES = ("30,-3,0.8,0@0", "34,3.5,0.8,40@0.7")


def write_asset(path: Path) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=BOX_LWH)
    mesh.visual.face_colors = np.tile([235, 190, 20, 255], (len(mesh.faces), 1))
    mesh.export(path)
    return mesh


def mesh_depth(mesh: trimesh.Trimesh, pose: np.ndarray, cam) -> np.ndarray:  # type: ignore[no-untyped-def]
    """(H, W) exact z-depth of ``mesh`` placed at ``pose`` (world_from_asset) seen by ``cam`` (a
    CameraImage), 0 where its rays miss."""
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    vertices = geometry.transform_points(pose, np.asarray(mesh.vertices))
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, np.uint32))
    )
    world_from_camera = cam.world_from_ego @ cam.calibration.ego_from_camera
    rays_cam = pixel_rays(cam)  # z = 1: the ray parameter is the z-depth
    directions = rays_cam @ world_from_camera[:3, :3].T
    origins = np.broadcast_to(world_from_camera[:3, 3], directions.shape)
    rays = o3d.core.Tensor(np.concatenate([origins, directions], 1).astype(np.float32))
    t_hit = scene.cast_rays(rays)["t_hit"].numpy()
    depth = np.where(np.isfinite(t_hit), t_hit, 0.0)
    return depth.reshape(cam.calibration.height, cam.calibration.width).astype(np.float32)


def score(out: Path, source: Path, mesh: trimesh.Trimesh, spec: InsertSpec) -> dict[str, float]:
    """The silhouette, depth and occlusion scores of the rendered cache ``out`` (see the docstring)."""
    src = CacheReader(source)
    truth = SyntheticTruth(src.manifest.arguments, src.manifest.source)
    reader = CacheReader(out)
    asset = spec.load()
    ious, abs_rels, shows, hidden = [], [], [0, 0], [0, 0]
    scenes: dict[str, tuple] = {}  # scene id -> (placement, like), from its first frame
    for i in range(len(reader)):
        frame = reader.frame(i)
        if frame.scene_id not in scenes:
            first = reader.frame(reader.frames_of(frame.scene_id)[0], decode_truth=False)
            like = dataclasses.replace(asset.gaussians, time_origin_micros=first.timestamp_micros)
            scenes[frame.scene_id] = (spec.placement(first.timestamp_micros, first.world_from_ego), like)
        placement, like = scenes[frame.scene_id]
        for cam in frame.cameras:
            t = cam.timestamp_micros
            exact = mesh_depth(mesh, placement.pose_at(t), cam)
            alone = render_camera(
                placed_gaussians(asset, placement, t, like), cam.calibration, cam.world_from_ego,
                like.seconds(t), None, None,
            )  # fmt: skip
            sil = alone.alpha >= 0.5
            hit = exact > 0
            if hit.any() or sil.any():
                ious.append((sil & hit).sum() / max((sil | hit).sum(), 1))
            both = sil & hit
            if both.any():
                abs_rels.append(float((np.abs(alone.depth_m[both] - exact[both]) / exact[both]).mean()))
            _, scene_truth = truth.render(frame.scene_id, cam.calibration, cam.world_from_ego, t)
            scene_depth = np.where(scene_truth.depth_m > 0, scene_truth.depth_m, np.inf)
            assert cam.depth is not None and cam.depth.dense_m is not None
            written = cam.depth.dense_m
            is_mesh = np.abs(written - exact) <= 0.05 * np.maximum(exact, 1e-6)
            front = hit & (exact < scene_depth)
            behind = hit & (scene_depth < 0.9 * exact)
            shows[0] += int((front & is_mesh).sum())
            shows[1] += int(front.sum())
            hidden[0] += int((behind & ~is_mesh).sum())
            hidden[1] += int(behind.sum())
    return {
        "iou": float(np.mean(ious)) if ious else float("nan"),
        "abs_rel": float(np.mean(abs_rels)) if abs_rels else float("nan"),
        "shows": shows[0] / max(shows[1], 1),
        "front_px": shows[1],
        "hidden": hidden[0] / max(hidden[1], 1),
        "behind_px": hidden[1],
    }


def picture(plain: Path, edited: Path, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = CacheReader(plain), CacheReader(edited)
    picks = [0, len(b) // 2, len(b) - 1]
    fig, axes = plt.subplots(3, len(picks), figsize=(3.2 * len(picks), 6.4))
    for j, k in enumerate(picks):
        before, after = a.frame(k).cameras[0], b.frame(k).cameras[0]
        assert after.depth is not None and after.depth.dense_m is not None
        for row, (img, title) in enumerate(
            [
                (before.decode_image(), f"frame {k}: rendered, no asset"),
                (after.decode_image(), f"frame {k}: asset inserted"),
                (after.depth.dense_m, "its rendered depth (0-40 m)"),
            ]
        ):
            ax = axes[row, j]
            ax.imshow(img, cmap="turbo", vmin=0, vmax=40) if img.ndim == 2 else ax.imshow(img)
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/insert-bench"))
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--spacing", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    ap.add_argument("--threads", type=int, default=2)
    add_update_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    source = work / "source"
    if not (source / "manifest.json").exists():
        prep.synthetic(source, scenes=1, frames=args.frames, seed=100, height=160, width=240, progress=False)
    asset_path = work / "car_box.ply"
    mesh = write_asset(asset_path)
    keys = tuple(parse_keyframe(k) for k in KEYFRAMES)

    def run(out: Path, insert: list[InsertSpec]) -> float:
        shutil.rmtree(out, ignore_errors=True)
        result = render(None, source, "waymo5", out, geometry="truth", insert=insert, progress=False)
        return result.seconds / max(result.frames, 1)

    plain_s = run(work / "plain", [])
    rows = [["none", "—", "—", "—", "—", "—", "—", f"{plain_s:.2f}"]]
    edited = None
    for spacing in args.spacing:
        spec = InsertSpec(asset_path, keys, "car", frame="ego", spacing_m=spacing)
        t0 = time.perf_counter()
        count = len(load_asset(asset_path, class_name="car", spacing_m=spacing).gaussians)
        load_ms = 1e3 * (time.perf_counter() - t0)
        out = work / f"edited-{spacing:g}"
        seconds = run(out, [spec])
        s = score(out, source, mesh, spec)
        edited = edited or out
        rows.append(
            [
                f"{spacing:g}",
                f"{count:,}",
                f"{load_ms:.0f}",
                f"{s['iou']:.3f}",
                f"{s['abs_rel']:.4f}",
                f"{100 * s['shows']:.1f} ({s['front_px']:,} px)",
                f"{100 * s['hidden']:.1f} ({s['behind_px']:,} px)",
                f"{seconds:.2f}",
            ]
        )
    assert edited is not None
    picture(work / "plain", edited, output_path(PICTURE, args.update))
    report = Report(
        "insert",
        "Scene editing: an inserted asset against its exact ray-cast (benchmarks/insert.py)",
        f"A synthetic waymo5 scene (seed 100, {args.frames} frames, 160 x 240, 5 cameras) rendered by "
        "`phigenesis-render --geometry truth --rig waymo5` with a 4.5 x 1.9 x 1.6 m box-shaped car "
        "(PLY mesh, yellow faces) inserted on a path in the first frame's ego frame "
        f"({', '.join(KEYFRAMES)}: "
        "x, y, z, yaw degrees @ seconds), against the same mesh ray-cast exactly at every camera's pose "
        "and capture time.",
    )
    report.table(
        "The asset against its exact ray-cast, by surface-Gaussian spacing",
        [
            "spacing m",
            "Gaussians",
            "load ms",
            "silhouette IoU",
            "depth AbsRel",
            "shows where in front %",
            "hidden where behind %",
            "s/frame",
        ],
        rows,
        note="Silhouette IoU and depth AbsRel: the asset's Gaussians alone rendered by each camera (alpha "
        ">= 0.5) against the mesh's exact hits, per image, averaged over images that see it. Shows where "
        "in front: of the pixels where the exact mesh is nearer than the scene's exact depth, the share "
        "whose written depth is the mesh's within 5 %. Hidden where behind: of the pixels where the "
        "scene's exact depth is nearer than the mesh by more than 10 %, the share whose written depth is "
        "not the mesh's. s/frame: the whole render command per frame (5 cameras; with an asset, each "
        "camera also renders the asset alone, to drop the LiDAR points it hides).",
    )
    report.text(
        f"![an inserted car]({PICTURE})\n\nThe FRONT camera at three frames: rendered without the asset, "
        f"with it (spacing {args.spacing[0]:g} m), and the edited frame's rendered depth: `{PICTURE}`."
    )
    report.write(update=args.update)


if __name__ == "__main__":
    main()
