"""An augmented-Lagrangian solver (seed 002, eq. 9) with an optax inner minimizer.

The restricted problem is

    minimize G(a)   subject to   E(a) = 0 (terminal),   C(a) <= 0 (path on the grid, terminal),
                                 a in the parameter box B (control bounds, ordered times).

The equalities enter with one penalty each, the inequality rows through the
Powell-Hestenes-Rockafellar term, all scaled by their gradient norms at a0
(`constraint_scale`). Outer iterations update the multipliers and grow the penalties by
ALGENCAN's rule; inner iterations (one per `step`) are `optax.lbfgs` or `optax.adam` steps in
coordinates preconditioned by the Gauss-Newton curvature of the penalty terms, on gradients
assembled from the forward sensitivities (`al_value`, a `jax.custom_vjp`). The parameter box
(`ParameterBox`) is kept by projection.

(The algorithm, its history and measurements: docs/solvers/augmented-lagrangian.md.)
"""

import math
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._checks import check_settings, is_count
from ._driver import AbstractSolver, SolverState, start_counters
from ._kkt import ACTIVE_TOL, inequality_rows, multipliers, parameter_scale
from ._sensitivity import Evaluation, evaluate_jitted
from ._solution import Solution
from ._status import Status, diverged, failed
from .controls import saturates_within, value_bounds

# ------------------------------------------------------------------------------------------
# The parameter box
# ------------------------------------------------------------------------------------------


#: a component this close to a bound (relative to max(|bound|, 1)) with the gradient pushing
#: it out is decoupled in the metric (`gauss_newton_metric`); KalmanSQP's `path_active`
BOUND_TOLERANCE = 1e-6


class ParameterBox(eqx.Module):
    """Bounds of a parameter vector: `lower <= a <= upper` component-wise (+-inf where free),
    and, if `knot_indices` is not empty, the free knot times a[knot_indices] = t_1..t_K kept
    increasing with gaps >= `min_gap`."""

    lower: jax.Array
    upper: jax.Array
    knot_indices: tuple[int, ...] = ()
    min_gap: float = 0.0

    def project(self, a):
        a = jnp.clip(a, self.lower, self.upper)
        if self.knot_indices:
            idx = jnp.asarray(self.knot_indices)
            t = a[idx]
            offs = self.min_gap * jnp.arange(1, t.shape[0] + 1, dtype=a.dtype)
            t = offs + jnp.maximum(0.0, jax.lax.cummax(t - offs))
            a = a.at[idx].set(t)
        return a

    def binding(self, a, g, tolerance=0.0):
        """The components on, beyond or within `tolerance` (relative to max(|bound|, 1)) of a
        bound that -g points out of."""

        def near(bound):
            return jnp.where(jnp.isfinite(bound), tolerance * jnp.maximum(jnp.abs(bound), 1.0), 0.0)

        return ((a <= self.lower + near(self.lower)) & (g > 0)) | ((a >= self.upper - near(self.upper)) & (g < 0))

    def reduce(self, a, g):
        """The gradient with the components zeroed where `a` sits on (or beyond) a bound and
        -g points out of the box. For free knot times the same rule acts on the durations
        h_k = t_k - t_(k-1) >= `min_gap` (gradient d/dh_k = sum_(j >= k) d/dt_j)."""
        g = jnp.where(self.binding(a, g), 0.0, g)
        if self.knot_indices:
            idx = jnp.asarray(self.knot_indices)
            t = a[idx]
            h = jnp.diff(t, prepend=jnp.zeros(1, t.dtype))
            g_h = jnp.cumsum(g[idx][::-1])[::-1]
            slack = self.min_gap * 1e-6 + 8.0 * jnp.finfo(t.dtype).eps * jnp.abs(t)
            g_h = jnp.where((h <= self.min_gap + slack) & (g_h > 0), 0.0, g_h)
            g = g.at[idx].set(g_h - jnp.concatenate([g_h[1:], jnp.zeros(1, g_h.dtype)]))
        return g


def _stationarity(box: ParameterBox, a, grad):
    """The reduced gradient's norm in the scaled parameters a_i / max(|a_i|, 1), as every
    solver's KKT test (`jaxtraj._kkt.stationarity`)."""
    return jnp.linalg.norm(parameter_scale(a) * box.reduce(a, grad))


