"""jaxtraj: trajectory optimization by control restriction in JAX.

Importing jaxtraj turns on JAX's float64 mode (`jax_enable_x64`): every result of this
package is float64. The public entry points refuse to run if it is turned off afterwards.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import controls as controls, io as io, problems as problems  # noqa: E402
from ._problem import Problem as Problem, minimum_time as minimum_time  # noqa: E402
from ._sensitivity import (  # noqa: E402
    Evaluation as Evaluation,
    evaluate as evaluate,
    sensitivities as sensitivities,
)
from ._simulate import (  # noqa: E402
    RK4 as RK4,
    AbstractSimulator as AbstractSimulator,
    Diffrax as Diffrax,
    Trajectory as Trajectory,
    simulate as simulate,
)
from ._kalman_search import KalmanSearch as KalmanSearch  # noqa: E402
from ._solution import History as History, Solution as Solution  # noqa: E402
from ._solve import AbstractSolver as AbstractSolver, solve as solve, solve_batch as solve_batch  # noqa: E402
from ._status import Status as Status, status_name as status_name  # noqa: E402

__version__ = "0.1.0"
