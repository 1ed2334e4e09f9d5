"""render: project -> rasterize -> weights -> shade what counts -> blend, each once.

Shading modes (RenderSettings.shading) follow OpenGL 1.x; where each mode lights the
surface and how fragments read the lit colours is diffshade.shading.samples (shared with the
fitting cache):
- 'phong': normals interpolated perspective-correctly and renormalized, lit per fragment;
  the final colour is clamped (when clamping is on).
- 'gouraud': lit per vertex, each vertex colour clamped, then interpolated.
- 'flat': one evaluation per face, at the centroid with the face normal.
- 'flat_last': OpenGL's flat shading: the whole face takes the lit colour of its last
  vertex (the provoking vertex), computed with that vertex's normal.
Two-sided lighting (scene.two_sided) flips the normal on faces that are clockwise on
screen and lights them with the back material, when the scene has one, as OpenGL does.
In a scene of several objects each sample takes its object's (front or back) material.

In soft mode the blend weights are computed once, before shading: Phong shading then
lights only the fragments whose weight is not 0 (diffshade.shading.compact).

A scene with a transparent material (kt) keeps K layers in hard mode too and composites
them (diffshade.composite.transparency); an opaque scene compiles none of that.
"""

import dataclasses
import functools
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.composite.blend import hard_blend, soft_blend, soft_weights
from diffshade.composite.transparency import (
    fragment_kt,
    hard_composite,
    layers_needed,
    soft_composite,
)
from diffshade.numerics import clamp01, safe_normalize
from diffshade.pipeline.cost import check_render
from diffshade.raster.fragments import Fragments, rasterize
from diffshade.raster.projection import Projected, project
from diffshade.scene.camera import Camera, view_dir_infinite
from diffshade.scene.materials import Material, has_textures
from diffshade.scene.mesh import check_mesh
from diffshade.scene.objects import take_material
from diffshade.scene.scene import Scene
from diffshade.settings import RenderSettings
from diffshade.shading.compact import on_active, take_rows
from diffshade.shading.lighting import ShadingParts, reads_points, shade
from diffshade.shading.samples import Samples, phong_samples_at, read, shading_samples
from diffshade.shading.shadows import shadow_maps
from diffshade.shading.texturing import textured_material

DEFAULT_SETTINGS = RenderSettings()

#: Phong shading of a soft render lights only the slots with a non-zero blend weight, in
#: an array of the first of these sizes (slots per pixel on average) that holds them all
#: (diffshade.shading.compact's tiers); all the slots when none does
ACTIVE_SLOTS_PER_PIXEL = (3, 4)


def view_dirs(scene, points):
    """Unit directions towards the viewer, [..., 3] for points [..., 3]: local (to the eye)
    or infinite (the camera's +z axis)."""
    return jnp.broadcast_to(_view_dirs(scene, points), points.shape)


def _view_dirs(scene, points):
    """view_dirs, where an infinite viewer's is one direction [3]: shade broadcasts it
    where it meets the normals, and reverse mode keeps no copy of it per sample."""
    if scene.local_viewer:
        return safe_normalize(scene.camera.eye - points)
    return view_dir_infinite(scene.camera).astype(points.dtype)


def _fill_absent(material, other):
    """`material` with each absent optional term (ks, emission) set to zeros shaped like
    `other`'s, so that front and back materials share one structure."""
    changes = {name: jnp.zeros_like(getattr(other, name)) for name in ("ks", "emission", "kt")
               if getattr(material, name) is None and getattr(other, name) is not None}
    shininess = material.shininess if material.shininess is not None else other.shininess
    return dataclasses.replace(material, shininess=shininess, **changes)


