"""Many views on many devices: a fit's views sharded across devices and streamed in chunks.

The cached fit (fitting.model.cache) keeps, per view, the shading samples of its kept pixels.
`shard_views(data, devices=..., chunk=...)` lays them out for a sharded, chunked fit:

- grouped: the views by sample layout (`layout_index`: which arrays their samples carry,
  e.g. shadow visibility for a view whose lights cast shadows beside one whose do not,
  or fragment layers); each group is chunked and compiled apart (one program per
  layout), its views' lights padded to one layout (fitting.model.batch.common_lights);
- chunked: each group's views cut into ceil(views / chunk) chunks of equal size, at most
  `chunk` views rounded up to a multiple of the device count (the last chunk padded with
  views of weight 0);
- stacked, per chunk and only from that chunk's views: their arrays (the samples, how
  the pixels read them, and where the scene has them the samples' shadow visibility and
  the pixels' fragment layers) padded to the group's largest row counts (padded pixels
  weigh 0 in the loss; padded rows repeat a real one, so that nothing in the padding is
  NaN) and stacked along a leading views axis, in host memory (NumPy), by
  fitting.model.batch.stack_views, as the one-device fit stacks them;
- sharded: each chunk is placed on a 1-D device mesh with axis name "views"
  (`jax.sharding.NamedSharding(mesh, PartitionSpec("views"))`), so every device holds
  chunk / devices of its views. The params and the accumulators are replicated.

A loss, gradient or Gauss-Newton system is then a sum over chunks of one jitted chunk
function (the same compiled program for every chunk of a group): the chunk is stacked
and transferred, its sum of rho(residual) and the gradient of that sum are added to the
running totals, and the total is divided by the number of kept pixel-channels at the end
— the same mean as `fitting.model.loss.make_loss`, summed in another order (equal to float32
rounding; tested). Inside a chunk XLA's SPMD partitioner splits the views over the
devices and reduces the sums across them (an all-reduce), so the gradient every device
sees is the whole chunk's.

Memory. With a chunk size (and more than one chunk) the chunks are streamed: no chunk is
kept; each is stacked on the host from its own views when it is used (the next one while
the devices run the current one), transferred, and dropped once its sums are done. What
a fit holds beyond the per-view cache is then one chunk on the devices and one on the
host, with the intermediates of one chunk's gradient, whatever the number of views. The
per-view cache itself (`fit_data`: each view's samples, unpadded, in host memory) grows
with the views: every step reads all of it. Without a chunk size every group is one
chunk, stacked and transferred once and kept on the devices (L-BFGS needs this: its line
search runs inside one compiled step).

Several hosts: after `jax.distributed.initialize()`, `devices="all"` is every process's
devices, and each process places only the rows of a chunk that its own devices hold
(`jax.make_array_from_callback`). Every process builds the same cache (all views), so
they agree on the padding and the chunks (docs/performance.md; not tested on real hosts).

`fitting.run` uses a `ShardedViews` where it would use the `FitData`: its optax steps
(Adam: the gradient accumulated over chunks, then one optimizer update; L-BFGS: the
resident chunks, whose loss its line search evaluates inside one compiled step), the
loss, the gradient and Levenberg-Marquardt's J^T W J (fitting.solve.gauss_newton). The
closed-form start of the 'linear' method (fitting.solve.linear), the uncertainty report
(fitting.report.uncertainty) and the misfit check (fitting.report.misfit) take the
ShardedViews too and run over the same chunks (`host_fold`): per chunk one compiled
program, the same for every chunk of a sample layout, gives the chunk's per-pixel results
(`parts_fold`: the unclamped shading parts; `rows_fold`: the residuals and their Jacobian
with respect to the physical values), which are read back and summed on the host in
float64 (the normal equations, J^T J, the rounding bound, per-view sums) and dropped; so
with a chunk size these too hold one chunk's rows, whatever the number of views. Across
several processes they run on the plain FitData, every view at once (`local`).
"""

import dataclasses
import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from fitting.model.batch import common_lights, stack_views
from fitting.model.cache import FitData, ViewSamples, pixel_parts, predict
from fitting.model.loss import check_kind, irls_weight, rho
from fitting.solve.step import make_step
from fitting.spec.gains import scaled_material, view_gains
from fitting.spec.params import to_values, values_to_lights, values_to_material

