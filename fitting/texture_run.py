"""Texture maps fitted together with the uniform quantities, by alternation.

    run = fit_maps(dataset, spec, init, {"kd": 64}, options, smoothness=1e-3)
    run.state, run.data, run.maps, run.rounds    # then fitting.driver.fit_result(...)

The rule (docs/textures.md, "Recovering a texture"):
0. a uniform fit: `spec`'s quantities, the mapped ones included as uniform RGB, from
   `init` (the usual fit: fitting.run, with `options`) gives the start; each map starts
   flat at its uniform value;
1. each round: the maps (kd, ks or both) and the uniform RGB coefficients (ka, and kd
   or ks where not mapped) solved as one least-squares system
   (fitting.solve.texture_joint, the shininess and everything else held at its current
   value), in closed form
   (fitting.solve.texture) or by the method's descent (Adam, L-BFGS:
   fitting.solve.texture_descent); then the uniform quantities of `spec` (less the
   mapped ones, the shininess included) refitted with the maps held, by the usual fit on
   the cached pixels
   (fitting.model.cache reads the maps at each sample's UV), Adam and L-BFGS starting
   from the last round's values;
2. a round's change is the largest of: each uniform value's change relative to its
   previous value (to 0.01 at least, so a value near 0 is not divided by 0), and each
   map's RMS change over its seen texels relative to the RMS of those texels. The fit
   stops after the first round whose change is at most `round_tol` (default ROUND_TOL),
   or after `rounds` rounds (default MAX_ROUNDS). A spec that fits nothing beside one
   map (--fit kd with --texture kd=RES) holds the rest at `init`: one round, the map's
   closed form.
3. the rounds carry only the shininess (the next round's joint solve sets the maps and
   the RGB coefficients again), and the shininess approaches its fixed point
   geometrically (each round's uniform fit sees the held maps' curvature, not the
   joint one): after two rounds whose steps in log-shininess shrink by a ratio r in
   (0, MAX_RATIO), the next round starts from their limit, Aitken's delta-squared
   x + dx r / (1 - r) (that step at most MAX_LOG_STEP; then two plain rounds again);
4. after the last round, the texels' share of the uniform values' normal matrix at the
   result (fitting.report.texel_share), so that their standard errors marginalise the
   texels (MapRun.eliminated).

Each step lowers the same least-squares objective, so the rounds only go down hill. The
maps' pixels are those the uniform fit counts (covered, inside the view's mask, edge_margin
away from the silhouette), less those saturated in any channel when the settings clamp
(the maps' model is the unclamped, linear one). A map's texels that no view sees are 0 in
the material (and NaN in the map reported). The truth, when the dataset has one, is
never read here.

`check_maps(dataset, maps, key)` checks a request before any work: the map names (kd, ks),
their resolutions, a mesh with UVs, one object, and the memory the solve needs
(`map_bytes`: every view's linearized render and the solver's copies of the texels,
against diffshade.budget).
"""

import dataclasses
import time
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from diffshade.budget import check, render_bytes
from diffshade.scene import Mesh, Texture
from fitting.data.views import view_scene
from fitting.model.batch import batched
from fitting.model.cache import build_cache
from fitting.model.loss import make_loss
from fitting.report.texel_share import texel_share
from fitting.run import advance, finish, start_run
from fitting.solve.texture import TEXTURE_FIELDS
from fitting.solve.texture_joint import solve_texture_jointly
from fitting.spec.params import FitSpec, material_values, to_values

__all__ = ["MAX_ROUNDS", "ROUND_TOL", "MapRun", "check_map_fit", "check_maps", "fit_maps",
           "map_bytes", "uniform_spec"]

MAX_ROUNDS = 10
ROUND_TOL = 1e-3
MAX_RES = 8192
#: copies of the texels a solve holds at once: the 16 probes and their responses, the
#: 3 x 3 stencil (as probed and made symmetric), the iterate, residual, direction,
#: preconditioner, prior, right-hand side of both conjugate-gradient passes and the
#: sampling's (fitting.solve.texture)
TEXEL_COPIES = 64
RELATIVE_FLOOR = 0.01
#: the largest ratio of two rounds' shininess steps that is extrapolated, and the largest
#: extrapolated step in log-shininess (_extrapolated)
MAX_RATIO = 0.97
MAX_LOG_STEP = np.log(2.0)
SATURATION_EPS = 1e-6
MATERIAL_VALUES = ("ka", "kd", "ks", "shininess")


