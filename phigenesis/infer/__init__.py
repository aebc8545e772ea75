"""Inference that export, evaluation, generation and rendering share.

Stage 2 lives here: rectified flow and its sampler (:mod:`.flow`), Stereo Forcing's condition
(:mod:`.stereo_forcing`), the uncertainty maps it weighs the rendered condition by
(:mod:`.uncertainty`) and the Gaussian buffer that carries a scene across rollout windows
(:mod:`.buffer`).
"""