AXIS = "views"


class Chunk(NamedTuple):
    """One chunk of C views, each padded to N pixels and S samples: samples: ViewSamples
    with a leading [C] axis; weight: [C, N] (1 at a kept pixel, 0 in the padding); view:
    [C] int32 index of the view (0 for a padding view); lights: LightGroups with a
    leading [C] axis (the views' own lights)."""

    samples: ViewSamples
    weight: np.ndarray
    view: np.ndarray
    lights: object


class Shared(NamedTuple):
    """What every view reads (replicated on every device): the base material, the global
    ambient, the settings, and the views' lights as given (a tuple, one LightGroups per
    view; only when the spec fits lights, else ())."""

    material: object
    global_ambient: object
    settings: object
    lights: tuple


def device_list(devices):
    """The devices a fit runs on: 'all' -> jax.devices() (every process's after
    jax.distributed.initialize), n -> the first n."""
    found = jax.devices()
    if devices == "all":
        return found
    if isinstance(devices, bool) or not isinstance(devices, int) or devices < 1:
        raise ValueError(f"devices: got {devices!r}; expected 'all' or an integer >= 1")
    if devices > len(found):
        raise ValueError(f"devices: got {devices}; expected at most {len(found)}, the "
                         f"devices JAX sees ({found[0].platform})")
    return found[:devices]


def wants_sharding(devices, chunk) -> bool:
    """Whether a fit with these options runs on the sharded views (several devices, or a
    chunk size); else on the plain FitData, as on one device."""
    return chunk is not None or len(device_list(devices)) > 1


def _host(tree):
    return jax.tree.map(np.asarray, tree)


def _chunk(views, lights, index, rows, spare, n):
    """The Chunk of `views` (ViewSamples in host memory; None: a padding view of weight
    0, a copy of the chunk's first real view), stacked by fitting.model.batch.stack_views with
    each leaf padded to its `rows` (every chunk of a sample layout alike: one compiled
    program); padded rows repeat a real one (`spare`'s first, for a view without pixels),
    so that nothing is NaN. n: the padded pixel count."""
    real = next(v for v in views if v is not None)
    weight = np.zeros((len(views), n), np.asarray(real.target).dtype)
    for i, (v, pad) in enumerate(zip(views, index, strict=True)):
        if pad is not None:
            weight[i, :v.pixels.shape[0]] = 1.0
    samples, lights = stack_views([real if v is None else v for v in views], lights, rows,
                                  spare)
    return Chunk(samples, weight, np.asarray([0 if i is None else i for i in index],
                                             np.int32), lights)


def _layout(view):
    return jax.tree.structure(view), tuple(np.shape(x)[1:] for x in jax.tree.leaves(view))


def layout_index(views) -> tuple:
    """The view numbers grouped by sample layout (which arrays a view's samples carry:
    shadow visibility, fragment layers, objects; and their trailing shapes), in order of
    first appearance: tuple of tuples. Each group is stacked into chunks of its own."""
    groups = {}
    for i, view in enumerate(views):
        groups.setdefault(_layout(view), []).append(i)
    return tuple(tuple(index) for index in groups.values())


def _stack_problem(data: FitData):
    """Why `data`'s views cannot be stacked into chunks (a message), or None. The views
    of each sample layout (layout_index) are stacked apart, their lights padded to one
    layout (common_lights), which needs the same static settings (shadow flags)."""
    for index in layout_index(data.views):
        try:
            common_lights([data.lights[i] for i in index], index)
        except ValueError as error:
            return str(error)
    return None


class Group(NamedTuple):
    """The views of one sample layout, as their chunks are built: index: the view
    numbers; rows: the row count of each ViewSamples leaf (jax.tree.leaves order), the
    group's largest, every chunk of the group padded to it; spare: a host ViewSamples of
    the group with pixels (its first rows pad a leaf none of a chunk's views has rows
    in); n: the padded pixel count; lights: {view: its LightGroups padded to the group's
    one layout (common_lights), host}."""

    index: tuple
    rows: list
    spare: object
    n: int
    lights: dict


