"""Textures: UVs on meshes, bilinear lookup, textured renders, gradients, bad input.

References are independent of the code under test:
- UV maps of the built-in shapes against their closed forms (longitude / latitude);
- seams: a mesh split at a UV seam has the normals of the same mesh welded (computed
  without UVs);
- the lookup against a naive NumPy bilinear loop over texel centres, with its own wrap;
- renders against tests/reference.py's naive rasterizer (perspective-correct
  barycentrics) and OpenGL lighting, with kd read by that NumPy lookup at the UV each
  shading mode uses;
- gradients in float64 against central differences.
"""

import json
import math
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import diffshade as ds
from diffshade.io import SceneFileError
from diffshade.scene import MAX_TEXELS
from diffshade.shading import sample_texture

# --------------------------------------------------------------------- naive lookup


def naive_sample(texels, u, v, wrap):
    """Bilinear value of texels [H, W, C] at one (u, v): the four nearest texel centres
    ((i + 0.5) / W, 1 - (j + 0.5) / H), weights by distance, indices wrapped or clamped."""
    h, w, _ = texels.shape
    x, y = u * w - 0.5, (1.0 - v) * h - 0.5
    if wrap == "clamp":
        x, y = min(max(x, 0.0), w - 1.0), min(max(y, 0.0), h - 1.0)
    x0, y0 = math.floor(x), math.floor(y)
    fx, fy = x - x0, y - y0
    value = 0.0
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            if wrap == "repeat":
                row, col = (y0 + dy) % h, (x0 + dx) % w
            else:
                row, col = min(y0 + dy, h - 1), min(x0 + dx, w - 1)
            value = value + wy * wx * texels[row, col]
    return value


def lookups(texture, uv, valid=None):
    """sample_texture by every path: {name: function of (texels, uv)}: the host kernels
    called at once (eager) and under jit (the FFI targets), and jax.numpy under jit."""
    def path(host):
        return lambda t, u: sample_texture(ds.replace(texture, texels=t), u, host, valid)
    return {"host": path(True), "host jit": jax.jit(path(True)),
            "jax.numpy jit": jax.jit(path(False))}


@pytest.mark.parametrize("channels", [1, 3, 8, 9])
@pytest.mark.parametrize("wrap", ["repeat", "clamp"])
def test_lookup_matches_a_naive_bilinear_loop_inside_and_outside_the_unit_square(wrap, channels,
                                                                                  x64):
    """Every path against a naive loop; the host kernel blends a texel row of up to 8
    channels as one vector (texture_kernels._blend_texels), 9 channels in its scalar loop."""
    rng = np.random.default_rng(1)
    texels = rng.random((5, 7, channels))
    uv = np.concatenate([rng.uniform(-2.5, 3.5, (60, 2)), [[0, 0], [1, 1], [0.5, 1e-9],
                                                          [1e6, -1e6], [-1.0, 2.0]]])
    want = np.array([naive_sample(texels, u, v, wrap) for u, v in uv])
    for name, lookup in lookups(ds.texture(texels, wrap), uv).items():
        got = np.asarray(lookup(jnp.asarray(texels), jnp.asarray(uv)))
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9, err_msg=name)


@pytest.mark.parametrize("wrap", ["repeat", "clamp"])
def test_lookup_of_nan_and_infinite_uvs_reads_in_range(wrap, x64):
    """A NaN UV (or an infinite one under 'repeat', whose modulo is NaN) reads NaN, by every
    path alike, its reads in range; clamp takes an infinite UV to the edge texels."""
    texels = np.arange(2.0, 14.0).reshape(3, 4, 1)
    inf, nan = np.inf, np.nan
    uv = np.array([[nan, 0.5], [0.5, nan], [inf, 0.5], [-inf, 0.5], [0.5, inf], [0.5, -inf],
                   [0.3, 0.7]])
    clamped = [naive_sample(texels, min(max(u, -1.0), 2.0), min(max(v, -1.0), 2.0), "clamp")
               for u, v in uv[2:6]]
    want = np.concatenate([np.full((2, 1), nan), clamped if wrap == "clamp" else
                           np.full((4, 1), nan), [naive_sample(texels, 0.3, 0.7, wrap)]])
    for name, lookup in lookups(ds.texture(texels, wrap), uv).items():
        got = np.asarray(lookup(jnp.asarray(texels), jnp.asarray(uv)))
        np.testing.assert_allclose(got, want, rtol=1e-12, err_msg=name)  # NaN where want's


@pytest.mark.parametrize("wrap", ["repeat", "clamp"])
def test_lookup_gradients_agree_across_paths_and_skip_invalid_samples(wrap, x64):
    """Reverse mode of every path against forward mode of jax.numpy (jvp), for the texels
    alone (the host backward then skips the UVs' gradient) and for texels and UVs; samples
    not `valid` read 0 and give no gradient."""
    rng = np.random.default_rng(4)
    texels, uv = rng.random((4, 6, 3)), rng.uniform(-0.5, 1.5, (40, 2))
    valid = np.arange(40) % 4 != 1
    weights = rng.normal(size=(40, 3))
    d_tex, d_uv = rng.normal(size=texels.shape), rng.normal(size=uv.shape)
    for name, lookup in lookups(ds.texture(texels, wrap), uv, jnp.asarray(valid)).items():
        loss = lambda t, u, lookup=lookup: jnp.sum(lookup(t, u) * weights)
        assert np.all(np.asarray(lookup(texels, uv))[~valid] == 0.0), name
        g_tex, g_uv = jax.grad(loss, (0, 1))(texels, uv)
        assert np.all(np.asarray(g_uv)[~valid] == 0.0), name
        np.testing.assert_allclose(jax.grad(loss)(texels, uv), g_tex, rtol=1e-12, atol=1e-12)
        _, jvp = jax.jvp(loss, (texels, uv), (d_tex, d_uv))
        np.testing.assert_allclose(np.sum(g_tex * d_tex) + np.sum(g_uv * d_uv), jvp,
                                   rtol=1e-10, err_msg=name)