def parameter_box(problem, control, min_duration: float = 1e-6) -> ParameterBox:
    """The `ParameterBox` of `control`'s parameters for `problem` (see docs/solvers/augmented-lagrangian.md), from
    the family's declared layout (`value_indices`, `limits`, `time_layout`). Pure (usable
    inside jit: the problem's bounds may be traced).

    **Raises:** `ValueError` (at trace time) if `problem` declares control bounds that the
    family has no control-value parameters for."""
    n = control.num_params
    lower = jnp.full(n, -jnp.inf)
    upper = jnp.full(n, jnp.inf)
    bounded = problem.control_lower is not None or problem.control_upper is not None
    idx, lo, hi = value_bounds(control, problem.control_lower, problem.control_upper)
    if bounded and not idx.size and not saturates_within(control, problem.control_lower, problem.control_upper):
        raise ValueError(
            f"`control`: {type(control).__name__} declares no control-value parameters "
            "(`value_indices`) and does not saturate within the bounds, so AugmentedLagrangian "
            "cannot honor the problem's control_lower/control_upper."
        )
    if idx.size:
        lower, upper = lower.at[idx].set(lo), upper.at[idx].set(hi)
    if problem.free_initial_state:
        free = np.asarray(control.parameter_indices, int)
        lower, upper = (b.at[free].set(v) for b, v in zip((lower, upper), problem.initial_state_bounds))
    times = np.asarray(control.time_indices, int)
    if control.time_layout == "durations":
        return ParameterBox(lower.at[times].set(min_duration), upper)
    if control.time_layout == "final_time":  # tf alone, equally spaced knots
        return ParameterBox(lower.at[times[0]].set(control.num_segments * min_duration), upper)
    if control.time_layout == "fixed":  # no time parameter
        return ParameterBox(lower, upper)
    if control.time_layout == "interior_knots":  # t_1 < ... < t_(K-1) < T fixed
        upper = upper.at[times[-1]].set(problem.final_time - min_duration) if times.size else upper
    return ParameterBox(lower, upper, tuple(int(t) for t in times), float(min_duration))


# ------------------------------------------------------------------------------------------
# The augmented Lagrangian
# ------------------------------------------------------------------------------------------


class Multipliers(eqx.Module):
    """Multipliers and penalties of the scaled constraints: `lam`, `rho` (l,) for E = 0;
    `nu` (R,) for the inequality rows C <= 0 (`inequality_block`: the path constraints on the
    grid, then the terminal inequalities) and one penalty `sigma` (g,) per row group (a path
    component, a terminal inequality); `e_scale` (l,), `c_scale` (g,): the constraint scaling
    (docs/solvers/augmented-lagrangian.md)."""

    lam: jax.Array
    rho: jax.Array
    nu: jax.Array
    sigma: jax.Array
    e_scale: jax.Array
    c_scale: jax.Array


def inequality_block(ev: Evaluation):
    """`(C, C_a, groups)`: the inequality rows of the augmented Lagrangian, C (R,) and C_a
    (R, np), `_kkt.inequality_rows` without the control-bound rows (the projection keeps the
    bounds): the path constraints on the grid (point after point), then the terminal
    inequalities D; and `groups` (R,), a static array naming each row's penalty group: path
    component j is group j (one penalty over the grid: the contact point of a touching
    constraint moves between grid points), terminal inequality i is group q + i."""
    no_bounds = eqx.tree_at(lambda e: (e.V, e.V_a), ev, (None, None), is_leaf=lambda x: x is None)
    rows = inequality_rows(no_bounds)
    if rows is None:
        rows = jnp.zeros(0, ev.G_a.dtype), jnp.zeros((0, ev.G_a.shape[0]), ev.G_a.dtype)
    n, q = (0, 0) if ev.C is None else ev.C.shape
    r = 0 if ev.D is None else ev.D.shape[0]
    return (*rows, np.concatenate([np.tile(np.arange(q), n), q + np.arange(r)]).astype(int))


