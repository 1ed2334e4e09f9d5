"""render: project -> rasterize -> interpolate -> shade -> blend, as a short composition.

Shading modes (RenderSettings.shading), following OpenGL 1.x:
- 'phong': normals interpolated perspective-correctly and renormalized, lit per fragment;
  the final colour is clamped (when clamping is on).
- 'gouraud': lit per vertex, each vertex colour clamped, then interpolated.
- 'flat': one evaluation per face, at the centroid with the face normal.
- 'flat_last': OpenGL's flat shading: the whole face takes the lit colour of its last
  vertex (the provoking vertex), computed with that vertex's normal.
Two-sided lighting (scene.two_sided) flips the normal and uses the back material on faces
that are clockwise on screen, as OpenGL does.
"""

import dataclasses
import functools
from functools import partial

import jax
import jax.numpy as jnp

from diffshade.blend import hard_blend, soft_blend, soft_weights
from diffshade.camera import view_dir_infinite
from diffshade.compact import on_active
from diffshade.interpolate import gather_faces, interpolate_tree
from diffshade.numerics import clamp01, safe_normalize
from diffshade.project import Projected, project
from diffshade.raster import Fragments, face_edge_coefficients, rasterize
from diffshade.scene import Scene
from diffshade.settings import RenderSettings
from diffshade.shading import ShadingParts, shade


def view_dirs(scene, points):
    """Unit directions towards the viewer, [..., 3] for points [..., 3]: local (to the eye)
    or infinite (the camera's +z axis)."""
    if scene.local_viewer:
        return safe_normalize(scene.camera.eye - points)
    return jnp.broadcast_to(view_dir_infinite(scene.camera), points.shape).astype(points.dtype)


def _fill_absent(material, other):
    """`material` with each absent optional term (ks, emission) set to zeros shaped like
    `other`'s, so that front and back materials share one structure."""
    changes = {name: jnp.zeros_like(getattr(other, name)) for name in ("ks", "emission")
               if getattr(material, name) is None and getattr(other, name) is not None}
    shininess = material.shininess if material.shininess is not None else other.shininess
    return dataclasses.replace(material, shininess=shininess, **changes)


def _pick_material(scene, front):
    """Front material where `front`, back material elsewhere; front: [...] bool."""
    back = scene.material if scene.back_material is None else scene.back_material
    front_mat, back = _fill_absent(scene.material, back), _fill_absent(back, scene.material)

    def pick(f, b):
        mask = front.reshape(front.shape + (1,) * jnp.ndim(f))
        return jnp.where(mask, f, b)
    return jax.tree.map(pick, front_mat, back)


def _shade_points(scene, settings, points, normals, front) -> ShadingParts:
    """Light samples with OpenGL's two-sided rule; front: [...] bool."""
    material = scene.material
    if scene.two_sided:
        normals = jnp.where(front[..., None], normals, -normals)
        material = _pick_material(scene, front)
    return shade(material, scene.lights, scene.global_ambient, points, normals,
                 view_dirs(scene, points), settings)


def _colour(parts, settings):
    return clamp01(parts.total) if settings.clamp else parts.total


def _phong(scene, proj, frags, settings, active=None):
    faces = scene.mesh.faces
    points, normals = interpolate_tree((proj.world, proj.normals), faces, frags)

    def light(points, normals, front):
        parts = _shade_points(scene, settings, points, safe_normalize(normals), front)
        return parts, _colour(parts, settings)
    if active is None:
        return light(points, normals, frags.front)
    height, width, k = frags.face_ids.shape
    capacity = height * width * min(k, ACTIVE_SLOTS_PER_PIXEL)
    return on_active(light, active, capacity, points, normals, frags.front)


def _vertex_sides(scene, proj, settings):
    """Per-vertex (parts, colour) lit as front and, when two-sided, as back faces."""
    n = proj.world.shape[0]
    sides = [True, False] if scene.two_sided else [True]
    lit = [_shade_points(scene, settings, proj.world, proj.normals, jnp.full(n, side))
           for side in sides]
    return [(parts, _colour(parts, settings)) for parts in lit]


def _by_side(sides, front, select):
    """Combine per-side values with `select(side)`, choosing by front-facing."""
    values = [select(side) for side in sides]
    if len(values) == 1:
        return values[0]
    return jax.tree.map(lambda f, b: jnp.where(front[..., None], f, b), *values)


def _gouraud(scene, proj, frags, settings):
    sides = _vertex_sides(scene, proj, settings)
    parts, colour = _by_side(sides, frags.front,
                             lambda side: interpolate_tree(side, scene.mesh.faces, frags))
    # the interpolated clamped colours can exceed 1 by a rounding error; keep [0, 1] exact
    return parts, clamp01(colour) if settings.clamp else colour


def _flat_last(scene, proj, frags, settings):
    last = scene.mesh.faces[:, 2]
    sides = _vertex_sides(scene, proj, settings)
    return _by_side(sides, frags.front,
                    lambda side: jax.tree.map(lambda a: gather_faces(a[last], frags), side))


