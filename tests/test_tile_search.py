"""search_tiles (pure-JAX tile-binned candidate search) against the host kernel
candidates.find_candidates, an independent implementation, in float64: face ids and
`dropped` must be equal exactly, hard and soft, with and without back-face culling, for
several K, image sizes that are not multiples of the tile, a mesh crossing the near plane
and an orthographic camera; tiles touched by more faces than their capacity are searched in
several passes (and a dense mesh through RenderSettings.kernels renders the host's image);
traced parameters under jit, vmap over cameras and use inside grad. The host search's
batch form (several views in one call, under vmap) against one call per view.
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compiles

from diffshade import (
    Mesh,
    icosphere,
    look_at,
    make_scene,
    model_matrix,
    project,
    rasterize_scene,
    render,
    torus,
)
from diffshade.host.candidates import find_candidates
from diffshade.raster.search import search_faces
from diffshade.raster.tile_search import search_tiles
from diffshade.settings import RenderSettings

pytestmark = pytest.mark.usefixtures("x64")

STATIC = ("width", "height", "k", "soft", "cull_backfaces", "perspective", "tile", "capacity")
search = jax.jit(search_tiles, static_argnames=STATIC)
#: (radius_px, sigma, gamma) of the soft cases: sharp, blurry with a flat depth weight, in
#: between
SOFT = ((1.5, 0.5, 1e-4), (2.5, 1.0, 1.0), (1.0, 0.1, 0.01))


def sphere(width=37, height=29):
    cam = look_at((0.4, 0.6, 3.5), (0.0, 0.0, 0.0), width=width, height=height, fov_y=45.0)
    model = model_matrix((0.1, -0.1, 0.0), (20.0, 30.0, 10.0), (1.2, 0.8, 1.0))
    return make_scene(icosphere(2), cam, model=model)


def ring():
    cam = look_at((0.3, 2.0, 2.5), (0.0, 0.0, 0.0), width=50, height=40, fov_y=45.0)
    return make_scene(torus(), cam)


def through_near_plane():
    """The eye 2 from a unit sphere's centre with near = 1.2: the near plane cuts off the
    middle of the visible cap (depths 1 to 1.5) and leaves a ring of front faces."""
    cam = look_at((0.4, 0.5, 1.89), (0.0, 0.0, 0.0), width=40, height=33, fov_y=70.0,
                  near=1.2)
    return make_scene(icosphere(2), cam)


def orthographic():
    cam = look_at((0.4, 0.6, 3.5), (0.0, 0.0, 0.0), width=33, height=40,
                  projection="orthographic", ortho_height=3.0)
    return make_scene(icosphere(2), cam)


SCENES = {"sphere": sphere, "torus": ring, "near_plane": through_near_plane,
          "orthographic": orthographic}
KS = {"sphere": (1, 4, 8), "torus": (4,), "near_plane": (8,), "orthographic": (1,)}


def host(scene, k, cull, radius_px=0.0, sigma=1.0, gamma=1e-4):
    cam = scene.camera
    return find_candidates(np.asarray(project(scene).clip), np.asarray(scene.mesh.faces),
                           float(cam.near), float(cam.far), width=cam.width,
                           height=cam.height, k=k, cull_backfaces=cull, radius_px=radius_px,
                           sigma=sigma, gamma=gamma,
                           perspective=cam.projection == "perspective")


def device(scene, k, cull, soft, radius_px=0.0, sigma=1.0, gamma=1e-4, tile=8, capacity=512):
    """search_tiles, by default with small tiles and room for every face (these scenes
    put up to a few hundred faces in a tile)."""
    cam = scene.camera
    ids, dropped = search(project(scene).clip, scene.mesh.faces, cam.near, cam.far, radius_px,
                          sigma, gamma, width=cam.width, height=cam.height, k=k, soft=soft,
                          cull_backfaces=cull, perspective=cam.projection == "perspective",
                          tile=tile, capacity=capacity)
    return np.asarray(ids), int(dropped)


def assert_same(got, want, near_ties=False):
    """Face ids and drop counts equal. near_ties (soft ranking): XLA's exp and log1p may
    differ from libm's in the last bit, so two keys within an ulp can swap places; then
    every pixel must still hold the same faces, and the order may differ only by swaps of
    neighbouring slots, in at most 0.1% of the slots."""
    got_ids, want_ids = np.asarray(got[0]), np.asarray(want[0])
    assert got[1] == want[1]
    if not near_ties:
        np.testing.assert_array_equal(got_ids, want_ids)
        return
    np.testing.assert_array_equal(np.sort(got_ids, -1), np.sort(want_ids, -1))
    differ = got_ids != want_ids
    assert differ.sum() <= max(2, differ.size // 1000), differ.sum()
    for pixel in zip(*np.nonzero(differ.any(-1)), strict=True):
        slots = np.flatnonzero(differ[pixel])
        assert len(slots) == 2 and slots[1] == slots[0] + 1, (pixel, got_ids[pixel],
                                                                want_ids[pixel])


@pytest.mark.parametrize("cull", [False, True])
@pytest.mark.parametrize("name", SCENES)
def test_hard_equals_host(name, cull):
    scene = SCENES[name]()
    for k in KS[name]:
        want = host(scene, k, cull)
        assert (want[0] >= 0).any()
        assert_same(device(scene, k, cull, soft=False), want)


@pytest.mark.parametrize("cull", [False, True])
@pytest.mark.parametrize("name", SCENES)
def test_soft_equals_host(name, cull):
    scene = SCENES[name]()
    for k in KS[name]:
        for radius, sigma, gamma in SOFT:
            want = host(scene, k, cull, radius, sigma, gamma)
            assert_same(device(scene, k, cull, True, radius, sigma, gamma), want,
                        near_ties=True)


def test_near_plane_scene_crosses_it():
    """The near-plane scene really has faces with corners on both sides of Z + W = 0."""
    scene = through_near_plane()
    clip = np.asarray(project(scene).clip)
    side = (clip[:, 2] + clip[:, 3] >= 0)[np.asarray(scene.mesh.faces)]
    assert (side.any(1) & ~side.all(1)).any()


def test_k_beyond_capacity_pads_with_empty_slots():
    """K = 8 from lists of 4 faces: the last slots stay empty (the 4 triangles of a
    square, each pixel covered by one)."""
    verts = jnp.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0],
                       [-1.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    faces = jnp.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    scene = make_scene(Mesh(verts, faces, jnp.tile(jnp.array([0.0, 0.0, 1.0]), (5, 1))),
                       look_at((0.1, 0.2, 3.0), (0.0, 0.0, 0.0), width=21, height=18))
    want = host(scene, 8, False)
    assert (want[0][..., 0] >= 0).sum() > 100
    assert_same(device(scene, 8, False, soft=False, capacity=4), want)


def tile_pairs(scene, tile):
    """Per tile, how many faces' screen boxes touch it: [tiles]. The torus lies in front
    of the eye, so a face's box is its corners' NDC box (no near clipping)."""
    cam = scene.camera
    clip = np.asarray(project(scene).clip)[np.asarray(scene.mesh.faces)]
    ndc = clip[..., :2] / clip[..., 3:]
    lo, hi = ndc.min(1), ndc.max(1)
    size = np.array([cam.width, cam.height])
    lo, hi = np.where([True, False], lo, -hi), np.where([True, False], hi, -lo)  # rows: y down
    first = np.maximum(np.ceil((lo + 1.0) * size / 2.0 - 0.5), 0)
    last = np.minimum(np.floor((hi + 1.0) * size / 2.0 - 0.5), size - 1)
    counts = []
    for row in range(0, cam.height, tile):
        for col in range(0, cam.width, tile):
            start, end = np.array([col, row]), np.array([col, row]) + tile - 1
            counts.append(np.all((first <= end) & (last >= start) & (first <= last), 1).sum())
    return np.array(counts)


def test_tiles_beyond_capacity_take_more_passes_and_equal_the_host():
    """With capacity 32, crowded torus tiles hold up to several times as many faces: they
    are searched in passes of 32, and every pixel equals the host's, hard and soft."""
    scene, capacity, tile = ring(), 32, 16
    assert tile_pairs(scene, tile).max() > 3 * capacity
    for k in (1, 8):
        want = host(scene, k, False)
        assert_same(device(scene, k, False, soft=False, tile=tile, capacity=capacity), want)
    radius, sigma, gamma = SOFT[1]
    want = host(scene, 8, False, radius, sigma, gamma)
    assert want[1] > 0
    assert_same(device(scene, 8, False, True, radius, sigma, gamma, tile=tile,
                       capacity=capacity), want, near_ties=True)


