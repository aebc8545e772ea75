"""A lightweight SegFormer-style semantic segmenter (after Xie et al. 2021), written for this toolkit.

Layout (timm-style): blocks, model, init, config table, registered variants.

- **Encoder** (a "Mix Transformer"): four stages; each starts with an overlapping patch embedding
  (a strided convolution whose kernel is larger than its stride, so neighbouring patches share
  pixels) and stacks transformer blocks of *efficient self-attention* (keys and values come from
  the tokens reduced ``sr`` times per side by a strided convolution, so attention costs
  ``N * N / sr^2`` instead of ``N^2``) and a *Mix-FFN* (MLP with a 3x3 depth-wise convolution
  between its layers, which gives the positions that a positional encoding would). Strides 4, 2, 2,
  2: features at 1/4, 1/8, 1/16 and 1/32 of the input.
- **Decoder** (all-MLP): each stage's features are projected to ``decoder_dim`` channels by a
  linear layer (a 1x1 convolution), upsampled to 1/4 of the input, concatenated, fused by a
  linear layer and classified per pixel.

Symbols: B images, 3 colour channels, H x W pixels, K classes.
:meth:`SegFormer.forward` takes float32 RGB in [0, 1] ``[B, 3, H, W]`` (any size; ImageNet
normalisation happens inside) and returns logits ``[B, K, ceil(H/4), ceil(W/4)]``;
:meth:`SegFormer.predict` returns class probabilities at the input size.

Variants (``phigenesis.models.list_models()``): ``segformer_tiny`` (0.5 M parameters, for CPU tests
and benchmarks), ``segformer_b0`` and ``segformer_b1`` (the paper's MiT-B0/B1 sizes, for GPUs).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from phigenesis import taxonomy as tx
from phigenesis.models import register_model
from phigenesis.options import check_options, option
from phigenesis.torch_files import read_torch_file

#: ImageNet mean and standard deviation of RGB in [0, 1] (what pretrained encoders expect).
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# --------------------------------------------------------------------------------------------
# Blocks


class OverlapPatchEmbed(nn.Module):
    """Strided convolution with kernel > stride, then LayerNorm over channels.

    ``[B, C_in, H, W] -> ([B, N, C], h, w)`` with ``h = ceil(H / stride)``, ``N = h * w``.
    """

    def __init__(self, in_channels: int, dim: int, kernel: int, stride: int):
        super().__init__()
        self.proj = nn.Conv2d(in_channels, dim, kernel, stride, padding=kernel // 2)
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, int, int]:
        x = self.proj(x)  # [B, C, h, w]
        _, _, h, w = x.shape
        return self.norm(x.flatten(2).transpose(1, 2)), h, w  # [B, N, C]


class EfficientSelfAttention(nn.Module):
    """Multi-head self-attention whose keys and values come from tokens reduced ``sr`` times per
    side (a ``sr x sr`` convolution with stride ``sr``); ``sr = 1`` is plain attention.

    ``[B, N, C] -> [B, N, C]``, N = h * w tokens of an h x w map.
    """

    def __init__(self, dim: int, heads: int, sr: int):
        super().__init__()
        assert dim % heads == 0, (dim, heads)
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)
        self.sr = sr
        if sr > 1:
            self.reduce = nn.Conv2d(dim, dim, sr, sr)
            self.reduce_norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        b, n, c = x.shape
        assert n == h * w, (x.shape, h, w)
        q = self.q(x).reshape(b, n, self.heads, c // self.heads).transpose(1, 2)  # [B, heads, N, C/heads]
        kv_in = x
        if self.sr > 1 and min(h, w) >= self.sr:
            grid = x.transpose(1, 2).reshape(b, c, h, w)
            kv_in = self.reduce_norm(self.reduce(grid).flatten(2).transpose(1, 2))  # [B, N', C]
        kv = self.kv(kv_in).reshape(b, -1, 2, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, kv[0], kv[1])  # [B, heads, N, C/heads]
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class MixFFN(nn.Module):
    """Linear -> 3x3 depth-wise convolution -> GELU -> linear. ``[B, N, C] -> [B, N, C]``."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.dwconv = nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        x = self.fc1(x)  # [B, N, hidden]
        b, _, c = x.shape
        x = self.dwconv(x.transpose(1, 2).reshape(b, c, h, w)).flatten(2).transpose(1, 2)
        return self.fc2(F.gelu(x))


