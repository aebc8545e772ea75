"""The densification methods' registry: :data:`DENSIFIERS` by name (:func:`register_densifier`),
their shared parameter class :class:`DensifyParams` (the ``densify_depth`` stage's YAML keys, each
method's keyword parameters declared once with type and range), their result
:class:`DenseResult`, and the constants they share (:data:`REFERENCE_FOCAL_PX`, the default
methods).

Conventions: :mod:`phigenesis.data.stages.densify`.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.records import (
    TRUSTED_DEPTH_CONFIDENCE,
)
from phigenesis.options import ConfigError, check_options, from_mapping, option

log = logging.getLogger("phigenesis.prep")


#: Focal length (pixels) at which ``*_ref_px`` parameters are given: KITTI's (about 721 px).
REFERENCE_FOCAL_PX = 721.0
#: The method :func:`densify` and the stage use unless told otherwise.
DEFAULT_DENSIFIER = "guided"
#: What the stage runs on a camera without an image when the method needs one.
DEFAULT_FALLBACK = "ipbasic"
#: Quadrant radius of the enclosure test, as a multiple of the fill distance.
ENCLOSURE_FACTOR = 1.5
#: Default of the stage's ``min_sparse_coverage``: a camera with a sparse depth on fewer of its
#: pixels than this share (over a scene) is warned about. The synthetic test scenes measure 3-50 %
#: per camera (16- to 64-beam LiDARs, 60x90 to 96x160 images); a camera the ego body hid, 0 %.
MIN_SPARSE_COVERAGE = 0.01
# Stand-ins for 0 and infinity that keep arithmetic finite: masks are applied by multiplying,
# since np.where is slow on the scattered masks of sparse depth.
_TINY = np.float32(1e-12)
_FAR = np.float32(1e30)

F32 = NDArray[np.float32]
Mask = NDArray[np.bool_]


@dataclass
class DenseResult:
    """A densified depth map.

    Attributes:
        depth_m: (H, W) float32 z-depth in metres, 0 where still unknown.
        confidence: (H, W) float32 in [0, 1], exactly 0 where ``depth_m`` is 0.
    """

    depth_m: F32
    confidence: F32


Densifier = Callable[..., DenseResult]
#: The registered methods by name.
DENSIFIERS: dict[str, Densifier] = {}
_NEEDS_RGB: set[str] = set()
Blur = Literal["bilateral", "gaussian", "none"]
EdgeFilter = Literal["dtf", "fgs"]


@dataclass(frozen=True)
class DensifyParams:
    """Parameters of the ``densify_depth`` stage: the stage's own, then every method's keyword
    parameters, each declared once here with its type and range (None: not given, so the method
    keeps its own default; a method is given only the parameters it takes, and naming one it does
    not take is an error). ``*_ref_px`` lengths are pixels at :data:`REFERENCE_FOCAL_PX`.

    Attributes:
        method: the registered method (:data:`DENSIFIERS`) run on every camera.
        fallback: the method run on a camera without an image when ``method`` needs one (it gets
            those of the given parameters it takes); it must not need the image.
        min_confidence: sparse depths below this confidence (depth-edge pixels) seed nothing.
        min_sparse_coverage: share of a camera's pixels, over the scene, below which its sparse
            depth is warned about.
        max_depth_m ... keep_tau: ``ipbasic``'s (see :func:`ipbasic`).
        window_ref_px, min_spread_px, residual_tol, edge_sigma_ref_px: ``planar``'s plane fits.
        edge_filter, smooth_ref_px, sigma_color, min_image_support: ``guided``'s image-guided mean.
        occlusion_ref_px, occlusion_tau: see-through samples dropped (all but ``ipbasic``).
        max_fill_ref_px, extrapolate_top, conf_distance_ref_px, conf_relative_depth: what every
            method may fill and the confidence of what it fills (densify.py's docstring).
    """

    method: str = option(DEFAULT_DENSIFIER)
    fallback: str = option(DEFAULT_FALLBACK)
    min_confidence: float = option(TRUSTED_DEPTH_CONFIDENCE, ge=0, le=1)
    min_sparse_coverage: float = option(MIN_SPARSE_COVERAGE, ge=0, le=1)
    max_depth_m: float | None = option(None, gt=0, le=1000)
    blur: Blur | None = option(None)
    dilate_ref_px: float | None = option(None, ge=0, le=1000)
    close_ref_px: float | None = option(None, ge=0, le=1000)
    fill_ref_px: float | None = option(None, ge=0, le=1000)
    blur_ref_px: float | None = option(None, gt=0, le=1000)
    bilateral_sigma_m: float | None = option(None, gt=0, le=1000)
    keep_measured: bool | None = option(None)
    keep_tau: float | None = option(None, ge=0, le=10)
    window_ref_px: float | None = option(None, ge=0, le=1000)
    min_spread_px: float | None = option(None, ge=0, le=1000)
    residual_tol: float | None = option(None, ge=0, le=10)
    edge_sigma_ref_px: float | None = option(None, gt=0, le=1000)
    edge_filter: EdgeFilter | None = option(None)
    smooth_ref_px: float | None = option(None, gt=0, le=1000)
    sigma_color: float | None = option(None, gt=0, le=1000)
    min_image_support: float | None = option(None, ge=0, le=1)
    occlusion_ref_px: float | None = option(None, ge=0, le=1000)
    occlusion_tau: float | None = option(None, ge=0, le=10)
    max_fill_ref_px: float | None = option(None, ge=0, le=10_000)
    extrapolate_top: bool | None = option(None)
    conf_distance_ref_px: float | None = option(None, gt=0, le=10_000)
    conf_relative_depth: float | None = option(None, gt=0, le=10)

    def __post_init__(self) -> None:
        check_options(self, "DensifyParams")
        for key in ("method", "fallback"):
            name = getattr(self, key)
            if name not in DENSIFIERS:
                known = sorted(DENSIFIERS)
                raise ConfigError(f"DensifyParams: {key} = {name!r}: must be one of {known}")
        if needs_rgb(self.fallback):
            raise ConfigError(f"DensifyParams: fallback = {self.fallback!r}: must not need the image")
        stage_keys = {"method", "fallback", "min_confidence", "min_sparse_coverage"}
        given = [f.name for f in dataclasses.fields(self) if f.name not in stage_keys]
        foreign = [k for k in given if getattr(self, k) is not None and k not in method_params(self.method)]
        if foreign:
            raise ConfigError(
                f"DensifyParams: method {self.method!r} takes no parameters {foreign}; it takes "
                f"{sorted(method_params(self.method))}"
            )

    def method_kwargs(self, method: str) -> dict[str, Any]:
        """The given parameters (not None) that ``method`` takes, as its keyword arguments."""
        values = {k: getattr(self, k) for k in method_params(method)}
        return {k: v for k, v in values.items() if v is not None}


def register_densifier(name: str, *, needs_rgb: bool = False) -> Callable[[Densifier], Densifier]:
    """Decorator registering a densification method under ``name``.

    The method is ``fn(sparse_m, sparse_confidence, rgb, focal_px, *, **params) -> DenseResult``
    with keyword-only parameters, each a field of :class:`DensifyParams` (its type and range are
    declared there, once for every method; ValueError otherwise); ``needs_rgb``: it uses the image
    and raises ValueError when ``rgb`` is None.
    """

    def wrap(fn: Densifier) -> Densifier:
        if name in DENSIFIERS and DENSIFIERS[name] is not fn:
            raise ValueError(f"a densifier named {name!r} is already registered")
        declared = {f.name for f in dataclasses.fields(DensifyParams)}
        undeclared = sorted(k for k, _ in _keyword_params(fn) if k not in declared)
        if undeclared:
            raise ValueError(
                f"densifier {name!r}: parameters {undeclared} are not declared in DensifyParams "
                "(each needs its type and range there)"
            )
        DENSIFIERS[name] = fn
        if needs_rgb:
            _NEEDS_RGB.add(name)
        return fn

    return wrap


def get_densifier(method: str) -> Densifier:
    """The method registered as ``method``; KeyError naming the registered ones otherwise."""
    if method not in DENSIFIERS:
        raise KeyError(f"unknown densifier {method!r}; registered: {sorted(DENSIFIERS)}")
    return DENSIFIERS[method]


def needs_rgb(method: str) -> bool:
    """Whether the method ``method`` needs the RGB image."""
    get_densifier(method)
    return method in _NEEDS_RGB


def method_params(method: str) -> dict[str, Any]:
    """The keyword parameters of ``method`` with their defaults."""
    return dict(_keyword_params(get_densifier(method)))


@functools.cache
def _keyword_params(fn: Densifier) -> tuple[tuple[str, Any], ...]:
    sig = inspect.signature(fn)
    return tuple(
        (p.name, p.default) for p in sig.parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY
    )


def check_params(method: str, params: dict[str, Any]) -> None:
    """Raises :class:`~phigenesis.options.ConfigError` (a ValueError) if ``params`` holds a name
    that ``method`` does not accept or a value outside its type or range (:class:`DensifyParams`)."""
    accepted = method_params(method)
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise ConfigError(f"densifier {method!r}: unknown parameters {unknown}; accepted: {sorted(accepted)}")
    from_mapping(DensifyParams, {**params, "method": method}, f"densifier {method!r}")