@pytest.mark.parametrize("raster", ["hard", "soft"])
def test_the_jax_path_renders_the_host_image_of_a_dense_mesh(raster):
    """5,120 faces in 64 x 64 pixels, as many as 4 per pixel in the tiles of the default
    search (RenderSettings.kernels 'jax' against 'host', float64): the same face ids,
    drop counts and image, with soft raster's default footprint too."""
    scene = make_scene(icosphere(4), look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=64,
                                             height=64, fov_y=45.0))
    paths = {kernels: RenderSettings(raster=raster, kernels=kernels)
             for kernels in ("host", "jax")}
    frags = {name: rasterize_scene(scene, s) for name, s in paths.items()}
    assert int(frags["host"].dropped) == int(frags["jax"].dropped) > 0
    np.testing.assert_array_equal(frags["jax"].face_ids, frags["host"].face_ids)
    np.testing.assert_allclose(render(scene, paths["jax"]), render(scene, paths["host"]),
                               atol=1e-12)


def test_jit_with_traced_parameters_equals_eager():
    scene = sphere()
    cam = scene.camera
    clip, faces = project(scene).clip, scene.mesh.faces
    static = {"width": cam.width, "height": cam.height, "k": 4, "soft": True, "capacity": 512}
    eager = search_tiles(clip, faces, cam.near, cam.far, 1.5, 0.5, 1e-3, **static)
    jitted = jax.jit(partial(search_tiles, **static))
    with compiles() as counted:
        for radius, sigma, gamma in ((1.5, 0.5, 1e-3), (2.5, 2.0, 0.1)):
            got = jitted(clip, faces, cam.near, cam.far, jnp.asarray(radius),
                         jnp.asarray(sigma), jnp.asarray(gamma))
            want = host(scene, 4, False, radius, sigma, gamma)
            assert_same((np.asarray(got[0]), int(got[1])), want, near_ties=True)
    assert counted.of("search_tiles") == 1  # the first call's; new values reuse it
    np.testing.assert_array_equal(eager[0], host(scene, 4, False, 1.5, 0.5, 1e-3)[0])


