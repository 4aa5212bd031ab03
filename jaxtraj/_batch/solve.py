"""`jt.solve_batch`: input checks, chunking, progress lines and resume."""

import contextlib
import os
import sys
import time
from collections.abc import Sequence

import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from .. import io as _io
from .._checks import (
    check_memory,
    check_problem_and_control,
    check_solver_memory,
    follow_final_time,
    memory_refusal,
)
from .._configure import unused_cores_hint
from .._driver import HISTORY_BYTES, AbstractSolver, check_step_counter
from .._fingerprint import fingerprint, problem_fingerprint
from .._implicit import OUTSIDE_JIT, differentiable_batch
from .._kkt import ACTIVE_TOL
from .._simulate import RK4, AbstractSimulator, check_simulator
from .._solution import Solution
from .._solve import check_solver
from .._status import Status
from ..controls import AbstractControl
from .files import FORMAT, chunk_path, prepare_out, read_chunk, run_id, write_chunk
from .lanes import AXIS, solve_chunk, template, to_global, to_host


def _check_devices(devices):
    if devices is None:
        return list(jax.devices())
    devices = list(devices) if isinstance(devices, Sequence) else None
    if not devices or not all(isinstance(d, jax.Device) for d in devices):
        raise ValueError("`devices` must be None or a non-empty sequence of jax devices (e.g. jax.devices()[:2]).")
    if len(set(devices)) != len(devices):
        raise ValueError("`devices` must not repeat a device.")
    return devices


def check_int(name, value, minimum):
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

    **Derivatives.** `jax.grad`, `jax.jvp`, `jax.jacfwd` / `jax.jacrev` (not under `jit` or
    `vmap`: the batch runs on the host) of the result with respect to the float arrays of
    `problem` and `control` are `jt.solve`'s, start by start: the implicit function theorem
    at each start's returned point (`jax.vmap` of the tangent over the starts), NaN for a
    start that did not end SUCCESS; `a0s` has no derivative. See docs/differentiable.md.

    **Raises:** `ValueError` for bad arguments (outside jit), or when `out` holds a run with
    other inputs (`resume=True`) or any run (`resume=False`).
    """
    solver, max_steps = check_solver(solver, max_steps)
    check_problem_and_control(problem, control)
    control = follow_final_time(problem, control, refuse_traced=OUTSIDE_JIT)
    check_simulator(simulator)
    solver.check(problem, control)
    a0s = _check_a0s(control, a0s)
    n = a0s.shape[0]
    chunk = min(n, 1024) if chunk_size is None else check_int("chunk_size", chunk_size, 1)
    chunk = min(chunk, n)
    devices = _check_devices(devices)
    per_device = -(-chunk // len(devices))
    if lanes is None:
        lanes = 1 if devices[0].platform == "cpu" else per_device
    lanes = min(check_int("lanes", lanes, 1), per_device)
    check_solver_memory(control, min(n, lanes * len(devices)))
    for name, flag in (("resume", resume), ("progress", progress), ("history", history)):
        if not isinstance(flag, bool):
            raise ValueError(f"`{name}` must be True or False; got {flag!r}.")
    if resume and out is None:
        raise ValueError("`resume=True` needs `out`, the folder of the run to resume.")
    keep_history = history
    if history:  # the history of every start comes back: n (N, max_steps) arrays
        check_memory("max_steps", n * max_steps * HISTORY_BYTES, f"the history of {n:,} starts x {max_steps:,} steps")
    check_step_counter(max_steps)

    if out is not None and not isinstance(out, str | os.PathLike):  # (os' TypeError named no argument)
        raise ValueError(f"`out` must be None or a folder path (str or os.PathLike); got {type(out).__name__}.")
    out = None if out is None else os.fspath(out)

    def solve_all(problem, control):
        num_chunks = -(-n // chunk)
        padded = -(-chunk // len(devices)) * len(devices)  # rows per compiled call
        mesh = Mesh(np.array(devices), (AXIS,))
        writer = jax.process_index() == 0
        with contextlib.ExitStack() as stack:
            if out is not None:
                manifest = {
                    "format": FORMAT,
                    "num_starts": n,
                    "chunk_size": chunk,
                    "num_chunks": num_chunks,
                    "history": keep_history,
                    "a0s_sha256": fingerprint(a0s),
                    # the problem by what it computes (its jaxpr and data), not by its functions' names
                    "problem_sha256": problem_fingerprint(problem, control, simulator),
                    **{
                        f"{name}_sha256": fingerprint(value)
                        for name, value in (
                            ("control", control),
                            ("solver", solver),
                            ("simulator", simulator),
                        )
                    },
                    "max_steps": max_steps,
                    "description": f"{getattr(problem, 'name', 'problem')}, {control!r}, {solver!r}, {simulator!r}, "
                    f"max_steps={max_steps}",
                }
                if writer:  # one run at a time in `out`: from the manifest check to the last chunk
                    stack.enter_context(_io.folder_lock(out))
                prepare_out(out, manifest, resume, writer)
                run = run_id(manifest)

            on_disk = {k for k in range(num_chunks) if resume and os.path.exists(chunk_path(out, k))}
            # the layout of one start's Solution: traced only if a chunk must be read (else taken
            # from the first solved chunk)
            treedef, spec = (
                template(solver, problem, control, control.num_params, simulator, max_steps, keep_history)
                if on_disk
                else (None, None)
            )
            show = progress and writer
            hint = unused_cores_hint(devices) if show else None
            if hint:
                print(hint, file=sys.stderr, flush=True)
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
                    leaves = read_chunk(out, k, hi - lo, spec, run)
                else:
                    rows = np.full((padded, control.num_params), np.nan)  # NaN padding ends at once
                    rows[: hi - lo] = a0s[lo:hi]
                    with memory_refusal(
                        "jt.solve_batch", "use a smaller chunk_size, fewer RK4 steps or segments, or history=False"
                    ):
                        sols = solve_chunk(
                            solver,
                            problem,
                            control,
                            to_global(rows, mesh),
                            simulator,
                            max_steps,
                            mesh,
                            keep_history,
                            lanes,
                        )
                    leaves = [x[: hi - lo] for x in to_host(sols)]
                    treedef = jax.tree.structure(sols)
                    if out is not None and writer:
                        write_chunk(out, k, leaves, run)
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
            assert results is not None  # (set by the first chunk; `_check_a0s` makes n >= 1)
            results.reverse()  # convert leaf by leaf, freeing each host copy (peak: one leaf twice)
            return jax.tree.unflatten(treedef, [jnp.asarray(results.pop()) for _ in range(len(results))])

    # differentiable in the problem's and control's arrays by the implicit function theorem,
    # per start (`_implicit.differentiable_batch`); `solve_all` itself runs on the host
    active_tol = getattr(solver, "path_active", ACTIVE_TOL)
    return differentiable_batch(solve_all, problem, control, simulator, active_tol)
