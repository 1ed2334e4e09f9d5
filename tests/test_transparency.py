"""Transparency (material kt) against independent references, in float64.

The scene: two parallel quads seen by an orthographic camera, a transparent one (the
front material) in front of an opaque one wound clockwise, so that two-sided lighting
lights it with the (opaque) back material. Every quad edge lies on a pixel boundary, so
each pixel centre sees a known set of quads, and each quad has one closed-form colour
(a directional light along the view axis: N.L = N.H = 1). The NumPy closed form is
I = (1 - kt) I_front + kt I_behind per channel.
"""

import collections

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.test_util import check_grads
from test_structure import equations, primitive_counts

from diffshade import (
    RenderSettings,
    directional_light,
    look_at,
    make_scene,
    material,
    rasterize_scene,
    render,
    replace,
)
from diffshade.composite.transparency import soft_composite
from diffshade.pipeline.rendering import shade_fragments
from diffshade.raster.projection import project
from fitting.report.result import mtl_text

pytestmark = pytest.mark.usefixtures("x64")

SIZE, HALF = 16, 2.0  # the image spans [-2, 2]^2: pixel boundaries at multiples of 0.25
FRONT_BOX = (-0.5, 1.5, -0.5, 0.5)  # x0, x1, y0, y1 at z = 0.5
REAR_BOX = (-1.0, 1.0, -1.0, 0.75)  # at z = 0; no diagonal through a pixel centre
KT = (0.3, 0.6, 0.9)
BACKGROUND = np.array([0.05, 0.1, 0.2])
HARD, SOFT = RenderSettings(), RenderSettings(raster="soft", sigma=0.5, gamma=0.005)


def quad(box, z, clockwise):
    x0, x1, y0, y1 = box
    verts = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    faces = [[0, 2, 1], [0, 3, 2]] if clockwise else [[0, 1, 2], [0, 2, 3]]
    return verts, faces


def two_quads(mesh, kt=KT):
    fv, ff = quad(FRONT_BOX, 0.5, clockwise=False)
    rv, rf = quad(REAR_BOX, 0.0, clockwise=True)
    normals = [[0.0, 0.0, 1.0]] * 4 + [[0.0, 0.0, -1.0]] * 4
    m = mesh(fv + rv, ff + [[i + 4 for i in f] for f in rf], normals)
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=SIZE, height=SIZE,
                  projection="orthographic", ortho_height=2 * HALF, near=0.5, far=10.0)
    front = material(ka=0.2, kd=(0.9, 0.3, 0.2), ks=0.4, shininess=10.0, kt=kt)
    back = material(ka=0.1, kd=(0.1, 0.7, 0.4))
    light = directional_light((0.0, 0.0, -1.0), 0.8)
    return make_scene(m, cam, [light], front, back_material=back, two_sided=True,
                      global_ambient=0.2, background=BACKGROUND)


def inside(box, x, y):
    return box[0] < x < box[1] and box[2] < y < box[3]


def closed_form(kt=KT):
    """[H, W, 4] by NumPy: per pixel centre, which quads it sees, then the blend."""
    kt = np.broadcast_to(np.asarray(kt, np.float64), (3,))
    front = np.clip(0.2 * 0.2 + np.array([0.9, 0.3, 0.2]) * 0.8 + 0.4 * 0.8, 0, 1)
    rear = np.clip(0.1 * 0.2 + np.array([0.1, 0.7, 0.4]) * 0.8, 0, 1)
    centres = -HALF + (np.arange(SIZE) + 0.5) * (2 * HALF / SIZE)
    image = np.zeros((SIZE, SIZE, 4))
    for row, y in enumerate(centres[::-1]):  # row 0 is the top of the image
        for col, x in enumerate(centres):
            behind, alpha_behind = ((rear, 1.0) if inside(REAR_BOX, x, y)
                                    else (BACKGROUND, 0.0))
            if inside(FRONT_BOX, x, y):
                rgb = (1 - kt) * front + kt * behind
                alpha = 1 - np.mean(kt) * (1 - alpha_behind)
            else:
                rgb, alpha = behind, alpha_behind
            image[row, col] = [*rgb, alpha]
    return image


def test_hard_composite_matches_the_closed_form(mesh):
    image = np.asarray(render(two_quads(mesh), HARD))
    np.testing.assert_allclose(image, closed_form(), atol=1e-12)


