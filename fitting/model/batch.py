"""A fit's views as one batch: one view's shading, mapped over all of them.

The fitting cache (fitting.model.cache) keeps each view's samples at their own size. A program
that shaded them one by one would hold one copy of the shading per view (six target
images: six copies, six times the compilation). `view_map(fn, data, lights, rows)`
instead groups the views by light layout (`layout_groups`: the kinds and counts of their
lights and static settings such as shadow flags), pads each group's arrays to its
largest view's (padded rows repeat the view's last real row, so nothing in the padding
is NaN; a view without pixels borrows another view's first row), stacks them along a
leading views axis, and runs `fn` once per group under `jax.vmap`: a program holds one
copy of the shading per light layout, and no view shades a light it does not have.
Its per-pixel results come back in view order as [V, N, ...] with a weight [V, N]: 1 at
a kept pixel, 0 in the padding.

Works inside a trace (the views and lights may be tracers; their shapes and static
settings decide the grouping and the padding), so a jitted program can take the FitData
as it is; the fit's programs take it `batched`, stacked once on the host. Views whose
samples differ in structure are shaded one by one and their results padded alike: the
same answer, with one copy of the shading per view. `common_lights` pads lights of
different layouts to one with lights of colour 0 (they add exactly 0): the result
panels (fitting.report.result) and the sharded fits (fitting.solve.distribute) stack views that way.
"""

import dataclasses
import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np


def _module(*arrays):
    """numpy when every array is a NumPy array (a host-side layout stays on the host),
    else jax.numpy (device arrays or tracers)."""
    return np if all(isinstance(a, np.ndarray) for a in arrays) else jnp


def _as_arrays(tree):
    return jax.tree.map(lambda x: x if isinstance(x, (jax.Array, np.ndarray))
                        else np.asarray(x), tree)


def light_layout(lights):
    return jax.tree.structure(lights), tuple(np.shape(x) for x in jax.tree.leaves(lights))


def _dark(light):
    """A copy of a light group's first light that emits nothing (colours 0)."""
    first = jax.tree.map(lambda x: x[:1], light)
    colours = {f: _module(getattr(first, f)).zeros_like(getattr(first, f))
               for f in ("ambient", "diffuse", "specular") if hasattr(first, f)}
    if hasattr(first, "shadows"):
        colours["shadows"] = (False,)
    return dataclasses.replace(first, **colours)


def _flags(group):
    n = np.shape(jax.tree.leaves(group)[0])[0]
    return group.shadows if isinstance(group.shadows, tuple) else (bool(group.shadows),) * n


def _concat(groups):
    """Light groups of one kind, concatenated along the light axis (shadow flags as one
    tuple per group, so that equal groups have equal static structure)."""
    def join(*x):
        return _module(*x).concatenate(x)

    if not hasattr(groups[0], "shadows"):
        return jax.tree.map(join, *groups)
    flags = sum((_flags(g) for g in groups), ())
    plain = [dataclasses.replace(g, shadows=False) for g in groups]
    return dataclasses.replace(jax.tree.map(join, *plain), shadows=flags)


def common_lights(lights, index=None):
    """The views' LightGroups given one structure, for stacking: every kind that some view
    has, with the largest count, padded with lights of colour 0 (copies of a real light
    of that kind, so that their geometry is finite). A light of colour 0 adds exactly 0
    to a colour and to its gradient. Raises ValueError when the padded groups still
    differ (static settings such as shadow flags or area-light sample counts), naming
    the view by its number in `index` (default: its position in `lights`)."""
    index = range(len(lights)) if index is None else index
    lights = [_as_arrays(g) for g in lights]
    kinds = [f.name for f in dataclasses.fields(lights[0])]
    padded = [{} for _ in lights]
    for kind in kinds:
        groups = [getattr(g, kind) for g in lights]
        present = [g for g in groups if g is not None]
        if not present:
            continue
        most = max(np.shape(jax.tree.leaves(g)[0])[0] for g in present)
        dark = _dark(present[0])
        for entry, group in zip(padded, groups, strict=True):
            have = 0 if group is None else np.shape(jax.tree.leaves(group)[0])[0]
            parts = ([] if group is None else [group]) + [dark] * (most - have)
            entry[kind] = _concat(parts)
    out = [dataclasses.replace(g, **entry) for g, entry in zip(lights, padded, strict=True)]
    for i, g in enumerate(out):
        if light_layout(g) != light_layout(out[0]):
            raise ValueError(f"views[{index[i]}].lights: differ from views[{index[0]}]'s in "
                             "a static setting "
                             "(shadow flags or area-light samples); sharded or chunked fits "
                             "stack the views' lights (fit with devices=1 and chunk=None)")
    return out


