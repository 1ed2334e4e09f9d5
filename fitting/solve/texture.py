"""A kd or ks texture (or both) in closed form: the texels that best explain the views, by
least squares.

With geometry, cameras, lights and every other material parameter fixed (the shininess
included), an unclamped render is affine in the kd texels t (and in the ks texels):
image_v = A_v t + b_v, b_v the render with the map at 0. `solve_texture` minimizes

    sum_v || m_v * (A_v t + b_v - y_v) ||^2 + lam * t' L t

over the texels of a RES x RES map, m_v the views' pixel masks, y_v their targets and L
the graph Laplacian of the texel grid (4 neighbours, wrapping as the texture does:
t' L t is the sum of squared differences of neighbouring texels), by conjugate gradients
on the normal equations (A'MA + lam L) t = A'M(y - b), preconditioned by their diagonal
(Jacobi). A_v is the JVP of the render at t = 0 (`jax.linearize`) and A_v' its transpose
(`jax.linear_transpose`): no matrix is formed from the render, and an iteration costs a
forward and a backward render per view.

Most of those iterations are spared: the probes that give the diagonal (below) give each
texel's couplings to its 8 neighbours too, a 3 x 3 stencil S of A'MA. Where every pixel
reads texels at most one apart (a bilinear cell: Phong or flat shading in hard raster)
S is A'MA itself; elsewhere (Gouraud's corner texels, soft raster's overlapping faces)
it is close. The solve first runs conjugate gradients on (S + lam L) t = A'M(y - b),
whose iterations cost a few array shifts, and then continues with the renders' operator
from there (from 0 should that start be worse) until the same tolerance: the solution
is the renders' normal equations', whatever S misses, and only the last few iterations
cost renders.

The prior's weight follows one rule: lam = smoothness * (the mean data weight of a seen
texel), the data weight of texel i being (A'MA 1)_i, what the views pin it by; so
`smoothness` is unitless (default DEFAULT_SMOOTHNESS) and the same value means the same
on any scene, resolution or exposure. A texel is *seen* when its data weight is above
1e-9 of the mean's (some view's lit pixel reads it); its coverage is the number of views
that do. The texels no view sees are reported as unseen (NaN), never invented: the prior
fills them only inside the solve, so that the system is well posed.

method 'adam' or 'lbfgs' minimizes the same objective by descent instead of conjugate
gradients (fitting.solve.texture_descent), on the same operator, prior and ridge: one
matvec per step, the gradient of the objective being the normal equations' residual.

The standard error of a seen texel is sigma / sqrt((A'MA)_ii), sigma^2 the residual
variance (residual sum of squares over the counted values less the seen unknowns): the
texel's error were its neighbours known, without the prior (the unregularized solve's
marginal error is at least this; the prior lowers it).

The diagonal (A'MA)_ii and the stencil come from PROBE_STRIDE^2 probes (and a few more
when RES is not a multiple of it; fitting.solve.texture_stencil): each probe holds texels
PROBE_STRIDE apart, and A'MA applied to it gives, at each texel, its coupling to the
probe's texel nearest to it. So the diagonal is exact wherever no pixel reads two texels
PROBE_STRIDE apart (a texel not much smaller than a pixel), and the stencil wherever none
reads two texels more than one apart.

Several maps at once (`solve_maps`: kd and ks): for a fixed shininess the image is affine
in the kd and the ks texels together, so t above is both maps' texels and the normal
equations one system, each map with its own prior weight (the rule above, per map) and
coverage; the stencil holds the couplings between the two maps' texels at one place (the
same pixels read both), and the preconditioner inverts, per texel and channel, the 2 x 2
block of the kd and the ks texel there. `solve_maps` also solves several right-hand sides
on one operator (the probes and the stencil are paid once), as fitting.solve.texture_joint
needs, and returns each one's render A t.

The views' lights are padded to one layout (`common_layout`: lights of colour 0), and the
views of one layout and camera size are rendered by one vmapped render: the compiled
program holds a copy of the render per such group, not per view, which keeps its
compilation short.
"""

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import RenderSettings, render, replace
from diffshade.scene import Texture
from fitting.model.batch import common_lights
from fitting.solve.texture_descent import (
    DEFAULT_MAXITER,
    DEFAULT_TEXEL_LR,
    DESCENT_METHODS,
    descend,
)
from fitting.solve.texture_stencil import (
    PROBE_STRIDE,
    block_preconditioner,
    block_stencil,
    stencil_operator,
)