def _material_at(scene, front, objects=None, uv=None, valid=None, host=None):
    """The material of each sample: the front one, or the back material where `front` is
    False when the scene has one; front: [...] bool; objects: [...] int32 object ids in a
    scene of several objects (its materials are stacked), else None; uv: [..., 2] where
    the scene has textures (read here, where valid, by host kernels or not:
    diffshade.shading.texturing), else None."""
    material = textured_material(scene.material, uv, host, valid)
    back_material = textured_material(scene.back_material, uv, host, valid)
    if objects is not None:
        material = take_material(material, objects)
    if not scene.two_sided or back_material is None:
        return material
    if objects is not None:
        back_material = take_material(back_material, objects)
    front_mat = _fill_absent(material, back_material)
    back = _fill_absent(back_material, material)

    # a field's own axes ([3], or none for shininess) follow the samples' axes, whether it
    # is one value, stacked per object and taken per sample, or read from a texture
    def pick(name):
        f, b = getattr(front_mat, name), getattr(back, name)
        if f is None:
            return None
        own = 0 if name == "shininess" else 1
        return jnp.where(front.reshape(front.shape + (1,) * own), f, b)
    return Material(**{f.name: pick(f.name) for f in dataclasses.fields(Material)})


def shade_samples(scene, samples: Samples, settings, maps=None):
    """(ShadingParts, colour) of each sample, [..., 3] each; colour clamped as OpenGL
    clamps (per sample) when settings.clamp. maps: the scene's shadow_maps (None: none)."""
    material = _material_at(scene, samples.front, samples.objects, samples.uv, samples.valid,
                            settings.use_host_kernels())
    parts = shade(material, scene.lights, scene.global_ambient,
                  samples.points, samples.normals, _view_dirs(scene, samples.points), settings,
                  maps)
    return parts, clamp01(parts.total) if settings.clamp else parts.total


def shade_fragments(scene, proj: Projected, frags: Fragments, settings, active=None,
                    axis_name=None):
    """(ShadingParts, colour) per fragment, each [H, W, K, 3], by settings.shading.

    active: optional [H, W, K] bool, the fragments whose colour matters; Phong shading
    then interpolates and lights only those (the others' values are 0 or unspecified;
    see _shade_active, and diffshade.shading.compact's axis_name for a batch of views)."""
    host, light, points = _lighting(scene, settings)
    if active is not None and settings.shading == "phong":
        parts, colour = _shade_active(scene, proj, frags, active, light, axis_name, host,
                                      points)
    else:
        samples, reader = shading_samples(scene, proj, frags, settings.shading, host, points)
        parts, colour = read(light(samples), reader, host)
    # interpolated clamped colours can exceed 1 by a rounding error; keep [0, 1] exact
    return parts, clamp01(colour) if settings.clamp else colour


def _lighting(scene, settings):
    """(whether host kernels run, light(Samples) -> (ShadingParts, colour) by
    shade_samples, whether `light` reads the samples' points): directional and ambient
    light seen from afar read the normals only."""
    maps = shadow_maps(scene, settings)
    light = lambda samples: shade_samples(scene, samples, settings, maps)
    return (settings.use_host_kernels(), light,
            scene.local_viewer or reads_points(scene.lights, maps))


def _shade_active(scene, proj, frags, active, light, axis_name, host, points=True,
                  weights=None):
    """Phong shading of the active fragments (active [H, W, K] bool): on_active gives
    their positions among the slots (and gathers their sides), and only those are
    interpolated (phong_samples_at reads their face ids and barycentrics there) and lit;
    light(Samples) -> (ShadingParts, colour); points: whether `light` reads the samples'
    points (phong_samples). Should on_active process every slot, the inactive ones are lit
    too, and their weight 0 drops them.

    weights: the slots' blend weights [H, W, K] (active where > 0): then returns their
    weighted sum of the colours per pixel, [H, W, 3], summed from the active rows
    (on_active's group) with no [H, W, K, 3] array of colours."""
    height, width, k = frags.face_ids.shape
    capacity = tuple(sorted({height * width * min(k, tier) for tier in ACTIVE_SLOTS_PER_PIXEL}))

    def lit(rows, front, face_ids, bary, *weight):
        shaded = light(phong_samples_at(scene, proj, rows, face_ids, bary, front, host, points))
        if not weight:
            return shaded
        # the padding's rows (N) read a weight of 0
        return shaded[1] * take_rows(weight[0], rows, host, clip=False)[:, None]
    # the face ids and barycentrics pass whole, as arguments (not closed over: a closure
    # would cross each tier's branch, and its derivative, as a separate array)
    whole = (frags.face_ids, frags.bary) + (() if weights is None else (weights,))
    return on_active(lit, active, capacity, frags.front, axis_name=axis_name, host=host,
                     positions=True, whole=whole, group=weights is not None)


