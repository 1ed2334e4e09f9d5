"""Maps and uniform coefficients together, in closed form: one least-squares solution.

With the shininess fixed, an unclamped render is affine jointly in the maps' texels t (a
kd map, a ks map, or both: fitting.solve.texture.solve_maps solves both as one system)
and in the uniform coefficients u (ka, and kd or ks where they are not maps):

    image_v = b_v + A_v t + sum_c u_c P_c,v

b_v the render with the maps and the coefficients at 0, P_c,v the part of coefficient c
at 1 (every channel). The maps that best explain the targets for given u are linear in
u: t*(u) = T_0 + sum_c u_c T_c, T_0 the maps' solve of the targets and T_c their solve of
the targets -P_c: the same operator, prior and pixels, so one solve_maps call with 1 + C
right-hand sides (the probes and the stencil paid once). Put back, the residual is
r_0 - sum_c u_c q_c with r_0 = y - b - A T_0 and q_c = P_c + A T_c, and the prior
sum_f lam_f t_f*' L t_f*: per channel a least-squares problem in the few u (channels do
not mix: a coefficient's channel and a texel's channel act on the image's channel
alone), solved with u in [0, upper] (fitting.solve.linear.box_least_squares). The maps
are then t*(u), by linearity the solve at the chosen u. So the maps and the coefficients
come out as one least-squares solution, not as solves taking turns (which trade the
coefficients against a map's level for many rounds when they are alike, e.g. ka against
a dark kd map, or a kd map against a ks map where the highlight is broad).

Those per-channel normal equations G u = g are the Schur complement of the texels in the
joint normal matrix: G = P'MP - P'MA H^-1 A'MP, H = A'MA + the prior. So the uniform
coefficients' covariance with the texels marginalised is sigma^2 G^-1
(`JointSolution.eliminated`, the texels' share P'MA H^-1 A'MP, for
fitting.report.uncertainty).

Unseen texels (NaN in the solves) count as 0 in the prior here: they are pinned by
nothing but the prior, and read by no counted pixel.
"""

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import render, replace
from fitting.solve.linear import box_least_squares
from fitting.solve.texture import common_layout, solve_maps

__all__ = ["JointSolution", "solve_texture_jointly"]


class JointSolution(NamedTuple):
    """maps: {field: TextureSolution}; values: {coefficient: [3] value}; eliminated: {
    (name, name2): [3]} per channel the texels' share of the normal matrix of the
    coefficients' columns (module docstring); unknowns: the seen texels' count (times 3,
    the channels), what the residuals' degrees of freedom lose to the maps."""

    maps: dict
    values: dict
    eliminated: dict
    unknowns: int


def _with(scene, **fields):
    return replace(scene, material=dataclasses.replace(scene.material, **fields))


@jax.jit
def _image(scene, settings):
    return render(scene, settings)[..., :3]


def _images(scenes, settings):
    return [np.asarray(_image(s, settings), np.float64) for s in common_layout(scenes)]


def _laplacian(t):
    return 4.0 * t - sum(np.roll(t, shift, axis) for axis in (0, 1) for shift in (1, -1))


def _prior(lam, maps_i, maps_j):
    """[3]: sum over the maps of lam_f t_i,f' L t_j,f per channel."""
    return sum(lam[f] * np.sum(maps_i[f] * _laplacian(maps_j[f]), (0, 1)) for f in lam)


def _channel_system(residuals, lam, maps):
    """Per channel the normal equations (G [3, p, p], g [3, p]) of u in
    ||r_0 - sum u_c q_c||^2 + sum_f lam_f t_f' L t_f, t = T_0 + sum u_c T_c. residuals:
    [r_0, q_1, ...], each [N, 3]; maps: [T_0, T_1, ...], each {field: [R, R, 3]}."""
    p = len(residuals) - 1
    gram, rhs = np.zeros((3, p, p)), np.zeros((3, p))
    for i in range(p):
        for j in range(p):
            gram[:, i, j] = (np.sum(residuals[i + 1] * residuals[j + 1], 0)
                             + _prior(lam, maps[i + 1], maps[j + 1]))
        rhs[:, i] = (np.sum(residuals[i + 1] * residuals[0], 0)
                     - _prior(lam, maps[i + 1], maps[0]))
    return gram, rhs