__all__ = ["DEFAULT_SMOOTHNESS", "TEXTURE_FIELDS", "MapSolve", "TextureSolution",
           "common_layout", "solve_kd_texture", "solve_maps", "solve_texture"]

DEFAULT_SMOOTHNESS = 1e-3
#: the material fields a map may be solved for (the image is linear in their texels)
TEXTURE_FIELDS = ("kd", "ks")


class TextureSolution(NamedTuple):
    """texels: [R, R, 3] linear kd, NaN where unseen (row 0 = v = 1); coverage: [R, R]
    int, the views that see each texel; iterations: CG iterations with the renders;
    smoothness and lam: the prior's unitless setting and its weight; residual: the
    relative residual of the normal equations at the end; std_error: [R, R, 3] per texel
    (NaN where unseen; module docstring); stencil_iterations: the CG iterations on the
    probed stencil that gave the renders' start."""

    texels: jax.Array
    coverage: jax.Array
    iterations: int
    smoothness: float
    lam: float
    residual: float
    std_error: jax.Array
    stencil_iterations: int = 0


class MapSolve(NamedTuple):
    """solve_maps' answer for K right-hand sides. Per map field: texels {field: [K, R, R,
    3]} (NaN where unseen), coverage {field: [R, R]}, diagonal {field: [R, R, 3]} (the
    probed (A'MA)_ii), lam {field: float}; per right-hand side: iterations, stencil
    iterations and relative residual [K] and sigma [K] (the residual standard deviation,
    module docstring); images: per view [K, H, W, 3], the masked render A t_k of the
    solution; values: the counted pixel-channels; smoothness: the prior's setting."""

    texels: dict
    coverage: dict
    diagonal: dict
    lam: dict
    iterations: np.ndarray
    stencil_iterations: np.ndarray
    residual: np.ndarray
    sigma: np.ndarray
    images: list
    values: int
    smoothness: float

    def seen(self, field):
        """[R, R] bool: the texels of `field` that some view sees."""
        return np.asarray(self.coverage[field]) > 0

    def solution(self, field, k=0, texels=None, sigma=None) -> TextureSolution:
        """The TextureSolution of map `field` for right-hand side k (or of `texels` [R, R,
        3], with residual deviation `sigma`: a combination of the right-hand sides')."""
        texels = self.texels[field][k] if texels is None else texels
        sigma = self.sigma[k] if sigma is None else sigma
        diagonal = np.asarray(self.diagonal[field])
        seen = self.seen(field)[..., None] & (diagonal > 0)
        std_error = np.where(seen, sigma / np.sqrt(np.where(seen, diagonal, 1.0)), np.nan)
        return TextureSolution(texels, self.coverage[field], int(np.max(self.iterations)),
                               float(self.smoothness), float(self.lam[field]),
                               float(np.max(self.residual)), std_error,
                               int(np.max(self.stencil_iterations)))


def _view_scene(scene, maps, fields):
    """The view's scene with maps[i] as its fields[i] texture's texels."""
    textures = {field: replace(getattr(scene.material, field), texels=texels)
                for field, texels in zip(fields, maps, strict=True)}
    return replace(scene, material=replace(scene.material, **textures))


def _view_map(scene, settings, fields):
    """(t [R, R, 3] per field) -> the view's [H, W, 3] render with t as its maps."""
    return lambda maps: render(_view_scene(scene, maps, fields), settings)[..., :3]


