"""The host rasterizer's kernels on inputs that once made them read or loop outside their
arrays (a segmentation fault or a hang, so each case runs in a child process with a time
limit): vertices whose pixel coordinates lie past int64 (a field of view of 1e-20 degrees
put them at ~1e22 pixels; look_at now refuses that, find_candidates can still be given
them), and a face index out of range in a mesh traced under jit (render's own check
cannot see traced values). Judged against what the geometry says: a triangle that
contains the whole image covers every pixel, one far off to the side none; a face that
does not exist is not drawn (the render equals that of the mesh without it)."""

import os
import subprocess
import sys
import textwrap

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run_child(code):
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, (done.returncode, done.stdout[-2000:], done.stderr[-3000:])
    return done.stdout


def test_pixel_coordinates_beyond_int64_cover_exactly_the_image_they_contain():
    out = run_child("""
        import numpy as np
        from diffshade.host.candidates import find_candidates
        big = 1e21  # NDC: times the image size, beyond int64 (9.2e18)
        # (X, Y, Z, W): a counter-clockwise triangle around the whole image, and the same
        # moved far to the right (no pixel), at NDC depth 0
        around = np.array([[-big, -big, 0.0, 1.0], [big, -big, 0.0, 1.0], [0.0, big, 0.0, 1.0]])
        aside = around + np.array([4.0 * big, 0.0, 0.0, 0.0])
        faces = np.array([[0, 1, 2]])
        for soft in (False, True):
            kw = dict(radius_px=3.0, sigma=1.0, gamma=1e-4) if soft else {}
            ids, dropped = find_candidates(around, faces, width=7, height=5, k=2, **kw)
            assert (ids[..., 0] == 0).all() and (ids[..., 1] == -1).all(), (soft, ids)
            assert dropped == 0
            ids, dropped = find_candidates(aside, faces, width=7, height=5, k=2, **kw)
            assert (ids == -1).all() and dropped == 0, (soft, ids)
        print("ok")
    """)
    assert out.strip().endswith("ok")


def test_a_face_index_out_of_range_under_jit_is_not_drawn():
    out = run_child("""
        import jax, numpy as np
        import diffshade as ds
        mesh = ds.icosphere(1)
        cam = ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=16, height=12)
        faces = np.asarray(mesh.faces)
        # face 3 as it faces the camera; it points at a vertex that does not exist
        bad = faces.copy()
        bad[3, 1] = 10**8
        kept = np.delete(faces, 3, axis=0)
        for raster in ("hard", "soft"):
            settings = ds.RenderSettings(raster=raster)
            draw = jax.jit(lambda f: ds.render(ds.make_scene(ds.replace(mesh, faces=f), cam),
                                               settings))
            got, want = np.asarray(draw(bad)), np.asarray(draw(kept))
            assert np.isfinite(got).all(), raster
            np.testing.assert_array_equal(got, want)
        print("ok")
    """)
    assert out.strip().endswith("ok")
