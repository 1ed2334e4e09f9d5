"""RenderSettings: the hashable choices of code path, static under `jit`.

Changing a setting recompiles; changing a scene array does not. Values:
- shading: 'phong' (per fragment), 'gouraud' (per vertex, interpolated), 'flat' (per face,
  face normal at the centroid), 'flat_last' (OpenGL flat: the last vertex's lit colour).
- specular: 'blinn' (N.H) or 'phong' (R.V).
- clamp: clip colours to [0, 1] (per vertex for Gouraud/flat_last, per face for flat, per
  fragment for Phong, as OpenGL does).
- cull_backfaces: drop faces whose projected winding is clockwise.
- spot_edge: 'hard' (OpenGL's step at the cutoff) or 'smooth' (a sigmoid of width
  `spot_softness` degrees, differentiable with respect to the cutoff).
- raster: 'hard' (z-buffer) or 'soft' (SoftRas aggregation, see blend.py).
- faces_per_pixel (K), sigma (pixels^2), gamma, soft_threshold: soft rasterization
  parameters (see blend.py); the footprint radius is sqrt(sigma * ln((1 - t) / t)) pixels.
"""

import dataclasses

SHADING_MODES = ("phong", "gouraud", "flat", "flat_last")
SPECULAR_MODELS = ("blinn", "phong")
SPOT_EDGES = ("hard", "smooth")
RASTER_MODES = ("hard", "soft")
# sigma, gamma and spot_softness divide float32 values: below ~1e-38 their reciprocal
# overflows and the soft blend (or the smooth spot edge) turns into inf - inf = NaN
MIN_SCALE = 1e-30


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

    def __post_init__(self):
        for name, allowed in (("shading", SHADING_MODES), ("specular", SPECULAR_MODELS),
                              ("spot_edge", SPOT_EDGES), ("raster", RASTER_MODES)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name}: got {getattr(self, name)!r}; expected one of {allowed}")
        k = self.faces_per_pixel
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"faces_per_pixel: got {k!r}; expected an integer >= 1")
        for name in ("clamp", "cull_backfaces"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: got {getattr(self, name)!r}; expected True or False")
        for name in ("spot_softness", "sigma", "gamma"):
            value = getattr(self, name)
            if not (_is_number(value) and MIN_SCALE <= value < float("inf")):
                raise ValueError(f"{name}: got {value!r}; expected a finite number >= "
                                 f"{MIN_SCALE:g} (float32 must hold its reciprocal)")
        if not (_is_number(self.soft_threshold) and 0 < self.soft_threshold < 0.5):
            raise ValueError(f"soft_threshold: got {self.soft_threshold!r}; expected (0, 0.5)")


def _is_number(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool)