def _kept(images, kept):
    """Per view [H, W, 3] -> the counted pixels' rows, all views: [N, 3]."""
    return np.concatenate([a[k] for a, k in zip(images, kept, strict=True)])


def _eliminated(coefficients, parts, solved, kept):
    """{(c, d): [3]} = P_c'MA H^-1 A'MP_d = -P_c'M (A T_d) per channel (T_d = -H^-1 A'MP_d),
    made symmetric."""
    share = {}
    for c in coefficients:
        for j, d in enumerate(coefficients):
            mapped = _kept([a[j + 1] for a in solved.images], kept)
            share[(c, d)] = -np.sum(_kept(parts[c], kept) * mapped, 0)
    return {(c, d): 0.5 * (share[(c, d)] + share[(d, c)]) for c, d in share}


def solve_texture_jointly(scenes, targets, masks, maps, settings, *, coefficients,
                          upper=1.0, **options) -> JointSolution:
    """The maps ({field: RES}) and the uniform `coefficients` (names among ka, kd, ks; none
    of them a map) that together best explain `targets` (module docstring). scenes: one
    per view, as solve_maps', with everything but the maps and `coefficients` at their
    values; options: solve_maps' keywords (method, smoothness, ...)."""
    settings = replace(settings, clamp=False)
    blanks = {field: replace(getattr(scenes[0].material, field),
                             texels=jnp.zeros((res, res, 3), targets[0].dtype))
              for field, res in maps.items()}
    zeros = {name: jnp.zeros(3) for name in coefficients}
    base = [_with(s, **blanks, **zeros) for s in scenes]
    b = _images(base, settings)
    parts = {name: [a - z for a, z in zip(_images(
        [_with(s, **{name: jnp.ones(3)}) for s in base], settings), b, strict=True)]
        for name in coefficients}
    sets = [np.stack([np.asarray(y, np.float64)] + [z - parts[c][v] for c in coefficients])
            for v, (y, z) in enumerate(zip(targets, b, strict=True))]
    solved = solve_maps(base, [s.astype(np.asarray(targets[0]).dtype) for s in sets],
                        masks, maps, settings, **options)
    fields = list(maps)
    texels = [{f: np.nan_to_num(np.asarray(solved.texels[f][k], np.float64)) for f in fields}
              for k in range(1 + len(coefficients))]
    kept = [np.asarray(m, bool) for m in masks]
    first = _kept([np.asarray(y, np.float64) - z - a[0]
                   for y, z, a in zip(targets, b, solved.images, strict=True)], kept)
    others = [_kept([p + a[i + 1] for p, a in zip(parts[c], solved.images, strict=True)], kept)
              for i, c in enumerate(coefficients)]
    gram, rhs = _channel_system([first, *others], solved.lam, texels)
    values = (np.stack([box_least_squares(gram[c], rhs[c], 0.0, upper) for c in range(3)], -1)
              if coefficients else np.zeros((0, 3)))
    residual = first - sum((values[i] * q for i, q in enumerate(others)), np.zeros_like(first))
    unknowns = 3 * sum(int(np.sum(solved.seen(f))) for f in fields)
    sigma = np.sqrt(np.sum(residual ** 2) / max(solved.values - unknowns - values.size, 1))
    solutions = {}
    for f in fields:
        combined = solved.texels[f][0] + sum(
            (values[i] * solved.texels[f][i + 1] for i in range(len(coefficients))),
            np.zeros_like(solved.texels[f][0]))
        solutions[f] = solved.solution(f, texels=combined, sigma=sigma)
    found = {name: jnp.asarray(values[i], targets[0].dtype)
             for i, name in enumerate(coefficients)}
    return JointSolution(solutions, found, _eliminated(coefficients, parts, solved, kept),
                         unknowns)
