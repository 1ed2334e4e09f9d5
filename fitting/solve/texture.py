"""A kd or ks texture in closed form: the texels that best explain the views, by least
squares.

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
when RES is not a multiple of it): each probe holds texels PROBE_STRIDE apart, and A'MA
applied to it gives, at each texel, its coupling to the probe's texel nearest to it. So
the diagonal is exact wherever no pixel reads two texels PROBE_STRIDE apart (a texel not
much smaller than a pixel), and the stencil wherever none reads two texels more than one
apart.
"""

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import RenderSettings, render, replace
from diffshade.scene import Texture
from fitting.solve.texture_descent import (
    DEFAULT_MAXITER,
    DEFAULT_TEXEL_LR,
    DESCENT_METHODS,
    descend,
)

__all__ = ["DEFAULT_SMOOTHNESS", "TEXTURE_FIELDS", "TextureSolution", "solve_kd_texture",
           "solve_texture"]

DEFAULT_SMOOTHNESS = 1e-3
PROBE_STRIDE = 4
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


def _view_scene(scene, texels, field="kd"):
    """The view's scene with `texels` as its `field` texture's texels."""
    texture = replace(getattr(scene.material, field), texels=texels)
    return replace(scene, material=replace(scene.material, **{field: texture}))


def _view_map(scene, settings, field="kd"):
    """t [R, R, 3] -> the view's [H, W, 3] render with t as its `field` texels."""
    return lambda texels: render(_view_scene(scene, texels, field), settings)[..., :3]


def _laplacian(t):
    """L t of the texel grid graph with wrapped neighbours: [R, R, 3] -> [R, R, 3]."""
    return 4.0 * t - sum(jnp.roll(t, shift, axis) for axis in (0, 1) for shift in (1, -1))


def _pcg(operator, rhs, inverse_diagonal, tol, maxiter, start=None):
    """Conjugate gradients preconditioned by the inverse diagonal (Jacobi) for
    operator(x) = rhs, from `start` (or from 0 when that is closer, by the residual; from
    0 without a start): (x, iterations, relative residual). Jacobi evens out texels seen
    by many pixels and by few (at a grazing angle, near a pole), whose scales differ by
    orders of magnitude and would otherwise cost most iterations."""
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
        z = inverse_diagonal * r
        rz_new = jnp.vdot(r, z)
        return x, r, z + (rz_new / rz) * p, rz_new, k + 1
    z = inverse_diagonal * r
    x, r, _, _, k = jax.lax.while_loop(more, step, (x, r, z, jnp.vdot(r, z), 0))
    return x, k, jnp.sqrt(jnp.vdot(r, r)) / jnp.maximum(norm_rhs, jnp.finfo(rhs.dtype).tiny)


def _linear_parts(scenes, settings, masks, res, dtype, field="kd"):
    """Per view (b_v [H, W, 3], A_v, A_v') of the affine render in the texels."""
    zero = jnp.zeros((res, res, 3), dtype)
    parts = []
    for scene, mask in zip(scenes, masks, strict=True):
        b, apply = jax.linearize(_view_map(scene, settings, field), zero)
        weight = mask[..., None].astype(dtype)
        masked = lambda t, apply=apply, weight=weight: weight * apply(t)  # noqa: E731
        parts.append((b, masked, jax.linear_transpose(masked, zero)))
    return parts


def _probe_colours(res, stride):
    """[res] int: texel index -> probe colour along an axis: i mod stride, except the
    last res mod stride texels, which get colours of their own, so that texels of one
    colour are at least `stride` apart, across the wrap too."""
    full = res - res % stride
    index = np.arange(res)
    return np.where(index < full, index % stride, stride + index - full)


def _probes(res, dtype, stride):
    """(probes [P, R, R, 3], which [R, R] int: the probe holding each texel): probe p
    holds the texels of one colour pair (_probe_colours)."""
    colours = _probe_colours(res, stride)
    count = int(colours.max()) + 1
    which = colours[:, None] * count + colours[None, :]
    probes = which[None] == np.arange(count * count)[:, None, None]
    return jnp.broadcast_to(jnp.asarray(probes, dtype)[..., None], probes.shape + (3,)), which


def _offsets(res):
    """The stencil's offsets along an axis of res texels: 0, -1 and +1, those that name
    distinct texels (with 2 texels -1 and +1 are one neighbour, with 1 there is none)."""
    offsets = []
    for d in (0, -1, 1):
        if all((d - e) % res for e in offsets):
            offsets.append(d)
    return offsets


def _shifted(t, offset):
    """[i] = t[i + offset] over the wrapped texel grid."""
    return jnp.roll(t, (-offset[0], -offset[1]), (0, 1))


def _stencil(data, res, dtype, stride=PROBE_STRIDE):
    """{(dr, dc): [R, R, 3]}: each texel's coupling in the data operator to its neighbour
    (dr, dc) (wrapped), by probes (module docstring); (0, 0) is the diagonal."""
    probes, which = _probes(res, dtype, min(stride, res))
    responses = jnp.stack([data(probe) for probe in probes])
    rows, cols = np.indices((res, res))
    # texel i's coupling to i + offset: what the probe holding i + offset gives at i, one
    # gather per offset (as sums of responses times shifted probe masks, XLA's fused
    # loops over 16 responses and constant masks took seconds at 256^2)
    stencil = {(dr, dc): responses[np.roll(which, (-dr, -dc), (0, 1)), rows, cols]
               for dr in _offsets(res) for dc in _offsets(res)}
    return _symmetric(stencil, res)


