"""Segment-wise integration of the controlled dynamics on rescaled time.

Segment k = [t_k, t_{k+1}] of the control is integrated on tau in [0, 1] with
dx/dtau = h_k f(t_k + h_k tau, x, u_k(tau)), h_k = t_{k+1} - t_k (seed 003 eq. 7). Knots and
tf are thus smooth parameters of x(tf), and every control discontinuity falls on a segment
boundary, where no integration step straddles it.

Integrators: fixed-step RK4 in `lax.scan` (default; `steps` per segment) or any diffrax
solver with adaptive steps (`Diffrax`). Both take the same per-segment vector field, which
is how the unit-solution sensitivities (`_sensitivity.py`) reuse them for the augmented
state (x, dx/da).
"""

import abc
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._checks import check_inputs, check_memory, check_problem_and_control, is_count, memory_refusal
from ._problem import Problem
from ._status import Status, as_indexable
from .controls import AbstractControl


class AbstractSimulator(eqx.Module):
    """Integrates one segment's vector field `field(tau, y)` over tau in [0, 1]."""

    @abc.abstractmethod
    def integrate(self, field: Callable, y0, dense: bool) -> tuple[Any, Any, jax.Array]:
        """Return `(y1, ys, ok)`: the state at tau = 1, the dense states on `dense_grid()`
        (or None) and a boolean that is False when the integrator itself failed (the states
        are pytrees of `y0`'s structure)."""

    @abc.abstractmethod
    def dense_grid(self) -> np.ndarray:
        """The tau values of the dense output of one segment (including 0 and 1)."""

    def num_dense(self) -> int:
        """`len(dense_grid())`, without forming the grid."""
        return len(self.dense_grid())

    def integrate_linearized(self, field: Callable, theta, theta_a, x0, x0_a):
        """Integrate `field(theta, tau, x)` over one segment together with dx/da.

        `theta` is the segment's row of `segment_data` with Jacobian `theta_a = dtheta/da`,
        `x0_a = dx0/da`. Returns `(x1, x1_a, ok)`, x1_a = dx1/dx0 x0_a + dx1/dtheta theta_a,
        by forward-mode autodiff of this segment's integration (tangent dimension
        n + len(theta), whatever len(a) is).
        """

        def run(x, th):
            x1, _, ok = self.integrate(lambda tau, y: field(th, tau, y), x, False)
            return x1, (x1, ok)

        (jx, jth), (x1, ok) = jax.jacfwd(run, argnums=(0, 1), has_aux=True)(x0, theta)
        return x1, _chain(jx, x0_a, jth, theta_a), ok


def _chain(jx, x_a, jth, theta_a):
    """jx @ x_a + jth @ theta_a as broadcast multiply-sums: XLA:CPU fuses these into the loop
    body, whereas these tiny `dot`s become separate library calls (measured 4.3x vs 28x the
    simulation on Earth-Mars case 5)."""
    return jnp.sum(jx[:, :, None] * x_a[None], axis=1) + jnp.sum(jth[:, :, None] * theta_a[None], axis=1)


def rk4_step(field, tau, dt, y):
    """One classical RK4 step of y' = field(tau, y) (pytrees) from tau to tau + dt."""

    def axpy(alpha, x, y):
        return jax.tree.map(lambda xi, yi: yi + alpha * xi, x, y)

    k1 = field(tau, y)
    k2 = field(tau + 0.5 * dt, axpy(0.5 * dt, k1, y))
    k3 = field(tau + 0.5 * dt, axpy(0.5 * dt, k2, y))
    k4 = field(tau + dt, axpy(dt, k3, y))
    incr = jax.tree.map(lambda a, b, c, d: a + 2.0 * b + 2.0 * c + d, k1, k2, k3, k4)
    return axpy(dt / 6.0, incr, y)