def test_vmap_over_cameras_equals_separate_calls():
    scenes = [sphere(), make_scene(icosphere(2), look_at((-1.0, 0.5, 2.5), (0.1, 0.0, 0.0),
                                                        width=37, height=29))]
    clips = jnp.stack([project(s).clip for s in scenes])
    cam = scenes[0].camera
    batched = jax.vmap(lambda clip: search_tiles(
        clip, scenes[0].mesh.faces, cam.near, cam.far, 2.0, 1.0, 1e-3, width=37, height=29,
        k=4, soft=True, capacity=512))(clips)
    for i, scene in enumerate(scenes):
        want = device(scene, 4, False, True, 2.0, 1.0, 1e-3)
        assert_same((np.asarray(batched[0][i]), int(batched[1][i])), want)
        assert_same(want, host(scene, 4, False, 2.0, 1.0, 1e-3), near_ties=True)


def test_usable_inside_grad():
    """A loss that picks faces with search_tiles differentiates through the chosen faces'
    geometry only; the ids are constants (integer outputs)."""
    scene = sphere()
    cam, faces = scene.camera, scene.mesh.faces

    def corner_w_sum(clip, ids):
        corner_w = clip[faces[jnp.maximum(ids[..., 0], 0)], 3]
        return jnp.sum(jnp.where(ids[..., :1] >= 0, corner_w, 0.0))

    def loss(clip):
        ids, _ = search_tiles(clip, faces, cam.near, cam.far, 0.0, 1.0, 1e-4,
                              width=cam.width, height=cam.height, k=1, soft=False,
                              capacity=512)
        return corner_w_sum(clip, ids)

    clip = project(scene).clip
    ids = jnp.asarray(device(scene, 1, False, soft=False)[0])
    grad = jax.jit(jax.grad(loss))(clip)
    np.testing.assert_array_equal(grad, jax.grad(corner_w_sum)(clip, ids))
    assert np.isfinite(grad).all() and np.abs(grad).sum() > 0