class DropPath(nn.Module):
    """Stochastic depth: drops a residual branch for a whole sample with probability ``p``."""

    def __init__(self, p: float):
        super().__init__()
        self.p = p

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        keep = torch.rand(x.shape[0], *([1] * (x.ndim - 1)), device=x.device) >= self.p
        return x * keep / (1.0 - self.p)


class Block(nn.Module):
    """Pre-norm transformer block: ``x + attn(norm(x))``, then ``x + ffn(norm(x))``."""

    def __init__(self, dim: int, heads: int, sr: int, mlp_ratio: float, drop_path: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = EfficientSelfAttention(dim, heads, sr)
        self.norm2 = nn.LayerNorm(dim)
        self.ffn = MixFFN(dim, int(dim * mlp_ratio))
        self.drop = DropPath(drop_path)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        x = x + self.drop(self.attn(self.norm1(x), h, w))
        return x + self.drop(self.ffn(self.norm2(x), h, w))


class Stage(nn.Module):
    """Patch embedding, blocks and a final LayerNorm: ``[B, C_in, H, W] -> [B, C, h, w]``."""

    def __init__(
        self, in_channels: int, dim: int, depth: int, heads: int, sr: int, kernel: int, stride: int,
        mlp_ratio: float, drop_paths: list[float],
    ):  # fmt: skip
        super().__init__()
        self.embed = OverlapPatchEmbed(in_channels, dim, kernel, stride)
        self.blocks = nn.ModuleList(Block(dim, heads, sr, mlp_ratio, p) for p in drop_paths[:depth])
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        tokens, h, w = self.embed(x)
        for block in self.blocks:
            tokens = block(tokens, h, w)
        return self.norm(tokens).transpose(1, 2).reshape(x.shape[0], -1, h, w)


class AllMLPDecoder(nn.Module):
    """Per-stage 1x1 projections to ``dim`` channels, upsampled to the first stage's size,
    concatenated, fused (1x1 conv, BatchNorm, ReLU) and classified.

    Features ``[B, C_i, h_i, w_i]`` (i = 1..4, h_1 = H/4) -> logits ``[B, K, h_1, w_1]``.
    """

    def __init__(self, in_dims: tuple[int, ...], dim: int, num_classes: int, dropout: float):
        super().__init__()
        self.proj = nn.ModuleList(nn.Conv2d(c, dim, 1) for c in in_dims)
        self.fuse = nn.Sequential(
            nn.Conv2d(dim * len(in_dims), dim, 1, bias=False), nn.BatchNorm2d(dim), nn.ReLU(inplace=True)
        )
        self.dropout = nn.Dropout2d(dropout)
        self.classify = nn.Conv2d(dim, num_classes, 1)

    def forward(self, features: list[torch.Tensor]) -> torch.Tensor:
        size = features[0].shape[-2:]
        up = [
            F.interpolate(p(f), size=size, mode="bilinear", align_corners=False) if i else p(f)
            for i, (p, f) in enumerate(zip(self.proj, features, strict=True))
        ]
        return self.classify(self.dropout(self.fuse(torch.cat(up[::-1], dim=1))))


# --------------------------------------------------------------------------------------------
# Model


#: Most encoder stages a SegFormer has.
MAX_STAGES = 8


@dataclass(frozen=True)
class SegFormerConfig:
    """Sizes of a SegFormer (per-stage tuples have one entry per stage, 4 stages).

    Attributes:
        embed_dims: channels of each stage.
        depths: transformer blocks per stage.
        num_heads: attention heads per stage.
        sr_ratios: key/value reduction per side in each stage's attention (1 = none).
        patch_sizes: patch-embedding kernel of each stage (pixels of the stage's input).
        strides: patch-embedding stride of each stage (the first gives 1/4 resolution).
        mlp_ratio: Mix-FFN hidden channels / stage channels.
        decoder_dim: channels of the all-MLP decoder.
        num_classes: K output classes (the unified taxonomy's 19).
        drop_path: stochastic-depth rate of the last block (linearly 0 -> this over all blocks).
        dropout: dropout before the classifier.
    """

    embed_dims: tuple[int, ...] = option((32, 64, 160, 256), ge=1, le=8192, help="channels per stage")
    depths: tuple[int, ...] = option((2, 2, 2, 2), ge=0, le=256, help="transformer blocks per stage")
    num_heads: tuple[int, ...] = option((1, 2, 5, 8), ge=1, le=256, help="attention heads per stage")
    sr_ratios: tuple[int, ...] = option((8, 4, 2, 1), ge=1, le=64, help="key/value reduction per side")
    patch_sizes: tuple[int, ...] = option((7, 3, 3, 3), ge=1, le=64, help="patch-embedding kernels")
    strides: tuple[int, ...] = option((4, 2, 2, 2), ge=1, le=64, help="patch-embedding strides")
    mlp_ratio: float = option(4.0, gt=0, le=64, help="Mix-FFN hidden channels over stage channels")
    decoder_dim: int = option(256, ge=1, le=8192, help="channels of the all-MLP decoder")
    num_classes: int = option(tx.NUM_CLASSES, ge=1, le=1024, help="K output classes")
    drop_path: float = option(0.1, ge=0, le=1, help="stochastic-depth rate of the last block")
    dropout: float = option(0.1, ge=0, le=1, help="dropout before the classifier")

    def __post_init__(self) -> None:
        check_options(self, "SegFormerConfig")
        n = len(self.embed_dims)
        if not 1 <= n <= MAX_STAGES:
            raise ValueError(f"SegFormerConfig: 1 to {MAX_STAGES} stages, got {n} embed_dims")
        lengths = {
            len(getattr(self, k)) for k in ("depths", "num_heads", "sr_ratios", "patch_sizes", "strides")
        }
        if lengths != {n}:
            raise ValueError(f"SegFormerConfig: per-stage tuples must all have {n} entries: {self}")
        bad = [(d, h) for d, h in zip(self.embed_dims, self.num_heads, strict=True) if d % h]
        if bad:
            raise ValueError(f"SegFormerConfig: stage channels must divide by their heads, got {bad}")

    def to_dict(self) -> dict[str, object]:
        """Plain values (tuples as lists), as stored in checkpoints."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict[str, object]) -> SegFormerConfig:
        return cls(**values)  # type: ignore[arg-type]


class SegFormer(nn.Module):
    """SegFormer: Mix Transformer encoder and all-MLP decoder (see the module docstring).

    Every model of :mod:`phigenesis.models` exposes ``name``, ``config``, ``forward`` and
    ``predict``.
    """

    def __init__(self, config: SegFormerConfig, name: str = "segformer"):
        super().__init__()
        self.name = name
        self.config = config
        c = config
        total = sum(c.depths)
        rates = [c.drop_path * i / max(total - 1, 1) for i in range(total)]
        stages, in_ch, start = [], 3, 0
        for i, dim in enumerate(c.embed_dims):
            stages.append(
                Stage(
                    in_ch, dim, c.depths[i], c.num_heads[i], c.sr_ratios[i], c.patch_sizes[i], c.strides[i],
                    c.mlp_ratio, rates[start : start + c.depths[i]],
                )
            )  # fmt: skip
            in_ch, start = dim, start + c.depths[i]
        self.stages = nn.ModuleList(stages)
        self.decoder = AllMLPDecoder(c.embed_dims, c.decoder_dim, c.num_classes, c.dropout)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.apply(_init_weights)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Logits ``[B, K, ceil(H/4), ceil(W/4)]`` (float32) of RGB ``[B, 3, H, W]`` in [0, 1]."""
        assert images.ndim == 4 and images.shape[1] == 3, images.shape
        x = (images - self.mean) / self.std
        features = []
        for stage in self.stages:
            x = stage(x)
            features.append(x)
        return self.decoder(features)

    @torch.no_grad()
    def predict(self, images: torch.Tensor) -> torch.Tensor:
        """Class probabilities ``[B, K, H, W]`` (float32, softmax) at the input's size, in eval mode.

        ``images``: ``[B, 3, H, W]`` uint8 RGB, or float in [0, 1].
        """
        if images.dtype == torch.uint8:
            images = images.float() / 255.0
        was_training = self.training
        self.eval()
        try:
            logits = self(images)
        finally:
            self.train(was_training)
        logits = F.interpolate(logits, size=images.shape[-2:], mode="bilinear", align_corners=False)
        return logits.softmax(dim=1)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


# --------------------------------------------------------------------------------------------
# Init


def _init_weights(m: nn.Module) -> None:
    """Truncated-normal linear layers, fan-out-scaled convolutions, unit norms."""
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, nn.Conv2d):
        fan_out = m.kernel_size[0] * m.kernel_size[1] * m.out_channels // m.groups
        nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / fan_out))
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, (nn.LayerNorm, nn.BatchNorm2d)):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)