class RK4(AbstractSimulator):
    """Classical fixed-step Runge-Kutta 4 with `steps` equal steps per segment, in `lax.scan`.

    Derivatives of the result with respect to the parameters are exact derivatives of the
    discrete map (forward-mode autodiff through the scan).
    """

    steps: int = eqx.field(default=100, converter=lambda v: int(v) if isinstance(v, np.integer) else v)

    def __check_init__(self):
        if not (isinstance(self.steps, int) and not isinstance(self.steps, bool) and self.steps >= 1):
            raise ValueError(f"`steps` must be an int >= 1; got {self.steps!r}.")

    def integrate(self, field, y0, dense):
        n = self.steps
        dt = 1.0 / n

        def step(y, j):
            y1 = rk4_step(field, j * dt, dt, y)
            return y1, (y1 if dense else None)

        # Rematerialized step: reverse mode (the trust region's forward-over-reverse Hessian)
        # keeps only the state per step and recomputes the step's internals, which XLA compiles
        # far faster at no warm cost (benchmarks/RESULTS.md); without reverse mode the program
        # is the same.
        y1, ys = lax.scan(jax.checkpoint(step, prevent_cse=False), y0, jnp.arange(n, dtype=jnp.float64))
        if dense:
            ys = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), y0, ys)
        return y1, ys, jnp.array(True)

    def dense_grid(self):
        return np.linspace(0.0, 1.0, self.steps + 1)

    def num_dense(self):
        return self.steps + 1

    def integrate_linearized(self, field, theta, theta_a, x0, x0_a):
        """Chain the derivative step by step: each RK4 step is differentiated with respect to
        (x, theta) only (n + len(theta) tangents) and x_a <- dstep/dx x_a + dstep/dtheta
        theta_a. The same numbers as `jax.jacfwd` through the whole integration (tested to
        1e-12), 2x faster on CPU."""
        dt = 1.0 / self.steps

        def one_step(x, th, tau):
            x1 = rk4_step(lambda s, y: field(th, s, y), tau, dt, x)
            return x1, x1

        step_jacobian = jax.jacfwd(one_step, argnums=(0, 1), has_aux=True)

        def body(carry, j):
            x, x_a = carry
            (jx, jth), x1 = step_jacobian(x, theta, j * dt)
            return (x1, _chain(jx, x_a, jth, theta_a)), None

        (x1, x1_a), _ = lax.scan(body, (x0, x0_a), jnp.arange(self.steps, dtype=jnp.float64))
        return x1, x1_a, jnp.array(True)


class Diffrax(AbstractSimulator):
    """Any diffrax solver with a PID step-size controller (adaptive steps) per segment.

    Uses `diffrax.ForwardMode()` so that forward-mode sensitivities work through it.
    Integration failures (step limit, step-size underflow) are reported as
    `Status.SIMULATION_FAILED`, never raised.
    """

    solver: diffrax.AbstractSolver = diffrax.Tsit5()
    rtol: float = 1e-10
    atol: float = 1e-12
    max_steps: int = 16384
    dense_points: int = 101

    def __check_init__(self):
        # (a solver without an error estimate, or no solver, failed inside diffrax at the
        # first simulation; a text, NaN or infinite tolerance, a bool count: issue 51)
        if not isinstance(self.solver, diffrax.AbstractAdaptiveSolver):
            raise ValueError(
                "`solver` must be a diffrax solver with an error estimate (adaptive steps, e.g. "
                f"diffrax.Tsit5()); got {self.solver!r}."
            )
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            try:
                number = np.nan if isinstance(value, bool | str) else float(value)
            except (TypeError, ValueError):
                number = np.nan
            if not 0 < number < np.inf:
                raise ValueError(f"`{name}` must be a finite number > 0; got {value!r}.")
        if not is_count(self.max_steps, 1):
            raise ValueError(f"`max_steps` must be an int >= 1; got {self.max_steps!r}.")
        if not (
            isinstance(self.dense_points, int) and not isinstance(self.dense_points, bool) and self.dense_points >= 2
        ):
            raise ValueError(f"`dense_points` must be an int >= 2; got {self.dense_points!r}.")

    def integrate(self, field, y0, dense):
        saveat = diffrax.SaveAt(ts=jnp.asarray(self.dense_grid())) if dense else diffrax.SaveAt(t1=True)
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda tau, y, args: field(tau, y)),
            self.solver,
            t0=0.0,
            t1=1.0,
            dt0=None,
            y0=y0,
            saveat=saveat,
            stepsize_controller=diffrax.PIDController(rtol=self.rtol, atol=self.atol),
            max_steps=self.max_steps,
            adjoint=diffrax.ForwardMode(),
            throw=False,
        )
        y1 = jax.tree.map(lambda ys: ys[-1], sol.ys)
        ok = sol.result == diffrax.RESULTS.successful
        return y1, (sol.ys if dense else None), ok

    def dense_grid(self):
        return np.linspace(0.0, 1.0, self.dense_points)


def integrate_segments(simulator: AbstractSimulator, field, data, y0, *, jump=None, dense=False):
    """Integrate segment after segment in a `lax.scan` over the rows of `data`.

    `field(theta, tau, y)` is the vector field on tau in [0, 1] of the segment whose row of
    `data` is theta; `jump(k, theta, y)`, if given, maps the state at the start of segment k
    (right after knot t_k) before that segment is integrated. Returns
    `(y_final, dense_states or None, ok)`; dense states have a leading
    `(num_segments, len(dense_grid))` shape. Scanning over the rows (instead of indexing
    `data[k]` inside the vector field) keeps gathers out of the integration loop.
    """

    def body(y, xs):
        k, theta = xs
        if jump is not None:
            y = jump(k, theta, y)
        y1, ys, ok = simulator.integrate(lambda tau, yy: field(theta, tau, yy), y, dense)
        return y1, (ys, ok)

    num_segments = jax.tree.leaves(data)[0].shape[0]
    yf, (ys, oks) = lax.scan(body, y0, (jnp.arange(num_segments), data))
    return yf, ys, jnp.all(oks)