def test_texel_centres_read_their_texel_and_v_runs_up_the_image(x64):
    texels = np.arange(12.0).reshape(3, 4, 1)
    tex = ds.texture(texels)
    rows, cols = np.mgrid[0:3, 0:4]
    uv = np.stack([(cols + 0.5) / 4, 1.0 - (rows + 0.5) / 3], -1)
    np.testing.assert_allclose(np.asarray(sample_texture(tex, jnp.asarray(uv))), texels)


# ------------------------------------------------------------------------ mesh UVs


def test_sphere_uvs_are_longitude_and_latitude():
    mesh = ds.icosphere(3, uv=True)
    plain = ds.icosphere(3)
    verts, uv = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.uv, np.float64)
    np.testing.assert_allclose(uv[:, 1], 0.5 + np.arcsin(np.clip(verts[:, 1], -1, 1)) / np.pi,
                               atol=1e-6)
    pole = np.hypot(verts[:, 0], verts[:, 2]) < 1e-6
    longitude = (0.5 + np.arctan2(verts[:, 0], verts[:, 2]) / (2 * np.pi)) % 1.0
    # u is the longitude up to whole turns (faces across the seam continue past 0 or 1)
    turns = (uv[~pole, 0] - longitude[~pole] + 0.5) % 1.0 - 0.5
    np.testing.assert_allclose(turns, 0.0, atol=1e-6)
    span = np.ptp(uv[np.asarray(mesh.faces)][..., 0], axis=1)
    assert span.max() < 0.25  # no face stretches across the map
    # the same surface: every face's corners are those of the plain sphere, same normals
    same = {tuple(np.round(v, 5)) for v in np.asarray(plain.vertices, np.float64).tolist()}
    assert {tuple(np.round(v, 5)) for v in verts.tolist()} == same
    np.testing.assert_allclose(np.asarray(mesh.normals), verts, atol=1e-6)
    assert mesh.faces.shape == plain.faces.shape


def test_torus_and_box_uvs_cover_the_unit_square():
    torus = ds.torus(1.0, 0.3, 8, 6, uv=True)
    uv = np.asarray(torus.uv)
    assert torus.vertices.shape[0] == 9 * 7
    assert uv.min() >= 0 and uv.max() <= 1 and np.ptp(uv[np.asarray(torus.faces)], 1).max() < 0.2
    box = ds.box(uv=True)
    corners = np.asarray(box.uv)[np.asarray(box.faces)]
    # each side's two triangles cover the unit square: area 1 per side in UV space
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    areas = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2
    np.testing.assert_allclose(areas.reshape(6, 2).sum(1), 1.0)
    assert ds.box().uv is None and ds.icosphere(1).uv is None


def split_strip():
    """A bent strip of 4 quads whose middle column of vertices is split in two (a seam:
    same positions, different UVs); and the same strip welded."""
    xs = np.array([0.0, 1.0, 2.0, 2.0, 3.0, 4.0])  # x = 2 twice: the seam
    heights = np.array([0.0, 0.3, 0.5, 0.5, 0.2, 0.0])
    verts = np.array([[x, y, h] for y in (0.0, 1.0) for x, h in zip(xs, heights, strict=True)])
    quads = [(0, 1), (1, 2), (3, 4), (4, 5)]
    faces = np.array([f for a, b in quads for f in ([a, b, b + 6], [a, b + 6, a + 6])])
    uv = np.stack([np.r_[0.0, 0.2, 0.4, 0.6, 0.8, 1.0][np.arange(12) % 6],
                   (np.arange(12) >= 6).astype(float)], -1)
    keep = np.array([0, 1, 2, 4, 5, 6, 7, 8, 10, 11])  # the seam's copies dropped
    remap = np.full(12, -1)
    remap[keep] = np.arange(10)
    remap[3], remap[9] = remap[2], remap[8]
    return verts, faces, uv, verts[keep], remap[faces]


@pytest.mark.parametrize("crease_angle", [None, 60.0])
def test_a_uv_seam_does_not_show_in_the_normals(crease_angle):
    verts, faces, uv, welded_verts, welded_faces = split_strip()
    split = ds.mesh_from_arrays(verts, faces, uv=uv, crease_angle=crease_angle)
    welded = ds.mesh_from_arrays(welded_verts, welded_faces, crease_angle=crease_angle)
    # each split vertex has the normal of the welded vertex at its position
    lookup = {tuple(p): n for p, n in zip(np.asarray(welded.vertices).tolist(),
                                          np.asarray(welded.normals), strict=True)}
    for p, n in zip(np.asarray(split.vertices).tolist(), np.asarray(split.normals), strict=True):
        np.testing.assert_allclose(n, lookup[tuple(p)], atol=1e-6)
    # and every face corner keeps its UV
    corner_uv = {tuple(p): set() for p in np.asarray(split.vertices).tolist()}
    for p, t in zip(np.asarray(split.vertices).tolist(), np.asarray(split.uv).tolist(),
                    strict=True):
        corner_uv[tuple(p)].add(tuple(np.round(t, 6)))
    assert corner_uv[(2.0, 0.0, 0.5)] == {(0.4, 0.0), (0.6, 0.0)}