@dataclasses.dataclass
class ShardedViews:
    """A FitData's views laid out for a sharded, chunked fit (module docstring).
    fit_data: the plain FitData, its views' arrays in host memory (NumPy), read by the
    chunks as they are built, by the closed-form start and the report; mesh: the 1-D
    "views" Mesh; groups: one Group per sample layout; slots: per chunk, (its group,
    its view numbers, None for a padding view of weight 0); count: kept pixel-channels
    over all views (the loss's denominator); n_views: the real views; chunk_size: the
    most views per chunk (a multiple of the device count); streamed: whether the chunks
    are built and transferred per use (a chunk size, and more than one chunk), else all
    are built once and kept on the devices."""

    fit_data: FitData
    mesh: Mesh
    groups: list
    slots: list
    count: int
    n_views: int
    chunk_size: int
    streamed: bool
    _resident: tuple | None = None
    _shared: dict = dataclasses.field(default_factory=dict)

    @property
    def lights(self):
        return self.fit_data.lights

    @property
    def views(self):
        return self.fit_data.views

    @property
    def n_devices(self) -> int:
        return self.mesh.devices.size

    @property
    def n_chunks(self) -> int:
        return len(self.slots)

    def host_chunk(self, k):
        """Chunk k, stacked in host memory from its own views only (fitting.model.batch
        .stack_views on at most chunk_size views)."""
        group, index = self.slots[k]
        group = self.groups[group]
        first = group.index[0]
        return _chunk([None if i is None else self.views[i] for i in index],
                      [group.lights[first if i is None else i] for i in index], index,
                      group.rows, group.spare, group.n)

    def sharded(self, tree):
        """tree placed with its leading axis split over the mesh (each process supplies
        the rows its devices hold)."""
        return _put(tree, NamedSharding(self.mesh, P(AXIS)))

    def placed(self, chunk):
        """A Chunk built by host_chunk placed as `sharded` places it; on CPU devices its
        arrays are taken without a copy where they allow it (_adopt): they are the
        chunk's own, written by nothing after."""
        return _put(chunk, NamedSharding(self.mesh, P(AXIS)), adopt=True)

    def replicated(self, tree):
        return _put(tree, NamedSharding(self.mesh, P()))

    def resident_chunks(self) -> tuple:
        """Every chunk on the devices (one per sample layout when no chunk size was
        given), built and transferred once and kept."""
        if self._resident is None:
            self._resident = tuple(self.placed(self.host_chunk(k))
                                   for k in range(self.n_chunks))
        return self._resident

    def accumulate(self, fn, total):
        """total = fn(total, chunk) over the chunks on the devices. Kept chunks
        (resident_chunks) when not streamed; else each chunk is built on the host from
        its views and transferred as it is used: chunk k + 1 is stacked while chunk k's
        sums run (JAX dispatches asynchronously), and placed only once they are done, so
        that at most one chunk is on the devices and one more on the host (without the
        wait, every chunk would be in memory at once)."""
        if not self.streamed:
            for chunk in self.resident_chunks():
                total = fn(total, chunk)
            return total
        host = self.host_chunk(0)
        for k in range(self.n_chunks):
            placed = self.placed(host)
            host = None
            total = fn(total, placed)
            if k + 1 < self.n_chunks:
                host = self.host_chunk(k + 1)
            total = jax.block_until_ready(total)
            del placed
        return total

    def shared(self, spec):
        """Shared, replicated on the devices (placed once per kind of spec)."""
        if spec.fits_lights not in self._shared:
            self._shared[spec.fits_lights] = self._place_shared(spec)
        return self._shared[spec.fits_lights]

    def _place_shared(self, spec):
        data = self.fit_data
        if spec.fits_lights:
            for i, g in enumerate(data.lights):
                if _light_shapes(g) != _light_shapes(data.lights[0]):
                    raise ValueError(f"views[{i}].lights: other kinds or counts than "
                                     "views[0]'s; a sharded or chunked fit of the lights "
                                     "needs one light layout (fit with devices=1 and "
                                     "chunk=None)")
        return self.replicated(Shared(data.material, data.global_ambient, data.settings,
                                      tuple(data.lights) if spec.fits_lights else ()))

    # ---- what fitting.run and fitting.solve.gauss_newton call ----

    def loss(self, params, spec, kind="mse"):
        """The loss (a scalar on the devices), as fitting.model.loss.make_loss(spec, kind)."""
        check_kind(kind)
        params, shared = self.replicated(params), self.shared(spec)
        total = self.replicated(jnp.zeros((), _dtype(params)))
        total = self.accumulate(lambda t, chunk: _chunk_loss(
            params, t, shared, chunk, spec, kind, self.n_views), total)
        return total / self.count

    def value_and_grad(self, params, spec, kind="mse"):
        """(loss, gradient with respect to params), accumulated over the chunks."""
        check_kind(kind)
        params, shared = self.replicated(params), self.shared(spec)
        total = self.replicated((jnp.zeros((), _dtype(params)),
                                 jax.tree.map(jnp.zeros_like, params)))
        total = self.accumulate(lambda t, chunk: _chunk_value_grad(
            params, t, shared, chunk, spec, kind, self.n_views), total)
        value, grads = total
        return value / self.count, jax.tree.map(lambda g: g / self.count, grads)

    def linearize(self, params, spec, kind="mse"):
        """(loss, J^T W J [p, p], J^T W r [p]) as fitting.solve.gauss_newton.linearize, J^T W J
        and J^T W r summed over the chunks."""
        check_kind(kind)
        params, shared = self.replicated(params), self.shared(spec)
        p = ravel_pytree(params)[0].shape[0]
        dtype = _dtype(params)
        total = self.replicated((jnp.zeros((), dtype), jnp.zeros((p, p), dtype),
                                 jnp.zeros(p, dtype)))
        total = self.accumulate(lambda t, chunk: _chunk_normal(
            params, t, shared, chunk, spec, kind, self.n_views), total)
        loss, hess, grad = total
        return loss / self.count, hess, grad

    @property
    def local(self) -> bool:
        """Whether this process holds every device of the mesh (one process): only then
        are the host sums taken a chunk at a time (host_fold reads each chunk back);
        across several processes the closed-form start and the report run on the plain
        per-view cache, which every process holds (fitting.solve.linear.fold_parts,
        fitting.report.uncertainty.rows_fold)."""
        return all(d.process_index == jax.process_index() for d in self.mesh.devices.flat)

    def host_fold(self, program, fn, total):
        """total = fn(total, out, weight, view, target) over the chunks (accumulate), out
        = program(chunk): the chunk's per-pixel results [C, N, ...] in host memory
        (float64), with its weight [C, N] (0 in the padding and for a padding view), view
        numbers [C] and targets [C, N, 3] (float64): the host sums of the closed-form
        start (fitting.solve.linear), the standard errors (fitting.report.uncertainty) and
        the misfit check (fitting.report.misfit), one chunk's rows at a time. One process
        only (`local`: the chunk's rows are read back on the host)."""
        def one(t, chunk):
            out = jax.tree.map(lambda a: np.asarray(a, np.float64), program(chunk))
            return fn(t, out, np.asarray(chunk.weight), np.asarray(chunk.view),
                      np.asarray(chunk.samples.target, np.float64))
        return self.accumulate(one, total)

    def parts_fold(self, material, lights, spec, fn, total):
        """host_fold of the unclamped parts (fitting.model.cache.pixel_parts, a ShadingParts of
        [C, N, 3], 0 in the padding) of `material` under `lights` (one LightGroups per
        view, as fitting.solve.linear.view_parts takes them; None: each view's own)."""
        shared = self.shared(spec)
        # host arrays of one dtype each: every caller's material shares one compilation
        material, every = _host((material, None if lights is None else tuple(lights)))
        return self.host_fold(lambda chunk: _chunk_parts(material, every, shared, chunk),
                              fn, total)

    def rows_fold(self, values, spec, fn, total):
        """host_fold of (residuals [C, N, 3], their Jacobian [C, N, 3, p] with respect to
        the physical `values`, columns in jax.tree.leaves order), 0 in the padding: per
        chunk what fitting.solve.gauss_newton.normal_system gives for all views at once."""
        shared, values = self.shared(spec), _host(values)
        return self.host_fold(lambda chunk: _chunk_rows(values, shared, chunk, spec,
                                                        self.n_views), fn, total)

    def step_fn(self, spec, options, optimizer):
        """step(params, opt_state, self) -> (params, opt_state, loss) for an optax method:
        L-BFGS (its line search evaluates the loss inside the compiled step) runs
        fitting.solve.step.make_step on the resident chunks (one per sample layout); Adam
        accumulates the gradient over the chunks, then makes one update."""
        if options.method == "lbfgs":  # FitOptions: chunk None, so the resident chunks
            step = _lbfgs_step(spec, options.loss, self.n_views, self.count, optimizer)
            shared = self.shared(spec)

            def lbfgs(params, opt_state, data):
                return step(self.replicated(params), self.replicated(opt_state),
                            (shared, data.resident_chunks()))
            return lbfgs
        update = _update(optimizer)

        def adam(params, opt_state, data):
            loss, grads = data.value_and_grad(params, spec, options.loss)
            return update(self.replicated(params), self.replicated(opt_state), loss, grads)
        return adam


