"""A map and uniform coefficients together, in closed form: the map's solve with the
coefficients eliminated.

With the shininess fixed, an unclamped render is affine jointly in a map's texels t and
in the uniform coefficients u (ka, and kd or ks where they are not the map):

    image_v = b_v + A_v t + sum_c u_c P_c,v

b_v the render with the map and the coefficients at 0, P_c,v the part of coefficient c
at 1 (every channel). The map that best explains the targets for given u is linear in
u: t*(u) = T_0 + sum_c u_c T_c, T_0 the map solve (fitting.solve.texture) of the targets
and T_c the map solve of the targets -P_c (so all of them are the same solve, with the
same prior, pixels and weight). Put back, the residual is r_0 - sum_c u_c q_c with
r_0 = y - b - A T_0 and q_c = P_c + A T_c, and the prior lam t*' L t*: per channel a
least-squares problem in the few u (channels do not mix: a coefficient's channel and a
texel's channel act on the image's channel alone), solved with u in [0, upper]
(fitting.solve.linear.box_least_squares). The map is then solved once more at the
chosen u, for its standard errors and coverage. So the map and the coefficients come
out as one least-squares solution, not as two solves taking turns (which trade the
coefficients against the map's level for many rounds when they are alike, e.g. ka
against a dark kd map, or a broad highlight against kd).

Unseen texels (NaN in the solves) count as 0 in the prior here: they are pinned by
nothing but the prior, and read by no counted pixel.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import render, replace
from fitting.solve.linear import box_least_squares
from fitting.solve.texture import solve_texture

__all__ = ["solve_texture_jointly"]


def _with(scene, **fields):
    return replace(scene, material=dataclasses.replace(scene.material, **fields))


@jax.jit
def _image(scene, settings):
    return render(scene, settings)[..., :3]


def _images(scenes, settings):
    return [np.asarray(_image(s, settings), np.float64) for s in scenes]


def _map_images(scenes, field, texels, settings, zero):
    """A t per view ([H, W, 3]): the render with the map t less the render with 0."""
    texture = replace(getattr(scenes[0].material, field), texels=jnp.asarray(texels))
    with_map = _images([_with(s, **{field: texture}) for s in scenes], settings)
    return [a - b for a, b in zip(with_map, zero, strict=True)]


def _laplacian(t):
    return 4.0 * t - sum(np.roll(t, shift, axis) for axis in (0, 1) for shift in (1, -1))


def _channel_system(residuals, lam, maps):
    """Per channel the normal equations (G [3, p, p], g [3, p]) of u in
    ||r_0 - sum u_c q_c||^2 + lam t' L t, t = T_0 + sum u_c T_c. residuals: [r_0, q_1,
    ...], each a list over views of [N_v, 3]; maps: [T_0, T_1, ...] [R, R, 3]."""
    flat = [np.concatenate([r.reshape(-1, 3) for r in views]) for views in residuals]
    prior = [_laplacian(t) for t in maps]
    p = len(flat) - 1
    gram, rhs = np.zeros((3, p, p)), np.zeros((3, p))
    for i in range(p):
        for j in range(p):
            gram[:, i, j] = (np.sum(flat[i + 1] * flat[j + 1], 0)
                             + lam * np.sum(maps[i + 1] * prior[j + 1], (0, 1)))
        rhs[:, i] = (np.sum(flat[i + 1] * flat[0], 0)
                     - lam * np.sum(maps[i + 1] * prior[0], (0, 1)))
    return gram, rhs


def solve_texture_jointly(scenes, targets, masks, res, settings, *, field, coefficients,
                          upper=1.0, **options):
    """(TextureSolution of the `field` map, {coefficient: [3] value}) that together best
    explain `targets` (module docstring). scenes: one per view, as solve_texture's, with
    everything but the map and `coefficients` (names among ka, kd, ks; not `field`) at
    their values; options: solve_texture's keywords (method, smoothness, ...)."""
    settings = replace(settings, clamp=False)
    if not coefficients:
        return solve_texture(scenes, targets, masks, res, settings, field=field,
                             **options), {}
    blank = replace(getattr(scenes[0].material, field),
                    texels=jnp.zeros((res, res, 3), targets[0].dtype))
    zeros = {name: jnp.zeros(3) for name in coefficients}
    base = [_with(s, **{field: blank}, **zeros) for s in scenes]
    b = _images(base, settings)
    parts = {name: [a - z for a, z in zip(_images(
        [_with(s, **{name: jnp.ones(3)}) for s in base], settings), b, strict=True)]
        for name in coefficients}
    maps = [solve_texture(base, targets, masks, res, settings, field=field, **options)]
    maps += [solve_texture(base, [z - p for z, p in zip(b, parts[name], strict=True)], masks,
                           res, settings, field=field, **options) for name in coefficients]
    texels = [np.nan_to_num(np.asarray(m.texels, np.float64)) for m in maps]
    kept = [np.asarray(m, bool) for m in masks]
    mapped = [_map_images(base, field, t, settings, b) for t in texels]
    first = [(np.asarray(y, np.float64) - z - a)[k]
             for y, z, a, k in zip(targets, b, mapped[0], kept, strict=True)]
    others = [[(p + a)[k] for p, a, k in zip(parts[name], mapped[i + 1], kept, strict=True)]
              for i, name in enumerate(coefficients)]
    gram, rhs = _channel_system([first, *others], maps[0].lam, texels)
    values = np.stack([box_least_squares(gram[c], rhs[c], 0.0, upper) for c in range(3)], -1)
    found = {name: jnp.asarray(values[i], targets[0].dtype)
             for i, name in enumerate(coefficients)}
    final = [_with(s, **found) for s in base]
    return solve_texture(final, targets, masks, res, settings, field=field, **options), found
