"""Variable projection: the coefficients in closed form inside a 1-D search on shininess.

With shininess and the lights fixed, the unclamped colour of every pixel and channel c is
linear in the coefficients:

    colour_c = ka_c * A_c + kd_c * D_c + ks_c * S_c(shininess) + emission_c

where A, D, S are the ambient, diffuse and specular parts that `diffshade.shade` returns
for unit coefficients (ka = kd = ks = 1). For a given shininess the best coefficients are
a bound-constrained linear least-squares problem, solved exactly: normal equations
(p x p, p <= 9) summed on the host in float64 from the parts of every view (one vmapped
program, `view_parts`, that the identifiability check shares; on sharded views with a
chunk size a chunk of views at a time, fitting.solve.distribute, `fold_parts`), and a small primal
active-set method for the box [0, upper] on the host (float64). Coefficients held fixed
move to the right-hand side.

Clamping makes a saturated pixel non-linear: a target at 1 (or at 0) only says the
unclamped colour is >= 1 (<= 0). Such pixel-channels (target >= 1 - 1e-6 or <= 1e-6 when
the settings clamp) are left out of the linear solve; the exact clamped model is restored
by the Levenberg-Marquardt polish that follows in `fit` (Gouraud's per-vertex clamp is
likewise only exact after the polish).

The outer problem in log-shininess is 1-D: evaluated on a log grid (so that a flat or
multi-modal profile cannot trap it; every other point first, then the two beside the best
of those), then refined by Brent's bounded method around the best grid point (to 1e-6 in
log-shininess, which the float64 sums resolve). This removes the ks-shininess ridge that
slows plain gradient descent. Only the specular part changes with shininess: where the
specular coefficient is fitted, the search takes the other parts' sums once and reads only
the specular part at each shininess (`_fixed_profile`).

A held coefficient may be a texture (a kd or ks map, fitting.texture_run): the parts are
then computed with the map in place of the unit coefficient (the cache reads it at each
sample's UV), so its part enters the offset as it is.

Per-view gains (fitting.spec.gains) multiply a view's parts, so with the gains fixed the
coefficients are still a linear problem, and with the coefficients fixed each view's gain
per channel is a 1-D least-squares ratio. When the spec fits gains, the two alternate
(`GAIN_ROUNDS` times at the searched shininess, which is then searched again with the
gains found): a start close enough for Levenberg-Marquardt to polish everything jointly.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.io import LIGHT_COMPILE, stored_jit
from diffshade.scene import Texture
from fitting.model.batch import batched, view_map
from fitting.model.cache import FitData, pixel_parts
from fitting.solve.bounded import minimize_bounded
from fitting.solve.distribute import ShardedViews, fit_data
from fitting.spec.gains import fitted_gains
from fitting.spec.params import COEFFICIENTS, FitSpec, values_to_material

SATURATION_EPS = 1e-6
GAIN_ROUNDS = 6


def _unit_material(base, spec, log_shininess):
    """The base material with unit coefficients (shininess exp(log_shininess) when
    fitted), built on the host: its leaves keep the base's dtype, so every call shares
    view_parts' one compilation. A held texture stays: its part is the map's."""
    dtype = base.ka.dtype
    ones = np.ones(3, dtype)
    has_specular = spec.ks is not None or base.ks is not None
    shininess = (np.asarray(np.exp(log_shininess), dtype) if spec.shininess
                 else base.shininess)
    kd, ks = (getattr(base, name) if _held_map(base, spec, name) else ones
              for name in ("kd", "ks"))
    return dataclasses.replace(base, ka=ones, kd=kd, ks=ks if has_specular else None,
                               shininess=shininess, emission=base.emission)


def _held_map(base, spec, name):
    """Whether coefficient `name` is held fixed as a texture (its part is then the map's)."""
    return getattr(spec, name) is None and isinstance(getattr(base, name), Texture)


def _selection(spec: FitSpec):
    """[p, 3 channels, 3 parts] 0/1: which (channel, part) each fitted coefficient scales
    (an 'rgb' coefficient one channel, a 'grey' one all three)."""
    rows = []
    for k, name in enumerate(COEFFICIENTS):
        channels = {"rgb": [[c] for c in range(3)], "grey": [[0, 1, 2]]}.get(getattr(spec, name),
                                                                           [])
        for chosen in channels:
            row = np.zeros((3, 3))
            row[chosen, k] = 1.0
            rows.append(row)
    return np.array(rows).reshape(-1, 3, 3)


def _offset(parts, spec, base):
    """[V, N, 3]: emission plus the parts of the coefficients held fixed."""
    offset = parts.emission
    for name, part in (("ka", parts.ambient), ("kd", parts.diffuse), ("ks", parts.specular)):
        if _held_map(base, spec, name):
            offset = offset + part
        elif getattr(spec, name) is None and getattr(base, name) is not None:
            offset = offset + np.asarray(getattr(base, name), np.float64) * part
    return offset


def _usable(target, weight, settings):
    """[V, N, 3] float: 1 where the pixel-channel is kept and linear in the coefficients."""
    usable = np.broadcast_to(weight[..., None], target.shape)
    if settings.clamp:
        usable = usable * ((target > SATURATION_EPS) & (target < 1.0 - SATURATION_EPS))
    return usable.astype(np.float64)


@stored_jit(compiler_options=LIGHT_COMPILE)
def view_parts(material, lights, data: FitData):
    """Every view's unclamped parts (fitting.model.cache.pixel_parts) of `material` under
    `lights` (one LightGroups per view; None: the data's) at the kept pixels, in one vmapped program
    (fitting.model.batch): (ShadingParts of [V, N, 3], targets [V, N, 3], weight [V, N]);
    the padding is 0. The linear solve, the gains and the identifiability check
    (fitting.report.uncertainty) all read it."""
    def one(samples, light, _):
        return (pixel_parts(material, light, data.global_ambient, samples, data.settings),
                samples.target)

    (parts, target), weight = view_map(one, data, lights)
    return parts, target, weight


def host_parts(material, lights, data: FitData):
    """view_parts on the host in float64, on `data`'s views stacked once
    (fitting.model.batch.batched)."""
    return jax.tree.map(lambda a: np.asarray(a, np.float64),
                        view_parts(material, lights, batched(data)))


def fold_parts(material, lights, data, spec, fn, total):
    """total = fn(total, parts, weight, view, target) over blocks of `data`'s views, in
    host memory (float64): parts a ShadingParts of [V, N, 3] (host_parts), weight [V, N],
    view [V] the blocks' view numbers, target [V, N, 3]. A FitData is one block (every
    view, stacked once); sharded views (fitting.solve.distribute.ShardedViews) are taken a
    chunk at a time (ShardedViews.parts_fold), so that a chunked fit's closed-form start
    holds one chunk's parts, whatever the number of views."""
    if isinstance(data, ShardedViews) and data.local:
        return data.parts_fold(material, lights, spec, fn, total)
    data = fit_data(data)  # (several processes: every view at once, as each holds all)
    parts, target, weight = host_parts(material, lights, data)
    return fn(total, parts, weight, np.arange(len(data.views)), target)


def normal_equations(log_shininess, data, spec: FitSpec, gains=None):
    """At shininess exp(log_shininess): G = X^T X [p, p], b = X^T y [p], c = y^T y and n
    (the number of usable pixel-channels), for the design X whose columns are the parts
    scaled by each fitted coefficient, and y = target - emission - fixed parts. gains:
    [V, 3] per-view gains that multiply the parts (None: 1). data: a FitData or its
    ShardedViews (then summed chunk by chunk). The parts come from view_parts (fold_parts);
    the sums are taken on the host in float64."""
    base = fit_data(data)
    material = _unit_material(base.material, spec, log_shininess)
    gains = None if gains is None else np.asarray(gains, np.float64)

    def add(total, parts, weight, view, target):
        if gains is not None:
            parts = parts.map(lambda a: a * gains[view][:, None, :])
        w = _usable(target, weight, base.settings)
        y = target - _offset(parts, spec, base.material)
        # per channel c, the 3 x 3 Gram of the parts (x [c, part, pixel]): 9x less work
        # than the design matrix, as matrix products
        x = np.stack([np.moveaxis(p, -1, 0).reshape(3, -1)
                      for p in (parts.ambient, parts.diffuse, parts.specular)], 1)
        xw = x * np.moveaxis(w, -1, 0).reshape(3, 1, -1)
        gram = xw @ np.swapaxes(x, 1, 2)
        rhs = (xw @ np.moveaxis(y, -1, 0).reshape(3, -1, 1))[..., 0]
        return (total[0] + gram, total[1] + rhs, total[2] + float(np.sum(w * y * y)),
                total[3] + float(np.sum(w)))

    gram, rhs, sq, count = fold_parts(material, None, data, spec, add,
                                      (np.zeros((3, 3, 3)), np.zeros((3, 3)), 0.0, 0.0))
    select = _selection(spec)
    return (np.einsum("ick,jcl,ckl->ij", select, select, gram),
            np.einsum("ick,ck->i", select, rhs), sq, count)


def box_least_squares(gram, rhs, lower, upper, max_iter=100):
    """argmin_x x^T G x - 2 b^T x subject to lower <= x <= upper (G [p, p] symmetric
    positive semi-definite, b [p]): a primal active-set method, exact for p this small."""
    p = len(rhs)
    if p == 0:
        return np.zeros(0)
    x = np.clip(np.linalg.lstsq(gram, rhs, rcond=None)[0], lower, upper)
    state = np.where(x <= lower, -1, np.where(x >= upper, 1, 0))
    for _ in range(max_iter):
        free = state == 0
        target = x.copy()
        if free.any():
            sub_rhs = rhs[free] - gram[np.ix_(free, ~free)] @ x[~free]
            target[free] = np.linalg.lstsq(gram[np.ix_(free, free)], sub_rhs, rcond=None)[0]
        step = target - x
        if np.max(np.abs(step), initial=0.0) <= 1e-14:
            grad = gram @ x - rhs
            wrong_side = np.where(state == -1, -grad, np.where(state == 1, grad, 0.0))
            worst = int(np.argmax(wrong_side))
            if wrong_side[worst] <= 1e-12 * max(np.abs(rhs).max(), 1e-30):
                return x
            state[worst] = 0
            continue
        x, state = _advance(x, step, state, lower, upper)
    return x


def _advance(x, step, state, lower, upper):
    """Move along `step` until the first bound is hit; pin that variable there."""
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(step < 0, (lower - x) / step, np.where(step > 0, (upper - x) / step,
                                                                 np.inf))
    reach = np.where(state == 0, reach, np.inf)
    blocking = int(np.argmin(reach))
    if reach[blocking] >= 1.0:
        return x + step, state
    x = x + reach[blocking] * step
    x[blocking] = lower if step[blocking] < 0 else upper
    state = state.copy()
    state[blocking] = -1 if step[blocking] < 0 else 1
    return x, state


def _solve(log_shininess, data, spec, gains=None):
    """(coefficients [p], mean squared residual) at shininess exp(log_shininess)."""
    gram, rhs, sq, count = normal_equations(np.asarray(log_shininess, np.float64), data,
                                            spec, gains)
    coef = box_least_squares(gram, rhs, 0.0, spec.upper)
    return coef, float(coef @ gram @ coef - 2 * coef @ rhs + sq) / max(float(count), 1.0)


def _dot(a, b):
    """a . b of two vectors, by einsum: BLAS (np.dot, @) starts its threads for vectors
    this long, which costs milliseconds a call where the cores are busy."""
    return float(np.einsum("i,i->", a, b))


def _channel_rows(a, w):
    """[3 channels, V * N] of a [V, N, 3] array, only where w > 0 (w: the same shape)."""
    return [np.moveaxis(a, -1, 0)[c][np.moveaxis(w, -1, 0)[c] > 0] for c in range(3)]


def _fixed_profile(data, spec, gains):
    """misfit(log_shininess) -> _solve's mean squared residual, for a search that varies
    shininess alone: where the specular coefficient is fitted, only the specular part
    changes with shininess, so the ambient and diffuse parts, the usable pixels, the
    right-hand side y and their sums are taken once, each evaluation computes the parts
    program once more and reads only its specular part (the sums over the usable
    pixel-channels, in float64, as normal_equations takes them). None where that does not
    hold (a fixed specular coefficient: the specular part is then in y; views summed
    chunk by chunk: their parts are not all in memory at once)."""
    if spec.ks is None or (isinstance(data, ShardedViews) and data.local):
        return None
    base = fit_data(data)
    stacked = batched(base)
    view_gain = np.ones((len(base.views), 1, 3)) if gains is None else gains[:, None, :]
    material = _unit_material(base.material, spec, np.float64(0.0))
    parts, target, weight = host_parts(material, None, base)
    parts = parts.map(lambda a: a * view_gain)
    w = _usable(target, weight, base.settings)
    y = target - _offset(parts, spec, base.material)
    rows = [_channel_rows(x, w) for x in (parts.ambient, parts.diffuse, w * y, w)]
    ambient, diffuse, wy, weights = rows
    fixed = [np.array([[_dot(weights[c] * p, q) for q in (ambient[c], diffuse[c])]
                       for p in (ambient[c], diffuse[c])]) for c in range(3)]
    fixed_rhs = [np.array([_dot(ambient[c], wy[c]), _dot(diffuse[c], wy[c])])
                 for c in range(3)]
    sq, count = float(np.sum(w * y * y)), float(np.sum(w))
    select = _selection(spec)

    def misfit(log_shininess):
        unit = _unit_material(base.material, spec, log_shininess)
        specular = np.asarray(view_parts(unit, None, stacked)[0].specular, np.float64)
        specular = _channel_rows(specular * view_gain, w)
        gram, rhs = np.zeros((3, 3, 3)), np.zeros((3, 3))
        for c in range(3):
            ws = weights[c] * specular[c]
            gram[c, :2, :2] = fixed[c]
            gram[c, 2, :2] = gram[c, :2, 2] = _dot(ws, ambient[c]), _dot(ws, diffuse[c])
            gram[c, 2, 2] = _dot(ws, specular[c])
            rhs[c] = (*fixed_rhs[c], _dot(specular[c], wy[c]))
        gram = np.einsum("ick,jcl,ckl->ij", select, select, gram)
        rhs = np.einsum("ick,ck->i", select, rhs)
        coef = box_least_squares(gram, rhs, 0.0, spec.upper)
        return float(coef @ gram @ coef - 2 * coef @ rhs + sq) / max(count, 1.0)
    return misfit


def _grid_minimum(misfit, grid):
    """(index of the best point of the grid, misfit at the points, inf where not taken),
    coarse to fine: every other point (and the last), then the two beside the best of
    those, whose best is then beside two points taken."""
    profile = np.full(len(grid), np.inf)
    for i in sorted({*range(0, len(grid), 2), len(grid) - 1}):
        profile[i] = misfit(grid[i])
    coarse = int(np.argmin(profile))
    for i in (coarse - 1, coarse + 1):
        if 0 <= i < len(grid) and profile[i] == np.inf:
            profile[i] = misfit(grid[i])
    return int(np.argmin(profile)), profile


def _search_shininess(data, spec, shininess_range, grid_size, gains=None):
    """Best log-shininess: the best point of a log grid (_grid_minimum), refined by
    bounded Brent."""
    misfit = _fixed_profile(data, spec, gains) or (lambda g: _solve(g, data, spec, gains)[1])
    grid = np.linspace(np.log(shininess_range[0]), np.log(shininess_range[1]), grid_size)
    best, profile = _grid_minimum(misfit, grid)
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, grid_size - 1)]
    x, fun = minimize_bounded(misfit, lo, hi, xatol=1e-6)
    return float(x) if fun <= profile[best] else float(grid[best])


