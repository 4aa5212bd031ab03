"""jaxtraj: trajectory optimization by control restriction in JAX.

Importing jaxtraj turns on JAX's float64 mode (`jax_enable_x64`): every result of this
package is float64. The public entry points refuse to run if it is turned off afterwards.
Nothing else global changes at import: `jt.configure_cpu()` sets the CPU device split and
XLA options jaxtraj is tuned for, when asked.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import (
    controls as controls,
    feedback as feedback,
    io as io,
    metaheuristics as metaheuristics,
    problems as problems,
    rotations as rotations,
)
from ._augmented_lagrangian import AugmentedLagrangian as AugmentedLagrangian
from ._batch import (
    MultistartResult as MultistartResult,
    multistart as multistart,
    random_starts as random_starts,
    solve_batch as solve_batch,
)
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._configure import configure_cpu as configure_cpu
from ._driver import AbstractSolver as AbstractSolver
from ._export_cache import (
    disable_solve_cache as disable_solve_cache,
    enable_solve_cache as enable_solve_cache,
)
from ._kalman_search import KalmanSearch as KalmanSearch
from ._kalman_sqp import KalmanSQP as KalmanSQP
from ._line_search import LineSearch as LineSearch
from ._problem import Problem as Problem, minimum_time as minimum_time
from ._report import KKTReport as KKTReport, kkt_report as kkt_report
from ._sensitivity import (
    Evaluation as Evaluation,
    evaluate as evaluate,
    sensitivities as sensitivities,
)
from ._simulate import (
    RK4 as RK4,
    AbstractSimulator as AbstractSimulator,
    Diffrax as Diffrax,
    Trajectory as Trajectory,
    simulate as simulate,
)
from ._solution import History as History, Solution as Solution
from ._solve import solve as solve
from ._status import Status as Status, status_name as status_name
from ._trust_region import TrustRegion as TrustRegion
from .feedback import (
    ClosedLoopTrajectory as ClosedLoopTrajectory,
    ControlErrors as ControlErrors,
    Dispersion as Dispersion,
    ExecutionErrors as ExecutionErrors,
    Linearization as Linearization,
    MonteCarloResult as MonteCarloResult,
    ThrustErrors as ThrustErrors,
    bryson_weights as bryson_weights,
    linearize as linearize,
    monte_carlo as monte_carlo,
    simulate_closed_loop as simulate_closed_loop,
    tracking_lqr as tracking_lqr,
)
from .metaheuristics import Dragonfly as Dragonfly, GreyWolf as GreyWolf, Whale as Whale

__version__ = "0.2.0"
