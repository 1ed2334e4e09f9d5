"""diffshade.shading.compact.on_active: values and gradients at the active entries equal a plain
evaluation, whether the active entries fit the capacity (compacted) or not (everywhere);
take_rows and put_rows (each the other's transpose; host: the compiled kernel) and sum_rows
(on_active's group) against NumPy loops; interpolate_rows_at (host: the compiled kernel
reading the fragments at the rows) against a loop and, for its derivatives, central
differences."""

import jax
import jax.extend.core as jex_core
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffshade.shading.compact import (
    active_indices,
    interpolate_rows_at,
    on_active,
    put_rows,
    sum_rows,
    take_rows,
)

pytestmark = pytest.mark.usefixtures("x64")


def _fn(x, y, flag):
    """A nonlinear per-entry function with a pytree output: x [N, 3], y [N], flag [N]."""
    a = jnp.sin(x) * y[:, None] + jnp.where(flag[:, None], x ** 2, -x)
    return {"a": a, "b": jnp.exp(-y)[:, None] * jnp.sum(x, -1, keepdims=True)}


def _inputs(active_fraction, seed=0):
    rng = np.random.default_rng(seed)
    x = jnp.asarray(rng.normal(size=(6, 5, 4, 3)))
    y = jnp.asarray(rng.normal(size=(6, 5, 4)))
    flag = jnp.asarray(rng.random((6, 5, 4)) < 0.5)
    active = jnp.asarray(rng.random((6, 5, 4)) < active_fraction)
    return x, y, flag, active


def _plain(x, y, flag):
    out = _fn(x.reshape(-1, 3), y.reshape(-1), flag.reshape(-1))
    return jax.tree.map(lambda o: o.reshape(x.shape[:-1] + o.shape[1:]), out)


@pytest.mark.parametrize("host", [True, False])
@pytest.mark.parametrize("capacity", [40, 10])
def test_active_indices_equal_numpy(capacity, host):
    active = _inputs(0.3)[-1].reshape(-1)
    want = np.flatnonzero(np.asarray(active))
    assert 10 < want.size < 40
    idx, count = jax.jit(lambda m: active_indices(m, capacity, host))(active)
    assert int(count) == want.size
    n = min(capacity, want.size)
    np.testing.assert_array_equal(np.asarray(idx)[:n], want[:n])
    np.testing.assert_array_equal(np.asarray(idx)[n:], active.size)