# --------------------------------------------------------------------------------------------
# Config table and registered variants

CONFIGS: dict[str, SegFormerConfig] = {
    # CPU tests and benchmarks: 0.53 M parameters.
    "segformer_tiny": SegFormerConfig(
        embed_dims=(16, 32, 64, 128),
        depths=(1, 1, 2, 1),
        num_heads=(1, 1, 2, 4),
        sr_ratios=(8, 4, 2, 1),
        decoder_dim=64,
        drop_path=0.0,
        dropout=0.0,
    ),
    # MiT-B0 sizes (3.7 M parameters).
    "segformer_b0": SegFormerConfig(),
    # MiT-B1 sizes (13.7 M parameters).
    "segformer_b1": SegFormerConfig(embed_dims=(64, 128, 320, 512), num_heads=(1, 2, 5, 8), decoder_dim=256),
}


def _create(name: str, **overrides: object) -> SegFormer:
    """The variant ``name`` with config fields replaced by ``overrides`` (e.g. ``num_classes``)."""
    return SegFormer(dataclasses.replace(CONFIGS[name], **overrides), name=name)  # type: ignore[arg-type]


@register_model
def segformer_tiny(**overrides: object) -> SegFormer:
    """Tiny SegFormer for CPU tests and benchmarks."""
    return _create("segformer_tiny", **overrides)


