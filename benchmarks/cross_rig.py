"""The cross-rig experiment (the PhiGenesis paper's domain-generalisation table, with exact truth instead of a
proxy): does training on a cache re-rendered for other cameras help a perception model on another car's
rig?

    python benchmarks/cross_rig.py [--work /tmp/cross-rig] [--scenes 24] [--frames 4] [--steps 1200]
                                   [--seeds 0 1 2]

1. A synthetic `waymo5` training cache (seed 200, ``--scenes`` x ``--frames`` at 96 x 144), and two
   held-out test caches of other scenes (seed 300): `nuscenes6` at 90 x 160 (the other rig: six cameras,
   other fields of view, mounting heights and a rear camera) and `waymo5` at 96 x 144 (the same rig).
2. ``phigenesis-render`` of the training cache with ``--geometry cache`` (the cache's LiDAR-derived dense
   depth lifted to Gaussians, so a render's labels come from the same LiDAR as the originals' and better
   labels cannot explain a gain) for: its own rig (`waymo5`, pinhole: a control with as many rendered
   images and no new viewpoints), random rigs drawing the field of view only (intrinsics), and random
   rigs drawing the field of view, mounting height, pitch, yaw and lateral offset (intrinsics and
   extrinsics); one rig per scene, every image 96 x 144.
3. The same small model (SegFormer-tiny with one output: log metric depth from one image) trained from
   the same initialisation for the same number of steps on each training set, per seed: per-pixel L1 of
   log depth over the labelled pixels (the cache's dense depth; rendered depth in the renders),
   horizontal flips. Depth lives in a canonical camera (as Metric3D does): the model predicts depth x
   (150 px / fx), so images of any focal length share one scale, and each prediction is scaled back by
   its image's fx; ``--plain-depth`` predicts metres directly (a model that cannot know the focal
   length of a new rig). The camera's mounting height is left for the model to infer from the image.
4. Scored on every camera of the test caches against the synthetic renderer's exact depth under the
   standard protocol (``phigenesis.eval.depth_protocol``: truth pixels, [1e-3, 80] m, per-image means).

Written to BENCHMARKS.md (section ``cross_rig``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag

from phigenesis import prep
from phigenesis.data.shards import CacheReader
from phigenesis.eval.depth_protocol import DepthAccumulator
from phigenesis.eval.stage1 import SyntheticTruth
from phigenesis.infer.rig_render import render
from phigenesis.infer.rigs import RandomRigRanges
from phigenesis.models.segformer import segformer_tiny

SIZE_HW = (96, 144)
TEST_SIZES = {"nuscenes6": (90, 160), "waymo5": SIZE_HW}
MIN_DEPTH_M, MAX_DEPTH_M = 1e-3, 80.0
#: The canonical camera's focal length (Metric3D's canonical camera space): the model predicts
#: depth x (CANONICAL_FOCAL_PX / fx), so images of every focal length share one depth scale.
CANONICAL_FOCAL_PX = 150.0


@dataclasses.dataclass
class Images:
    """Images and their depth labels (0: none), stacked: ``rgb`` (N, 3, H, W) uint8, ``depth_m``
    (N, H, W) float32, metres (camera z), ``focal_px`` (N,) float32 each image's fx, pixels."""

    rgb: torch.Tensor
    depth_m: torch.Tensor
    focal_px: torch.Tensor

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    @staticmethod
    def join(parts: list[Images]) -> Images:
        return Images(*(torch.cat([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(Images)))


def cache_images(cache: Path) -> Images:
    """Every camera image of ``cache`` with its dense depth (the cache's label) as :class:`Images`."""
    reader = CacheReader(cache)
    rgb, depth, focal = [], [], []
    for i in range(len(reader)):
        for cam in reader.frame(i).cameras:
            assert cam.depth is not None and cam.depth.dense_m is not None, f"{cache}: no dense depth"
            rgb.append(torch.from_numpy(cam.decode_image()).permute(2, 0, 1))
            depth.append(torch.from_numpy(cam.depth.dense_m))
            focal.append(float(cam.calibration.intrinsics[0, 0]))
    return Images(torch.stack(rgb), torch.stack(depth), torch.tensor(focal))


def truth_images(cache: Path) -> Images:
    """Every camera image of the synthetic ``cache`` with its exact depth (the renderer's truth)."""
    reader = CacheReader(cache)
    truth = SyntheticTruth(reader.manifest.arguments, reader.manifest.source)
    rgb, depth, focal = [], [], []
    for i in range(len(reader)):
        frame = reader.frame(i)
        for cam in frame.cameras:
            _, exact = truth.render(frame.scene_id, cam.calibration, cam.world_from_ego, cam.timestamp_micros)
            rgb.append(torch.from_numpy(cam.decode_image()).permute(2, 0, 1))
            depth.append(torch.from_numpy(exact.depth_m.astype(np.float32)))
            focal.append(float(cam.calibration.intrinsics[0, 0]))
    return Images(torch.stack(rgb), torch.stack(depth), torch.tensor(focal))


def depth_model(seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    return segformer_tiny(num_classes=1)


def focal_scale(focal_px: torch.Tensor, canonical: bool) -> torch.Tensor:
    """(N, 1, 1) metric depth / the model's depth: fx / CANONICAL_FOCAL_PX, or 1 without the canonical
    camera."""
    return (focal_px / CANONICAL_FOCAL_PX if canonical else torch.ones_like(focal_px))[:, None, None]


def predict_depth_m(
    model: torch.nn.Module, rgb: torch.Tensor, focal_px: torch.Tensor, canonical: bool
) -> torch.Tensor:
    """(N, H, W) metres from (N, 3, H, W) uint8 of focal lengths ``focal_px`` (N,) (the model's log
    depth upsampled to the input size, out of the canonical camera)."""
    log_depth = model(rgb.float() / 255.0)
    log_depth = F.interpolate(log_depth, size=rgb.shape[-2:], mode="bilinear", align_corners=False)[:, 0]
    depth = log_depth.exp() * focal_scale(focal_px, canonical)
    return depth.clamp(MIN_DEPTH_M, MAX_DEPTH_M)


def train(
    data: Images, seed: int, steps: int, batch: int, lr: float, canonical: bool
) -> tuple[torch.nn.Module, float]:
    """The model of ``seed`` trained on ``data``; returns it and the training seconds."""
    model = depth_model(seed)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    warmup = max(1, steps // 20)

    def factor(step: int) -> float:  # linear warm-up, then cosine to 0
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1.0 + math.cos(math.pi * (step - warmup) / max(steps - warmup, 1)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
    gen = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    for _ in range(steps):
        idx = torch.randint(len(data), (batch,), generator=gen)
        rgb, depth, scale = data.rgb[idx], data.depth_m[idx], focal_scale(data.focal_px[idx], canonical)
        flip = torch.rand(batch, generator=gen) < 0.5
        rgb = torch.where(flip[:, None, None, None], rgb.flip(-1), rgb)
        depth = torch.where(flip[:, None, None], depth.flip(-1), depth)
        log_pred = F.interpolate(model(rgb.float() / 255.0), size=rgb.shape[-2:], mode="bilinear")[:, 0]
        valid = (depth > MIN_DEPTH_M) & (depth <= MAX_DEPTH_M)
        target = (depth.clamp_min(MIN_DEPTH_M) / scale).log()
        loss = (log_pred - target).abs()[valid].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
    return model.eval(), time.perf_counter() - t0


@torch.no_grad()
def score(model: torch.nn.Module, test: Images, canonical: bool) -> dict[str, float]:
    """AbsRel, RMSE and delta < 1.25 of ``model`` on ``test`` (standard protocol, per-image means)."""
    acc = DepthAccumulator((), min_depth_m=MIN_DEPTH_M, max_depth_m=MAX_DEPTH_M)
    for lo in range(0, len(test), 16):
        part = slice(lo, lo + 16)
        pred = predict_depth_m(model, test.rgb[part], test.focal_px[part], canonical)
        acc.add(pred.numpy(), test.depth_m[part].numpy())
    d = acc.image_mean()["all"]
    return {"abs_rel": d.abs_rel, "rmse_m": d.rmse_m, "delta": d.delta_1_25}


def build(work: Path, scenes: int, frames: int, test_scenes: int, test_frames: int) -> dict[str, Path]:
    """The training cache, its renders and the test caches (kept in ``work`` for a rerun)."""
    paths = {"train": work / "train-waymo5"}
    if not (paths["train"] / "manifest.json").exists():
        prep.synthetic(paths["train"], scenes=scenes, frames=frames, seed=200, height=SIZE_HW[0],
                       width=SIZE_HW[1], workers=2, progress=False)  # fmt: skip
    for rig, (h, w) in TEST_SIZES.items():
        path = paths[f"test-{rig}"] = work / f"test-{rig}"
        if not (path / "manifest.json").exists():
            prep.synthetic(path, scenes=test_scenes, frames=test_frames, seed=300, rig=rig, height=h,
                           width=w, workers=2, progress=False)  # fmt: skip
    one_size = (SIZE_HW,)
    renders = {
        "own rig": ("waymo5", None),
        "random intrinsics": ("random", RandomRigRanges(extrinsics=False, sizes_hw=one_size)),
        "random intrinsics + extrinsics": ("random", RandomRigRanges(sizes_hw=one_size)),
    }
    for name, (rig, ranges) in renders.items():
        path = paths[name] = work / ("render-" + name.replace(" ", "-").replace("+", "and"))
        if not (path / "manifest.json").exists():
            render(None, paths["train"], rig, path, geometry="cache", seed=7, ranges=ranges,
                   height=SIZE_HW[0], width=SIZE_HW[1], progress=False)  # fmt: skip
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/cross-rig"))
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--test-scenes", type=int, default=4)
    ap.add_argument("--test-frames", type=int, default=3)
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--plain-depth", action="store_true", help="predict metric depth directly (no canonical camera)"
    )
    add_update_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    args.work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    paths = build(args.work, args.scenes, args.frames, args.test_scenes, args.test_frames)
    originals = cache_images(paths["train"])
    sets = {"originals only": originals}
    for name in ("own rig", "random intrinsics", "random intrinsics + extrinsics"):
        sets[f"originals + renders, {name}"] = Images.join([originals, cache_images(paths[name])])
    tests = {rig: truth_images(paths[f"test-{rig}"]) for rig in TEST_SIZES}
    build_s = time.perf_counter() - t_start
    results: dict[str, list[dict[str, dict[str, float]]]] = {name: [] for name in sets}
    minutes: list[float] = []
    for seed in args.seeds:
        for name, data in sets.items():
            model, seconds = train(data, seed, args.steps, args.batch, args.lr, not args.plain_depth)
            minutes.append(seconds / 60)
            results[name].append({rig: score(model, t, not args.plain_depth) for rig, t in tests.items()})
            s = results[name][-1]
            print(f"seed {seed} {name}: nuscenes6 AbsRel {s['nuscenes6']['abs_rel']:.3f} "
                  f"waymo5 AbsRel {s['waymo5']['abs_rel']:.3f} ({seconds:.0f} s)", flush=True)  # fmt: skip

    def cell(name: str, rig: str, key: str, scale: float = 1.0, digits: int = 3) -> str:
        values = np.array([r[rig][key] * scale for r in results[name]])
        return f"{values.mean():.{digits}f} ± {values.std(ddof=1) if len(values) > 1 else 0.0:.{digits}f}"

    rows = []
    for name, data in sets.items():
        rows.append([
            name, len(data),
            cell(name, "nuscenes6", "abs_rel"), cell(name, "nuscenes6", "rmse_m", digits=2),
            cell(name, "nuscenes6", "delta", 100, 1),
            cell(name, "waymo5", "abs_rel"), cell(name, "waymo5", "delta", 100, 1),
        ])  # fmt: skip
    base = np.array([r["nuscenes6"]["abs_rel"] for r in results["originals only"]])
    gains = []
    for name in list(sets)[1:]:
        other = np.array([r["nuscenes6"]["abs_rel"] for r in results[name]])
        diff = other - base  # paired by seed: same initialisation and batches' seed
        gains.append([name, f"{diff.mean():+.3f} ± {diff.std(ddof=1) if len(diff) > 1 else 0.0:.3f}",
                      f"{int((diff < 0).sum())} / {len(diff)}"])  # fmt: skip
    n_test = {rig: len(t) for rig, t in tests.items()}
    report = Report(
        "cross_rig",
        "The cross-rig experiment: training on renders for other rigs (benchmarks/cross_rig.py)",
        "Monocular metric depth (SegFormer-tiny, one output: log depth"
        + (
            ")"
            if args.plain_depth
            else " in a canonical camera of fx = 150 px, scaled back by each image's fx)"
        )
        + " trained on a synthetic `waymo5` "
        f"cache ({args.scenes} scenes x {args.frames} frames x 5 cameras, 96 x 144, seed 200) with or "
        "without `phigenesis-render` renders of it (`--geometry cache`: the cache's own LiDAR-derived "
        "dense depth lifted, so renders carry labels from the same LiDAR as the originals; one rig per "
        "scene, 96 x 144), tested on held-out scenes (seed 300) of another rig, `nuscenes6` at 90 x 160 "
        f"({n_test['nuscenes6']} images), and of the same rig, `waymo5` ({n_test['waymo5']} images), against "
        f"the exact depth. Each model: {args.steps} steps of batch {args.batch}, AdamW (lr {args.lr}, "
        "warm-up then cosine), L1 of log depth on the labelled pixels, horizontal flips; seeds "
        f"{', '.join(map(str, args.seeds))} (a seed fixes the initialisation and the batches); training "
        f"{np.median(minutes):.1f} min per model on 2 CPU cores (median), caches and truth "
        f"{build_s / 60:.1f} min.",
    )
    report.table(
        "Depth from one image on the other rig (nuscenes6) and the same rig (waymo5), mean ± std over seeds",
        [
            "training set",
            "images",
            "nuscenes6 AbsRel",
            "nuscenes6 RMSE m",
            "nuscenes6 δ<1.25 %",
            "waymo5 AbsRel",
            "waymo5 δ<1.25 %",
        ],
        rows,
        note="Standard depth protocol: pixels with truth, both clamped to [1e-3, 80] m, metrics per image "
        "averaged. `own rig`: renders for the training cache's own cameras (pinhole), as many rendered "
        "images as the random rigs give: it separates more (rendered) data from new viewpoints.",
    )
    report.table(
        "Change of nuscenes6 AbsRel against originals only (paired by seed; negative is better)",
        ["training set", "AbsRel change, mean ± std", "seeds improved"],
        gains,
    )
    report.write(update=args.update)


if __name__ == "__main__":
    main()
