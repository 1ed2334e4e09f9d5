"""Random Blinn-Phong materials for synthetic fitting data.

Coefficients are drawn independently per RGB channel, uniformly within
COEFFICIENT_RANGES; shininess log-uniformly within SHININESS_RANGE. The ranges keep most
pixels of a `make_dataset` scene unsaturated (ambient 0.4 * ka <= 0.24, a fully lit pixel
<= 0.24 + 0.7 * kd <= 0.73; only the peaks of bright highlights clip at 1), and keep every
coefficient far enough from 0 for a relative error to mean something: the darkest unlit
pixel, 0.4 * 0.25 = 0.1, is still 25 levels of an 8-bit image.
"""

import numpy as np

from diffshade.scene import Material, material

COEFFICIENT_RANGES = {"ka": (0.25, 0.6), "kd": (0.2, 0.7), "ks": (0.15, 0.6)}
SHININESS_RANGE = (2.0, 500.0)


def random_material(rng: np.random.Generator) -> Material:
    """A Material with RGB ka, kd, ks uniform in COEFFICIENT_RANGES and shininess
    log-uniform in SHININESS_RANGE; rng: a numpy Generator (e.g. default_rng(seed))."""
    coefficients = {name: rng.uniform(lo, hi, size=3)
                    for name, (lo, hi) in COEFFICIENT_RANGES.items()}
    log_lo, log_hi = np.log(SHININESS_RANGE)
    return material(**coefficients, shininess=float(np.exp(rng.uniform(log_lo, log_hi))))