def aligned_empty(shape, dtype, alignment=64):
    """np.empty(shape, dtype) whose data start on a multiple of `alignment` bytes: XLA's
    CPU client then takes the array without a copy (jax.dlpack.from_dlpack; a sharded
    fit's chunks, fitting.solve.distribute)."""
    dtype = np.dtype(dtype)
    size = math.prod(shape) * dtype.itemsize
    raw = np.empty(size + alignment, np.uint8)
    start = -raw.ctypes.data % alignment
    return raw[start:start + size].view(dtype).reshape(shape)


def _pad_rows(a, rows, spare):
    """[R, ...] -> [rows, ...]: a's rows, then its last row repeated (`spare`, one row,
    when R == 0); NumPy for NumPy arrays, else jax.numpy."""
    have = a.shape[0]
    if have == rows:
        return a
    xp = _module(a)
    fill = a[-1:] if have else spare
    return xp.concatenate([a, xp.broadcast_to(fill, (rows - have, *a.shape[1:]))])


def stack_views(views, lights, rows=None, spare=None):
    """(ViewSamples with a leading [V] axis, LightGroups with a leading [V] axis) of the
    views, padded (module docstring); None when they cannot be stacked. NumPy arrays
    stay NumPy arrays (built on the host), others become jax arrays. rows: the row count
    of each leaf (in jax.tree.leaves order) to pad to, at least the views' largest (the
    sharded fits pad every chunk alike, fitting.solve.distribute); default the largest. spare:
    a ViewSamples whose first rows pad a leaf that none of `views` has rows in (default:
    those views' own)."""
    try:
        lights = stack_lights(lights)
    except ValueError:
        return None
    if len({jax.tree.structure(v) for v in views}) > 1:
        return None
    columns = list(zip(*(jax.tree.leaves(v) for v in views), strict=True))
    if any(len({a.shape[1:] for a in column}) > 1 for column in columns):
        return None
    rows = [max(a.shape[0] for a in column) for column in columns] if rows is None else rows
    spares = [None] * len(columns) if spare is None else [a[:1] for a in
                                                           jax.tree.leaves(spare)]
    stacked = []
    for column, count, extra in zip(columns, rows, spares, strict=True):
        first = next((a[:1] for a in column if a.shape[0]), extra)
        if _module(*column) is np:  # in place: a chunk of a sharded fit is not copied twice
            out = aligned_empty((len(column), count, *column[0].shape[1:]),
                                np.result_type(*column))
            for i, a in enumerate(column):
                out[i, :a.shape[0]] = a
                if a.shape[0] < count:
                    out[i, a.shape[0]:] = a[-1] if a.shape[0] else first
            stacked.append(out)
        else:
            stacked.append(jnp.stack([_pad_rows(a, count, first) for a in column]))
    return jax.tree.unflatten(jax.tree.structure(views[0]), stacked), lights


def stack_lights(lights):
    """The views' LightGroups (one each) padded to one layout (common_lights) and
    stacked: LightGroups with a leading [V] axis. Raises ValueError as common_lights."""
    return jax.tree.map(lambda *x: _module(*x).stack(x), *common_lights(lights))


def layout_groups(lights) -> tuple:
    """The view indices grouped by light layout (kinds, counts and static settings such
    as shadow flags), in order of first appearance: tuple of tuples."""
    groups = {}
    for i, g in enumerate(lights):
        groups.setdefault(light_layout(_as_arrays(g)), []).append(i)
    return tuple(tuple(index) for index in groups.values())


@partial(jax.tree_util.register_dataclass, data_fields=["samples", "lights", "weight"],
         meta_fields=["index", "counts"])
@dataclasses.dataclass(frozen=True)
class ViewBatch:
    """A FitData's views stacked once, on the host (`batched`), one stack per light
    layout: samples: tuple of ViewSamples with a leading [V_g] axis (padded to the group's
    largest counts); lights: tuple of LightGroups with a leading [V_g] axis; weight:
    [V, N] 1 at the kept pixels, in view order; index: the views of each group (static);
    counts: kept pixels per view (static)."""

    samples: tuple
    lights: tuple
    weight: jax.Array
    index: tuple
    counts: tuple

    def __len__(self):
        return len(self.counts)


def view_counts(views) -> tuple:
    """Kept pixels per view of a tuple of ViewSamples or a ViewBatch."""
    if isinstance(views, ViewBatch):
        return views.counts
    return tuple(int(v.pixels.shape[0]) for v in views)


