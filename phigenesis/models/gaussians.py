"""A 4D Gaussian scene: what the Stage 1 adapter predicts, what the rasterizer renders and what
``phigenesis-export ply`` writes.

Every Gaussian lives in the scene's world frame (metres) at its own reference time ``time_s``
(seconds after ``time_origin_micros``, the scene's first frame in caches made by this toolkit). A
Gaussian moves at constant velocity: its centre at time ``t`` is ``means + velocity * (t - time_s)``.
Static Gaussians (``dynamic`` false) have zero velocity exactly, so they never drift.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from phigenesis.models.rasterizer import RenderOutput, rasterize


@dataclass(frozen=True)
class GaussianScene:
    """N Gaussians with geometry, appearance, semantics and motion (torch tensors on one device).

    Attributes:
        means: (N, 3) float32 centres, world frame, metres, at each Gaussian's ``time_s``.
        quats: (N, 4) float32 rotations ``w, x, y, z`` (world from Gaussian), unit norm.
        scales: (N, 3) float32 standard deviations along the Gaussian's axes, metres.
        opacities: (N,) float32 in [0, 1].
        colors: (N, 3) float32 RGB in [0, 1] (the images' sRGB values).
        semantic_logits: (N, K) float32 logits over the unified classes (K = 19), or (N, 0).
        velocity: (N, 3) float32 world-frame velocity, m/s; zero where ``dynamic`` is false.
        dynamic: (N,) bool, whether the Gaussian belongs to something that moves.
        time_s: (N,) float32 reference time of each Gaussian, seconds after ``time_origin_micros``.
        time_origin_micros: the time origin (int64 microseconds).
        depth_entropy: (N,) float32 entropy (nats) of the depth distribution each Gaussian's
            pixel predicted (Stage 1's bins head; one of Stage 2's uncertainty maps), or None.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    semantic_logits: Tensor
    velocity: Tensor
    dynamic: Tensor
    time_s: Tensor
    time_origin_micros: int = 0
    depth_entropy: Tensor | None = None

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "scales": (n, 3),
            "opacities": (n,),
            "colors": (n, 3),
            "velocity": (n, 3),
            "dynamic": (n,),
            "time_s": (n,),
        }
        if self.depth_entropy is not None:
            expected["depth_entropy"] = (n,)
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(
                    f"GaussianScene.{name}: shape {tuple(getattr(self, name).shape)}, expected {shape}"
                )
        if self.semantic_logits.ndim != 2 or self.semantic_logits.shape[0] != n:
            raise ValueError(f"GaussianScene.semantic_logits: shape {tuple(self.semantic_logits.shape)}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_classes(self) -> int:
        return int(self.semantic_logits.shape[1])

    def seconds(self, timestamp_micros: int) -> float:
        """Seconds of ``timestamp_micros`` after this scene's time origin."""
        return (int(timestamp_micros) - self.time_origin_micros) * 1e-6

    def means_at(self, t_s: float | Tensor) -> Tensor:
        """(N, 3) centres at time ``t_s`` (seconds after the time origin), world frame, metres."""
        return self.means + self.velocity * (t_s - self.time_s)[:, None]

    def tensors(self) -> dict[str, Tensor]:
        """Every per-Gaussian tensor by field name (optional ones only when present)."""
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "time_origin_micros"}
        return {k: v for k, v in values.items() if v is not None}

    def select(self, mask: Tensor) -> GaussianScene:
        """The Gaussians where ``mask`` (N,) bool is true (or at the given indices)."""
        return replace(self, **{k: v[mask] for k, v in self.tensors().items()})

    def detach(self) -> GaussianScene:
        return replace(self, **{k: v.detach() for k, v in self.tensors().items()})

    def to(self, device: str | torch.device) -> GaussianScene:
        return replace(self, **{k: v.to(device) for k, v in self.tensors().items()})

    @staticmethod
    def concatenate(scenes: list[GaussianScene]) -> GaussianScene:
        """One scene holding the Gaussians of all ``scenes`` (same time origin and class count)."""
        origins = {s.time_origin_micros for s in scenes}
        if len(origins) != 1:
            raise ValueError(f"GaussianScene.concatenate: different time origins {sorted(origins)}")
        names = {tuple(s.tensors()) for s in scenes}
        if len(names) != 1:
            raise ValueError("GaussianScene.concatenate: some scenes have a depth_entropy and others not")
        values = {name: torch.cat([s.tensors()[name] for s in scenes]) for name in names.pop()}
        return GaussianScene(**values, time_origin_micros=origins.pop())

    def render(
        self,
        world_from_camera: Tensor,
        intrinsics: Tensor,
        width: int,
        height: int,
        t_s: float | Tensor,
        *,
        semantics: bool = False,
        motion: bool = False,
        entropy: bool = False,
        values: Tensor | None = None,
        near: float = 0.2,
        backend: str = "auto",
    ) -> SceneRender:
        """Renders the scene at time ``t_s`` into C pinhole cameras.

        Args:
            world_from_camera: (C, 4, 4) camera poses (OpenCV axes), world frame.
            intrinsics: (C, 3, 3) pinhole matrices at ``width`` x ``height`` (pixel centres at integers).
            t_s: render time, seconds after the time origin: one for all cameras, or (C,) one per camera.
            semantics: also composite class probabilities (softmax of the logits).
            motion: also composite the velocities (a flow map, m/s, world frame).
            entropy: also render the depth entropy (needs ``depth_entropy``).
            values: (N,) one number x_i per Gaussian (e.g. how far a rollout trusts it), rendered as
                the depth is: ``sum w_i x_i / sum w_i`` over the blend weights w_i (``SceneRender.value``).
        """
        feats = [self.colors]
        if semantics:
            feats.append(torch.softmax(self.semantic_logits, dim=-1))
        if motion:
            feats.append(self.velocity)
        if entropy:
            if self.depth_entropy is None:
                raise ValueError("GaussianScene.render(entropy=True): this scene has no depth_entropy")
            feats.append(self.depth_entropy[:, None])
        if values is not None:
            if tuple(values.shape) != (len(self),):
                raise ValueError(
                    f"GaussianScene.render: values of shape {tuple(values.shape)}, expected ({len(self)},)"
                )
            feats.append(values.to(self.colors.dtype)[:, None])
        features = torch.cat(feats, dim=-1)
        dtype = self.means.dtype
        times = torch.as_tensor(t_s, dtype=torch.float64).reshape(-1).expand(world_from_camera.shape[0])
        # Cameras of one rig fire at different times (a rolling rig): one set of centres per
        # distinct time, all cameras in one pass.
        distinct, which = torch.unique(times, return_inverse=True)
        if len(distinct) == 1:
            means = self.means_at(float(distinct[0]))
        else:
            means = torch.stack([self.means_at(float(t)) for t in distinct])[which]  # (C, N, 3)
        out = rasterize(
            means,
            self.quats,
            self.scales,
            self.opacities,
            features,
            world_from_camera.to(dtype),
            intrinsics.to(dtype),
            width,
            height,
            near=near,
            backend=backend,  # type: ignore[arg-type]
        )
        return SceneRender.split(
            out, self.num_classes if semantics else 0, motion, entropy, values is not None
        )