@register_model
def segformer_b0(**overrides: object) -> SegFormer:
    """SegFormer with MiT-B0 sizes."""
    return _create("segformer_b0", **overrides)


@register_model
def segformer_b1(**overrides: object) -> SegFormer:
    """SegFormer with MiT-B1 sizes."""
    return _create("segformer_b1", **overrides)


# --------------------------------------------------------------------------------------------
# Pretrained weights in the Hugging Face layout (local files only)

#: Our parameter name prefixes -> the Hugging Face ``SegformerForSemanticSegmentation`` ones
#: (``{i}`` stage, ``{j}`` block), applied after the fused key/value weights are split.
_HF_NAMES = (
    ("stages.{i}.embed.proj.", "segformer.encoder.patch_embeddings.{i}.proj."),
    ("stages.{i}.embed.norm.", "segformer.encoder.patch_embeddings.{i}.layer_norm."),
    ("stages.{i}.blocks.{j}.norm1.", "segformer.encoder.block.{i}.{j}.layer_norm_1."),
    ("stages.{i}.blocks.{j}.attn.q.", "segformer.encoder.block.{i}.{j}.attention.self.query."),
    ("stages.{i}.blocks.{j}.attn.reduce.", "segformer.encoder.block.{i}.{j}.attention.self.sr."),
    ("stages.{i}.blocks.{j}.attn.reduce_norm.", "segformer.encoder.block.{i}.{j}.attention.self.layer_norm."),
    ("stages.{i}.blocks.{j}.attn.proj.", "segformer.encoder.block.{i}.{j}.attention.output.dense."),
    ("stages.{i}.blocks.{j}.norm2.", "segformer.encoder.block.{i}.{j}.layer_norm_2."),
    ("stages.{i}.blocks.{j}.ffn.fc1.", "segformer.encoder.block.{i}.{j}.mlp.dense1."),
    ("stages.{i}.blocks.{j}.ffn.dwconv.", "segformer.encoder.block.{i}.{j}.mlp.dwconv.dwconv."),
    ("stages.{i}.blocks.{j}.ffn.fc2.", "segformer.encoder.block.{i}.{j}.mlp.dense2."),
    ("stages.{i}.norm.", "segformer.encoder.layer_norm.{i}."),
    ("decoder.proj.{i}.", "decode_head.linear_c.{i}.proj."),
    ("decoder.fuse.0.", "decode_head.linear_fuse."),
    ("decoder.fuse.1.", "decode_head.batch_norm."),
    ("decoder.classify.", "decode_head.classifier."),
)


