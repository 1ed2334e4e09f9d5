"""What a fit runs: the one table of methods, and `FitOptions`, every setting that shapes
a fit's trajectory.

`fitting.fit(...)` takes the options as keywords, `diffshade fit` as flags generated from
`OPTIONS` (`--lr-shininess` for `lr_shininess`), and a checkpoint stores them all, so a
resumed fit continues with the settings it started with. Each option is validated here,
at the boundary: a ValueError names it, the value and what was expected.
"""

import dataclasses
import math

import numpy as np

from fitting.model.loss import LOSSES


@dataclasses.dataclass(frozen=True)
class Method:
    """default_steps: the step budget when none is given; patience: the steps in a row of
    small relative change that mean converged (None: FitOptions.patience); optax: steps
    are fitting.solve.step's optax steps (else Levenberg-Marquardt iterations after a closed-form
    start); summary: one line for --help."""

    default_steps: int
    patience: int | None
    optax: bool
    summary: str


METHODS = {
    "linear": Method(50, 1, False, "the coefficients in closed form inside a search on "
                     "shininess, then Levenberg-Marquardt (independent of the start)"),
    "adam": Method(3000, None, True, "Adam with a learning rate per parameter group"),
    "lbfgs": Method(500, None, True, "optax L-BFGS with a zoom line search"),
}
FIT_METHODS = tuple(METHODS)
OPTAX_METHODS = tuple(name for name, m in METHODS.items() if m.optax)
DEFAULT_STEPS = {name: m.default_steps for name, m in METHODS.items()}


@dataclasses.dataclass(frozen=True)
class Option:
    """help: one line; check(value) -> True when valid; expected: what check wants."""

    help: str
    check: object
    expected: str


def _number(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


MAX_EDGE_MARGIN = 16384  # diffshade's largest image side (docs/scene-format.md)
#: a learning rate's upper bound: the fit's arithmetic is float32, where a larger one
#: overflows to inf (--lr 1e300 returned the starting values, silently)
MAX_RATE = float(np.finfo(np.float32).max)


def _rate(x):
    return _number(x) and 0 < x <= MAX_RATE


_RATE = f"a positive learning rate of at most {MAX_RATE:.4g} (float32's largest number)"


def _count(low):
    return lambda x: isinstance(x, int) and not isinstance(x, bool) and x >= low


OPTIONS = {
    "method": Option("fitting method: " + "; ".join(f"'{n}': {m.summary}" for n, m in
                                                     METHODS.items()),
                     lambda x: x in METHODS, f"one of {FIT_METHODS}"),
    "steps": Option("step budget (Levenberg-Marquardt iterations for 'linear'), counted "
                    "across resumes; default " + ", ".join(f"{n} {m.default_steps}" for n, m
                                                           in METHODS.items()),
                    lambda x: x is None or _count(0)(x), "an integer >= 0 or None"),
    "loss": Option("image loss", lambda x: x in LOSSES, f"one of {LOSSES}"),
    "tol": Option("converged when the relative loss change stays below this for "
                  "'patience' steps (0: never)", lambda x: _number(x) and x >= 0,
                  "a finite number >= 0"),
    "atol": Option("converged when the loss falls to this", lambda x: _number(x) and x >= 0,
                   "a finite number >= 0"),
    "patience": Option("steps in a row of small change for Adam and L-BFGS",
                       _count(1), "an integer >= 1"),
    "gtol": Option("converged when the gradient norm (checked every 'patience' steps) "
                   "falls below this (default: not checked)",
                   lambda x: x is None or (_number(x) and x >= 0), "a finite number >= 0"),
    "lr": Option("Adam's learning rate for coefficients and light colours", _rate, _RATE),
    "lr_shininess": Option("Adam's learning rate for log-shininess", _rate, _RATE),
    "lr_position": Option("Adam's learning rate for light positions", _rate, _RATE),
    # at most the largest image side (any more leaves no pixel): the margin is eroded pixel
    # by pixel, so 10**12 would run for ever (a catalogue case, tests/test_catalogue_fit.py)
    "edge_margin": Option("silhouette pixels left out",
                          lambda x: _count(0)(x) and x <= MAX_EDGE_MARGIN,
                          f"an integer from 0 to {MAX_EDGE_MARGIN} (the largest image side)"),
    "shininess_range": Option(
        "the 'linear' method's search interval for shininess, LOW,HIGH",
        lambda x: isinstance(x, tuple) and len(x) == 2 and all(map(_number, x))
        and 0 < x[0] < x[1], "two numbers 0 < low < high"),
    "max_bad": Option("non-finite steps in a row that stop the fit", _count(1),
                      "an integer >= 1"),
    "devices": Option("devices the views are sharded over: 'all' (every device JAX sees; "
                      "one CPU device runs today's unsharded fit) or a count",
                      lambda x: x == "all" or _count(1)(x), "'all' or an integer >= 1"),
    "chunk": Option("views per chunk: the loss and gradient are summed over chunks of this "
                    "many views, so a step's memory is one chunk's (default: all views at "
                    "once)", lambda x: x is None or _count(1)(x), "None or an integer >= 1"),
}

# Where a fit runs, not what it computes (equal to rounding): a resumed fit may change them.
PLACEMENT = ("devices", "chunk")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Every setting of a fit's trajectory (OPTIONS has the meaning of each). Frozen and
    hashable: steps compiled for one set of options are shared."""

    method: str = "linear"
    steps: int | None = None
    loss: str = "mse"
    tol: float = 1e-7
    atol: float = 1e-12
    patience: int = 20
    gtol: float | None = None
    lr: float = 0.05
    lr_shininess: float = 0.05
    lr_position: float = 0.02
    edge_margin: int = 1
    shininess_range: tuple = (1.0, 2000.0)
    max_bad: int = 5
    devices: object = "all"
    chunk: int | None = None

    def __post_init__(self):
        if isinstance(self.shininess_range, list):
            object.__setattr__(self, "shininess_range", tuple(self.shininess_range))
        for field in dataclasses.fields(self):
            value, option = getattr(self, field.name), OPTIONS[field.name]
            if not option.check(value):
                raise ValueError(f"{field.name}: got {value!r}; expected {option.expected}")
        if self.method == "lbfgs" and self.chunk is not None:
            raise ValueError(f"chunk: got {self.chunk!r}; 'lbfgs' evaluates its line search "
                             "in one compiled step over all views; expected None (or method "
                             "'adam' or 'linear')")

    @property
    def budget(self) -> int:
        """The step budget: steps, or the method's default."""
        return METHODS[self.method].default_steps if self.steps is None else self.steps

    @property
    def stop_patience(self) -> int:
        """The patience the method uses (Levenberg-Marquardt: 1)."""
        return METHODS[self.method].patience or self.patience

    def as_dict(self) -> dict:
        """JSON-ready; FitOptions(**d) rebuilds it."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}
