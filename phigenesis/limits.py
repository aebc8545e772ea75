"""Upper bounds of the trainers' declared options (:mod:`phigenesis.options`): generous, but a value
past them is a typo or an attack, not a training run. Each trainer's config declares its own
defaults and lower bounds beside these."""

from __future__ import annotations

MAX_STEPS = 10**9
MAX_BATCH = 65_536
#: Adam moves each weight by about the learning rate per step: past 1 that is no longer training.
MAX_LR = 1.0
#: AdamW's decoupled weight decay (each step multiplies weights by 1 - lr * weight_decay).
MAX_WEIGHT_DECAY = 1.0
MAX_GRAD_CLIP = 1e6
MAX_LOSS_WEIGHT = 1e4
#: Seeds combine as (seed * 1_000_003 + step) * 131 + rank (``runner.step_generator``), which must
#: fit torch's 64-bit seed.
MAX_SEED = 2**32 - 1
MAX_THREADS = 1024
#: The longest side of an image a trainer resizes to (pixels).
MAX_IMAGE_SIDE = 16_384
MAX_CACHE_MB = 1e7
