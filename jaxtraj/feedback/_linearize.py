"""Linearization along an optimized trajectory, and the tracking LQR built on it."""

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .._checks import as_float64, check_inputs, check_memory, memory_refusal
from .._simulate import RK4, simulation_status
from .._status import Status, as_indexable
from ._common import check_shape, check_weight, interp_rows, numbers
from ._errors import AbstractExecutionErrors, Exact
from ._lqr import continuous_lqr, discrete_lqr, propagate_covariance
from ._sampled import bounded_control, check_gains, gain_sequence, noise_free, sample_step


class Linearization(eqx.Module):
    """The reference trajectory of `a` on the control-sample grid and its linearization.

    Grid: one sample per RK4 step of the simulator, `N = num_segments * steps`, sample times
    `t` (`(N + 1,)`, t_N = tf).

    - `x` `(N + 1, n)`: reference states (the RK4 solution, as `jt.simulate`).
    - `u` `(N + 1, m)`: reference control at the sample times (right-continuous at knots; the
      last entry is the left limit at tf).
    - `A` `(N + 1, n, n)`, `B` `(N + 1, n, m)`: df/dx, df/du at (t_k, x_k, u_k) by `jax.jacfwd`;
      `A_fn(t)`, `B_fn(t)` interpolate them linearly (for `continuous_lqr`).
    - `Ad` `(N, n, n)`, `Bd` `(N, n, m)`: the sampled-data (zero-order hold) linearization,
      x_{k+1} - xref_{k+1} = Ad_k (x_k - xref_k) + Bd_k du_k, as the exact Jacobians of the
      simulator's RK4 step with a correction du_k held over the sample (for linear
      time-invariant dynamics, `zoh_discretize(A, B, dt)` up to RK4's O(dt^5) per step).
    - `Gd` `(N, n, n)`: Jacobian of the step with respect to a process noise w added to dx/dt
      and held over the sample (~ dt I).
    - `Ed` `(N, n, p)`: Jacobian of the step with respect to the execution noise xi (p = 0
      without `execution`).
    - `dt` `(N,)`: sample durations; `status`: `Status.NONFINITE` if the reference is not finite.
    """

    t: jax.Array
    x: jax.Array
    u: jax.Array
    A: jax.Array
    B: jax.Array
    Ad: jax.Array
    Bd: jax.Array
    Gd: jax.Array
    Ed: jax.Array
    dt: jax.Array
    status: Status = eqx.field(converter=as_indexable)

    def A_fn(self, t):
        """A(t) by linear interpolation between samples (clamped outside [0, tf])."""
        return interp_rows(self.t, self.A, t)

    def B_fn(self, t):
        """B(t) by linear interpolation between samples (clamped outside [0, tf])."""
        return interp_rows(self.t, self.B, t)

    def predict_covariance(self, gains=None, *, initial_covariance=None, process_noise=None):
        """Linear covariance analysis of the sampled closed loop (white execution noise,
        `correlation_time=0`): P_{k+1} = F_k P_k F_k^T + Gd_k (W / dt_k) Gd_k^T + Ed_k Ed_k^T,
        F_k = Ad_k - Bd_k K_k. Valid while the dispersion is small enough for the
        linearization. `gains` as in `monte_carlo`. **Returns:** `(N + 1, n, n)`."""
        N, n = self.Ad.shape[:2]
        m, p = self.Bd.shape[2], self.Ed.shape[2]
        gains = check_gains(gains, N, m, n)
        K = gain_sequence(gains, self.t)
        F = self.Ad if K is None else self.Ad - self.Bd @ K
        P0 = jnp.zeros((n, n)) if initial_covariance is None else as_float64(initial_covariance)
        check_shape("initial_covariance", P0.shape, (n, n))
        W = jnp.zeros((n, n)) if process_noise is None else as_float64(process_noise)
        check_shape("process_noise", W.shape, (n, n))
        dt = jnp.where(self.dt > 0, self.dt, 1.0)
        Ws = jnp.zeros((N, n + p, n + p))
        Ws = Ws.at[:, :n, :n].set(W[None] / dt[:, None, None]).at[:, n:, n:].set(jnp.eye(p))
        return propagate_covariance(P0, F, Ws, jnp.concatenate([self.Gd, self.Ed], axis=2))


def check_simulator_rk4(simulator):
    if not isinstance(simulator, RK4):
        raise ValueError(
            "`simulator` must be a fixed-step jt.RK4(steps) here (one control sample per RK4 "
            f"step); got {type(simulator).__name__}."
        )


def check_execution(execution, problem):
    if execution is None:
        return Exact()
    if not isinstance(execution, AbstractExecutionErrors):
        raise ValueError(
            f"`execution` must be None, ThrustErrors, ControlErrors or ExecutionErrors; got {type(execution).__name__}."
        )
    execution.check(problem)
    return execution


def linearize(problem, control, a, *, simulator=RK4(), execution=None) -> Linearization:
    """Linearize the dynamics along the trajectory of the parameters `a`.

    The reference is the RK4 solution on the simulator's grid (the same arithmetic as
    `jt.simulate(problem, control, a, simulator=simulator)` at the step boundaries). A(t),
    B(t) are `jax.jacfwd` of `problem.dynamics` there; the discrete `Ad`, `Bd` (and the noise
    inputs `Gd`, `Ed`) are `jax.jacfwd` of one sampled RK4 step, i.e. of the map that
    `simulate_closed_loop` and `monte_carlo` iterate.

    **Arguments:**

    - `problem`, `control`, `a`: as in `jt.simulate` (typically `a = sol.params`).
    - `simulator`: keyword-only, `jt.RK4(steps)`: one control sample per RK4 step.
    - `execution`: keyword-only execution-error model for `Ed` (default: none, p = 0).

    **Returns:** a `Linearization`. Jit-compiled; usable under `jax.vmap` over `a`.
    Feed it to `tracking_lqr` (or to `continuous_lqr` / `discrete_lqr` directly).
    """
    a = check_inputs(problem, control, a)
    check_simulator_rk4(simulator)
    execution = check_execution(execution, problem)
    p = execution.num_noise(problem.num_controls)
    n, m, N = problem.num_states, problem.num_controls, control.num_segments * simulator.steps
    check_memory("simulator", 8 * N * 2 * n * (n + m + p), f"the linearization at {N:,} samples")
    with memory_refusal("jt.linearize", "use fewer RK4 steps"):
        return _linearize(problem, control, a, execution, p, simulator.steps)


