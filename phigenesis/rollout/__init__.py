"""Stage 2 rollouts, shared by training (``phigenesis-train stage2``), generation
(``phigenesis-generate``) and evaluation (``phigenesis-eval stage2``): the condition a window is
generated from (:mod:`~phigenesis.rollout.conditions`), the configs a Stage 2 checkpoint records
(:mod:`~phigenesis.rollout.config`) and the runner that rolls a scene out
(:mod:`~phigenesis.rollout.runner`)."""
