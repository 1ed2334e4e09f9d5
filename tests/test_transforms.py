"""Every JAX transform through the renderer, on both kernel paths (RenderSettings.kernels).

Default settings on this CPU run the fragment ops as host kernels behind JAX primitives
with their own jvp, transpose and batching rules (diffshade/host/hostop.py); kernels='jax'
runs them in jax.numpy. Checked in float64 on a tiny scene (the one of
test_gradients.py, lit by every light type):
- jax.test_util.check_grads, forward and reverse mode, against central finite
  differences, jointly in vertices, normals, model matrix, camera (eye, target, fov),
  material (ka, kd, ks, shininess, emission), light positions, directions and colours,
  and the background; order 1 on the default path, order 2 on the JAX path; hard and soft
  raster; every shading mode (order 2: each of flat_last's parts, under Gouraud and flat);
- jacfwd against jacrev, vmap of grad against a loop of grads, checkpoint;
- the two paths against each other (images and gradients to 1e-9);
- continuous settings as data: no recompilation for new sigma / gamma values, and a
  gradient with respect to sigma and gamma under jit against finite differences;
- batched views (render_views) against a loop of renders.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compiles
from jax.test_util import check_grads
from test_gradients import KINDS, field, scene_for_gradients, weights

from diffshade import RenderSettings, look_at, render, render_views

pytestmark = pytest.mark.usefixtures("x64")

NAMES = ("vertices", "normals", "model_translation", "model_linear", "eye", "target",
         "fov_y", "ka", "kd", "ks", "shininess", "emission", "point_position",
         "spot_position", "directional_direction", "spot_direction", "point_diffuse",
         "directional_specular", "spot_diffuse", "ambient_light", "background")
PARAMS = {**KINDS, "normals": field("mesh", "normals")}
# K = 80 holds every face, and a threshold of 1e-10 puts a face's footprint edge where its
# coverage is 1e-10: no step a finite difference takes changes the candidates by more
# than that (their first and second derivatives are checked against differences)
SOFT = dict(raster="soft", faces_per_pixel=80, sigma=2.0, gamma=1e-2, spot_edge="smooth",
            soft_threshold=1e-10)
# LLVM's backend optimizations only schedule IEEE operations (no fast-math), so they change
# no value beyond rounding; without them these programs compile much faster
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


MODES = [(raster, shading) for raster in ("hard", "soft")
         for shading in ("phong", "gouraud", "flat", "flat_last")]


def settings_for(raster, shading, **extra):
    soft = SOFT if raster == "soft" else {"spot_edge": "smooth"}
    return RenderSettings(shading=shading, **soft, **extra)


def loss_and_params(settings, names=NAMES, lights=None):
    """loss(params) = sum(w * image), and the scene's params (every kind in `names`);
    lights: which of the scene's light groups to keep (default all)."""
    scene = scene_for_gradients()
    if lights is not None:
        scene = dataclasses.replace(scene, lights=dataclasses.replace(scene.lights, **{
            kind: None for kind in ("ambient", "directional", "point", "spot")
            if kind not in lights}))
    w = weights(scene)
    params = {n: PARAMS[n][0](scene) for n in names}
    return (lambda p: jnp.sum(w * render(with_params_all(scene, p), settings))), params


def with_params_all(scene, params):
    for name, value in params.items():
        scene = PARAMS[name][1](scene, value)
    return scene


@pytest.mark.parametrize("raster,shading", MODES)
def test_default_path_passes_check_grads_forward_and_reverse(raster, shading):
    settings = settings_for(raster, shading)
    assert settings.use_host_kernels()  # the default on the CPU backend
    loss, params = loss_and_params(settings)
    check_grads(jax.jit(loss), (params,), order=1, modes=("fwd", "rev"), eps=1e-6,
                atol=1e-5, rtol=1e-5)


def second_order_terms(loss):
    """One jitted function of (x, v, u): the second-order products forward over reverse
    (H v), reverse over forward (H v) and forward over forward (u.H v)."""
    tangent = lambda y, t: jax.jvp(loss, (y,), (t,))[1]

    def terms(x, v, u):
        return (jax.jvp(jax.grad(loss), (x,), (v,))[1], jax.grad(lambda y: tangent(y, v))(x),
                jax.jvp(lambda y: tangent(y, v), (x,), (u,))[1])
    return jax.jit(terms, compiler_options=FAST_COMPILE)


def random_like(tree, seed):
    """A random direction of unit norm over all the leaves of `tree`."""
    rng = np.random.default_rng(seed)
    v = jax.tree.map(lambda a: rng.normal(size=np.shape(a)), tree)
    norm = np.sqrt(sum(np.sum(a * a) for a in jax.tree.leaves(v)))
    return jax.tree.map(lambda a: jnp.asarray(a / norm), v)


