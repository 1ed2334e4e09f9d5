"""Soft rasterization (raster='soft') against the dense oracle in soft_reference.py, in
float64: the candidate search, the per-fragment geometry, the rendered RGBA for every
shading mode, overflow counting, the hard limit, and silhouette recovery by gradient
descent (translation, scale and rotation about the view axis).

The oracle evaluates every (pixel, face) pair, so the real implementation must equal it
whenever K covers every face that reaches a pixel (asserted through `dropped == 0`).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import reference
from soft_reference import dense_fragments, soft_reference

from diffshade import (
    Mesh,
    RenderSettings,
    ambient_light,
    box,
    directional_light,
    icosphere,
    look_at,
    make_scene,
    material,
    point_light,
    rasterize_scene,
    render,
    render_fragments,
    replace,
    spot_light,
)
from diffshade.numerics import float_dtype
from diffshade.pipeline.shading_cache import cache_shading, render_cached, slot_samples
from diffshade.shading.samples import Reader

pytestmark = pytest.mark.usefixtures("x64")


def soft(**kw):
    return RenderSettings(raster="soft", **kw)


def soft_render(scene, settings):
    """render() without its jit: the tests below try many settings on a few shapes, and
    op-by-op execution (compiled once per shape) is far cheaper than one compile each."""
    return render_fragments(scene, rasterize_scene(scene, settings), settings)


def dense(scene, settings):
    """The oracle's geometry of every (pixel, face) pair, numpy arrays [H, W, F, ...]."""
    return {name: np.asarray(a) for name, a in dense_fragments(scene, settings).items()}


def as_mesh(vertices, faces, normals):
    """Mesh in the current default float dtype (normals are normalized)."""
    dt = float_dtype()
    normals = np.asarray(normals, np.float64)
    normals = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    return Mesh(jnp.asarray(np.asarray(vertices, np.float64), dt),
                jnp.asarray(np.asarray(faces), jnp.int32), jnp.asarray(normals, dt))


def cast_mesh(mesh):
    """A float32 builder's mesh in the current default float dtype."""
    return as_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.normals))


def lights():
    return [ambient_light(0.1), point_light((1.5, 2.0, 3.0), 0.6, attenuation=(1.0, 0.05, 0.01)),
            directional_light((-0.3, -0.5, -1.0), (0.4, 0.3, 0.2)),
            spot_light((0.0, 0.0, 3.0), (0.1, 0.05, -1.0), 0.5, cutoff=25.0, exponent=2.0)]


def shiny():
    return material(ka=0.2, kd=(0.6, 0.5, 0.4), ks=0.4, shininess=16.0, emission=0.02)


def triangles_scene(**kw):
    """Four triangles at several depths, facing the camera well away from edge-on: two
    overlapping large ones, a small clockwise (back-facing) one in front, one cut by the
    image border. Per-vertex normals differ, so Phong and Gouraud interpolation matter."""
    verts = np.array([[-1.2, -1.0, 0.0], [1.1, -0.8, -0.3], [0.1, 1.2, 0.2],
                      [-0.5, -1.3, -0.8], [1.4, 0.4, -0.6], [-0.9, 0.9, -1.0],
                      [0.2, -0.3, 0.8], [-0.4, 0.1, 0.7], [0.4, 0.5, 0.9],
                      [1.0, 0.8, 0.3], [1.9, 1.0, 0.0], [1.3, 1.8, 0.1]])
    normals = verts * np.array([0.4, 0.4, 0.0]) + np.array([0.0, 0.0, 1.0])
    mesh = as_mesh(verts, np.arange(12).reshape(4, 3), normals)
    cam = look_at((0.2, 0.3, 4.0), (0.0, 0.0, 0.0), width=28, height=24, fov_y=40.0)
    return make_scene(mesh, cam, lights(), shiny(), background=(0.1, 0.2, 0.3), **kw)


def sphere_scene(width=24, height=20, **kw):
    """Icosphere (80 faces) with its silhouette in view; back faces are kept."""
    cam = look_at((0.3, 0.2, 3.5), (0.0, 0.0, 0.0), width=width, height=height, fov_y=40.0)
    return make_scene(cast_mesh(icosphere(1)), cam, lights(), shiny(), background=0.1, **kw)


