"""Texture resolution and sampling against the error of a textured render against time
(the textures section of the accuracy-versus-time study, docs/accuracy-vs-time.md).

    python benchmarks/accuracy_textures.py            # the table (a few minutes)
    python benchmarks/accuracy_textures.py --quick    # seconds-long subset
    python benchmarks/accuracy_study.py --only textures --docs   # and the page's tables

Scene: the study's sphere and lights (accuracy_vs_time.sphere_scene's camera and lights)
on icosphere(4, uv=True), Phong shading, hard raster, ka 0.2, no specular, kd a texture
of `texels`^2 independent random texels (uniform in [0.2, 0.8], seed 0: detail at every
scale down to one texel, the hardest case for sampling). diffshade reads a texture
bilinearly at each sample's UV and does not mip-map (docs/textures.md, "Minification"):
where a texel is smaller than a pixel the remedies are supersampling the image
(render_supersampled, `factor`^2 samples per pixel) or a coarser texture (`prefiltered`:
the texture box-filtered by 2^k, k the mip level a GPU picks at the sphere's nearest
point, rendered with one sample per pixel: what mip-mapping would do there).

Reference: the same scene with the full texture, render_supersampled at REFERENCE_SIDE /
size samples a side (2048^2 samples in all), the pixel's mean over its area. Errors over
the RGB channels in 1/255 units: `rmse_255` over the image, `inside_rmse_255` over the
pixels inside the silhouette (the reference's alpha 1 there and at the 4 neighbours), the
texture's own error without the silhouette's. `texels_per_pixel`: texels across one pixel
at the sphere's point nearest the camera, along v (on the sphere's longitude / latitude
map a texel spans 2 pi / texels in u and pi / texels in v: v is the denser way). Times:
the forward render of every row timed against each other (common.time_settings: median
and quartiles), the first call (trace, compile, run) apart.
"""

import math
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy_vs_time import sphere_scene  # noqa: E402
from common import study_main, time_settings, timing_columns, with_spreads  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.pipeline import render_supersampled  # noqa: E402

NAME = "textures"
OUT = "benchmarks/results/accuracy_textures.json"
REFERENCE_SIDE = 2048
SUBDIVISIONS = 4


def random_texels(texels):
    """[texels, texels, 3] independent uniform texels in [0.2, 0.8] (seed 0)."""
    return np.random.default_rng(0).uniform(0.2, 0.8, (texels, texels, 3)).astype(np.float32)


def textured_scene(texels_array, size):
    """The study's sphere and lights with kd the texture `texels_array` [R, R, 3]."""
    plain = sphere_scene(SUBDIVISIONS, size)
    return ds.replace(plain, mesh=ds.icosphere(SUBDIVISIONS, uv=True),
                      material=ds.material(ka=0.2, kd=ds.texture(texels_array), ks=None))


def texels_per_pixel(texels, size):
    """Texels across one pixel along v at the sphere's point nearest the camera: the
    pixel's width there (at distance |eye| - 1 from the eye) over a texel's, pi / texels."""
    camera = sphere_scene(1, size).camera
    distance = float(np.linalg.norm(np.asarray(camera.eye, np.float64))) - 1.0
    pixel = 2 * distance * math.tan(math.radians(float(camera.fov_y)) / 2) / size
    return pixel * texels / math.pi


def prefilter_level(texels, size):
    """The mip level a GPU picks at the sphere's nearest point (GL_NEAREST_MIPMAP_*:
    log2 of texels_per_pixel, rounded; 0 where the texture is not minified): the
    power-of-two box filter that brings a pixel closest to one texel."""
    return max(0, round(math.log2(texels_per_pixel(texels, size))))


def box_down(texels_array, level):
    """The texture box-filtered by 2^level along both axes."""
    f = 2 ** level
    r = texels_array.shape[0] // f
    return texels_array.reshape(r, f, r, f, 3).mean(axis=(1, 3))


def settings_of(texels, size, factors):
    """[(sampling label, factor, mip level)] of one (texels, size): each supersampling
    factor, and the prefiltered texture where it is minified."""
    rows = [(f"{f}×{f} samples" if f > 1 else "1 sample", f, 0) for f in factors]
    level = prefilter_level(texels, size)
    if level > 0:
        rows.append((f"prefiltered to {texels >> level}²", 1, level))
    return rows


