"""The rendering sections of the choices study (benchmarks/accuracy_choices.py).

- soft_overlap: soft raster's sigma and K on a torus seen at an angle (many faces overlap
  a pixel), against the hard render of the same scene; forward, gradient with respect to
  the material and to the vertices.
- kernels: RenderSettings(kernels='host') against kernels='jax', hard and soft.
- supersample_levels: render_supersampled at subdivisions 3 and 4 against the analytic
  sphere (accuracy_vs_time's reference and errors).
- gradients: gradients of an image loss in float32 and float64 against central finite
  differences in float64 (material: hard and soft raster; vertices: soft raster).
- highlight_front: the Pareto front of highlight RMSE against forward time over the mesh
  and supersample rows of accuracy_vs_time.json (read, not re-run).

Image errors are RMSEs over the RGB channels in 1/255 units; the highlight is where the
exact specular part (for the torus: the hard render's) exceeds 0.05. Times come from
common.time_settings, every setting of a section timed against the others; each
program's first call in the section is its compile_s.
"""

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy_vs_time import errors, reference, sphere_scene  # noqa: E402
from common import time_settings  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.pipeline import render_supersampled  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STUDY_JSON = ROOT / "benchmarks" / "results" / "accuracy_vs_time.json"
HIGHLIGHT_THRESHOLD = 0.05


def torus_scene(size):
    """A torus (2,304 faces) seen from 35 degrees above its plane: its far half shows
    behind its near half, so up to four surfaces cover a pixel."""
    return ds.make_scene(
        ds.torus(),
        ds.look_at((0.0, 1.9, 2.7), (0.0, -0.1, 0.0), width=size, height=size, fov_y=40.0),
        [ds.directional_light((-1.0, -1.0, -1.0), 0.8),
         ds.point_light((2.0, 2.5, 2.0), 0.6, attenuation=(1.0, 0.05, 0.01))],
        ds.material(ka=0.2, kd=(0.7, 0.3, 0.2), ks=0.5, shininess=60.0))


def rmse_255(image, ref, mask=None):
    diff = np.asarray(image, np.float64)[..., :3] - np.asarray(ref, np.float64)[..., :3]
    return 255 * float(np.sqrt(np.mean(diff[mask] ** 2 if mask is not None else diff ** 2)))


def material_loss(render_fn, scene, target):
    def loss(material):
        return jnp.mean((render_fn(ds.replace(scene, material=material))[..., :3] - target) ** 2)
    return loss


def vertex_loss(render_fn, scene, target):
    def loss(vertices):
        mesh = ds.replace(scene.mesh, vertices=vertices)
        return jnp.mean((render_fn(ds.replace(scene, mesh=mesh))[..., :3] - target) ** 2)
    return loss


def timed_calls(render_fn, scene, target, columns=("fwd", "fwd_bwd", "fwd_bwd_vertices")):
    """{column: zero-argument call} for the columns asked: the jitted forward render
    ('fwd') and the gradients of an MSE loss with respect to the material ('fwd_bwd') and
    to the vertices ('fwd_bwd_vertices')."""
    make = {"fwd": lambda: (jax.jit(render_fn), scene),
            "fwd_bwd": lambda: (jax.jit(jax.grad(material_loss(render_fn, scene, target))),
                                scene.material),
            "fwd_bwd_vertices": lambda: (jax.jit(jax.grad(vertex_loss(render_fn, scene,
                                                                      target))),
                                         scene.mesh.vertices)}
    return {column: (lambda f, x: lambda: f(x))(*make[column]()) for column in columns}


def add_times(rows, calls, rounds, measure=()):
    """Time every row's calls against each other (calls: {(row index, column): fn}), then
    add to each row what measure[i]() returns (its errors: computed after the timing, so
    that each program's first call, compile_s, is its first call in the section)."""
    named = {f"{i}/{column}": fn for (i, column), fn in calls.items()}
    times = time_settings(named, rounds=rounds)
    for (i, column) in calls:
        t = times[f"{i}/{column}"]
        rows[i][f"{column}_ms"] = t["median_ms"]
        rows[i][f"{column}_iqr_ms"] = [t["q1_ms"], t["q3_ms"]]
        rows[i].setdefault("compile_s", t["compile_s"])
    for row, fn in zip(rows, measure, strict=False):
        row.update(fn())
    return rows


