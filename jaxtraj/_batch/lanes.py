"""The compiled chunk: a device's slice of starts on vmapped lanes fed from a queue, sharded
over a mesh of devices."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from .._driver import init_state, run, run_loop

AXIS = "starts"


def _finished(state, max_steps):
    return state.done | (state.num_steps >= max_steps)


def _select(mask, new, old):
    """Per-lane `where` over a batched tree (mask: one bool per lane)."""
    return jax.tree.map(lambda n, o: jnp.where(mask.reshape(mask.shape + (1,) * (n.ndim - 1)), n, o), new, old)


def _refill_width(lanes):
    """Finished lanes collected before they are refilled at once (see `_solve_queue`)."""
    return max(1, lanes // 8)


def _solve_queue(init1, step1, finish1, a0s, max_steps, lanes):
    """Solve the rows of `a0s` on `lanes` vmapped lanes fed from a queue.

    Every iteration advances each lane's solve by one vmapped `step` (finished lanes are
    masked). When `_refill_width(lanes)` lanes have finished, those lanes' solutions are
    written to the output and the lanes take the next starts from the queue (a real
    `lax.cond`, taken for the whole group: its `init` evaluates only the refilled lanes).
    So the lanes stay busy until the queue runs dry, unlike a vmapped group of solves,
    which iterates until its slowest start is done. Which start runs on which lane depends
    only on the rows and on `lanes`, so a chunk gives the same results every time.
    """
    m = a0s.shape[0]
    r = _refill_width(lanes)
    # the loop carries the array part of the solver states; the rest is static
    shapes = jax.eval_shape(init1, a0s[0])
    _, static = eqx.partition(shapes, lambda x: isinstance(x, jax.ShapeDtypeStruct))
    init = jax.vmap(lambda a: eqx.partition(init1(a), eqx.is_array)[0])
    step = jax.vmap(lambda s: eqx.partition(step1(eqx.combine(s, static)), eqx.is_array)[0])

    def finish_one(s):  # the history records past `steps` (see `body`) cleared first
        s = eqx.combine(s, static)
        return finish1(eqx.tree_at(lambda x: x.history, s, s.history.clear_from(s.num_steps)))

    finish = jax.vmap(finish_one)
    finished = jax.vmap(lambda s: _finished(eqx.combine(s, static), max_steps))

    def write(out, rows, states):
        return jax.tree.map(lambda o, v: o.at[rows].set(v, mode="drop"), out, finish(states))

    def refill(carry):
        state, lane_start, queue, out = carry
        (idx,) = jnp.nonzero(finished(state) & (lane_start < m), size=r, fill_value=lanes)  # first r done
        picked = jax.tree.map(lambda x: x[jnp.minimum(idx, lanes - 1)], state)
        out = write(out, jnp.where(idx < lanes, lane_start[jnp.minimum(idx, lanes - 1)], m), picked)
        rows = queue + jnp.arange(r)
        fresh = init(a0s[jnp.minimum(rows, m - 1)])
        state = jax.tree.map(lambda s, f: s.at[idx].set(f, mode="drop"), state, fresh)
        lane_start = lane_start.at[idx].set(jnp.where(rows < m, rows, m), mode="drop")
        return state, lane_start, queue + r, out

    def running(state, lane_start):
        return ~finished(state) & (lane_start < m)

    def body(carry):
        state, lane_start, queue, out = carry
        # A finished lane (or an idle one) still runs the vmapped step, its result discarded;
        # marked done it asks the step's `only_where` for no work (a lane at `max_steps`
        # is not done by itself).
        new = step(eqx.tree_at(lambda s: s.done, state, ~running(state, lane_start)))
        # Finished lanes keep their state, except the history: selecting it would copy the
        # (lanes, max_steps) buffers every step. Their extra records (at index `steps`) are
        # cleared by `finish`.
        state = eqx.tree_at(lambda s: s.history, _select(running(state, lane_start), new, state), new.history)
        ready = jnp.sum(finished(state) & (lane_start < m)) >= r
        return lax.cond((queue < m) & ready, refill, lambda c: c, (state, lane_start, queue, out))

    state = init(a0s[:lanes])
    out = jax.tree.map(  # row m: where writes of idle lanes go (dropped)
        lambda t: jnp.zeros((m, *t.shape[1:]), t.dtype), jax.eval_shape(finish, state)
    )
    carry = (state, jnp.arange(lanes), jnp.asarray(lanes), out)  # lane_start m: idle lane
    state, lane_start, _, out = lax.while_loop(lambda c: jnp.any(running(*c[:2])), body, carry)
    return write(out, jnp.where(lane_start < m, lane_start, m), state)  # the starts still on a lane


@eqx.filter_jit
def solve_chunk(solver, problem, control, a0s, simulator, max_steps, mesh, keep_history, lanes):
    """The rows of `a0s`, each device of `mesh` taking its slice: one solve after the other
    (`lanes=1`) or on `lanes` vmapped lanes fed from the slice (`_solve_queue`)."""
    params, static = eqx.partition((solver, problem, control, simulator), eqx.is_array)

    def local(params, a0s):
        solver, problem, control, simulator = eqx.combine(params, static)

        def finish(state):
            return solver.postprocess(problem, control, simulator, state)

        if lanes == 1:  # no vmap: the solver's lax.cond stay real branches
            return lax.map(
                lambda a: finish(run_loop(solver, problem, control, a, simulator, max_steps, history=keep_history)), a0s
            )
        return _solve_queue(
            lambda a: init_state(solver, problem, control, a, simulator, max_steps, keep_history),
            lambda s: solver.step(problem, control, simulator, s),
            finish,
            a0s,
            max_steps,
            min(lanes, a0s.shape[0]),
        )

    return jax.shard_map(local, mesh=mesh, in_specs=(P(), P(AXIS)), out_specs=P(AXIS), check_vma=False)(params, a0s)


def template(solver, problem, control, num_params, simulator, max_steps, keep_history):
    """Tree structure and per-start leaf shapes/dtypes of one start's `Solution`."""
    a = jax.ShapeDtypeStruct((num_params,), jnp.float64)
    shape = eqx.filter_eval_shape(run, solver, problem, control, a, simulator, max_steps)
    if not keep_history:
        shape = eqx.tree_at(
            lambda s: s.history, shape, jax.tree.map(lambda x: jax.ShapeDtypeStruct((0,), x.dtype), shape.history)
        )
    leaves, treedef = jax.tree.flatten(shape)
    return treedef, [(tuple(x.shape), np.dtype(x.dtype)) for x in leaves]


def to_global(rows: np.ndarray, mesh: Mesh):
    """A host array as one global array sharded over `mesh` (every process passes the same rows)."""
    sharding = NamedSharding(mesh, P(AXIS))
    return jax.make_array_from_callback(rows.shape, sharding, lambda index: rows[index])


def to_host(tree):
    """Every leaf as a full numpy array on this host (all-gathered across processes)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))]