def blended_colour(scene, proj, frags, settings, weights, axis_name=None):
    """sum_k w_k c_k [H, W, 3] of soft_blend for the slots' weights [H, W, K] (> 0: the
    fragments whose colour matters), the colours c by settings.shading: with Phong shading
    only the active fragments are lit and summed per pixel (_shade_active's weights)."""
    if settings.shading != "phong":
        _, colours = shade_fragments(scene, proj, frags, settings, None, axis_name)
        return jnp.sum(weights[..., None] * colours, -2)
    host, light, points = _lighting(scene, settings)
    # shade_samples' colours are clamped per sample already where settings.clamp
    return _shade_active(scene, proj, frags, weights > 0.0, light, axis_name, host, points,
                         weights)


def _check_types(scene, settings):
    if not isinstance(scene, Scene):
        raise TypeError(f"scene: got {type(scene).__name__}; expected Scene "
                        "(diffshade.make_scene)")
    if not isinstance(settings, RenderSettings):
        raise TypeError(f"settings: got {type(settings).__name__}; expected RenderSettings")


def _check_mesh_data(mesh):
    """The scene's mesh checked as mesh_from_arrays checks its input (scene.mesh.check_mesh:
    finite vertices and normals, at least one face, integer face indices in range), where
    its arrays are concrete: a Mesh made directly (Mesh(...), replace) is not checked
    before, and an index out of range would make the rasterizer read outside the
    vertices. A mesh traced under the caller's jit is left to the kernels, which skip
    such a face (host.candidates._corners_exist)."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(mesh)):
        return
    for field in ("vertices", "faces", "normals") + (() if mesh.uv is None else ("uv",)):
        value = getattr(mesh, field)
        if not isinstance(value, (jax.Array, np.ndarray)):
            raise TypeError(f"scene.mesh.{field}: got {type(value).__name__}; expected an "
                            "array (mesh_from_arrays makes a Mesh of any array-like data)")
    if not jnp.issubdtype(mesh.faces.dtype, jnp.integer):
        raise TypeError(f"scene.mesh.faces: got dtype {mesh.faces.dtype}; expected integers "
                        "(mesh_from_arrays converts whole numbers)")
    check_mesh(mesh, name=lambda field: f"scene.mesh.{field}")


def check_arguments(scene, settings, views=1, factor=1, camera=None):
    """Raise a clear TypeError unless scene is a Scene and settings a RenderSettings, a
    ValueError where the scene's mesh data is not what a Mesh holds (_check_mesh_data),
    and budget.SizeError when rendering it (from `views` cameras of `camera`'s size,
    default the scene's own, at `factor` x their resolution) needs more memory than is
    available (checked before jit, at the API boundary)."""
    _check_types(scene, settings)
    settings.validate()
    _check_mesh_data(scene.mesh)
    textured = has_textures(scene.material) or has_textures(scene.back_material)
    if textured and (scene.mesh.uv is None or scene.objects is not None):
        raise ValueError("scene.material: has a texture; expected a scene of one object whose "
                         "mesh has UVs (mesh.uv)")
    costed = scene if camera is None else dataclasses.replace(scene, camera=camera)
    check_render(costed, settings, views, factor)


def finite_image(image):
    """image (a render's result), after checking that every value is finite where it is
    concrete (called outside jit): a scene whose numbers pass every builder's check can
    still overflow float32 on the way (vertices some 1e19 times farther out than the
    camera is from them, a point light 1e20 away), and the caller gets a ValueError saying
    so rather than NaN pixels. Under the caller's jit the image is returned as it is."""
    if isinstance(image, jax.core.Tracer):
        return image
    bad = int(jnp.size(image) - jnp.count_nonzero(jnp.isfinite(image)))
    if bad:
        raise ValueError(
            f"scene: its image has {bad} values that are not finite (NaN or inf); expected "
            "numbers float32 can hold on the way: a coordinate, a light's position or "
            "power, or the camera's lens at an extreme scale overflows (jax_enable_x64 "
            "renders in float64, whose range is far wider)")
    return image


def _checked(jitted, image=False):
    """The public entry point of a jitted renderer: arguments checked, then the call (its
    result checked by finite_image where `image`)."""
    @functools.wraps(jitted)
    def entry(scene, settings=DEFAULT_SETTINGS, *args, **kwargs):
        check_arguments(scene, settings)
        out = jitted(scene, settings, *args, **kwargs)
        return finite_image(out) if image else out
    return entry


@jax.jit
def _rasterize_scene(scene, settings=DEFAULT_SETTINGS) -> Fragments:
    """Project and rasterize the scene's mesh (cache the result when geometry is fixed)."""
    return rasterize(project(scene), scene.mesh.faces, scene.camera, settings,
                     layers=layers_needed(scene, settings))


def blend_weights(scene, frags: Fragments, settings):
    """Soft mode's aggregation weights (per slot [H, W, K], the background's [H, W];
    blend.soft_weights), or None in hard mode."""
    if settings.raster == "hard":
        return None
    cam = scene.camera
    return soft_weights(frags, cam.near, cam.far, settings.sigma, settings.gamma)


def _composite(scene, colours, frags, settings, kt):
    """blend for a transparent scene: the layers composited (diffshade.composite.transparency)."""
    if settings.raster == "hard":
        return hard_composite(colours, kt, frags, scene.background)
    cam = scene.camera
    return soft_composite(colours, kt, frags, scene.background, cam.near, cam.far,
                          settings.sigma, settings.gamma)


def blend(scene, colours, frags: Fragments, settings, weights=None, kt=None, summed=None):
    """Hard (nearest fragment) or soft (SoftRas) blending by settings.raster: [H, W, 4].
    weights: blend_weights, when the caller has them already. kt: [H, W, K, 3] per-fragment
    transparency (transparency.fragment_kt) composites the layers instead. summed: soft
    mode's sum_k w_k c_k (blended_colour), when the caller has it."""
    if settings.raster == "hard" and kt is None:
        return hard_blend(colours, frags, scene.background)
    cam = scene.camera
    image = (_composite(scene, colours, frags, settings, kt) if kt is not None else
             soft_blend(colours, frags, scene.background, cam.near, cam.far, settings.sigma,
                        settings.gamma, weights, summed))
    if not settings.clamp:
        return image
    # the weights sum to 1 only up to rounding: keep a blend of clamped colours in [0, 1]
    return jnp.concatenate([clamp01(image[..., :3]), image[..., 3:]], -1)


def render_fragments(scene, frags: Fragments, settings=DEFAULT_SETTINGS, axis_name=None,
                     proj: Projected | None = None):
    """Shade and blend cached fragments: [H, W, 4] RGBA. In soft mode only the fragments
    with a non-zero blend weight need a colour (blended_colour); transparent layers behind
    them may show, so a transparent scene shades every fragment. proj: the scene's
    Projected when the caller has it (fixed geometry), else projected here."""
    kt = fragment_kt(scene, frags)
    weights = None if kt is not None else blend_weights(scene, frags, settings)
    proj = project(scene) if proj is None else proj
    if weights is not None:
        summed = blended_colour(scene, proj, frags, settings, weights[0], axis_name)
        return blend(scene, None, frags, settings, weights, summed=summed)
    _, colours = shade_fragments(scene, proj, frags, settings, None, axis_name)
    return blend(scene, colours, frags, settings, weights, kt)


@jax.jit
def _render(scene, settings=DEFAULT_SETTINGS):
    """Render the scene: [H, W, 4] RGBA (alpha = coverage) over scene.background."""
    return render_fragments(scene, _rasterize_scene(scene, settings), settings)


@jax.jit
def _render_parts(scene, settings=DEFAULT_SETTINGS) -> ShadingParts:
    """The unclamped ambient, diffuse, specular and emission images, each [H, W, 3]
    (zero where no face covers the pixel)."""
    frags = _rasterize_scene(scene, settings)
    parts, _ = shade_fragments(scene, project(scene), frags, settings)
    return parts.map(lambda a: jnp.where(frags.valid[..., 0, None], a[..., 0, :], 0.0))


def stack_cameras(cameras) -> Camera:
    """One Camera whose array fields have a leading view axis [N, ...], from a sequence of
    cameras of one image size and projection (or such a stacked Camera, returned as is)."""
    if isinstance(cameras, Camera):
        return cameras
    cameras = list(cameras)
    if not cameras or not all(isinstance(c, Camera) for c in cameras):
        raise TypeError(f"cameras: got {cameras!r}; expected a non-empty sequence of Camera")
    static = {(c.width, c.height, c.projection) for c in cameras}
    if len(static) > 1:
        raise ValueError(f"cameras: got image sizes / projections {sorted(static)}; expected "
                         "one (a batched render has one image shape)")
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *cameras)


@jax.jit
def _render_views(scene, cameras, settings=DEFAULT_SETTINGS):
    def one(cam):
        view = dataclasses.replace(scene, camera=cam)
        return render_fragments(view, _rasterize_scene(view, settings), settings, "views")
    return jax.vmap(one, axis_name="views")(cameras)


def render_views(scene, cameras, settings=DEFAULT_SETTINGS):
    """Render one scene from N cameras as one batched call: [N, H, W, 4]. cameras: a
    sequence of Camera of one image size (or a stacked Camera, see stack_cameras); the
    scene's own camera is ignored."""
    _check_types(scene, settings)
    cameras = stack_cameras(cameras)
    views = jax.tree.leaves(cameras)[0].shape[0]
    check_arguments(scene, settings, views, camera=jax.tree.map(lambda a: a[0], cameras))
    return finite_image(_render_views(scene, cameras, settings))


def downsample(image, factor: int):
    """Box-filter an [H*f, W*f, C] image to [H, W, C]."""
    h, w, c = image.shape
    return image.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3))


@partial(jax.jit, static_argnames=("factor",))
def _render_supersampled(scene, settings=DEFAULT_SETTINGS, factor: int = 2):
    """Anti-aliased render: render at factor x the camera's resolution, then box-filter
    down: [H, W, 4]."""
    cam = dataclasses.replace(scene.camera, width=scene.camera.width * factor,
                              height=scene.camera.height * factor)
    big = _render(dataclasses.replace(scene, camera=cam), settings)
    return downsample(big, factor)


rasterize_scene = _checked(_rasterize_scene)
render = _checked(_render, image=True)
render_parts = _checked(_render_parts)


def render_supersampled(scene, settings=DEFAULT_SETTINGS, factor: int = 2):
    """Anti-aliased render: render at factor x the camera's resolution, then box-filter
    down: [H, W, 4]."""
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor: got {factor!r}; expected an integer >= 1")
    check_arguments(scene, settings, factor=factor)
    return finite_image(_render_supersampled(scene, settings, factor))
