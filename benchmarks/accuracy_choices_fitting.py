"""The shadow and fitting sections of the choices study (benchmarks/accuracy_choices.py).

- soft_shadows: the shadow edge of soft raster against hard raster, on accuracy_shadows'
  sphere over a floor, against the exact shadow (SphereOverPlane.shadow).
- fit_effects: the linear solver's recovery error and time with and without shadows in
  its model (targets with shadows), with an area light modelled with as many samples as
  the targets' or fewer, with a transparent box (kt known, or fitted with kd) against an
  opaque one, and against the number of views and of lights.
- fit_resolution: the linear solver against image size under noise sigma = 0.01 and on
  8-bit targets (median and largest error over seeds).

Errors are deterministic (fixed seeds, fixed order); fit times come from
common.time_settings (a fit is one call: cache building, solve), interleaved per section.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np
from accuracy_fitting import NOISE_SEEDS, material_error
from accuracy_shadows import GEOMETRY, GLOBAL, KA, LIGHT, LIGHT_AMBIENT, boundary, scene
from common import time_settings

import diffshade as ds
from data_synth import make_dataset
from fitting import FitSpec, View, dataset_of_scene, fit, view_scene

SHADOW_SIZE = 128


# ---------------------------------------------------------------- 6. soft-raster shadows
def shadow_edge(image, lit, camera):
    """(wrong floor pixels, reference edge pixels): a floor pixel counts as shadowed when
    less than half its light reaches it, (image - ambient) / (lit - ambient) < 0.5, where
    `lit` is the same render without shadows (soft raster's edge is a ramp, not a step)."""
    on_floor, shadow = GEOMETRY.shadow(camera, ("point", LIGHT))
    ambient = KA * (GLOBAL + LIGHT_AMBIENT)
    image, lit = (np.asarray(x, np.float64)[..., 0] - ambient for x in (image, lit))
    dark = image < 0.5 * lit
    wrong = on_floor & (dark != shadow)
    return int(wrong.sum()), int(boundary(shadow).sum())


def soft_shadows(quick, rounds):
    size = 64 if quick else SHADOW_SIZE
    rows_of = [("hard", None, None, 256)] if quick else [
        ("hard", None, None, m) for m in (64, 256)]
    rows_of += [("soft", 1.0, 0.1, 256)] if quick else [
        ("soft", sigma, softness, 256) for sigma in (0.1, 1.0) for softness in (0.1, 1.0)]
    shadowed, plain = scene(size, True), scene(size, False)
    rows, calls = [], {}
    for raster, sigma, softness, map_size in rows_of:
        st = ds.RenderSettings(raster=raster, shadow_map_size=map_size,
                               **({} if raster == "hard" else
                                  {"sigma": sigma, "shadow_softness": softness}))
        wrong, edge = shadow_edge(ds.render(shadowed, st), ds.render(plain, st),
                                  shadowed.camera)
        calls[f"{len(rows)}"] = lambda st=st: ds.render(shadowed, st)
        rows.append({"size": size, "raster": raster, "sigma": sigma,
                     "shadow_softness": softness, "map": map_size, "wrong_px": wrong,
                     "edge_px": edge, "edge_error_px": wrong / edge})
    return _with_times(rows, calls, rounds, "fwd")


def _with_times(rows, calls, rounds, column):
    times = time_settings(calls, rounds=rounds)
    for key, t in times.items():
        rows[int(key)] |= {f"{column}_ms": t["median_ms"],
                           f"{column}_iqr_ms": [t["q1_ms"], t["q3_ms"]],
                           "compile_s": t["compile_s"]}
    return rows


def _fit_call(dataset, spec=None, init=None):
    """One linear fit, returning arrays so that the timer can wait on them."""
    return lambda: fit(dataset, spec, init, method="linear", with_uncertainty=False).material


# ---------------------------------------------------------------- 7. inside a fit
SUN = ((0.3, -1.0, -0.5), 0.3)
AREA_AT = (-1.0, 1.8, -1.0)  # accuracy_shadows' light position, as a disk facing the origin


def key_light(kind, shadows=False, samples=64):
    """The light that lights the floor scene besides the sun: accuracy_shadows' point
    light, or a disk of radius 0.5 in its place, facing the origin."""
    if kind == "point":
        return ds.point_light(LIGHT, 1.0, ambient=LIGHT_AMBIENT, shadows=shadows)
    normal = -np.asarray(AREA_AT) / np.linalg.norm(AREA_AT)
    return ds.area_light(AREA_AT, normal=normal, radius=0.5, color=2.0, ambient=LIGHT_AMBIENT,
                         samples=samples)


def floor_dataset(size, n_views, target_light, model_light):
    """Views of accuracy_shadows' sphere over a floor (one material), each lit by the sun
    and a key light: targets rendered with `target_light`, fitted with `model_light`."""
    truth = ds.material(ka=0.25, kd=(0.6, 0.4, 0.3), ks=0.3, shininess=40.0)
    settings = ds.RenderSettings(shadow_map_size=256)
    views = []
    for k in range(n_views):
        angle = np.radians(360.0 * k / n_views)
        eye = (3.2 * np.sin(angle), 4.5, 3.2 * np.cos(angle))
        camera = ds.look_at(eye, (0.0, -1.0, 0.0), width=size, height=size, fov_y=40.0)
        views.append(View(camera, [target_light, ds.directional_light(*SUN)],
                          np.zeros((size, size, 3))))
    data = dataset_of_scene(scene(size, True), views, truth=truth, settings=settings)
    targets = [np.asarray(ds.render(view_scene(data, i, truth), settings))[..., :3]
               for i in range(n_views)]
    return dataclasses.replace(data, views=[
        dataclasses.replace(v, target=t, lights=[model_light, ds.directional_light(*SUN)])
        for v, t in zip(views, targets, strict=True)])


# (case, model, the target's key light, the model's)
FLOOR_CASES = [
    ("shadows", "with shadows", lambda: key_light("point", True), lambda: key_light("point", True)),
    ("shadows", "without shadows", lambda: key_light("point", True), lambda: key_light("point")),
    ("area light", "disk, 64 samples", lambda: key_light("disk"), lambda: key_light("disk")),
    ("area light", "disk, 4 samples", lambda: key_light("disk"),
     lambda: key_light("disk", samples=4)),
]


# tests/test_fit_effects' box on a table, the box lifted off the table top (resting on it,
# its bottom and the table's top are ordered by the depth test's tie rule,
# docs/rendering.md#coplanar-faces; tests/test_depth_ties.py fits that case)
BOX = dict(ka=(0.25, 0.2, 0.15), kd=(0.6, 0.3, 0.2), ks=(0.4, 0.35, 0.3), shininess=30.0)
TABLE = dict(ka=(0.2, 0.25, 0.3), kd=(0.3, 0.45, 0.7), ks=0.1, shininess=8.0)
KT = (0.35, 0.5, 0.65)


def box_dataset(size, glass):
    """2 views of a box (transparent when `glass`) over a table, lit by a point light
    casting shadows and the sun; targets rendered with the truth."""
    box = ds.material(**BOX, kt=KT if glass else None)
    objects = [ds.scene_object(ds.box((0.7, 0.7, 0.7)), box,
                               transform=ds.model_matrix((0.1, 0.4, 0.0), (0.0, 30.0, 0.0))),
               ds.scene_object(ds.box((2.4, 0.2, 1.8)), ds.material(**TABLE),
                               transform=ds.model_matrix((0.0, -0.1, 0.0)))]
    views = []
    for eye in ((0.4, 1.8, 2.4), (-1.6, 1.4, 1.8)):
        camera = ds.look_at(eye, (0.0, 0.2, 0.0), width=size, height=size, fov_y=50.0)
        lights = [ds.point_light((1.2, 2.2, 0.8), 0.8, shadows=True),
                  ds.directional_light(*SUN)]
        views.append(View(camera, lights, np.zeros((size, size, 3))))
    scene_ = ds.make_scene(objects=objects, camera=views[0].camera, global_ambient=0.3)
    settings = ds.RenderSettings(shadow_map_size=256)
    data = dataset_of_scene(scene_, views, truth=scene_.material, settings=settings)
    return dataclasses.replace(data, views=[
        dataclasses.replace(v, target=np.asarray(ds.render(view_scene(data, i, data.truth),
                                                           settings))[..., :3])
        for i, v in enumerate(data.views)])


def box_fit(size, model):
    """(dataset, spec, init) of a transparency row: kd fitted from 0.5 (and kt from 0.5 on
    the box, 0.05 on the opaque table when `model` fits kt); the rest known."""
    dataset = box_dataset(size, model != "opaque box, kd")
    truth, fit_kt = dataset.truth, model == "glass box, kd + kt"
    init = dataclasses.replace(truth, kd=jnp.full_like(truth.kd, 0.5))
    if fit_kt:
        init = dataclasses.replace(init, kt=jnp.asarray([[0.5] * 3, [0.05] * 3],
                                                        truth.kd.dtype))
    return dataset, FitSpec.from_names(["kd", "kt"] if fit_kt else ["kd"]), init


def box_error(material, truth):
    """Largest relative error of kd and of the box's kt (the table's kt is 0: absolute)."""
    kd = np.abs(np.asarray(material.kd) - np.asarray(truth.kd)) / np.asarray(truth.kd)
    if truth.kt is None:
        return float(kd.max())
    kt = np.abs(np.asarray(material.kt) - np.asarray(truth.kt))
    return float(max(kd.max(), (kt[0] / np.asarray(truth.kt)[0]).max(), kt[1].max()))


TRANSPARENCY_MODELS = ("opaque box, kd", "glass box, kd (kt known)", "glass box, kd + kt")


def fit_effects(quick, rounds):
    size = 32 if quick else 64
    counts = ((1, 1), (2, 2)) if quick else ((1, 1), (1, 2), (1, 4), (2, 2), (4, 2), (8, 2))
    cases = [(case, {"model": model}, target, fitted)
             for case, model, target, fitted in FLOOR_CASES]
    cases += [("views × lights", {"n_views": v, "n_lights": n}, None, None) for v, n in counts]
    rows, calls = [], {}
    for model in TRANSPARENCY_MODELS[-1:] if quick else TRANSPARENCY_MODELS:
        dataset, spec, init = box_fit(size, model)
        result = fit(dataset, spec, init, method="linear", with_uncertainty=False)
        calls[f"{len(rows)}"] = _fit_call(dataset, spec, init)
        rows.append({"case": "transparency", "size": size, "model": model,
                     "images": len(dataset.views),
                     "max_rel_error": box_error(result.material, dataset.truth)})
    for case, params, target, fitted in cases:
        if target is not None:
            dataset = floor_dataset(size, 2, target(), fitted())
        else:
            dataset = make_dataset(size=size, seed=NOISE_SEEDS[0], noise_std=0.01, **params)
        result = fit(dataset, method="linear", with_uncertainty=False)
        calls[f"{len(rows)}"] = _fit_call(dataset)
        rows.append({"case": case, "size": size, **params, "images": len(dataset.views),
                     "max_rel_error": material_error(result.material, dataset.truth)})
    return _with_times(rows, calls, rounds, "fit")


# ---------------------------------------------------------------- 8. resolution for fitting
def fit_resolution(quick, rounds):
    sizes, seeds = ((32, 64), NOISE_SEEDS[:1]) if quick else ((32, 64, 128, 256), NOISE_SEEDS)
    rows, calls = [], {}
    for noise_std, quantize in ((0.01, False), (0.0, True)):
        for size in sizes:
            errors = []
            for seed in seeds:
                dataset = make_dataset(size=size, seed=seed, noise_std=noise_std,
                                       quantize_8bit=quantize)
                result = fit(dataset, method="linear", with_uncertainty=False)
                errors.append(material_error(result.material, dataset.truth))
            calls[f"{len(rows)}"] = _fit_call(dataset)
            rows.append({"size": size, "noise_std": noise_std, "quantized": quantize,
                         "seeds": len(seeds), "median_rel_error": float(np.median(errors)),
                         "max_rel_error": float(np.max(errors))})
    return _with_times(rows, calls, rounds, "fit")
