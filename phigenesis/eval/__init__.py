"""Evaluation: every evaluator (Stage 1, ``phigenesis-eval stage1``: :mod:`.stage1`; Stage 2,
``phigenesis-eval stage2``: :mod:`.stage2`) and the metrics they share (the depth protocol, scene
flow, FID/KID from a local TorchScript Inception)."""
