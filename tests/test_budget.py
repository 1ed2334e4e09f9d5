"""The memory budget (diffshade.budget, diffshade.pipeline.cost; issue 26): the bytes a
render implies follow the documented formulas (recomputed here by hand from the
documented constants), stay above what XLA's own memory analysis reports for the same
render, and are compared with DIFFSHADE_MEMORY_LIMIT or the memory the machine has free.
"""

import numpy as np
import pytest

import diffshade as ds
from diffshade import budget
from diffshade.pipeline.cost import render_cost
from diffshade.pipeline.rendering import _render

GIB = 2**30


@pytest.mark.parametrize("text, expected", [("123", 123), ("8G", 8 * GIB), ("1.5M", 3 * 2**19),
                                            ("2 GiB", 2 * GIB), ("4k", 4096)])
def test_the_limit_variable_reads_bytes_and_suffixes(monkeypatch, text, expected):
    monkeypatch.setenv(budget.LIMIT_VARIABLE, text)
    assert budget.available_bytes() == (expected, budget.LIMIT_VARIABLE)


def test_a_bad_limit_variable_is_named(monkeypatch):
    monkeypatch.setenv(budget.LIMIT_VARIABLE, "lots")
    with pytest.raises(ValueError, match="DIFFSHADE_MEMORY_LIMIT: got 'lots'; expected bytes"):
        budget.available_bytes()


def test_without_the_variable_the_cpu_budget_is_memavailable(monkeypatch):
    monkeypatch.delenv(budget.LIMIT_VARIABLE, raising=False)
    with open("/proc/meminfo") as file:
        fields = dict(line.split(":", 1) for line in file)
    free = int(fields["MemAvailable"].split()[0]) * 1024
    available, source = budget.available_bytes()
    assert source == "MemAvailable in /proc/meminfo"
    assert abs(available - free) < 512 * 2**20  # other processes come and go meanwhile


def small_scene(width=16, height=8, lights=()):
    camera = ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=width, height=height)
    return ds.make_scene(ds.icosphere(0), camera, list(lights))


def test_render_cost_is_the_documented_sum():
    """16x8 soft raster, K = 4, 20 faces, a point light and a 5-sample disk light with
    shadows in 32x32 maps: every term of docs/cli.md's formula, by hand."""
    lights = [ds.point_light((1.0, 1.0, 2.0), shadows=True),
              ds.area_light((0.0, 2.0, 2.0), normal=(0.0, -1.0, -1.0), radius=0.3,
                            color=1.0, samples=5, shadows=True)]
    settings = ds.RenderSettings(raster="soft", faces_per_pixel=4, shadow_map_size=32)
    cost = render_cost(small_scene(lights=lights), settings)
    pixels, texels = 16 * 8, 32 * 32
    image = 512 * 2**20 + pixels * 256 + pixels * 4 * 256 + 20 * 1024
    kept_maps = 6 * (1 + 5) * texels * 8  # the point light's cube and one per sample
    one_cube_rasterized = 6 * texels * (256 + 256)
    assert cost.bytes == image + kept_maps + one_cube_rasterized
    assert cost.elements == 6 * texels * 5  # the sample maps' depths
    assert (cost.key, cost.value) == ("shadow_map_size", 32)


def test_the_costliest_setting_is_the_one_named():
    base = small_scene(width=64, height=64)
    cases = [(ds.RenderSettings(), "camera width x height", "64x64"),
             (ds.RenderSettings(raster="soft", faces_per_pixel=64), "faces_per_pixel", 64)]
    for settings, key, value in cases:
        assert render_cost(base, settings)[2:4] == (key, value)
    many = [ds.sphere_light((0.0, 2.0, 2.0), 0.2, samples=4096, shadows=True)]
    assert render_cost(small_scene(lights=many), ds.RenderSettings())[2:4] == ("samples", 4096)


def test_views_and_supersampling_multiply_the_pixels():
    settings = ds.RenderSettings()
    one = render_cost(small_scene(), settings)
    four = render_cost(small_scene(), settings, views=4)
    twice = render_cost(small_scene(), settings, factor=2)
    per_view = one.bytes - budget.BASE_BYTES
    assert four.bytes - budget.BASE_BYTES == 4 * per_view
    assert twice.bytes - one.bytes == 3 * 16 * 8 * (256 + 256)


def xla_bytes(scene, settings):
    """What XLA's memory analysis says the compiled render holds (arguments, output and
    temporaries)."""
    stats = _render.lower(scene, settings).compile().memory_analysis()
    return stats.temp_size_in_bytes + stats.output_size_in_bytes + stats.argument_size_in_bytes