def _laplacian(t):
    """L t of the texel grid graph with wrapped neighbours: [R, R, 3] -> [R, R, 3]."""
    return 4.0 * t - sum(jnp.roll(t, shift, axis) for axis in (0, 1) for shift in (1, -1))


def _pcg(operator, rhs, precondition, tol, maxiter, start=None):
    """Conjugate gradients preconditioned by `precondition` (the inverse of the system's
    per-texel blocks) for operator(x) = rhs, from `start` (or from 0 when that is closer,
    by the residual; from 0 without a start): (x, iterations, relative residual). The
    preconditioner evens out texels seen by many pixels and by few (at a grazing angle,
    near a pole), whose scales differ by orders of magnitude and would otherwise cost
    most iterations."""
    norm_rhs = jnp.sqrt(jnp.vdot(rhs, rhs))
    x, r = jnp.zeros_like(rhs), rhs
    if start is not None:
        r_start = rhs - operator(start)
        closer = jnp.vdot(r_start, r_start) < jnp.vdot(rhs, rhs)
        x, r = jnp.where(closer, start, x), jnp.where(closer, r_start, r)

    def more(state):
        _, r, _, _, k = state
        return (k < maxiter) & (jnp.sqrt(jnp.vdot(r, r)) > tol * norm_rhs)

    def step(state):
        x, r, p, rz, k = state
        ap = operator(p)
        alpha = rz / jnp.vdot(p, ap)
        x, r = x + alpha * p, r - alpha * ap
        z = precondition(r)
        rz_new = jnp.vdot(r, z)
        return x, r, z + (rz_new / rz) * p, rz_new, k + 1
    z = precondition(r)
    x, r, _, _, k = jax.lax.while_loop(more, step, (x, r, z, jnp.vdot(r, z), 0))
    return x, k, jnp.sqrt(jnp.vdot(r, r)) / jnp.maximum(norm_rhs, jnp.finfo(rhs.dtype).tiny)


def common_layout(scenes):
    """The scenes with their lights padded to one layout (fitting.model.batch
    .common_lights: lights of colour 0, which add exactly 0), so that views of one
    camera size share one compiled render; the scenes as they are where a static
    setting (shadow flags, area-light samples) still differs."""
    try:
        lights = common_lights([s.lights for s in scenes])
    except ValueError:
        return list(scenes)
    return [replace(s, lights=g) for s, g in zip(scenes, lights, strict=True)]


def _layout_groups(scenes):
    """The view indices grouped by pytree structure and leaf shapes (the views one
    vmapped render serves), in order of first appearance."""
    groups = {}
    for i, scene in enumerate(scenes):
        key = (jax.tree.structure(scene), tuple(jnp.shape(x) for x in jax.tree.leaves(scene)))
        groups.setdefault(key, []).append(i)
    return tuple(tuple(g) for g in groups.values())


class _Group(NamedTuple):
    """Views rendered by one vmapped program: index (their view indices), b [V_g, H, W,
    3], forward (per view maps, a tuple of [V_g, R_f, R_f, 3] -> the masked renders A_v t_v
    [V_g, H, W, 3]) and its transpose."""

    index: tuple
    b: jax.Array
    forward: object
    transpose: object

    def stack(self, per_view):
        return jnp.stack([per_view[i] for i in self.index])

    def spread(self, maps):
        """tuple of [R_f, R_f, 3] -> the same maps for every view of the group."""
        return tuple(jnp.broadcast_to(m, (len(self.index), *m.shape)) for m in maps)


def _linear_parts(scenes, settings, masks, res, dtype, fields):
    """The views' groups (_Group) of the affine render in the maps' texels (a tuple of
    [R_f, R_f, 3]): one vmapped render per group of views alike, so the program holds one
    copy of the render per group, not per view."""
    parts = []
    for index in _layout_groups(scenes):
        stacked = jax.tree.map(lambda *x: jnp.stack(x), *[scenes[i] for i in index])
        zero = tuple(jnp.zeros((len(index), r, r, 3), dtype) for r in res)
        images = jax.vmap(lambda scene, maps: _view_map(scene, settings, fields)(maps))
        b, apply = jax.linearize(partial(images, stacked), zero)
        weight = jnp.stack([masks[i] for i in index])[..., None].astype(dtype)
        masked = lambda t, apply=apply, weight=weight: weight * apply(t)  # noqa: E731
        parts.append(_Group(index, b, masked, jax.linear_transpose(masked, zero)))
    return parts