def _num_groups(ev: Evaluation):
    """The penalty groups of `inequality_block`: path components, then terminal inequalities."""
    return (0 if ev.C is None else ev.C.shape[1]) + (0 if ev.D is None else ev.D.shape[0])


def _group_max(values, groups, num_groups):
    """The largest of `values` (>= 0) in each group, 0 for an empty group."""
    return jnp.maximum(jax.ops.segment_max(values, groups, num_groups), 0.0)


def augmented_lagrangian(ev: Evaluation, m: Multipliers):
    """`(L_A, dL_A/da)` at an evaluation (docs/solvers/augmented-lagrangian.md), assembled from G_a, H and the
    inequality rows' Jacobian, with the scaled constraints e_scale E and c_scale C."""
    C, C_a, groups = inequality_block(ev)
    E, H = m.e_scale * ev.E, m.e_scale[:, None] * ev.H
    value = ev.G - m.lam @ E + 0.5 * jnp.sum(m.rho * E**2)
    grad = ev.G_a + (m.rho * E - m.lam) @ H
    sigma, scale = m.sigma[groups], m.c_scale[groups]
    s = jnp.maximum(0.0, m.nu + sigma * scale * C)
    value = value + jnp.sum((s**2 - m.nu**2) / (2.0 * sigma))
    grad = grad + (s * scale) @ C_a
    return value, grad


def constraint_scale(rows, floor=1e-3):
    """1 / |row| for each constraint gradient (last axis), with the norms floored at `floor`
    times the largest (and at 1e-300), so that every scaled constraint has a unit gradient
    at the start except those (nearly) insensitive to the parameters there."""
    norms = jnp.linalg.norm(rows, axis=-1)
    top = jnp.max(norms, initial=0.0)
    scale = 1.0 / jnp.maximum(norms, jnp.maximum(floor * top, 1e-300))
    return jnp.where(jnp.isfinite(scale), scale, 1.0)


class Metric(eqx.Module):
    """Preconditioned coordinates z = L^T (a - center), M = L L^T (docs/solvers/augmented-lagrangian.md): the inner
    minimizer works on z, where the penalty terms' Gauss-Newton curvature is the identity."""

    center: jax.Array
    L: jax.Array  # lower Cholesky factor of M

    def to_z(self, a):
        return self.L.T @ (a - self.center)

    def to_a(self, z):
        return self.center + jax.scipy.linalg.solve_triangular(self.L.T, z, lower=False)

    def grad_z(self, g):
        """d/dz of a function whose gradient in a is g."""
        return jax.scipy.linalg.solve_triangular(self.L, g, lower=True)


def gauss_newton_metric(ev: Evaluation, m: Multipliers, a, grad, box: ParameterBox, curvature):
    """`Metric` at `a` with M = curvature I + sum_i rho_i h_i h_i^T + sum_(active j) sigma_j c_j
    c_j^T (h_i, c_j: gradients of the scaled constraints; an inequality row is active where
    nu + sigma C > 0); rows and columns of parameters on or near (`BOUND_TOLERANCE`) a bound the
    gradient pushes them out of are decoupled."""
    C, C_a, groups = inequality_block(ev)
    Hs = m.e_scale[:, None] * ev.H
    Cs_a = m.c_scale[groups][:, None] * C_a
    sigma = m.sigma[groups]
    w = jnp.where(m.nu + sigma * m.c_scale[groups] * C > 0, sigma, 0.0)
    gn = (Hs.T * m.rho[None, :]) @ Hs + (Cs_a.T * w[None, :]) @ Cs_a
    n = a.shape[0]
    # Decoupled: the components on a bound that the gradient pushes out of, and those within
    # BOUND_TOLERANCE (relative to max(|bound|, 1)) of it (Bertsekas's epsilon-active set).
    # With exact comparisons a node 1.6e-11 below its bound stayed coupled: its share of the
    # step was clipped by the projection after 1.6e-11 and the rest of the step ascended, so
    # every step was rejected (`test_control_bounds_against_slsqp` on an AVX-without-AVX2
    # CPU). Decoupled, its own step takes it onto the bound and the rest descends.
    free = ~box.binding(a, grad, BOUND_TOLERANCE)
    gn = jnp.where(free[:, None] & free[None, :], gn, 0.0)
    M = gn + curvature * jnp.eye(n, dtype=a.dtype)
    L = jnp.linalg.cholesky(0.5 * (M + M.T))
    L = jnp.where(jnp.all(jnp.isfinite(L)), L, jnp.sqrt(curvature) * jnp.eye(n, dtype=a.dtype))
    return Metric(center=a, L=L)