# ---------------------------------------------------------------- 1. soft raster, overlap
def soft_overlap(quick, rounds):
    size = 64 if quick else 128
    sigmas, ks = ((1.0,), (4,)) if quick else ((0.1, 0.5, 1.0, 2.0), (1, 2, 4, 8, 16))
    scene = torus_scene(size)
    hard = np.asarray(ds.render(scene, ds.RenderSettings()))
    glossy = ds.replace(scene, material=ds.material(ka=0.0, kd=0.0, ks=0.5, shininess=60.0),
                        global_ambient=jnp.zeros(3))
    highlight = np.asarray(ds.render(glossy))[..., :3].max(-1) > HIGHLIGHT_THRESHOLD
    target = jnp.asarray(hard[..., :3])
    settings = [("hard", None, None, ds.RenderSettings())] + [
        ("soft", sigma, k, ds.RenderSettings(raster="soft", sigma=sigma, faces_per_pixel=k))
        for sigma in sigmas for k in ks]
    rows, calls = [], {}
    for i, (raster, sigma, k, st) in enumerate(settings):
        render_fn = lambda s, st=st: ds.render(s, st)  # noqa: E731
        image = np.asarray(render_fn(scene))
        rows.append({"raster": raster, "sigma": sigma, "K": k, "gamma": st.gamma, "size": size,
                     "faces": int(scene.mesh.faces.shape[0]),
                     "vs_hard_rmse_255": rmse_255(image, hard),
                     "vs_hard_highlight_rmse_255": rmse_255(image, hard, highlight)})
        # hard raster has no silhouette gradient, only the shading's: quick skips it
        columns = ("fwd", "fwd_bwd") + (() if quick and raster == "hard" else
                                        ("fwd_bwd_vertices",))
        for column, fn in timed_calls(render_fn, scene, target, columns).items():
            calls[(i, column)] = fn
    return add_times(rows, calls, rounds)


# ---------------------------------------------------------------- 2. the kernels path
def kernels(quick, rounds):
    """Both paths on the study's sphere; at 64 px the subdivision-4 sphere puts more faces
    on a jax tile than its capacity (diffshade.raster.search.TILE_CAPACITY): the jax
    search takes several passes there."""
    level, sizes = (3, (64,)) if quick else (4, (64, 128, 256))
    rows, calls, images = [], {}, {}
    for size in sizes:
        scene = sphere_scene(level, size)
        for raster in ("hard", "soft"):
            for path in ("host", "jax"):
                st = ds.RenderSettings(raster=raster, kernels=path)
                render_fn = lambda s, st=st: ds.render(s, st)  # noqa: E731
                images[size, raster, path] = np.asarray(render_fn(scene))
                target = jnp.asarray(images[size, raster, "host"][..., :3])
                columns = ("fwd",) if quick else ("fwd", "fwd_bwd") + (
                    ("fwd_bwd_vertices",) if raster == "soft" else ())
                for column, fn in timed_calls(render_fn, scene, target, columns).items():
                    calls[(len(rows), column)] = fn
                diff = np.abs(images[size, raster, path] - images[size, raster, "host"])
                rows.append({"size": size, "raster": raster, "kernels": path,
                             "subdivisions": level, "faces": 20 * 4 ** level,
                             "vs_host_max_abs": float(diff.max()),
                             "differing_px": int((diff.max(-1) > 1e-5).sum())})
    return add_times(rows, calls, rounds)


# ---------------------------------------------------------------- 3. supersampling s3/s4
def supersample_levels(quick, rounds):
    levels, sizes, factors = ((3,), (64,), (1, 2)) if quick else ((3, 4), (64, 128, 256),
                                                                   (1, 2, 4))
    rows, calls = [], {}
    for size in sizes:
        ref, highlight = reference(size)
        for level in levels:
            scene = sphere_scene(level, size)
            for factor in factors:
                render_fn = lambda s, f=factor: render_supersampled(s, ds.RenderSettings(), f)  # noqa: E731,E501
                calls[(len(rows), "fwd")] = timed_calls(render_fn, scene, None, ("fwd",))["fwd"]
                rows.append({"subdivisions": level, "faces": 20 * 4 ** level, "size": size,
                             "factor": factor, **errors(render_fn(scene), ref, highlight)})
    return add_times(rows, calls, rounds)