def pixel_weight(counts, dtype):
    """[V, N] 1 at each view's kept pixels, 0 in the padding (N the largest count)."""
    counts = np.asarray(counts)
    n = max(int(counts.max(initial=0)), 1)
    return (np.arange(n)[None, :] < counts[:, None]).astype(dtype)


def _grouped(views, lights, index):
    """[(samples, lights)] stacked per group of `index`, or None when one does not stack."""
    stacks = [stack_views([views[i] for i in group], [lights[i] for i in group])
              for group in index]
    return None if any(s is None for s in stacks) else stacks


def batched(data):
    """`data` (a FitData) with its views stacked into a ViewBatch, built once on the host
    and kept on the device with `data` (a second copy of the cache's arrays; a replaced
    FitData builds its own); `data` itself when its views do not stack. The fit's
    programs take it: stacking inside them would add a padding and a concatenation per
    view and array to every one. Views held as NumPy arrays (the plain FitData of
    sharded views, fitting.solve.distribute) are stacked in host memory for each call and not
    kept, so that a chunked fit's device memory stays one chunk's."""
    if isinstance(data.views, ViewBatch):
        return data
    if "_batched" in data.__dict__:
        return data.__dict__["_batched"]
    host = lambda tree: jax.tree.map(np.asarray, tree)
    index = layout_groups(data.lights)
    stacks = _grouped([host(v) for v in data.views], [host(g) for g in data.lights], index)
    if stacks is None:
        return data
    counts = view_counts(data.views)
    weight = pixel_weight(counts, np.asarray(data.views[0].target).dtype)
    found = dataclasses.replace(data, views=ViewBatch(
        tuple(s for s, _ in stacks), tuple(g for _, g in stacks), weight, index, counts))
    if all(isinstance(x, np.ndarray) for x in jax.tree.leaves(data.views[0])):
        return found
    found = jax.device_put(found)
    object.__setattr__(data, "_batched", found)
    return found


def view_map(fn, data, lights=None, rows=None):
    """fn(samples, lights, row) -> a pytree of per-pixel arrays [N_v, ...], for every view
    of `data` (a FitData, its views as given or `batched`): samples a ViewSamples, lights
    its LightGroups (of `lights`, one per view, default the data's), row its row of `rows`
    (a pytree of [V, ...] arrays, or None). Returns (the results with leaves [V, N, ...],
    0 in the padding; weight [V, N]): one vmapped `fn` per light layout when the views
    stack, else one call per view (module docstring)."""
    views = data.views
    if isinstance(views, ViewBatch):
        index, weight = views.index, views.weight
        stacks = list(zip(views.samples, views.lights if lights is None else [
            stack_lights([lights[i] for i in group]) for group in index], strict=True))
    else:
        lights = data.lights if lights is None else lights
        index = layout_groups(lights)
        weight = jnp.asarray(pixel_weight(view_counts(views), views[0].target.dtype))
        stacks = _grouped(views, lights, index)
    n = weight.shape[1]
    if stacks is None:
        out = [fn(view, light, jax.tree.map(lambda r, i=i: r[i], rows))
               for i, (view, light) in enumerate(zip(views, lights, strict=True))]
        return jax.tree.map(lambda *x: jnp.stack([_pad_to(a, n, 0) for a in x]), *out), weight
    outs = [jax.vmap(fn)(samples, light, jax.tree.map(lambda r, g=group: r[np.asarray(g)],
                                                       rows))
            for (samples, light), group in zip(stacks, index, strict=True)]
    order = np.argsort(np.concatenate(index))
    out = jax.tree.map(lambda *x: _in_order(jnp.concatenate([_pad_to(a, n, 1) for a in x]),
                                            order), *outs)
    return jax.tree.map(lambda a: jnp.where(_expand(weight, a) > 0, a, 0), out), weight


def _pad_to(a, n, axis):
    """a padded with zeros to n along `axis`."""
    widths = [(0, 0)] * a.ndim
    widths[axis] = (0, n - a.shape[axis])
    return jnp.pad(a, widths)


def _in_order(a, order):
    return a if np.array_equal(order, np.arange(len(order))) else a[order]


def _expand(weight, a):
    return weight.reshape(weight.shape + (1,) * (a.ndim - 2))


def unpadded(stacked, views):
    """Per view, its rows of a [V, N, ...] array: tuple of [N_v, ...] (views: a tuple of
    ViewSamples or a ViewBatch)."""
    return tuple(stacked[i, :n] for i, n in enumerate(view_counts(views)))