class MapRun(NamedTuple):
    """state: the last uniform fit's RunState (fitting.run; its wall_time the whole
    alternation's); data: its FitData (the base
    material holds the maps); maps: {field: TextureSolution}; rounds: one dict per round
    (its number, change, the uniform fit's loss and steps, each map's iterations);
    converged: the last round's change was at most round_tol; eliminated: (the texels'
    share of the uniform values' normal matrix, the seen texels' unknowns) for their
    standard errors with the maps marginalised (fitting.report.texel_share), None when
    no uniform value is fitted."""

    state: object
    data: object
    maps: dict
    rounds: tuple
    converged: bool
    eliminated: tuple | None = None


def _resolution(field, res, key):
    if isinstance(res, bool) or not isinstance(res, (int, np.integer)) or not (
            1 <= res <= MAX_RES):
        raise ValueError(f"{key}: got {field}={res!r}; expected a texture resolution RES "
                         f"in [1, {MAX_RES}]")


def map_bytes(dataset, res) -> int:
    """Bytes a RES x RES map solve needs: every view's linearized render (kept at once)
    and TEXEL_COPIES float64 copies of the texels per view and in all."""
    slots = dataset.settings.faces_per_pixel if dataset.settings.raster == "soft" else 1
    renders = sum(render_bytes(v.camera.width * v.camera.height, slots)
                  for v in dataset.views)
    return renders + res * res * 3 * 8 * (TEXEL_COPIES + len(dataset.views))


def check_maps(dataset, maps, key="textures"):
    """ValueError (diffshade.budget.SizeError for memory) naming `key` unless `maps` ({field: RES})
    is a request this dataset can serve (module docstring)."""
    if not isinstance(maps, dict) or not maps:
        raise ValueError(f"{key}: got {maps!r}; expected maps by name, e.g. {{'kd': 64}}")
    for field, res in maps.items():
        if field not in TEXTURE_FIELDS:
            raise ValueError(f"{key}: got a map named {field!r}; expected names among "
                             f"{', '.join(TEXTURE_FIELDS)}")
        _resolution(field, res, key)
        if not isinstance(dataset.mesh, Mesh) or dataset.mesh.uv is None:
            raise ValueError(f"{key}: {field}={res}: the dataset's mesh has no UVs; expected "
                             "a mesh with texture coordinates (an OBJ with vt, a built-in "
                             "shape with \"uv\": true)")
        if dataset.objects is not None:
            raise ValueError(f"{key}: {field}={res}: the dataset has several objects; "
                             "expected one (textures are for scenes of one object)")
        check(key, f"{field}={res}", map_bytes(dataset, res),
                     f"a {res}x{res} {field} map from {len(dataset.views)} views",
                     elements=12 * res * res)
    if len(maps) > 1:  # one system: the renders once, every map's texels
        texels = sum(map_bytes(dataset, res) - map_bytes(dataset, 0) for res in maps.values())
        text = ",".join(f"{field}={res}" for field, res in maps.items())
        check(key, text, map_bytes(dataset, 0) + texels,
              f"{text} maps solved together from {len(dataset.views)} views",
              elements=12 * sum(res * res for res in maps.values()))


def check_map_fit(dataset, spec: FitSpec, maps, options, callback=None, key="textures"):
    """ValueError unless a fit of `maps` with `spec`'s uniform quantities can run: the
    maps (check_maps), a spec of material quantities (no lights, gains or kt), one
    device, no chunks, no callback. A spec that fits nothing beside the maps holds the
    rest at the start."""
    check_maps(dataset, maps, key)
    unsupported = [name for name in ("light_colors", "light_positions", "exposure",
                                     "white_balance") if getattr(spec, name)]
    if spec.kt is not None:
        unsupported.append("kt")
    if unsupported:
        raise ValueError(f"spec: fits {', '.join(unsupported)} with {key}; expected only "
                         "material quantities (ka, kd, ks, shininess) beside maps")
    if options.chunk is not None or options.devices not in ("all", 1):
        raise ValueError(f"devices/chunk: got {options.devices!r}/{options.chunk!r} with "
                         f"{key}; expected one device and no chunks (a map fit is not "
                         "sharded)")
    if callback is not None:
        raise ValueError(f"callback: got {callback!r} with {key}; expected None")