def test_soft_composite_approaches_the_closed_form_for_small_sigma_and_gamma(mesh):
    sharp = RenderSettings(raster="soft", sigma=1e-5, gamma=1e-4)
    image = np.asarray(render(two_quads(mesh), sharp))
    np.testing.assert_allclose(image, closed_form(), atol=1e-6)


@pytest.mark.parametrize("settings", [HARD, SOFT], ids=["hard", "soft"])
def test_kt_zero_renders_as_the_opaque_material(mesh, settings):
    glass = two_quads(mesh, kt=0.0)
    opaque = replace(glass, material=replace(glass.material, kt=None))
    np.testing.assert_allclose(render(glass, settings), render(opaque, settings), atol=1e-12)


# ---------------------------------------------------------------- shared edges
# A glass grid (cells split along their diagonals) in front of the opaque rear quad. Its
# shared edges pass exactly through pixel centres: the diagonals of square cells whose
# corners lie on pixel boundaries ("diagonals"), and, with the corners on pixel centres,
# every grid line, the outer boundary and the vertices where up to eight faces meet
# ("centres"). Each pixel must see the glass once. Hard raster's tie rule (top-left) makes
# the glass cover the half-open box x0 <= x < x1, y0 < y <= y1 (NDC, y up); the "centres"
# images are a power of two pixels a side, so that NDC pixel centres are exact and lie on
# the outer boundary exactly.
EDGE_CASES = {  # name: (width, height, box, cells a side)
    "diagonals": (SIZE, SIZE, (-1.0, 1.0, -1.0, 1.0), 2),
    "diagonals_wide": (20, 12, (-1.0, 1.0, -0.5, 0.5), (4, 2)),
    "centres": (SIZE, SIZE, (-1.125, 0.875, -0.875, 1.125), 4),
    "centres_tall": (8, 16, (-0.875, 0.625, -1.125, 0.875), (3, 4)),
}


def glass_grid(mesh, width, height, box, cells, kt=KT):
    """Two-sided scene: the glass grid (front material, counter-clockwise) at z = 0.5 over
    the rear quad (back material) at z = 0, pixels 0.25 wide (orthographic)."""
    nx, ny = (cells, cells) if isinstance(cells, int) else cells
    xs, ys = np.linspace(box[0], box[1], nx + 1), np.linspace(box[2], box[3], ny + 1)
    verts = [[x, y, 0.5] for y in ys for x in xs]
    faces = []
    for j in range(ny):
        for i in range(nx):
            a, b, c, d = (j * (nx + 1) + i, j * (nx + 1) + i + 1,
                          (j + 1) * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i)
            faces += [[a, b, c], [a, c, d]] if (i + j) % 2 == 0 else [[a, b, d], [b, c, d]]
    rv, rf = quad(REAR_BOX, 0.0, clockwise=True)
    normals = [[0.0, 0.0, 1.0]] * len(verts) + [[0.0, 0.0, -1.0]] * 4
    m = mesh(verts + rv, faces + [[i + len(verts) for i in f] for f in rf], normals)
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=width, height=height,
                  projection="orthographic", ortho_height=height / 4, near=0.5, far=10.0)
    scene = two_quads(mesh, kt)
    return replace(scene, mesh=m, camera=cam)


def grid_closed_form(width, height, box, kt=KT):
    """[H, W, 4] by NumPy: the glass over the half-open box, seen once, over the rear."""
    kt = np.asarray(kt, np.float64)
    front = np.clip(0.2 * 0.2 + np.array([0.9, 0.3, 0.2]) * 0.8 + 0.4 * 0.8, 0, 1)
    rear = np.clip(0.1 * 0.2 + np.array([0.1, 0.7, 0.4]) * 0.8, 0, 1)
    image = np.zeros((height, width, 4))
    for row in range(height):
        for col in range(width):
            x, y = (col + 0.5 - width / 2) / 4, (height / 2 - row - 0.5) / 4
            behind, alpha = (rear, 1.0) if inside(REAR_BOX, x, y) else (BACKGROUND, 0.0)
            if box[0] <= x < box[1] and box[2] < y <= box[3]:
                behind, alpha = (1 - kt) * front + kt * behind, 1 - np.mean(kt) * (1 - alpha)
            image[row, col] = [*behind, alpha]
    return image