def shifted(x, v, h):
    return jax.tree.map(lambda a, b: a + h * b, x, v)


def assert_tree_close(actual, expected, tol):
    for a, e in zip(jax.tree.leaves(actual), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(a, e, rtol=tol, atol=tol * (1.0 + np.abs(e).max()))


#: the second-order checks light with a spot and a directional light (positions,
#: directions, colours, the spot's cone): every light type costs compile time here
SECOND_ORDER_LIGHTS = ("directional", "spot")
SECOND_ORDER_NAMES = tuple(n for n in NAMES if not n.startswith(("point", "ambient")))


# flat_last's samples are Gouraud's (per vertex and side) read as flat's are (one sample
# per fragment, unweighted: diffshade.shading.samples), so the modes below run each of its parts
# in both rasters; its first-order gradients are checked above with every other mode
SECOND_ORDER_MODES = [(raster, shading) for raster, shading in MODES if shading != "flat_last"]


@pytest.mark.cost(40)
@pytest.mark.parametrize("raster,shading", SECOND_ORDER_MODES)
def test_jax_path_second_order_derivatives_match_finite_differences(raster, shading):
    """check_grads at order 2 (below, for one mode) compiles a dozen programs; this is the
    same check in two programs: the second-order products in each mode pairing against
    central differences of the gradient (reverse over reverse: the Hessian test below),
    in every raster mode and every way of lighting and reading the shading samples."""
    loss, x = loss_and_params(settings_for(raster, shading, kernels="jax"),
                              SECOND_ORDER_NAMES, SECOND_ORDER_LIGHTS)
    v, u, h = random_like(x, 1), random_like(x, 2), 1e-5
    hv_fwd_rev, hv_rev_fwd, uhv = second_order_terms(loss)(x, v, u)
    grad = jax.jit(jax.grad(loss), compiler_options=FAST_COMPILE)
    hv = jax.tree.map(lambda a, b: (a - b) / (2 * h), grad(shifted(x, v, h)),
                      grad(shifted(x, v, -h)))
    assert max(float(jnp.abs(a).max()) for a in jax.tree.leaves(hv)) > 1e-2
    for got in (hv_fwd_rev, hv_rev_fwd):
        assert_tree_close(got, hv, 1e-5)
    expected = sum(jnp.vdot(a, b) for a, b in zip(jax.tree.leaves(u), jax.tree.leaves(hv),
                                                  strict=True))
    np.testing.assert_allclose(uhv, expected, rtol=1e-4)


def test_jax_path_passes_check_grads_at_order_2():
    """jax.test_util.check_grads itself (its dozen compilations make it the costliest test:
    one mode and one light here; the test above covers every mode)."""
    names = tuple(n for n in SECOND_ORDER_NAMES if not n.startswith("spot"))
    loss, params = loss_and_params(settings_for("hard", "phong", kernels="jax"), names,
                                   ("directional",))
    check_grads(jax.jit(loss), (params,), order=2, modes=("fwd", "rev"), eps=1e-6,
                atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("raster,shading", [("hard", "gouraud")])
def test_hessian_on_the_default_path_equals_the_jax_path(raster, shading):
    out = []
    for kernels in ("host", "jax"):
        loss, params = loss_and_params(settings_for(raster, shading, kernels=kernels))
        sub = {"vertices": params["vertices"][:6], "kd": params["kd"]}
        f = lambda s, loss=loss, params=params: loss(
            {**params, "kd": s["kd"], "vertices": params["vertices"].at[:6].set(s["vertices"])})
        out.append(jax.jit(jax.hessian(f), compiler_options=FAST_COMPILE)(sub))
    for a, b in zip(jax.tree.leaves(out[0]), jax.tree.leaves(out[1]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("shading", ["phong", "gouraud"])
def test_jax_path_equals_host_path(shading):
    """Soft raster: it runs every op of both paths (the search, the geometry with its
    distances, the interpolation per fragment and per vertex; flat modes use no other)."""
    raster = "soft"
    results = []
    for kernels in ("host", "jax"):
        settings = settings_for(raster, shading, kernels=kernels)
        loss, params = loss_and_params(settings)
        image = render(scene_for_gradients(), settings)
        grad = jax.jit(jax.grad(loss), compiler_options=FAST_COMPILE)
        results.append((image, grad(params)))
    for a, b in zip(jax.tree.leaves(results[0]), jax.tree.leaves(results[1]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


def _random_fragments(seed, block, height=24, width=20, k=4, faces=7):
    """(rng, ids [height, width, k] with empty slots among them, the per-face inputs of
    fragment_geometry) at random: more fragments than 4 blocks of `block`."""
    rng = np.random.default_rng(seed)
    ids = rng.integers(-1, faces, (height, width, k)).astype(np.int32)
    assert np.sum(ids >= 0) > 4 * block
    per_face = (rng.uniform(0.5, 2.0, (faces, 3)), rng.uniform(-5.0, -1.0, (faces, 3)),
                rng.normal(size=(faces, 3, 3)), rng.uniform(0.0, width, (faces, 3, 2)))
    return rng, ids, per_face


@pytest.mark.parametrize("soft", [False, True])
def test_geometry_forward_kernel_equals_the_jax_geometry(soft):
    """fragment_geometry's forward kernel (barycentrics, depth, signed distance) against its
    jax.numpy form on random fragments, empty slots among them (written as zeros)."""
    from diffshade.raster.fragments import fragment_geometry

    rng, ids, per_face = _random_fragments(6, 64)
    height, width, k = ids.shape
    outs = [jax.jit(lambda *a, host=host: fragment_geometry(
        ids, *a, host=host, width=width, height=height, soft=soft))(*per_face)
        for host in (True, False)]
    for got, want in zip(*outs, strict=True):
        assert np.abs(want).max() > 0.0 or not soft
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    assert np.all(outs[0][0][ids < 0] == 0.0) and np.all(outs[0][1][ids < 0] == 0.0)


def _projected_faces(height, width, rng):
    """fragment_geometry's per-face inputs of triangles in clip space: one with its corners
    on pixel centres (W = 1; on an image whose sides are powers of two, the pixels along
    its edges lie exactly on them), a zero-area one (corners on a line), a tiny one (a
    millionth of a pixel) and random ones behind the camera's plane, perspective among
    them."""
    from diffshade.raster import fragments as raster

    ndc = lambda col, row: [(2.0 * col + 1.0) / width - 1.0, 1.0 - (2.0 * row + 1.0) / height]
    on_centres = [ndc(0, 0) + [0.0, 1.0], ndc(width - 1, 0) + [0.1, 1.0],
                  ndc(0, height - 1) + [0.2, 1.0]]
    line = [[-0.5, -0.5, 0.0, 1.0], [0.0, 0.0, 0.1, 1.0], [0.5, 0.5, 0.2, 1.0]]
    tiny_face = [[0.1, 0.1, 0.0, 1.0], [0.1 + 1e-6 / width, 0.1, 0.0, 1.0],
                 [0.1, 0.1 + 1e-6 / height, 0.0, 1.0]]
    w = rng.uniform(0.5, 3.0, (9, 1))
    random = np.concatenate([rng.uniform(-1.2, 1.2, (9, 2)) * w, rng.uniform(-1, 1, (9, 1)), w],
                            -1)
    clip = jnp.asarray(np.concatenate([on_centres, line, tiny_face, random]))
    faces = jnp.arange(clip.shape[0]).reshape(-1, 3)
    depth = -jnp.asarray(rng.uniform(1.0, 5.0, clip.shape[0]))
    return (jnp.take(clip[:, 3], faces), jnp.take(depth, faces),
            raster.face_edge_coefficients(clip, faces)[0],
            jnp.take(raster._screen_positions(clip, width, height), faces, axis=0))


@pytest.mark.parametrize("soft", [False, True])
@pytest.mark.parametrize("batch, height, width, k", [(1, 1, 1, 1), (1, 1, 1, 9), (2, 4, 8, 5),
                                                    (1, 8, 2, 3), (3, 3, 5, 2), (1, 2, 3, 130)])
def test_geometry_forward_kernel_on_awkward_fragments(soft, batch, height, width, k):
    """The forward kernel against the jax.numpy geometry (fragment_geometry's native form)
    where its loops have edges: 1-pixel and non-square images, a batch of images folded
    into one call's rows, one or two parts (chunks), K of 1, odd and above 128 (one
    pixel's slots over several of fragment_kernels._BLOCK, for a kernel that gathers its
    fragments in blocks), pixels with every slot empty or every slot full, pixels exactly
    on a triangle's edge, zero-area and tiny triangles. Empty slots are zeros."""
    from diffshade.host import fragment_kernels as kernels
    from diffshade.numerics import tiny
    from diffshade.raster.fragments import _geometry_native

    rng = np.random.default_rng(height * 1000 + width * 10 + k)
    per_face = _projected_faces(height, width, rng)
    nfaces = per_face[0].shape[0]
    ids = rng.integers(0, nfaces, (batch * height, width, k)).astype(np.int32)
    ids[rng.random(ids.shape) < 0.3] = -1
    ids[0, 0] = -1  # a pixel without faces
    ids[-1, -1] = np.arange(k) % nfaces  # one with every slot full, every face among them
    want = _geometry_native(jnp.asarray(ids), *per_face, width=width, height=height,
                            soft=soft)
    for chunks in (1, 2):
        *got, edge = kernels.geometry_forward(ids.reshape(-1, k), *map(np.asarray, per_face),
                                              width, height, soft, tiny(np.float64), chunks)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g.reshape(w.shape), w, rtol=1e-9, atol=1e-9)
        empty = ids.reshape(-1, k) < 0
        assert np.all(got[0][empty] == 0.0) and np.all(got[1][empty] == 0.0)
        assert np.all(got[2][empty] == 0.0) and np.all(edge[empty] == 0)
        assert np.all(edge == 0) if not soft else np.array_equal(
            edge >= kernels.OUTSIDE, np.signbit(got[2]) & ~empty)
    if soft and (width, height) == (8, 4):
        # the pixels on the first face's edges are inside it, at distance 0 (up to the
        # rounding of the nearest point's parameter on the edge)
        on_edge = (ids[:height] == 0) & ((np.arange(height)[:, None, None] == 0)
                                         | (np.arange(width)[None, :, None] == 0))
        assert on_edge.any()
        dist = np.asarray(got[2]).reshape(ids.shape)[:height][on_edge]
        assert np.all(dist >= 0.0) and np.all(dist < 1e-28), dist


@pytest.mark.parametrize("soft", [False, True])
def test_geometry_backward_kernel_equals_reverse_mode_of_the_jax_geometry(soft):
    """fragment_geometry's backward kernel against jax.vjp of its jax.numpy form on random
    fragments, with a cotangent of the barycentrics and depth on about half of them (the
    distance's on all): more per part than the kernel gathers in one block
    (fragment_kernels._BLOCK), so that full blocks and the last partial one all count."""
    from diffshade.host.fragment_kernels import _BLOCK
    from diffshade.raster.fragments import fragment_geometry

    rng, ids, per_face = _random_fragments(5, _BLOCK)
    height, width, k = ids.shape
    on = rng.random((height, width, k)) < 0.5
    cot = (rng.normal(size=(height, width, k, 3)) * on[..., None],
           rng.normal(size=(height, width, k)) * on, rng.normal(size=(height, width, k)))
    grads = []
    for host in (True, False):
        op = lambda *a, host=host: fragment_geometry(ids, *a, host=host, width=width,
                                                     height=height, soft=soft)
        grads.append(jax.jit(lambda *a, op=op: jax.vjp(op, *a)[1](cot))(*per_face))
    for got, want in zip(*grads, strict=True):
        assert np.abs(want).max() > 0.0 or not soft
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("raster", ["soft"])
def test_jacfwd_equals_jacrev_on_the_default_path(raster):
    scene = scene_for_gradients()
    settings = settings_for(raster, "gouraud")

    def image(p):
        return render(with_params_all(scene, p), settings)[6:9, 8:12]
    params = {"vertices": scene.mesh.vertices, "kd": scene.material.kd,
              "normals": scene.mesh.normals}
    fwd = jax.jit(jax.jacfwd(image), compiler_options=FAST_COMPILE)(params)
    rev = jax.jit(jax.jacrev(image), compiler_options=FAST_COMPILE)(params)
    for a, b in zip(jax.tree.leaves(fwd), jax.tree.leaves(rev), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    assert np.abs(fwd["vertices"]).max() > 1e-3


@pytest.mark.parametrize("raster", ["soft"])
def test_vmap_of_grad_equals_a_loop_of_grads(raster):
    loss, params = loss_and_params(settings_for(raster, "phong"))
    grad = jax.jit(jax.grad(loss), compiler_options=FAST_COMPILE)
    batch = [params, {**params, "vertices": params["vertices"] * 1.02,
                      "eye": params["eye"] + 0.05}]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *batch)
    batched = jax.jit(jax.vmap(jax.grad(loss)), compiler_options=FAST_COMPILE)(stacked)
    for i, p in enumerate(batch):
        for a, b in zip(jax.tree.leaves(grad(p)), jax.tree.leaves(batched), strict=True):
            np.testing.assert_allclose(b[i], a, rtol=1e-10, atol=1e-12)


def test_checkpoint_gives_the_same_gradient():
    loss, params = loss_and_params(settings_for("hard", "gouraud"))
    plain = jax.jit(jax.grad(loss), compiler_options=FAST_COMPILE)(params)
    remat = jax.jit(jax.grad(jax.checkpoint(loss)), compiler_options=FAST_COMPILE)(params)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(remat), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


def test_new_sigma_gamma_and_spot_softness_values_do_not_recompile():
    scene = scene_for_gradients()
    settings = settings_for("soft", "phong")
    render(scene, settings)
    with compiles() as counted:
        for sigma, gamma, softness in ((0.5, 1e-3, 1.0), (1.5, 3e-2, 4.0), (3.0, 1e-4, 0.5)):
            render(scene, dataclasses.replace(settings, sigma=sigma, gamma=gamma,
                                              spot_softness=softness)).block_until_ready()
    assert counted.of(render) == 0


def test_gradient_with_respect_to_sigma_and_gamma_under_jit():
    scene = scene_for_gradients()
    w = weights(scene)
    base = settings_for("soft", "phong")

    @jax.jit
    def loss(sigma, gamma):
        return jnp.sum(w * render(scene, dataclasses.replace(base, sigma=sigma, gamma=gamma)))
    sigma, gamma, h = 2.0, 1e-2, 1e-7
    g_sigma, g_gamma = jax.grad(loss, argnums=(0, 1))(sigma, gamma)
    fd_sigma = (loss(sigma + h, gamma) - loss(sigma - h, gamma)) / (2 * h)
    fd_gamma = (loss(sigma, gamma + h * 1e-2) - loss(sigma, gamma - h * 1e-2)) / (2 * h * 1e-2)
    assert abs(float(fd_sigma)) > 1e-3 and abs(float(fd_gamma)) > 1e-3
    np.testing.assert_allclose(g_sigma, fd_sigma, rtol=1e-5)
    np.testing.assert_allclose(g_gamma, fd_gamma, rtol=1e-5)


@pytest.mark.parametrize("raster", ["hard", "soft"])
def test_render_views_equals_a_loop_of_renders(raster):
    scene = scene_for_gradients()
    settings = settings_for(raster, "phong")
    cams = [look_at(eye, (0.0, 0.0, 0.0), width=20, height=18, fov_y=40.0)
            for eye in ((0.4, 0.3, 3.4), (-1.0, 0.5, 3.0), (2.0, -0.5, 2.5))]
    batched = render_views(scene, cams, settings)
    for i, cam in enumerate(cams):
        single = render(dataclasses.replace(scene, camera=cam), settings)
        np.testing.assert_allclose(batched[i], single, rtol=1e-12, atol=1e-12)


def test_render_views_rejects_cameras_of_different_sizes():
    cams = [look_at((0, 0, 3), (0, 0, 0), width=20, height=18),
            look_at((0, 0, 3), (0, 0, 0), width=16, height=18)]
    with pytest.raises(ValueError, match="cameras"):
        render_views(scene_for_gradients(), cams)


SHARDED = """
import jax, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
import diffshade as ds
assert jax.device_count() == 2, jax.devices()
scene = ds.builtin_scene("sphere", 24, 20)
cams = ds.stack_cameras([ds.look_at(e, (0, 0, 0), width=24, height=20, fov_y=45)
                         for e in [(0, 0, 3), (2, 0.5, 2.2), (-2, 1, 2), (0.5, -2.5, 1.8)]])
mesh = Mesh(np.array(jax.devices()), ("views",))
sharded = jax.device_put(cams, NamedSharding(mesh, P("views")))
for kernels in ("auto", "jax"):
    settings = ds.RenderSettings(raster="soft", kernels=kernels)
    assert not settings.use_host_kernels()
    alone = np.asarray(ds.render_views(scene, cams, settings))
    images = ds.render_views(scene, sharded, settings)
    assert len(images.sharding.device_set) == 2, images.sharding
    np.testing.assert_allclose(np.asarray(images), alone, rtol=1e-5, atol=1e-5)  # float32
print("ok")
"""


def test_views_sharded_over_two_devices_equal_one_device():
    """Two CPU devices (XLA's host platform device count), views sharded along the batch:
    the images equal the one-device render on the JAX path, which the default settings
    pick with several devices (the host path's callbacks are pinned to device 0 by the
    SPMD partitioner and deadlock with the other device's collectives)."""
    import os
    import subprocess
    import sys

    flags = os.environ.get("XLA_FLAGS", "")  # the suite's compile flags (conftest)
    env = dict(os.environ, XLA_FLAGS=f"{flags} --xla_force_host_platform_device_count=2".strip(),
               JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", SHARDED], capture_output=True, text=True,
                          env=env, timeout=600)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-3000:]