def test_host_search_batch_equals_one_call_per_view():
    """find_candidates' batch form (views x bands in one parallel loop), with per-view
    near, far, radius, sigma and gamma, hard and soft: the ids and drop counts of separate
    calls, exactly."""
    near_plane = dataclasses.replace(through_near_plane().camera, width=37, height=29)
    scenes = [sphere(), make_scene(icosphere(2), near_plane), make_scene(icosphere(2), look_at(
        (-1.0, 0.5, 2.5), (0.1, 0.0, 0.0), width=37, height=29, near=0.5, far=20.0))]
    clips = np.stack([np.asarray(project(s).clip) for s in scenes])
    near = np.array([float(s.camera.near) for s in scenes])
    far = np.array([float(s.camera.far) for s in scenes])
    faces = np.asarray(scenes[0].mesh.faces)
    for radius, sigma, gamma in (((0.0,) * 3, 1.0, 1e-4), ((1.5, 2.5, 1.0), (0.5, 1.0, 0.1),
                                                           (1e-4, 1.0, 0.01))):
        got = find_candidates(clips, faces, near, far, width=37, height=29, k=4,
                              radius_px=np.array(radius), sigma=sigma, gamma=gamma)
        assert got[0].shape == (3, 29, 37, 4) and got[1].shape == (3,)
        for i in range(3):
            want = find_candidates(clips[i], faces, near[i], far[i], width=37, height=29, k=4,
                                   radius_px=radius[i], sigma=np.broadcast_to(sigma, 3)[i],
                                   gamma=np.broadcast_to(gamma, 3)[i])
            assert (want[0] >= 0).any()
            assert_same((got[0][i], got[1][i]), want)


def test_host_search_under_vmap_equals_separate_calls():
    """search_faces on the host path under vmap: views of one mesh go to the kernel in one
    call, a batch of different meshes (faces batched) one mesh at a time; both give the
    unbatched results."""
    settings = RenderSettings(raster="soft", kernels="host")
    cams = [look_at(eye, (0.0, 0.0, 0.0), width=23, height=19, fov_y=45.0)
            for eye in ((0.4, 0.6, 3.5), (-1.0, 0.5, 2.5))]
    mesh = icosphere(2)
    # another mesh of the same size: the same triangles listed in reverse order
    meshes = [mesh, Mesh(mesh.vertices, mesh.faces[::-1], mesh.normals)]
    run = lambda clip, faces, cam: search_faces(clip, faces, cam, 4, settings, True)
    clip = lambda mesh, cam: project(make_scene(mesh, cam)).clip
    for vary_mesh in (False, True):
        pairs = [(meshes[i] if vary_mesh else mesh, cams[i]) for i in range(2)]
        clips = jnp.stack([clip(m, c) for m, c in pairs])
        faces = jnp.stack([m.faces for m, _ in pairs])
        stacked = jax.tree.map(lambda *a: jnp.stack(a), *cams)
        got = jax.jit(jax.vmap(run))(clips, faces, stacked)
        for i, (m, c) in enumerate(pairs):
            want = jax.jit(run)(clip(m, c), m.faces, c)
            assert (np.asarray(want[0]) >= 0).any()
            assert_same((np.asarray(got[0][i]), int(got[1][i])),
                        (np.asarray(want[0]), int(want[1])))


