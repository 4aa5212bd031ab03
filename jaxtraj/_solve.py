"""`jt.solve`: check the input, pick the default solver, run the driver (differentiable by
the implicit function theorem: `_implicit`)."""

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _export_cache
from ._checks import (
    BOUNDS_CHANGED,
    CLOSED_OVER_TRACER,
    bounds_changed,
    check_inputs,
    check_memory,
    check_problem_and_control,
    check_solver_memory,
    closed_over_tracer,
    follow_final_time,
    is_count,
    memory_refusal,
    traced_bounds,
)
from ._driver import HISTORY_BYTES, AbstractSolver, check_max_steps, check_step_counter, run
from ._implicit import differentiable_solve
from ._kalman_sqp import KalmanSQP
from ._kkt import ACTIVE_TOL
from ._problem import Problem
from ._simulate import RK4, AbstractSimulator, check_simulator
from ._solution import Solution
from .controls import AbstractControl


def check_solver(solver, max_steps):
    """`(solver, max_steps)`: the solver to use (default `jt.KalmanSQP()`) and the step limit
    as an int, after checking both."""
    if solver is None:
        solver = KalmanSQP()
    if not isinstance(solver, AbstractSolver):
        raise ValueError(f"`solver` must be a jaxtraj solver (e.g. jt.KalmanSearch()); got {type(solver).__name__}.")
    return solver, check_max_steps(max_steps)


def check_start(problem, control, a0):
    """`check_inputs`; where the concrete checks of `a0`'s values cannot run because the
    control's arrays are traced (a fixed final time under `jax.grad`, or inside `jax.jit`,
    where even a constant becomes a tracer), `a0`'s shape only, as for a traced start."""
    try:
        return check_inputs(problem, control, a0)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        check_problem_and_control(problem, control)
    a0 = jnp.asarray(a0, dtype=jnp.float64)
    if a0.shape != (control.num_params,):
        raise ValueError(f"`a` must have shape ({control.num_params},) for {control!r}; got {a0.shape}.")
    return a0


def solve(
    problem: Problem,
    control: AbstractControl,
    a0,
    solver: AbstractSolver | None = None,
    *,
    simulator: AbstractSimulator = RK4(),
    max_steps: int = 5000,
    progress: int = 0,
) -> Solution:
    """Solve the restricted problem: minimize G(a) subject to E(a) = 0.

    **Arguments:**

    - `problem`: a `jt.Problem`; `control`: a control family; `a0`: the starting vector.
    - `solver`: default `jt.KalmanSQP()`; `jt.KalmanSearch()` is the source thesis's method.
    - `simulator`: keyword-only, default `jt.RK4(100)`.
    - `max_steps`: keyword-only cap on candidate integrations (static: changing it
      recompiles).
    - `progress`: keyword-only; if > 0, print a progress line every `progress` steps and
      at the end (from inside the compiled loop, via `jax.debug.callback`).

    **Returns:** a `jt.Solution`. Jit-compiled; call it under `jax.vmap` for a batch of
    starting vectors (or use `jt.solve_batch`). Failures are reported in `status`, never
    raised, and a non-finite candidate trajectory is a rejected step, not a NaN result.

    **Derivatives.** `jax.grad`, `jax.jvp`, `jax.jacfwd` / `jax.jacrev` (under `jit` and
    `vmap`) of any float field of the result with respect to the float arrays of `problem`
    (`args`, `x0`, ...) and of `control` (a fixed final time) come from the implicit
    function theorem at the returned point with its active set, never from the iterations;
    `a0` has no derivative, and a solve that did not end SUCCESS (or where the tangent is
    not unique: a singular reduced Hessian, dependent active rows that cannot all stay
    active) gives NaN derivatives. See docs/differentiable.md.

    **Raises:** `ValueError` for bad input (outside jit).
    """
    solver, max_steps = check_solver(solver, max_steps)
    a0 = check_start(problem, control, a0)
    control = follow_final_time(problem, control)
    check_simulator(simulator)
    solver.check(problem, control)
    check_memory("max_steps", max_steps * HISTORY_BYTES, f"the history of {max_steps:,} steps")
    check_step_counter(max_steps)
    check_solver_memory(control)
    # (True printed every step; 2**40 wrapped in int32 and printed every step too)
    if not is_count(progress, 0):
        raise ValueError(f"`progress` must be an int >= 0 and < 2**31; got {progress!r}.")
    progress = int(progress)  # (a NumPy integer, an array leaf, was traced)

    if _export_cache.usable(
        problem, control, a0, progress, solver, simulator
    ):  # (`jt.enable_solve_cache`: primal only)
        with memory_refusal("jt.solve", "use fewer RK4 steps or segments, or a smaller max_steps"):
            sol = _export_cache.cached_solve(run, solver, problem, control, a0, simulator, max_steps)
        if sol is not None:
            return sol

    checked = traced_bounds(problem)

    def solve_from(problem, control, a0):
        if checked:  # (concrete bounds: checked above, `check_problem_and_control`)
            a0 = eqx.error_if(a0, bounds_changed(problem), f"jt.solve: {BOUNDS_CHANGED}")
        return run(solver, problem, control, a0, simulator, max_steps, progress)

    # the activity tolerance of the solver's own KKT test, where it has one
    active_tol = getattr(solver, "path_active", ACTIVE_TOL)
    with memory_refusal("jt.solve", "use fewer RK4 steps or segments, or a smaller max_steps"):
        try:
            return differentiable_solve(solve_from, problem, control, a0, simulator, active_tol)
        except jax.errors.UnexpectedTracerError as e:
            where = closed_over_tracer(problem)
            if where is None:
                raise
            raise ValueError(f"`{where}` {CLOSED_OVER_TRACER}") from e