def _adoptable(x, sharding) -> bool:
    return (isinstance(x, np.ndarray) and x.flags.c_contiguous and x.flags.writeable
            and x.dtype.kind in "biuf" and x.ndim > 0
            and all(d.platform == "cpu" for d in sharding.device_set))


def _adopt(host, sharding):
    """A NumPy array as a jax.Array with `sharding` on CPU devices, each device's rows
    handed to XLA through DLPack: without a copy where XLA's CPU client can use the
    memory as it is (64-byte aligned, on the first device: fitting.model.batch.aligned_empty),
    else copied, as jax.device_put would. The array must not be written afterwards."""
    parts = [jax.dlpack.from_dlpack(host[index], device=device) for device, index in
             sharding.addressable_devices_indices_map(host.shape).items()]
    return jax.make_array_from_single_device_arrays(host.shape, sharding, parts)


def _put(tree, sharding, adopt=False):
    """tree's leaves placed with `sharding`; across several processes each process
    supplies, from its own host copy, the slices its devices hold. adopt: NumPy leaves
    that nothing writes afterwards are handed to CPU devices without a copy (_adopt)."""
    if sharding.is_fully_addressable:  # one process: one call for what is not placed
        leaves, treedef = jax.tree.flatten(tree)
        if adopt:
            leaves = [_adopt(x, sharding) if _adoptable(x, sharding) else x
                      for x in leaves]
        moving = [i for i, x in enumerate(leaves)
                  if not (isinstance(x, jax.Array) and x.sharding == sharding)]
        for i, x in zip(moving, jax.device_put([leaves[i] for i in moving], sharding),
                        strict=True):
            leaves[i] = x
        return jax.tree.unflatten(treedef, leaves)

    def one(x):
        if isinstance(x, jax.Array) and x.sharding == sharding:
            return x
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])
    return jax.tree.map(one, tree)


