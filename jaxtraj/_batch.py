"""Batched solves at scale: `solve_batch` (vmap + device sharding + chunks + resumable
result folders) and `multistart` (random starts around a vector, solved as one batch, with
a summary of the local optima found).

How a batch runs:

* One compiled program solves one *chunk* of starts. `jax.shard_map` over a 1-D mesh of
  devices gives every device its own slice of the chunk and its own loops (no cross-device
  traffic while iterating). Every chunk is padded to the same size (a multiple of the
  device count), so all chunks share one compilation; padding rows are NaN starts, which
  end at their first evaluation, and are stripped from the result.
* On a device the slice runs on `lanes` vmapped lanes fed from a queue (`_solve_queue`):
  each iteration is one vmapped solver `step` on every lane, and when a few lanes have
  finished they hand their solutions over and take the next starts, so no lane idles while
  starts are left (a vmapped group of whole solves would iterate until its slowest start is
  done: 40-72 % useful work on Earth-Mars). `lanes=1` is a compiled loop of single solves.
* Under `vmap` a start's iterations only touch its own lane, so a start that diverges (NaN,
  step limit) comes back with its failure `status` and leaves every other result unchanged.
  Every lane does the work of every step, though: a `lax.cond` on a per-start predicate runs
  both branches. On CPU, XLA's vmapped kernels gain too little over single ones for that
  (benchmarks/batch.py: lanes=8 or 32 give 0.75-1.46x the loop, lanes=1 1.22-1.39x), so the
  default there is `lanes=1`; on accelerators it is the whole per-device slice.
* With `out=FOLDER` each finished chunk is written atomically (`chunk_00000.npz`, ...) next
  to `manifest.json` (number of starts, chunk size, and SHA-256 fingerprints of `a0s` and of
  the problem / control / solver / simulator / `max_steps`). `resume=True` loads the chunks
  already on disk and solves only the rest; a resume with different inputs is refused. Chunk
  files hold the exact float64 arrays, so a resumed run returns exactly what an
  uninterrupted one does on the same devices (another device count or `lanes` can change
  results by round-off only). To read a finished folder back, call `solve_batch` again
  with the same inputs and `resume=True`: nothing is recomputed.
* CPU cores: XLA runs one CPU device on (mostly) one core. To use several cores, split the
  host into devices before JAX starts computing: `jax.config.update("jax_num_cpu_devices",
  os.cpu_count())` right after the imports (`import jaxtraj` runs no JAX computation), or
  `XLA_FLAGS=--xla_force_host_platform_device_count=<cores>`; `solve_batch` then shards over
  all of them (the CLI does this for `--starts`).

Several hosts (multi-host is the scaling path; there is no cluster code here). Start the same
script on every host with the same inputs and call `jax.distributed.initialize` first; the
mesh then spans the devices of all hosts, each host feeds and runs its own devices' slices of
every chunk, and the solutions are all-gathered so every process returns the whole batch.
Only process 0 prints progress and writes `out`; for `resume` the folder must be on a file
system every host can read::

    import jax
    jax.distributed.initialize()  # on a cluster manager (SLURM, ...) the arguments are found;
    # otherwise: jax.distributed.initialize("host0:1234", num_processes=H, process_id=i)
    # CPU-only hosts also need: jax.config.update("jax_cpu_collectives_implementation", "gloo")
    import jaxtraj as jt

    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    a0s = ...  # the same (N, num_params) array on every host (e.g. from the same PRNG key)
    sols = jt.solve_batch(prob, ctrl, a0s, chunk_size=4096, out="/shared/run1", resume=True)

`jax.devices()` lists every host's devices after `initialize`; pass `devices=` to use a
subset. Each host should see the same number of local devices (on CPU hosts, set
`XLA_FLAGS=--xla_force_host_platform_device_count=<cores>` to split each host into one device
per core). An independent alternative needing no coordination: give each host a disjoint
slice of `a0s` and its own `out` folder. (The recipe is exercised with two processes on one
machine by `tests/test_batch.py::test_two_hosts_with_jax_distributed`, marked slow.)
"""