def test_host_softplus_is_within_half_an_ulp_of_one_of_libms():
    """The host soft key's log1p(exp(-a)) (candidates._softplus_neg, a polynomial that LLVM
    vectorizes) against libm's (Python's math.log1p and math.exp) on a dense grid of a:
    within 5e-16, and never negative (the key's bounds rely on it)."""
    import math

    import numba

    from diffshade.host.candidates import _softplus_neg

    @numba.njit
    def worst(a):
        error, lowest = 0.0, np.inf
        for v in a:
            u = _softplus_neg(v)
            error, lowest = max(error, abs(u - math.log1p(math.exp(-v)))), min(lowest, u)
        return error, lowest

    grid = np.concatenate([np.linspace(0.0, 40.0, 2_000_001), np.linspace(0.0, 1e-3, 100_001),
                           np.linspace(36.0, 800.0, 10_001), [1e-300, 5e-324, 1e4, 1e300]])
    error, lowest = worst(grid)
    assert error <= 5e-16 and lowest >= 0.0, (error, lowest)


def test_host_soft_key_against_libm():
    """The host soft key (candidates._fragment_key) of depth parts from 0 (and -0.0,
    subnormal) to -1e6 and coverage terms on both sides of the edge (-0.0 included)
    against depth - log_sigmoid(x) computed in Python with libm: within the polynomial's
    5e-16 plus the sums' roundings on both sides, at least the depth part, and
    outside (x < 0) at least depth - x, the bounds that drop fragments before their keys."""
    import math

    from diffshade.host.candidates import _fragment_key

    rng = np.random.default_rng(5)
    depths = np.concatenate([[0.0, -0.0, -5e-324, -1e-310, -1e-300, -1e-12, -0.5, -1.0],
                             -10.0 ** rng.uniform(-8, 6, 400)])
    xs = np.concatenate([[0.0, -0.0, 36.0, -36.0, 40.0, -40.0, 745.0, -800.0],
                         rng.uniform(-12, 12, 300), rng.uniform(-60, 80, 200)])
    checked = 0
    for depth in depths:
        for x, sigma in zip(rng.choice(xs, 60), rng.choice([0.05, 0.75, 1.0, 3.0], 60),
                            strict=True):
            signed_d2 = x * sigma
            x = signed_d2 / sigma
            log_d = -math.log1p(math.exp(-x)) if x >= 0.0 else x - math.log1p(math.exp(x))
            want = depth - log_d
            got = _fragment_key(depth, signed_d2, sigma)
            # each side rounds x - u (outside) and the sum: half an ulp of each, twice
            tolerance = 5e-16 + np.spacing(abs(want)) + (np.spacing(-x) if x < 0.0 else 0.0)
            assert abs(got - want) <= tolerance, (depth, x, got, want)
            assert got >= depth and (x >= 0.0 or got >= depth - x), (depth, x, got)
            checked += 1
    assert checked == len(depths) * 60


