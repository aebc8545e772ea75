"""The geometric depth completion behind the ``complete_depth`` stage, one module per role.

- :mod:`~.params`: :class:`CompletionParams`, :class:`CompletionResult` and shared constants;
- :mod:`~.segments`: image segments (step 1) and segment labels;
- :mod:`~.planes`: robust plane fits of many segments at once (step 2);
- :mod:`~.completer`: one image's completion state, planes' fills and holes (steps 2-4);
- :mod:`~.facades`: ground and facades beyond the data (steps 5, 6d, 7);
- :mod:`~.thin`: thin structures, crowns, vehicles (steps 6-6c);
- :mod:`~.depth_map`: :func:`complete_depth_map`, one depth map in plain arrays.

The algorithm, step by step, and the stage: :mod:`phigenesis.data.stages.complete`.
"""
