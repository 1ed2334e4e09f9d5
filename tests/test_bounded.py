"""fitting.solve.bounded: the bounded Brent search the linear fit refines its shininess
with, held to SciPy's `minimize_scalar(method="bounded")`, which it replaces: the same
points, the same answer, bit for bit, on smooth, flat, multi-modal and edge-seeking
profiles and a shininess-like valley."""

import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from fitting.solve.bounded import minimize_bounded

PROFILES = {
    "parabola": (lambda x: (x - 0.3) ** 2, (-2.0, 3.0)),
    "quartic off-centre": (lambda x: (x - 2.9) ** 4 + 0.1 * x, (-1.0, 3.0)),
    "minimum at the lower bound": (lambda x: x, (1.5, 4.0)),
    "minimum at the upper bound": (lambda x: -math.exp(x), (0.0, 2.0)),
    "several minima": (lambda x: math.sin(3 * x) + 0.1 * x * x, (-4.0, 4.0)),
    "flat": (lambda x: 1.0, (0.0, 1.0)),
    "kink": (lambda x: abs(x - 1.234567), (0.0, 7.0)),
    # a shininess profile's shape: a narrow valley in log-shininess near a large exponent
    "log-shininess valley": (lambda g: 1e-3 * (1 - math.exp(-(g - 5.85) ** 2 / 0.01)) + 1e-9,
                             (np.log(200.0), np.log(600.0))),
    "empty interval": (lambda x: (x - 1) ** 2, (2.0, 2.0)),
}


def recorded(fun):
    """fun, and the list of the points it is called at."""
    calls = []

    def wrapped(x):
        calls.append(x)
        return fun(x)
    return wrapped, calls


@pytest.mark.parametrize("name", sorted(PROFILES))
@pytest.mark.parametrize("xatol", [1e-5, 1e-6, 0.1])
def test_bounded_matches_scipy_bit_for_bit(name, xatol):
    fun, (lo, hi) = PROFILES[name]
    ours, our_calls = recorded(fun)
    theirs, their_calls = recorded(fun)
    x, value = minimize_bounded(ours, lo, hi, xatol=xatol)
    reference = minimize_scalar(theirs, bounds=(lo, hi), method="bounded",
                                options={"xatol": xatol})
    assert our_calls == their_calls
    assert x == reference.x and value == reference.fun


def test_bounded_stops_at_maxiter_as_scipy():
    fun = lambda x: (x - 0.3) ** 2  # noqa: E731
    x, value = minimize_bounded(fun, -2.0, 3.0, xatol=1e-12, maxiter=4)
    reference = minimize_scalar(fun, bounds=(-2.0, 3.0), method="bounded",
                                options={"xatol": 1e-12, "maxiter": 4})
    assert x == reference.x and value == reference.fun


@pytest.mark.parametrize("bounds", [(1.0, 0.0), (0.0, math.inf), (math.nan, 1.0)])
def test_bounded_refuses_bad_bounds(bounds):
    with pytest.raises(ValueError, match="bounds: got"):
        minimize_bounded(lambda x: x, *bounds)