def _dtype(params):
    return jax.tree.leaves(params)[0].dtype


def _light_shapes(lights):
    """The kinds and counts of a LightGroups (its leaves' shapes), static settings left
    out: the views whose lights a sharded fit of the lights stacks must share them."""
    kinds = tuple(f.name for f in dataclasses.fields(lights) if getattr(lights, f.name)
                  is not None)
    return kinds, tuple(np.shape(x) for x in jax.tree.leaves(lights))


def shard_views(data: FitData, devices="all", chunk=None, *,
                consume=False) -> ShardedViews:
    """`data`'s views laid out for a sharded, chunked fit (module docstring). devices:
    'all' or a count; chunk: the most views per chunk (None: all views of each sample
    layout in one chunk), rounded up to a multiple of the device count. Use the returned
    ShardedViews' fit_data in place of `data` from then on: its views are `data`'s in
    host memory (on a CPU the same memory, no copy). Nothing is stacked here: each chunk
    is stacked from its own views when it is used. consume: free each view's arrays in
    `data` (jax.Array.delete) once the host holds them, so that an accelerator's memory
    does not keep the whole cache; `data`'s views are unusable after."""
    if not isinstance(data, FitData):
        raise TypeError(f"data: got {type(data).__name__}; expected fitting.model.FitData")
    found = device_list(devices)
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int)
                              or chunk < 1):
        raise ValueError(f"chunk: got {chunk!r}; expected None or an integer >= 1")
    problem = _stack_problem(data)
    if problem is not None:
        raise ValueError(problem)
    views = []
    for view in data.views:  # one view at a time: on an accelerator, one more view's memory
        views.append(_host(view))
        if consume:
            for leaf in jax.tree.leaves(view):
                if isinstance(leaf, jax.Array) and not leaf.is_deleted():
                    leaf.delete()
    n_dev, n_views = len(found), len(views)
    groups, slots, size = [], [], n_dev
    for index in layout_index(views):
        real = [i for i in index if views[i].pixels.shape[0]]
        if not real:  # no kept pixel: nothing to add to any sum
            continue
        n_chunks = 1 if chunk is None else math.ceil(len(index) / chunk)
        per = math.ceil(math.ceil(len(index) / n_chunks) / n_dev) * n_dev  # balanced
        n_chunks, size = math.ceil(len(index) / per), max(size, per)
        rows = [max(column) for column in zip(*([np.shape(x)[0] for x in
                                                 jax.tree.leaves(views[i])]
                                                for i in index), strict=True)]
        lights = common_lights([_host(data.lights[i]) for i in index], index)
        groups.append(Group(index, rows, views[real[0]], max(
            views[i].pixels.shape[0] for i in index), dict(zip(index, lights, strict=True))))
        padded = list(index) + [None] * (n_chunks * per - len(index))
        slots += [(len(groups) - 1, tuple(padded[k:k + per]))
                  for k in range(0, len(padded), per)]
    count = 3 * sum(v.pixels.shape[0] for v in views)
    mesh = Mesh(np.array(found), (AXIS,))
    return ShardedViews(dataclasses.replace(data, views=tuple(views)), mesh, groups, slots,
                        count, n_views, size, chunk is not None and len(slots) > 1)