def al_value(problem, control, simulator, box: ParameterBox, m: Multipliers, metric: Metric, method="forward"):
    """The scalar function z -> L_A(P(metric.to_a(z))) (P = `box.project`) as a
    `jax.custom_vjp`: its forward pass is one integration with forward sensitivities, its
    gradient is the reduced gradient (`ParameterBox.reduce`) assembled from the sensitivities
    (G_a, H and the inequality rows' Jacobian), mapped to z. For optax's line search (`jax.value_and_grad`); non-finite
    evaluations give +inf."""
    dynamic, static = eqx.partition((problem, control, simulator, box, m, metric), eqx.is_array)

    def evaluate(z, dyn):
        problem, control, simulator, box, m, metric = eqx.combine(dyn, static)
        x = metric.to_a(z)
        ev = evaluate_jitted(problem, control, box.project(x), simulator, method)
        value, grad = augmented_lagrangian(ev, m)
        ok = (ev.status == Status.SUCCESS) & jnp.isfinite(value) & jnp.all(jnp.isfinite(grad))
        return jnp.where(ok, value, jnp.inf), jnp.where(ok, metric.grad_z(box.reduce(x, grad)), 0.0)

    @jax.custom_vjp
    def f(z, dyn):
        return evaluate(z, dyn)[0]

    def fwd(z, dyn):
        value, grad = evaluate(z, dyn)
        return value, (grad, dyn)

    def bwd(res, ct):
        grad, dyn = res
        return ct * grad, jax.tree.map(_zero_cotangent, dyn)

    f.defvjp(fwd, bwd)
    return lambda z: f(z, dynamic)


def _zero_cotangent(v):
    if jnp.issubdtype(v.dtype, jnp.inexact):
        return jnp.zeros_like(v)
    return np.zeros(v.shape, dtype=jax.dtypes.float0)


# ------------------------------------------------------------------------------------------
# The solver
# ------------------------------------------------------------------------------------------


class _State(SolverState):
    a: jax.Array
    ev: Evaluation
    value: jax.Array  # L_A(a) with the current multipliers
    grad: jax.Array  # dL_A/da (full, not reduced)
    m: Multipliers
    metric: Metric
    opt_state: optax.OptState
    omega: jax.Array  # inner tolerance in force
    prev_E: jax.Array  # |scaled E| at the previous outer update (inf at first)
    prev_V: jax.Array  # max |scaled V| per path component at the previous outer update
    inner_count: jax.Array
    inner_accepted: jax.Array  # accepted steps in this outer iteration
    rejected: jax.Array  # consecutive rejected steps
    num_outer: jax.Array