@pytest.mark.parametrize("size", [1003, 4096, 7])
@pytest.mark.parametrize("capacity", [0, 1, 7, 8, 9, 300, 5000])
def test_active_indices_of_long_masks_equal_numpy(capacity, size):
    """The kernel takes eight entries at a time while eight more fit, then one at a time:
    masks of lengths that are and are not multiples of 8, runs of True and False, and
    capacities below, at and above the count."""
    rng = np.random.default_rng(size + capacity)
    mask = np.repeat(rng.random(size // 5 + 1) < 0.5, 5)[:size] ^ (rng.random(size) < 0.1)
    want = np.flatnonzero(mask)
    idx, count = active_indices(jnp.asarray(mask), capacity, host=True)
    assert int(count) == want.size
    n = min(capacity, want.size)
    np.testing.assert_array_equal(np.asarray(idx)[:n], want[:n])
    np.testing.assert_array_equal(np.asarray(idx)[n:], size)


@pytest.mark.parametrize("host", [True, False])
@pytest.mark.parametrize("capacity", [40, 60, 120, 200, (20, 40), (40, 60), (50, 100)])
def test_values_and_gradients_at_active_entries(capacity, host):
    x, y, flag, active = _inputs(0.4)
    # capacity 40 and tiers (20, 40) take the fallback branch; the others fit (tiers: the
    # second of (40, 60), the first of (50, 100))
    assert 40 < int(active.sum()) <= 50
    got = jax.jit(lambda x, y: on_active(_fn, active, capacity, x, y, flag, host=host))(x, y)
    want = _plain(x, y, flag)
    for key in ("a", "b"):
        np.testing.assert_allclose(np.asarray(got[key])[np.asarray(active)],
                                   np.asarray(want[key])[np.asarray(active)], rtol=1e-14)
    weight = jnp.asarray(np.random.default_rng(1).normal(size=(6, 5, 4, 3)))

    def loss(x, y, compact):
        out = (on_active(_fn, active, capacity, x, y, flag, host=host) if compact
               else _plain(x, y, flag))
        mask = active[..., None]
        return jnp.sum(jnp.where(mask, out["a"] * weight + out["b"], 0.0))
    g_got = jax.jit(jax.grad(lambda x, y: loss(x, y, True), argnums=(0, 1)))(x, y)
    g_want = jax.grad(lambda x, y: loss(x, y, False), argnums=(0, 1))(x, y)
    for a, b in zip(g_got, g_want, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)


def _add_shapes(jaxpr):
    """Output shapes of the add_any equations of a jaxpr, sub-jaxprs included."""
    shapes = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "add_any":
            shapes.append(eqn.outvars[0].aval.shape)
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                if isinstance(sub, (jex_core.ClosedJaxpr, jex_core.Jaxpr)):
                    shapes += _add_shapes(getattr(sub, "jaxpr", sub))
    return shapes


def test_a_value_fn_closes_over_reaches_the_tiers_once():
    """An array fn closes over (a texture, in the renders) is one operand of the tiers,
    not one per tier: its gradient is one array, not one per tier summed; and it is
    right."""
    x, y, flag, active = _inputs(0.4)
    weight = jnp.asarray(np.random.default_rng(2).normal(size=(7, 3)))

    def loss(w, compact):
        fn = lambda x: jnp.sin(x) * jnp.sum(w, 0)  # linear in w: its own VJP adds nothing
        out = on_active(fn, active, (40, 60), x) if compact else fn(x)
        return jnp.sum(jnp.where(active[..., None], out, 0.0))
    grad = jax.grad(lambda w: loss(w, True))
    assert weight.shape not in _add_shapes(jax.make_jaxpr(grad)(weight).jaxpr)
    np.testing.assert_allclose(jax.jit(grad)(weight), jax.grad(lambda w: loss(w, False))(
        weight), rtol=1e-12)


def test_inactive_entries_are_zero_when_compacted():
    x, y, flag, active = _inputs(0.2)
    got = on_active(_fn, active, 100, x, y, flag)
    assert np.all(np.asarray(got["a"])[~np.asarray(active)] == 0.0)


def test_under_vmap():
    x, y, flag, active = _inputs(0.3)
    batched = jax.vmap(lambda s: on_active(_fn, active, 60, x * s, y, flag)["a"])(
        jnp.array([1.0, 2.0]))
    np.testing.assert_allclose(np.asarray(batched[1])[np.asarray(active)],
                               np.asarray(_plain(2.0 * x, y, flag)["a"])[np.asarray(active)],
                               rtol=1e-14)


@pytest.mark.parametrize("capacity", [(20, 60), (60, 100), (10, 20)])
def test_tiers_under_vmap_with_an_axis_name(capacity):
    """A batch of two members, the first with fewer active entries: the tier is chosen
    once for both (the smallest that holds each), and the values are right in each."""
    x, y, flag, active = _inputs(0.3)
    fewer = active & jnp.asarray(np.arange(active.size).reshape(active.shape) % 2 == 0)
    masks = jnp.stack([fewer, active])
    batched = jax.jit(jax.vmap(
        lambda m, s: on_active(_fn, m, capacity, x * s, y, flag, axis_name="views")["a"],
        axis_name="views"))(masks, jnp.array([1.0, 2.0]))
    for member, (mask, scale) in enumerate(zip(masks, (1.0, 2.0), strict=True)):
        mask = np.asarray(mask)
        np.testing.assert_allclose(np.asarray(batched[member])[mask],
                                   np.asarray(_plain(scale * x, y, flag)["a"])[mask],
                                   rtol=1e-14)


def _rows_case(dtype, tail, seed=0):
    """x [12, *tail], idx [9]: distinct indices in range in random order, then padding
    out of range at both ends (clipped), and a cotangent of the gathered rows."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(12,) + tail).astype(dtype)
    idx = np.concatenate([rng.permutation(12)[:6], [12, 15, -1]]).astype(np.int32)
    ct = rng.normal(size=(9,) + tail).astype(dtype)
    return x, idx, ct


def _put_loop(ct, idx, count, clip=True):
    """The transpose of a gather (clip: clipped indices; else out of range reads 0), one
    row at a time."""
    out = np.zeros((count,) + ct.shape[1:], ct.dtype)
    for i, j in enumerate(idx):
        if clip or 0 <= j < count:
            out[min(max(j, 0), count - 1)] += ct[i]
    return out


def _take_loop(x, idx, clip=True):
    return np.stack([x[min(max(j, 0), len(x) - 1)] if clip or 0 <= j < len(x)
                     else np.zeros_like(x[0]) for j in idx])


@pytest.mark.parametrize("host", [True, False])
@pytest.mark.parametrize("clip", [True, False])
@pytest.mark.parametrize("tail", [(3,), (2,), (1, 3), ()])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_take_rows_and_put_rows_equal_loops(dtype, tail, clip, host):
    x, idx, ct = _rows_case(dtype, tail)
    out, pull = jax.vjp(lambda x: take_rows(x, idx, host, clip), x)
    np.testing.assert_array_equal(np.asarray(out), _take_loop(x, idx, clip))
    tol = 1e-6 if dtype == np.float32 else 1e-15
    np.testing.assert_allclose(np.asarray(jax.jit(pull)(ct)[0]), _put_loop(ct, idx, 12, clip),
                               rtol=tol, atol=tol)
    # put_rows itself, and its transpose: <put(ct), t> = <ct, take(t)>
    t = np.random.default_rng(2).normal(size=x.shape).astype(dtype)
    put, pull_back = jax.vjp(lambda c: put_rows(c, idx, 12, host, clip), ct)
    np.testing.assert_allclose(np.asarray(put), _put_loop(ct, idx, 12, clip), rtol=tol,
                               atol=tol)
    np.testing.assert_array_equal(np.asarray(pull_back(t)[0]), _take_loop(t, idx, clip))
    _, tangent = jax.jvp(lambda x: take_rows(x, idx, host, clip), (x,), (t,))
    np.testing.assert_array_equal(np.asarray(tangent), _take_loop(t, idx, clip))


def _sum_loop(rows, idx, count, group):
    """sum_rows one row at a time: row i added to out[idx[i] // group] where in range."""
    out = np.zeros((count,) + rows.shape[1:], rows.dtype)
    for i, j in enumerate(idx):
        if 0 <= j < count * group:
            out[j // group] += rows[i]
    return out


@pytest.mark.parametrize("host", [True, False])
@pytest.mark.parametrize("tail", [(3,), (2,), ()])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sum_rows_equals_a_loop(dtype, tail, host):
    """Ascending indices with negative ones first, runs of one group (up to its 4 rows),
    empty groups (the first and last among them) and padding past the end; the transpose
    is the gather by idx // group (0 for the rows out of range), the tangent the same sum."""
    rng = np.random.default_rng(5)
    idx = np.array([-4, -1, 4, 5, 7, 8, 12, 13, 14, 15, 17, 28, 28 + 3, 32, 40],
                   np.int32)  # groups of 4, count 8: 0 and 2 empty, 3 full; 32, 40 padding
    rows = rng.normal(size=(idx.size,) + tail).astype(dtype)
    got, pull = jax.vjp(lambda r: sum_rows(r, idx, 8, 4, host), rows)
    tol = 1e-6 if dtype == np.float32 else 1e-15
    np.testing.assert_allclose(np.asarray(got), _sum_loop(rows, idx, 8, 4), rtol=tol,
                               atol=tol)
    ct = rng.normal(size=(8,) + tail).astype(dtype)
    want = np.stack([ct[j // 4] if 0 <= j < 32 else np.zeros_like(ct[0]) for j in idx])
    np.testing.assert_array_equal(np.asarray(jax.jit(pull)(ct)[0]), want)
    _, tangent = jax.jvp(lambda r: sum_rows(r, idx, 8, 4, host), (rows,), (2.0 * rows,))
    np.testing.assert_allclose(np.asarray(tangent), 2.0 * _sum_loop(rows, idx, 8, 4),
                               rtol=tol, atol=tol)


@pytest.mark.parametrize("group", [8, 3, 7, 1])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sum_rows_kernel_adds_in_index_order_bit_for_bit(dtype, group):
    """The compiled kernel (active_kernel.sum_rows) against the loop, exactly (its
    docstring: the sums in index order, bit for bit): groups of `group` with 0 to `group`
    rows each in random runs, -0.0 and large and tiny values (so the order of the
    additions shows), negative indices first and padding past the end dropped."""
    from diffshade.host import active_kernel

    rng = np.random.default_rng(11)
    count = 700
    per = rng.integers(0, group + 1, count)
    idx = np.concatenate([np.array([-9, -1])] + [
        p * group + np.sort(rng.choice(group, n, replace=False)) for p, n in enumerate(per)]
        + [np.full(37, count * group)]).astype(np.int32)
    rows = (rng.normal(size=(idx.size, 3)) * 10.0 ** rng.integers(-8, 9, (idx.size, 3)))
    rows[rng.random(rows.shape) < 0.05] = -0.0
    rows = rows.astype(dtype)
    got = active_kernel.sum_rows(idx, rows, count, group)
    assert got.tobytes() == _sum_loop(rows, idx, count, group).tobytes()


def test_sum_rows_under_vmap():
    """The batch rides along as an axis of the rows (one set of indices), or each member
    has its own indices (one call of the kernel on the members' lists joined), negative
    ones and padding dropped."""
    rng = np.random.default_rng(6)
    idx = np.array([0, 1, 5, 6, 7, 11, 12], np.int32)
    rows = rng.normal(size=(2, 7, 3))
    got = jax.jit(jax.vmap(lambda r: sum_rows(r, idx, 3, 4, True)))(rows)
    for b in range(2):
        np.testing.assert_allclose(np.asarray(got[b]), _sum_loop(rows[b], idx, 3, 4),
                                   rtol=1e-15)
    idxs = np.stack([idx, np.array([-1, 3, 4, 8, 9, 11, 12], np.int32)])
    got = jax.jit(jax.vmap(lambda r, i: sum_rows(r, i, 3, 4, True)))(rows, idxs)
    for b in range(2):
        np.testing.assert_allclose(np.asarray(got[b]), _sum_loop(rows[b], idxs[b], 3, 4),
                                   rtol=1e-15)


@pytest.mark.parametrize("host", [True, False])
@pytest.mark.parametrize("capacity", [40, 60, 200, (20, 40), (40, 60), (50, 100)])
def test_grouped_values_and_gradients_equal_plain_sums(capacity, host):
    """on_active's group: fn's values (0 where inactive, as a weight of 0 makes them)
    summed over the last axis, compacted, by tiers or everywhere; and their gradients."""
    x, y, flag, active = _inputs(0.4)
    weight = jnp.where(active, jnp.asarray(np.random.default_rng(7).uniform(
        0.5, 1.0, active.shape)), 0.0)

    def weighted(x, y, flag, w):
        return _fn(x, y, flag)["a"] * w[:, None]

    def summed(x, y, compact):
        if compact:
            return on_active(weighted, active, capacity, x, y, flag, weight, host=host,
                             group=True)
        out = weighted(x.reshape(-1, 3), y.reshape(-1), flag.reshape(-1), weight.reshape(-1))
        return out.reshape(x.shape).sum(-2)
    got = jax.jit(lambda x, y: summed(x, y, True))(x, y)
    assert got.shape == (6, 5, 3)
    np.testing.assert_allclose(np.asarray(got), np.asarray(summed(x, y, False)), rtol=1e-13,
                               atol=1e-15)
    ct = jnp.asarray(np.random.default_rng(8).normal(size=(6, 5, 3)))
    loss = lambda x, y, compact: jnp.sum(summed(x, y, compact) * ct)
    g_got = jax.jit(jax.grad(lambda x, y: loss(x, y, True), argnums=(0, 1)))(x, y)
    g_want = jax.grad(lambda x, y: loss(x, y, False), argnums=(0, 1))(x, y)
    for a, b in zip(g_got, g_want, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("batched_idx", [False, True])
def test_take_rows_under_vmap(batched_idx):
    x, idx, ct = _rows_case(np.float64, (3,))
    xs = np.stack([x, 2.0 * x + 1.0])
    idxs = np.stack([idx, idx[::-1]]) if batched_idx else idx
    cts = np.stack([ct, -ct])

    def grad(x, idx, ct):
        return jax.vjp(lambda x: take_rows(x, idx, True), x)[1](ct)[0]
    got = jax.jit(jax.vmap(grad, in_axes=(0, 0 if batched_idx else None, 0)))(xs, idxs, cts)
    for b in range(2):
        member = idxs[b] if batched_idx else idx
        np.testing.assert_allclose(np.asarray(got[b]), _put_loop(cts[b], member, 12),
                                   rtol=1e-15, atol=1e-15)
    jac = jax.jacfwd(lambda x: take_rows(x, idx, True))(x)
    np.testing.assert_array_equal(np.asarray(jac), np.asarray(jax.jacrev(
        lambda x: take_rows(x, idx, False))(x)))


def _interpolation_case(seed=3):
    """Fragments (face ids [N] with empty ones, barycentrics [N, 3]), rows [M] (distinct,
    and entries outside [0, N)), vertex attributes (a pytree of [V, C] leaves), faces [F, 3]."""
    rng = np.random.default_rng(seed)
    n, faces = 40, rng.integers(0, 9, (7, 3)).astype(np.int32)
    ids = rng.integers(-1, 7, n).astype(np.int32)
    bary = rng.uniform(0.1, 1.0, (n, 3))
    rows = np.concatenate([rng.permutation(n)[:25], [n, -1, n + 5]]).astype(np.int32)
    attrs = (jnp.asarray(rng.normal(size=(9, 3))), jnp.asarray(rng.normal(size=(9, 2))))
    return ids, jnp.asarray(bary), rows, attrs, faces


def _interpolation_loop(ids, bary, rows, attrs, faces):
    """interpolate_rows_at by a plain loop: [M, C] per leaf."""
    out = []
    for attr in (np.asarray(a) for a in attrs):
        values = np.zeros((rows.size, attr.shape[1]))
        for i, r in enumerate(rows):
            if 0 <= r < ids.size and ids[r] >= 0:
                values[i] = sum(np.asarray(bary)[r, j] * attr[faces[ids[r], j]] for j in range(3))
        out.append(values)
    return out


@pytest.mark.parametrize("host", [True, False])
def test_interpolate_rows_at_equals_a_loop(host):
    ids, bary, rows, attrs, faces = _interpolation_case()
    got = jax.jit(lambda b, a: interpolate_rows_at(a, faces, rows, ids, b, host))(bary, attrs)
    for g, want in zip(got, _interpolation_loop(ids, bary, rows, attrs, faces), strict=True):
        np.testing.assert_allclose(np.asarray(g), want, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("host", [True, False])
def test_interpolate_rows_at_gradients_equal_finite_differences(host):
    ids, bary, rows, attrs, faces = _interpolation_case()
    fn = lambda b, a: interpolate_rows_at(a, faces, rows, ids, b, host)
    check_grads(jax.jit(fn), (bary, attrs), order=1, modes=("fwd", "rev"), eps=1e-6)


@pytest.mark.parametrize("host", [True, False])
def test_interpolate_rows_at_under_vmap(host):
    ids, bary, rows, attrs, faces = _interpolation_case()
    batch = jnp.stack([bary, 2.0 * bary[::-1]])
    fn = lambda b, a: interpolate_rows_at(a, faces, rows, ids, b, host)
    got = jax.jit(jax.vmap(fn, (0, None)))(batch, attrs)
    for member in range(2):
        want = _interpolation_loop(ids, batch[member], rows, attrs, faces)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(np.asarray(g[member]), w, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("host", [True, False])
@pytest.mark.parametrize("capacity", [30, (20, 30), 10])
def test_positions_and_whole_arrays(capacity, host):
    """on_active handing fn its positions and whole arrays (as render's Phong shading
    uses it, through interpolate_rows_at): values and gradients at the active entries
    equal those of every entry, the last entry active (the padding's neighbour)."""
    ids, bary, _, attrs, faces = _interpolation_case()
    active = jnp.asarray(np.random.default_rng(5).random(ids.size) < 0.5).at[-1].set(True)
    assert 20 < int(active.sum()) <= 30
    weights = jnp.asarray(np.random.default_rng(6).normal(size=(ids.size, 5)))

    def compacted(b, a):
        fn = lambda rows, ids, b: jnp.concatenate(interpolate_rows_at(a, faces, rows, ids, b,
                                                                      host), -1)
        out = on_active(fn, active, capacity, positions=True, whole=(ids, b), host=host)
        return jnp.sum(jnp.where(active[:, None], out, 0.0) * weights)

    def plain(b, a):
        out = jnp.concatenate(_interpolation_loop_jax(ids, b, a, faces), -1)
        return jnp.sum(jnp.where(active[:, None], out, 0.0) * weights)
    got, want = (jax.jit(jax.value_and_grad(f, (0, 1)))(bary, attrs) for f in (compacted, plain))
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-13, atol=1e-14)


def _interpolation_loop_jax(ids, bary, attrs, faces):
    """Every fragment's interpolated attributes in jax.numpy (no kernel, no gather by
    rows), for derivatives to compare with."""
    corners = [jnp.asarray(a)[faces[np.maximum(ids, 0)]] for a in attrs]
    return [jnp.where((ids >= 0)[:, None], jnp.einsum("nj,njc->nc", bary, c), 0.0)
            for c in corners]