def _split(coef, spec, dtype):
    values, start = {}, 0
    for name in spec.coefficients:
        size = 3 if getattr(spec, name) == "rgb" else 1
        chunk = coef[start:start + size]
        values[name] = jnp.asarray(chunk if size == 3 else chunk[0], dtype)
        start += size
    return values


def gain_moments(values, data, spec: FitSpec):
    """([V, 3] sum of w p t, [V, 3] sum of w p p) per view and channel: p the unclamped
    colour of the values' material at unit gain, t the target, w 1 at usable pixels
    (summed chunk by chunk for sharded views: fold_parts)."""
    base = fit_data(data)
    material = values_to_material(values, spec, base.material)

    def add(total, parts, weight, view, target):
        p, w = parts.total, _usable(target, weight, base.settings)
        np.add.at(total[0], view, np.sum(w * p * target, 1))  # a padding view: w = 0
        np.add.at(total[1], view, np.sum(w * p * p, 1))
        return total

    n = len(base.views)
    return fold_parts(material, None, data, spec, add, (np.zeros((n, 3)), np.zeros((n, 3))))


def _best_gains(values, data, spec):
    """[V, 3] least-squares gains for the values' material: per channel with white
    balance, shared by the channels for an exposure alone, green 1 for white balance
    alone; view 0 stays the reference (1)."""
    num, den = (np.asarray(a, np.float64) for a in gain_moments(values, data, spec))
    if not spec.white_balance:
        num, den = np.repeat(num.sum(1, keepdims=True), 3, 1), np.repeat(
            den.sum(1, keepdims=True), 3, 1)
    gains = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
    if not spec.exposure:
        gains = gains / gains[:, 1:2]
    gains[0] = 1.0
    return np.maximum(gains, 1e-6)