def segment_data(control: AbstractControl, a):
    """Everything segment k depends on, one row per segment: `[shape coefficients..., t_k, h_k]`."""
    knots = control.knots(a)
    return jnp.concatenate([control.segment_table(a), knots[:-1, None], (knots[1:] - knots[:-1])[:, None]], axis=1)


def rescaled_field(problem: Problem, control: AbstractControl):
    """`field(theta, tau, x) = h f(t_k + h tau, x, u(theta, tau))` for one row `theta` of
    `segment_data`."""
    check_problem_and_control(problem, control)  # at trace time: a fixed final time, free x0

    def field(theta, tau, x):
        row, t_k, h = theta[:-2], theta[-2], theta[-1]
        u = control.local_control(row, h, tau)
        return h * problem.dynamics(t_k + h * tau, x, u, problem.args)

    return field


def initial_state(problem: Problem, control: AbstractControl, a):
    """x(0) for parameters `a`: the problem's x0, with its free components (if any) from `a`."""
    return control.initial_state(problem.x0.astype(a.dtype), a)


def final_state(problem: Problem, control: AbstractControl, a, simulator: AbstractSimulator):
    """x(tf) and the status of the integration (pure; jit/vmap/jacfwd-able)."""
    field = rescaled_field(problem, control)
    xf, _, ok = integrate_segments(simulator, field, segment_data(control, a), initial_state(problem, control, a))
    return xf, simulation_status(ok, xf)


def simulation_status(ok, *values):
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in values]))
    return Status.where(ok, Status.where(finite, Status.SUCCESS, Status.NONFINITE), Status.SIMULATION_FAILED)


class Trajectory(eqx.Module):
    """A dense trajectory for plots and reports.

    `t`, `x`, `u` hold every segment's grid points, segment after segment; a knot appears
    twice (end of one segment, start of the next), so control jumps show as vertical steps.
    """

    t: jax.Array
    x: jax.Array
    u: jax.Array
    knots: jax.Array
    xf: jax.Array
    status: Status = eqx.field(converter=as_indexable)

    @property
    def tf(self):
        return self.knots[..., -1]


def check_simulator(simulator):
    if not isinstance(simulator, AbstractSimulator):
        raise ValueError(f"`simulator` must be jt.RK4(...) or jt.Diffrax(...); got {type(simulator).__name__}.")


@eqx.filter_jit
def _simulate(problem, control, a, simulator):
    field = rescaled_field(problem, control)
    K = control.num_segments
    xf, xs, ok = integrate_segments(
        simulator, field, segment_data(control, a), initial_state(problem, control, a), dense=True
    )
    knots = control.knots(a)
    grid = jnp.asarray(simulator.dense_grid())
    h = knots[1:] - knots[:-1]
    t = knots[:-1, None] + h[:, None] * grid[None, :]
    # each segment ends at its knot exactly (t_k + h_k rounds past t_{k+1} by an ulp: the
    # times went backwards there, and `jt.io.load` refused the saved result)
    t = t.at[:, -1].set(knots[1:])
    ks = jnp.broadcast_to(jnp.arange(K)[:, None], t.shape)
    taus = jnp.broadcast_to(grid[None, :], t.shape)
    u = jax.vmap(jax.vmap(lambda k, tau: control.segment_control(a, k, tau)))(ks, taus)
    return Trajectory(
        t=t.reshape(-1),
        x=xs.reshape(-1, xs.shape[-1]),
        u=u.reshape(-1, u.shape[-1]),
        knots=knots,
        xf=xf,
        status=simulation_status(ok, xf),
    )


def simulate(problem: Problem, control: AbstractControl, a, *, simulator: AbstractSimulator = RK4()) -> Trajectory:
    """Integrate the controlled dynamics from 0 to tf(a) and return the dense trajectory.

    **Arguments:**

    - `problem`: a `jt.Problem`.
    - `control`: a control parametrization (`jt.controls.*`).
    - `a`: parameter vector, shape `(control.num_params,)`.
    - `simulator`: `jt.RK4(steps)` (default, 100 steps per segment) or `jt.Diffrax(...)`.
      Keyword-only.

    **Returns:** a `jt.Trajectory` (t, x, u, knots, xf, status). Jit-compiled; the same
    compiled code serves every value of `a`.

    **Raises:** `ValueError` for a parameter vector of the wrong length, non-finite
    entries, or times out of order (checked on concrete input, outside jit). A final time
    of 0 (every segment collapsed, where a solver may end) gives a trajectory that stays at x0.
    """
    # (tf = 0: a solver's result with every segment collapsed, e.g. from a start at tf =
    # 1e-300; refused, `jaxtraj solve` died before writing the finished solve)
    a = check_inputs(problem, control, a, zero_tf=True)
    check_simulator(simulator)
    points = control.num_segments * simulator.num_dense()
    check_memory(
        "simulator", 8 * points * (problem.num_states + problem.num_controls + 1), f"{points:,} trajectory points"
    )
    with memory_refusal("jt.simulate", "use fewer RK4 steps"):
        return _simulate(problem, control, a, simulator)