def _per_view(parts, grouped, count):
    """Per-group results with a leading [V_g] axis (pytrees) -> a list per view."""
    out = [None] * count
    for group, values in zip(parts, grouped, strict=True):
        for j, i in enumerate(group.index):
            out[i] = jax.tree.map(lambda a, j=j: a[j], values)
    return out


def _add(a, b):
    return tuple(x + y for x, y in zip(a, b, strict=True))


def _flat(maps):
    """tuple of [R_f, R_f, 3] -> [sum 3 R_f^2]: the solvers' vector."""
    return jnp.concatenate([m.reshape(-1) for m in maps])


def _unflat(x, res):
    out, start = [], 0
    for r in res:
        out.append(x[start:start + r * r * 3].reshape(r, r, 3))
        start += r * r * 3
    return tuple(out)


def _check_arguments(scenes, res, field):
    """ValueError unless res is a texture side in [1, 8192] and each scene's `field` a
    Texture (the memory a fit needs is fitting.texture_run.check_maps')."""
    if not isinstance(res, int) or isinstance(res, bool) or not 1 <= res <= 8192:
        raise ValueError(f"res: got {res!r}; expected a texture resolution in [1, 8192]")
    for i, scene in enumerate(scenes):
        value = getattr(scene.material, field)
        if not isinstance(value, Texture):
            raise ValueError(f"scenes[{i}].material.{field}: got {type(value).__name__}; "
                             "expected a Texture (diffshade.texture), whose texels are solved")


def _check_options(field_names, method, smoothness):
    for field in field_names:
        if field not in TEXTURE_FIELDS:
            raise ValueError(f"field: got {field!r}; expected one of {TEXTURE_FIELDS}")
    if method not in ("linear", *DESCENT_METHODS):
        raise ValueError(f"method: got {method!r}; expected one of "
                         f"{('linear', *DESCENT_METHODS)}")
    if not (isinstance(smoothness, (int, float)) and smoothness >= 0):
        raise ValueError(f"smoothness: got {smoothness!r}; expected a number >= 0")


def solve_maps(scenes, targets, masks, maps, settings=None, *, method="linear",
               smoothness=DEFAULT_SMOOTHNESS, tol=1e-6, maxiter=None,
               lr=DEFAULT_TEXEL_LR, affine=True) -> MapSolve:
    """The maps ({field: RES}, fields among kd and ks) that explain each of K sets of
    targets, together, on one operator (module docstring).

    scenes: one Scene per view whose material's fields in `maps` are Textures (their
    texels are ignored; their wraps kept); targets: per view [K, H, W, 3] (or [H, W, 3]:
    K = 1) linear images; masks, settings, method, smoothness, tol, maxiter, lr: as
    solve_texture's. affine=False: each target is an image d itself, not less the render
    with the maps at 0 (the normal equations' right-hand side is A'Md: the solve is
    H^-1 A'Md, its sigma meaningless)."""
    settings = replace(RenderSettings() if settings is None else settings, clamp=False)
    fields = tuple(maps)
    _check_options(fields, method, smoothness)
    scenes = list(scenes)
    for field in fields:
        _check_arguments(scenes, maps[field], field)
    maxiter = DEFAULT_MAXITER.get(method, 1000) if maxiter is None else maxiter
    targets = [jnp.asarray(y) for y in targets]
    targets = [y[None] if y.ndim == 3 else y for y in targets]
    masks = [jnp.asarray(m, bool) for m in masks]
    out = _solve(common_layout(scenes), targets, masks, smoothness, tol, maxiter, lr, affine,
                 res=tuple(maps[f] for f in fields), settings=settings, fields=fields,
                 method=method)
    texels, coverage, diagonal, lam, iterations, residual, sigma, warm, images = out
    host = lambda values: dict(zip(fields, (np.asarray(v) for v in values), strict=True))  # noqa: E731
    return MapSolve(host(texels), host(coverage), host(diagonal), host(lam),
                    np.asarray(iterations), np.asarray(warm), np.asarray(residual),
                    np.asarray(sigma), [np.asarray(a) for a in images],
                    3 * int(sum(np.sum(np.asarray(m)) for m in masks)), float(smoothness))


