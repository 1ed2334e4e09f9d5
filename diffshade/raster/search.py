"""The candidate search: which faces reach which pixel, best first (discrete, no gradient).

A compiled kernel on the host (diffshade.host.candidates, through diffshade.host.hostcall;
under `vmap`, views of one mesh are searched in one call), or tile binning in JAX
(diffshade.raster.tile_search), as RenderSettings.kernels says. Both rank faces the same
way: nearest first in hard mode, by their weight in the soft blend in soft mode, up to
`search_depth` faces per pixel. diffshade.raster.fragments turns the ids into fragments.
"""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.host.candidates import find_candidates
from diffshade.host.hostcall import host_call
from diffshade.raster.tile_search import search_tiles

#: the JAX search's tiles (pixels a side) and faces tested per tile and pass
#: (tile_search.py): a tile touched by more faces takes more passes, so this trades
#: passes against the work wasted on tiles with fewer faces, never correctness
TILE, TILE_CAPACITY = 8, 128


def soft_radius(settings):
    """Soft footprint radius in pixels: where sigmoid(-d^2 / sigma) falls to the threshold t,
    d^2 = sigma * ln((1 - t) / t). A JAX scalar (sigma and t are data)."""
    t = jnp.asarray(settings.soft_threshold)
    return jnp.sqrt(settings.sigma * jnp.log((1.0 - t) / t))


def search_faces(clip, faces, camera, k, settings, soft):
    """The candidate search: (face_ids [H, W, k] int32, dropped [] int32), by the host
    kernel (candidates.py) or in JAX (tile_search.py), as settings.kernels says."""
    radius = soft_radius(settings) if soft else jnp.zeros(())
    operands = jax.lax.stop_gradient((clip, camera.near, camera.far, radius, settings.sigma,
                                      settings.gamma))
    perspective = camera.projection == "perspective"
    if not settings.use_host_kernels():
        return search_tiles(*operands[:1], faces, *operands[1:], width=camera.width,
                            height=camera.height, k=k, soft=soft,
                            cull_backfaces=settings.cull_backfaces, perspective=perspective,
                            tile=TILE, capacity=TILE_CAPACITY)
    shapes = (jax.ShapeDtypeStruct((camera.height, camera.width, k), jnp.int32),
              jax.ShapeDtypeStruct((), jnp.int32))

    def search(clip, faces, near, far, radius, sigma, gamma):
        # under vmap (a batch of views) every argument has leading batch axes: one call
        # searches all the views (find_candidates' batch form)
        lead = np.broadcast_shapes(clip.shape[:-2], faces.shape[:-2], near.shape,
                                   far.shape, radius.shape, sigma.shape, gamma.shape)
        flat = lambda x, tail=0: np.broadcast_to(
            x, lead + x.shape[x.ndim - tail:]).reshape((-1,) + x.shape[x.ndim - tail:])
        one = partial(find_candidates, width=camera.width, height=camera.height, k=k,
                      cull_backfaces=settings.cull_backfaces, perspective=perspective)
        batch = (flat(clip, 2), flat(faces, 2), flat(near), flat(far), flat(radius),
                 flat(sigma), flat(gamma))
        if (batch[1] == batch[1][:1]).all():  # views of one mesh: one call
            ids, dropped = one(*batch[:1], batch[1][0], *batch[2:4], radius_px=batch[4],
                               sigma=batch[5], gamma=batch[6])
        else:
            ids, dropped = map(np.stack, zip(*(
                one(c, f, n, r, radius_px=float(p), sigma=float(s), gamma=float(g))
                for c, f, n, r, p, s, g in zip(*batch, strict=True)), strict=True))
        return ids.reshape(lead + ids.shape[1:]), dropped.reshape(lead)
    clip, near, far, radius, sigma, gamma = operands
    ffi = ("search_soft" if soft else "search_hard",
           (camera.width, camera.height, k, settings.cull_backfaces, perspective))
    return host_call(search, shapes, clip, faces, near, far, radius, sigma, gamma,
                     batched=True, ffi=ffi)


def search_depth(settings, layers=1) -> int:
    """Faces kept per pixel by the search: settings.faces_per_pixel in soft mode, else
    `layers` (see rasterize)."""
    return settings.faces_per_pixel if settings.raster == "soft" else layers