SCENES = {"triangles": triangles_scene, "sphere": sphere_scene}


def covering(scene, **kw):
    """Soft settings whose K covers every face of the scene (at most 40)."""
    return soft(faces_per_pixel=min(scene.mesh.faces.shape[0], 40), **kw)


def assert_matches_oracle(scene, settings):
    frags = rasterize_scene(scene, settings)
    assert int(frags.dropped) == 0
    got = np.asarray(render_fragments(scene, frags, settings))
    np.testing.assert_allclose(got, np.asarray(soft_reference(scene, settings)), rtol=0, atol=1e-5)


def test_jitted_render_is_the_composition_checked_here():
    scene, settings = triangles_scene(), soft(faces_per_pixel=4, sigma=1.5, gamma=1e-3)
    np.testing.assert_allclose(np.asarray(render(scene, settings)),
                               np.asarray(soft_render(scene, settings)), rtol=0, atol=1e-12)


# ------------------------------------------------------------------- render vs the oracle


CASES = [("triangles", "phong", 1.0, 1e-4), ("triangles", "phong", 2.0, 1e-2),
         ("triangles", "phong", 0.3, 1e-3), ("triangles", "gouraud", 1.0, 1e-4),
         ("triangles", "flat", 2.0, 1e-3), ("triangles", "flat_last", 1.0, 1e-2),
         ("sphere", "phong", 1.0, 1e-4), ("sphere", "gouraud", 2.0, 1e-2),
         ("sphere", "flat", 0.5, 1e-3)]


@pytest.mark.parametrize("name, shading, sigma, gamma", CASES)
def test_soft_render_equals_the_dense_oracle(name, shading, sigma, gamma):
    scene = SCENES[name]()
    assert_matches_oracle(scene, covering(scene, shading=shading, sigma=sigma, gamma=gamma))


def test_triangles_scene_has_no_pixel_whose_ray_misses_a_reached_face_plane():
    # guards the purpose of the scene: the sphere has such pairs at its silhouette (see
    # test_clamped_barycentrics_when_the_pixel_ray_misses_the_face_plane), this one has none
    geom = dense(triangles_scene(), soft(sigma=2.0))
    assert np.all(geom["ray_hits_plane"] | ~geom["reach"])
    geom = dense(sphere_scene(), soft(sigma=2.0))
    assert np.any(~geom["ray_hits_plane"] & geom["reach"])


def orthographic(scene):
    cam = look_at((0.2, 0.3, 4.0), (0.0, 0.0, 0.0), width=28, height=24,
                  projection="orthographic", ortho_height=3.5)
    return replace(scene, camera=cam)


def moved(scene):
    rot = np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])
    model = np.eye(4)
    model[:3, :3] = rot @ np.diag([1.1, 0.8, 1.3])
    model[:3, 3] = (0.2, -0.1, 0.3)
    return replace(scene, model=jnp.asarray(model, float_dtype()))


VARIANTS = {
    "two_sided": lambda: triangles_scene(two_sided=True, back_material=material(
        ka=0.1, kd=(0.2, 0.7, 0.3), ks=0.1, shininess=4.0, emission=0.05)),
    "local_viewer": lambda: triangles_scene(local_viewer=True),
    "orthographic": lambda: orthographic(triangles_scene()),
    "model_matrix": lambda: moved(triangles_scene()),
}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_soft_render_equals_the_oracle_for_scene_variants(variant):
    scene = VARIANTS[variant]()
    assert_matches_oracle(scene, covering(scene, sigma=1.5, gamma=1e-3))


# ------------------------------------------------------------------------ cached shading


def other_material():
    return material(ka=(0.1, 0.3, 0.2), kd=(0.2, 0.4, 0.8), ks=0.7, shininess=6.0)


@pytest.mark.parametrize("name, shading, two_sided", [("sphere", "phong", False),
                                                      ("triangles", "gouraud", True),
                                                      ("triangles", "flat", False)])
