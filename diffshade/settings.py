"""RenderSettings: the structural choices of code path, and the continuous soft parameters.

RenderSettings is a pytree. Its structural fields are static (part of the tree's
structure: changing one recompiles); its continuous fields are leaves (data: changing one
never recompiles, and they can be traced and differentiated, e.g. a sigma schedule or a
gradient with respect to gamma under `jit`). Pass it to `render` like any other argument.

Structural (static):
- shading: 'phong' (per fragment), 'gouraud' (per vertex, interpolated), 'flat' (per face,
  face normal at the centroid), 'flat_last' (OpenGL flat: the last vertex's lit colour).
- specular: 'blinn' (N.H) or 'phong' (R.V).
- clamp: clip colours to [0, 1] (per vertex for Gouraud/flat_last, per face for flat, per
  fragment for Phong, as OpenGL does).
- cull_backfaces: drop faces whose projected winding is clockwise.
- spot_edge: 'hard' (OpenGL's step at the cutoff) or 'smooth' (a sigmoid of width
  `spot_softness` degrees, differentiable with respect to the cutoff).
- raster: 'hard' (z-buffer) or 'soft' (SoftRas aggregation, see blend.py).
- faces_per_pixel: K, the fragment slots per pixel in soft mode.
- kernels: where the fragment ops run. 'host': compiled CPU kernels (numba, through host
  callbacks) for the face search and the per-fragment geometry and interpolation, with
  hand-written derivative rules so that every transform still works; 'jax': the same ops
  written in jax.numpy (a tile-binned face search), for accelerators and for exact
  higher-order derivatives; 'auto' (default): 'host' when JAX's default backend is the
  CPU with one device, 'jax' elsewhere (nothing then leaves the device; and the host
  kernels' callbacks do not shard: under XLA's SPMD partitioner they deadlock).
  DIFFSHADE_KERNELS=host or jax in the environment (read when a program is traced) says
  what 'auto' means instead; the command line sets it to 'jax' for a run on a fresh
  install, while the host kernels compile (diffshade.host.warmup).
- shadow_map_size: texels a side of each shadow map (diffshade.shading.shadows), for the lights
  with shadows=True; a scene without such a light compiles no shadow pass.

Continuous (data):
- sigma (pixels^2), gamma, soft_threshold: soft rasterization (see blend.py); the
  footprint radius is sqrt(sigma * ln((1 - t) / t)) pixels.
- spot_softness: degrees, the width of the smooth spot edge.
- shadow_bias: the shadow maps' depth bias, in texels, slope-scaled: a point at depth d
  is lit while d <= d_map + shadow_bias * texel(d) * (1 + tan(angle of incidence)).
- shadow_softness: soft raster's shadow edge, in texels: visibility =
  sigmoid((d_map + bias - d) / (shadow_softness * texel(d))) (hard raster: a step).
"""

import dataclasses
import os

import jax
import numpy as np

__all__ = ["AUTO_KERNELS", "KERNELS", "RASTER_MODES", "SHADING_MODES", "SPECULAR_MODELS",
           "SPOT_EDGES", "RenderSettings"]

SHADING_MODES = ("phong", "gouraud", "flat", "flat_last")
SPECULAR_MODELS = ("blinn", "phong")
SPOT_EDGES = ("hard", "smooth")
RASTER_MODES = ("hard", "soft")
KERNELS = ("auto", "host", "jax")
#: the environment variable that says what kernels="auto" means ("host" or "jax")
AUTO_KERNELS = "DIFFSHADE_KERNELS"
# sigma, gamma and spot_softness divide float32 values: below ~1e-38 their reciprocal
# overflows and the soft blend (or the smooth spot edge) turns into inf - inf = NaN
MIN_SCALE = 1e-30
DATA_FIELDS = ("spot_softness", "sigma", "gamma", "soft_threshold", "shadow_bias",
               "shadow_softness")