def test_host_face_key_bound_is_below_every_fragment_key():
    """The host soft search drops a fragment before its key when its face's key bound
    (candidates._face_key_bound) ranks after its pixel's full list; that is exact only if
    the bound is at most the key of every fragment of the face: checked against the keys
    computed as the search does (_soft_block, _soft_keys) of every pixel in
    reach of every face of two scenes, perspective and orthographic, at three settings."""
    from diffshade.host import candidates as c

    checked = 0
    for scene in (sphere(), orthographic()):
        cam = scene.camera
        clip = np.asarray(project(scene).clip, np.float64)[None]
        faces = np.asarray(scene.mesh.faces, np.int64)
        for radius, sigma, gamma in SOFT:
            soft = (sigma, gamma, float(cam.near), float(cam.far),
                    cam.projection == "perspective")
            scr, edge, inv_len, zndc, box, reach, lowest = c._soft_setup(
                clip, faces, cam.width, cam.height, False, np.array([radius]),
                np.array([soft[:4]]), soft[4])
            out = np.empty((2, c.TILE_H * c.TILE_W))
            never = np.full(c.TILE_H * c.TILE_W, np.inf)
            for f in np.flatnonzero(reach[0]):
                face = c._face_scalars(scr[0, f], edge[0, f], inv_len[0, f], zndc[0, f])
                bound = lowest[0, f]
                assert bound == c._face_key_bound(zndc[0, f], soft)
                r0, r1 = max(int(box[0, f, 0]), 0), min(int(box[0, f, 1]), cam.height - 1)
                for row in range(r0, r1 + 1):
                    for tile_c0 in range(0, cam.width, c.TILE_W):
                        c._soft_block(face, tile_c0, row, int(box[0, f, 2]),
                                      int(box[0, f, 3]), radius, out, c.TILE_W, np.nan, never)
                        lanes = np.flatnonzero(out[0, :c.TILE_W] < np.inf)
                        if lanes.size == 0:
                            continue
                        depth, signed_d2 = out[0, lanes].copy(), out[1, lanes].copy()
                        c._soft_keys(depth, signed_d2, lanes.size, soft)
                        for i in range(lanes.size):
                            assert bound <= depth[i], (f, row, tile_c0 + lanes[i], bound,
                                                       depth[i])
                            checked += 1
    assert checked > 10_000


def test_host_sort_network_orders_lists_by_key_then_face():
    """The host soft search sorts a full list of 8 by a network of compare-exchanges
    (candidates._sort_full): against Python's sorted() by (key, face), on every list of
    0/1 keys (by the 0-1 principle this covers every order of 8 distinct keys), on random
    lists with tied keys, -0.0 against 0.0 and infinities, and on lists of other lengths
    (the rank sort it falls back to)."""
    from diffshade.host.candidates import _sort_full

    rng = np.random.default_rng(7)
    cases = [np.array([(m >> b) & 1 for b in range(8)], np.float64) for m in range(256)]
    pool = np.array([-3.5, -1.0, -0.0, 0.0, 2.0, 2.0 + 2.0 ** -51, np.inf, -np.inf, 1e300])
    cases += [rng.choice(pool, 8) for _ in range(500)]
    cases += [rng.normal(size=n) * rng.integers(1, 3, n) for n in (1, 3, 4, 8, 16)
              for _ in range(40)]
    for keys in cases:
        ids = rng.permutation(40)[:len(keys)].astype(np.int32)
        want = sorted(zip(keys.tolist(), ids.tolist(), strict=True))
        got_ids, got_keys = ids[None].copy(), keys[None].copy()
        _sort_full(got_ids, got_keys, 0, np.empty(len(keys), np.int32), np.empty(len(keys)))
        assert got_ids[0].tolist() == [face for _, face in want], (keys, ids)
        assert got_keys[0].tolist() == [key for key, _ in want]


def test_host_gather_keeps_the_lanes_in_reach_in_lane_order():
    """The host soft search gathers a tile's fragments in reach (out[0] < inf) a row of 8
    lanes at a time by vector compresses (candidates._gather_reached): against NumPy's
    boolean indexing, bit for bit (-0.0 distances keep their sign), on rows with each of
    the 256 sets of lanes in reach, NaN and +inf depths out of reach, -inf in it, into
    arrays no longer than the lanes (each row writes 8 entries from the count)."""
    import numba

    from diffshade.host import candidates as c

    @numba.njit
    def gather(out, first):
        lanes = out.shape[1]
        fragments, depth, signed_d2 = np.empty(lanes, np.int64), np.empty(lanes), np.empty(lanes)
        count = 0
        for lane in range(0, lanes, c.TILE_W):
            count = c._gather_reached(out, lane, first, fragments, depth, signed_d2, count)
        return fragments[:count], depth[:count], signed_d2[:count]

    rng = np.random.default_rng(3)
    masks = rng.permutation(256)
    reached = ((masks[:, None] >> np.arange(8)) & 1).astype(bool).reshape(-1)
    out = rng.normal(size=(2, reached.size))
    out[1, rng.random(reached.size) < 0.2] = -0.0
    out[0, ~reached] = rng.choice([np.inf, np.nan], (~reached).sum())
    out[0, np.flatnonzero(reached)[::97]] = -np.inf
    fragments, depth, signed_d2 = gather(out, 4096)
    lanes = np.flatnonzero(reached)
    assert fragments.tolist() == (4096 + lanes).tolist()
    assert depth.view(np.int64).tolist() == out[0, lanes].view(np.int64).tolist()
    assert signed_d2.view(np.int64).tolist() == out[1, lanes].view(np.int64).tolist()