def _gain_values(gains, spec, dtype):
    """The values ('exposure' [V - 1], 'white_balance' [V - 1, 2]) of [V, 3] gains."""
    rest = jnp.asarray(gains[1:], dtype)
    values = {"exposure": rest[:, 1]} if spec.exposure else {}
    if spec.white_balance:
        values["white_balance"] = jnp.stack([rest[:, 0], rest[:, 2]], -1) / rest[:, 1:2]
    return values


def solve_linear(data, spec: FitSpec, *, shininess_range=(1.0, 2000.0),
                 grid_size=24) -> dict:
    """Physical values of the spec's material quantities: the coefficients in closed form,
    shininess (when fitted) by a 1-D search within `shininess_range`, and the per-view
    gains the spec fits (module docstring). Lights are held at `data.lights`. data: a
    FitData, or its ShardedViews (fitting.solve.distribute; with a chunk size, every sum is
    taken a chunk of views at a time). Returns the values dict (see fitting.spec.params)."""
    lo, hi = shininess_range
    if not (0 < lo < hi < float("inf")):
        raise ValueError(f"shininess_range: got {shininess_range!r}; expected 0 < low < high")
    base = fit_data(data)
    dtype = base.material.ka.dtype
    gains = np.ones((len(base.views), 3)) if fitted_gains(spec) else None

    def solve(gains):
        log_s = (_search_shininess(data, spec, shininess_range, grid_size, gains)
                 if spec.shininess else jnp.log(jnp.maximum(base.material.shininess, 1e-6)))
        values = _split(_solve(log_s, data, spec, gains)[0], spec, dtype)
        if spec.shininess:
            values["shininess"] = jnp.asarray(np.exp(log_s), dtype)
        return values, log_s

    values, log_s = solve(gains)
    if gains is None:
        return values
    for _ in range(GAIN_ROUNDS):
        gains = _best_gains(values, data, spec)
        values = {**values, **_split(_solve(log_s, data, spec, gains)[0], spec, dtype)}
    values, _ = solve(gains)
    return values | _gain_values(gains, spec, dtype)
