"""PhiGenesis: 4D driving-scene caches and lightweight 4D Gaussian models.

The public API, each name loaded on first use (``import phigenesis`` itself stays light):

- Caches: :mod:`phigenesis.prep` (``prep.synthetic``, ``prep.waymo``, ``prep.nuscenes``,
  ``prep.verify``, ``prep.preview``: the functions behind ``phigenesis-prep``); :class:`FrameDataset`
  (with :func:`collate_frames`) reads a cache into torch, :class:`CacheReader` reads its rows.
- Training: :func:`train_vae`, :func:`train_segmenter`, :func:`train_stage1`, :func:`train_stage2`.
- Evaluation: :func:`evaluate_stage1`, :func:`evaluate_stage2`.
- Use: :func:`generate` (Stage 2 rollouts as a cache), :func:`render` (a cache as another rig sees
  it), :func:`export_ply` (a frame's Gaussians as a 3DGS PLY file).
- Models: :func:`create_model`, :func:`list_models`, :func:`load_stage1`, :func:`load_stage2`.
"""

from __future__ import annotations

import importlib
from typing import Any

from phigenesis.version import __version__

#: Public name -> the module that defines it.
_API = {
    "prep": "phigenesis.prep",
    "FrameDataset": "phigenesis.data.loader",
    "collate_frames": "phigenesis.data.loader",
    "CacheReader": "phigenesis.data.shards",
    "train_vae": "phigenesis.train.vae",
    "train_segmenter": "phigenesis.train.segmenter",
    "train_stage1": "phigenesis.train.stage1",
    "train_stage2": "phigenesis.train.stage2",
    "evaluate_stage1": "phigenesis.eval.stage1",
    "evaluate_stage2": "phigenesis.eval.stage2",
    "generate": "phigenesis.infer.generate",
    "render": "phigenesis.infer.rig_render",
    "export_ply": "phigenesis.export.stage1",
    "create_model": "phigenesis.models",
    "list_models": "phigenesis.models",
    "load_stage1": "phigenesis.models.loading",
    "load_stage2": "phigenesis.models.loading",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    # Loaded on first use: the API spans every layer, and importing any submodule runs this file.
    if name not in _API:
        raise AttributeError(f"module 'phigenesis' has no attribute {name!r}")
    module = importlib.import_module(_API[name])
    value = module if name == "prep" else getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
