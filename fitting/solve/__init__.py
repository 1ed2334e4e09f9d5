"""solve: the solvers: FitOptions and its methods, the optax step, the closed form and
Levenberg-Marquardt, pose refinement.

The floor's public face, listed in `__all__`; the rest stays in its modules. fitting's
own modules import each other by full module path.
"""

from fitting.solve.gauss_newton import levenberg_marquardt
from fitting.solve.linear import solve_linear
from fitting.solve.options import FIT_METHODS, METHODS, FitOptions
from fitting.solve.pose import PoseRefinement, refine_poses
from fitting.solve.step import make_optimizer, make_step
from fitting.solve.texture import (
    DEFAULT_SMOOTHNESS,
    TextureSolution,
    solve_kd_texture,
    solve_texture,
)

__all__ = [
    "levenberg_marquardt", "solve_linear", "FIT_METHODS", "METHODS", "FitOptions",
    "make_optimizer", "make_step", "PoseRefinement", "refine_poses",
    "DEFAULT_SMOOTHNESS", "TextureSolution", "solve_kd_texture", "solve_texture",
]