def on_shared_edge_count(width, height, box, cells):
    """How many pixel centres lie on a diagonal of a cell (the cases' shared edges that are
    not grid lines), so that a test cannot pass for want of such pixels."""
    nx, ny = (cells, cells) if isinstance(cells, int) else cells
    step_x, step_y = (box[1] - box[0]) / nx, (box[3] - box[2]) / ny
    count = 0
    for row in range(height):
        for col in range(width):
            x, y = (col + 0.5 - width / 2) / 4, (height / 2 - row - 0.5) / 4
            u, v = (x - box[0]) / step_x, (y - box[2]) / step_y
            if 0 < u < nx and 0 < v < ny and (u % 1 == v % 1 or u % 1 == 1 - v % 1):
                count += 1
    return count


@pytest.mark.parametrize("kernels", ["host", "jax"])
@pytest.mark.parametrize("case", EDGE_CASES)
def test_hard_glass_is_seen_once_on_edges_through_pixel_centres(mesh, case, kernels):
    width, height, box, cells = EDGE_CASES[case]
    assert on_shared_edge_count(width, height, box, cells) >= 4
    scene = glass_grid(mesh, width, height, box, cells)
    image = np.asarray(render(scene, replace(HARD, kernels=kernels)))
    np.testing.assert_allclose(image, grid_closed_form(width, height, box), atol=1e-12)


@pytest.mark.parametrize("case", ["diagonals", "diagonals_wide"])
def test_soft_glass_colour_is_seen_once_on_edges_through_pixel_centres(mesh, case):
    """Sharp soft raster: the colour is the closed form's. Alpha is SoftRas's product over
    faces, which counts the two half-covering faces of a pixel centre on a shared edge as
    two layers (docs/transparency.md, Limits): it is checked off those pixels only."""
    width, height, box, cells = EDGE_CASES[case]
    scene = glass_grid(mesh, width, height, box, cells)
    sharp = RenderSettings(raster="soft", sigma=1e-5, gamma=1e-4)
    image, want = np.asarray(render(scene, sharp)), grid_closed_form(width, height, box)
    np.testing.assert_allclose(image[..., :3], want[..., :3], atol=1e-6)
    frags = rasterize_scene(scene, sharp)
    on_edge = (np.asarray(frags.valid) & (np.asarray(frags.dist) == 0.0)).sum(-1) >= 2
    assert on_edge.sum() >= 4
    np.testing.assert_allclose(image[~on_edge, 3], want[~on_edge, 3], atol=1e-6)


def recursive_blend(colours, kt, logits, valid, zt, background):
    """The soft composite of one pixel written out: sort by depth (nearest first), then
    from the farthest layer forward B_k = the normalized-weight (D e^(zt / gamma)) sum over
    the layers j with zt_k - zt_j > 4 gamma and the background; layer k shows
    (1 - kt) c + kt B_k; the pixel is the plain SoftRas blend of what the layers show."""
    layers = [k for _, k in sorted((-zt[k], k) for k in range(len(zt)) if valid[k])]
    bg_logit = 1e-3 / SOFT.gamma

    def blend(members):
        w = np.array([logits[j] for j in members] + [bg_logit])
        w = np.exp(w - w.max())
        w = w / w.sum()
        return sum(w[n] * shown[j] for n, j in enumerate(members)) + w[-1] * background

    shown = {}
    for i in reversed(range(len(layers))):
        k = layers[i]
        behind = blend([j for j in layers[i + 1:] if zt[k] - zt[j] > 4.0 * SOFT.gamma])
        shown[k] = (1 - kt[k]) * colours[k] + kt[k] * behind
    return blend(layers)


