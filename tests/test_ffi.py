"""The host kernels as XLA FFI targets (diffshade/host/ffi.py): under jit on the CPU, XLA calls
the compiled handlers with its own buffers. Each target against the kernel called directly
from NumPy (fragment_kernels, candidates, the reference search loop of compact's test:
np.flatnonzero), bit for bit, in float32 and float64, batched and not; and the lowered
programs name the targets (else the callback path would be tested twice)."""

import os
import re
import shutil
import subprocess
import tempfile
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade.host import active_kernel, candidates, hostcall, texture_kernels, xla_ffi
from diffshade.host import fragment_kernels as kernels
from diffshade.numerics import tiny
from diffshade.raster.fragments import fragment_geometry
from diffshade.raster.interpolation import interpolate_corners
from diffshade.shading import compact
from diffshade.shading.texturing import sample_texels

H, W, K, F = 6, 5, 3, 7


def _fragment_inputs(dtype, seed=0):
    rng = np.random.default_rng(seed)
    ids = rng.integers(-1, F, (H, W, K)).astype(np.int32)
    corner_w = rng.uniform(0.5, 2.0, (F, 3)).astype(dtype)
    corner_z = rng.uniform(-5.0, -1.0, (F, 3)).astype(dtype)
    coeffs = rng.normal(size=(F, 3, 3)).astype(dtype)
    scr = rng.uniform(0.0, W, (F, 3, 2)).astype(dtype)
    return ids, corner_w, corner_z, coeffs, scr


def _targets(fn, *args):
    """The diffshade FFI targets named in fn's lowered program."""
    return set(re.findall(r"custom_call @(diffshade_\w+)", jax.jit(fn).lower(*args).as_text()))


@pytest.mark.parametrize("x64", [False, True])
@pytest.mark.parametrize("soft", [False, True])
def test_geometry_targets_equal_the_kernels(x64, soft):
    with jax.enable_x64(x64):
        dtype = np.float64 if x64 else np.float32
        ids, *per_face = _fragment_inputs(dtype)
        op = lambda *a: fragment_geometry(ids, *a, host=True, width=W, height=H, soft=soft)
        cot = tuple(np.random.default_rng(1).normal(size=s.shape).astype(dtype)
                    for s in jax.eval_shape(op, *per_face))

        def fb(*a):
            out, vjp = jax.vjp(op, *a)
            return out, vjp(cot)
        width = "f64" if x64 else "f32"
        assert _targets(fb, *per_face) == {f"diffshade_geometry_forward_{width}",
                                            f"diffshade_geometry_backward_{width}"}
        (bary, depth, dist), grads = jax.jit(fb)(*per_face)
        args = (*per_face, W, H, soft, tiny(dtype), 2)
        *want, edge = kernels.geometry_forward(ids.reshape(-1, K), *args)
        for got, ref in zip((bary, depth, dist), want, strict=True):
            assert got.dtype == dtype
            np.testing.assert_array_equal(np.asarray(got).reshape(ref.shape), ref)
        want = kernels.geometry_backward(ids.reshape(-1, K), *args, edge,
                                         cot[0].reshape(-1, K, 3), cot[1].reshape(-1, K),
                                         cot[2].reshape(-1, K))
        for got, ref in zip(grads, want, strict=True):
            np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12 if x64 else 1e-5,
                                       atol=1e-12 if x64 else 1e-5)


@pytest.mark.parametrize("soft", [False, True])
def test_geometry_forward_saves_the_nearest_edge(soft):
    # soft: the index of the nearest edge (from corner i to corner i+1), measured here
    # with NumPy, plus OUTSIDE where the distance is negated; the backward reads it
    ids, corner_w, corner_z, coeffs, scr = _fragment_inputs(np.float64)
    flat = ids.reshape(-1, K)
    _, _, dist, edge = kernels.geometry_forward(flat, corner_w, corner_z, coeffs, scr, W, H,
                                                soft, tiny(np.float64), 2)
    valid = flat >= 0
    assert edge.dtype == np.int8
    assert np.all(edge[~valid] == 0)
    if not soft:
        assert np.all(edge == 0)
        return
    rows, cols = np.divmod(np.arange(H * W), W)
    p = np.stack([cols + 0.5, rows + 0.5], -1)[:, None, :]  # [P, 1, 2]
    corners = scr[np.maximum(flat, 0)]  # [P, K, 3, 2]
    d2 = []
    for i in range(3):
        a, b = corners[..., i, :], corners[..., (i + 1) % 3, :]
        e = b - a
        t = np.clip(np.sum((p - a) * e, -1) / np.sum(e * e, -1), 0.0, 1.0)
        d2.append(np.sum((p - a - t[..., None] * e) ** 2, -1))
    d2 = np.stack(d2, -1)
    # the saved edge is a nearest one: its distance is the least (up to rounding, which
    # decides ties such as a corner nearest, shared by two edges: the kernel fuses
    # multiplications and additions, NumPy does not)
    saved = np.take_along_axis(d2, (edge % kernels.OUTSIDE)[..., None], -1)[..., 0]
    np.testing.assert_allclose(saved[valid], d2.min(-1)[valid], rtol=1e-12)
    np.testing.assert_array_equal((edge >= kernels.OUTSIDE)[valid], np.signbit(dist)[valid])
    np.testing.assert_allclose(np.abs(dist)[valid], d2.min(-1)[valid], rtol=1e-12)