def _symmetric(stencil, res):
    """The stencil made symmetric, each coupling the mean of its two probed values (they
    agree where the stencil is exact), so that conjugate gradients may run on it."""
    def opposite(offset):
        return next(o for o in stencil if (o[0] + offset[0]) % res == (o[1] + offset[1]) % res
                    == 0)
    return {offset: 0.5 * (values + _shifted(stencil[opposite(offset)], offset))
            for offset, values in stencil.items()}


def _stencil_operator(stencil):
    """t [R, R, 3] -> S t, S the probed stencil."""
    return lambda t: sum(values * _shifted(t, offset) for offset, values in stencil.items())


def _std_error(parts, targets, masks, texels, seen, diagonal):
    """sigma / sqrt(diag(A'MA)) per texel, NaN where unseen (module docstring)."""
    rss = sum(jnp.sum(jnp.where(mask[..., None], forward(texels) + b - y, 0.0) ** 2)
              for (b, forward, _), y, mask in zip(parts, targets, masks, strict=True))
    values = 3 * sum(jnp.sum(mask) for mask in masks)
    sigma = jnp.sqrt(rss / jnp.maximum(values - 3 * jnp.sum(seen), 1))
    safe = jnp.where(seen[..., None], diagonal, 1.0)
    return jnp.where(seen[..., None] & (diagonal > 0), sigma / jnp.sqrt(safe), jnp.nan)


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
    settings = RenderSettings() if settings is None else settings
    settings = replace(settings, clamp=False)
    if field not in TEXTURE_FIELDS:
        raise ValueError(f"field: got {field!r}; expected one of {TEXTURE_FIELDS}")
    if method not in ("linear", *DESCENT_METHODS):
        raise ValueError(f"method: got {method!r}; expected one of "
                         f"{('linear', *DESCENT_METHODS)}")
    if not (isinstance(smoothness, (int, float)) and smoothness >= 0):
        raise ValueError(f"smoothness: got {smoothness!r}; expected a number >= 0")
    scenes = list(scenes)
    _check_arguments(scenes, res, field)
    maxiter = DEFAULT_MAXITER.get(method, 1000) if maxiter is None else maxiter
    targets = [jnp.asarray(y) for y in targets]
    masks = [jnp.asarray(m, bool) for m in masks]
    texels, coverage, iterations, lam, residual, std_error, warm = _solve(
        scenes, targets, masks, smoothness, tol, maxiter, lr, res=res,
        settings=settings, field=field, method=method)
    return TextureSolution(texels, coverage, int(iterations), float(smoothness), float(lam),
                           float(residual), std_error, int(warm))


def solve_kd_texture(scenes, targets, masks, res, settings=None, **options) -> TextureSolution:
    """solve_texture of the kd map (options: solve_texture's keywords)."""
    return solve_texture(scenes, targets, masks, res, settings, field="kd", **options)


def _minimize(method, operator, probed, rhs, inverse, tol, maxiter, lr):
    """(texels, iterations, relative residual, stencil iterations) of operator(t) = rhs by
    `method`; 'linear' starts from the solution of probed(t) = rhs (module docstring)."""
    if method == "linear":
        start, warm, _ = _pcg(probed, rhs, inverse, tol, maxiter)
        return (*_pcg(operator, rhs, inverse, tol, maxiter, start), warm)
    return (*descend(method, operator, rhs, inverse, tol, maxiter, lr), 0)


@partial(jax.jit, static_argnames=("res", "settings", "field", "method"))
def _solve(scenes, targets, masks, smoothness, tol, maxiter, lr, *, res, settings, field,
           method):
    """solve_texture's arrays, as one compiled program (the views unrolled)."""
    dtype = targets[0].dtype
    parts = _linear_parts(scenes, settings, masks, res, dtype, field)

    def data(t):
        return sum(transpose(forward(t))[0] for _, forward, transpose in parts)
    per_view = [transpose(forward(jnp.ones((res, res, 3), dtype)))[0]
                for _, forward, transpose in parts]
    weights = sum(per_view)
    mean_weight = jnp.mean(weights)
    seen = weights.max(-1) > 1e-9 * mean_weight
    lam = smoothness * jnp.sum(jnp.where(seen[..., None], weights, 0.0)) / jnp.maximum(
        3 * jnp.sum(seen), 1)
    rhs = sum(transpose(jnp.where(mask[..., None], y - b, 0.0).astype(dtype))[0]
              for (b, _, transpose), y, mask in zip(parts, targets, masks, strict=True))
    # a texel no view sees is pinned by the prior alone (lam > 0) or by a tiny ridge
    ridge = jnp.where(seen, 0.0, 1e-6 * mean_weight)[..., None]
    stencil = _stencil(data, res, dtype)
    diagonal = stencil[(0, 0)]
    inverse = 1.0 / jnp.maximum(diagonal + 4.0 * lam + ridge, 1e-12 * mean_weight)
    probed = _stencil_operator(stencil)
    texels, iterations, residual, warm = _minimize(
        method, lambda t: data(t) + lam * _laplacian(t) + ridge * t,
        lambda t: probed(t) + lam * _laplacian(t) + ridge * t, rhs, inverse, tol, maxiter, lr)
    coverage = sum((w.max(-1) > 1e-9 * mean_weight).astype(jnp.int32) for w in per_view)
    std_error = _std_error(parts, targets, masks, texels, seen, diagonal)
    return (jnp.where(seen[..., None], texels, jnp.nan), coverage, iterations, lam, residual,
            std_error, warm)