def for_options(data: FitData, options):
    """The data a fit with `options` runs on: ShardedViews when it asks for several
    devices or a chunk size (fitting.solve.options: devices, chunk), else `data` itself. A
    sharded `data` is consumed (shard_views): use fit_data(result) from then on."""
    default = options.devices == "all" and options.chunk is None
    if default and _stack_problem(data) is not None:
        return data  # views that do not stack: one device, as documented
    if wants_sharding(options.devices, options.chunk):
        return shard_views(data, options.devices, options.chunk, consume=True)
    return data


def fit_data(data) -> FitData:
    """The plain FitData of `data` (a FitData or a ShardedViews)."""
    return data.fit_data if isinstance(data, ShardedViews) else data


# ---- the compiled chunk functions (one program per chunk shape, spec and loss) ----


def _view_lights(chunk, every):
    """The chunk's lights: its own, or (every: one LightGroups per view, all views alike)
    its views' rows of `every`, with the chunk's static flags."""
    if every is None:
        return chunk.lights
    leaves = [jnp.stack(x)[chunk.view] for x in zip(*map(jax.tree.leaves, every),
                                                    strict=True)]
    return jax.tree.unflatten(jax.tree.structure(chunk.lights), leaves)


def _value_residuals(values, shared: Shared, chunk: Chunk, spec, n_views):
    """Residuals [C, N, 3] of the chunk's views at the physical values (padded pixels
    included)."""
    material = values_to_material(values, spec, shared.material)
    every = (values_to_lights(values, spec, shared.lights) if "lights" in values
             else None)  # fitted lights: every view's, then the chunk's rows
    gains = view_gains(values, n_views)

    def one(samples, light, view):
        m = material if gains is None else scaled_material(material, gains[view])
        return predict(m, light, shared.global_ambient, samples, shared.settings) - samples.target

    return jax.vmap(one)(chunk.samples, _view_lights(chunk, every), chunk.view)


def _chunk_residuals(params, shared: Shared, chunk: Chunk, spec, n_views):
    """Residuals [C, N, 3] of the chunk's views (padded pixels included)."""
    return _value_residuals(to_values(params, spec), shared, chunk, spec, n_views)