@pytest.mark.parametrize("x64", [False, True])
def test_interpolation_targets_equal_the_kernels(x64):
    with jax.enable_x64(x64):
        dtype = np.float64 if x64 else np.float32
        rng = np.random.default_rng(2)
        ids = rng.integers(-1, F, (H, W, K)).astype(np.int32)
        bary = rng.uniform(size=(H, W, K, 3)).astype(dtype)
        corners = rng.normal(size=(F, 3, 4)).astype(dtype)
        g_out = rng.normal(size=(H, W, K, 4)).astype(dtype)

        def fb(bary, corners):
            out, vjp = jax.vjp(lambda b, c: interpolate_corners(ids, b, c, host=True)[0],
                               bary, corners)
            return out, vjp(g_out)
        width = "f64" if x64 else "f32"
        assert _targets(fb, bary, corners) == {f"diffshade_interpolate_forward_{width}",
                                                f"diffshade_interpolate_backward_{width}"}
        out, (g_bary, g_corners) = jax.jit(fb)(bary, corners)
        flat = ids.reshape(-1, K), bary.reshape(-1, K, 3), corners
        np.testing.assert_array_equal(np.asarray(out).reshape(-1, K, 4),
                                      kernels.interpolate_forward(*flat, 2))
        want_bary, want_corners = kernels.interpolate_backward(*flat, g_out.reshape(-1, K, 4), 3)
        np.testing.assert_array_equal(np.asarray(g_bary).reshape(-1, K, 3), want_bary)
        np.testing.assert_allclose(np.asarray(g_corners), want_corners, rtol=1e-12 if x64
                                   else 1e-5, atol=1e-12 if x64 else 1e-5)