def load_hf_weights(model: SegFormer, path: str) -> SegFormer:
    """Loads a Hugging Face SegFormer checkpoint (a local ``pytorch_model.bin``, or
    ``model.safetensors`` where safetensors is installed; nothing is downloaded) into ``model``,
    whose config must match its sizes (``nvidia/segformer-b0-finetuned-cityscapes-*`` fits
    ``segformer_b0`` with the unified taxonomy's 19 classes, in the same order). Encoder-only
    checkpoints (``nvidia/mit-b0``) load the encoder and leave the decoder as initialised.
    Raises ValueError naming missing or mis-shaped weights."""
    if str(path).endswith(".safetensors"):
        from safetensors.torch import load_file  # optional dependency

        hf = load_file(path)
    else:
        hf = read_torch_file(path)
    hf = {k.removeprefix("module."): v for k, v in hf.items()}
    ours = model.state_dict()
    converted: dict[str, torch.Tensor] = {}
    for name, target in ours.items():
        source = _hf_name(name)
        if source is None:
            continue
        if name.endswith(("attn.kv.weight", "attn.kv.bias")):
            prefix, kind = source.rsplit(".", 2)[0], source.rsplit(".", 1)[1]
            parts = [hf.get(f"{prefix}.key.{kind}"), hf.get(f"{prefix}.value.{kind}")]
            value = None if any(p is None for p in parts) else torch.cat(parts)  # type: ignore[arg-type]
        else:
            value = hf.get(source)
        if value is None:
            continue
        if value.shape != target.shape and value.numel() == target.numel() and target.ndim == 4:
            value = value.reshape(target.shape)  # decoder linear layers are our 1x1 convolutions
        if value.shape != target.shape:
            raise ValueError(
                f"{path}: {source} has shape {tuple(value.shape)}, {name} needs {tuple(target.shape)}"
            )
        converted[name] = value
    missing_encoder = [n for n in ours if n.startswith("stages.") and n not in converted]
    if missing_encoder:
        raise ValueError(
            f"{path}: not a SegFormer checkpoint of this size; missing {missing_encoder[:3]} ..."
        )
    model.load_state_dict(converted, strict=False)
    return model


def _hf_name(name: str) -> str | None:
    """The Hugging Face name of our parameter ``name`` (for ``attn.kv``: ``...attention.self.kv.*``,
    split by the caller), or None for parameters it has no counterpart for."""
    m = re.match(r"(?:stages\.(\d+)\.(?:blocks\.(\d+)\.)?|decoder\.proj\.(\d+)\.)", name)
    index = {"i": (m.group(1) or m.group(3)) if m else "", "j": (m.group(2) or "") if m else ""}
    for ours, theirs in _HF_NAMES:
        prefix = ours.format(**index)
        if name.startswith(prefix):
            return theirs.format(**index) + name.removeprefix(prefix)
    if ".attn.kv." in name:
        return f"segformer.encoder.block.{index['i']}.{index['j']}.attention.self.kv.{name.rsplit('.', 1)[1]}"
    return None