def uniform_spec(spec: FitSpec, maps) -> FitSpec:
    """`spec` less the mapped coefficients (they are held as maps)."""
    return dataclasses.replace(spec, **{field: None for field in maps})


def _counted_masks(dataset, data):
    """Per view [H, W] bool: the pixels the cache keeps, less those saturated in some
    channel when the settings clamp."""
    masks = []
    for view, samples in zip(dataset.views, data.views, strict=True):
        height, width = view.target.shape[:2]
        mask = np.zeros(height * width, bool)
        mask[np.asarray(samples.pixels)] = True
        mask = mask.reshape(height, width)
        if dataset.settings.clamp:
            mask &= np.all((view.target > SATURATION_EPS)
                           & (view.target < 1.0 - SATURATION_EPS), -1)
        masks.append(mask)
    return masks


def _uniform_fit(data, spec, material, options):
    """The usual fit of `spec` on the cached data with `material` as the base and start
    (Adam and L-BFGS continue from its values); a spec that fits nothing (only maps)
    only takes the loss. Returns (RunState, the FitData)."""
    data = dataclasses.replace(data, material=material)
    state = start_run(data, spec, material, options)
    if not spec.fits_material:
        loss = float(make_loss(spec, options.loss)({}, batched(data)))
        state.history.append(loss)
        state.best_loss, state.best_params, state.converged = loss, {}, True
        return state, data
    advance(state, data)
    finish(state, data)
    return state, data


def _joint(spec):
    """The uniform RGB coefficients solved with the maps."""
    return [name for name in ("ka", "kd", "ks") if getattr(spec, name) == "rgb"]


def _solve_maps(dataset, material, maps, masks, options, smoothness, spec):
    """The maps ({field: RES}) with the uniform RGB coefficients of `spec` solved with them,
    as one least-squares solution (fitting.solve.texture_joint), everything else at
    `material`'s; returns (the JointSolution, the material with those coefficients and
    the maps)."""
    blank = dataclasses.replace(material, **{field: Texture(jnp.zeros((res, res, 3)))
                                             for field, res in maps.items()})
    scenes = [view_scene(dataset, i, blank) for i in range(len(dataset.views))]
    targets = [v.target for v in dataset.views]
    solution = solve_texture_jointly(
        scenes, targets, masks, maps, dataset.settings, coefficients=_joint(spec),
        upper=spec.upper, method=options.method, smoothness=smoothness)
    material = dataclasses.replace(material, **solution.values)
    return solution, _with_maps(material, solution.maps)


def _with_maps(material, maps):
    """material with each solved map in place (unseen texels 0)."""
    return dataclasses.replace(material, **{
        field: Texture(jnp.nan_to_num(jnp.asarray(solution.texels), nan=0.0))
        for field, solution in maps.items()})


def _change(old_values, values, old_maps, maps):
    """The round's change (module docstring): old_maps, maps {field: [R, R, 3]} (NaN
    where unseen)."""
    changes = [0.0]
    for name, new in values.items():
        old, new = np.asarray(old_values[name], np.float64), np.asarray(new, np.float64)
        changes.append(float(np.max(np.abs(new - old) / np.maximum(np.abs(old),
                                                                   RELATIVE_FLOOR))))
    for field, new in maps.items():
        old = old_maps[field]
        seen = np.isfinite(new) & np.isfinite(old)
        scale = np.sqrt(np.mean(old[seen] ** 2)) if seen.any() else 0.0
        if scale > 0:
            changes.append(float(np.sqrt(np.mean((new[seen] - old[seen]) ** 2)) / scale))
    return max(changes)


def _with_values(material, values):
    """material with the uniform material values of a fit in place."""
    return dataclasses.replace(material, **{k: values[k] for k in MATERIAL_VALUES
                                            if k in values})


def _start(data, spec, maps, init, options):
    """Step 0: the uniform fit with the mapped coefficients uniform (RGB); returns the
    material with each map flat at its uniform value."""
    start_spec = dataclasses.replace(spec, **{field: "rgb" for field in maps})
    state, _ = _uniform_fit(data, start_spec, init, options)
    material = _with_values(init, to_values(state.best_params, start_spec))
    return dataclasses.replace(material, **{
        field: Texture(jnp.broadcast_to(jnp.asarray(getattr(material, field)), (res, res, 3)))
        for field, res in maps.items()})


