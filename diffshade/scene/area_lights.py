"""Area and extended lights as scene objects: `area_light` (a rectangle or a disk) and
`sphere_light`, checked at the boundary. How they light a surface (their radiometric
convention, the closed form and the sample patterns) is diffshade.shading.area's.
"""

import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype
from diffshade.scene.lights import (
    DiskLight,
    RectLight,
    SphereLight,
    _array,
    _colours,
    _direction,
    _scalar,
    _shadows,
)

#: the most samples a light may have: each sample is a point light per shaded fragment
#: (and, with shadows, a shadow map), so the count bounds a render's memory
MAX_SAMPLES = 4096


def _sample_count(samples):
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or not (
            1 <= samples <= MAX_SAMPLES):
        raise ValueError(f"samples: got {samples!r}; expected an integer in [1, {MAX_SAMPLES}]")
    return int(samples)


def _radius(radius):
    value = _scalar("radius", radius, "a finite number >= 0")
    if value < 0:
        raise ValueError(f"radius: got {radius!r}; expected a finite number >= 0")
    return jnp.asarray(value, float_dtype())


def area_light(center, edge_u=None, edge_v=None, *, normal=None, radius=None, color=None,
               ambient=0.0, diffuse=None, specular=None, samples=16, shadows=False):
    """A rectangle (center and edge vectors edge_u, edge_v: it spans center + s edge_u +
    t edge_v, s, t in [-1/2, 1/2], and emits towards edge_u x edge_v) or a disk (center,
    normal: the side it emits towards, radius). A zero-size light is allowed (a zero
    rectangle emits nothing: it has no normal). samples: the count of the sampled terms;
    shadows=True: a shadow map from each sample point (penumbrae; module docstring)."""
    rect = edge_u is not None or edge_v is not None
    disk = normal is not None or radius is not None
    if rect == disk:
        got = "both a rectangle's edges and a disk's normal" if rect else "neither"
        raise ValueError(f"edge_u, normal: got {got}; expected edge_u and edge_v (a "
                         "rectangle) or normal and radius (a disk)")
    count, flag = _sample_count(samples), _shadows(shadows)
    colours = _colours(color, ambient, diffuse, specular)
    centre = _array("center", center, (3,))
    if rect:
        return RectLight(centre, _array("edge_u", edge_u, (3,)), _array("edge_v", edge_v, (3,)),
                         *colours, samples=count, shadows=flag)
    if radius is None or normal is None:
        missing = "radius" if radius is None else "normal"
        raise ValueError(f"{missing}: missing; expected a disk's normal and radius")
    return DiskLight(centre, _direction("normal", normal), _radius(radius), *colours,
                     samples=count, shadows=flag)


def sphere_light(position, radius, color=None, *, ambient=0.0, diffuse=None, specular=None,
                 samples=16, shadows=False) -> SphereLight:
    """A spherical light of the given radius (0: a point light with 1/d^2 falloff);
    shadows as `area_light`'s."""
    return SphereLight(_array("position", position, (3,)), _radius(radius),
                       *_colours(color, ambient, diffuse, specular),
                       samples=_sample_count(samples), shadows=_shadows(shadows))