OBJ = """mtllib quad.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0.5 -0.5
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.25 0.75
vt 0.5 0.5
usemtl painted
f 1/1 2/2 3/3
f 1/1 3/3 4/4
f 2/5 5/6 3/3
"""
MTL = "newmtl painted\nKd 1 1 1\nmap_Kd -s 1 1 1 paint.png\nmap_Ks gloss.npy\n"


@pytest.fixture
def obj_folder(tmp_path):
    (tmp_path / "quad.obj").write_text(OBJ)
    (tmp_path / "quad.mtl").write_text(MTL)
    paint = np.random.default_rng(3).integers(0, 256, (4, 6, 3)).astype(np.uint8)
    from PIL import Image
    Image.fromarray(paint).save(tmp_path / "paint.png")
    np.save(tmp_path / "gloss.npy", np.full((2, 2, 1), 0.25, np.float32))
    return tmp_path, paint


def test_obj_uvs_follow_the_file_and_split_at_its_seam(obj_folder):
    folder, _ = obj_folder
    mesh = ds.load_mesh(folder / "quad.obj")
    verts, faces, uv = (np.asarray(a, np.float64) for a in (mesh.vertices, mesh.faces, mesh.uv))
    file_v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, -0.5]], float)
    file_vt = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.25, 0.75], [0.5, 0.5]])
    file_f = [[(0, 0), (1, 1), (2, 2)], [(0, 0), (2, 2), (3, 3)], [(1, 4), (4, 5), (2, 2)]]
    assert len(verts) == 6  # vertex 2 has two UVs: split
    for face, corners in zip(faces.astype(int), file_f, strict=True):
        for index, (v, t) in zip(face, corners, strict=True):
            np.testing.assert_allclose(verts[index], file_v[v])
            np.testing.assert_allclose(uv[index], file_vt[t])