import dataclasses
import hashlib
import json
import os
import re
import sys
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from . import io as _io
from ._checks import check_problem_and_control
from ._driver import AbstractSolver, init_state, run, run_loop
from ._simulate import RK4, AbstractSimulator, check_simulator
from ._solution import Solution
from ._solve import check_solver
from ._status import STATUS_NAMES, Status
from .controls import AbstractControl, value_bounds

_AXIS = "starts"
_FORMAT = "jaxtraj-batch-1"


# ---------------------------------------------------------------------- compiled chunk


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
        new = step(state)
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
def _solve_chunk(solver, problem, control, a0s, simulator, max_steps, mesh, keep_history, lanes):
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

    return jax.shard_map(local, mesh=mesh, in_specs=(P(), P(_AXIS)), out_specs=P(_AXIS), check_vma=False)(params, a0s)


def _template(solver, problem, control, num_params, simulator, max_steps, keep_history):
    """Tree structure and per-start leaf shapes/dtypes of one start's `Solution`."""
    a = jax.ShapeDtypeStruct((num_params,), jnp.float64)
    shape = eqx.filter_eval_shape(run, solver, problem, control, a, simulator, max_steps)
    if not keep_history:
        shape = eqx.tree_at(
            lambda s: s.history, shape, jax.tree.map(lambda x: jax.ShapeDtypeStruct((0,), x.dtype), shape.history)
        )
    leaves, treedef = jax.tree.flatten(shape)
    return treedef, [(tuple(x.shape), np.dtype(x.dtype)) for x in leaves]


def _to_global(rows: np.ndarray, mesh: Mesh):
    """A host array as one global array sharded over `mesh` (every process passes the same rows)."""
    sharding = NamedSharding(mesh, P(_AXIS))
    return jax.make_array_from_callback(rows.shape, sharding, lambda index: rows[index])


def _to_host(tree):
    """Every leaf as a full numpy array on this host (all-gathered across processes)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))]


# ---------------------------------------------------------------------- fingerprints and files


def _fingerprint(tree) -> str:
    """SHA-256 of a pytree's structure and leaves that is stable across processes: array
    leaves by dtype, shape and bytes; functions by module and qualified name; others by repr
    (memory addresses removed)."""
    leaves, treedef = jax.tree.flatten(tree)
    h = hashlib.sha256(re.sub(r" at 0x[0-9a-fA-F]+", "", str(treedef)).encode())
    for leaf in leaves:
        if isinstance(leaf, (np.ndarray, jax.Array, np.generic)):
            arr = np.ascontiguousarray(np.asarray(leaf))
            h.update(f"array {arr.dtype} {arr.shape}".encode() + arr.tobytes())
        elif callable(leaf) and hasattr(leaf, "__qualname__"):
            h.update(f"callable {getattr(leaf, '__module__', '?')}.{leaf.__qualname__}".encode())
        else:
            h.update(re.sub(r" at 0x[0-9a-fA-F]+", "", repr(leaf)).encode())
    return h.hexdigest()


def _chunk_path(out, k):
    return os.path.join(out, f"chunk_{k:05d}.npz")


def _write_chunk(out, k, leaves):
    arrays = {f"leaf_{i:03d}": x for i, x in enumerate(leaves)}
    _io.atomic_write(_chunk_path(out, k), lambda f: np.savez(f, **arrays))


def _read_chunk(out, k, rows, spec):
    path = _chunk_path(out, k)
    with np.load(path) as data:
        leaves = [data[f"leaf_{i:03d}"] for i in range(len(spec))] if len(data.files) == len(spec) else None
    if leaves is None or any(x.shape != (rows, *s) or x.dtype != d for x, (s, d) in zip(leaves, spec)):
        raise ValueError(
            f"`out`: {path} does not hold {rows} solutions of this batch's layout; delete it to recompute it."
        )
    return leaves


def _prepare_out(out, manifest, resume, writer):
    """Create `out` and its manifest (process 0), or check an existing manifest against
    this run's."""
    path = os.path.join(out, "manifest.json")
    if os.path.exists(path):
        if not resume:
            if writer:  # (other processes may see the manifest process 0 just wrote)
                raise ValueError(
                    f"`out`: {out!r} already holds a batch run (manifest.json); pass resume=True to "
                    "continue it, or choose another folder."
                )
            return
        with open(path) as f:
            old = json.load(f)
        diff = [k for k in manifest if k != "description" and old.get(k) != manifest[k]]
        if diff:
            details = "; ".join(f"{k}: on disk {old.get(k)!r}, now {manifest[k]!r}" for k in diff)
            raise ValueError(
                f"`resume`: the run in {out!r} was started with different inputs ({details}). "
                "Use the same a0s, problem, control, solver, simulator, max_steps, chunk_size and "
                "history, or another `out` folder."
            )
        return
    if not writer:
        return
    os.makedirs(out, exist_ok=True)
    text = json.dumps(manifest, indent=2).encode()
    _io.atomic_write(path, lambda f: f.write(text))