def test_host_strip_rows_hold_every_pixel_in_reach():
    """The host soft search evaluates a face only in the rows of a tile's columns that its
    footprint can reach (candidates._strip_rows, from the triangle clipped to the strip of
    columns): against every pixel within radius_px of the triangle (the distance to its
    nearest point, in Python), on random triangles small and large, thin, off-screen and
    far off-screen, with vertical and horizontal edges, for strips of 1 to 8 columns; and
    the same rows as the loop with branches it replaced."""
    from diffshade.host.candidates import _strip_rows

    def distance(px, py, tri):
        ax, ay, bx, by, cx, cy = tri.ravel()
        d = [(bx - ax) * (py - ay) - (by - ay) * (px - ax),
             (cx - bx) * (py - by) - (cy - by) * (px - bx),
             (ax - cx) * (py - cy) - (ay - cy) * (px - cx)]
        if all(v >= 0 for v in d) or all(v <= 0 for v in d):
            return 0.0
        best = np.inf
        for (x0, y0), (x1, y1) in zip(tri, np.roll(tri, -1, 0), strict=True):
            ex, ey = x1 - x0, y1 - y0
            t = min(max(((px - x0) * ex + (py - y0) * ey) / (ex * ex + ey * ey), 0.0), 1.0)
            best = min(best, np.hypot(px - x0 - t * ex, py - y0 - t * ey))
        return best

    def strip_rows_loop(tri, c0, c1, radius, height):
        """The rows as a Python loop with branches: the kernel's selects must give the
        same, not merely rows enough (a wider range costs time, not pixels)."""
        from diffshade.host.candidates import ROW_MARGIN, ROW_MARGIN_REL
        reach = radius + ROW_MARGIN + ROW_MARGIN_REL * np.abs(tri).max()
        x_lo, x_hi = c0 + 0.5 - reach, c1 + 0.5 + reach
        ys = []
        for (xi, yi), (xj, yj) in zip(tri, np.roll(tri, -1, 0), strict=True):
            if x_lo <= xi <= x_hi:
                ys.append(yi)
            ys += [yi + (side - xi) / (xj - xi) * (yj - yi) for side in (x_lo, x_hi)
                   if (xi - side) * (xj - side) < 0.0]
        if not ys:
            return 0, -1
        first = max(min(np.ceil(min(ys) - 0.5 - reach), height), -1)
        last = max(min(np.floor(max(ys) - 0.5 + reach), height), -1)
        return max(int(first), 0), min(int(last), height - 1)

    rng = np.random.default_rng(8)
    height, checked = 40, 0
    for case in range(300):
        scale = [3.0, 15.0, 60.0, 1e4][case % 4]
        tri = rng.uniform(-10, 50, 2) + rng.normal(0, scale, (3, 2))
        if case % 7 == 0:
            tri[2] = tri[0] + rng.normal(0, 1e-3, 2)  # a sliver
        if case % 5 == 1:
            tri[1, 0] = tri[0, 0]  # a vertical edge (its crossings divide by 0: not kept)
        if case % 5 == 2:
            tri[2, 1] = tri[1, 1]  # a horizontal edge
        radius = rng.choice([0.5, 1.5, 3.03])
        c0 = int(rng.integers(0, 40))
        c1 = min(c0 + int(rng.integers(0, 8)), 47)
        first, last = _strip_rows(tri, c0, c1, radius, height)
        assert (first, last) == strip_rows_loop(tri, c0, c1, radius, height)
        for row in range(height):
            for col in range(c0, c1 + 1):
                if distance(col + 0.5, row + 0.5, tri) <= radius:
                    assert first <= row <= last, (tri, radius, c0, c1, row, col, first, last)
                    checked += 1
    assert checked > 1000


