"""The lighting core: Blinn-Phong / Phong with OpenGL 1.x fixed-function semantics.

    I = ke + ka*Ia_global + sum_i att_i * spot_i * (ka*Ia_i + kd*Id_i*max(N.L, 0)
                                                      + ks*Is_i*f_i*max(N.H, 0)^n)

with H = normalize(L + V) (Blinn) or the Phong variant max(R.V, 0)^n, R = 2(N.L)N - L;
f_i = 1 where N.L > 0, else 0; att = 1/(a + b d + c d^2) for point and spot lights;
spot = max(-L.D, 0)^e inside the cutoff cone, 0 outside (OpenGL 1.x spec, section 2.14.1).

`shade` is written for one sample and broadcasts over any leading shape: points, normals
and view_dirs are [..., 3]; material fields broadcast against [..., 3] (so a per-pixel
material, as two-sided lighting needs, works too). All vectors are world space; the
caller passes unit normals and unit directions *towards* the viewer. Absent light types,
`ks=None` and `emission=None` are skipped at trace time: no code is compiled for them.
Area and sphere lights (diffshade.shading.area) add their terms through the same
`_light_terms`, once per light sample.
"""

import dataclasses

import jax
import jax.numpy as jnp

from diffshade.numerics import dot, safe_norm, safe_normalize, safe_pow, tiny
from diffshade.scene.lights import LightGroups
from diffshade.scene.materials import Material
from diffshade.shading import area
from diffshade.shading.shadows import ShadowMap, sampled_visibility, visibility


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ShadingParts:
    """The parts of the lit colour, each [..., 3]; `total` is their (unclamped) sum."""

    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    emission: jax.Array

    @property
    def total(self):
        return self.ambient + self.diffuse + self.specular + self.emission

    def map(self, fn):
        """Apply `fn` to every part (e.g. interpolation or a gather)."""
        return jax.tree.map(fn, self)


def _unstack(group):
    """The lights of a stacked group, one pytree per light (the count is static)."""
    count = jax.tree.leaves(group)[0].shape[0]
    return [jax.tree.map(lambda a, i=i: a[i], group) for i in range(count)]


def _attenuation(coeffs, dist):
    """1 / (a + b d + c d^2): coeffs [3], dist [..., 1] -> [..., 1]. The denominator is
    floored at tiny(dtype) (continuously, by max): with a = 0 (pure inverse square) it
    reaches 0 at d = 0, and the light at a surface point must stay finite, gradient too."""
    den = coeffs[0] + coeffs[1] * dist + coeffs[2] * dist * dist
    return 1.0 / jnp.maximum(den, tiny(den.dtype))


def _spot_factor(light_dir, spot, edge, softness_deg):
    """OpenGL spot term: max(-L.D, 0)^e inside the cone, 0 outside; cutoff 180 = no cone."""
    cos_angle = -dot(light_dir, safe_normalize(spot.direction), keepdims=True)
    cutoff = jnp.deg2rad(spot.cutoff)
    cos_cut = jnp.cos(cutoff)
    falloff = safe_pow(jnp.maximum(cos_angle, 0.0), spot.exponent)
    if edge == "hard":
        inside = (cos_angle >= cos_cut).astype(cos_angle.dtype)
    else:
        width = jnp.maximum(jnp.sin(cutoff), 1e-3) * jnp.deg2rad(softness_deg)
        inside = jax.nn.sigmoid((cos_angle - cos_cut) / width)
    return jnp.where(spot.cutoff == 180.0, 1.0, falloff * inside)


def _incidence(kind, light, points, settings):
    """Unit direction to the light [..., 3] and its attenuation * spot scale [..., 1], or
    for a directional light its one direction [3] and None (no attenuation: nothing to
    multiply per fragment; the direction broadcasts where it meets the normals, so that
    reverse mode keeps no copy of it per fragment)."""
    if kind == "directional":
        return safe_normalize(-light.direction), None
    to_light = light.position - points
    light_dir = safe_normalize(to_light)
    scale = _attenuation(light.attenuation, safe_norm(to_light, keepdims=True))
    if kind == "spot":
        scale = scale * _spot_factor(light_dir, light, settings.spot_edge, settings.spot_softness)
    return light_dir, scale


def _specular_base(normals, light_dir, view_dirs, model):
    """max(N.H, 0) (Blinn) or max(R.V, 0) (Phong): [..., 1]."""
    if model == "blinn":
        base = dot(normals, safe_normalize(light_dir + view_dirs), keepdims=True)
    else:
        n_dot_l = dot(normals, light_dir, keepdims=True)
        base = dot(2.0 * n_dot_l * normals - light_dir, view_dirs, keepdims=True)
    return jnp.maximum(base, 0.0)