@eqx.filter_jit
def _linearize(problem, control, a, execution, p, steps):
    grid, x = noise_free(problem, control, a, steps)
    rows, h = grid.theta[:, :-2], grid.theta[:, -1]
    u = jax.vmap(control.local_control)(rows, h, grid.tau)
    u = jnp.concatenate([u, control.local_control(rows[-1], h[-1], 1.0)[None]])
    u = bounded_control(problem, u)
    jac = jax.jacfwd(problem.dynamics, argnums=(1, 2))
    A, B = jax.vmap(lambda t, x, u: jac(t, x, u, problem.args))(grid.t, x, u)

    n, m = problem.num_states, problem.num_controls

    def step(theta, tau, x, du, xi, w):
        return sample_step(problem, control, execution, grid.dtau, theta, tau, x, du, xi, w)

    N = grid.tau.shape[0]
    Ad, Bd, Ed, Gd = jax.vmap(jax.jacfwd(step, argnums=(2, 3, 4, 5)))(
        grid.theta, grid.tau, x[:-1], jnp.zeros((N, m)), jnp.zeros((N, p)), jnp.zeros((N, n))
    )
    status = simulation_status(jnp.array(True), x, A, B)
    return Linearization(t=grid.t, x=x, u=u, A=A, B=B, Ad=Ad, Bd=Bd, Gd=Gd, Ed=Ed, dt=grid.dt, status=status)


def bryson_weights(lin: Linearization, state_scale, control_scale, terminal_scale):
    """LQR weights by Bryson's rule for the cost int (dx^T Q dx + du^T R du) dt
    + dx(tf)^T Qf dx(tf) of `tracking_lqr`: each term is about 1 when a deviation stays at its
    acceptable size over [0, tf],

        Q = diag(1 / (tf state_scale^2)),  R = diag(1 / (tf control_scale^2)),
        Qf = diag(1 / terminal_scale^2),

    with tf = `lin.t[-1]`. The scales are scalars or per-component vectors (`(n,)`, `(m,)`,
    `(n,)`). **Returns:** `(Q, R, Qf)`."""
    n, m = lin.B.shape[1:]
    tf = lin.t[-1]

    def diag(name, scale, k):
        scale = as_float64(scale)
        check_shape(name, scale.shape, (), (k,))
        if not isinstance(scale, jax.core.Tracer) and not np.all(np.isfinite(scale) & (scale > 0)):
            raise ValueError(f"`{name}` must be finite and > 0 (an acceptable deviation); got {np.asarray(scale)}.")
        return jnp.diag(jnp.broadcast_to(1.0 / scale**2, (k,)))

    return (
        diag("state_scale", state_scale, n) / tf,
        diag("control_scale", control_scale, m) / tf,
        diag("terminal_scale", terminal_scale, n),
    )


def tracking_lqr(lin: Linearization, Q, R, Qf, *, discrete=True, multiplicative=None, **kwargs):
    """The LQR tracking law around a linearized trajectory, u = u_ref - K (x - x_ref), for the
    cost int (dx^T Q dx + du^T R du) dt + dx(tf)^T Qf dx(tf).

    - `discrete=True` (default): `discrete_lqr` on the sampled-data model (`lin.Ad`,
      `lin.Bd`) with per-sample weights Q dt_k, R dt_k (rectangle rule): the gains of the
      sampled controller that `monte_carlo` simulates. `multiplicative` is passed on (seed eq.
      2.19). **Returns:** `DiscreteLQRGains` (one gain per sample).
    - `discrete=False`: `continuous_lqr` on `lin.A_fn`, `lin.B_fn` over [0, tf], sampled at
      `lin.t`, stepping to every sample time (`step_ts`, where the interpolated A, B have
      kinks); other keyword arguments are passed on. **Returns:** `LQRGains`.

    `Q`, `Qf`: `(n, n)` PSD; `R`: `(m, m)` positive definite.
    """
    n, m = lin.B.shape[1:]
    Q, R, Qf = numbers("Q", Q), numbers("R", R), numbers("Qf", Qf)
    check_shape("Q", Q.shape, (n, n))
    check_shape("R", R.shape, (m, m))
    check_shape("Qf", Qf.shape, (n, n))
    for name, M in (("Q", Q), ("R", R), ("Qf", Qf)):
        check_weight(name, M, definite=name == "R")
    if discrete:
        if kwargs:
            raise ValueError(f"unexpected keyword(s) {sorted(kwargs)} for discrete=True.")
        dt = lin.dt[:, None, None]
        return discrete_lqr(lin.Ad, lin.Bd, Q[None] * dt, R[None] * dt, Qf, multiplicative=multiplicative)
    if multiplicative is not None:
        raise ValueError("`multiplicative` needs discrete=True (seed eq. 2.19).")
    kwargs = {"step_ts": lin.t, "max_steps": 8 * lin.t.shape[0] + 4096, **kwargs}
    return continuous_lqr(lin.A_fn, lin.B_fn, Q, R, Qf, lin.t[0], lin.t[-1], ts=lin.t, **kwargs)
