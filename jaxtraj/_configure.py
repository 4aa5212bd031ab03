"""`jt.configure_cpu`: the XLA:CPU options and CPU device split jaxtraj is tuned for, asked for
explicitly (importing jaxtraj changes nothing global but float64)."""

import importlib.metadata
import os
import re

import jax


def configure_cpu(devices: int | None = None, *, xla_options: bool = True) -> int | None:
    """Set up JAX's CPU backend the way jaxtraj's benchmarks run: one CPU device per core
    and two XLA:CPU options. Call it once, right after the imports and before the first
    JAX computation of the process (XLA reads both when its backends start); later it
    raises `RuntimeError`, unless an earlier call already set things up so (then it does
    nothing, so that a script that calls it can run inside a program that did). The
    `jaxtraj` command line, the tests, the examples and the benchmark scripts call it.

    **Arguments:**

    - `devices`: the number of CPU devices. `None`: one per core available to the process
      (`JAXTRAJ_CPU_DEVICES=N` in the environment overrides), unless the user already chose
      (`JAX_NUM_CPU_DEVICES`, `jax.config.update("jax_num_cpu_devices", N)`,
      `--xla_force_host_platform_device_count` in `XLA_FLAGS`, an initialized
      `jax.distributed`), and not with jaxlib >= 0.11 (see below).
    - `xla_options`: append the XLA:CPU options below to `XLA_FLAGS` (an option the user
      set stays theirs; `JAXTRAJ_NO_XLA_TUNING=1` in the environment turns this off).

    **Returns:** the CPU device count it asked JAX for, or `None` where it left the count.

    Why (measurements in benchmarks/RESULTS.md):

    * One device per core: XLA runs one CPU device on about one core, so `jt.solve_batch`
      and `jt.multistart`, which shard a batch over the devices, use every core (2.2x the
      loop of single solves with two devices on two cores against 1.3x with one). Single
      computations run on the first device as before. Not by default with jaxlib >= 0.11:
      with jax 0.11.2 KalmanSQP's batch program sharded over several CPU devices crashed the
      process (2026-12-04), so there `devices` must be given.
    * `xla_cpu_small_while_loop_byte_threshold`: a while loop runs as one compiled function
      only when its loop state is "small"; the state of a forward-mode Jacobian through RK4
      (states x parameters) is just above XLA's default, which made simulation + Jacobian
      20x the simulation alone; raised, ~8x.
    * `--xla_cpu_use_fusion_emitters=false` (jaxlib 0.5.3 to 0.10 only: XLA aborts on a flag
      it does not know, and retired it in 2026-09): the legacy emitters compile a solver in
      0.63-0.93x the time, same results.
    """
    if devices is not None and (isinstance(devices, bool) or not isinstance(devices, int) or devices < 1):
        raise ValueError(f"configure_cpu: devices must be a positive int or None, got {devices!r}")
    tune = xla_options and not os.environ.get("JAXTRAJ_NO_XLA_TUNING")
    count = devices if devices is not None else _default_device_count()
    chosen = jax.config.jax_num_cpu_devices  # pyright: ignore[reportAttributeAccessIssue]  (JAX config options are dynamic attributes)
    try:  # the public way to ask whether JAX's backends have started: a change is refused then
        jax.config.update("jax_num_cpu_devices", chosen + 1)
        jax.config.update("jax_num_cpu_devices", chosen)
    except RuntimeError:
        if (count is None or count == len(jax.devices("cpu"))) and not (tune and _missing_xla_cpu_options()):
            return count  # already set up so (a second call): nothing to do
        raise RuntimeError(
            "jt.configure_cpu() must run before the first JAX computation of the process "
            "(JAX has started its backends, which fixes XLA's options and the CPU device "
            "count): call it right after the imports"
        ) from None
    if tune:
        os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_missing_xla_cpu_options()]).strip()
    if count is not None:
        jax.config.update("jax_num_cpu_devices", count)
    return count


def configure_cpu_if_possible() -> None:
    """`configure_cpu()` where JAX has not computed yet (the command line, which may also
    be called from a program that has)."""
    try:
        configure_cpu()
    except RuntimeError:
        pass


_hinted = False


def unused_cores_hint(devices) -> str | None:
    """A line for `solve_batch`'s progress output, once per process, when its batch runs on
    one CPU device of a host with several cores that `configure_cpu()` would have split
    (None otherwise)."""
    global _hinted
    if _hinted or len(devices) != 1 or devices[0].platform != "cpu":
        return None
    cores = _default_device_count()
    if cores is None or cores < 2 or len(jax.devices("cpu")) > 1:
        return None
    _hinted = True
    return (
        f"solve_batch: one CPU device on {cores} cores: `jt.configure_cpu()` right after the "
        "imports shards batches over every core"
    )


def _missing_xla_cpu_options():
    """The options of `configure_cpu` that XLA_FLAGS lacks (the user's own values stay)."""
    flags = os.environ.get("XLA_FLAGS", "")
    missing = []
    if "--xla_backend_extra_options" not in flags:
        missing.append("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000")
    if "--xla_cpu_use_fusion_emitters" not in flags and _jaxlib_at_least((0, 5, 3)) and not _jaxlib_at_least((0, 11)):
        missing.append("--xla_cpu_use_fusion_emitters=false")
    return missing


def _default_device_count():
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return None
    # set by the user (config or JAX_NUM_CPU_DEVICES)
    if jax.config.jax_num_cpu_devices != -1:  # pyright: ignore[reportAttributeAccessIssue]  (JAX config options are dynamic attributes)
        return None
    if getattr(jax.distributed, "is_initialized", lambda: False)():  # a multi-host setup of its own
        return None
    try:
        count = int(os.environ.get("JAXTRAJ_CPU_DEVICES", "0"))
    except ValueError:
        count = 0
    if count >= 1:
        return count
    if _jaxlib_at_least((0, 11)):
        return None
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _jaxlib_at_least(version):
    """Whether the installed jaxlib is at least `version`, from its package metadata."""
    try:
        release = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return False
    return tuple(int(x) for x in re.findall(r"\d+", release)[:3]) >= tuple(version)
