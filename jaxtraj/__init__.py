"""jaxtraj: trajectory optimization by control restriction in JAX.

Importing jaxtraj turns on JAX's float64 mode (`jax_enable_x64`): every result of this
package is float64. The public entry points refuse to run if it is turned off afterwards.
"""

import os as _os


def _xla_cpu_options():
    """XLA:CPU options jaxtraj sets at import, appended to XLA_FLAGS (read when the CPU
    backend starts: only effective if jaxtraj is imported before the first JAX computation).
    JAXTRAJ_NO_XLA_TUNING=1 sets none; an option the user already set is left as it is.

    * A while loop runs as one compiled function only when its loop state is "small"
      (xla_cpu_small_while_loop_byte_threshold); larger loops execute kernel by kernel with
      a per-kernel dispatch cost. The loop state of a forward-mode Jacobian through RK4
      (states x parameters) is just above the default, which made simulation + Jacobian
      20x the simulation alone; with the threshold raised it is ~8x.
    * The legacy loop emitters (`--xla_cpu_use_fusion_emitters=false`) compile a solver in
      0.63-0.93x the time of the MLIR fusion emitters with the same results and no
      consistent warm cost: time to the first answer is mostly XLA compile. XLA aborts the
      process on a flag it does not know, so only for jaxlib 0.5.3 (the first release with
      it) to 0.10 (XLA retired the legacy emitters in 2026-09; jaxlib 0.11.2, on the GPU
      machine, aborted at the first computation).
    Measurements: benchmarks/RESULTS.md."""
    if _os.environ.get("JAXTRAJ_NO_XLA_TUNING"):
        return
    flags = _os.environ.get("XLA_FLAGS", "")
    extra = []
    if "--xla_backend_extra_options" not in flags:
        extra.append("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000")
    if "--xla_cpu_use_fusion_emitters" not in flags and _has_legacy_emitters():
        extra.append("--xla_cpu_use_fusion_emitters=false")
    if extra:
        _os.environ["XLA_FLAGS"] = " ".join([flags, *extra]).strip()


def _has_legacy_emitters():
    """Whether the installed jaxlib knows `--xla_cpu_use_fusion_emitters` (0.5.3 to 0.10)."""
    return _jaxlib_at_least((0, 5, 3)) and not _jaxlib_at_least((0, 11))


def _jaxlib_at_least(version):
    """Whether the installed jaxlib is at least `version`, from its package metadata
    (without importing it)."""
    import importlib.metadata
    import re

    try:
        release = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return False
    return tuple(int(x) for x in re.findall(r"\d+", release)[:3]) >= tuple(version)


_xla_cpu_options()

import jax as _jax

_jax.config.update("jax_enable_x64", True)


def _one_cpu_device_per_core():
    """Split the CPU into one JAX device per core, so that `jt.solve_batch` and
    `jt.multistart` shard a batch over every core by default: XLA runs one CPU device on
    about one core (2.2x the loop of single solves with two devices on two cores against
    1.3x with one; benchmarks/RESULTS.md). Single computations run on the first device as
    before. Left alone where the user chose: `JAX_NUM_CPU_DEVICES` or an earlier
    `jax.config.update("jax_num_cpu_devices", N)`, the host device count in XLA_FLAGS, an
    initialized `jax.distributed`, or JAXTRAJ_CPU_DEVICES=N (1: JAX's single device); a
    later `jax.config.update` still wins.
    Only possible before JAX starts its backends (not when jaxtraj is imported after a JAX
    computation). Not by default with jaxlib >= 0.11: with jax 0.11.2 KalmanSQP's batch
    program sharded over 2 or more CPU devices crashed the process (a segmentation fault;
    KalmanSearch's did not, nor did sharded eigh, svd, lstsq, solve or a while loop of eigh
    alone; the GPU machine's 16 cores, 2026-12-04, benchmarks/RESULTS.md), so there JAX's
    single device stays unless JAXTRAJ_CPU_DEVICES asks for more."""
    if "xla_force_host_platform_device_count" in _os.environ.get("XLA_FLAGS", ""):
        return
    if _jax.config.jax_num_cpu_devices != -1:  # set by the user (config or JAX_NUM_CPU_DEVICES)
        return
    if getattr(_jax.distributed, "is_initialized", lambda: False)():  # a multi-host setup of its own
        return
    try:
        count = int(_os.environ.get("JAXTRAJ_CPU_DEVICES", "0"))
    except ValueError:
        count = 0
    if count < 1:
        if _jaxlib_at_least((0, 11)):
            return
        count = len(_os.sched_getaffinity(0)) if hasattr(_os, "sched_getaffinity") else (_os.cpu_count() or 1)
    try:
        _jax.config.update("jax_num_cpu_devices", count)
    except RuntimeError:  # JAX already computed something: its backends are fixed
        pass


_one_cpu_device_per_core()

from . import (
    controls as controls,
    feedback as feedback,
    io as io,
    metaheuristics as metaheuristics,
    problems as problems,
    rotations as rotations,
)
from ._augmented_lagrangian import AugmentedLagrangian as AugmentedLagrangian
from ._batch import (
    MultistartResult as MultistartResult,
    multistart as multistart,
    random_starts as random_starts,
    solve_batch as solve_batch,
)
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._driver import AbstractSolver as AbstractSolver
from ._kalman_search import KalmanSearch as KalmanSearch
from ._kalman_sqp import KalmanSQP as KalmanSQP
from ._line_search import LineSearch as LineSearch
from ._problem import Problem as Problem, minimum_time as minimum_time
from ._report import KKTReport as KKTReport, kkt_report as kkt_report
from ._sensitivity import (
    Evaluation as Evaluation,
    evaluate as evaluate,
    sensitivities as sensitivities,
)
from ._simulate import (
    RK4 as RK4,
    AbstractSimulator as AbstractSimulator,
    Diffrax as Diffrax,
    Trajectory as Trajectory,
    simulate as simulate,
)
from ._solution import History as History, Solution as Solution
from ._solve import solve as solve
from ._status import Status as Status, status_name as status_name
from ._trust_region import TrustRegion as TrustRegion
from .feedback import (
    ClosedLoopTrajectory as ClosedLoopTrajectory,
    ControlErrors as ControlErrors,
    Dispersion as Dispersion,
    ExecutionErrors as ExecutionErrors,
    Linearization as Linearization,
    MonteCarloResult as MonteCarloResult,
    ThrustErrors as ThrustErrors,
    bryson_weights as bryson_weights,
    linearize as linearize,
    monte_carlo as monte_carlo,
    simulate_closed_loop as simulate_closed_loop,
    tracking_lqr as tracking_lqr,
)
from .metaheuristics import Dragonfly as Dragonfly, GreyWolf as GreyWolf, Whale as Whale

__version__ = "0.1.0"
