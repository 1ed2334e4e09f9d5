"""Random Blinn-Phong materials for synthetic fitting data.

Coefficients are drawn independently per RGB channel, uniformly within
COEFFICIENT_RANGES; shininess log-uniformly within SHININESS_RANGE. The ranges keep most
pixels of a `make_dataset` scene unsaturated (ambient 0.4 * ka <= 0.24, a fully lit pixel
<= 0.24 + 0.7 * kd <= 0.73; only the peaks of bright highlights clip at 1), and keep every
coefficient far enough from 0 for a relative error to mean something: the darkest unlit
pixel, 0.4 * 0.25 = 0.1, is still 25 levels of an 8-bit image.

`procedural_kd(res)` is the known kd texture of `synth --texture`: a closed form of the
UV, so that a recovered map can be compared with the truth at any resolution.
"""

import numpy as np

from diffshade.scene import Material, material

COEFFICIENT_RANGES = {"ka": (0.25, 0.6), "kd": (0.2, 0.7), "ks": (0.15, 0.6)}
SHININESS_RANGE = (2.0, 500.0)
#: procedural_kd's pattern: per RGB channel, its mean and amplitude
KD_MEAN, KD_AMPLITUDE = np.array([0.45, 0.4, 0.35]), np.array([0.25, 0.2, 0.15])


def procedural_kd_at(u, v):
    """The procedural kd [..., 3] at UVs u, v [...]: KD_MEAN + KD_AMPLITUDE *
    sin(2 pi 3 u) cos(2 pi 2 v) in red, the pattern shifted by a quarter turn in u for
    green and blue reversed: smooth, in [0.2, 0.7], every channel different."""
    shifts = np.array([0.0, 0.25, 0.5])
    u, v = np.asarray(u)[..., None], np.asarray(v)[..., None]
    return KD_MEAN + KD_AMPLITUDE * np.sin(2 * np.pi * 3 * (u + shifts)) * np.cos(
        2 * np.pi * 2 * v)


def procedural_kd(res: int) -> np.ndarray:
    """procedural_kd_at at the texel centres of a res x res texture: [res, res, 3]
    float32, row 0 = the top of the image (v = 1)."""
    centres = (np.arange(res) + 0.5) / res
    return procedural_kd_at(centres[None, :], 1.0 - centres[:, None]).astype(np.float32)


def random_material(rng: np.random.Generator) -> Material:
    """A Material with RGB ka, kd, ks uniform in COEFFICIENT_RANGES and shininess
    log-uniform in SHININESS_RANGE; rng: a numpy Generator (e.g. default_rng(seed))."""
    coefficients = {name: rng.uniform(lo, hi, size=3)
                    for name, (lo, hi) in COEFFICIENT_RANGES.items()}
    log_lo, log_hi = np.log(SHININESS_RANGE)
    return material(**coefficients, shininess=float(np.exp(rng.uniform(log_lo, log_hi))))