def test_cached_shading_equals_the_oracle_for_any_material(name, shading, two_sided):
    scene = SCENES[name](two_sided=two_sided)
    # gamma 1e-5: the sphere's back faces get a blend weight of 0 (in float64 too)
    settings = covering(scene, shading=shading, sigma=1.5, gamma=1e-5)
    frags = rasterize_scene(scene, settings)
    cache = cache_shading(scene, frags, settings)
    if name == "sphere":  # only the fragments with a non-zero blend weight are kept
        assert 0 < cache.pixels.shape[0] < int(np.sum(np.asarray(frags.valid)))
    for s in (scene, replace(scene, material=other_material())):
        np.testing.assert_allclose(np.asarray(render_cached(s, cache, settings)),
                                   np.asarray(soft_reference(s, settings)), rtol=0, atol=1e-5)


def test_cached_shading_in_hard_mode_equals_the_reference():
    scene = replace(sphere_scene(), material=other_material())
    settings = RenderSettings()
    cache = cache_shading(scene, rasterize_scene(scene, settings), settings)
    ref, frags = reference.render(scene)
    clear = frags.edge_dist > 1e-6
    np.testing.assert_allclose(np.asarray(render_cached(scene, cache, settings))[clear],
                               ref[clear], rtol=0, atol=1e-9)


def test_cached_shading_gradients_equal_central_differences():
    scene = sphere_scene()
    settings = soft(faces_per_pixel=8, sigma=1.0, gamma=1e-3)
    cache = cache_shading(scene, rasterize_scene(scene, settings), settings)
    weights = jnp.asarray(np.random.default_rng(3).normal(size=(20, 24, 4)))

    def loss(kd, shininess, colour):
        light = replace(scene.lights, point=replace(scene.lights.point, diffuse=colour))
        s = replace(scene, lights=light,
                    material=replace(scene.material, kd=kd, shininess=shininess))
        return jnp.sum(weights * render_cached(s, cache, settings))
    args = (scene.material.kd, scene.material.shininess, scene.lights.point.diffuse)
    grads = jax.grad(loss, argnums=(0, 1, 2))(*args)
    eps = 1e-6
    for i, (arg, grad) in enumerate(zip(args, grads, strict=True)):
        flat = np.asarray(arg, np.float64).reshape(-1)
        for j in range(flat.size):
            step = np.zeros_like(flat)
            step[j] = eps
            shifted = [list(args), list(args)]
            shifted[0][i] = jnp.asarray((flat + step).reshape(np.shape(arg)))
            shifted[1][i] = jnp.asarray((flat - step).reshape(np.shape(arg)))
            want = (loss(*shifted[0]) - loss(*shifted[1])) / (2 * eps)
            np.testing.assert_allclose(np.asarray(grad).reshape(-1)[j], want, rtol=1e-6,
                                       atol=1e-8)


@pytest.mark.parametrize("weighted", [False, True])
def test_slot_samples_keep_what_the_chosen_fragments_read(weighted):
    """Against a loop over the chosen fragments: each reads, from the kept samples through
    the new Reader, the weighted sum of the samples its table row names; only read
    samples are kept."""
    rng = np.random.default_rng(7)
    values = rng.normal(size=(9, 2))
    table = rng.integers(0, 9, size=(6, 3)) if weighted else rng.integers(0, 9, size=(6, 1))
    ids = rng.integers(0, 6, size=(2, 3, 4))
    weights = rng.random(ids.shape + table.shape[1:]) if weighted else None
    slots = np.array([3, 17, 8, 22, 0], np.int32)
    (kept,), reader = slot_samples([values], Reader(ids, weights, table), slots, (5, 1, 1))
    for m, slot in enumerate(slots):
        row = table[ids.reshape(-1)[slot]]
        w = np.ones(1) if weights is None else weights.reshape(-1, 3)[slot]
        got_w = np.ones(1) if reader.weights is None else reader.weights.reshape(5, -1)[m]
        got = sum(got_w[g] * kept[reader.table[reader.ids.reshape(-1)[m], g]]
                  for g in range(row.size))
        np.testing.assert_allclose(got, sum(w[g] * values[row[g]] for g in range(row.size)))
    assert len(kept) == len(np.unique(table[ids.reshape(-1)[slots]]))


def test_cached_shading_rejects_a_transparent_scene():
    scene = replace(triangles_scene(), material=material(kd=0.5, kt=0.3))
    settings = soft(faces_per_pixel=4)
    with pytest.raises(ValueError, match="transparent"):
        cache_shading(scene, rasterize_scene(scene, settings), settings)