def solve_texture(scenes, targets, masks, res, settings=None, *, field="kd",
                  method="linear", smoothness=DEFAULT_SMOOTHNESS, tol=1e-6, maxiter=None,
                  lr=DEFAULT_TEXEL_LR) -> TextureSolution:
    """The `field` texture (RES x RES; field 'kd' or 'ks') that explains `targets`
    (module docstring).

    scenes: one Scene per view, of one object whose mesh has UVs and whose material's
    `field` is a Texture (its texels are ignored; its wrap is kept); targets: [H, W, 3]
    linear images; masks: [H, W] bool (the pixels that count); settings: RenderSettings
    (clamp is turned off: the model must stay linear, so saturated pixels belong out of
    the masks). method: 'linear' (conjugate gradients), 'adam' or 'lbfgs' (descent on the
    same objective; lr: Adam's learning rate, in texel units); maxiter: the most
    iterations (default 1000; fitting.solve.texture_descent.DEFAULT_MAXITER for descent).
    smoothness >= 0: the prior's unitless weight. Raises ValueError for a bad argument."""
    return solve_maps(scenes, [jnp.asarray(y)[None] for y in targets], masks, {field: res},
                      settings, method=method, smoothness=smoothness, tol=tol,
                      maxiter=maxiter, lr=lr).solution(field)


def solve_kd_texture(scenes, targets, masks, res, settings=None, **options) -> TextureSolution:
    """solve_texture of the kd map (options: solve_texture's keywords)."""
    return solve_texture(scenes, targets, masks, res, settings, field="kd", **options)


def _minimize(method, operator, probed, rhs, precondition, inverse, tol, maxiter, lr):
    """(texels, iterations, relative residual, stencil iterations) of operator(t) = rhs by
    `method`; 'linear' starts from the solution of probed(t) = rhs (module docstring)."""
    if method == "linear":
        start, warm, _ = _pcg(probed, rhs, precondition, tol, maxiter)
        return (*_pcg(operator, rhs, precondition, tol, maxiter, start), warm)
    return (*descend(method, operator, rhs, inverse, tol, maxiter, lr), 0)


def _weights(parts, res, dtype, count):
    """Per view the data weight of every texel of each map f, (A_f'MA_f 1) (a tuple over
    the maps): what the views pin it by, the other maps aside."""
    zeros = tuple(jnp.zeros((r, r, 3), dtype) for r in res)

    def unit(f):
        return tuple(jnp.ones_like(z) if g == f else z for g, z in enumerate(zeros))
    grouped = [tuple(g.transpose(g.forward(g.spread(unit(f))))[0][f] for f in range(len(res)))
               for g in parts]
    return _per_view(parts, grouped, count)


def _prior_weight(smoothness, weights, seen):
    """lam = smoothness * the mean data weight of a seen texel (module docstring)."""
    return smoothness * jnp.sum(jnp.where(seen[..., None], weights, 0.0)) / jnp.maximum(
        3 * jnp.sum(seen), 1)


def _sigma(bases, targets, masks, images, seen_count):
    """sigma of one right-hand side's solution (images: its A t per view; bases: b per
    view): sqrt(RSS / (counted values less the seen unknowns))."""
    rss = sum(jnp.sum(jnp.where(mask[..., None], image + b - y, 0.0) ** 2)
              for b, image, y, mask in zip(bases, images, targets, masks, strict=True))
    values = 3 * sum(jnp.sum(mask) for mask in masks)
    return jnp.sqrt(rss / jnp.maximum(values - 3 * seen_count, 1))