def test_host_depth_order_is_front_to_back_up_to_one_class():
    """The host soft search visits faces roughly front to back (candidates._depth_order,
    a counting sort): a permutation of the faces whose first entries are the faces in
    reach with a finite depth, each no farther than the next by more than one class
    width (against NumPy's sums and a plain loop), then every other face (out of reach,
    or a depth that is infinite or NaN)."""
    from diffshade.host.candidates import DEPTH_BUCKETS, _depth_order

    rng = np.random.default_rng(3)
    zndc = rng.uniform(-1.0, 1.0, (3000, 3))
    zndc[rng.choice(3000, 20, replace=False), 1] = np.nan
    zndc[rng.choice(3000, 20, replace=False), 2] = np.inf
    reach = rng.random(3000) < 0.8
    order = _depth_order(zndc, reach)
    assert sorted(order.tolist()) == list(range(3000))
    depth = zndc.sum(1)
    ranked = reach & np.isfinite(depth)
    first = order[:ranked.sum()]
    assert ranked[first].all() and not ranked[order[ranked.sum():]].any()
    width = (depth[ranked].max() - depth[ranked].min()) / (DEPTH_BUCKETS - 1)
    for near, far in zip(first[:-1], first[1:], strict=True):
        assert depth[near] <= depth[far] + width * (1 + 1e-9)


def test_host_tile_claims_give_each_item_to_one_thread():
    """intrinsics.claim (an atomic counter) from every thread of a parallel loop at once:
    each item is claimed by exactly one of them, and the items come costliest first
    (_tile_order: by the faces binned per (view, tile), against NumPy's stable argsort)."""
    import numba

    from diffshade.host.candidates import _tile_order
    from diffshade.host.intrinsics import claim

    @numba.njit(parallel=True)
    def claim_all(items, threads):
        counter, hits = np.zeros(1, np.int64), np.zeros((threads, items), np.uint8)
        for worker in numba.prange(threads):
            item = claim(counter)
            while item < items:
                hits[worker, item] = 1
                item = claim(counter)
        return hits

    hits = claim_all(2_000_000, numba.get_num_threads())
    np.testing.assert_array_equal(hits.sum(0), 1)
    counts = np.random.default_rng(5).integers(0, 40, (3, 50))
    start = np.concatenate([np.zeros((3, 1), np.int64), np.cumsum(counts, 1)], 1)
    np.testing.assert_array_equal(_tile_order(start),
                                  np.argsort(-counts.reshape(-1), kind="stable"))


def test_host_soft_search_is_the_same_on_any_thread_count():
    """The soft search hands its (view, tile) items to the threads as they come free, so
    which thread searches which tile varies from call to call: the ids and drop counts of
    a batch of views are the same on one thread as on all of them."""
    import numba

    clip = np.asarray(project(make_scene(icosphere(3), sphere().camera)).clip)
    clips = np.stack([clip, clip + [0.05, 0.0, 0.0, 0.0] * clip[:, 3:],
                      clip - [0.0, 0.1, 0.0, 0.0] * clip[:, 3:]])  # shifted views
    faces = np.asarray(icosphere(3).faces)
    search = lambda: find_candidates(clips, faces, 0.1, 100.0, width=37, height=29, k=6,
                                     radius_px=2.0, sigma=1.0, gamma=1e-3)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = search()
    finally:
        numba.set_num_threads(threads)
    assert (one[0] >= 0).sum() > 1000 and (one[1] > 0).all()
    for _ in range(3):
        got = search()
        np.testing.assert_array_equal(got[0], one[0])
        np.testing.assert_array_equal(got[1], one[1])