def test_culling_rules_match_the_oracle():
    # a face crossing the near plane (culled in soft mode), a zero-area face (skipped), and
    # back faces dropped by cull_backfaces
    scene = triangles_scene()
    verts = np.concatenate([np.asarray(scene.mesh.vertices),
                            [[-0.5, 0.0, 4.5], [0.5, 0.0, 3.0], [0.0, 0.5, 3.0],
                             [0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [0.6, 0.6, 0.5]]])
    normals = np.concatenate([np.asarray(scene.mesh.normals), np.tile([0.0, 0.0, 1.0], (6, 1))])
    mesh = as_mesh(verts, np.arange(18).reshape(6, 3), normals)
    for cull in (False, True):
        culled = replace(scene, mesh=mesh)
        settings = covering(culled, sigma=1.0, gamma=1e-3, cull_backfaces=cull)
        ids = np.asarray(rasterize_scene(culled, settings).face_ids)
        assert not np.isin([4, 5], ids).any()
        assert np.isin(2, ids).any() != cull
        assert_matches_oracle(culled, settings)


# ------------------------------------------------------------- fragments vs dense geometry


def fragments_and_dense(scene, settings):
    frags = rasterize_scene(scene, settings)
    geom = dense(scene, settings)
    ids = np.asarray(frags.face_ids)
    rows, cols = np.indices(ids.shape[:2])
    at_ids = {k: v[rows[..., None], cols[..., None], np.maximum(ids, 0)] for k, v in geom.items()}
    return frags, ids, geom, at_ids


def chosen(ids, num_faces):
    """[H, W, K] face ids -> [H, W, F] bool: the face is a candidate of the pixel."""
    mask = np.zeros(ids.shape[:2] + (num_faces,), bool)
    rows, cols, _ = np.nonzero(ids >= 0)
    mask[rows, cols, ids[ids >= 0]] = True
    return mask


@pytest.mark.parametrize("name", ["triangles", "sphere"])
def test_candidates_are_the_faces_within_reach_heaviest_first(name):
    scene = SCENES[name]()
    settings = covering(scene, sigma=2.0)
    frags, ids, geom, at_ids = fragments_and_dense(scene, settings)
    assert int(frags.dropped) == 0
    np.testing.assert_array_equal(chosen(ids, geom["reach"].shape[-1]), geom["reach"])
    # ranked by weight in the blend, log D + zt / gamma (for small gamma: nearest first)
    both = (ids[..., 1:] >= 0) & (ids[..., :-1] >= 0)
    assert np.all(np.diff(at_ids["logit"], axis=-1)[both] <= 1e-9)


@pytest.mark.parametrize("name", ["triangles", "sphere"])
def test_signed_distance_matches_the_dense_geometry(name):
    scene = SCENES[name]()
    frags, ids, _, at_ids = fragments_and_dense(scene, covering(scene, sigma=2.0))
    valid = ids >= 0
    np.testing.assert_allclose(np.asarray(frags.dist)[valid], at_ids["dist"][valid], atol=1e-9)


def test_edge_distances_side_by_side_equal_one_edge_at_a_time():
    """The geometry kernel's three edge distances in one vector (_edge_dist2) against
    _segment, which the backward uses for the nearest edge, one edge at a time: the same
    numbers bit for bit, for points inside, outside, on a corner and far away, a
    degenerate face (a zero-length edge and a point) and a coordinate that is NaN."""
    import numba

    from diffshade.host import fragment_kernels as kernels

    @numba.njit(fastmath={"contract"})
    def both(table, points):
        out = np.empty((2, points.shape[0], table.shape[0], 3))
        for p in range(points.shape[0]):
            px, py = points[p, 0], points[p, 1]
            for f in range(table.shape[0]):
                out[0, p, f, 0], out[0, p, f, 1], out[0, p, f, 2] = kernels._edge_dist2(
                    table, f, px, py)
                for i in range(3):
                    out[1, p, f, i] = kernels._segment(px, py, table, f, i)[0]
        return out

    rng = np.random.default_rng(3)
    scr = np.concatenate([rng.uniform(-5.0, 40.0, (30, 3, 2)),
                          [[[3.0, 4.0], [3.0, 4.0], [9.0, 1.5]],     # a zero-length edge
                           [[2.0, 2.0], [2.0, 2.0], [2.0, 2.0]],     # a point
                           [[1e7, 0.5], [-1e7, 3.5], [0.5, 1e-9]]]])  # long and thin
    faces = scr.shape[0]
    table = kernels._face_table(np.ones((faces, 3)), np.ones((faces, 3)),
                                rng.normal(size=(faces, 3, 3)), scr, 1e-300)
    points = np.concatenate([rng.uniform(-20.0, 60.0, (200, 2)), scr[:, 0], scr.mean(1),
                             [[1e9, -1e9], [np.nan, 1.0]]])
    vector, scalar = both(table, points)
    np.testing.assert_array_equal(vector, scalar)
    assert np.isnan(vector[-1]).all() and np.isfinite(vector[:-1]).all()


@pytest.mark.parametrize("name", ["triangles", "sphere"])
def test_clamped_barycentrics_and_depth_match_the_dense_geometry(name):
    scene = SCENES[name]()
    frags, ids, _, at_ids = fragments_and_dense(scene, covering(scene, sigma=2.0))
    valid = ids >= 0
    np.testing.assert_allclose(np.asarray(frags.bary)[valid], at_ids["bary"][valid], atol=1e-9)
    np.testing.assert_allclose(np.asarray(frags.depth)[valid], at_ids["depth"][valid], rtol=1e-9)


def test_clamped_barycentrics_when_the_pixel_ray_misses_the_face_plane():
    # A floor triangle seen almost edge-on: the eye is 0.1 above its plane y = -0.1, the
    # near edge at depth 2 and the apex at depth 30 (screen row ~12.1, just below the
    # horizon y = 12). Pixel (11, 12) lies 0.64 px above the apex, within the footprint,
    # and above the horizon: its eye ray never meets the plane in front of the eye. The
    # point of the triangle that reaches it is the apex (screen-space clamped barycentrics
    # (0, 0, 1), depth 30); clamping the perspective-correct barycentrics instead (whose
    # signs all flip there) lands on the near edge, at depth 2.
    verts = [[-1.0, -0.1, -2.0], [1.0, -0.1, -2.0], [0.0, -0.1, -30.0]]
    mesh = as_mesh(verts, [[0, 1, 2]], np.tile([0.0, 1.0, 0.0], (3, 1)))
    scene = make_scene(mesh, look_at((0, 0, 0), (0, 0, -1), width=24, height=24))
    frags, ids, geom, _ = fragments_and_dense(scene, soft(faces_per_pixel=1))
    assert ids[11, 12, 0] == 0 and not geom["ray_hits_plane"][11, 12, 0]
    np.testing.assert_allclose(geom["bary"][11, 12, 0], [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(np.asarray(frags.bary)[11, 12, 0], [0.0, 0.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(float(frags.depth[11, 12, 0]), 30.0, rtol=1e-9)


# ------------------------------------------------------------------------------- overflow


@pytest.mark.parametrize("k", [1, 4])
def test_overflow_is_counted_and_the_heaviest_faces_are_kept(k):
    scene = sphere_scene()
    settings = soft(faces_per_pixel=k, sigma=2.0)
    frags, ids, geom, at_ids = fragments_and_dense(scene, settings)
    # the oracle's count: (pixel, face) pairs within reach beyond the K kept per pixel
    counts = geom["reach"].sum(-1)
    want = int(np.maximum(counts - k, 0).sum())
    assert want > 0
    assert int(frags.dropped) == want
    # each pixel keeps min(K, reached) faces, none lighter in the blend than a dropped one
    np.testing.assert_array_equal((ids >= 0).sum(-1), np.minimum(counts, k))
    kept_light = np.min(np.where(ids >= 0, at_ids["logit"], np.inf), -1)
    dropped = geom["reach"] & ~chosen(ids, geom["reach"].shape[-1])
    dropped_heavy = np.max(np.where(dropped, geom["logit"], -np.inf), -1)
    assert np.all(kept_light >= dropped_heavy - 1e-9)


def test_tied_fragments_keep_the_lower_face_id_first():
    """Every face listed twice: the copies reach the same pixels with bit-identical keys.
    The search visits faces front to back, in no fixed order among equal depths, and still
    lists the lower id of a tie first; with K too small for both copies, it keeps that
    one. Checked against the dense oracle's reach and the tie rule, not against itself."""
    base = icosphere(2)
    mesh = as_mesh(np.asarray(base.vertices), np.tile(np.asarray(base.faces), (2, 1)),
                   np.asarray(base.normals))
    count = base.faces.shape[0]
    scene = make_scene(mesh, sphere_scene().camera, lights(), shiny())
    most = int(dense(scene, soft(sigma=2.0))["reach"].sum(-1).max())
    for k in (most, 3):
        frags, ids, geom, _ = fragments_and_dense(scene, soft(faces_per_pixel=k, sigma=2.0))
        reach = geom["reach"]
        np.testing.assert_array_equal(reach[..., :count], reach[..., count:])
        assert int(frags.dropped) == int(np.maximum(reach.sum(-1) - k, 0).sum())
        kept = chosen(ids, 2 * count)
        # position of each face in its pixel's list (k: not kept)
        slot = np.full(kept.shape, k)
        rows, cols, slots = np.nonzero(ids >= 0)
        slot[rows, cols, ids[rows, cols, slots]] = slots
        if k == most:
            np.testing.assert_array_equal(kept, reach)
        pairs = kept[..., count:]
        assert pairs.sum() > 100
        assert np.all(slot[..., :count][pairs] < slot[..., count:][pairs])
        assert np.all(kept[..., :count][pairs])


@pytest.mark.parametrize("sigma, tier", [(0.05, 3), (0.15, 4), (0.2, None)])
def test_phong_blend_of_the_active_slots_equals_the_oracle_in_each_branch(sigma, tier):
    """The Phong soft render lights only the slots of non-zero weight and sums their
    weighted colours per pixel (rendering.blended_colour): with at most 3 or 4 active
    slots per pixel on average (the compacted branches) or more (every slot), on a
    non-square image, the image and its gradients with respect to the material and the
    vertices equal the dense oracle's (which blends all H x W x F pairs)."""
    from diffshade.pipeline.rendering import ACTIVE_SLOTS_PER_PIXEL, blend_weights

    scene = sphere_scene()
    settings = soft(faces_per_pixel=20, sigma=sigma, gamma=1e-4, shading="phong")
    frags = rasterize_scene(scene, settings)
    assert int(frags.dropped) == 0
    active = int((np.asarray(blend_weights(scene, frags, settings)[0]) > 0.0).sum())
    pixels = scene.camera.width * scene.camera.height
    branch = next((t for t in sorted(ACTIVE_SLOTS_PER_PIXEL) if active <= t * pixels), None)
    assert branch == tier, (active / pixels, branch)
    target = np.random.default_rng(3).uniform(size=(20, 24, 4))

    def loss(render_fn, kd, vertices):
        moved = replace(scene, material=replace(scene.material, kd=kd),
                        mesh=replace(scene.mesh, vertices=vertices))
        return jnp.sum((render_fn(moved, settings) - target) ** 2)
    args = (scene.material.kd, scene.mesh.vertices)
    np.testing.assert_allclose(np.asarray(render(scene, settings)),
                               np.asarray(soft_reference(scene, settings)), rtol=0, atol=1e-5)
    got = jax.jit(jax.grad(lambda *a: loss(render, *a), argnums=(0, 1)))(*args)
    want = jax.grad(lambda *a: loss(soft_reference, *a), argnums=(0, 1))(*args)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-4,
                                   atol=1e-6 * float(np.abs(np.asarray(w)).max()))


def test_overflowing_render_equals_the_oracle_on_the_kept_faces():
    scene, k = triangles_scene(), 2
    settings = soft(faces_per_pixel=k, sigma=1.0, gamma=1e-3)
    assert int(rasterize_scene(scene, settings).dropped) > 0
    np.testing.assert_allclose(np.asarray(soft_render(scene, settings)),
                               np.asarray(soft_reference(scene, settings, k=k)), atol=1e-5)


# ----------------------------------------------------------------------------- hard limit


def image_error(a, b):
    """(mean |a - b| over RGBA, fraction of pixels with a channel off by more than 1/255)."""
    diff = np.abs(np.asarray(a) - np.asarray(b))
    return float(diff.mean()), float(np.mean(diff.max(-1) > 1.0 / 255.0))


def test_soft_converges_to_hard_as_sigma_and_gamma_shrink():
    scene = sphere_scene()
    hard = render_fragments(scene, rasterize_scene(scene, RenderSettings()), RenderSettings())
    # the pixels that still differ at the end (7 of 480) are those whose centre lies within
    # the footprint radius (0.03 px at sigma 1e-4) of the silhouette
    errors = [image_error(soft_render(scene, covering(scene, sigma=s, gamma=g)), hard)
              for s, g in [(1.0, 1e-2), (1e-1, 1e-3), (1e-2, 1e-4), (1e-3, 1e-5), (1e-4, 1e-6)]]
    mean_abs, frac = np.array(errors).T
    assert np.all(np.diff(mean_abs) < 0), mean_abs
    assert np.all(np.diff(frac) < 0), frac
    assert mean_abs[-1] < 5e-4 and frac[-1] < 0.02, errors[-1]


# -------------------------------------------------------------------- silhouette recovery
#
# In float32 (the dtype fitting runs in), 32 x 32 pixels, where 1 world unit is ~13 px.


def fit(loss, params, steps, lr):
    """Adam with a cosine-decayed step (so that it settles instead of circling the optimum)."""
    opt = optax.adam(optax.cosine_decay_schedule(lr, steps))

    @jax.jit
    def step(params, state):
        updates, state = opt.update(jax.grad(loss)(params), state, params)
        return optax.apply_updates(params, updates), state

    state = opt.init(params)
    for _ in range(steps):
        params, state = step(params, state)
    return params


SIL = soft(faces_per_pixel=8, sigma=4.0, gamma=1e-2, cull_backfaces=True)


def recover(mesh, place, truth, start, lr, steps=80):
    """Fit the parameters of place(params) -> scene to the alpha of place(truth)."""
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=32, height=32, fov_y=45.0)
    scene = make_scene(mesh, cam, [directional_light((0.0, 0.0, -1.0))])
    target = render(place(scene, truth), SIL)[..., 3]

    def loss(params):
        return jnp.mean((render(place(scene, params), SIL)[..., 3] - target) ** 2)
    return fit(loss, start, steps, lr)


def with_model(scene, linear, translate):
    """scene with the model matrix [linear translate; 0 0 0 1] (linear [3, 3], translate [3])."""
    top = jnp.concatenate([linear, translate[:, None]], 1)
    return replace(scene, model=jnp.concatenate([top, jnp.eye(4, dtype=top.dtype)[3:]], 0))


def rotation_z(angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, nil = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, -s, nil]), jnp.stack([s, c, nil]), jnp.stack([nil, nil, one])])