@dataclass(frozen=True)
class SceneRender:
    """A :class:`GaussianScene` rendered into C cameras (no background: add ``(1 - alpha) * sky``)."""

    rgb: Tensor  # (C, H, W, 3) premultiplied colour in [0, 1]
    depth: Tensor  # (C, H, W) expected camera z-depth, metres; 0 where alpha is 0
    alpha: Tensor  # (C, H, W) accumulated opacity
    semantic_probs: Tensor | None  # (C, H, W, K) premultiplied class probabilities, if asked for
    velocity: Tensor | None  # (C, H, W, 3) premultiplied velocity, m/s, if asked for
    #: (C, H, W) depth entropy (nats) of what the pixel sees, ``sum w_i e_i / sum w_i`` as the depth
    #: is (not premultiplied; 0 where alpha is 0), if asked for.
    depth_entropy: Tensor | None = None
    #: (C, H, W) the per-Gaussian ``values`` given to :meth:`GaussianScene.render`, averaged as the
    #: depth is (0 where alpha is 0), if given.
    value: Tensor | None = None

    @staticmethod
    def split(
        out: RenderOutput, num_classes: int, motion: bool, entropy: bool = False, value: bool = False
    ) -> SceneRender:
        f = out.features
        sem = f[..., 3 : 3 + num_classes] if num_classes else None
        end = 3 + num_classes + (3 if motion else 0)
        vel = f[..., 3 + num_classes : end] if motion else None
        covered = out.alpha > 0

        def normalised(channel: int) -> Tensor:
            return torch.where(
                covered, f[..., channel] / out.alpha.clamp(min=1e-12), torch.zeros_like(out.alpha)
            )

        ent = normalised(end) if entropy else None
        val = normalised(end + int(entropy)) if value else None
        return SceneRender(
            rgb=f[..., :3],
            depth=out.depth,
            alpha=out.alpha,
            semantic_probs=sem,
            velocity=vel,
            depth_entropy=ent,
            value=val,
        )