def inside(alpha):
    """Pixels inside the silhouette: alpha 1 there and at the 4 neighbours."""
    full = np.pad(alpha >= 1.0, 1, constant_values=False)
    return (full[1:-1, 1:-1] & full[:-2, 1:-1] & full[2:, 1:-1] & full[1:-1, :-2]
            & full[1:-1, 2:])


def errors(image, reference):
    diff = np.asarray(image, np.float64)[..., :3] - reference[..., :3]
    mask = inside(reference[..., 3])
    return {"rmse_255": 255 * float(np.sqrt(np.mean(diff ** 2))),
            "inside_rmse_255": 255 * float(np.sqrt(np.mean(diff[mask] ** 2)))}


def configs(texel_sides, sizes, factors):
    """{(texels, size, sampling): (jitted forward render, scene)} of every row."""
    out = {}
    for texels in texel_sides:
        full = random_texels(texels)
        for size in sizes:
            for label, factor, level in settings_of(texels, size, factors):
                render = jax.jit(lambda s, f=factor: render_supersampled(
                    s, ds.RenderSettings(), f))
                out[texels, size, label] = (render, textured_scene(box_down(full, level),
                                                                   size))
    return out


def run(quick=False):
    """{"rows": per texture side, image size and sampling: the errors against the
    reference and the forward time (all rows timed together)}."""
    texel_sides, sizes = ((256,), (64,)) if quick else ((64, 256, 1024), (64, 128, 256))
    factors = (1, 2) if quick else (1, 2, 4)
    timing = {"rounds": 3, "max_warmup": 6} if quick else {"rounds": 7}
    rows_of = configs(texel_sides, sizes, factors)
    stats = time_settings({key: (lambda c=c: c[0](c[1])) for key, c in rows_of.items()},
                          **timing)
    references, rows = {}, []
    for (texels, size, label), (render, scene) in rows_of.items():
        if (texels, size) not in references:
            full = textured_scene(random_texels(texels), size)
            references[texels, size] = np.asarray(
                render_supersampled(full, ds.RenderSettings(), REFERENCE_SIDE // size),
                np.float64)
        rows.append({"texels": texels, "size": size, "sampling": label,
                     "texels_per_pixel": texels_per_pixel(texels, size),
                     **errors(render(scene), references[texels, size]),
                     **timing_columns(stats[texels, size, label], "fwd", "compile_s")})
    return {"rows": rows}


COLUMNS = [("texels", "texture", "{}²"), ("size", "px", "{}"),
           ("texels_per_pixel", "texels per px", "{:.2f}"), ("sampling", "sampling", "{}"),
           ("inside_rmse_255", "inside RMSE /255", "{:.2f}"), ("rmse_255", "RMSE /255", "{:.2f}"),
           ("fwd_ms", "fwd ms", "{:.1f}"), ("fwd_spread", "fwd spread ms", "{}"),
           ("compile_s", "first call s", "{:.1f}")]


def tables(results):
    from accuracy_tables import table
    return table(with_spreads(results["rows"]), COLUMNS)


def plot(axes, rows):
    """One panel per texture side (the texture is given; the image size and the sampling
    are chosen): the error inside the silhouette against forward time, colour the
    sampling, marker the image size."""
    from accuracy_plots import plot_generic

    sides = sorted({r["texels"] for r in rows})
    for ax, texels in zip(axes, sides, strict=True):
        # one colour for every prefiltered texture: the marker tells the image sizes apart
        chosen = [{**r, "sampling": r["sampling"].split(" to ")[0]} for r in rows
                  if r["texels"] == texels]
        plot_generic(ax, chosen, ("sampling", "size"), f"a {texels}² texture",
                     "inside_rmse_255", legend=ax is axes[-1])
        ax.set_ylabel("RMSE inside the silhouette (1/255 units)")


def plots(results, folder):
    from accuracy_plots import _draw

    count = len({r["texels"] for r in results["rows"]})
    return [_draw(folder, "textures", count,
                  lambda axes: plot(axes if count > 1 else [axes], results["rows"]),
                  width=5.0 * count + 2.0)]


def main(argv=None):
    return study_main(sys.modules[__name__], argv)


if __name__ == "__main__":
    main()
