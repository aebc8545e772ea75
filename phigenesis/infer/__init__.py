"""Generation and rendering from trained models: ``phigenesis-generate`` writes Stage 2 rollouts
(:class:`phigenesis.rollout.runner.Stage2Runner`) as a cache (:mod:`.generate`); ``phigenesis-render``
renders a cache for another rig (:mod:`.rig_render`, :mod:`.rigs`) with inserted assets
(:mod:`.insert`, :mod:`.asset_files`).
"""
