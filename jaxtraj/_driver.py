"""The loop contract every solver implements, and the one driver that runs it.

A solver is a state machine over an array-only state: `init` builds the initial state (it
evaluates the start, or leaves that to the first `step`, so that the compiled program holds
each evaluation kernel once), `step` runs in a `lax.while_loop` until `state.done` or
`max_steps` steps, `postprocess` turns the final state into a `Solution`. `run` is jit-compiled once per (problem, control,
solver configuration, simulator, max_steps) and vmap-able over starting vectors; the batch
lane queue (`_batch`) drives the same `init` / `step` per lane. This module imports no
solver (the default one is chosen by `jt.solve`)."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._solution import History, Solution
from ._status import Status, without_point


class SolverState(eqx.Module):
    """The counters every solver's state carries (each solver's state subclasses this and
    adds its own fields): `num_iterations` accepted steps, `num_integrations` integrations
    (with sensitivities or the Hessian's), `num_steps` calls of `step`, `done`, the `status`
    so far, and the `history` (written only by `History.record`)."""

    num_iterations: jax.Array
    num_integrations: jax.Array
    num_steps: jax.Array
    done: jax.Array
    status: Status
    history: History


def start_counters(
    max_steps: int, details: tuple, *, integrations: int = 0, done: bool | jax.Array = False, status=Status.SUCCESS
) -> dict:
    """`SolverState`'s fields at the start, as keywords for the state's constructor: no
    iteration or step yet, `integrations` done by `init`, an empty history of `max_steps`
    entries with the solver's `details`."""
    return dict(
        num_iterations=jnp.array(0, jnp.int32),
        num_integrations=jnp.array(integrations, jnp.int32),
        num_steps=jnp.array(0, jnp.int32),
        done=jnp.asarray(done),
        status=status,
        history=History.empty(max_steps, details),
    )


class AbstractSolver(eqx.Module):
    """A solver of the restricted problem as a state machine over an array-only state.

    `state` is a `SolverState` (its subclass with the solver's own fields; drivers may give
    its `history` length 0). Each `step` integrates one
    candidate point with sensitivities (KalmanSQP adds one second-order integration, the
    exact Hessian, at an accepted point; `Solution.integrations` counts them all) and
    records one History entry. A batch runs `step` vmapped, finished lanes included (their
    results are dropped, their state marked `done`): work only some steps need belongs
    under `only_where`, with a predicate that is False where `state.done`. Everything static
    (configuration, shapes) stays the same from step to step: the driver checks it at trace
    time.
    """

    @abc.abstractmethod
    def init(self, problem, control, a0, simulator, max_steps: int):
        """Initial state (evaluates a0, or marks it as the first step's candidate)."""

    @abc.abstractmethod
    def step(self, problem, control, simulator, state):
        """One step: one candidate integration (see the class docs); returns the new state."""

    @abc.abstractmethod
    def postprocess(self, problem, control, simulator, state) -> Solution:
        """The `Solution` (status MAX_ITERATIONS if the loop ran out of steps)."""

    @abc.abstractmethod
    def progress(self, state) -> dict:
        """Scalars worth printing during a long solve (name -> array)."""

    def check(self, problem, control) -> None:
        """Outside jit, before any work: raise a `ValueError` for a declared part of the
        problem this solver cannot honour with this control (default: none)."""
        del problem, control


def _once(pred, fn, otherwise, operands):
    """`fn(*operands)` if `pred` else `otherwise`: a loop of at most one round. The operands
    pass through an optimization barrier with the loop's predicate: else XLA hoists `fn`'s
    work, invariant in the loop, out of it, and runs it every time."""

    def body(carry):
        pred, args = lax.optimization_barrier((carry[0], operands))
        return jnp.zeros_like(pred), fn(*args)

    return lax.while_loop(lambda carry: carry[0], body, (jnp.asarray(pred), otherwise))[1]


def only_where(pred, fn, otherwise, *operands):
    """`fn(*operands)` where `pred`, else `otherwise` (a tree of `fn`'s output structure and
    dtypes): the data-dependent work of a step (a Hessian, a fallback test) that most steps
    skip.

    In one solve this is `lax.cond`. Under `vmap` (the batch lanes, a user's `jax.vmap` of
    `jt.solve`) a `lax.cond` on a per-lane predicate runs both branches on every lane, so a
    batch would pay the expensive branch every step. Here (a `custom_vmap` rule) `fn` runs,
    vmapped, only in a step where some lane needs it, and the lanes that do not need it run
    it on the inputs of one that does (their results are dropped): a loop inside `fn` (the
    trust region's QP rounds, KalmanSearch's re-tuning) then iterates as long as the lanes
    that need it, not as long as the worst lane on its own stale data (issue 21). `fn` may
    close over per-lane values: they are hoisted into inputs (`eqx.filter_closure_convert`),
    since a `custom_vmap` function may not close over batched ones."""
    closed = eqx.filter_closure_convert(fn, *operands)
    dynamic, static = eqx.partition(closed, eqx.is_array)

    @jax.custom_batching.custom_vmap
    def call(pred, dynamic, otherwise, operands):
        return _once(pred, eqx.combine(dynamic, static), otherwise, operands)

    @call.def_vmap
    def rule(axis_size, in_batched, pred, dynamic, otherwise, operands):
        args = (pred, dynamic, otherwise, operands)
        pred, dynamic, otherwise, operands = jax.tree.map(
            lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))), args, tuple(in_batched)
        )
        per_lane = lambda mask, x: mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        donor = jnp.argmax(pred)  # a lane that needs fn (any, when none does: then fn does not run)
        inputs = jax.tree.map(lambda x: jnp.where(per_lane(pred, x), x, x[donor]), (dynamic, operands))
        vmapped = jax.vmap(lambda d, ops: eqx.combine(d, static)(*ops))
        out = _once(jnp.any(pred), vmapped, otherwise, inputs)
        out = jax.tree.map(lambda n, o: jnp.where(per_lane(pred, n), n, o), out, otherwise)
        return out, jax.tree.map(lambda _: True, out)

    return call(jnp.asarray(pred), dynamic, otherwise, operands)


