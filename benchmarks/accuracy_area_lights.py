"""Area and sphere lights: light samples against error against time.

    python benchmarks/accuracy_area_lights.py            # the table (a few minutes)
    python benchmarks/accuracy_area_lights.py --quick    # fewer sample counts

The scene: a sphere (icosphere, subdivision 3) on a floor, 64², Phong shading, lit by
one light of each kind in turn (a rectangle 1.6 x 1.6, a disk of radius 0.9, a sphere of
radius 0.6) close to the sphere, so that the light's extent matters. Reference: the same
light with REFERENCE_SAMPLES samples (the rectangle's diffuse term is exact at every
count: Lambert's formula; its samples serve the specular term). The material is glossy
(ks 0.5, shininess 30), so the sampled specular term shows. Errors in 1/255 units over the
RGB channels of the clamped image: RMSE and the maximum absolute error. Times: every row's
forward render and gradient timed against each other in one interleaved run
(common.time_settings: warm-up until the time settles, median and quartiles), the first
call (trace + compile + run) apart; 'fwd+bwd' is the gradient of an MSE loss with respect
to the material and the light.
"""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import study_main, time_settings, timing_columns, with_spreads  # noqa: E402

import diffshade as ds  # noqa: E402

NAME = "area_lights"
OUT = "benchmarks/results/accuracy_area_lights.json"
KINDS = ("rect", "disk", "sphere")
SIZE = 64
REFERENCE_SAMPLES = 4096
AT = (1.2, 1.8, 1.0)
COLOUR = 2.5


def _frame():
    down = -np.asarray(AT) / np.linalg.norm(AT)
    tangent = np.cross(down, [0.0, 1.0, 0.0])
    tangent /= np.linalg.norm(tangent)
    return down, tangent, np.cross(down, tangent)


def light(kind, samples):
    down, u, v = _frame()
    if kind == "rect":
        return ds.area_light(AT, 1.6 * u, 1.6 * v, color=COLOUR, samples=samples)
    if kind == "disk":
        return ds.area_light(AT, normal=down, radius=0.9, color=COLOUR, samples=samples)
    return ds.sphere_light(AT, 0.6, COLOUR, samples=samples)


def scene(kind, samples):
    ball = ds.icosphere(3)
    verts = np.asarray(ball.vertices, np.float64)
    floor = np.array([[-3, -1, -3], [3, -1, -3], [3, -1, 3], [-3, -1, 3]], np.float64)
    mesh = ds.mesh_from_arrays(np.concatenate([verts, floor]),
                               np.concatenate([np.asarray(ball.faces),
                                               np.array([[0, 2, 1], [0, 3, 2]]) + len(verts)]))
    cam = ds.look_at((0.0, 1.6, 4.2), (0.0, -0.3, 0.0), width=SIZE, height=SIZE, fov_y=45.0)
    mat = ds.material(ka=0.1, kd=(0.75, 0.7, 0.6), ks=0.5, shininess=30.0)
    return ds.make_scene(mesh, cam, [light(kind, samples)], mat, global_ambient=0.05)


@jax.jit
def render(s):
    return ds.render(s)


@jax.jit
def loss_grad(s, target):
    def loss(mat, lights):
        return jnp.mean((ds.render(ds.replace(s, material=mat, lights=lights)) - target) ** 2)
    return jax.grad(loss, argnums=(0, 1))(s.material, s.lights)


def calls(kind, count, reference):
    """{"fwd", "grad"}: zero-argument calls of one row, for common.time_settings."""
    s, target = scene(kind, count), jnp.asarray(reference, jnp.float32)
    return {"fwd": lambda: render(s), "grad": lambda: loss_grad(s, target)}


def errors(kind, count, reference):
    diff = np.asarray(render(scene(kind, count)), np.float64)[..., :3] - reference[..., :3]
    return {"rmse_255": 255 * float(np.sqrt(np.mean(diff ** 2))),
            "max_255": 255 * float(np.abs(diff).max())}


def run(quick=False):
    """{"rows": per light kind and sample count, the errors against the reference and the
    times, all rows timed together; "reference_samples"}."""
    counts = (1, 4, 16) if quick else (1, 4, 16, 64, 256)
    timing = {"rounds": 3, "max_warmup": 6} if quick else {"rounds": 7}
    references = {kind: np.asarray(render(scene(kind, REFERENCE_SAMPLES)), np.float64)
                  for kind in KINDS}
    timed = {(kind, count, part): fn for kind in KINDS for count in counts
             for part, fn in calls(kind, count, references[kind]).items()}
    stats = time_settings(timed, **timing)
    # the errors' renders come after the timing, so that each first call compiles
    rows = [{"light": kind, "samples": count, **errors(kind, count, references[kind]),
             **timing_columns(stats[kind, count, "fwd"], "fwd", "compile_s"),
             **timing_columns(stats[kind, count, "grad"], "grad")}
            for kind in KINDS for count in counts]
    return {"rows": rows, "reference_samples": REFERENCE_SAMPLES}


COLUMNS = [("light", "light", "{}"), ("samples", "samples", "{}"),
           ("rmse_255", "RMSE /255", "{:.3f}"), ("max_255", "max /255", "{:.2f}"),
           ("fwd_ms", "fwd ms", "{:.1f}"), ("fwd_spread", "fwd spread ms", "{}"),
           ("grad_ms", "fwd+bwd ms", "{:.1f}"), ("grad_spread", "fwd+bwd spread ms", "{}"),
           ("compile_s", "first call s", "{:.1f}")]


def tables(results):
    from accuracy_tables import table
    return table(with_spreads(results["rows"]), COLUMNS)


def plots(results, folder):
    from accuracy_plots import draw_area_lights
    return draw_area_lights(results, folder)


def main(argv=None):
    return study_main(sys.modules[__name__], argv)


if __name__ == "__main__":
    main()