def _light_terms(material, light, light_dir, scale, normals, view_dirs, settings):
    """Ambient, diffuse and specular of one light: [..., 3] each; scale None means 1."""
    scaled = (lambda x: x) if scale is None else (lambda x: scale * x)
    n_dot_l = dot(normals, light_dir, keepdims=True)
    ambient = scaled(material.ka * light.ambient)
    diffuse = scaled(material.kd * light.diffuse * jnp.maximum(n_dot_l, 0.0))
    if material.ks is None:
        return ambient, diffuse, None
    base = _specular_base(normals, light_dir, view_dirs, settings.specular)
    # materialize per-fragment intermediates (see shade's docstring)
    base = jax.lax.optimization_barrier(base)
    power = safe_pow(base, jnp.asarray(material.shininess)[..., None])
    lit = jnp.where(n_dot_l > 0.0, power, 0.0)
    return ambient, diffuse, scaled(material.ks * light.specular * lit)


def _lights(lights: LightGroups, kinds=("directional", "point", "spot")):
    """(kind, index in its group, single light) for every light of the scene of the given
    kinds."""
    return [(kind, i, light) for kind in kinds if getattr(lights, kind) is not None
            for i, light in enumerate(_unstack(getattr(lights, kind)))]


def _seen(shadow, points, normals, light_dir, settings):
    """The visibility [..., 1] a shadow entry stands for: looked up in a ShadowMap, or
    the visibility itself, computed before (light_visibility)."""
    if isinstance(shadow, ShadowMap):
        return visibility(shadow, points, normals, light_dir, settings)
    return shadow


def reads_points(lights: LightGroups, shadow_maps=None) -> bool:
    """Whether `shade` reads its `points` for these lights and shadow entries: a point,
    spot, area or sphere light's direction and attenuation, or a shadow map lookup. With
    only ambient and directional lights (and visibilities computed before, if any) it
    reads the normals alone, and a caller need not compute the points (the view
    directions are the caller's: a local viewer reads them too)."""
    positional = ("point", "spot", *area.KINDS)
    return (any(getattr(lights, kind) is not None for kind in positional)
            or any(isinstance(entry, ShadowMap) for entry in (shadow_maps or {}).values()))


def light_visibility(lights: LightGroups, points, normals, settings, shadow_maps):
    """{(kind, index): visibility [..., 1]} of the points for every light with a shadow
    map: what `shade` scales those lights' diffuse and specular terms by. With geometry
    and lights fixed it is fixed too: a caller computes it once and passes it to `shade`
    in place of the maps (fitting.model.cache)."""
    shadow_maps = shadow_maps or {}
    return {(kind, index): _seen(shadow_maps[(kind, index)], points, normals,
                                 _incidence(kind, light, points, settings)[0], settings)
            for kind, index, light in _lights(lights) if (kind, index) in shadow_maps}


def shade(material: Material, lights: LightGroups, global_ambient, points, normals,
          view_dirs, settings, shadow_maps=None) -> ShadingParts:
    """Light samples. points, normals, view_dirs: [..., 3] float world space (normals and
    view_dirs unit); global_ambient: [3]; settings: RenderSettings (specular model, spot
    edge, shadow lookup); shadow_maps: {(kind, index): diffshade.shading.shadows.ShadowMap, or the
    points' visibility [..., 1] (light_visibility)} of the scene's shadowed lights, whose
    diffuse and specular terms are scaled by their visibility (None: no shadows).
    Returns ShadingParts, each [..., 3], unclamped.

    The loop over lights is unrolled at trace time (the light count is static): written
    out, the sums vectorize far better on CPU than a reduction over a small light axis.
    Each light's direction and attenuation, and the specular base, pass through
    `optimization_barrier`: XLA then stores them once instead of recomputing their chains
    inside every fusion of the backward pass that reads them (XLA on CPU has no
    multi-output fusion, so without the barrier each fusion recomputes the chain).
    """
    shape = jnp.broadcast_shapes(points.shape, normals.shape, jnp.shape(material.kd))
    ambient_light = global_ambient
    if lights.ambient is not None:
        ambient_light = ambient_light + sum(a.ambient for a in _unstack(lights.ambient))
    ambient = jnp.broadcast_to(material.ka * ambient_light, shape)
    diffuse = specular = jnp.zeros(shape, points.dtype)
    for kind, index, light in _lights(lights):
        incidence = _incidence(kind, light, points, settings)
        light_dir, scale = jax.lax.optimization_barrier(incidence)
        a, d, s = _light_terms(material, light, light_dir, scale, normals, view_dirs, settings)
        shadow = (shadow_maps or {}).get((kind, index))
        if shadow is not None:
            seen = _seen(shadow, points, normals, light_dir, settings)
            d, s = seen * d, None if s is None else seen * s
        ambient, diffuse = ambient + a, diffuse + d
        specular = specular if s is None else specular + s
    for kind, index, light in _lights(lights, area.KINDS):
        maps = (shadow_maps or {}).get((kind, index))
        seen = None if maps is None else sampled_visibility(kind, light, maps, points,
                                                            normals, settings)
        a, d, s = area.terms(kind, light, material, points, normals, view_dirs,
                             settings, _light_terms, seen)
        ambient, diffuse = ambient + a, diffuse + d
        specular = specular if s is None else specular + s
    emission = (jnp.zeros(shape, points.dtype) if material.emission is None
                else jnp.broadcast_to(material.emission, shape))
    return ShadingParts(ambient, diffuse, specular, emission)