# ---------------------------------------------------------------------- solve_batch


def _check_devices(devices):
    if devices is None:
        return list(jax.devices())
    devices = list(devices) if isinstance(devices, Sequence) else None
    if not devices or not all(isinstance(d, jax.Device) for d in devices):
        raise ValueError("`devices` must be None or a non-empty sequence of jax devices (e.g. jax.devices()[:2]).")
    if len(set(devices)) != len(devices):
        raise ValueError("`devices` must not repeat a device.")
    return devices


def _check_int(name, value, minimum):
    if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= minimum):
        raise ValueError(f"`{name}` must be an int >= {minimum}; got {value!r}.")
    return int(value)


def _check_a0s(control, a0s):
    if isinstance(a0s, jax.core.Tracer):
        raise ValueError("`a0s` must be concrete: solve_batch runs outside jit (inside jit, vmap jt.solve).")
    arr = np.asarray(a0s)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"`a0s` must be a real numeric array; got dtype {arr.dtype}.")
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] != control.num_params:
        raise ValueError(
            f"`a0s` must have shape (N, {control.num_params}) with N >= 1 for {control!r}; got {arr.shape}."
        )
    return np.ascontiguousarray(arr, dtype=np.float64)


def solve_batch(
    problem,
    control: AbstractControl,
    a0s,
    solver: AbstractSolver | None = None,
    *,
    simulator: AbstractSimulator = RK4(),
    max_steps: int = 5000,
    chunk_size: int | None = None,
    devices=None,
    out: str | os.PathLike | None = None,
    resume: bool = False,
    progress: bool = True,
    history: bool = True,
    lanes: int | None = None,
) -> Solution:
    """`jt.solve` for every row of `a0s`, vmapped, sharded over devices and run in chunks.

    **Arguments:**

    - `problem`, `control`, `solver`, `simulator`, `max_steps`: as for `jt.solve`.
    - `a0s`: starting vectors, shape `(N, control.num_params)`. Rows are not value-checked:
      a NaN start or one with its times out of order comes back as that start's failure
      status without affecting the others.
    - `chunk_size`: starts per compiled call, per progress line and per file (bounds
      memory; default `min(N, 1024)`). Every chunk is padded to the same size, so all
      share one compilation.
    - `devices`: the devices to shard each chunk over (default `jax.devices()`).
    - `out`: a folder; every finished chunk is written there atomically, with a manifest.
    - `resume`: load the chunks already in `out` instead of solving them again. The inputs
      must be those of the run that wrote `out` (checked by fingerprint).
    - `progress`: print one line per finished chunk to stderr (starts done / total, elapsed
      time, solves per second, successes so far).
    - `history`: keep the per-step `History` (`(N, max_steps)` per field). With `False` the
      history fields have shape `(N, 0)`; use it for large N, where the history dominates
      memory and disk.
    - `lanes`: starts vmapped together on a device (default: 1 on CPU, the device's whole
      slice of the chunk elsewhere); see the module notes.

    **Returns:** a `jt.Solution` whose fields have a leading N axis: per start, what
    `jt.solve` returns, within the solver's stated tolerance. Not bitwise: vmapped lanes
    (`lanes > 1`, `jax.vmap`) are compiled as another program, with other round-off; with
    `lanes=1` each start runs the single-solve step, and the results have matched
    `jt.solve`'s to 1e-12 in the tests, but XLA does not promise it.

    **Raises:** `ValueError` for bad arguments (outside jit), or when `out` holds a run with
    other inputs (`resume=True`) or any run (`resume=False`).
    """
    solver = check_solver(solver, max_steps)
    check_problem_and_control(problem, control)
    check_simulator(simulator)
    a0s = _check_a0s(control, a0s)
    n = a0s.shape[0]
    chunk = min(n, 1024) if chunk_size is None else _check_int("chunk_size", chunk_size, 1)
    chunk = min(chunk, n)
    devices = _check_devices(devices)
    per_device = -(-chunk // len(devices))
    if lanes is None:
        lanes = 1 if devices[0].platform == "cpu" else per_device
    lanes = min(_check_int("lanes", lanes, 1), per_device)
    for name, flag in (("resume", resume), ("progress", progress), ("history", history)):
        if not isinstance(flag, bool):
            raise ValueError(f"`{name}` must be True or False; got {flag!r}.")
    if resume and out is None:
        raise ValueError("`resume=True` needs `out`, the folder of the run to resume.")
    keep_history = history

    num_chunks = -(-n // chunk)
    padded = -(-chunk // len(devices)) * len(devices)  # rows per compiled call
    mesh = Mesh(np.array(devices), (_AXIS,))
    writer = jax.process_index() == 0
    if out is not None:
        out = os.fspath(out)
        manifest = {
            "format": _FORMAT,
            "num_starts": n,
            "chunk_size": chunk,
            "num_chunks": num_chunks,
            "history": keep_history,
            "a0s_sha256": _fingerprint(a0s),
            "inputs_sha256": _fingerprint((problem, control, solver, simulator, max_steps)),
            "description": f"{getattr(problem, 'name', 'problem')}, {control!r}, {solver!r}, {simulator!r}, "
            f"max_steps={max_steps}",
        }
        _prepare_out(out, manifest, resume, writer)

    on_disk = {k for k in range(num_chunks) if resume and os.path.exists(_chunk_path(out, k))}
    # the layout of one start's Solution: traced only if a chunk must be read (else taken
    # from the first solved chunk)
    treedef, spec = (
        _template(solver, problem, control, control.num_params, simulator, max_steps, keep_history)
        if on_disk
        else (None, None)
    )
    show = progress and writer
    if show and on_disk:
        print(
            f"solve_batch: resuming {out}: {len(on_disk)}/{num_chunks} chunk(s) already done, loading them",
            file=sys.stderr,
            flush=True,
        )
    results = None
    success = solved = 0
    t_start = time.perf_counter()
    for k in range(num_chunks):
        lo, hi = k * chunk, min((k + 1) * chunk, n)
        if k in on_disk:
            leaves = _read_chunk(out, k, hi - lo, spec)
        else:
            rows = np.full((padded, control.num_params), np.nan)  # NaN padding ends at once
            rows[: hi - lo] = a0s[lo:hi]
            sols = _solve_chunk(
                solver, problem, control, _to_global(rows, mesh), simulator, max_steps, mesh, keep_history, lanes
            )
            leaves = [x[: hi - lo] for x in _to_host(sols)]
            treedef = jax.tree.structure(sols)
            if out is not None and writer:
                _write_chunk(out, k, leaves)
            solved += hi - lo
        if results is None:
            results = [np.empty((n, *x.shape[1:]), x.dtype) for x in leaves]
        for dst, src in zip(results, leaves):
            dst[lo:hi] = src
        success += int(np.sum(np.asarray(jax.tree.unflatten(treedef, leaves).status == Status.SUCCESS)))
        if show and k not in on_disk:
            elapsed = time.perf_counter() - t_start
            print(
                f"solve_batch: {hi}/{n} starts (chunk {k + 1}/{num_chunks}) | {elapsed:.1f} s | "
                f"{solved / elapsed:.1f} solves/s | success {success}/{hi}",
                file=sys.stderr,
                flush=True,
            )
    results.reverse()  # convert leaf by leaf, freeing each host copy (peak: one leaf twice)
    return jax.tree.unflatten(treedef, [jnp.asarray(results.pop()) for _ in range(len(results))])


# ---------------------------------------------------------------------- multistart


@eqx.filter_jit
def _draws(control, around, key, n):
    """Knots of `around`, their Jacobian, and the normal draws of `random_starts` (one
    compiled call instead of many small eager ones)."""
    k_dur, k_val = jax.random.split(key)
    z = jax.random.normal(k_dur, (n, control.num_segments), jnp.float64)
    noise = jax.random.normal(k_val, (n, control.num_params), jnp.float64)
    return control.knots(around), jax.jacfwd(control.knots)(around), z, noise


@eqx.filter_jit
def _all_knots(control, a):
    return jax.vmap(control.knots)(a)


def random_starts(problem, control: AbstractControl, key, n: int, around, spread=0.1):
    """`n` reproducible random starting vectors around `around`, valid for `control`.

    - Segment durations (knot gaps) are multiplied by independent factors exp(spread z), and
      the time parameters are solved back from the new knots (exact for node-time and
      duration layouts; a least-squares fit of tf when only tf is free). Times therefore stay
      increasing and tf > 0 by construction.
    - Every other entry gets additive noise spread * s * z, with s the RMS of those entries
      of `around` (1 if they are all zero); `spread` may also be an array `(num_params,)`.
    - Control values (the family's `value_indices`) are clipped to the bounds of the problem
      (`control_lower/upper`) and the family's own `limits`.
    """
    around = jnp.asarray(control.validate(around))
    n = _check_int("n", n, 1)
    typed = isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key) and key.shape == ()
    raw = isinstance(key, (jax.Array, np.ndarray)) and key.dtype == np.uint32 and key.shape == (2,)
    if not (typed or raw):
        raise ValueError(f"`key` must be a JAX PRNG key (jax.random.key(seed)); got {key!r}.")
    spread = np.broadcast_to(np.asarray(spread, dtype=np.float64), (control.num_params,))
    if not np.all(np.isfinite(spread) & (spread >= 0)):
        raise ValueError(f"`spread` must be >= 0 and finite; got {spread}.")
    t_idx = np.asarray(control.time_indices, int)
    other = np.setdiff1d(np.arange(control.num_params), t_idx)
    knots, jac, z, noise = (np.asarray(x) for x in _draws(control, around, key, n))
    # times: perturb the knot gaps multiplicatively, solve the time parameters back
    gaps = np.diff(knots)
    jac = jac[:, t_idx]  # knots are linear in the time parameters
    t_spread = float(np.mean(spread[t_idx])) if t_idx.size else 0.0
    new_knots = np.concatenate([np.zeros((n, 1)), np.cumsum(gaps * np.exp(t_spread * z), axis=1)], axis=1)
    times = np.linalg.lstsq(jac, new_knots.T, rcond=None)[0].T
    # other entries: additive noise on their own scale, then the bounds
    vals = np.asarray(around)[other]
    scale = float(np.sqrt(np.mean(vals**2))) if vals.size and np.any(vals != 0) else 1.0
    starts = np.asarray(around)[None, :] + spread * scale * noise
    starts[:, t_idx] = times
    idx, lo, hi = value_bounds(control, problem.control_lower, problem.control_upper)
    starts[:, idx] = np.clip(starts[:, idx], np.asarray(lo), np.asarray(hi))
    # check the promise (vectorized version of control.validate's ordering checks)
    kn = np.asarray(_all_knots(control, jnp.asarray(starts)))
    if not (np.all(np.isfinite(starts)) and np.all(np.diff(kn, axis=1) > 0) and np.all(kn[:, -1] > 0)):
        raise ValueError("`around`/`spread`: could not generate valid starts (knots not increasing); lower `spread`.")
    return jnp.asarray(starts)


@dataclasses.dataclass(frozen=True)
class MultistartResult:
    """Outcome of `jt.multistart`.

    - `starts`: `(n, num_params)` starting vectors; `solutions`: the batch `Solution`.
    - `success`: bool `(n,)`; `success_rate`: their mean.
    - `best_index`: the successful start with the lowest objective (-1 if none); `best`:
      its `Solution` (unbatched) or None.
    - `optima`: distinct local optima among the successful starts, best first, as
      `(objective, count, index of its best start)`; objectives closer than
      `tol (1 + |G|)` (chained) are one optimum.
    - `wall_time`: seconds for the whole call (including compilation); `solves_per_second`.
    """

    starts: jax.Array
    solutions: Solution
    success: np.ndarray
    best_index: int
    optima: tuple
    tol: float
    wall_time: float

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.success))

    @property
    def solves_per_second(self) -> float:
        return len(self.success) / self.wall_time

    @property
    def best(self) -> Solution | None:
        if self.best_index < 0:
            return None
        return jax.tree.map(lambda x: x[self.best_index], self.solutions)

    def summary(self) -> str:
        """A readable report: counts, timing, status breakdown and the table of optima."""
        n = len(self.success)
        sols = self.solutions
        lines = [
            f"multistart: {n} starts, {int(self.success.sum())} SUCCESS ({self.success_rate:.1%}), "
            f"{self.wall_time:.2f} s ({self.solves_per_second:.1f} solves/s, compilation included)",
        ]
        counts = {name: int(np.sum(np.asarray(sols.status == getattr(Status, name)))) for name in STATUS_NAMES}
        lines.append("status: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v))
        if self.best_index >= 0:
            b = self.best
            lines.append(
                f"best: start {self.best_index}, objective {float(b.objective):.10g}, "
                f"max|E| {float(b.max_constraint_error):.2e}, {int(b.iterations)} iterations"
            )
            lines.append("")
            lines.append(f"| optimum | objective (tol {self.tol:g}) | starts | share of successes | best start |")
            lines.append("|---:|---:|---:|---:|---:|")
            ns = max(int(self.success.sum()), 1)
            for i, (g, c, j) in enumerate(self.optima):
                lines.append(f"| {i + 1} | {g:.10g} | {c} | {c / ns:.1%} | {j} |")
        return "\n".join(lines)

    def __str__(self):
        return self.summary()


def _cluster(values, indices, tol):
    """Sort and chain objectives within tol (1 + |G|) of their neighbour: `(best, count, index)`."""
    order = np.argsort(values, kind="stable")
    groups = []
    for j in order:
        g = values[j]
        if groups and g - groups[-1][3] <= tol * (1.0 + abs(g)):
            groups[-1][1] += 1
            groups[-1][3] = g
        else:
            groups.append([g, 1, int(indices[j]), g])  # best value, count, best index, last value
    return tuple((float(g), c, i) for g, c, i, _ in groups)


def multistart(
    problem,
    control: AbstractControl,
    key,
    n: int,
    *,
    around=None,
    spread=0.1,
    solver: AbstractSolver | None = None,
    tol: float = 1e-6,
    **solve_batch_kwargs,
) -> MultistartResult:
    """Solve from `n` random starts around `around` and summarize the optima found.

    **Arguments:**

    - `key`: a JAX PRNG key; the same key gives the same starts (and results).
    - `n`: number of starts.
    - `around`: the centre vector (required), e.g. `control.initial_guess(tf, u0, u1)`.
    - `spread`: relative size of the perturbation (see `jt.random_starts`).
    - `solver`: as for `jt.solve`; `tol`: objectives closer than `tol (1 + |G|)` count as
      one local optimum.
    - other keywords go to `jt.solve_batch` (`chunk_size`, `devices`, `out`, `max_steps`, ...).

    **Returns:** a `MultistartResult`; `print(result)` shows the summary table.
    """
    if around is None:
        raise ValueError(
            "`around` is required: the vector to perturb, e.g. control.initial_guess(tf, u_start, u_end) "
            "or a previous solution's params."
        )
    if not (isinstance(tol, (int, float)) and tol >= 0):
        raise ValueError(f"`tol` must be a number >= 0; got {tol!r}.")
    t0 = time.perf_counter()
    starts = random_starts(problem, control, key, n, around, spread)
    sols = solve_batch(problem, control, starts, solver, **solve_batch_kwargs)
    wall = time.perf_counter() - t0
    ok = np.asarray(sols.status == Status.SUCCESS)
    obj = np.asarray(sols.objective)
    idx = np.flatnonzero(ok)
    best = int(idx[np.argmin(obj[idx])]) if idx.size else -1
    optima = _cluster(obj[idx], idx, float(tol)) if idx.size else ()
    return MultistartResult(starts, sols, ok, best, optima, float(tol), wall)


__all__ = ["MultistartResult", "multistart", "random_starts", "solve_batch"]