def test_translation_is_recovered_from_the_silhouette():
    # the start is off by about (3, -2.5) px
    with jax.enable_x64(False):
        place = lambda scene, t: with_model(scene, jnp.eye(3), jnp.append(t, 0.0))
        truth = jnp.array([0.1, -0.05])
        found = recover(icosphere(1, radius=0.5), place, truth, truth + jnp.array([0.25, -0.2]),
                        lr=0.03)
        np.testing.assert_allclose(np.asarray(found), np.asarray(truth), atol=0.01)


def test_uniform_scale_is_recovered_from_the_silhouette():
    # radius 0.6 (about 8 px): the start, scale 0.75, is 2 px short all around
    with jax.enable_x64(False):
        place = lambda scene, log_s: with_model(scene, jnp.exp(log_s) * jnp.eye(3), jnp.zeros(3))
        found = recover(icosphere(1, radius=0.6), place, jnp.float32(0.0),
                        jnp.log(jnp.float32(0.75)), lr=0.05)
        np.testing.assert_allclose(float(jnp.exp(found)), 1.0, atol=0.01)


def test_rotation_about_the_view_axis_is_recovered_from_the_silhouette():
    # a 1.2 x 0.5 slab has no rotational symmetry below 180 degrees; starting 17 degrees
    # off moves its ends by about 2 px
    with jax.enable_x64(False):
        place = lambda scene, angle: with_model(scene, rotation_z(angle), jnp.zeros(3))
        truth = math.radians(25.0)
        found = recover(box((1.2, 0.5, 0.2)), place, jnp.float32(truth),
                        jnp.float32(truth - 0.3), lr=0.03)
        assert abs(math.degrees(float(found) - truth)) < 0.5