def _print_progress(step, values):
    parts = [f"step {int(step):5d}"] + [f"{k} {float(v):.6g}" for k, v in values.items()]
    print("  " + "  ".join(parts), flush=True)


#: Progress values of the current point: NaN while there is none (a start that ended
#: NONFINITE before an accepted step printed its placeholder's zeros).
_POINT_VALUES = ("objective", "max|E|", "max C", "L_A")


def _progress_values(solver, state):
    values = solver.progress(state)
    status, iterations = getattr(state, "status", None), getattr(state, "num_iterations", None)
    if status is None or iterations is None:
        return values
    blank = without_point(status, iterations)
    return {k: jnp.where(blank, jnp.nan, v) if k in _POINT_VALUES else v for k, v in values.items()}


def init_state(solver, problem, control, a0, simulator, max_steps, history=True):
    """The solver's initial state; with `history=False` its `History` has length 0 (not
    recorded: under `vmap` the per-step record of a long history costs more than a step)."""
    state = solver.init(problem, control, a0, simulator, max_steps)
    return state if history else eqx.tree_at(lambda s: s.history, state, History.empty(0, tuple(state.history.details)))


def run_loop(solver, problem, control, a0, simulator, max_steps, progress_every=0, history=True):
    """The solver's final state: `init`, then `step` until `done` or `max_steps` steps."""
    state = init_state(solver, problem, control, a0, simulator, max_steps, history)
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
                # (and the last step: done, or `max_steps` reached, where the line was missing)
                (new.num_steps % progress_every == 0) | new.done | (new.num_steps >= max_steps),
                lambda: jax.debug.callback(_print_progress, new.num_steps, _progress_values(solver, new)),
                lambda: None,
            )
        return new_dyn

    return eqx.combine(lax.while_loop(cond, body, dynamic), static)


@eqx.filter_jit
def run(solver, problem, control, a0, simulator, max_steps, progress_every=0):
    state = run_loop(solver, problem, control, a0, simulator, max_steps, progress_every)
    return solver.postprocess(problem, control, simulator, state)


#: Bytes of one History entry (4 float64 fields and a bool), a lower bound on the memory a
#: solve's `max_steps` takes (solvers add up to 2 float64 details).
HISTORY_BYTES = 33


def check_max_steps(max_steps):
    """`max_steps` as a Python int (NumPy integers accepted), or a ValueError naming it."""
    if isinstance(max_steps, np.integer):
        max_steps = int(max_steps)
    if isinstance(max_steps, bool) or not (isinstance(max_steps, int) and max_steps >= 1):
        raise ValueError(f"`max_steps` must be an int >= 1; got {max_steps!r}.")
    return max_steps


def check_step_counter(max_steps):
    """A ValueError naming `max_steps` where it passes the int32 step counter (`SolverState.
    num_steps`): 2**31 wrapped to a negative limit, and a batch without history (whose memory
    check is not made) ended every start MAX_ITERATIONS after 0 steps. After the memory check,
    whose message says more where the history is kept."""
    if max_steps >= 2**31:
        raise ValueError(f"`max_steps` must be < 2**31 (the solvers count steps in int32); got {max_steps:,}.")