def _chunk_sum(params, shared, chunk, spec, kind, n_views):
    """Sum of rho over the chunk's kept pixel-channels."""
    r = _chunk_residuals(params, shared, chunk, spec, n_views)
    w = chunk.weight[..., None]
    return jnp.sum(w * rho(kind, jnp.where(w > 0, r, 0.0)))


@partial(jax.jit, static_argnames=("spec", "kind", "n_views"))
def _chunk_loss(params, total, shared, chunk, spec, kind, n_views):
    return total + _chunk_sum(params, shared, chunk, spec, kind, n_views)


@partial(jax.jit, static_argnames=("spec", "kind", "n_views"))
def _chunk_value_grad(params, total, shared, chunk, spec, kind, n_views):
    value, grads = jax.value_and_grad(_chunk_sum)(params, shared, chunk, spec, kind, n_views)
    return total[0] + value, jax.tree.map(jnp.add, total[1], grads)


@partial(jax.jit, static_argnames=("spec", "kind", "n_views"))
def _chunk_normal(params, total, shared, chunk, spec, kind, n_views):
    flat, unravel = ravel_pytree(params)

    def residual(x):
        return _chunk_residuals(unravel(x), shared, chunk, spec, n_views).reshape(-1)

    r = residual(flat)
    jac = jax.jacfwd(residual)(flat)                            # [M, p]
    w = jnp.repeat(chunk.weight.reshape(-1), 3)
    r = jnp.where(w > 0, r, 0.0)
    irls = w * irls_weight(kind, r)
    loss = jnp.sum(w * rho(kind, r))
    return (total[0] + loss, total[1] + jac.T @ (irls[:, None] * jac),
            total[2] + jac.T @ (irls * r))


@jax.jit
def _chunk_parts(material, every, shared, chunk):
    """The chunk's unclamped parts (pixel_parts) of `material`, 0 in the padding: one
    chunk of fitting.solve.linear.view_parts."""
    def one(samples, light):
        return pixel_parts(material, light, shared.global_ambient, samples, shared.settings)

    parts = jax.vmap(one)(chunk.samples, _view_lights(chunk, every))
    kept = chunk.weight[..., None] > 0
    return jax.tree.map(lambda a: jnp.where(kept, a, 0), parts)


@partial(jax.jit, static_argnames=("spec", "n_views"))
def _chunk_rows(values, shared, chunk, spec, n_views):
    """(residuals [C, N, 3], d residuals / d values [C, N, 3, p]) of the chunk's views, 0
    in the padding: one chunk of fitting.solve.gauss_newton.normal_system's r and rows."""
    def flat(v):
        r = _value_residuals(v, shared, chunk, spec, n_views)
        return r.reshape(-1), r

    columns, r = jax.jacfwd(flat, has_aux=True)(values)
    jac = jnp.concatenate([c.reshape(r.size, -1) for c in jax.tree.leaves(columns)], 1)
    kept = chunk.weight[..., None] > 0
    return jnp.where(kept, r, 0), jnp.where(kept[..., None], jac.reshape(*r.shape, -1), 0)


_UPDATES = {}


def _update(optimizer):
    """update(params, opt_state, loss, grads) -> (params, opt_state, loss): the
    optimizer's update (grads made NaN where the loss is not finite, as in
    fitting.solve.step), jitted once per optimizer."""
    if optimizer not in _UPDATES:
        def update(params, opt_state, loss, grads):
            grads = jax.tree.map(lambda g: jnp.where(jnp.isfinite(loss), g, jnp.nan), grads)
            updates, state = optimizer.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), state, loss
        _UPDATES[optimizer] = jax.jit(update)
    return _UPDATES[optimizer]


_LBFGS = {}


def _lbfgs_step(spec, kind, n_views, count, optimizer):
    key = (spec, kind, n_views, count, optimizer)
    if key not in _LBFGS:
        def loss_fn(params, data):
            shared, chunks = data
            return sum(_chunk_sum(params, shared, chunk, spec, kind, n_views)
                       for chunk in chunks) / count
        _LBFGS[key] = make_step(loss_fn, optimizer)
    return _LBFGS[key]
