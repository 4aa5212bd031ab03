"""Batched solves at scale: `solve_batch` (vmap + device sharding + chunks + resumable
result folders) and `multistart` (random starts around a vector, solved as one batch, with
a summary of the local optima found).

How a batch runs:

* One compiled program solves one *chunk* of starts. `jax.shard_map` over a 1-D mesh of
  devices gives every device its own slice of the chunk and its own loops (no cross-device
  traffic while iterating). Every chunk is padded to the same size (a multiple of the
  device count), so all chunks share one compilation; padding rows are NaN starts, which
  end at their first evaluation, and are stripped from the result.
* On a device the slice runs on `lanes` vmapped lanes fed from a queue (`lanes.py`):
  each iteration is one vmapped solver `step` on every lane, and when a few lanes have
  finished they hand their solutions over and take the next starts, so no lane idles while
  starts are left (a vmapped group of whole solves would iterate until its slowest start is
  done). `lanes=1` is a compiled loop of single solves.
* Under `vmap` a start's iterations only touch its own lane, so a start that diverges (NaN,
  step limit) comes back with its failure `status` and leaves every other result unchanged.
  Every lane does the work of every step, though: a `lax.cond` on a per-start predicate runs
  both branches. On CPU, XLA's vmapped kernels gain too little over single ones for that
  (benchmarks/RESULTS.md, `benchmarks/batch.py`), so the default there is `lanes=1`; on accelerators it is the whole per-device slice.
* With `out=FOLDER` each finished chunk is written atomically (`chunk_00000.npz`, ...) next
  to `manifest.json` (number of starts, chunk size, and SHA-256 fingerprints of `a0s`, of
  what the problem computes (the jaxpr of its functions and the arrays they close over: a
  changed function body is seen, a renamed one is not), and of the control / solver /
  simulator / `max_steps`). `resume=True` loads the chunks
  already on disk and solves only the rest; a resume with different inputs is refused. Chunk
  files hold the exact float64 arrays, so a resumed run returns exactly what an
  uninterrupted one does on the same devices (another device count or `lanes` can change
  results by round-off only). To read a finished folder back, call `solve_batch` again
  with the same inputs and `resume=True`: nothing is recomputed.
* CPU cores: XLA runs one CPU device on (mostly) one core, and `solve_batch` shards over
  the devices JAX has: `jt.configure_cpu()`, called right after the imports, splits the
  host into one device per core (or `JAX_NUM_CPU_DEVICES`, `jax.config.update(
  "jax_num_cpu_devices", N)`, `XLA_FLAGS=--xla_force_host_platform_device_count=N`). Without
  it, the first `solve_batch` that runs on one device of several cores says so.

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

from .solve import solve_batch as solve_batch
from .starts import (
    MultistartResult as MultistartResult,
    multistart as multistart,
    random_starts as random_starts,
)
