"""Stage 2 rollouts: a trained Stage 2 model with its Stage 1 model generates a scene's frames along
a trajectory, window by window (``window_frames`` frames each, the Stage 2 model's training window).
``phigenesis-generate`` (:mod:`phigenesis.infer.generate`) writes them as a cache and
``phigenesis-eval stage2`` (:mod:`phigenesis.eval.stage2`) scores them; both roll out with
:class:`Stage2Runner`. A rollout of ``frames`` frames from frame ``start`` on:

1. the history's Gaussians (window 0: the recorded history frames before ``start``, through the
   Stage 1 model or ``geometry``; later windows: what the rollout generated) live in a
   :class:`~phigenesis.models.buffer.GaussianBuffer` (static ones persist, moving ones move, bounded);
2. the buffer is rendered at every camera of the window at its own capture time, the chosen
   uncertainty map ``u`` computed (with ``generated_trust < 1``, scaled per pixel by the trust of the
   Gaussians it shows: 1 for the recorded history's, ``generated_trust`` for generated windows', so a
   rollout leans less on its own output than on what was observed), and the render's latent turned
   into Stereo Forcing's condition ``SF(u, z_ren)`` (:mod:`phigenesis.models.stereo_forcing`);
3. the denoiser samples the window's latents by Euler steps of the rectified flow with guidance
   ``omega`` (:func:`~phigenesis.models.flow.euler_sample`), the history's latents held at a small
   noise level (0 for recorded history, ``history_level`` for generated history: DFoT's
   stabilisation against drift); with render anchoring (``anchor > 0``) each latent cell of the
   window is pulled, after every step down to flow time ``anchor_until``, ``anchor * u`` of the way
   to the straight path from its starting noise to the latent of the render over Stage 1's sky
   (:class:`~phigenesis.models.flow.Anchor`): the render fixes the layout where u trusts it and the
   network fills the holes and finishes the details;
4. the latents go through the VAE decoder; with render pasting (``paste > 0``) each pixel of the
   decoded frame is then moved ``paste * u`` of the way to the render over Stage 1's sky (the
   render kept where u trusts it, the generation in the holes: a small VAE's decoding is blurrier
   than what it encodes, so a generated copy of the render falls below the render itself), and the
   frames are encoded again;
5. the Stage 1 adapter (:meth:`~phigenesis.models.stage1.Stage1Model.forward_latents`) turns the
   window's latents into its Gaussians (its written depth and classes); those of its newest
   ``lift_frames`` frames (by default as many as the history frames the model was trained with, the
   frames the next window takes as its history) join the buffer and condition the next window: each
   frame lifted adds its own copy of every surface it shows, at its own depth error, and five copies
   render as streaks from the next window's cameras (docs/design/stage2.md). With
   ``spawn_max_u < 1`` only pixels whose u is at most that (and moving things) add Gaussians: where
   the frame kept the render, the buffer keeps the Gaussians it came from rather than a copy of them
   lifted again through the VAE and Stage 1 (each such copy adds their errors).

Trajectories: ``recorded`` (the cache's own poses and capture times), ``shift:Xm`` (the recorded
ones moved X metres along the ego's +y, left; negative: right) or a JSON file (``{"frames":
[{"timestamp_micros": int, "world_from_ego": 4x4}, ...]}``, one entry per generated frame, strictly
increasing times after the history and below 2^62, rigid poses of plain numbers in the cache's world
frame, no other key; a regular file of at most 1 MiB; each camera at the recorded rig's extrinsics and
its recorded offset from the frame time).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from phigenesis.data import records
from phigenesis.data.clips import Stage1Clips
from phigenesis.data.records import (
    MAX_USER_MICROS,
    InvalidRecord,
)
from phigenesis.errors import CheckpointError, PhiGenesisError, argument
from phigenesis.models.buffer import BufferConfig, GaussianBuffer
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.dit import MultiViewDiT
from phigenesis.models.flow import Anchor, FixedFrames, euler_sample
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.loading import load_stage1
from phigenesis.models.stage1 import Stage1Model
from phigenesis.models.stereo_forcing import pool_to_latent, stereo_forcing
from phigenesis.models.uncertainty import DEFAULT_LP_TRUST, LEGACY_LP_TRUST, LpTrust, check_lp_trust
from phigenesis.options import check_options, option, same_as
from phigenesis.rollout.conditions import (
    GEOMETRY_SOURCES,
    ConditionKind,
    ConditionRender,
    GeometrySource,
    TargetCameras,
    history_scene,
    render_condition,
    sequence_plucker,
    truth_maps,
    uncertainty_maps,
    with_sky,
)
from phigenesis.rollout.config import trained_config
from phigenesis.user_files import check_keys, matrix_problem, read_small_file

log = logging.getLogger(__name__)


#: The largest guidance scale a rollout takes (guided samplers use about 1-10; 1e30 overflows the
#: guided velocity in float32).
MAX_OMEGA = 100.0
#: A rendered pixel below this alpha is a hole (no depth, no label) in the generated cache.
HOLE_ALPHA = 0.5
#: Rig shift trajectories: ``shift:2m``, ``shift:-1.5m``.
SHIFT_PATTERN = re.compile(r"^shift:(-?\d+(?:\.\d+)?)m$")


@dataclass(frozen=True)
class TrajectoryFrame:
    """Where the rig is at one generated frame (world frame of the cache, metres, microseconds)."""

    timestamp_micros: int
    world_from_ego: np.ndarray  # (4, 4) float64 at timestamp_micros
    camera_world_from_ego: np.ndarray  # (V, 4, 4) the ego pose at each camera's capture time
    camera_timestamp_micros: np.ndarray  # (V,) int64 capture times


@dataclass(frozen=True)
class GenerateOptions:
    """How a rollout samples (the CLI's options)."""

    uncertainty: ConditionKind = option(
        "localization_potential", help="SF's map: an uncertainty kind or none"
    )
    lp_trust: LpTrust | None = option(
        None, help="localization potential's mapping; None: as the model was trained"
    )
    omega: float = option(1.0, ge=0, le=MAX_OMEGA, help="guidance scale: v(z) + omega [v(z | SF) - v(z)]")
    steps: int = option(10, ge=1, le=10_000, help="Euler steps per window")
    shift: float = option(1.0, gt=0, le=100, help="time shift of the sampling grid")
    history_level: float = option(
        0.02, ge=0, lt=1, help="flow time generated history is held at (recorded history: 0)"
    )
    anchor: float = option(
        1.0, ge=0, le=1, help="render anchoring: each latent cell pulled anchor * u of the way to the render"
    )
    anchor_until: float = option(
        0.1, ge=0, lt=1, help="the anchor acts at flow times >= this (the rest is the network's)"
    )
    paste: float = option(
        1.0, ge=0, le=1, help="render pasting: each decoded pixel moved paste * u of the way to the render"
    )
    generated_trust: float = option(
        1.0, ge=0, le=1, help="u is scaled by this where the render shows generated windows' Gaussians"
    )
    spawn_max_u: float = option(
        1.0, ge=0, le=1, help="a generated pixel adds static Gaussians only where u is at most this"
    )
    lift_frames: int | None = option(
        None, ge=1, le=1024, help="a window's newest frames that join the buffer; None: the history's count"
    )
    geometry: GeometrySource | None = option(
        None, help="window 0's history Gaussians: stage1 | cache | truth; None: as trained"
    )
    voxel_m: float = same_as(BufferConfig, "voxel_m")
    max_gaussians: int = same_as(BufferConfig, "max_gaussians")
    seed: int = option(0, ge=0, le=2**32 - 1)

    def __post_init__(self) -> None:
        check_options(self, "GenerateOptions")


@dataclass
class Rollout:
    """What a rollout generated, per frame (N frames, V views of H x W at the model's size)."""

    images: Tensor  # [N, V, H, W, 3] RGB in [0, 1], the VAE's decoding of the generated latents (pasted)
    depth: Tensor  # [N, V, H, W] z-depth of the generated Gaussians, metres, 0 = none
    alpha: Tensor  # [N, V, H, W] their accumulated opacity
    semantic: Tensor  # [N, V, H, W] uint8 argmax class (SKY where alpha < HOLE_ALPHA)
    condition_rgb: Tensor  # [N, V, H, W, 3] the buffer's render each window was conditioned on
    u: Tensor  # [N, V, H, W] the uncertainty map it was weighed by (zeros for "none")
    trajectory: list[TrajectoryFrame]
    world_from_camera: Tensor  # [N, V, 4, 4]
    time_s: Tensor  # [N, V] seconds after time_origin_micros
    time_origin_micros: int
    windows: list[GaussianScene] = field(default_factory=list)  # what each window added to the buffer
    buffer_sizes: list[int] = field(default_factory=list)
    seconds_per_window: list[float] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# Trajectories


def recorded_trajectory(frames: list[dict[str, Any]]) -> list[TrajectoryFrame]:
    """The trajectory of loaded cache frames (loader dicts) as they were recorded."""
    return [
        TrajectoryFrame(
            int(f["frame_timestamp_micros"]),
            f["world_from_ego"].double().numpy(),
            f["camera_world_from_ego"].double().numpy(),
            f["camera_timestamp_micros"].numpy().astype(np.int64),
        )
        for f in frames
    ]


def shifted_trajectory(trajectory: list[TrajectoryFrame], metres: float) -> list[TrajectoryFrame]:
    """``trajectory`` with every pose moved ``metres`` along its own ego +y (left)."""
    shift = np.eye(4)
    shift[1, 3] = metres
    return [
        TrajectoryFrame(
            f.timestamp_micros,
            f.world_from_ego @ shift,
            f.camera_world_from_ego @ shift,
            f.camera_timestamp_micros,
        )
        for f in trajectory
    ]


class TrajectoryError(PhiGenesisError, ValueError):
    """A trajectory file that cannot be used: the message names the file, the entry and the key."""


#: Largest trajectory file read, bytes (as rig and path files).
MAX_TRAJECTORY_FILE_BYTES = 1 << 20
#: The keys of a trajectory file's entry.
TRAJECTORY_KEYS = ("timestamp_micros", "world_from_ego")


def load_trajectory_file(
    path: str | os.PathLike[str], count: int, rig: TrajectoryFrame, after_micros: int
) -> list[TrajectoryFrame]:
    """The ``count`` frames of a trajectory JSON file (format in the module docstring); each camera
    fires at its offset from the frame time in ``rig`` (a recorded frame).

    Raises:
        TrajectoryError: naming the file, the entry and the key, for anything but a regular file of
            at most :data:`MAX_TRAJECTORY_FILE_BYTES`, invalid JSON, a key other than ``frames`` (or,
            in an entry, than :data:`TRAJECTORY_KEYS`), a wrong length, a time that is not an
            integer in (``after_micros``, ``MAX_USER_MICROS``) after the previous one, or a pose that
            is not a rigid 4x4 matrix of numbers (numeric strings are not numbers).
    """
    path = Path(path)
    text = read_small_file(path, "trajectory file", TrajectoryError, MAX_TRAJECTORY_FILE_BYTES)
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as e:
        raise TrajectoryError(f"{path}: not a JSON trajectory ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        raise TrajectoryError(f'{path}: a trajectory is {{"frames": [...]}}, one entry per generated frame')
    entries = check_keys(doc, ["frames"], str(path), TrajectoryError)["frames"]
    if len(entries) != count:
        raise TrajectoryError(f"{path}: holds {len(entries)} frames, --frames asks for {count}")
    offsets = rig.camera_timestamp_micros - rig.timestamp_micros
    ego_offsets = np.linalg.inv(rig.world_from_ego) @ rig.camera_world_from_ego  # camera-time ego motion
    out, last = [], after_micros
    for i, e in enumerate(entries):
        t, pose = _trajectory_entry(f"{path}: frames[{i}]", e, last)
        out.append(TrajectoryFrame(t, pose, pose @ ego_offsets, t + offsets))
        last = t
    return out


def _trajectory_entry(where: str, e: Any, after_micros: int) -> tuple[int, np.ndarray]:
    """(timestamp_micros, world_from_ego) of one trajectory entry, checked (see
    :func:`load_trajectory_file`); ``where`` names the file and the entry."""
    check_keys(e, TRAJECTORY_KEYS, where, TrajectoryError)
    missing = [k for k in TRAJECTORY_KEYS if k not in e]
    if missing:
        raise TrajectoryError(f"{where}: needs {' and '.join(TRAJECTORY_KEYS)}; {missing[0]} is missing")
    t = e["timestamp_micros"]
    if not isinstance(t, int) or isinstance(t, bool):
        raise TrajectoryError(f"{where}.timestamp_micros: {t!r} is not an integer")
    if t <= after_micros:
        raise TrajectoryError(
            f"{where}.timestamp_micros: {t} is not after {after_micros} (time must increase)"
        )
    if t >= MAX_USER_MICROS:
        raise TrajectoryError(
            f"{where}.timestamp_micros: {t} is not below {MAX_USER_MICROS} (int64 microseconds)"
        )
    problem = matrix_problem(e["world_from_ego"], 4, 4)
    if problem is not None:
        raise TrajectoryError(f"{where}.world_from_ego: {problem}")
    try:
        pose = records.check_transform(f"{where}.world_from_ego", np.array(e["world_from_ego"], np.float64))
    except InvalidRecord as err:
        raise TrajectoryError(str(err)) from None
    return t, pose


# --------------------------------------------------------------------------------------------
# The rollout


def _cameras(
    traj: list[TrajectoryFrame],
    ego_from_camera: Tensor,
    intrinsics: Tensor,
    origin: int,
    size_hw: tuple[int, int],
) -> TargetCameras:
    wfe = torch.as_tensor(np.stack([f.camera_world_from_ego for f in traj]))  # [F, V, 4, 4]
    wfc = wfe @ ego_from_camera.double()[None]
    times = torch.as_tensor(np.stack([f.camera_timestamp_micros for f in traj]) - origin).double() * 1e-6
    return TargetCameras(wfc, intrinsics.float(), times, size_hw)


def _encode(stage1: Stage1Model, images: Tensor) -> Tensor:
    """[1, V, C, T_z, h, w] latents of [F, V, 3, H, W] images in [0, 1]."""
    return stage1.encode(images[None])


def _condition(
    denoiser: MultiViewDiT,
    denoiser_kind: str,
    stage1: Stage1Model,
    buffer_scene: GaussianScene,
    targets: TargetCameras,
    history: TargetCameras,
    options: GenerateOptions,
    generator: torch.Generator,
    trust: Tensor | None = None,
) -> tuple[ConditionRender, Tensor, Tensor]:
    """(the render, u [F, V, H, W], the SF condition of the targets [1, V, C + 1, T, h, w]).

    ``trust`` (N,) in [0, 1] per Gaussian of ``buffer_scene``: u is multiplied by its per-pixel
    average (None: by 1)."""
    render = render_condition(buffer_scene, targets, trust=trust)
    z_render = denoiser.normalize_latents(_encode(stage1, render.rgb.permute(0, 1, 4, 2, 3)))
    f, v = targets.frames, targets.views
    if denoiser_kind == "none":
        c = z_render.shape[2]
        return render, torch.zeros(f, v, *targets.size_hw), torch.zeros(1, v, c + 1, *z_render.shape[3:])
    hist_depth = render_condition(buffer_scene, history).depth
    bins = int(stage1.config.adapter_config.depth_bins)
    lp_trust: LpTrust = options.lp_trust or DEFAULT_LP_TRUST
    maps = uncertainty_maps(
        render, targets, history, hist_depth, bins, generator, 8, (denoiser_kind,), lp_trust
    )
    if denoiser_kind not in maps:
        raise ValueError(f"uncertainty {denoiser_kind!r}: the history's Gaussians carry no depth entropy")
    u = maps[denoiser_kind]
    if render.trust is not None:
        u = u * render.trust.clamp(0.0, 1.0)
    tc = int(stage1.vae.config.temporal_compression)
    u_lat = pool_to_latent(u.permute(1, 0, 2, 3), tuple(z_render.shape[-2:]), tc)  # [V, T_z, h, w]
    return render, u, stereo_forcing(u_lat[None], z_render)


def _window_scene(
    stage1: Stage1Model,
    z: Tensor,
    cams: TargetCameras,
    origin: int,
    spawn: Tensor | None,
    lift_frames: int,
) -> tuple[GaussianScene, GaussianScene]:
    """The Gaussians Stage 1 builds from generated latents [1, V, C, T_z, h, w] at ``cams``: those of
    every frame (what the window shows: its written depth and classes) and the part that joins the
    buffer, the newest ``lift_frames`` frames' (the same scene when that is every frame).

    ``spawn`` [F, V, H, W] bool: the pixels whose static Gaussians may enter (moving ones always do,
    since the buffer keeps moving Gaussians of the newest window only); None: every pixel."""
    pred = stage1.forward_latents(
        z, cams.intrinsics[None], cams.world_from_camera[None].float(), cams.time_s[None].float()
    )
    threshold = stage1.config.dynamic_threshold
    keep = pred.default_keep(0)  # [F, V, H, W]
    if spawn is not None:
        keep = keep & (spawn | (pred.dynamic_prob[0] > threshold))
    scene = pred.scene(0, keep=keep, dynamic_threshold=threshold, time_origin_micros=origin)
    if lift_frames >= cams.frames:
        return scene, scene
    keep[: cams.frames - lift_frames] = False  # the older frames stay out of the buffer
    return scene, pred.scene(0, keep=keep, dynamic_threshold=threshold, time_origin_micros=origin)


def generated_trust(windows: Tensor, options: GenerateOptions) -> Tensor | None:
    """(N,) trust of the buffer's Gaussians by the window that added them (window 0: the recorded
    history, 1; later windows: generated, ``options.generated_trust``), or None when every Gaussian
    would get 1."""
    if options.generated_trust >= 1 or not bool((windows > 0).any()):
        return None
    return torch.where(windows == 0, 1.0, float(options.generated_trust))


@torch.no_grad()
def rollout(
    denoiser: MultiViewDiT,
    stage1: Stage1Model,
    history_clip: Any,
    trajectory: list[TrajectoryFrame],
    ego_from_camera: Tensor,
    window_frames: int,
    options: GenerateOptions,
    truth: dict[str, Tensor] | None = None,
    progress: bool = False,
) -> Rollout:
    """Generates one frame per entry of ``trajectory`` after the recorded ``history_clip`` (a Stage
    1 clip whose context is the history), window by window (see the module docstring).
    ``options.geometry`` None is ``stage1`` here (:meth:`Stage2Runner.resolve` fills in the trained one)."""
    denoiser.eval()
    stage1.eval()
    origin = int(history_clip.time_origin_micros)
    size = tuple(history_clip.context.images.shape[-2:])
    k = history_clip.intrinsics
    ctx = history_clip.context
    t_h = ctx.images.shape[0]
    tc = int(stage1.vae.config.temporal_compression)
    generator = torch.Generator().manual_seed(int(options.seed))
    buffer = GaussianBuffer(voxel_m=options.voxel_m, max_gaussians=options.max_gaussians)
    first = history_scene(options.geometry or "stage1", history_clip, stage1, **(truth or {}))  # type: ignore[arg-type]
    buffer.add(first, window=0)
    hist_cams = TargetCameras(ctx.world_from_camera, k, ctx.time_s, size)
    hist_images, level = ctx.images, 0.0
    n = len(trajectory)
    windows = math.ceil(n / window_frames)
    # Pad the last window with its last pose (frames past the end are generated and dropped).
    padded = trajectory + [trajectory[-1]] * (windows * window_frames - n)
    out: dict[str, list[Tensor]] = {
        k_: [] for k_ in ("images", "depth", "alpha", "semantic", "cond", "u", "wfc", "t")
    }
    result = Rollout(
        *(torch.empty(0),) * 6,
        trajectory=trajectory,
        world_from_camera=torch.empty(0),
        time_s=torch.empty(0),
        time_origin_micros=origin,
    )

    for w in tqdm(range(windows), disable=not progress, unit="window", desc="generate"):
        tic = time.perf_counter()
        cams = _cameras(padded[w * window_frames : (w + 1) * window_frames], ego_from_camera, k, origin, size)
        trust = generated_trust(buffer.windows(), options)
        render, u, cond_t = _condition(
            denoiser, options.uncertainty, stage1, buffer.scene(), cams, hist_cams, options, generator, trust
        )
        z_hist = denoiser.normalize_latents(_encode(stage1, hist_images))  # [1, V, C, T_zh, h, w]
        t_zh = z_hist.shape[3]
        t_z = cond_t.shape[3]
        v, c = z_hist.shape[1], z_hist.shape[2]
        hw = tuple(z_hist.shape[-2:])
        condition = torch.cat([torch.zeros(1, v, c + 1, t_zh, *hw), cond_t], dim=3)
        plucker = sequence_plucker(hist_cams, cams, (t_zh, t_z), hw, tc)[None]
        z0 = torch.cat([z_hist, torch.zeros(1, v, c, t_z, *hw)], dim=3)
        mask = torch.zeros(t_zh + t_z, dtype=torch.bool)
        mask[:t_zh] = True
        noise = torch.randn(z0.shape, generator=generator)
        fixed = FixedFrames(mask=mask, z0=z0, level=level)

        def velocity(
            z: Tensor, t: Tensor, cnd: Tensor | None, plucker: Tensor = plucker, zero: Tensor = condition
        ) -> Tensor:
            return denoiser(z, t, cnd if cnd is not None else torch.zeros_like(zero), plucker)

        cond_arg = None if options.uncertainty == "none" else condition
        anchor = full = None
        if options.uncertainty != "none" and (options.anchor > 0 or options.paste > 0):
            full = with_sky(render, stage1, cams).permute(0, 1, 4, 2, 3)  # [F, V, 3, H, W]
        if options.anchor > 0 and full is not None:
            # The render over Stage 1's sky, where u trusts it (u is the condition's last channel).
            weight = options.anchor * condition[:, :, c:]  # [1, V, 1, T_zh + T_z, h, w]; 0 for history
            z_full = denoiser.normalize_latents(_encode(stage1, full))
            z_ref = torch.cat([torch.zeros_like(z_hist), z_full], dim=3)
            anchor = Anchor(z0=z_ref, weight=weight, until=options.anchor_until)
        z = euler_sample(
            velocity,
            noise,
            options.steps,
            options.shift,
            options.omega,
            cond_arg,
            fixed,
            generator,
            anchor=anchor,
        )
        if not torch.isfinite(z).all():
            raise FloatingPointError(f"window {w}: the sampler produced NaN or Inf latents")
        z_gen = denoiser.denormalize_latents(z[:, :, :, t_zh:])  # the VAE's latents again
        images = stage1.decode(z_gen)[0]  # [F, V, 3, H, W]
        if options.paste > 0 and full is not None:
            images = torch.lerp(images, full, (options.paste * u)[:, :, None].to(images.dtype))
            z_gen = _encode(stage1, images)  # the Gaussians of the frames as they are kept
        spawn = u <= options.spawn_max_u if options.spawn_max_u < 1 else None
        shown, scene = _window_scene(stage1, z_gen, cams, origin, spawn, options.lift_frames or t_h)
        if first.depth_entropy is None:
            # History lifted from the cache or the truth has no depth distributions: the buffer keeps
            # one kind of Gaussian, so the generated windows' entropy is left out too.
            scene = dataclasses.replace(scene, depth_entropy=None)
        ego = torch.as_tensor(padded[(w + 1) * window_frames - 1].world_from_ego[:3, 3]).float()
        buffer.add(scene.detach(), window=w + 1, ego_position_world=ego)
        # The generated scene's depth and classes: its own Gaussians, or, where trusted pixels kept
        # the buffer's instead (spawn), everything the buffer now holds. (The whole buffer for every
        # window was measured: AbsRel a little lower, delta < 1.25 and RMSE a little worse.)
        own = render_condition(shown.detach() if spawn is None else buffer.scene(), cams, semantics=True)
        result.windows.append(scene.detach())
        result.buffer_sizes.append(len(buffer))
        out["images"].append(images.permute(0, 1, 3, 4, 2))
        out["depth"].append(own.depth)
        out["alpha"].append(own.alpha)
        assert own.semantic is not None
        out["semantic"].append(own.semantic)
        out["cond"].append(render.rgb)
        out["u"].append(u)
        out["wfc"].append(cams.world_from_camera)
        out["t"].append(cams.time_s)
        # The next window's history: the last generated frames, held at a small noise level.
        hist_images = images[-t_h:]
        hist_cams = TargetCameras(cams.world_from_camera[-t_h:], k, cams.time_s[-t_h:], size)
        level = options.history_level
        result.seconds_per_window.append(time.perf_counter() - tic)
    cat = {k_: torch.cat(v_)[:n] for k_, v_ in out.items()}
    result.images, result.depth, result.alpha = cat["images"].clamp(0, 1), cat["depth"], cat["alpha"]
    result.semantic, result.condition_rgb, result.u = cat["semantic"], cat["cond"], cat["u"]
    result.world_from_camera, result.time_s = cat["wfc"], cat["t"]
    return result


# --------------------------------------------------------------------------------------------
# The runner


def _stage2_checkpoint(path: str | os.PathLike[str]) -> tuple[MultiViewDiT, dict[str, Any]]:
    """(the denoiser, its training config as recorded) of a Stage 2 checkpoint, the config checked
    by the training config's own checks (:func:`phigenesis.rollout.config.trained_config`);
    CheckpointError otherwise."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.safetensors"
    ckpt = load_checkpoint(path, kind="dit")
    assert isinstance(ckpt.model, MultiViewDiT), type(ckpt.model)  # every "dit" variant is one
    train = ckpt.meta.get("train")
    trained_config(path, train)
    return ckpt.model, train


def trained_uncertainty(ckpt: str | os.PathLike[str]) -> str:
    """The uncertainty kind a Stage 2 checkpoint was trained with."""
    return str(_stage2_checkpoint(ckpt)[1].get("uncertainty", "localization_potential"))


def trained_lp_trust(train: dict[str, Any], where: str) -> LpTrust:
    """The localization potential's mapping the Stage 2 checkpoint ``where``, with training config
    ``train``, was trained with: its ``lp_trust``, or the one there was before the choice existed
    (:data:`LEGACY_LP_TRUST`); CheckpointError for another value."""

    try:
        return check_lp_trust(
            train.get("lp_trust", LEGACY_LP_TRUST), f"{where}: its training config's lp_trust"
        )
    except ValueError as e:
        raise CheckpointError(str(e)) from None


def trained_geometry(train: dict[str, Any], where: str) -> str:
    """The geometry source the Stage 2 checkpoint ``where``, with training config ``train``, was
    trained on (its condition renders): its ``geometry``, ``stage1`` when the config predates the
    field; CheckpointError for another value."""

    geometry = train.get("geometry", "stage1")
    if geometry not in GEOMETRY_SOURCES:
        raise CheckpointError(
            f"{where}: its training config's geometry must be one of {GEOMETRY_SOURCES}, got {geometry!r}"
        )
    return str(geometry)


class Stage2Runner:
    """A trained Stage 2 model with its Stage 1 model over a frame cache: rolls scenes out.

    ``stage1``: the Stage 1 checkpoint (default: the one the Stage 2 model was trained with).
    Raises CheckpointError for a checkpoint that is not Stage 2's, ValueError for a cache Stage 1
    cannot read."""

    def __init__(
        self,
        ckpt: str | os.PathLike[str],
        shards: str | os.PathLike[str],
        stage1: str | os.PathLike[str] | None = None,
    ):
        self.ckpt, self.shards = str(ckpt), str(shards)
        self.denoiser, self.train = _stage2_checkpoint(ckpt)
        stage1_path = stage1 or self.train.get("stage1_checkpoint")
        if not stage1_path:
            stage1_arg = argument("stage1=", "--stage1")
            raise CheckpointError(f"{ckpt}: names no Stage 1 checkpoint; pass {stage1_arg}")
        self.stage1_path = str(stage1_path)
        self.stage1 = load_stage1(stage1_path)
        self.window = int(self.train["window_frames"])
        self.history_frames = int(self.train["history_frames"])
        self.lp_trust = trained_lp_trust(self.train, self.ckpt)
        self.geometry = trained_geometry(self.train, self.ckpt)
        self.data = Stage1Clips(shards, self.stage1.config.image_size, self.history_frames, "auto")

    def resolve(self, options: GenerateOptions | None) -> GenerateOptions:
        """``options`` (default: :class:`GenerateOptions`) with what they leave to the model filled
        in from its training config: the localization potential's mapping and the history's geometry
        source (a model trained on the truth's renders is sampled on them unless told otherwise)."""
        options = options or GenerateOptions()
        if options.lp_trust is None:
            options = dataclasses.replace(options, lp_trust=self.lp_trust)
        if options.geometry is None:
            options = dataclasses.replace(options, geometry=self.geometry)
        return options

    def check(self, scene: str, start: int, frames: int, trajectory: str) -> None:
        """Raises ValueError naming what is wrong with a rollout request."""
        if frames < 1:
            raise ValueError(f"--frames must be at least 1, got {frames}")
        if scene not in self.data.scenes:
            known = ", ".join(sorted(self.data.scenes)[:10])
            raise ValueError(f"scene {scene!r} is not in {self.shards} (scenes: {known})")
        length = self.data.scene_length(scene)
        t_h = self.history_frames
        if not t_h <= start < length:
            raise ValueError(
                f"--start {start}: scene {scene} has frames 0..{length - 1}; "
                f"generation needs {t_h} recorded history frame(s) before --start"
            )
        if (trajectory == "recorded" or SHIFT_PATTERN.match(trajectory)) and start + frames > length:
            raise ValueError(
                f"--frames {frames} from --start {start} runs past the end of scene {scene} "
                f"({length} frames): a {trajectory} trajectory needs recorded poses; "
                f"at most {length - start} frames"
            )

    def run(
        self,
        scene: str,
        start: int,
        frames: int,
        trajectory: str = "recorded",
        options: GenerateOptions | None = None,
        progress: bool = False,
    ) -> tuple[Rollout, Any]:
        """(the rollout, the history clip) of ``frames`` frames of ``scene`` from ``start`` on."""
        options = self.resolve(options)
        clip, traj = self.inputs(scene, start, frames, trajectory)
        return self.roll_out(clip, traj, start, options, progress), clip

    def inputs(
        self, scene: str, start: int, frames: int, trajectory: str
    ) -> tuple[Any, list[TrajectoryFrame]]:
        """(the history clip, the trajectory) of a rollout request, checked: ValueError naming what
        is wrong (:meth:`check`, a bad trajectory file) before anything is generated."""
        self.check(scene, start, frames, trajectory)
        t_h = self.history_frames
        clip = self.data.clip(scene, start - t_h, [], keep_frames=True)
        assert clip.frames is not None
        length = self.data.scene_length(scene)
        loaded = [self.data._frame(scene, i) for i in range(start, min(start + frames, length))]
        rig = recorded_trajectory([clip.frames[start - 1]])[0]
        if trajectory == "recorded":
            traj = recorded_trajectory(loaded)
        elif m := SHIFT_PATTERN.match(trajectory):
            traj = shifted_trajectory(recorded_trajectory(loaded), float(m.group(1)))
        else:
            traj = load_trajectory_file(trajectory, frames, rig, rig.timestamp_micros)
        return clip, traj

    def roll_out(
        self, clip: Any, traj: list[TrajectoryFrame], start: int, options: GenerateOptions, progress: bool
    ) -> Rollout:
        """The rollout along ``traj`` from the history ``clip`` of :meth:`inputs` (``options``
        resolved by :meth:`resolve`)."""
        truth = None
        if options.geometry == "truth":
            depth, sem, flow = truth_maps(clip)
            truth = {"truth_depth_m": depth, "truth_semantic": sem, "truth_flow_mps": flow}
        ego_from_camera = clip.frames[start - 1]["ego_from_camera"]
        return rollout(
            self.denoiser, self.stage1, clip, traj, ego_from_camera, self.window, options, truth, progress
        )
