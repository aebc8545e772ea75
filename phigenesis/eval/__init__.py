"""Evaluation: the metrics the toolkit's evaluators share (the depth protocol, FID/KID from a local
TorchScript Inception) and the Stage 2 evaluator (``phigenesis-eval stage2``)."""
