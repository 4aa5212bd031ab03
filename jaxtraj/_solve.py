"""The one driver every solver runs in: `init`, then `step` in a `lax.while_loop` until
`state.done` or `max_steps`, then `postprocess`. Jit-compiled once per (problem, control,
solver configuration, simulator, max_steps); vmap-able over starting vectors."""

import abc

import equinox as eqx
import jax
from jax import lax

from ._problem import Problem
from ._simulate import RK4, AbstractSimulator, check_inputs, check_simulator
from ._solution import History, Solution
from .controls import AbstractControl


class AbstractSolver(eqx.Module):
    """A solver of the restricted problem as a state machine over an array-only state.

    `state` must carry `done` (bool scalar), `num_steps` and `history` (a `History`, written
    only by `History.record`: drivers may give it length 0); `step` performs one trajectory
    integration.
    """

    @abc.abstractmethod
    def init(self, problem, control, a0, simulator, max_steps: int):
        """Initial state (evaluates a0)."""

    @abc.abstractmethod
    def step(self, problem, control, simulator, state):
        """One step (at most one integration with sensitivities); returns the new state."""

    @abc.abstractmethod
    def postprocess(self, problem, control, simulator, state) -> Solution:
        """The `Solution` (status MAX_ITERATIONS if the loop ran out of steps)."""

    @abc.abstractmethod
    def progress(self, state) -> dict:
        """Scalars worth printing during a long solve (name -> array)."""


def _print_progress(step, values):
    parts = [f"step {int(step):5d}"] + [f"{k} {float(v):.6g}" for k, v in values.items()]
    print("  " + "  ".join(parts), flush=True)


def _init(solver, problem, control, a0, simulator, max_steps, history=True):
    """The solver's initial state; with `history=False` its `History` has length 0 (not
    recorded: under `vmap` the per-step record of a long history costs more than a step)."""
    state = solver.init(problem, control, a0, simulator, max_steps)
    return state if history else eqx.tree_at(lambda s: s.history, state, History.empty(0))


def _loop(solver, problem, control, a0, simulator, max_steps, progress_every=0, history=True):
    """The solver's final state: `init`, then `step` until `done` or `max_steps` steps."""
    state = _init(solver, problem, control, a0, simulator, max_steps, history)
    dynamic, static = eqx.partition(state, eqx.is_array)

    def cond(dyn):
        s = eqx.combine(dyn, static)
        return ~s.done & (s.num_steps < max_steps)

    def body(dyn):
        new = solver.step(problem, control, simulator, eqx.combine(dyn, static))
        new_dyn, new_static = eqx.partition(new, eqx.is_array)
        assert eqx.tree_equal(static, new_static) is True  # trace-time guard: no static drift
        if progress_every:
            lax.cond(
                (new.num_steps % progress_every == 0) | new.done,
                lambda: jax.debug.callback(_print_progress, new.num_steps, solver.progress(new)),
                lambda: None,
            )
        return new_dyn

    return eqx.combine(lax.while_loop(cond, body, dynamic), static)


@eqx.filter_jit
def _run(solver, problem, control, a0, simulator, max_steps, progress_every=0):
    state = _loop(solver, problem, control, a0, simulator, max_steps, progress_every)
    return solver.postprocess(problem, control, simulator, state)


def _check_solver(solver, max_steps):
    """The solver to use (default `jt.KalmanSQP()`), after checking it and `max_steps`."""
    if solver is None:
        from ._kalman_sqp import KalmanSQP  # it imports this module

        solver = KalmanSQP()
    if not isinstance(solver, AbstractSolver):
        raise ValueError(f"`solver` must be a jaxtraj solver (e.g. jt.KalmanSearch()); got {type(solver).__name__}.")
    if not (isinstance(max_steps, int) and max_steps >= 1):
        raise ValueError(f"`max_steps` must be an int >= 1; got {max_steps!r}.")
    return solver


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

    **Raises:** `ValueError` for bad input (outside jit).
    """
    solver = _check_solver(solver, max_steps)
    a0 = check_inputs(problem, control, a0)
    check_simulator(simulator)
    if not (isinstance(progress, int) and progress >= 0):
        raise ValueError(f"`progress` must be an int >= 0; got {progress!r}.")
    return _run(solver, problem, control, a0, simulator, max_steps, progress)