class AugmentedLagrangian(AbstractSolver):
    """Augmented-Lagrangian method with an optax inner minimizer (see docs/solvers/augmented-lagrangian.md).

    Fields:

    - `inner`: `"lbfgs"` (`optax.lbfgs` with its zoom line search) or `"adam"`.
    - `ctol`: feasibility tolerance on max |E_i| and on the path constraints (1e-9).
    - `gtol`: final tolerance on the reduced gradient of the Lagrangian, relative to 1 + |G|.
    - `inner_tol_init`, `inner_tol_shrink`: the first inner tolerance (relative like `gtol`)
      and its factor per outer iteration (never below `gtol`).
    - `max_inner`: inner steps before an outer update is forced.
    - `max_outer`: outer iterations before MAX_ITERATIONS.
    - `penalty_init`: first penalty (None: ALGENCAN's scaling rule).
    - `penalty_growth`, `feasibility_ratio`: a penalty is multiplied by `penalty_growth`
      when its constraint's infeasibility did not fall below `feasibility_ratio` times the
      previous one.
    - `penalty_max`, `multiplier_max`: caps.
    - `learning_rate`: Adam's step size (parameter units; `inner="adam"` only).
    - `memory_size`, `max_linesearch_steps`: of L-BFGS and its zoom line search.
    - `min_duration`: smallest segment duration kept by the projection.
    - `precondition`: inner minimization in the Gauss-Newton preconditioned coordinates.
    - `curvature`: the curvature assumed for the Lagrangian in the preconditioner (parameter
      units; the library's problems have O(1) parameters).
    - `max_step`: largest change of any parameter in one L-BFGS step (parameter units).
    - `method`: sensitivity method (`"forward"`; `"unit"`/`"fd"` for problems without path
      constraints).

    History: `rho` holds the length |delta a| of the step taken, `phase` the outer iteration
    index, `constraint_tolerance` `ctol`. `iterations` counts accepted inner steps.
    """

    inner: str = "lbfgs"
    ctol: float = 1e-9
    gtol: float = 1e-6
    inner_tol_init: float = 1e-2
    inner_tol_shrink: float = 0.1
    max_inner: int = 200
    max_outer: int = 40
    penalty_init: float | None = None
    penalty_growth: float = 10.0
    feasibility_ratio: float = 0.25
    penalty_max: float = 1e12
    multiplier_max: float = 1e12
    learning_rate: float = 1e-2
    memory_size: int = 10
    max_linesearch_steps: int = 20
    min_duration: float = 1e-6
    precondition: bool = True
    max_step: float = 1.0
    curvature: float = 1.0
    method: str = "forward"

    def __check_init__(self):
        if self.inner not in ("lbfgs", "adam"):
            raise ValueError(f"AugmentedLagrangian: `inner` must be 'lbfgs' or 'adam'; got {self.inner!r}.")
        if self.method not in ("forward", "unit", "fd"):
            raise ValueError(f"AugmentedLagrangian: `method` must be 'forward', 'unit' or 'fd'; got {self.method!r}.")

        checks = {
            "ctol": lambda: 0 < self.ctol < math.inf,
            "gtol": lambda: 0 < self.gtol < math.inf,
            "inner_tol_init": lambda: self.inner_tol_init > 0,
            "inner_tol_shrink": lambda: 0 < self.inner_tol_shrink <= 1,
            "max_inner": lambda: is_count(self.max_inner, 1),
            "max_outer": lambda: is_count(self.max_outer, 1),
            "penalty_init": lambda: self.penalty_init is None or self.penalty_init > 0,
            "penalty_growth": lambda: self.penalty_growth > 1,
            "feasibility_ratio": lambda: 0 < self.feasibility_ratio < 1,
            "penalty_max": lambda: self.penalty_max > 0,
            "multiplier_max": lambda: self.multiplier_max > 0,
            "learning_rate": lambda: self.learning_rate > 0,
            "memory_size": lambda: is_count(self.memory_size, 1),
            "max_linesearch_steps": lambda: is_count(self.max_linesearch_steps, 1),
            "min_duration": lambda: self.min_duration > 0,
            "precondition": lambda: isinstance(self.precondition, bool),
            "curvature": lambda: self.curvature > 0,
            "max_step": lambda: self.max_step > 0,
        }
        check_settings("AugmentedLagrangian", self, checks, flags=("precondition",))

    # ------------------------------------------------------------------ pieces

    def _optimizer(self):
        """Adam, or the L-BFGS direction of `optax.lbfgs` (its first two links; the third, its
        zoom line search, is `_linesearch`, applied separately so that its largest step can
        depend on the direction)."""
        if self.inner == "adam":
            return optax.adam(self.learning_rate)
        return optax.chain(optax.scale_by_lbfgs(memory_size=self.memory_size), optax.scale(-1.0))

    def _linesearch(self, max_learning_rate=None):
        return optax.scale_by_zoom_linesearch(
            max_linesearch_steps=self.max_linesearch_steps,
            max_learning_rate=max_learning_rate,
            initial_guess_strategy="one",
        )

    def _init_opt(self, z):
        if self.inner == "adam":
            return self._optimizer().init(z)
        return (self._optimizer().init(z), self._linesearch().init(z))

    def _evaluate(self, problem, control, a, simulator):
        return evaluate_jitted(problem, control, a, simulator, self.method)

    def _initial_multipliers(self, ev: Evaluation):
        C, C_a, groups = inequality_block(ev)
        num_groups = _num_groups(ev)
        e_scale = constraint_scale(ev.H)
        # one scale per row group: its largest gradient (over the grid for a path component)
        c_scale = constraint_scale(_group_max(jnp.linalg.norm(C_a, axis=-1), groups, num_groups)[:, None])
        E, Cs = e_scale * ev.E, c_scale[groups] * C
        if self.penalty_init is None:
            infeas = 0.5 * (E @ E) + 0.5 * jnp.sum(jnp.maximum(Cs, 0.0) ** 2)
            rho0 = jnp.clip(10.0 * jnp.maximum(1.0, jnp.abs(ev.G)) / jnp.maximum(1.0, infeas), 1e-8, 1e8)
            rho0 = jnp.where(jnp.isfinite(rho0), rho0, 1.0)
        else:
            rho0 = jnp.asarray(self.penalty_init, ev.G.dtype)
        # first-order estimate: G_a = lambda^T (e_scale H) in the least-squares sense
        lam0 = -multipliers(e_scale[:, None] * ev.H, ev.G_a)
        lam0 = jnp.clip(jnp.where(jnp.all(jnp.isfinite(lam0)), lam0, 0.0), -self.multiplier_max, self.multiplier_max)
        return Multipliers(
            lam=lam0,
            rho=jnp.full_like(ev.E, rho0),
            nu=jnp.zeros_like(C),
            sigma=jnp.full(num_groups, rho0, C.dtype),
            e_scale=e_scale,
            c_scale=c_scale,
        )

    def _scale(self, ev):
        return 1.0 + jnp.abs(ev.G)

    # ------------------------------------------------------------------ state machine

    def init(self, problem, control, a0, simulator, max_steps):
        box = parameter_box(problem, control, self.min_duration)
        a = box.project(a0)
        ev = self._evaluate(problem, control, a, simulator)
        m = self._initial_multipliers(ev)
        value, grad = augmented_lagrangian(ev, m)
        ok = (
            (ev.status == Status.SUCCESS) & jnp.isfinite(value) & jnp.all(jnp.isfinite(grad)) & jnp.all(jnp.isfinite(a))
        )
        metric = self._metric(ev, m, a, grad, box)
        f = jnp.float64
        status = Status.where(ok, Status.SUCCESS, failed(ev.status))
        return _State(
            a=a,
            ev=ev,
            value=value,
            grad=grad,
            m=m,
            metric=metric,
            opt_state=self._init_opt(jnp.zeros_like(a)),
            omega=jnp.asarray(max(self.inner_tol_init, self.gtol), f),
            prev_E=jnp.full_like(ev.E, jnp.inf),
            prev_V=jnp.full(_num_groups(ev), jnp.inf, ev.G.dtype),
            inner_count=jnp.array(0, jnp.int32),
            inner_accepted=jnp.array(0, jnp.int32),
            rejected=jnp.array(0, jnp.int32),
            num_outer=jnp.array(0, jnp.int32),
            **start_counters(max_steps, ("outer_iteration",), integrations=1, done=~ok, status=status),
        )

    def _metric(self, ev, m, a, grad, box):
        if self.precondition:
            return gauss_newton_metric(ev, m, a, grad, box, self.curvature)
        return Metric(center=a, L=jnp.eye(a.shape[0], dtype=a.dtype))

    def step(self, problem, control, simulator, state: _State):
        box = parameter_box(problem, control, self.min_duration)
        opt = self._optimizer()
        a, m, metric = state.a, state.m, state.metric
        z = metric.to_z(a)
        g_z = metric.grad_z(box.reduce(a, state.grad))

        # ---- one inner iteration (optax, in the preconditioned z), then one evaluation at
        # the projected new point
        if self.inner == "lbfgs":
            fn = al_value(problem, control, simulator, box, m, metric, self.method)
            # optax's L-BFGS stores the pair (z - z_prev, g - g_prev) without a curvature
            # check; the projection can make it non-positive: restart the memory then.
            # (`_init_opt`'s pair: the chain's states, L-BFGS's first, and the line search's; optax
            # annotates states as any tree, their fields as any array-like: arrays here)
            lb = cast(Any, state.opt_state)[0][0]
            s_, y_ = z - lb.params, g_z - lb.updates
            bad_pair = (lb.count > 0) & ~(s_ @ y_ > 1e-12 * jnp.linalg.norm(s_) * jnp.linalg.norm(y_))
            prior = jax.tree.map(lambda n, o: jnp.where(bad_pair, n, o), self._init_opt(z), state.opt_state)
            # (optax's L-BFGS adds its int32 memory index to an int64 arange under x64: standard
            # promotion for that call, whatever the user set)
            with jax.numpy_dtype_promotion("standard"):
                direction, dir_state = opt.update(g_z, prior[0], z)
            # the line search's largest step keeps every parameter's change <= max_step
            reach = jnp.max(jnp.abs(metric.to_a(direction) - metric.center))
            cap = self.max_step / jnp.where(reach > 0, reach, 1.0)
            updates, ls_state = self._linesearch(cap).update(
                direction, prior[1], z, value=state.value, grad=g_z, value_fn=fn
            )
            opt_state = (dir_state, ls_state)
            trials = cast(Any, ls_state).info.num_linesearch_steps.astype(jnp.int32)  # (as `lb` above)
        else:
            # (optax's Adam raises a float decay to its int32 step count: standard promotion)
            with jax.numpy_dtype_promotion("standard"):
                updates, opt_state = opt.update(g_z, state.opt_state, z)
            trials = jnp.array(0, jnp.int32)
        # (optax's updates have the parameters' structure: here one array)
        cand_a = box.project(metric.to_a(z + cast(jax.Array, updates)))
        cand = self._evaluate(problem, control, cand_a, simulator)
        cand_value, cand_grad = augmented_lagrangian(cand, m)
        finite = (
            (cand.status == Status.SUCCESS)
            & jnp.isfinite(cand_value)
            & jnp.all(jnp.isfinite(cand_grad))
            & jnp.all(jnp.isfinite(cand_a))
        )
        if self.inner == "lbfgs":
            slack = 10.0 * jnp.finfo(cand_value.dtype).eps * (1.0 + jnp.abs(state.value))
            accept = finite & (cand_value <= state.value + slack)
        else:
            accept = finite
        pick = lambda new, old: jax.tree.map(lambda n, o: jnp.where(accept, n, o), new, old)
        new_a = pick(cand_a, a)
        ev = pick(cand, state.ev)
        value, grad = pick(cand_value, state.value), pick(cand_grad, state.grad)
        opt_state = jax.tree.map(lambda n, o: jnp.where(accept, n, o), opt_state, self._init_opt(z))
        rejected = jnp.where(accept, 0, state.rejected + 1)
        inner_count = state.inner_count + 1
        inner_accepted = state.inner_accepted + accept.astype(jnp.int32)

        # ---- inner termination, and the outer update computed for every step (branch-free)
        scale = self._scale(ev)
        pg = _stationarity(box, new_a, grad)
        stuck = rejected >= 2
        solved = pg <= state.omega * scale
        inner_done = solved | (inner_count >= self.max_inner) | stuck

        C, _, groups = inequality_block(ev)
        num_groups = _num_groups(ev)
        scale_r, sigma_r = m.c_scale[groups], m.sigma[groups]
        Es, Cs = m.e_scale * ev.E, scale_r * C  # scaled: the penalty rule and the updates
        V = jnp.maximum(C, -m.nu / (sigma_r * scale_r))  # unscaled: the tests
        Vs = _group_max(jnp.abs(scale_r * V), groups, num_groups)  # per row group
        absV = _group_max(jnp.abs(V), groups, num_groups)
        maxE = jnp.max(jnp.abs(ev.E), initial=0.0)
        maxV = jnp.max(V, initial=-jnp.inf)
        feasible = (maxE <= self.ctol) & (maxV <= self.ctol)
        converged = inner_done & feasible & (pg <= self.gtol * scale)
        stalled = inner_done & stuck & (inner_accepted == 0) & feasible & ~converged
        gone = diverged(ev.G, new_a) & ~converged

        cap = self.multiplier_max
        lam1 = jnp.clip(m.lam - m.rho * Es, -cap, cap)
        nu1 = jnp.clip(jnp.maximum(0.0, m.nu + sigma_r * Cs), 0.0, cap)
        # Penalties grow only after a solved inner problem (an unfinished one says nothing
        # about the penalty being too small).
        grow_E = solved & (jnp.abs(Es) > self.feasibility_ratio * state.prev_E) & (jnp.abs(ev.E) > self.ctol)
        grow_V = solved & (Vs > self.feasibility_ratio * state.prev_V) & (absV > self.ctol)
        rho1 = jnp.where(grow_E, jnp.minimum(self.penalty_growth * m.rho, self.penalty_max), m.rho)
        sigma1 = jnp.where(grow_V, jnp.minimum(self.penalty_growth * m.sigma, self.penalty_max), m.sigma)
        m_outer = Multipliers(lam=lam1, rho=rho1, nu=nu1, sigma=sigma1, e_scale=m.e_scale, c_scale=m.c_scale)
        value_outer, grad_outer = augmented_lagrangian(ev, m_outer)  # no integration
        metric_outer = self._metric(ev, m_outer, new_a, grad_outer, box)
        outer = inner_done & ~converged & ~stalled
        sel = lambda new, old: jax.tree.map(lambda n, o: jnp.where(outer, n, o), new, old)
        m_new, metric_new = sel(m_outer, m), sel(metric_outer, metric)
        value, grad = sel(value_outer, value), sel(grad_outer, grad)
        opt_state = sel(self._init_opt(z), opt_state)  # new coordinates: a fresh memory
        num_outer = state.num_outer + outer.astype(jnp.int32)
        done = converged | stalled | gone | (num_outer >= self.max_outer)

        i = state.num_steps
        history = state.history.record(
            i,
            objective=ev.G,
            max_constraint_error=maxE,
            step_norm=jnp.linalg.norm(cand_a - a),
            accepted=accept,
            constraint_tolerance=self.ctol,
            details={"outer_iteration": state.num_outer},
        )
        return _State(
            a=new_a,
            ev=ev,
            value=value,
            grad=grad,
            m=m_new,
            metric=metric_new,
            opt_state=opt_state,
            omega=jnp.where(outer, jnp.maximum(state.omega * self.inner_tol_shrink, self.gtol), state.omega),
            prev_E=jnp.where(outer, jnp.abs(Es), state.prev_E),
            prev_V=jnp.where(outer, Vs, state.prev_V),
            inner_count=jnp.where(inner_done, 0, inner_count),
            inner_accepted=jnp.where(inner_done, 0, inner_accepted),
            rejected=jnp.where(inner_done, 0, rejected),
            num_outer=num_outer,
            num_iterations=state.num_iterations + accept.astype(jnp.int32),
            num_integrations=state.num_integrations + 1 + trials,
            num_steps=i + 1,
            done=done,
            status=Status.where(
                converged,
                Status.SUCCESS,
                Status.where(gone, Status.DIVERGED, Status.where(stalled, Status.STALLED, Status.MAX_ITERATIONS)),
            ),
            history=history,
        )

    def progress(self, state: _State):
        C, _, _ = inequality_block(state.ev)
        return {
            "outer": state.num_outer,
            "objective": state.ev.G,
            "max|E|": jnp.max(jnp.abs(state.ev.E), initial=0.0),
            "max C": jnp.max(C, initial=-jnp.inf),
            "L_A": state.value,
            "max rho": jnp.max(state.m.rho, initial=0.0),
        }

    def postprocess(self, problem, control, simulator, state: _State) -> Solution:
        box = parameter_box(problem, control, self.min_duration)
        return Solution.from_evaluation(
            state.ev,
            state.a,
            control=control,
            active_tol=ACTIVE_TOL,
            projected_gradient=_stationarity(box, state.a, state.grad),
            iterations=state.num_iterations,
            integrations=state.num_integrations,
            steps=state.num_steps,
            done=state.done,
            status=state.status,
            history=state.history,
        )
