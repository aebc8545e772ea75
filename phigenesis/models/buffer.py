"""The Gaussian buffer: Stage 2's scene memory across rollout windows (the paper's 3D cache).

A rollout generates the future window by window. After each window, Stage 1 turns the generated frames
into a :class:`~phigenesis.models.gaussians.GaussianScene`, :meth:`GaussianBuffer.add` merges it into
the buffer, and the next window's condition is rendered from :meth:`GaussianBuffer.scene`.

Entry point: :class:`GaussianBuffer` (``add``, ``scene``, ``windows``, ``state_dict``,
``load_state_dict``). Everything is in the scene's world frame (metres) and in seconds after the
scene's ``time_origin_micros``, as in :class:`GaussianScene`: a Gaussian's ``means`` are its centre at
its own ``time_s`` and its centre at ``t`` is ``means + velocity * (t - time_s)``.

Rules, applied by every :meth:`GaussianBuffer.add` (window ``w``, the scene's newest time ``t_ref``):

1. **Moving or static.** A Gaussian moves in the buffer when the scene flags it ``dynamic`` (Stage 1
   thresholds its dynamic probability; :class:`GaussianScene` keeps only that flag) *and* it is
   faster than ``dynamic_speed_mps``. Everything else is stored static: velocity exactly zero, centre
   where it was observed (``means_at(time_s)`` unchanged). A parked car flagged dynamic then persists
   like the road instead of vanishing after one window ("model only what a scene needs").
2. **Re-basing.** Every moving Gaussian, old and new, is re-based to ``t_ref``: ``means`` become its
   centre at ``t_ref`` and ``time_s`` becomes ``t_ref``, so ``means_at(t)`` is unchanged for every
   ``t`` (up to float32 rounding) and all moving Gaussians share one reference time. Static Gaussians
   keep the time they were observed at (irrelevant to where they are).
3. **Static de-duplication, newest observation wins.** Voxels are ``floor(means / voxel_m)``. An old
   static Gaussian whose voxel holds a new static Gaussian is dropped ("replaced"): the newest window
   saw that place again, and what it generated is what the next window must continue. Gaussians within
   one added scene are never merged (near the camera one voxel holds many pixels' Gaussians, which
   together make the texture), so adding the same static scene twice leaves the count unchanged.
4. **Moving Gaussians: from the newest ``dynamic_windows`` windows only** (default 1: the newest
   window only). Without object identities an old copy of a moving thing can only be matched to its new
   copy by extrapolating it, and any error in its velocity (braking, turning) would leave a trail of
   ghost copies; so a moving Gaussian inserted at window ``v`` is dropped ("superseded") once
   ``w - v >= dynamic_windows``. The surviving older ones are de-duplicated against the new moving ones
   at the common time ``t_ref`` by voxel, as in rule 3. A car driving through 20 windows thus leaves
   at most ``dynamic_windows`` windows' worth of Gaussians, all near where it is now. Moving and static
   Gaussians are never de-duplicated against each other.
5. **The cap, oldest first.** When more than ``max_gaussians`` remain, Gaussians are evicted in this
   order: those farther than ``far_first_m`` from ``ego_position_world`` (when the ego is given), then
   by insertion window, oldest first; within a window the farthest from the ego first (without an ego,
   in a fixed pseudo-random order, so that no camera or frame of a window is dropped as a block). The
   newest window's Gaussians go only when it alone exceeds the cap.

Voxel keys pack the three integer voxel coordinates into one int64 (21 bits each), so every voxel
coordinate must lie in ``[-2**20, 2**20)``: +-209 km from the world origin at ``voxel_m = 0.2``.
No step loops over Gaussians in Python: adding a window's Gaussians to a full buffer
(de-duplication, re-basing and eviction included) is a few vectorised passes over both.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from phigenesis.models.gaussians import GaussianScene
from phigenesis.options import check_options, option

#: Bits per voxel coordinate in a packed voxel key (three of them fill 63 bits of an int64).
KEY_BITS = 21
#: Voxel coordinates must lie in ``[-KEY_HALF, KEY_HALF)``.
KEY_HALF = 1 << (KEY_BITS - 1)
#: Windows are numbered from 0 to ``MAX_WINDOW - 1`` (their offsets fill 31 bits of an eviction key).
MAX_WINDOW = 1 << 31
#: Seed of the fixed order in which one window's Gaussians are evicted when no ego is given.
_EVICTION_SEED = 0x5EED


@dataclass(frozen=True)
class BufferConfig:
    """How a :class:`GaussianBuffer` de-duplicates and bounds its contents (see the module docstring)."""

    voxel_m: float = option(0.2, gt=0, le=100, help="voxel edge for de-duplication, metres")
    max_gaussians: int = option(
        200_000, ge=1, le=100_000_000, help="the buffer holds at most this many Gaussians after every add"
    )
    dynamic_speed_mps: float = option(
        0.5, ge=0, le=1000, help="a dynamic-flagged Gaussian moves only when faster than this, m/s"
    )
    dynamic_windows: int = option(
        1, ge=1, le=1_000_000, help="a moving Gaussian is kept for this many windows (1: newest only)"
    )
    far_first_m: float | None = option(
        150.0, gt=0, le=1e6, help="over the cap, Gaussians farther than this from the ego go first, m"
    )

    def __post_init__(self) -> None:
        check_options(self, "BufferConfig")


@dataclass(frozen=True)
class AddStats:
    """What one :meth:`GaussianBuffer.add` did.

    ``size`` is the size before plus ``added`` minus ``replaced``, ``superseded`` and ``evicted``.
    """

    added: int  # Gaussians of the added scene that entered the buffer (before the cap)
    replaced: int  # older Gaussians dropped because a new one of the same kind took their voxel
    superseded: int  # moving Gaussians dropped for being ``dynamic_windows`` windows old
    evicted: int  # Gaussians dropped to respect ``max_gaussians`` (may include just-added ones)
    made_static: int  # dynamic-flagged Gaussians of the scene no faster than ``dynamic_speed_mps``
    size: int  # Gaussians in the buffer after the add


def voxel_keys(means: Tensor, voxel_m: float) -> Tensor:
    """(N,) int64 key of the voxel ``floor(means / voxel_m)`` of each of the (N, 3) centres (metres).

    Equal keys mean the same voxel. Raises ``ValueError`` when a voxel coordinate falls outside
    ``[-2**20, 2**20)`` (the packing's range: +-209 km at 0.2 m voxels).
    """
    assert means.ndim == 2 and means.shape[1] == 3, tuple(means.shape)
    coords = torch.floor(means.double() / voxel_m)  # (N, 3)
    outside = ((coords < -KEY_HALF) | (coords >= KEY_HALF)).any(dim=1)  # (N,)
    if bool(outside.any()):
        raise ValueError(
            f"voxel_keys: {int(outside.sum())} of {len(means)} centres lie farther than "
            f"{KEY_HALF * voxel_m:.0f} m from the world origin along an axis, beyond the voxel keys' "
            f"range at voxel_m = {voxel_m}"
        )
    c = coords.long() + KEY_HALF  # (N, 3) in [0, 2**21)
    return (c[:, 0] << (2 * KEY_BITS)) | (c[:, 1] << KEY_BITS) | c[:, 2]  # (N,)


def rebase(scene: GaussianScene, rows: Tensor, t_s: float) -> GaussianScene:
    """``scene`` with the Gaussians where ``rows`` (N,) bool is true re-based to time ``t_s`` (seconds).

    Their ``means`` become their centres at ``t_s`` and their ``time_s`` becomes ``t_s``, so that
    ``means_at(t)`` is the same for every ``t``; the other rows are untouched.
    """
    moved = scene.means_at(t_s)  # (N, 3)
    means = torch.where(rows[:, None], moved, scene.means)
    time_s = torch.where(rows, torch.full_like(scene.time_s, t_s), scene.time_s)
    return replace(scene, means=means, time_s=time_s)


def _empty_scene(
    num_classes: int = 0,
    entropy: bool = False,
    origin: int = 0,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
) -> GaussianScene:
    """A scene with no Gaussians and ``num_classes`` semantic classes."""

    def z(*shape: int, dtype: torch.dtype = dtype) -> Tensor:
        return torch.zeros(shape, dtype=dtype, device=device)

    return GaussianScene(
        means=z(0, 3),
        quats=z(0, 4),
        scales=z(0, 3),
        opacities=z(0),
        colors=z(0, 3),
        semantic_logits=z(0, num_classes),
        velocity=z(0, 3),
        dynamic=z(0, dtype=torch.bool),
        time_s=z(0),
        time_origin_micros=origin,
        depth_entropy=z(0) if entropy else None,
    )


def _gather(
    old: GaussianScene, old_rows: Tensor, new: GaussianScene, new_rows: Tensor | None
) -> GaussianScene:
    """The Gaussians ``old[old_rows]`` followed by ``new[new_rows]`` (all of ``new`` when None)."""
    tensors_new = new.tensors()
    values = {}
    for name, value in old.tensors().items():
        other = tensors_new[name] if new_rows is None else tensors_new[name][new_rows]
        values[name] = torch.cat([value[old_rows], other])
    return GaussianScene(**values, time_origin_micros=old.time_origin_micros)


def _non_finite(scene: GaussianScene) -> list[str]:
    """``"scene.FIELD: K of N Gaussians"`` for every floating field with NaN or Inf values."""
    problems = []
    for name, value in scene.tensors().items():
        if not value.is_floating_point() or value.numel() == 0:
            continue
        if bool(torch.isfinite(value.sum(dtype=torch.float64))):  # fast path: NaN and Inf propagate
            continue
        bad = ~torch.isfinite(value)
        if value.ndim > 1:
            bad = bad.flatten(1).any(dim=1)
        if bool(bad.any()):
            problems.append(f"scene.{name}: {int(bad.sum())} of {len(scene)} Gaussians NaN or Inf")
    return problems


class GaussianBuffer:
    """The scene memory of a Stage 2 rollout: the Gaussians of past windows, de-duplicated and bounded.

    Args: the fields of :class:`BufferConfig` (voxel size in metres, cap, speed threshold in m/s,
    windows a moving Gaussian is kept for, distance in metres beyond which Gaussians are evicted first).

    Example::

        buffer = GaussianBuffer(voxel_m=0.2, max_gaussians=200_000)
        for w in range(windows):
            condition = buffer.scene().render(world_from_camera, intrinsics, W, H, t_s)
            ...  # generate window w from the condition, reconstruct it with Stage 1 -> scene
            stats = buffer.add(scene, window=w, ego_position_world=ego_xyz)
    """

    def __init__(
        self,
        voxel_m: float = 0.2,
        max_gaussians: int = 200_000,
        dynamic_speed_mps: float = 0.5,
        dynamic_windows: int = 1,
        far_first_m: float | None = 150.0,
    ) -> None:
        self.config = BufferConfig(voxel_m, max_gaussians, dynamic_speed_mps, dynamic_windows, far_first_m)
        self._reset()

    def _reset(self) -> None:
        self._scene: GaussianScene | None = None  # None until the first add fixes origin, K, fields
        self._window = torch.zeros(0, dtype=torch.long)  # (N,) insertion window of each Gaussian
        self._latest_window = -1
        self._reference_time_s = 0.0

    def __len__(self) -> int:
        return 0 if self._scene is None else len(self._scene)

    @property
    def latest_window(self) -> int:
        """The newest window added, or -1 before the first add."""
        return self._latest_window

    @property
    def reference_time_s(self) -> float:
        """The time (seconds after the time origin) every moving Gaussian's ``means`` refer to."""
        return self._reference_time_s

    def scene(self) -> GaussianScene:
        """The buffer's Gaussians as one detached :class:`GaussianScene` (world frame, metres).

        Its tensors share storage with the buffer: do not modify them in place. Before the first add,
        an empty scene with no classes.
        """
        return _empty_scene() if self._scene is None else self._scene

    def windows(self) -> Tensor:
        """(N,) int64 window at which each of :meth:`scene`'s Gaussians was added, in the same order."""
        return self._window

    def _check(self, scene: GaussianScene, window: int) -> None:
        where = f"GaussianBuffer.add(window={window})"
        if not isinstance(scene, GaussianScene):
            raise TypeError(f"{where}: expected a GaussianScene, got {type(scene).__name__}")
        if not 0 <= window < MAX_WINDOW:
            raise ValueError(f"{where}: windows are numbered from 0 to {MAX_WINDOW - 1}")
        if window < self._latest_window:
            raise ValueError(f"{where}: window {self._latest_window} was already added; windows go forward")
        problems = _non_finite(scene)
        if problems:
            raise ValueError(f"{where}: " + "; ".join(problems))
        if not scene.means.is_floating_point():
            raise ValueError(f"{where}: scene.means must be floating point, got {scene.means.dtype}")
        if scene.dynamic.dtype != torch.bool:
            raise ValueError(f"{where}: scene.dynamic must be bool, got {scene.dynamic.dtype}")
        if self._scene is None:
            return
        mine = self._scene
        if scene.time_origin_micros != mine.time_origin_micros:
            raise ValueError(
                f"{where}: scene.time_origin_micros {scene.time_origin_micros} differs from the "
                f"buffer's {mine.time_origin_micros}"
            )
        if scene.num_classes != mine.num_classes:
            raise ValueError(
                f"{where}: scene has {scene.num_classes} semantic classes, the buffer {mine.num_classes}"
            )
        if (scene.depth_entropy is None) != (mine.depth_entropy is None):
            has = "has no" if scene.depth_entropy is None else "has a"
            raise ValueError(f"{where}: scene {has} depth_entropy, unlike the buffer's earlier windows")
        if scene.means.dtype != mine.means.dtype or scene.means.device != mine.means.device:
            raise ValueError(
                f"{where}: scene is {scene.means.dtype} on {scene.means.device}, the buffer "
                f"{mine.means.dtype} on {mine.means.device}"
            )

    def add(
        self,
        scene: GaussianScene,
        window: int,
        ego_position_world: Tensor | Sequence[float] | None = None,
    ) -> AddStats:
        """Merges one window's Gaussians into the buffer (rules 1-5 of the module docstring).

        Args:
            scene: the window's Gaussians (Stage 1 on its generated frames), world frame; detached here.
                The first add fixes the buffer's time origin, class count, ``depth_entropy`` presence,
                dtype and device; later scenes must match.
            window: the window's index, >= 0 and >= every earlier one (a window may be added in several
                parts).
            ego_position_world: (3,) the ego's position now, world frame, metres; orders eviction.

        Returns:
            What was added, replaced, superseded and evicted.

        Raises:
            ValueError: a NaN or Inf in any floating field of ``scene`` (the message names each field and
                how many Gaussians), a window earlier than the latest, a mismatched scene, or centres
                beyond the voxel keys' range. The buffer is unchanged then.
        """
        window = operator.index(window)
        self._check(scene, window)
        cfg = self.config
        scene = scene.detach()
        ego = None
        if ego_position_world is not None:
            ego = torch.as_tensor(ego_position_world, dtype=torch.float64).reshape(-1)
            if ego.shape != (3,) or not bool(torch.isfinite(ego).all()):
                raise ValueError(f"GaussianBuffer.add: ego_position_world must be 3 finite metres, got {ego}")
        old, old_window = self._scene, self._window
        if old is None:  # the first add fixes what every later scene must match
            old = _empty_scene(
                scene.num_classes,
                scene.depth_entropy is not None,
                scene.time_origin_micros,
                scene.means.dtype,
                scene.means.device,
            )
            old_window = old_window.to(scene.means.device)

        # Rule 1: only flagged and fast Gaussians move; the rest are static with zero velocity exactly.
        speed = scene.velocity.norm(dim=-1)  # (M,) m/s
        moving = scene.dynamic & (speed > cfg.dynamic_speed_mps)  # (M,)
        made_static = int((scene.dynamic & ~moving).sum())
        velocity = torch.where(moving[:, None], scene.velocity, torch.zeros_like(scene.velocity))
        new = replace(scene, velocity=velocity, dynamic=moving)

        # Rule 2: every moving Gaussian at the newest time of this scene (t_ref).
        t_ref = float(scene.time_s.max()) if len(scene) else self._reference_time_s
        new = rebase(new, moving, t_ref)
        old_moving = old.dynamic  # (N,)
        old = rebase(old, old_moving, t_ref)

        # Rule 4's age limit, then rules 3 and 4's voxel de-duplication (moving ones at t_ref).
        superseded = old_moving & (old_window <= window - cfg.dynamic_windows)  # (N,)
        keys_old = voxel_keys(old.means, cfg.voxel_m)  # (N,)
        keys_new = voxel_keys(new.means, cfg.voxel_m)  # (M,)
        replaced = torch.zeros_like(old_moving)  # (N,)
        for kind, candidates in ((old_moving & ~superseded, moving), (~old_moving, ~moving)):
            rows = kind.nonzero().squeeze(1)  # old rows of this kind (moving / static)
            replaced[rows] = torch.isin(keys_old[rows], keys_new[candidates])
        kept = (~(superseded | replaced)).nonzero().squeeze(1)  # (N',) old rows that stay
        windows = torch.cat([old_window[kept], torch.full((len(new),), window, device=old_window.device)])

        # Rule 5: the cap, over the candidates (kept old rows, then the new ones), by row index only.
        new_rows = None  # all of them
        excess = len(windows) - cfg.max_gaussians
        if excess > 0:
            means = torch.cat([old.means[kept], new.means])  # (N' + M, 3) moving ones at t_ref
            survive = torch.ones(len(windows), dtype=torch.bool, device=windows.device)
            survive[self._eviction_order(means, windows, ego)[:excess]] = False
            rows = survive.nonzero().squeeze(1)  # ascending: old rows first
            split = int((rows < len(kept)).sum())
            kept, new_rows, windows = kept[rows[:split]], rows[split:] - len(kept), windows[rows]
        merged = _gather(old, kept, new, new_rows)

        self._scene, self._window = merged, windows
        self._latest_window = window
        self._reference_time_s = t_ref
        return AddStats(
            added=len(new),
            replaced=int(replaced.sum()),
            superseded=int(superseded.sum()),
            evicted=max(excess, 0),
            made_static=made_static,
            size=len(merged),
        )

    def _eviction_order(self, means: Tensor, windows: Tensor, ego: Tensor | None) -> Tensor:
        """(N,) int64 row indices in the order rule 5 evicts them (first = first to go), given the
        (N, 3) centres now (world, metres) and the (N,) insertion windows.

        One sort of an int64 key: bit 62 "not far", bits 31-61 the window's offset from the oldest,
        bits 0-30 the tie-break (the distance in centimetres, farthest first, or a fixed
        pseudo-random number without an ego)."""
        n = len(windows)
        low = (1 << 31) - 1
        if ego is None:
            gen = torch.Generator().manual_seed(_EVICTION_SEED)
            tie = torch.randint(0, low + 1, (n,), generator=gen).to(windows.device)  # (N,)
            near = torch.ones_like(windows)
        else:
            dist = (means.double() - ego.to(means.device)).norm(dim=-1)  # (N,) metres
            tie = low - (dist * 100).round().clamp(max=low).long()  # (N,) farther: smaller
            limit = self.config.far_first_m
            near = torch.ones_like(windows) if limit is None else (dist <= limit).long()
        key = (near << 62) | ((windows - windows.min()) << 31) | tie  # (N,)
        return torch.argsort(key, stable=True)

    def state_dict(self) -> dict[str, Tensor]:
        """The buffer as plain tensors (no pickled objects): contents, windows, clock and config.

        Keys: ``gaussians.<field>`` for each :class:`GaussianScene` tensor (``depth_entropy`` only when
        present), ``window`` (N,) int64, and 0-d ``time_origin_micros``, ``latest_window``,
        ``reference_time_s`` (float64 seconds), ``initialized`` (bool) and ``config.<field>``
        (float64; ``far_first_m`` None is stored as inf). Loads with ``torch.load(weights_only=True)``.
        """
        scene = self.scene()
        state = {f"gaussians.{k}": v.detach().clone() for k, v in scene.tensors().items()}
        state["window"] = self._window.clone()
        state["time_origin_micros"] = torch.tensor(scene.time_origin_micros, dtype=torch.int64)
        state["latest_window"] = torch.tensor(self._latest_window, dtype=torch.int64)
        state["reference_time_s"] = torch.tensor(self._reference_time_s, dtype=torch.float64)
        state["initialized"] = torch.tensor(self._scene is not None)
        for f in fields(BufferConfig):
            value = getattr(self.config, f.name)
            state[f"config.{f.name}"] = torch.tensor(
                math.inf if value is None else value, dtype=torch.float64
            )
        return state

    def load_state_dict(self, state: Mapping[str, Tensor]) -> None:
        """Restores what :meth:`state_dict` gave, after checking it; the buffer's config must match.

        Raises:
            ValueError: a missing or non-tensor entry, a config that differs from this buffer's, shapes
                that do not agree, NaN or Inf values, or windows after ``latest_window``. The buffer is
                unchanged then.
        """
        where = "GaussianBuffer.load_state_dict"
        names = [
            f.name for f in fields(GaussianScene) if f.name not in ("time_origin_micros", "depth_entropy")
        ]
        required = [f"gaussians.{n}" for n in names] + ["window", "time_origin_micros", "latest_window"]
        required += ["reference_time_s", "initialized"] + [f"config.{f.name}" for f in fields(BufferConfig)]
        missing = [k for k in required if k not in state]
        if missing:
            raise ValueError(f"{where}: missing entries {missing}")
        not_tensors = [k for k, v in state.items() if not isinstance(v, Tensor)]
        if not_tensors:
            raise ValueError(f"{where}: entries {not_tensors} are not tensors")
        for f in fields(BufferConfig):
            mine = getattr(self.config, f.name)
            mine = math.inf if mine is None else float(mine)
            theirs = float(state[f"config.{f.name}"])
            if mine != theirs:
                raise ValueError(f"{where}: config.{f.name} is {theirs} in the state, {mine} in this buffer")
        values = {n: state[f"gaussians.{n}"] for n in names}
        if "gaussians.depth_entropy" in state:
            values["depth_entropy"] = state["gaussians.depth_entropy"]
        try:
            scene = GaussianScene(**values, time_origin_micros=int(state["time_origin_micros"]))
        except ValueError as error:
            raise ValueError(f"{where}: {error}") from None
        if scene.dynamic.dtype != torch.bool:
            raise ValueError(f"{where}: gaussians.dynamic must be bool, got {scene.dynamic.dtype}")
        problems = _non_finite(scene)
        if problems:
            raise ValueError(f"{where}: " + "; ".join(p.replace("scene.", "gaussians.") for p in problems))
        if bool((scene.velocity[~scene.dynamic] != 0).any()):
            raise ValueError(f"{where}: static Gaussians (dynamic false) with a non-zero velocity")
        window, latest = state["window"], int(state["latest_window"])
        if window.shape != (len(scene),) or window.dtype != torch.int64:
            raise ValueError(
                f"{where}: window is {window.dtype} {tuple(window.shape)}, expected int64 ({len(scene)},)"
            )
        if len(window) and (int(window.min()) < 0 or int(window.max()) > latest):
            raise ValueError(f"{where}: windows outside [0, latest_window = {latest}]")
        reference = float(state["reference_time_s"])
        if not math.isfinite(reference):
            raise ValueError(f"{where}: reference_time_s is {reference}")
        if not bool(state["initialized"]):
            self._reset()
            return
        self._scene = replace(scene, **{k: v.clone() for k, v in scene.tensors().items()})
        self._window = window.clone()
        self._latest_window = latest
        self._reference_time_s = reference


__all__ = ["KEY_BITS", "KEY_HALF", "AddStats", "BufferConfig", "GaussianBuffer", "rebase", "voxel_keys"]