@partial(jax.jit, static_argnames=("res", "settings", "fields", "method"))
def _solve(scenes, targets, masks, smoothness, tol, maxiter, lr, affine, *, res, settings,
           fields, method):
    """solve_maps' arrays, as one compiled program (the views of one layout vmapped, the
    right-hand sides and the probes looped)."""
    dtype = targets[0].dtype
    parts = _linear_parts(scenes, settings, masks, res, dtype, fields)
    bases = _per_view(parts, [g.b for g in parts], len(scenes))

    def data_op(t):
        out = None
        for group in parts:
            term = tuple(jnp.sum(x, 0) for x in group.transpose(group.forward(
                group.spread(t)))[0])
            out = term if out is None else _add(out, term)
        return out
    per_view = _weights(parts, res, dtype, len(scenes))
    weights = per_view[0]
    for more in per_view[1:]:
        weights = _add(weights, more)
    means = [jnp.mean(w) for w in weights]
    seen = [w.max(-1) > 1e-9 * m for w, m in zip(weights, means, strict=True)]
    lam = [_prior_weight(smoothness, w, s) for w, s in zip(weights, seen, strict=True)]
    # a texel no view sees is pinned by the prior alone (lam > 0) or by a tiny ridge
    ridge = [jnp.where(s, 0.0, 1e-6 * m)[..., None] for s, m in zip(seen, means, strict=True)]
    stencil = block_stencil(data_op, res, dtype, PROBE_STRIDE)
    count = len(res)
    extra = [4.0 * weight + r for weight, r in zip(lam, ridge, strict=True)]
    tiny = 1e-12 * sum(means) / count
    block = block_preconditioner(stencil, extra, tiny)
    probed_op = stencil_operator(stencil, count)

    def regular(t):
        return tuple(weight * _laplacian(x) + r * x
                     for weight, r, x in zip(lam, ridge, t, strict=True))

    def operator(x):
        t = _unflat(x, res)
        return _flat(_add(data_op(t), regular(t)))

    def probed(x):
        t = _unflat(x, res)
        return _flat(_add(probed_op(t), regular(t)))

    def precondition(x):
        return _flat(block(_unflat(x, res)))
    inverse = _flat(tuple(jnp.broadcast_to(1.0 / jnp.maximum(stencil[(f, f, (0, 0))] + e,
                                                             tiny), (r, r, 3))
                          for f, (e, r) in enumerate(zip(extra, res, strict=True))))

    def one(target_k):
        rhs = None
        for group in parts:
            y, mask = group.stack(target_k), group.stack(masks)
            # affine is traced: the texel share's solves (affine=False) share this program
            term = tuple(jnp.sum(x, 0) for x in group.transpose(jnp.where(
                mask[..., None], jnp.where(affine, y - group.b, y), 0.0).astype(dtype))[0])
            rhs = term if rhs is None else _add(rhs, term)
        x, iterations, residual, warm = _minimize(method, operator, probed, _flat(rhs),
                                                  precondition, inverse, tol, maxiter, lr)
        maps = _unflat(x, res)
        images = _per_view(parts, [g.forward(g.spread(maps)) for g in parts], len(scenes))
        sigma = _sigma(bases, target_k, masks, images, sum(jnp.sum(s) for s in seen))
        return maps, iterations, residual, warm, sigma, images
    maps, iterations, residual, warm, sigma, images = jax.lax.map(
        one, [jnp.asarray(y) for y in targets])
    coverage = [sum((w.max(-1) > 1e-9 * m).astype(jnp.int32) for w in view)
                for view, m in zip(zip(*per_view, strict=True), means, strict=True)]
    texels = [jnp.where(s[..., None], t, jnp.nan) for s, t in zip(seen, maps, strict=True)]
    diagonal = [stencil[(f, f, (0, 0))] for f in range(count)]
    return (texels, coverage, diagonal, lam, iterations, residual, sigma, warm, images)