def srgb_decode(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def test_an_obj_scene_takes_its_mtl_maps_where_the_material_sets_none(obj_folder):
    folder, paint = obj_folder
    scene_file = {"mesh": {"path": "quad.obj"}, "material": {"ks": 0.5},
                  "camera": {"eye": [0.5, 0.5, 3], "target": [0.5, 0.5, 0], "width": 8,
                             "height": 8}}
    scene, _ = ds.scene_from_dict(scene_file, folder)
    np.testing.assert_allclose(np.asarray(scene.material.kd.texels),
                               srgb_decode(paint / 255.0), atol=1e-6)
    np.testing.assert_allclose(np.asarray(scene.material.ks), 0.5)  # the file's own wins


# ------------------------------------------------------------------------- renders


def quad_scene(texture, width=12, height=10, **material):
    """A tilted textured quad (2 faces, UVs over [0, 1]^2) in perspective, lit head-on."""
    verts = np.array([[-1.0, -0.8, 0.0], [1.0, -0.8, -0.6], [1.0, 0.8, -0.6], [-1.0, 0.8, 0.0]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    mesh = ds.mesh_from_arrays(verts, [[0, 1, 2], [0, 2, 3]], uv=uv)
    cam = ds.look_at((0.3, 0.2, 2.5), (0.0, 0.0, -0.3), width=width, height=height, fov_y=50.0)
    lights = [ds.directional_light((-0.2, -0.3, -1.0), 0.9), ds.point_light((1, 1, 2), 0.4)]
    mat = ds.material(ka=0.1, kd=texture, **material)
    return ds.make_scene(mesh, cam, lights, mat, global_ambient=0.3)


def corner_uv(scene, face, bary, shading):
    """Where each shading mode reads the texture: (UV per lit sample, their weights)."""
    uv = np.asarray(scene.mesh.uv, np.float64)[np.asarray(scene.mesh.faces)[face]]
    if shading == "phong":
        return [bary @ uv], None
    if shading == "flat":
        return [uv.mean(0)], None
    if shading == "flat_last":
        return [uv[2]], None
    return list(uv), bary


def textured_reference(scene, texels, wrap, shading):
    """tests/reference.py's render with kd read by naive_sample where each mode lights."""
    # the reference reads plain materials: kd is set per sample below
    untextured = ds.replace(scene, material=ds.replace(scene.material, kd=jnp.zeros(3)))
    rgba, frags = ref.render(untextured, shading)
    scene_ref = ref.RefScene(untextured)
    world, faces = scene_ref.world, scene_ref.faces
    for row, col in zip(*np.nonzero(frags.face_ids >= 0), strict=True):
        face, bary = frags.face_ids[row, col], frags.bary[row, col]
        uvs, weights = corner_uv(scene, face, bary, shading)
        tri = world[faces[face]]
        face_normal = ref.unit(np.cross(tri[1] - tri[0], tri[2] - tri[0]))
        points = {"phong": [bary @ tri], "flat": [tri.mean(0)], "flat_last": [tri[2]]}.get(
            shading, list(tri))
        normals = ({"phong": [ref.unit(bary @ scene_ref.normals[faces[face]])],
                    "flat": [face_normal], "flat_last": [scene_ref.normals[faces[face][2]]]}
                   .get(shading, list(scene_ref.normals[faces[face]])))
        colours = []
        for uv, point, normal in zip(uvs, points, normals, strict=True):
            scene_ref.front_mat = dict(scene_ref.front_mat, kd=naive_sample(texels, *uv, wrap))
            colours.append(np.clip(ref.total(scene_ref.light(point, normal)), 0, 1))
        rgba[row, col, :3] = colours[0] if weights is None else weights @ np.array(colours)
    return rgba


@pytest.mark.parametrize("shading", ["phong", "gouraud", "flat", "flat_last"])
def test_a_textured_render_matches_the_reference_in_every_shading_mode(shading, x64):
    texels = np.random.default_rng(4).random((6, 5, 3))
    scene = quad_scene(ds.texture(texels), ks=0.2, shininess=8.0)
    got = np.asarray(ds.render(scene, ds.RenderSettings(shading=shading)))
    want = textured_reference(scene, texels, "repeat", shading)
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_soft_textured_render_equals_its_shading_cache_and_a_uniform_texture(x64):
    settings = ds.RenderSettings(raster="soft", sigma=1e-5, gamma=1e-4)
    textured = quad_scene(ds.texture(np.full((3, 4, 3), [0.6, 0.3, 0.2])), ks=0.3, shininess=5.0)
    uniform = ds.replace(textured, material=ds.material(ka=0.1, kd=(0.6, 0.3, 0.2), ks=0.3,
                                                        shininess=5.0))
    image = np.asarray(ds.render(textured, settings))
    np.testing.assert_allclose(image, np.asarray(ds.render(uniform, settings)), atol=1e-12)
    rng = np.random.default_rng(5)
    varied = ds.replace(textured, material=ds.replace(textured.material,
                                                      kd=ds.texture(rng.random((3, 4, 3)))))
    frags = ds.rasterize_scene(varied, settings)
    cache = ds.cache_shading(varied, frags, settings)
    np.testing.assert_allclose(np.asarray(ds.render_cached(varied, cache, settings)),
                               np.asarray(ds.render(varied, settings)), atol=1e-10)


def test_ks_and_shininess_textures_vary_the_highlight(x64):
    flat = quad_scene(0.5, ks=0.4, shininess=12.0)
    textured = quad_scene(0.5, ks=ds.texture(np.full((2, 2, 1), 0.4)),
                          shininess=ds.texture(np.full((2, 2), 12.0)))
    np.testing.assert_allclose(np.asarray(ds.render(textured)), np.asarray(ds.render(flat)),
                               atol=1e-12)
    assert textured.material.ks.texels.shape == (2, 2, 3)


# ---------------------------------------------------------------------- gradients


def tiny_scene():
    rng = np.random.default_rng(6)
    return quad_scene(ds.texture(rng.random((3, 3, 3))), width=6, height=5, ks=0.2,
                      shininess=6.0)


SOFT = ds.RenderSettings(raster="soft", sigma=1e-2, gamma=1e-2)


def image_of(texels, uv, scene, settings=SOFT):
    mat = ds.replace(scene.material, kd=ds.replace(scene.material.kd, texels=texels))
    mesh = ds.replace(scene.mesh, uv=uv)
    return ds.render(ds.replace(scene, material=mat, mesh=mesh), settings)


def loss(texels, uv, scene, weights):
    return jnp.sum(image_of(texels, uv, scene)[..., :3] * weights)


def central_difference(fn, x, direction, eps=1e-6):
    return (fn(x + eps * direction) - fn(x - eps * direction)) / (2 * eps)


@pytest.mark.cost(8)
def test_gradients_reach_every_texel_and_the_uvs_and_match_central_differences(x64):
    scene = tiny_scene()
    texels, uv = scene.material.kd.texels, scene.mesh.uv
    weights = jnp.asarray(np.random.default_rng(7).random((5, 6, 3)))
    g_tex, g_uv = jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=())(
        texels, uv, scene, weights)
    assert np.all(np.abs(np.asarray(g_tex)).sum(-1) > 0)  # the quad shows every texel
    rng = np.random.default_rng(8)
    for _ in range(2):
        d_tex, d_uv = rng.normal(size=texels.shape), rng.normal(size=uv.shape) * 0.1
        fd_tex = central_difference(lambda t: loss(t, uv, scene, weights), texels, d_tex)
        fd_uv = central_difference(lambda u: loss(texels, u, scene, weights), uv, d_uv)
        np.testing.assert_allclose(np.sum(g_tex * d_tex), fd_tex, rtol=1e-6)
        np.testing.assert_allclose(np.sum(g_uv * d_uv), fd_uv, rtol=1e-5, atol=1e-8)
        # forward mode agrees with reverse mode
        _, jvp = jax.jvp(lambda t, u: loss(t, u, scene, weights), (texels, uv),
                         (jnp.asarray(d_tex), jnp.asarray(d_uv)))
        np.testing.assert_allclose(jvp, np.sum(g_tex * d_tex) + np.sum(g_uv * d_uv), rtol=1e-9)


@pytest.mark.cost(6)
def test_jacfwd_and_vmap_over_textures(x64):
    scene = tiny_scene()
    texels, uv = scene.material.kd.texels, scene.mesh.uv
    jac = jax.jacfwd(lambda t: image_of(t, uv, scene)[2, 3, :3])(texels)
    rev = jax.jacrev(lambda t: image_of(t, uv, scene)[2, 3, :3])(texels)
    np.testing.assert_allclose(jac, rev, atol=1e-12)
    batch = jnp.stack([texels, 1.0 - texels, 0.5 * texels])
    batched = jax.vmap(lambda t: image_of(t, uv, scene))(batch)
    for i in range(3):
        np.testing.assert_allclose(batched[i], image_of(batch[i], uv, scene), atol=1e-12)


# ---------------------------------------------------------------------- bad input


@pytest.mark.parametrize("texels, words", [
    (np.array([[[0.1, np.nan, 0.2]]]), ["texel [0, 0, 1]", "nan", "finite"]),
    (np.full((2, 2, 3), -0.5), ["texel [0, 0, 0]", ">= 0"]),
    (np.zeros((2, 2, 2, 3)), ["shape (2, 2, 2, 3)", "[H, W]"]),
    (np.zeros((0, 3, 3)), ["shape (0, 3, 3)"]),
    (np.broadcast_to(np.float32(0), (8193, 8192, 3)), ["8193 x 8192", str(MAX_TEXELS)]),
])
def test_bad_texels_get_one_line_naming_them(texels, words):
    with pytest.raises(ValueError) as err:
        ds.texture(texels)
    assert "\n" not in str(err.value) and all(w in str(err.value) for w in words), err.value


def test_bad_texture_files_and_uses_are_refused(tmp_path):
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(ValueError, match="broken.png"):
        ds.texture(tmp_path / "broken.png")
    with pytest.raises(FileNotFoundError, match="missing.png"):
        ds.texture(tmp_path / "missing.png")
    with pytest.raises(ValueError, match="wrap: got 'mirror'"):
        ds.texture(np.ones((2, 2)), wrap="mirror")
    cam = ds.look_at((0, 0, 3), (0, 0, 0), width=4, height=4)
    tex = ds.texture(np.ones((2, 2, 3)))
    with pytest.raises(ValueError, match=r"material.kd: a texture on a mesh without UVs"):
        ds.make_scene(ds.icosphere(1), cam, [], ds.material(kd=tex))
    with pytest.raises(ValueError, match=r"kt: got a texture"):
        ds.material(kt=tex)
    with pytest.raises(ValueError, match=r"shininess: a texture of 3 channels"):
        ds.material(shininess=tex)
    objects = [ds.scene_object(ds.box(uv=True), ds.material(kd=tex)),
               ds.scene_object(ds.box(uv=True))]
    with pytest.raises(ValueError, match=r"objects\[0\].material.kd: a texture in a scene of "):
        ds.make_scene(camera=cam, objects=objects)
    with pytest.raises(ValueError, match=r"uv: shape \(2, 2\) of float64; expected \[3, 2\]"):
        ds.mesh_from_arrays(np.eye(3) + 1, [[0, 1, 2]], uv=np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"uv: row 1 is \[nan, 0.0\]"):
        ds.mesh_from_arrays(np.eye(3) + 1, [[0, 1, 2]], uv=[[0, 0], [np.nan, 0], [1, 1]])


def scene_file(texture_entry):
    return {"mesh": {"builtin": {"icosphere": {"subdivisions": 1, "uv": True}}},
            "material": {"kd": texture_entry},
            "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 8, "height": 8},
            "lights": [{"type": "directional", "direction": [0, 0, -1]}]}


def test_scene_files_name_the_key_of_a_bad_texture(tmp_path):
    np.save(tmp_path / "nan.npy", np.full((2, 2, 3), np.nan))
    cases = {"missing.png": "material.kd.texture: texture file 'missing.png' not found",
             "nan.npy": "material.kd.texture: texture",
             }
    for name, words in cases.items():
        with pytest.raises(SceneFileError, match="^" + words.replace(".", r"\.")):
            ds.scene_from_dict(scene_file({"texture": name}), tmp_path)
    with pytest.raises(SceneFileError, match=r"material.kd.wrap: got \"tile\""):
        ds.scene_from_dict(scene_file({"texture": "nan.npy", "wrap": "tile"}), tmp_path)
    with pytest.raises(SceneFileError, match=r"material.kd.colour: unknown key"):
        ds.scene_from_dict(scene_file({"colour": "x.png"}), tmp_path)


def test_a_textured_scene_file_round_trips_through_save_scene(tmp_path):
    np.save(tmp_path / "kd.npy", np.random.default_rng(9).random((4, 4, 3)).astype(np.float32))
    scene, settings = ds.scene_from_dict(scene_file({"texture": "kd.npy", "wrap": "clamp"}),
                                         tmp_path)
    ds.save_scene(tmp_path / "out" / "again.json", scene, settings)
    assert (tmp_path / "out" / "again.kd.npy").is_file()
    loaded, _ = ds.load_scene(tmp_path / "out" / "again.json")
    assert loaded.material.kd.wrap == "clamp"
    np.testing.assert_array_equal(np.asarray(ds.render(loaded, settings)),
                                  np.asarray(ds.render(scene, settings)))


def run_cli(*args, env=None):
    return subprocess.run([sys.executable, "-m", "diffshade", *map(str, args)],
                          capture_output=True, text=True, env=env)


@pytest.mark.cost(8)
def test_cli_renders_a_textured_scene_and_refuses_a_nan_texture(tmp_path, cli_env):
    np.save(tmp_path / "kd.npy", np.random.default_rng(9).random((4, 4, 3)))
    np.save(tmp_path / "nan.npy", np.full((2, 2, 3), np.nan))
    for name, texture in (("good", "kd.npy"), ("bad", "nan.npy")):
        (tmp_path / f"{name}.json").write_text(json.dumps(scene_file({"texture": texture})))
    done = run_cli("render", tmp_path / "good.json", "-o", tmp_path / "good.png", env=cli_env)
    assert done.returncode == 0, done.stderr
    assert ds.read_image(tmp_path / "good.png").shape == (8, 8, 3)
    done = run_cli("render", tmp_path / "bad.json", "-o", tmp_path / "bad.png", env=cli_env)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "material.kd.texture" in lines[0] and "nan" in lines[0]
    assert not os.path.exists(tmp_path / "bad.png")


# ------------------------------------------------------------- synthetic datasets


def test_a_synthetic_dataset_with_a_procedural_texture_round_trips(tmp_path):
    from data_synth import make_dataset
    from fitting.data.folder import load_dataset, save_dataset
    from fitting.inputs import load_checked_dataset

    data = make_dataset("icosphere", n_views=1, n_lights=1, size=16, texture=6)
    texels = np.asarray(data.truth.kd.texels, np.float64)
    # the closed form at the texel centres (row 0 = v = 1)
    u = (np.arange(6) + 0.5) / 6
    v = 1.0 - u
    red = 0.45 + 0.25 * np.sin(2 * np.pi * 3 * u)[None, :] * np.cos(2 * np.pi * 2 * v)[:, None]
    np.testing.assert_allclose(texels[..., 0], red, atol=1e-6)
    assert data.mesh.uv is not None
    save_dataset(data, tmp_path / "set")
    assert (tmp_path / "set" / "truth.kd.png").is_file()
    loaded = load_dataset(tmp_path / "set")
    np.testing.assert_array_equal(np.asarray(loaded.truth.kd.texels), texels)
    # the saved scene file, with its texture, renders the saved target
    scene, settings = ds.load_scene(tmp_path / "set" / "view_000.json")
    np.testing.assert_allclose(np.asarray(ds.render(scene, settings))[..., :3],
                               loaded.views[0].target, atol=1e-6)
    with pytest.raises(ValueError, match="truth.json: kd is a texture; expected uniform"):
        load_checked_dataset(str(tmp_path / "set"))


# ------------------------------------------------------- recovering a kd texture


def texture_views(truth, azimuths, size=20):
    """Views of a textured sphere (one directional light from each camera), their
    unclamped renders as targets, covered pixels as masks."""
    mesh = ds.icosphere(2, uv=True)
    scenes, targets, masks = [], [], []
    for azimuth in np.radians(azimuths):
        eye = (3 * np.sin(azimuth), 0.8, 3 * np.cos(azimuth))
        cam = ds.look_at(eye, (0, 0, 0), width=size, height=size)
        scene = ds.make_scene(mesh, cam, [ds.directional_light(-np.asarray(eye), 0.8)],
                              ds.material(kd=truth, ks=0.2, shininess=10.0))
        image = ds.render(scene, ds.RenderSettings(clamp=False))
        scenes.append(scene)
        targets.append(image[..., :3])
        masks.append(image[..., 3] > 0.5)
    return scenes, targets, masks


def grid_laplacian(res):
    """The graph Laplacian [R*R, R*R] of a res x res grid, neighbours wrapped."""
    lap = np.zeros((res * res, res * res))
    for r in range(res):
        for c in range(res):
            for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                lap[r * res + c, r * res + c] += 1
                lap[r * res + c, ((r + dr) % res) * res + (c + dc) % res] -= 1
    return lap


def dense_normal_equations(scenes, targets, masks, res, settings):
    """(A'MA, A'M(y - b)) as dense NumPy arrays, A from jacfwd of each view's render;
    texel (r, c) channel k is row (r * res + c) * 3 + k."""
    normal, rhs = np.zeros((res * res * 3,) * 2), np.zeros(res * res * 3)
    for scene, target, mask in zip(scenes, targets, masks, strict=True):
        view = lambda t, s=scene: ds.render(ds.replace(s, material=ds.replace(  # noqa: E731
            s.material, kd=ds.replace(s.material.kd, texels=t))), settings)[..., :3]
        zero = jnp.zeros((res, res, 3))
        a = np.asarray(jax.jacfwd(view)(zero)).reshape(-1, res * res * 3)
        keep = np.repeat(np.asarray(mask).reshape(-1), 3)
        a, residual = a[keep], (np.asarray(target) - np.asarray(view(zero))).reshape(-1)[keep]
        normal += a.T @ a
        rhs += a.T @ residual
    return normal, rhs


def dense_solution(normal, rhs, res, smoothness):
    """The prior's weight (every texel seen: smoothness x the mean data weight) and the
    solution of the regularized normal equations, [R, R, 3]."""
    lam = smoothness * normal.sum(1).mean()
    # the Laplacian acts per channel
    lap = np.kron(grid_laplacian(res), np.eye(3))
    return lam, np.linalg.solve(normal + lam * lap, rhs).reshape(res, res, 3)


@pytest.mark.cost(12)
def test_the_kd_texture_solve_matches_dense_least_squares_and_reports_unseen_texels(x64):
    from fitting.solve import solve_kd_texture

    res = 4
    truth = ds.texture(np.random.default_rng(10).uniform(0.2, 0.7, (res, res, 3)))
    scenes, targets, masks = texture_views(truth, [0.0, 120.0, 240.0])
    exact = solve_kd_texture(scenes, targets, masks, res, smoothness=0.0, tol=1e-13)
    np.testing.assert_allclose(exact.texels, truth.texels, atol=1e-7)  # noiseless: the truth
    # a strong prior: the same as solving the normal equations with dense matrices
    noisy = [t + 0.01 * np.random.default_rng(i).normal(size=t.shape)
             for i, t in enumerate(targets)]
    solved = solve_kd_texture(scenes, noisy, masks, res, smoothness=0.5, tol=1e-13)
    normal, rhs = dense_normal_equations(scenes, noisy, masks, res,
                                         ds.RenderSettings(clamp=False))
    lam, want = dense_solution(normal, rhs, res, 0.5)
    np.testing.assert_allclose(solved.lam, lam, rtol=1e-9)
    np.testing.assert_allclose(solved.texels, want, atol=1e-8)
    # hard raster, Phong: every pixel reads one bilinear cell, so the probed stencil is
    # the normal matrix and the renders only confirm its solution
    assert solved.iterations <= 1 < solved.stencil_iterations
    # standard errors: sigma from the residuals, over the diagonal of A'MA
    residuals = np.concatenate([
        (np.asarray(view_image) - np.asarray(target)).reshape(-1)[np.repeat(
            np.asarray(mask).reshape(-1), 3)]
        for view_image, target, mask in zip(
            [ds.render(ds.replace(s, material=ds.replace(s.material, kd=ds.replace(
                s.material.kd, texels=jnp.asarray(want)))), ds.RenderSettings(clamp=False))[
                ..., :3] for s in scenes], noisy, masks, strict=True)])
    sigma = np.sqrt(np.sum(residuals ** 2) / (residuals.size - want.size))
    np.testing.assert_allclose(solved.std_error,
                               (sigma / np.sqrt(np.diag(normal))).reshape(res, res, 3),
                               rtol=1e-7)
    assert np.all(np.asarray(solved.coverage) >= 1)
    # one view sees only the front: the back's texels are unseen, reported as NaN
    one = solve_kd_texture(scenes[:1], targets[:1], masks[:1], 8, smoothness=1e-3)
    unseen = np.asarray(one.coverage) == 0
    assert unseen.any() and (~unseen).any()
    assert np.all(np.isnan(np.asarray(one.texels)[unseen]))
    assert not np.any(np.isnan(np.asarray(one.texels)[~unseen]))


@pytest.mark.cost(8)
def test_the_kd_texture_solve_reaches_dense_least_squares_where_the_stencil_is_inexact(x64):
    """Gouraud shading reads the texels at a face's three corners, far apart: the probed
    stencil is only a start, and the renders' iterations finish the same solve."""
    from fitting.solve import solve_kd_texture

    res = 4
    truth = ds.texture(np.random.default_rng(12).uniform(0.2, 0.7, (res, res, 3)))
    scenes, targets, masks = texture_views(truth, [0.0, 120.0, 240.0])
    settings = ds.RenderSettings(shading="gouraud", clamp=False)
    solved = solve_kd_texture(scenes, targets, masks, res, settings, smoothness=0.1,
                              tol=1e-13)
    lam, want = dense_solution(*dense_normal_equations(scenes, targets, masks, res, settings),
                               res, 0.1)
    np.testing.assert_allclose(solved.texels, want, atol=1e-8)
    assert solved.iterations > 1


@pytest.mark.cost(10)
def test_fit_texture_recovers_a_synthetic_kd_map_and_writes_its_files(tmp_path):
    from data_synth import make_dataset
    from fitting.texture_fit import fit_texture, write_maps

    data = make_dataset("icosphere", n_views=3, n_lights=1, size=24, texture=6, seed=1)
    solution = fit_texture(data, 6)
    coverage = np.asarray(solution.coverage)
    seen_twice = coverage >= 2
    assert seen_twice.sum() >= 12
    error = np.abs(np.asarray(solution.texels) - np.asarray(data.truth.kd.texels))
    assert np.median(error[seen_twice]) < 0.01  # 8-bit-free targets: only clipped highlights
    entries = write_maps(tmp_path, {"kd": solution})
    kd = np.load(tmp_path / "kd.npy")
    np.testing.assert_array_equal(np.isnan(kd).any(-1), coverage == 0)
    np.testing.assert_array_equal(np.load(tmp_path / "kd_coverage.npy"), coverage)
    assert ds.read_image(tmp_path / "kd.png").shape == (6, 6, 3)
    assert entries["kd"]["unseen_texels"] == int(np.sum(coverage == 0))
    assert entries["kd"]["npy"] == "kd.npy"
    with pytest.raises(ValueError, match="res: got kd=0"):
        fit_texture(data, 0)


def bilinear_normal_matrix(res, rng, reach=1):
    """A'A [R*R*3, R*R*3] of random pixels that each read a cell of texels (wrapped), as
    a texel grid's normal matrix: reach 1 reads a bilinear 2 x 2 cell (couplings at most
    one apart), reach 3 a 4 x 4 one (couplings up to 3 apart). Channels independent."""
    rows = []
    for _ in range(3 * res * res):
        row, col = rng.integers(res, size=2)
        read = np.zeros((res, res))
        for dr in range(reach + 1):
            for dc in range(reach + 1):
                read[(row + dr) % res, (col + dc) % res] += rng.uniform(0.1, 1.0)
        rows.append(read.reshape(-1))
    a = np.array(rows)
    return np.kron(a.T @ a, np.eye(3))


@pytest.mark.parametrize("res", [2, 3, 9])
def test_probed_stencil_is_the_operator_for_couplings_one_apart(res, x64):
    from fitting.solve.texture_stencil import block_stencil, stencil_operator

    normal = bilinear_normal_matrix(res, np.random.default_rng(res))

    def data(maps):
        return ((jnp.asarray(normal) @ maps[0].reshape(-1)).reshape(maps[0].shape),)
    operator = stencil_operator(block_stencil(data, (res,), jnp.float64), 1)
    t = np.random.default_rng(1).normal(size=(res, res, 3))
    np.testing.assert_allclose(operator((jnp.asarray(t),))[0].reshape(-1),
                               normal @ t.reshape(-1), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("res", [3, 8])
def test_the_block_stencil_of_two_maps_is_their_joint_operator(res, x64):
    """Pixels that read a bilinear cell of a kd map and of a ks map at the same place: the
    probed block stencil is the joint normal matrix, the couplings between the maps
    included, and its preconditioner inverts each texel's 2 x 2 block."""
    from fitting.solve.texture_stencil import (
        block_preconditioner,
        block_stencil,
        stencil_operator,
    )

    rng = np.random.default_rng(res)
    rows = []
    for _ in range(6 * res * res):
        row, col = rng.integers(res, size=2)
        read = np.zeros((2, res, res))
        for dr in range(2):
            for dc in range(2):
                read[:, (row + dr) % res, (col + dc) % res] += rng.uniform(0.1, 1.0, 2)
        rows.append(read.reshape(-1))
    a = np.array(rows)
    normal = a.T @ a  # [kd texels, ks texels] per channel
    n = res * res

    def data(maps):
        flat = jnp.stack([m.reshape(n, 3) for m in maps]).reshape(2 * n, 3)
        out = (jnp.asarray(normal) @ flat).reshape(2, res, res, 3)
        return out[0], out[1]
    stencil = block_stencil(data, (res, res), jnp.float64)
    maps = tuple(jnp.asarray(rng.normal(size=(res, res, 3))) for _ in range(2))
    got = stencil_operator(stencil, 2)(maps)
    np.testing.assert_allclose(np.stack(got), np.stack(data(maps)), rtol=1e-12, atol=1e-12)
    z = block_preconditioner(stencil, (0.0, 0.0), 1e-30)(maps)
    for i in range(n):
        block = normal[np.ix_([i, n + i], [i, n + i])]
        r = np.stack([m.reshape(n, 3)[i] for m in maps])
        np.testing.assert_allclose(np.stack([x.reshape(n, 3)[i] for x in z]),
                                   np.linalg.solve(block, r), rtol=1e-9)


@pytest.mark.parametrize("res", [9])
def test_probed_diagonal_is_exact_for_couplings_shorter_than_the_stride(res, x64):
    from fitting.solve.texture_stencil import block_stencil

    normal = bilinear_normal_matrix(res, np.random.default_rng(res), reach=3)
    stencil = block_stencil(
        lambda maps: ((jnp.asarray(normal) @ maps[0].reshape(-1)).reshape(maps[0].shape),),
        (res,), jnp.float64)
    np.testing.assert_allclose(stencil[(0, 0, (0, 0))].reshape(-1), np.diag(normal),
                               rtol=1e-12)


def test_the_material_fit_refuses_a_textured_truth_pointing_at_texture(tmp_path, capsys):
    from data_synth import make_dataset
    from diffshade.cli import main
    from fitting.data.folder import save_dataset

    save_dataset(make_dataset("icosphere", n_views=1, n_lights=1, size=12, texture=4),
                 tmp_path / "set")
    assert main(["fit", str(tmp_path / "set"), "-o", str(tmp_path / "bad")]) == 2
    assert "--texture kd=RES" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_a_batch_of_textured_views_renders_as_its_single_views():
    tex = ds.texture(np.random.default_rng(11).random((8, 16, 3)).astype(np.float32))
    cams = [ds.look_at((3 * np.sin(a), 0.5, 3 * np.cos(a)), (0, 0, 0), width=16, height=16)
            for a in (0.0, 2.0)]
    scene = ds.make_scene(ds.icosphere(1, uv=True), cams[0], [ds.directional_light((0, 0, -1))],
                          ds.material(kd=tex))
    settings = ds.RenderSettings(raster="soft")
    batch = ds.render_views(scene, cams, settings)
    for i, cam in enumerate(cams):
        np.testing.assert_allclose(batch[i], ds.render(ds.replace(scene, camera=cam), settings),
                                   atol=1e-6)