@pytest.mark.cost(20)
def test_the_estimate_bounds_what_xla_allocates():
    """kernels='jax' keeps every array inside XLA, where its analysis sees it: the
    estimate is above it (at these sizes XLA holds every pixel's temporaries at once)."""
    soft = ds.RenderSettings(raster="soft", faces_per_pixel=4, kernels="jax")
    for scene in (small_scene(32, 32), small_scene(64, 64)):
        assert render_cost(scene, soft).bytes >= xla_bytes(scene, soft)
    shadowed = small_scene(32, 32, [ds.point_light((1.0, 1.0, 2.0), shadows=True)])
    hard = ds.RenderSettings(kernels="jax", shadow_map_size=64)
    assert render_cost(shadowed, hard).bytes >= xla_bytes(shadowed, hard)


def test_a_render_beyond_the_limit_is_refused_before_compiling(monkeypatch):
    monkeypatch.setenv(budget.LIMIT_VARIABLE, "1M")
    with pytest.raises(budget.SizeError) as info:
        ds.render(small_scene(), ds.RenderSettings())
    needed = 512 * 2**20 + 16 * 8 * (256 + 256) + 20 * 1024
    assert str(info.value) == (
        f"camera width x height: got 16x8; a 16x8 render with 1 fragment slot a pixel and 20 "
        f"faces needs {budget.show_bytes(needed)} of memory; expected at most 1.05 MB "
        "(1048576 bytes), the memory available (DIFFSHADE_MEMORY_LIMIT; set "
        "DIFFSHADE_MEMORY_LIMIT to change it)")


def test_an_array_beyond_int32_is_refused_whatever_the_memory(monkeypatch):
    monkeypatch.setenv(budget.LIMIT_VARIABLE, "1000T")
    settings = ds.RenderSettings(raster="soft", faces_per_pixel=10**7)
    with pytest.raises(budget.SizeError, match=r"faces_per_pixel: got 10000000; .* needs an "
                       r"array of 3840000000 values; expected at most 2147483647"):
        ds.render(small_scene(), settings)


def test_a_batch_of_views_is_costed_as_all_of_them(monkeypatch):
    """One 16x8 view fits 513 MiB (512 MiB + 16·8·512 + 20·1024 bytes); 100 at once do
    not."""
    monkeypatch.setenv(budget.LIMIT_VARIABLE, "513M")
    scene = small_scene()
    assert render_cost(scene, ds.RenderSettings()).bytes <= 513 * 2**20
    with pytest.raises(budget.SizeError, match=r"^camera width x height: got 16x8; a 16x8 "
                       r"render of 100 views with"):
        ds.render_views(scene, [scene.camera] * 100)


def textured_scene(width, height, texels):
    """small_scene on a sphere with UVs, its kd a texels x texels RGB texture."""
    scene = small_scene(width, height)
    kd = ds.texture(np.full((texels, texels, 3), 0.5, np.float32))
    return ds.replace(scene, mesh=ds.icosphere(0, uv=True),
                      material=ds.replace(scene.material, kd=kd))


def test_a_texture_costs_its_texels_once_whatever_the_views():
    """texels · channels · 96 bytes, beside the untextured render's terms (the UV mesh's
    faces are the same 20)."""
    settings = ds.RenderSettings()
    plain, textured = small_scene(), textured_scene(16, 8, 64)
    for views in (1, 3):
        assert (render_cost(textured, settings, views=views).bytes
                - render_cost(plain, settings, views=views).bytes) == 64 * 64 * 3 * 96


def test_a_texture_beyond_the_limit_is_named(monkeypatch):
    monkeypatch.setenv(budget.LIMIT_VARIABLE, "600M")
    scene = textured_scene(16, 8, 1024)  # 1024^2 · 3 · 96 bytes = 288 MiB, beside 512 MiB
    with pytest.raises(budget.SizeError, match=r"^material\.kd: got 1024x1024 texels; a 16x8 "
                       r"render with 1 fragment slot a pixel and 20 faces needs .* of memory; "
                       r"expected at most 629 MB \(629145600 bytes\)"):
        ds.render(scene, ds.RenderSettings())


def test_the_texture_estimate_bounds_what_xla_allocates(x64):
    """A texture much larger than the image, so that its term is what counts."""
    settings = ds.RenderSettings(kernels="jax", clamp=False)
    scene = textured_scene(8, 8, 96)
    assert render_cost(scene, settings).bytes - budget.BASE_BYTES >= xla_bytes(scene, settings)
