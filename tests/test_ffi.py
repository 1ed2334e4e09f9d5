"""The host kernels as XLA FFI targets (diffshade/host/ffi.py): under jit on the CPU, XLA calls
the compiled handlers with its own buffers. Each target against the kernel called directly
from NumPy (fragment_kernels, candidates, the reference search loop of compact's test:
np.flatnonzero), bit for bit, in float32 and float64, batched and not; and the lowered
programs name the targets (else the callback path would be tested twice)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade.host import candidates, hostcall
from diffshade.host import fragment_kernels as kernels
from diffshade.numerics import tiny
from diffshade.raster.fragments import fragment_geometry
from diffshade.raster.interpolate import interpolate_corners
from diffshade.shade import compact

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
        want = kernels.geometry_forward(ids.reshape(-1, K), *args)
        for got, ref in zip((bary, depth, dist), want, strict=True):
            assert got.dtype == dtype
            np.testing.assert_array_equal(np.asarray(got).reshape(ref.shape), ref)
        want = kernels.geometry_backward(ids.reshape(-1, K), *args, cot[0].reshape(-1, K, 3),
                                         cot[1].reshape(-1, K), cot[2].reshape(-1, K))
        for got, ref in zip(grads, want, strict=True):
            np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12 if x64 else 1e-5,
                                       atol=1e-12 if x64 else 1e-5)


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


def _search(clip, faces, near, far, radius, sigma, gamma, *, k=4, size=16):
    shapes = (jax.ShapeDtypeStruct((size, size, k), jnp.int32),
              jax.ShapeDtypeStruct((), jnp.int32))

    def fallback(*arrays):  # never run under jit on the CPU: the target is
        raise AssertionError("the Python callback ran instead of the FFI target")
    return hostcall.host_call(fallback, shapes, clip, faces, near, far, radius, sigma, gamma,
                     batched=True, ffi=("search_soft" if radius > 0.0 else "search_hard",
                                        (size, size, k, False, True)))


def _direct(clip, faces, near, far, radius, sigma, gamma, k=4, size=16):
    return candidates.find_candidates(clip, faces, near, far, width=size, height=size, k=k,
                                      radius_px=radius, sigma=sigma, gamma=gamma)


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
    # there the kernels go through the (locked) callbacks
    import numba

    ids, *per_face = _fragment_inputs(np.float32)
    op = lambda *a: fragment_geometry(ids, *a, host=True, width=W, height=H, soft=True)
    monkeypatch.setattr(numba, "threading_layer", lambda: "workqueue")
    assert _targets(op, *per_face) == set()


def test_switch_turns_the_targets_off(monkeypatch):
    ids, *per_face = _fragment_inputs(np.float32)
    # a new function per program: the switch is read when a program is traced
    op = lambda: lambda *a: fragment_geometry(ids, *a, host=True, width=W, height=H, soft=True)
    on = jax.jit(op())(*per_face)
    monkeypatch.setenv(hostcall.FFI_SWITCH, "0")
    assert _targets(op(), *per_face) == set()
    off = jax.jit(op())(*per_face)
    for a, b in zip(on, off, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_concurrent_renders_from_two_threads_equal_one_at_a_time():
    # the FFI targets take no lock (the callbacks do): numba's OpenMP layer runs parallel
    # kernels started from two threads at once
    import threading

    import diffshade as ds

    cam = ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=32, height=32, fov_y=45.0)
    scene = ds.make_scene(ds.icosphere(2), cam, [ds.directional_light((-0.3, -0.5, -1.0))],
                          ds.material(ka=0.1, kd=0.6, ks=0.3, shininess=20.0))
    settings = ds.RenderSettings(raster="soft", faces_per_pixel=4, shading="phong")
    render = jax.jit(lambda s: ds.render(s, settings))
    want = np.asarray(render(scene))
    got = [None] * 4

    def run(i):
        got[i] = [np.asarray(render(scene)) for _ in range(5)]
    threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for images in got:
        for image in images:
            np.testing.assert_array_equal(image, want)