@pytest.mark.parametrize("chunks", [1, 2, 3])
def test_interpolate_backward_equals_a_loop_over_several_blocks(chunks):
    """interpolate_backward against a NumPy loop on more fragments than its parts' blocks
    (kernels._DEALT, dealt in turn): a ragged last block, empty slots (-1) in the middle
    and a padded end as the compacted active slots have, faces shared across blocks."""
    rng = np.random.default_rng(8)
    n, faces, c = 5 * kernels._DEALT + 37, 11, 4
    ids = rng.integers(0, faces, (n, 1)).astype(np.int32)
    ids[rng.random(n) < 0.2] = -1
    ids[-300:] = -1
    bary = rng.uniform(size=(n, 1, 3))
    corners, g_out = rng.normal(size=(faces, 3, c)), rng.normal(size=(n, 1, c))
    want_bary, want_corners = np.zeros((n, 1, 3)), np.zeros((faces, 3, c))
    for i in range(n):
        f = ids[i, 0]
        if f >= 0:
            want_bary[i, 0] = corners[f] @ g_out[i, 0]
            want_corners[f] += bary[i, 0][:, None] * g_out[i, 0][None, :]
    g_bary, g_corners = kernels.interpolate_backward(ids, bary, corners, g_out, chunks)
    np.testing.assert_allclose(g_bary, want_bary, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g_corners, want_corners, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("channels", [1, 6, kernels.ROW_LANES, kernels.ROW_LANES + 1])
def test_interpolate_forward_equals_a_loop(channels, dtype):
    """interpolate_forward against a NumPy loop, bit for bit (b0 c0 + b1 c1, then + b2 c2,
    each rounded to the dtype, as the kernel adds them): empty slots, channel counts up to
    one vector (masked lanes) and one more (the scalar loop), split in 3 parts."""
    rng = np.random.default_rng(4)
    npix, k, faces = 301, 5, 13
    ids = rng.integers(-1, faces, (npix, k)).astype(np.int32)
    bary = rng.uniform(size=(npix, k, 3)).astype(dtype)
    corners = rng.normal(size=(faces, 3, channels)).astype(dtype)
    want = np.zeros((npix, k, channels), dtype)
    for p in range(npix):
        for slot in range(k):
            f = ids[p, slot]
            if f >= 0:
                b, corner = bary[p, slot], corners[f]
                want[p, slot] = b[0] * corner[0] + b[1] * corner[1] + b[2] * corner[2]
    got = kernels.interpolate_forward(ids, bary, corners, 3)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("channels", [1, 5, 6, kernels.ROW_LANES, kernels.ROW_LANES + 1])
@pytest.mark.parametrize("chunks", [1, 2, 3])
def test_interpolate_at_equals_a_loop_over_several_blocks(chunks, channels, dtype):
    """interpolate_at against a NumPy loop on thousands of rows split into 1 to 3 parts:
    rows in any order, empty slots (-1), and the padding (N) at the end that the
    compacted active slots have; channel counts up to one vector (masked lanes) and one
    more (the scalar loop). Bit for bit: the loop adds b0 c0 + b1 c1, then b2 c2, each
    product and sum rounded to the dtype, as the kernel does."""
    rng = np.random.default_rng(9)
    n, m, faces, c = 4 * kernels._DEALT, 5 * kernels._DEALT + 37, 11, channels
    ids = rng.integers(-1, faces, n).astype(np.int32)
    bary = rng.uniform(size=(n, 3)).astype(dtype)
    corners = rng.normal(size=(faces, 3, c)).astype(dtype)
    rows = rng.integers(0, n, m).astype(np.int32)
    rows[-300:] = n
    want = np.zeros((m, c), dtype)
    for i, r in enumerate(rows):
        if r < n and ids[r] >= 0:
            b, corner = bary[r], corners[ids[r]]
            want[i] = b[0] * corner[0] + b[1] * corner[1] + b[2] * corner[2]
    got = kernels.interpolate_at(rows, ids, bary, corners, chunks)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("x64", [False, True])
@pytest.mark.parametrize("clamp", [0, 1])
def test_texture_targets_equal_the_kernels(x64, clamp):
    with jax.enable_x64(x64):
        dtype = np.float64 if x64 else np.float32
        rng = np.random.default_rng(5)
        n, height, width = 50, 4, 6
        ids = np.where(rng.uniform(size=n) < 0.2, -1, 0).astype(np.int32)
        uv = rng.uniform(-0.5, 1.5, (n, 2)).astype(dtype)
        texels = rng.uniform(size=(height * width, 3)).astype(dtype)
        g_out = rng.normal(size=(n, 3)).astype(dtype)
        op = lambda u, t: sample_texels(ids, u, t, host=True, height=height, width=width,
                                        clamp=clamp, uv_grad=1)[0]

        def fb(uv, texels):  # both gradients: the backward with uv_grad = 1
            out, vjp = jax.vjp(op, uv, texels)
            return out, vjp(g_out)

        def fb_texels(uv, texels):  # the texels' only: uv_grad = 0
            return jax.vjp(lambda t: op(uv, t), texels)[1](g_out)[0]
        width_name = "f64" if x64 else "f32"
        assert _targets(fb, uv, texels) == {f"diffshade_texture_forward_{width_name}",
                                             f"diffshade_texture_backward_{width_name}"}
        out, (g_uv, g_texels) = jax.jit(fb)(uv, texels)
        args = (height, width, bool(clamp))
        np.testing.assert_array_equal(np.asarray(out), texture_kernels.sample_forward(
            ids, uv, texels, *args, 2))
        for uv_grad, got in ((True, (g_uv, g_texels)), (False, (None, jax.jit(fb_texels)(
                uv, texels)))):
            want = texture_kernels.sample_backward(ids, uv, texels, g_out, *args, uv_grad, 3)
            for a, b in zip(got, want, strict=True):
                if a is not None:
                    np.testing.assert_allclose(np.asarray(a), b, rtol=1e-12 if x64 else 1e-5,
                                               atol=1e-12 if x64 else 1e-5)
            assert uv_grad or not np.any(want[0])


@pytest.mark.parametrize("x64", [False, True])
def test_put_rows_target_equals_the_kernel(x64):
    """compact.put_rows and the transpose of compact.take_rows (rows of 3 floats) are the
    put_rows target, dropping or clipping the indices out of range."""
    with jax.enable_x64(x64):
        dtype = np.float64 if x64 else np.float32
        rng = np.random.default_rng(4)
        x = rng.normal(size=(40, 3)).astype(dtype)
        idx = np.concatenate([rng.permutation(40)[:25], [40] * 5, [-3]]).astype(np.int32)
        ct = rng.normal(size=(31, 3)).astype(dtype)
        fn = lambda x, ct: jax.vjp(lambda x: compact.take_rows(x, idx, True), x)[1](ct)[0]
        assert _targets(fn, x, ct) == {f"diffshade_put_rows_{'f64' if x64 else 'f32'}"}
        want = active_kernel.put_rows(idx, ct, 40, True, kernels.chunks())
        np.testing.assert_array_equal(np.asarray(jax.jit(fn)(x, ct)), want)
        # put_rows of on_active's outputs: the padding dropped
        put = lambda ct: compact.put_rows(ct, idx, 40, True)
        assert _targets(put, ct) == {f"diffshade_put_rows_{'f64' if x64 else 'f32'}"}
        want = active_kernel.put_rows(idx, ct, 40, False, kernels.chunks())
        np.testing.assert_array_equal(np.asarray(jax.jit(put)(ct)), want)


@pytest.mark.parametrize("x64", [False, True])
def test_sum_rows_target_equals_the_kernel(x64):
    """compact.sum_rows (rows of 3 floats) is the sum_rows target."""
    with jax.enable_x64(x64):
        dtype = np.float64 if x64 else np.float32
        rng = np.random.default_rng(9)
        idx = np.sort(rng.choice(80, 30, replace=False)).astype(np.int32)
        idx = np.concatenate([[-2], idx, [80] * 4]).astype(np.int32)
        rows = rng.normal(size=(35, 3)).astype(dtype)
        fn = lambda r: compact.sum_rows(r, idx, 10, 8, True)
        assert _targets(fn, rows) == {f"diffshade_sum_rows_{'f64' if x64 else 'f32'}"}
        want = active_kernel.sum_rows(idx, rows, 10, 8)
        np.testing.assert_array_equal(np.asarray(jax.jit(fn)(rows)), want)
        # a batch with indices of their own: one call of the target
        idxs = np.stack([idx, np.concatenate([idx[1:], [80]]).astype(np.int32)])
        batched = jax.vmap(lambda r, i: compact.sum_rows(r, i, 10, 8, True))
        assert _targets(batched, np.stack([rows, -rows]), idxs) == {
            f"diffshade_sum_rows_{'f64' if x64 else 'f32'}"}
        got = jax.jit(batched)(np.stack([rows, -rows]), idxs)
        np.testing.assert_array_equal(np.asarray(got[0]), want)
        np.testing.assert_array_equal(np.asarray(got[1]), active_kernel.sum_rows(
            idxs[1], -rows, 10, 8))


@pytest.mark.parametrize("group", [1, 3, 8])
def test_sum_rows_equals_a_loop_on_thousands_of_rows(group):
    """active_kernel.sum_rows against a NumPy loop: thousands of ascending indices with
    negative ones first and padding last, groups of 1 to 8 rows, empty ones between."""
    rng = np.random.default_rng(group)
    count = 1000
    idx = np.sort(rng.choice(count * group, 3 * count * group // 8, replace=False))
    idx = np.concatenate([[-5, -1], idx, [count * group] * 50]).astype(np.int32)
    rows = rng.normal(size=(idx.size, 3))
    want = np.zeros((count, 3))
    for i, j in enumerate(idx):
        if 0 <= j < count * group:
            want[j // group] += rows[i]
    got = active_kernel.sum_rows(idx, rows, count, group)
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("capacity", [1, 10, 40])
def test_active_target_equals_flatnonzero(capacity):
    mask = np.random.default_rng(3).uniform(size=30) < 0.4
    fn = lambda m: compact.active_indices(m, capacity, host=True)
    assert _targets(fn, mask) == {"diffshade_active"}
    idx, count = jax.jit(fn)(mask)
    found = np.flatnonzero(mask)[:capacity]
    want = np.full(capacity, mask.size, np.int32)
    want[:found.size] = found
    np.testing.assert_array_equal(np.asarray(idx), want)
    assert int(count) == mask.sum()


def _clips(views, seed=4):
    """Clip coordinates of a small random mesh seen by `views` cameras."""
    rng = np.random.default_rng(seed)
    vertices = rng.uniform(-1.0, 1.0, (12, 3))
    clips = []
    for v in range(views):
        z = vertices[:, 2] - 3.0 - 0.3 * v
        clips.append(np.stack([vertices[:, 0] * 2.0, vertices[:, 1] * 2.0,
                               -z * 1.002 - 0.2, -z], -1))
    faces = rng.integers(0, 12, (20, 3)).astype(np.int32)
    return np.asarray(clips, np.float32), faces


def _search(clip, faces, near, far, radius, sigma, gamma, *, k=4, size=16, height=None):
    height = size if height is None else height
    shapes = (jax.ShapeDtypeStruct((height, size, k), jnp.int32),
              jax.ShapeDtypeStruct((), jnp.int32))

    def fallback(*arrays):  # never run under jit on the CPU: the target is
        raise AssertionError("the Python callback ran instead of the FFI target")
    return hostcall.host_call(fallback, shapes, clip, faces, near, far, radius, sigma, gamma,
                     batched=True, ffi=("search_soft" if radius > 0.0 else "search_hard",
                                        (size, height, k, False, True)))


def _direct(clip, faces, near, far, radius, sigma, gamma, k=4, size=16, height=None):
    return candidates.find_candidates(clip, faces, near, far, width=size,
                                      height=size if height is None else height, k=k,
                                      radius_px=radius, sigma=sigma, gamma=gamma)


def _naive_hard_search(clip, faces, width, height, k):
    """The k nearest covering faces per pixel by a loop over pixels and faces: the pixel's
    NDC point p = (x, y, 1) is sum_i l_i (X_i, Y_i, W_i) of the face's clip corners, and
    the face covers it when every l_i >= 0 (then W = 1: in front) and z = sum_i l_i Z_i
    lies in [-1, 1]; nearest first by z, then by face id. -> [height, width, k], -1 empty."""
    clip = np.asarray(clip, np.float64)
    ids = np.full((height, width, k), -1, np.int32)
    for row in range(height):
        for col in range(width):
            p = np.array([(2 * col + 1) / width - 1, 1 - (2 * row + 1) / height, 1.0])
            hits = []
            for f, face in enumerate(faces):
                corners = clip[face][:, [0, 1, 3]].T
                if abs(np.linalg.det(corners)) < 1e-12:
                    continue
                weights = np.linalg.solve(corners, p)
                z = weights @ clip[face][:, 2]
                if np.all(weights >= 0.0) and -1.0 <= z <= 1.0:
                    hits.append((z, f))
            found = [f for _, f in sorted(hits)[:k]]
            ids[row, col, :len(found)] = found
    return ids


@pytest.mark.parametrize("radius", [0.0, 2.0])
@pytest.mark.parametrize("width, height", [(13, 7), (6, 11)])
def test_search_target_on_a_non_square_image(radius, width, height):
    """Rows and columns are not swapped: the target equals find_candidates, and in hard
    mode a naive loop over pixels and faces, on images wider than tall and taller than
    wide (the faces cover the image unevenly, so a transposed result cannot pass)."""
    clip, faces = _clips(1)
    scalars = (np.float32(0.1), np.float32(100.0), np.float32(radius), np.float32(1.0),
               np.float32(1e-3))
    ids, dropped = jax.jit(lambda c: _search(c, faces, *scalars, size=width,
                                             height=height))(clip[0])
    want_ids, want_dropped = _direct(clip[0], faces, *scalars, size=width, height=height)
    np.testing.assert_array_equal(np.asarray(ids), want_ids)
    assert int(dropped) == int(want_dropped)
    if radius == 0.0:
        naive = _naive_hard_search(clip[0], faces, width, height, 4)
        assert (naive[..., 0] >= 0).sum() >= 10 and (naive[..., 1] >= 0).sum() >= 5
        np.testing.assert_array_equal(np.asarray(ids), naive)


@pytest.mark.parametrize("radius", [0.0, 2.0])
def test_search_target_equals_find_candidates_for_batches(radius):
    clips, faces = _clips(3)
    sigmas = np.asarray([0.5, 1.0, 2.0], np.float32)
    scalars = lambda s: (np.float32(0.1), np.float32(100.0), np.float32(radius), s,
                         np.float32(1e-3))
    one = jax.jit(lambda c, s: _search(c, faces, *scalars(s)))
    many = jax.jit(jax.vmap(lambda c, s: _search(c, faces, *scalars(s))))
    mode = "soft" if radius > 0.0 else "hard"
    assert _targets(lambda c: _search(c, faces, *scalars(sigmas[0])), clips[0]) == {
        f"diffshade_search_{mode}_f32_i32"}
    ids, dropped = many(clips, sigmas)
    for v in range(3):
        want_ids, want_dropped = _direct(clips[v], faces, *scalars(sigmas[v]))
        np.testing.assert_array_equal(np.asarray(ids[v]), want_ids)
        np.testing.assert_array_equal(np.asarray(one(clips[v], sigmas[v])[0]), want_ids)
        assert int(dropped[v]) == int(want_dropped)
    # nested batches, one argument batched at the inner level only (broadcast against the
    # outer), and one mesh per view (searched one view at a time)
    grid = jax.jit(jax.vmap(jax.vmap(lambda c, s: _search(c, faces, *scalars(s)),
                                     in_axes=(0, None)), in_axes=(None, 0)))
    ids = grid(clips, sigmas[:2])
    for row in range(2):
        for v in range(3):
            want = _direct(clips[v], faces, *scalars(sigmas[row]))[0]
            np.testing.assert_array_equal(np.asarray(ids[0][row, v]), want)
    meshes = np.stack([faces, faces[::-1], np.roll(faces, 1, 0)])
    per_mesh = jax.jit(jax.vmap(lambda c, f: _search(c, f, *scalars(sigmas[1]))))
    ids = per_mesh(clips, meshes)[0]
    for v in range(3):
        want = _direct(clips[v], meshes[v], *scalars(sigmas[1]))[0]
        np.testing.assert_array_equal(np.asarray(ids[v]), want)


def test_workqueue_threading_layer_keeps_the_callbacks(monkeypatch):
    # numba's workqueue layer aborts on parallel kernels started from two threads at once:
    # there the kernels go through the (locked) callbacks, and host_call says so once
    import numba

    ids, *per_face = _fragment_inputs(np.float32)
    op = lambda *a: fragment_geometry(ids, *a, host=True, width=W, height=H, soft=True)
    monkeypatch.setattr(numba, "threading_layer", lambda: "workqueue")
    monkeypatch.setattr(hostcall, "_WARNED", set())
    with pytest.warns(hostcall.FallbackWarning, match="threading layer is 'workqueue'"):
        assert _targets(op, *per_face) == set()
    with warnings.catch_warnings():
        warnings.simplefilter("error", hostcall.FallbackWarning)
        assert _targets(op, *per_face) == set()


def test_another_ffi_api_keeps_the_callbacks_and_warns(monkeypatch):
    ids, *per_face = _fragment_inputs(np.float32)
    op = lambda *a: fragment_geometry(ids, *a, host=True, width=W, height=H, soft=True)
    monkeypatch.setattr(xla_ffi, "header_version", lambda: (xla_ffi.API_MAJOR + 1, 0))
    monkeypatch.setattr(hostcall, "_WARNED", set())
    with pytest.warns(hostcall.FallbackWarning, match=f"FFI API is {xla_ffi.API_MAJOR + 1}.0"):
        assert _targets(op, *per_face) == set()


def test_ffi_api_version_gate():
    assert xla_ffi.compatible(xla_ffi.API_MAJOR, xla_ffi.API_MINOR)
    assert xla_ffi.compatible(xla_ffi.API_MAJOR, xla_ffi.API_MINOR + 1)
    assert not xla_ffi.compatible(xla_ffi.API_MAJOR + 1, xla_ffi.API_MINOR)
    assert not xla_ffi.compatible(xla_ffi.API_MAJOR, xla_ffi.API_MINOR - 1)
    assert xla_ffi.header_version("/nonexistent") is None


def test_render_under_the_pinned_versions_runs_the_ffi_targets():
    # the versions pyproject.toml admits are the ones tested: there a jitted render calls
    # the handlers and no Python callback, and nothing falls back
    import diffshade as ds

    cam = ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=16, height=16, fov_y=45.0)
    scene = ds.make_scene(ds.icosphere(1), cam, [ds.directional_light((-0.3, -0.5, -1.0))],
                          ds.material(ka=0.1, kd=0.6, ks=0.3, shininess=20.0))
    settings = ds.RenderSettings(raster="soft", faces_per_pixel=4, shading="phong")
    with warnings.catch_warnings():
        warnings.simplefilter("error", hostcall.FallbackWarning)
        text = jax.jit(lambda s: ds.render(s, settings)).lower(scene).as_text()
    targets = set(re.findall(r"custom_call @(diffshade_\w+)", text))
    assert {"diffshade_search_soft_f32_i32", "diffshade_geometry_forward_f32"} <= targets
    assert "callback" not in text


def _header_values(include, expressions):
    """{name: value of the C expression} for the header under `include`, by a C program
    compiled against it."""
    lines = [f'printf("{name} %lld\\n", (long long)({expression}));'
             for name, expression in expressions.items()]
    source = ("#include <stdio.h>\n#include <stddef.h>\n#include \"xla/ffi/api/c_api.h\"\n"
              "int main(void) {\n" + "\n".join(lines) + "\nreturn 0;\n}\n")
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "layout.c")
        with open(path, "w") as f:
            f.write(source)
        binary = os.path.join(folder, "layout")
        subprocess.run([_compiler(), "-I", include, "-o", binary, path], check=True)
        out = subprocess.run([binary], check=True, capture_output=True, text=True).stdout
    return {name: int(value) for name, value in (line.split() for line in out.splitlines())}


def _compiler():
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")


#: xla_ffi's constants, as C expressions on the header's types
_LAYOUT = {
    "EXTENSION_TYPE": "offsetof(XLA_FFI_Extension_Base, type)",
    "EXTENSION_BASE_SIZE": "XLA_FFI_Extension_Base_STRUCT_SIZE",
    "EXTENSION_METADATA": "XLA_FFI_Extension_Metadata",
    "VERSION_MAJOR": "offsetof(XLA_FFI_Api_Version, major_version)",
    "VERSION_MINOR": "offsetof(XLA_FFI_Api_Version, minor_version)",
    "VERSION_SIZE": "XLA_FFI_Api_Version_STRUCT_SIZE",
    "API_VERSION": "offsetof(XLA_FFI_Api, api_version)",
    "API_ERROR_CREATE": "offsetof(XLA_FFI_Api, XLA_FFI_Error_Create)",
    "ERROR_MESSAGE": "offsetof(XLA_FFI_Error_Create_Args, message)",
    "ERROR_CODE": "offsetof(XLA_FFI_Error_Create_Args, errc)",
    "ERROR_ARGS_SIZE": "XLA_FFI_Error_Create_Args_STRUCT_SIZE",
    "INVALID_ARGUMENT": "XLA_FFI_Error_Code_INVALID_ARGUMENT",
    "FRAME_EXTENSION": "offsetof(XLA_FFI_CallFrame, extension_start)",
    "FRAME_API": "offsetof(XLA_FFI_CallFrame, api)",
    "FRAME_STAGE": "offsetof(XLA_FFI_CallFrame, stage)",
    "FRAME_ARGS": "offsetof(XLA_FFI_CallFrame, args)",
    "FRAME_RETS": "offsetof(XLA_FFI_CallFrame, rets)",
    "FRAME_ATTRS": "offsetof(XLA_FFI_CallFrame, attrs)",
    "FRAME_SIZE": "XLA_FFI_CallFrame_STRUCT_SIZE",
    "STAGE_EXECUTE": "XLA_FFI_ExecutionStage_EXECUTE",
    "LIST_SIZE": "offsetof(XLA_FFI_Args, size)",
    "LIST_TYPES": "offsetof(XLA_FFI_Args, types)",
    "LIST_ITEMS": "offsetof(XLA_FFI_Args, args)",
    "ARGS_SIZE": "XLA_FFI_Args_STRUCT_SIZE",
    "RETS_SIZE": "XLA_FFI_Rets_STRUCT_SIZE",
    "BUFFER_TYPE": "XLA_FFI_ArgType_BUFFER",
    "ATTRS_NAMES": "offsetof(XLA_FFI_Attrs, names)",
    "ATTRS_ITEMS": "offsetof(XLA_FFI_Attrs, attrs)",
    "ATTRS_SIZE": "XLA_FFI_Attrs_STRUCT_SIZE",
    "ATTR_SCALAR": "XLA_FFI_AttrType_SCALAR",
    "SPAN_LENGTH": "offsetof(XLA_FFI_ByteSpan, len)",
    "SCALAR_VALUE": "offsetof(XLA_FFI_Scalar, value)",
    "BUFFER_DTYPE": "offsetof(XLA_FFI_Buffer, dtype)",
    "BUFFER_DATA": "offsetof(XLA_FFI_Buffer, data)",
    "BUFFER_RANK": "offsetof(XLA_FFI_Buffer, rank)",
    "BUFFER_DIMS": "offsetof(XLA_FFI_Buffer, dims)",
    "BUFFER_SIZE": "XLA_FFI_Buffer_STRUCT_SIZE",
    "PRED": "XLA_FFI_DataType_PRED",
    "S8": "XLA_FFI_DataType_S8",
    "S32": "XLA_FFI_DataType_S32",
    "S64": "XLA_FFI_DataType_S64",
    "F32": "XLA_FFI_DataType_F32",
    "F64": "XLA_FFI_DataType_F64",
    "METADATA_POINTER": "offsetof(XLA_FFI_Metadata_Extension, metadata)",
    "METADATA_EXTENSION_SIZE": "XLA_FFI_Metadata_Extension_STRUCT_SIZE",
    "METADATA_VERSION": "offsetof(XLA_FFI_Metadata, api_version)",
    "METADATA_TRAITS": "offsetof(XLA_FFI_Metadata, traits)",
    "METADATA_SIZE": "XLA_FFI_Metadata_STRUCT_SIZE",
}


def test_layout_equals_the_installed_header():
    if _compiler() is None:
        pytest.skip("no C compiler (cc, gcc or $CC) to read the header's layout with")
    include = jax.ffi.include_dir()
    assert _header_values(include, _LAYOUT) == {name: getattr(xla_ffi, name)
                                                for name in _LAYOUT}
    # the accessors read XLA_FFI_Rets and XLA_FFI_Attrs's list fields at XLA_FFI_Args's
    shared = {f"{struct}_{field}": f"offsetof(XLA_FFI_{struct}, {field})"
              for struct, fields in (("Rets", ("size", "types", "rets")),
                                     ("Attrs", ("size", "types")))
              for field in fields}
    values = _header_values(include, shared)
    assert (values["Rets_size"], values["Rets_types"], values["Rets_rets"]) == (
        xla_ffi.LIST_SIZE, xla_ffi.LIST_TYPES, xla_ffi.LIST_ITEMS)
    assert (values["Attrs_size"], values["Attrs_types"]) == (xla_ffi.LIST_SIZE,
                                                             xla_ffi.LIST_TYPES)
    version = _header_values(include, {"major": "XLA_FFI_API_MAJOR",
                                       "minor": "XLA_FFI_API_MINOR"})
    assert xla_ffi.header_version(include) == (version["major"], version["minor"])
    assert xla_ffi.compatible(version["major"], version["minor"]), version


def _ffi_call(target, operands, results, **attributes):
    """jax.jit of a bare jax.ffi.ffi_call of `target` (registered first); Python int
    attributes as int64."""
    from diffshade.host import ffi

    ffi._register(target)
    named = {name: np.int64(value) if isinstance(value, int) else value
             for name, value in attributes.items()}
    call = jax.ffi.ffi_call(target, results)
    return jax.jit(lambda *a: call(*a, **named))(*operands)


_ACTIVE = (jax.ShapeDtypeStruct((4,), jnp.int32), jax.ShapeDtypeStruct((), jnp.int32))


@pytest.mark.parametrize("operands, results, attributes, expected", [
    ((np.ones(3, np.float32),), _ACTIVE, {"threads": 1},
     "argument 0 has dtype float32 (F32), expected bool (PRED)"),
    ((np.ones((3, 2), bool),), _ACTIVE, {"threads": 1}, "argument 0 has rank 2, expected 1"),
    ((np.ones(3, bool), np.ones(3, bool)), _ACTIVE, {"threads": 1},
     "2 arguments, expected 1"),
    ((np.ones(3, bool),), _ACTIVE[:1], {"threads": 1}, "1 results, expected 2"),
    ((np.ones(3, bool),), (_ACTIVE[0], jax.ShapeDtypeStruct((1,), jnp.int32)),
     {"threads": 1}, "result 1 has rank 1, expected 0"),
    ((np.ones(3, bool),), _ACTIVE, {}, "no attribute 'threads'"),
])
def test_active_target_rejects_a_bad_call(operands, results, attributes, expected):
    with pytest.raises(Exception, match=re.escape(f"diffshade_active: {expected}")):
        _ffi_call("diffshade_active", operands, results, **attributes)
    # the process survives, and the target still runs a good call
    idx, count = _ffi_call("diffshade_active", (np.asarray([False, True, True]),), _ACTIVE,
                           threads=1)
    np.testing.assert_array_equal(np.asarray(idx), [1, 2, 3, 3])
    assert int(count) == 2


def test_geometry_target_rejects_bad_shapes():
    ids, corner_w, corner_z, coeffs, scr = _fragment_inputs(np.float32)
    results = (jax.ShapeDtypeStruct((H, W, K, 3), jnp.float32),
               jax.ShapeDtypeStruct((H, W, K), jnp.float32),
               jax.ShapeDtypeStruct((H, W, K), jnp.float32),
               jax.ShapeDtypeStruct((H, W, K), jnp.int8))
    attributes = {"width": W, "height": H, "soft": 1, "threads": 1}
    target = "diffshade_geometry_forward_f32"
    cases = [
        ((ids, corner_w, corner_z, coeffs, scr[..., :1]), results,
         "argument 4 has 1 at axis -1, expected 2"),
        ((ids, corner_w.astype(np.float64), corner_z, coeffs, scr), results,
         "argument 1 has dtype float64 (F64), expected float32 (F32)"),
        ((ids, corner_w, corner_z, coeffs, scr), (results[0], results[1],
                                                  jax.ShapeDtypeStruct((H, W), jnp.float32),
                                                  results[3]),
         f"result 2 has {H * W} elements, expected {H * W * K} (1 per element of argument 0)"),
        ((ids, corner_w, corner_z, coeffs, scr), results[:3] + (
            jax.ShapeDtypeStruct((H, W, K), jnp.int32),),
         "result 3 has dtype int32 (S32), expected int8 (S8)"),
    ]
    with jax.enable_x64(True):
        for operands, shapes, expected in cases:
            with pytest.raises(Exception, match=re.escape(f"{target}: {expected}")):
                _ffi_call(target, operands, shapes, **attributes)
        with pytest.raises(Exception, match=re.escape(f"{target}: attribute 'soft' is of")):
            _ffi_call(target, (ids, corner_w, corner_z, coeffs, scr), results,
                      **{**attributes, "soft": np.int32(1)})


@pytest.mark.parametrize("x64", [False, True])
def test_interpolate_at_target_equals_the_kernel(x64):
    with jax.enable_x64(x64):
        dtype = np.float64 if x64 else np.float32
        rng = np.random.default_rng(4)
        ids = rng.integers(-1, F, H * W * K).astype(np.int32)
        bary = rng.uniform(size=(H * W * K, 3)).astype(dtype)
        corners = rng.normal(size=(F, 3, 4)).astype(dtype)
        rows = np.concatenate([rng.permutation(ids.size)[:40], [ids.size, -1]]).astype(np.int32)
        at = lambda b, c: compact._interpolate_at(rows, ids, b, c)
        width = "f64" if x64 else "f32"
        assert _targets(at, bary, corners) == {f"diffshade_interpolate_at_{width}"}
        np.testing.assert_array_equal(np.asarray(jax.jit(at)(bary, corners)),
                                      kernels.interpolate_at(rows, ids, bary, corners, 2))