def test_soft_composite_equals_a_per_pixel_recursion(mesh):
    scene = two_quads(mesh)
    frags = rasterize_scene(scene, SOFT)
    _, colours = shade_fragments(scene, project(scene), frags, SOFT)
    dist, valid = np.asarray(frags.dist), np.asarray(frags.valid)
    kt = np.where(np.asarray(frags.front)[..., None], np.asarray(KT), 0.0)
    cam = scene.camera
    got = np.asarray(soft_composite(colours, jnp.asarray(kt), frags, scene.background,
                                    cam.near, cam.far, SOFT.sigma, SOFT.gamma))
    depth = np.where(valid, np.asarray(frags.depth), 1.0)
    zt = np.clip((1 / depth - 1 / 10.0) / (1 / 0.5 - 1 / 10.0), 0, 1)
    logits = -np.logaddexp(0.0, -dist / SOFT.sigma) + zt / SOFT.gamma
    colours = np.asarray(colours)
    assert int(frags.dropped) == 0 and valid.sum(-1).max() >= 2
    for row in range(SIZE):
        for col in range(SIZE):
            want = recursive_blend(colours[row, col], kt[row, col], logits[row, col],
                                   valid[row, col], zt[row, col], BACKGROUND)
            np.testing.assert_allclose(got[row, col, :3], want, atol=1e-12)
    cover = 1 / (1 + np.exp(-dist / SOFT.sigma))
    clear = np.prod(np.where(valid, 1 - cover * (1 - kt.mean(-1)), 1.0), -1)
    np.testing.assert_allclose(got[..., 3], 1 - clear, atol=1e-12)


@pytest.mark.parametrize("settings", [HARD, SOFT], ids=["hard", "soft"])
def test_kt_gradients_equal_central_differences(mesh, settings):
    scene = two_quads(mesh)
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (SIZE, SIZE, 4)))

    def loss(kt, kd):
        mat = replace(scene.material, kt=kt, kd=kd)
        return jnp.sum(weights * render(replace(scene, material=mat), settings))

    check_grads(loss, (scene.material.kt, scene.material.kd), order=1, modes=["rev"],
                eps=1e-6, atol=1e-6, rtol=1e-6)


def test_kt_is_recovered_by_gradient_descent(mesh):
    """The fit a driver would run: Adam on logit(kt) against a target rendered with KT."""
    target = render(two_quads(mesh), HARD)
    start = two_quads(mesh, kt=0.5)

    @jax.jit
    def loss(u):
        mat = replace(start.material, kt=jax.nn.sigmoid(u))
        return jnp.mean((render(replace(start, material=mat), HARD) - target) ** 2)

    opt = optax.adam(0.1)
    u = jnp.zeros(3)
    state = opt.init(u)
    step = jax.jit(lambda u, s: opt.update(jax.grad(loss)(u), s))
    for _ in range(300):
        updates, state = step(u, state)
        u = optax.apply_updates(u, updates)
    np.testing.assert_allclose(jax.nn.sigmoid(u), KT, atol=1e-4)


def layer_sorts(scene, settings):
    """The sort equations over a per-pixel layer axis ([H, W, K] operands) in the jaxpr
    of render(scene), sub-jaxprs included."""
    return [eqn for eqn in equations(scene, settings)
            if eqn.primitive.name == "sort" and eqn.invars[0].aval.ndim == 3]


def test_opaque_scenes_compile_no_layer_sorting_and_transparent_ones_do(mesh):
    glass = two_quads(mesh)
    opaque = replace(glass, material=replace(glass.material, kt=None))
    for settings in (HARD, SOFT):
        assert not layer_sorts(opaque, settings)
        # hard layers arrive nearest first from the search; soft ones are ranked by weight
        assert len(layer_sorts(glass, settings)) == (settings.raster == "soft")
        if settings.raster == "hard":
            # (soft: an opaque scene lights only its active slots, in capacity tiers
            # (shading.compact), more code for less work than shading every layer)
            assert sum(primitive_counts(glass, settings).values()) > sum(
                primitive_counts(opaque, settings).values())
    # hard raster keeps one fragment per pixel unless something is transparent
    assert rasterize_scene(opaque, HARD).face_ids.shape[-1] == 1
    assert rasterize_scene(glass, HARD).face_ids.shape[-1] == HARD.faces_per_pixel


def test_kt_is_validated():
    for bad in (-0.1, 1.5, (0.2, 0.3), "clear", float("nan")):
        with pytest.raises(ValueError, match="kt: got"):
            material(kt=bad)
    assert collections.Counter(np.asarray(material(kt=0.25).kt).tolist()) == {0.25: 3}


def test_mtl_writes_kt_as_tr():
    text = mtl_text(material(kd=0.5, kt=(0.2, 0.4, 0.9)))
    assert "Tr 0.500000" in text.splitlines() and "Tf 0.200000 0.400000 0.900000" in text
    assert "Tr" not in mtl_text(material(kd=0.5))