# ---------------------------------------------------------------- 4. gradient accuracy
GRADIENT_CASES = (("hard", "material"), ("soft", "material"), ("soft", "vertices"))


def gradient_problem(raster, wrt, x64):
    """(loss of a flat parameter vector, the vector) for one case, in float64 or float32:
    an icosphere of subdivision 1 at 32 px against the target of a perturbed material
    (and, for the vertices, a stretched mesh), so that the gradient is far from zero."""
    with jax.enable_x64(x64):
        scene = sphere_scene(1, 32)
        st = ds.RenderSettings(raster=raster)
        target_scene = ds.replace(
            scene, material=ds.material(ka=0.25, kd=(0.6, 0.35, 0.25), ks=0.4, shininess=50.0),
            mesh=ds.replace(scene.mesh, vertices=scene.mesh.vertices * jnp.array([1.1, 0.95, 1])))
        target = ds.render(target_scene, st)[..., :3]
        render_fn = lambda s: ds.render(s, st)  # noqa: E731
        if wrt == "material":
            leaves, unflatten = ravel_pytree(scene.material)
            loss = material_loss(render_fn, scene, target)
        else:
            leaves, unflatten = ravel_pytree(scene.mesh.vertices)
            loss = vertex_loss(render_fn, scene, target)
        return (lambda x: loss(unflatten(x))), leaves


def central_differences(loss, x, step=1e-6):
    """The gradient of loss at x by central differences, one coordinate at a time."""
    f = jax.jit(loss)
    eye = np.eye(x.size)
    return np.array([(f(x + step * e) - f(x - step * e)) / (2 * step) for e in eye])


def gradients(quick, rounds):
    cases = GRADIENT_CASES[:1] if quick else GRADIENT_CASES
    rows, calls, measure = [], {}, []
    for raster, wrt in cases:
        with jax.enable_x64(True):
            reference_grad = central_differences(*gradient_problem(raster, wrt, True))
        for dtype in ("float32", "float64"):
            wide = dtype == "float64"
            with jax.enable_x64(wide):
                loss, x = gradient_problem(raster, wrt, wide)
                grad = jax.jit(jax.grad(loss))

            def call(grad=grad, x=x, wide=wide):
                with jax.enable_x64(wide):
                    return grad(x)

            def error(call=call, reference_grad=reference_grad):
                g = np.asarray(call(), np.float64)
                return {"rel_error": float(np.linalg.norm(g - reference_grad)
                                           / np.linalg.norm(reference_grad))}
            calls[(len(rows), "grad")] = call
            measure.append(error)
            rows.append({"raster": raster, "wrt": wrt, "dtype": dtype,
                         "parameters": int(x.size)})
    return add_times(rows, calls, rounds, measure)


# ---------------------------------------------------------------- 5. highlight front
def highlight_front(quick, rounds, study_json=STUDY_JSON):
    """The mesh and supersample rows of the published study on the Pareto front of
    highlight RMSE against forward time (no other row both faster and more accurate)."""
    study = json.loads(Path(study_json).read_text())
    rows = [{"study": r["study"], "subdivisions": r["subdivisions"], "shading": r["shading"],
             "size": r["size"], "factor": r.get("factor", 1), "faces": 20 * 4 ** r["subdivisions"],
             "highlight_rmse_255": r["highlight_rmse_255"], "rmse_255": r["rmse_255"],
             "fwd_ms": r["fwd_ms"]} for r in study["mesh"] + study["supersample"]]
    front = [r for r in rows if not any(
        o["fwd_ms"] <= r["fwd_ms"] and o["highlight_rmse_255"] <= r["highlight_rmse_255"]
        and o is not r for o in rows)]
    return sorted(front, key=lambda r: r["fwd_ms"])