def flat_samples(scene, proj: Projected):
    """Per face, where flat shading lights it: centroids [F, 3], unit face normals [F, 3]
    and front [F] bool (counter-clockwise on screen)."""
    tri = proj.world[scene.mesh.faces]
    normals = safe_normalize(jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    _, det = face_edge_coefficients(proj.clip, scene.mesh.faces)
    return tri.mean(1), normals, det > 0


def _flat(scene, proj, frags, settings):
    parts = _shade_points(scene, settings, *flat_samples(scene, proj))
    return jax.tree.map(lambda a: gather_faces(a, frags), (parts, _colour(parts, settings)))


DEFAULT_SETTINGS = RenderSettings()

_SHADERS = {"phong": _phong, "gouraud": _gouraud, "flat": _flat, "flat_last": _flat_last}


#: Phong shading of a soft render lights at most this many slots per pixel on average
#: when only that many have a non-zero blend weight (diffshade.compact); else all of them
ACTIVE_SLOTS_PER_PIXEL = 4


def shade_fragments(scene, proj: Projected, frags: Fragments, settings, active=None):
    """(ShadingParts, colour) per fragment, each [H, W, K, 3], by settings.shading.

    active: optional [H, W, K] bool, the fragments whose colour matters; Phong shading
    may then skip the others (their values are then 0; see diffshade.compact)."""
    if settings.shading == "phong":
        return _phong(scene, proj, frags, settings, active)
    return _SHADERS[settings.shading](scene, proj, frags, settings)


def check_arguments(scene, settings):
    """Raise a clear TypeError unless scene is a Scene and settings a RenderSettings
    (checked before jit: a dict as a static argument fails while being hashed)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene: got {type(scene).__name__}; expected Scene "
                        "(diffshade.make_scene)")
    if not isinstance(settings, RenderSettings):
        raise TypeError(f"settings: got {type(settings).__name__}; expected RenderSettings")


def _checked(jitted):
    """The public entry point of a jitted renderer: arguments checked, then the call."""
    @functools.wraps(jitted)
    def entry(scene, settings=DEFAULT_SETTINGS, *args, **kwargs):
        check_arguments(scene, settings)
        return jitted(scene, settings, *args, **kwargs)
    entry._cache_size = jitted._cache_size
    return entry


@partial(jax.jit, static_argnames=("settings",))
def _rasterize_scene(scene, settings=DEFAULT_SETTINGS) -> Fragments:
    """Project and rasterize the scene's mesh (cache the result when geometry is fixed)."""
    return rasterize(project(scene), scene.mesh.faces, scene.camera, settings)


def blend(scene, colours, frags: Fragments, settings):
    """Hard (nearest fragment) or soft (SoftRas) blending by settings.raster: [H, W, 4]."""
    if settings.raster == "hard":
        return hard_blend(colours, frags, scene.background)
    cam = scene.camera
    image = soft_blend(colours, frags, scene.background, cam.near, cam.far, settings.sigma,
                       settings.gamma)
    if not settings.clamp:
        return image
    # the weights sum to 1 only up to rounding: keep a blend of clamped colours in [0, 1]
    return jnp.concatenate([clamp01(image[..., :3]), image[..., 3:]], -1)


def render_fragments(scene, frags: Fragments, settings=DEFAULT_SETTINGS):
    """Shade and blend cached fragments: [H, W, 4] RGBA. In soft mode only the fragments
    with a non-zero blend weight need a colour (shade_fragments' `active`)."""
    active = None
    if settings.raster == "soft":
        cam = scene.camera
        weights = soft_weights(frags, cam.near, cam.far, settings.sigma, settings.gamma)
        active = weights[..., :-1] > 0.0
    _, colours = shade_fragments(scene, project(scene), frags, settings, active)
    return blend(scene, colours, frags, settings)


@partial(jax.jit, static_argnames=("settings",))
def _render(scene, settings=DEFAULT_SETTINGS):
    """Render the scene: [H, W, 4] RGBA (alpha = coverage) over scene.background."""
    return render_fragments(scene, rasterize_scene(scene, settings), settings)


@partial(jax.jit, static_argnames=("settings",))
def _render_parts(scene, settings=DEFAULT_SETTINGS) -> ShadingParts:
    """The unclamped ambient, diffuse, specular and emission images, each [H, W, 3]
    (zero where no face covers the pixel)."""
    frags = rasterize_scene(scene, settings)
    parts, _ = shade_fragments(scene, project(scene), frags, settings)
    return parts.map(lambda a: jnp.where(frags.valid[..., 0, None], a[..., 0, :], 0.0))


def downsample(image, factor: int):
    """Box-filter an [H*f, W*f, C] image to [H, W, C]."""
    h, w, c = image.shape
    return image.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3))


@partial(jax.jit, static_argnames=("settings", "factor"))
def _render_supersampled(scene, settings=DEFAULT_SETTINGS, factor: int = 2):
    """Anti-aliased render: render at factor x the camera's resolution, then box-filter
    down: [H, W, 4]."""
    cam = dataclasses.replace(scene.camera, width=scene.camera.width * factor,
                              height=scene.camera.height * factor)
    big = render(dataclasses.replace(scene, camera=cam), settings)
    return downsample(big, factor)


rasterize_scene = _checked(_rasterize_scene)
render = _checked(_render)
render_parts = _checked(_render_parts)
render_supersampled = _checked(_render_supersampled)
