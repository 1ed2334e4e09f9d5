"""Bounded 1-D minimization: Brent's method on an interval, as SciPy's
`minimize_scalar(method="bounded")` (its fminbound), step for step.

The linear fit refines its shininess with it (fitting.solve.linear). It is written out
here rather than imported: SciPy's optimize package, with the linalg and sparse packages
it pulls in, takes about a quarter of a second to import, more than the search itself,
at every `diffshade fit`. tests/test_bounded.py holds it to SciPy's result, bit for bit.
"""

import math

_SQRT_EPS = math.sqrt(2.2e-16)
_GOLDEN = 0.5 * (3.0 - math.sqrt(5.0))


def _sign(value):
    """1 for value >= 0, else -1 (fminbound's sign(v) + (v == 0))."""
    return 1.0 if value >= 0 else -1.0


def _parabolic_step(xf, fx, nfc, fnfc, fulc, ffulc):
    """(p, q) of the parabola through the three best points: the step is p / q."""
    r = (xf - nfc) * (fx - ffulc)
    q = (xf - fulc) * (fx - fnfc)
    p = (xf - fulc) * q - (xf - nfc) * r
    q = 2.0 * (q - r)
    return (-p if q > 0.0 else p), abs(q)


def minimize_bounded(fun, lo, hi, xatol=1e-5, maxiter=500):
    """(x, fun(x)): a local minimum of the scalar function `fun` on [lo, hi] to within
    `xatol`, after at most `maxiter` calls (SciPy's bounded Brent)."""
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"bounds: got ({lo!r}, {hi!r}); expected finite lo <= hi")
    a, b = lo, hi
    xf = nfc = fulc = a + _GOLDEN * (b - a)
    rat = e = 0.0
    fx = ffulc = fnfc = fun(xf)
    calls = 1
    xm = 0.5 * (a + b)
    tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
    tol2 = 2.0 * tol1
    while abs(xf - xm) > tol2 - 0.5 * (b - a):
        golden = True
        if abs(e) > tol1:  # try a parabolic step
            p, q = _parabolic_step(xf, fx, nfc, fnfc, fulc, ffulc)
            r, e = e, rat
            if abs(p) < abs(0.5 * q * r) and q * (a - xf) < p < q * (b - xf):
                golden = False
                rat = (p + 0.0) / q
                x = xf + rat
                if (x - a) < tol2 or (b - x) < tol2:
                    rat = tol1 * _sign(xm - xf)
        if golden:
            e = (a - xf) if xf >= xm else (b - xf)
            rat = _GOLDEN * e
        x = xf + _sign(rat) * max(abs(rat), tol1)
        fu = fun(x)
        calls += 1
        if fu <= fx:
            a, b = (xf, b) if x >= xf else (a, xf)
            fulc, ffulc, nfc, fnfc, xf, fx = nfc, fnfc, xf, fx, x, fu
        else:
            a, b = (x, b) if x < xf else (a, x)
            if fu <= fnfc or nfc == xf:
                fulc, ffulc, nfc, fnfc = nfc, fnfc, x, fu
            elif fu <= ffulc or fulc == xf or fulc == nfc:
                fulc, ffulc = x, fu
        xm = 0.5 * (a + b)
        tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1
        if calls >= maxiter:
            break
    return xf, fx
