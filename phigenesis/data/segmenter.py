"""Running a trained segmenter (``phigenesis-train segmenter``, a SegFormer) over camera images: the
first source of prep's pseudo-semantic labels (:mod:`phigenesis.data.stages.semantics`). Only a
pipeline that names a segmenter checkpoint loads PyTorch and the model registry."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # torch is imported only when a segmenter runs (pipelines without one skip it)
    import torch


@dataclass(frozen=True)
class SegmenterOutput:
    """A segmenter's answer for one image: class (H, W) uint8 and its probability (H, W) float32."""

    label: NDArray[np.uint8]
    confidence: NDArray[np.float32]


@dataclass
class Segmenter:
    """A loaded segmentation model and how to feed it.

    ``model.predict`` maps ``[B, 3, H, W]`` float RGB in [0, 1] to probabilities ``[B, K, H, W]``.
    """

    model: torch.nn.Module
    input_height: int | None = None
    device: str = "cpu"

    @classmethod
    def load(
        cls, path: str, model: str | None = None, input_height: int | None = None, device: str = "cpu"
    ) -> Segmenter:
        """The model of the checkpoint at ``path`` (which must be of variant ``model`` if given)."""
        # torch and the model registry load only when a segmenter checkpoint is given
        from phigenesis.models.checkpoint import load_checkpoint

        return cls(load_checkpoint(path, model, map_location=device).model.to(device), input_height, device)

    def segment(self, rgb: list[NDArray[np.uint8]]) -> list[SegmenterOutput]:
        """The most likely class (H, W) uint8 and its probability (H, W) float32 of each (H, W, 3)
        uint8 RGB image (images of one size go through the model as one batch)."""
        # torch loads only when a segmenter runs: pipelines without one never import it
        import torch
        import torch.nn.functional as F

        out: list[SegmenterOutput | None] = [None] * len(rgb)
        by_size: dict[tuple[int, int], list[int]] = {}
        for i, image in enumerate(rgb):
            by_size.setdefault(image.shape[:2], []).append(i)
        for (h, w), index in by_size.items():
            x = torch.from_numpy(np.stack([rgb[i] for i in index])).permute(0, 3, 1, 2).to(self.device)
            x = x.float() / 255.0  # [B, 3, H, W]
            if self.input_height is not None and self.input_height != h:
                size = (self.input_height, max(8, round(w * self.input_height / h)))
                x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
            prob = self.model.predict(x)  # [B, K, h', w']
            for k, i in enumerate(index):
                p = prob[k : k + 1]
                if p.shape[-2:] != (h, w):  # one image at a time: [K, H, W] can be large
                    p = F.interpolate(p, size=(h, w), mode="bilinear", align_corners=False)
                confidence, label = p[0].max(dim=0)
                out[i] = SegmenterOutput(label.to(torch.uint8).cpu().numpy(), confidence.cpu().numpy())
        return out  # type: ignore[return-value]