@dataclasses.dataclass(frozen=True)
class RenderSettings:
    shading: str = "phong"
    specular: str = "blinn"
    clamp: bool = True
    cull_backfaces: bool = False
    spot_edge: str = "hard"
    spot_softness: float = 2.0
    raster: str = "hard"
    faces_per_pixel: int = 8
    sigma: float = 1.0
    gamma: float = 1e-4
    soft_threshold: float = 1e-4
    kernels: str = "auto"
    shadow_map_size: int = 256
    shadow_bias: float = 1.5
    shadow_softness: float = 0.1

    def __post_init__(self):
        for name, allowed in (("shading", SHADING_MODES), ("specular", SPECULAR_MODELS),
                              ("spot_edge", SPOT_EDGES), ("raster", RASTER_MODES),
                              ("kernels", KERNELS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name}: got {getattr(self, name)!r}; expected one of {allowed}")
        for name in ("faces_per_pixel", "shadow_map_size"):
            k = getattr(self, name)
            if isinstance(k, bool) or not isinstance(k, int) or k < 1:
                raise ValueError(f"{name}: got {k!r}; expected an integer >= 1")
        for name in ("clamp", "cull_backfaces"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: got {getattr(self, name)!r}; expected True or False")
        for name in DATA_FIELDS:
            _check_type(name, getattr(self, name))
        if _all_python_numbers(self):
            self.validate()

    def validate(self):
        """Check the continuous fields' values (render's entry points call this): each a
        real scalar in its range. Tracers pass: they are data by design."""
        for name in ("spot_softness", "sigma", "gamma", "shadow_softness"):
            _check_value(name, getattr(self, name), lambda v: MIN_SCALE <= v < float("inf"),
                         f"a finite number >= {MIN_SCALE:g} (float32 must hold its reciprocal)")
        _check_value("soft_threshold", self.soft_threshold, lambda v: 0 < v < 0.5,
                     "a number in (0, 0.5)")
        _check_value("shadow_bias", self.shadow_bias, lambda v: 0 <= v < float("inf"),
                     "a finite number >= 0 (texels)")

    def use_host_kernels(self) -> bool:
        """Whether the fragment ops run as compiled host kernels (see `kernels`)."""
        kernels = self.kernels
        if kernels == "auto":
            kernels = os.environ.get(AUTO_KERNELS) or "auto"
            if kernels not in KERNELS:
                raise ValueError(f"{AUTO_KERNELS} (environment): got {kernels!r}; expected "
                                 f"one of {KERNELS}")
        if kernels == "auto":
            return jax.default_backend() == "cpu" and jax.local_device_count() == 1
        return kernels == "host"


def _check_type(name, value):
    """Reject what is never a continuous setting (strings, booleans, complex numbers,
    containers). Anything else may be a placeholder JAX puts in the pytree while
    transforming it (None, an object, an array of gradients or of a stacked batch), so
    values are checked only where they are the user's (`validate`)."""
    if isinstance(value, (bool, str, bytes, complex, np.bool_, list, tuple, dict)):
        raise ValueError(f"{name}: got {value!r}; expected a real number")


def _all_python_numbers(settings):
    return all(isinstance(getattr(settings, n), (int, float)) for n in DATA_FIELDS)


def _check_value(name, value, ok, expected):
    if isinstance(value, jax.core.Tracer):
        return
    if not isinstance(value, (int, float, np.ndarray, np.generic, jax.Array)) or isinstance(
            value, (bool, np.bool_)):
        raise ValueError(f"{name}: got {value!r}; expected {expected}")
    if np.ndim(value) != 0 or np.asarray(value).dtype.kind not in "fiu":
        raise ValueError(f"{name}: got {value!r}; expected a real scalar, {expected}")
    if not ok(float(value)):
        raise ValueError(f"{name}: got {value!r}; expected {expected}")


jax.tree_util.register_dataclass(
    RenderSettings, data_fields=list(DATA_FIELDS),
    meta_fields=[f.name for f in dataclasses.fields(RenderSettings) if f.name not in DATA_FIELDS])
