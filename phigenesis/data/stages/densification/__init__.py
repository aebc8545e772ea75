"""The densification methods behind the ``densify_depth`` stage, one module per role.

- :mod:`~.registry`: :data:`DENSIFIERS`, :class:`DensifyParams`, :class:`DenseResult`, constants;
- :mod:`~.support`: scale, occlusion test, support, confidence and the finish every method shares;
- :mod:`~.ipbasic`: the ``ipbasic`` method;
- :mod:`~.inverse_depth`: the ``planar``, ``guided`` and ``planar_guided`` methods;
- :mod:`~.depth_map`: :func:`densify`, one depth map with a registered method.

Importing any of them registers the built-in methods (this package imports their modules). The
conventions and the stage: :mod:`phigenesis.data.stages.densify`.
"""

from phigenesis.data.stages.densification import inverse_depth, ipbasic  # noqa: F401  (registers them)
