"""Benchmark of the candidate search: search_tiles (pure JAX, tile binning) against
find_candidates (the host numba kernel), float32.

Scene: the 5,120-face icosphere (icosphere(4)) seen from 3 units, 256 x 256, K = 8, hard
mode and soft mode (default sigma, gamma and footprint radius). search_tiles is jitted;
its first call (trace + compile + run) is reported as compile time. find_candidates is
called directly (its numba kernels are cached on disk, so its first call is mostly
loading them). Both report the median of `--repeats` calls after warm-up, `dropped`, and
whether the face ids agree (float32 clip coordinates: the host computes in float64, the
device path in float32, so a few edge pixels may differ).

    .venv/bin/python benchmarks/tile_search.py [--repeats 10] [--tile 16] [--capacity 128]
"""

import argparse
from functools import partial

import jax
import numpy as np
from common import machine_info, time_call

import diffshade as ds
from diffshade.host.candidates import find_candidates
from diffshade.raster.search import soft_radius
from diffshade.raster.tile_search import search_tiles
from diffshade.settings import RenderSettings

SIZE, K = 256, 8


def scene_clip():
    """Clip coordinates [V, 4] float32 and faces [F, 3] of the benchmark scene."""
    cam = ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=SIZE, height=SIZE, fov_y=45.0)
    scene = ds.make_scene(ds.icosphere(4), cam)
    return ds.project(scene).clip.astype(np.float32), scene.mesh.faces, cam


def run(mode, clip, faces, cam, args):
    settings = RenderSettings()
    soft = mode == "soft"
    radius = soft_radius(settings) if soft else 0.0
    scalars = (cam.near, cam.far, radius, settings.sigma, settings.gamma)
    device = jax.jit(partial(search_tiles, width=SIZE, height=SIZE, k=K, soft=soft,
                             tile=args.tile, capacity=args.capacity))
    dev_compile, dev_median, _ = time_call(device, clip, faces, *scalars, repeats=args.repeats)
    host = partial(find_candidates, np.asarray(clip), np.asarray(faces), float(cam.near),
                   float(cam.far), width=SIZE, height=SIZE, k=K, radius_px=radius,
                   sigma=settings.sigma, gamma=settings.gamma)
    host_first, host_median, _ = time_call(host, repeats=args.repeats)
    dev_ids, dev_dropped = device(clip, faces, *scalars)
    host_ids, host_dropped = host()
    agree = np.mean(np.all(np.asarray(dev_ids) == host_ids, -1))
    print(f"{mode:4s}  search_tiles: compile {dev_compile:6.2f} s, median {dev_median * 1e3:8.1f}"
          f" ms, dropped {int(dev_dropped)}  |  find_candidates: first call {host_first:5.2f} s,"
          f" median {host_median * 1e3:7.1f} ms, dropped {int(host_dropped)}  |  "
          f"pixels agreeing {agree:.4%}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--tile", type=int, default=16)
    parser.add_argument("--capacity", type=int, default=128)
    args = parser.parse_args()
    print(machine_info())
    clip, faces, cam = scene_clip()
    print(f"icosphere(4): {faces.shape[0]} faces, {SIZE}x{SIZE}, K={K}, tile {args.tile},"
          f" capacity {args.capacity}, float32")
    for mode in ("hard", "soft"):
        run(mode, clip, faces, cam, args)


if __name__ == "__main__":
    main()
