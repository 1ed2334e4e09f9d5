"""The probed stencil of a texture solve's normal matrix, for one map or several.

A texture solve (fitting.solve.texture) has the normal matrix A'MA over the texels of its
maps (kd, ks, or both, one [R, R, 3] grid each). Probing it with PROBE_STRIDE^2 probes per
map (each holds the texels of one colour, PROBE_STRIDE apart) gives, at every texel of
every map, its coupling to the probed texel nearest to it: so each texel's couplings to
its 8 neighbours in its own map, and, where two maps have one resolution, to the texel at
the same place and its 8 neighbours in the other map (the same pixels read both). That
block stencil S is A'MA itself where every pixel reads texels at most one apart (a
bilinear cell), and close elsewhere; its (0, 0) entries are the diagonal, exact wherever
no pixel reads two texels PROBE_STRIDE apart. Couplings between maps of different
resolutions are left out of S (the renders' iterations account for them).

`block_stencil(data, res, dtype)` -> {(out, in, (dr, dc)): [R, R, 3]}, `stencil_operator`
applies it to a tuple of maps, and `block_preconditioner` inverts its per-texel blocks
(one map: the diagonal, Jacobi; two maps of one resolution: the 2 x 2 block of the kd and
ks texel at one place and channel, whose strong coupling Jacobi would leave to the
iterations).
"""

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["PROBE_STRIDE", "block_preconditioner", "block_stencil", "stencil_operator"]

PROBE_STRIDE = 4


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


def shifted(t, offset):
    """[i] = t[i + offset] over the wrapped texel grid (the grid's axes first)."""
    return jnp.roll(t, (-offset[0], -offset[1]), (0, 1))


def _probed(data, res, dtype, stride, field):
    """The responses of every map to the probes of map `field`: a tuple over the maps of
    [P, R_out, R_out, 3], and the probes' `which`."""
    probes, which = _probes(res[field], dtype, min(stride, res[field]))
    zeros = [jnp.zeros((r, r, 3), dtype) for r in res]

    def respond(probe):
        return data(tuple(probe if f == field else z for f, z in enumerate(zeros)))
    # one probe at a time (a loop compiled once): the memory of one product
    return jax.lax.map(respond, probes), which


def block_stencil(data, res, dtype, stride=PROBE_STRIDE):
    """{(out, in, (dr, dc)): [R_out, R_out, 3]}: each texel of map `out`'s coupling in the
    data operator to texel (dr, dc) away (wrapped) in map `in` (module docstring), made
    symmetric. data: a tuple of maps [R_f, R_f, 3] -> the tuple A'MA t; res: (R_f, ...)."""
    stencil = {}
    for field in range(len(res)):
        responses, which = _probed(data, res, dtype, stride, field)
        rows, cols = np.indices((res[field],) * 2)
        for out, response in enumerate(responses):
            if res[out] != res[field]:
                continue
            # texel i's coupling to i + offset: what the probe holding i + offset gives at
            # i, one gather per offset (sums of responses times shifted probe masks took
            # seconds at 256^2 in XLA's fused loops)
            for dr in _offsets(res[field]):
                for dc in _offsets(res[field]):
                    stencil[(out, field, (dr, dc))] = response[
                        np.roll(which, (-dr, -dc), (0, 1)), rows, cols]
    return _symmetric(stencil, res)


def _symmetric(stencil, res):
    """The stencil made symmetric, each coupling the mean of its two probed values (they
    agree where the stencil is exact), so that conjugate gradients may run on it."""
    def opposite(out, field, offset):
        size = res[out]
        return next(o for (a, b, o) in stencil if (a, b) == (field, out)
                    and (o[0] + offset[0]) % size == (o[1] + offset[1]) % size == 0)
    return {(out, field, offset): 0.5 * (values + shifted(
        stencil[(field, out, opposite(out, field, offset))], offset))
        for (out, field, offset), values in stencil.items()}


def stencil_operator(stencil, count):
    """tuple of `count` maps t -> the tuple S t, S the block stencil."""
    def apply(maps):
        out = [jnp.zeros_like(t) for t in maps]
        for (row, field, offset), values in stencil.items():
            out[row] = out[row] + values * shifted(maps[field], offset)
        return tuple(out)
    return apply


def block_preconditioner(stencil, extra, tiny):
    """tuple of maps r -> the per-texel block inverse of (S + diag(extra)) applied to r
    (module docstring); extra: a tuple of [R, R, 3] or [R, R, 1] added to the diagonal
    (the prior's and the ridge's); tiny: the floor of a diagonal entry."""
    diagonal = [jnp.maximum(stencil[(f, f, (0, 0))] + e, tiny) for f, e in enumerate(extra)]
    pair = (0, 1, (0, 0)) in stencil and len(diagonal) == 2
    if not pair:
        return lambda maps: tuple(r / d for r, d in zip(maps, diagonal, strict=True))
    a, d = diagonal
    c = stencil[(0, 1, (0, 0))]
    det = a * d - c * c
    # a block that is (nearly) singular in float falls back to its diagonal
    block = det > 1e-6 * a * d

    def apply(maps):
        r0, r1 = maps
        z0 = jnp.where(block, (d * r0 - c * r1) / jnp.where(block, det, 1.0), r0 / a)
        z1 = jnp.where(block, (a * r1 - c * r0) / jnp.where(block, det, 1.0), r1 / d)
        return z0, z1
    return apply
