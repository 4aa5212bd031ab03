"""Feedback around an optimized trajectory: linearization, LQR, closed-loop Monte Carlo.

Two layers:

* the generic linear-quadratic core: Riccati equations (`continuous_lqr`, `discrete_lqr`),
  zero-order hold (`zoh_discretize`), covariance propagation (`propagate_covariance*`);
* the trajectory layer: `linearize` (A(t), B(t) and the sampled-data Ad, Bd along the RK4
  solution of a parameter vector), `tracking_lqr` (the LQR law u = u_ref - K (x - x_ref)),
  `simulate_closed_loop` (one noisy run of the sampled-data loop) and `monte_carlo` (N runs
  in one vmapped call: terminal-error statistics and dispersion bands), with execution-error
  models `ThrustErrors`, `ControlErrors`, `ExecutionErrors`.

Equation numbers refer to seed 001 (lecture notes on synthesis of optimal control; which
equations each function solves: docs/api/feedback.md).

Conventions (all functions): cost-to-go V_k(x) = x^T S_k x + c_k for the cost
sum_k (x_k^T Q x_k + u_k^T R u_k) + x_N^T Qf x_N (continuous: the integral of the same
integrand plus x(tf)^T Qf x(tf)); feedback u = -K x. The seed's cost has Q = 0; the state term
is its exercise (1.34)/(3.58) and only adds Q to the Riccati right-hand side.

Every function is pure JAX and returns float64; the numerical cores are jitted (repeated calls
with the same shapes, and for the continuous ones the same callables, do not recompile) and
may be called under jit / vmap. Differentiation: the discrete functions support forward and
reverse mode; the continuous ones forward mode by default (see `adjoint`). Shape errors are
`ValueError`s raised at call (trace) time, naming the argument.
"""

from ._errors import (
    AbstractExecutionErrors as AbstractExecutionErrors,
    ControlErrors as ControlErrors,
    ExecutionErrors as ExecutionErrors,
    ThrustErrors as ThrustErrors,
)
from ._linearize import (
    Linearization as Linearization,
    bryson_weights as bryson_weights,
    linearize as linearize,
    tracking_lqr as tracking_lqr,
)
from ._lqr import (
    DiscreteLQRGains as DiscreteLQRGains,
    LQRGains as LQRGains,
    continuous_lqr as continuous_lqr,
    discrete_lqr as discrete_lqr,
    propagate_covariance as propagate_covariance,
    propagate_covariance_continuous as propagate_covariance_continuous,
    zoh_discretize as zoh_discretize,
)
from ._monte_carlo import (
    ClosedLoopTrajectory as ClosedLoopTrajectory,
    Dispersion as Dispersion,
    MonteCarloResult as MonteCarloResult,
    monte_carlo as monte_carlo,
    simulate_closed_loop as simulate_closed_loop,
)

__all__ = [
    "AbstractExecutionErrors",
    "ClosedLoopTrajectory",
    "ControlErrors",
    "DiscreteLQRGains",
    "Dispersion",
    "ExecutionErrors",
    "LQRGains",
    "Linearization",
    "MonteCarloResult",
    "ThrustErrors",
    "bryson_weights",
    "continuous_lqr",
    "discrete_lqr",
    "linearize",
    "monte_carlo",
    "propagate_covariance",
    "propagate_covariance_continuous",
    "simulate_closed_loop",
    "tracking_lqr",
    "zoh_discretize",
]