def _round(dataset, data, masks, maps, uniform, material, options, smoothness):
    """One round (module docstring): (the maps' JointSolution, the material after it, the
    uniform fit's RunState, its FitData)."""
    joint, material = _solve_maps(dataset, material, maps, masks, options, smoothness,
                                  uniform)
    state, data = _uniform_fit(data, uniform, material, options)
    return joint, _with_values(material, to_values(state.best_params, uniform)), state, data


def _extrapolated(material, carried):
    """(the material for the next round, the log-shininess history since the last
    extrapolation): after two plain rounds whose shininess moves geometrically (ratio r
    in (0, MAX_RATIO)), the shininess they converge to, Aitken's delta-squared (module
    docstring), which the next round starts from."""
    carried = [*carried, np.log(np.asarray(material.shininess, np.float64))]
    if len(carried) < 3:
        return material, carried
    first, second = carried[-2] - carried[-3], carried[-1] - carried[-2]
    ratio = np.where(np.abs(first) > 0, second / np.where(first == 0, 1.0, first), 0.0)
    if not np.all((ratio > 0) & (ratio < MAX_RATIO)):
        return material, carried[-2:]
    target = carried[-1] + np.clip(second * ratio / (1.0 - ratio), -MAX_LOG_STEP,
                                   MAX_LOG_STEP)
    shininess = np.exp(target).astype(np.asarray(material.shininess).dtype)
    return dataclasses.replace(material, shininess=jnp.asarray(shininess)), [target]


def fit_maps(dataset, spec: FitSpec, init, maps: dict, options, *, smoothness,
             rounds=MAX_ROUNDS, round_tol=ROUND_TOL) -> MapRun:
    """The maps ({field: RES}) and `spec`'s uniform quantities of `dataset`, fitted by
    alternation from `init` (module docstring). options: FitOptions (the method runs
    the maps too); smoothness: the maps' prior weight (fitting.solve.texture). The request
    is checked by the caller (check_map_fit)."""
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"rounds: got {rounds!r}; expected an integer >= 1")
    if not (isinstance(round_tol, (int, float)) and 0 <= round_tol < np.inf):
        raise ValueError(f"round_tol: got {round_tol!r}; expected a finite number >= 0")
    start = time.perf_counter()
    data = build_cache(dataset, init, edge_margin=options.edge_margin, uv=True)
    material = _start(data, spec, maps, init, options)
    masks = _counted_masks(dataset, data)
    uniform = uniform_spec(spec, maps)
    values = material_values(material, uniform)
    texels = {field: np.asarray(getattr(material, field).texels) for field in maps}
    log, converged = [], False
    carried = [np.log(np.asarray(material.shininess, np.float64))] if uniform.shininess else None
    for number in range(1, rounds + 1):
        joint, material, state, data = _round(dataset, data, masks, maps, uniform,
                                              material, options, smoothness)
        solved = joint.maps
        new_values = material_values(material, uniform)
        new_texels = {field: np.asarray(s.texels) for field, s in solved.items()}
        change = _change(values, new_values, texels, new_texels)
        values, texels = new_values, new_texels
        log.append({"round": number, "change": change, "loss": state.best_loss,
                    "steps": state.step,
                    "map_iterations": {f: s.iterations for f, s in solved.items()}})
        # one map and nothing else fitted: the map's closed form is the answer
        converged = change <= round_tol or (len(maps) == 1 and not uniform.fits_material)
        if converged:
            break
        if carried is not None:
            material, carried = _extrapolated(material, carried)
    eliminated = None
    if uniform.fits_material:
        share = texel_share(dataset, data, to_values(state.best_params, uniform), uniform,
                            maps, masks, batch=1 + len(_joint(uniform)), method=options.method,
                            smoothness=smoothness)
        unknowns = 3 * sum(int(np.sum(np.asarray(s.coverage) > 0)) for s in solved.values())
        eliminated = (share, unknowns)
    state.wall_time = time.perf_counter() - start  # the whole alternation's
    return MapRun(state, data, solved, tuple(log), converged, eliminated)
