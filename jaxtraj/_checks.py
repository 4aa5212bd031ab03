"""Input checks of the public entry points (outside jit): float64 mode, problem and control
types, the parameter vector. Errors name the argument."""

import contextlib
import functools
import os
import re

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from ._problem import Problem, check_bound_shapes
from .controls import AbstractControl, FixedFinalTime, FreeInitialState


def require_float64():
    """Raise a RuntimeError unless JAX's float64 mode is on (jaxtraj turns it on at import)."""
    if not jax.config.jax_enable_x64:  # pyright: ignore[reportAttributeAccessIssue]  (JAX config options are dynamic attributes)
        raise RuntimeError(
            "jaxtraj needs float64: `jax_enable_x64` was turned off after importing jaxtraj. "
            "Call jax.config.update('jax_enable_x64', True)."
        )


def check_settings(owner: str, obj, rules: dict, flags: tuple = ()):
    """Raise a ValueError naming `owner` and the field for the first rule (field name ->
    callable returning bool) that fails or cannot be evaluated (a wrong type, e.g. a string
    tolerance), or whose value is not a scalar or (unless in `flags`) is a bool."""
    for name, rule in rules.items():
        value = getattr(obj, name)
        try:  # (an array of shape (1,) failed inside the solve; True was taken as 1)
            ok = np.ndim(value) == 0 and (name in flags or not isinstance(value, bool | np.bool_)) and bool(rule())
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{owner}: invalid `{name}` = {getattr(obj, name)!r} (see the field docs).")


def is_count(value, least: int = 0) -> bool:
    """An int (not a bool) in least..2**31 - 1: a count the compiled loops hold in int32."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool) and bool(least <= value < 2**31)


def as_float64(x):
    """`x` as a float64 array, after `require_float64`."""
    require_float64()
    return jnp.asarray(x, dtype=jnp.float64)


def check_problem_and_control(problem: Problem, control: AbstractControl):
    """Outside-jit type and compatibility checks of the public entry points: for a problem
    with a fixed `final_time` or a `free_initial_state`, `control` must be the problem's
    parametrization of a family (`problem.parametrize(family)`)."""
    require_float64()
    if not isinstance(problem, Problem):
        raise ValueError(f"`problem` must be a jaxtraj.Problem; got {type(problem).__name__}.")
    n, x0 = len(problem.state_names), problem.x0  # (`num_states` reads x0's shape)
    is_array = isinstance(x0, jax.Array | np.ndarray)
    if not (is_array and x0.shape == (n,)):
        # (a list or a scalar put in with eqx.tree_at failed deep inside the integration)
        got = f"shape {x0.shape}" if is_array else f"a {type(x0).__name__}"
        raise ValueError(
            f"`problem.x0` must be an array of shape ({n},) (the states {problem.state_names}); got {got}. "
            "Put in a new one with `eqx.tree_at(lambda p: p.x0, problem, problem.x0.at[:k].set(value))`."
        )
    if not isinstance(control, AbstractControl):
        raise ValueError(f"`control` must be a jaxtraj control (jt.controls.*); got {type(control).__name__}.")
    if control.num_controls != problem.num_controls:
        raise ValueError(
            f"`control` has {control.num_controls} channel(s) but `problem` {problem.name!r} "
            f"expects num_controls={problem.num_controls}."
        )
    free = control.indices if isinstance(control, FreeInitialState) else ()
    inner = control.control if isinstance(control, FreeInitialState) else control
    T = inner.final_time if isinstance(inner, FixedFinalTime) else None
    fits = free == problem.free_initial_state and (T is None) == (problem.final_time is None)
    T_problem = problem.final_time  # (None exactly when T is, given `fits`)
    if (
        fits
        and T is not None
        and T_problem is not None
        and not any(isinstance(v, jax.core.Tracer) for v in (T, T_problem))
    ):
        fits = float(T) == float(T_problem)
    check_bound_shapes(problem)
    changed = [
        f"{name} {np.asarray(value)} (built with {np.asarray(box)})"
        for name, value, box in _bounds_and_boxes(problem)
        if not isinstance(value, jax.core.Tracer) and np.any(np.asarray(value) != np.asarray(box))
    ]
    if changed:
        raise ValueError(f"`problem`: {'; '.join(changed)}. {BOUNDS_CHANGED}")
    if not fits:
        wants = []
        if problem.final_time is not None:
            wants.append(f"final_time={float(problem.final_time):g}")
        if problem.free_initial_state:
            wants.append(f"free initial states {[problem.state_names[i] for i in problem.free_initial_state]}")
        raise ValueError(
            f"`control` {control!r} does not fit problem {problem.name!r} "
            f"({', '.join(wants) or 'no fixed final time, no free initial state'}): pass "
            "`problem.parametrize(family)` for a control family (jt.controls.*)."
        )


#: Why a traced final time of the problem must be the control's too.
FINAL_TIME_DIFFERS = (
    "`problem.final_time` and the final time of `control` differ: a fixed final time lives in the "
    "control too (the solve reads the control's). After `eqx.tree_at(lambda p: p.final_time, problem, T)`, "
    "rebuild the control: `control = problem.parametrize(family)`."
)


def follow_final_time(problem: Problem, control: AbstractControl, refuse_traced: str | None = None):
    """`control`, for a fixed final time that is traced in the problem or the control (not the
    same array in both): a control whose final time is concrete takes the problem's traced
    one, which the solve read nowhere (`jax.grad` in `problem.final_time` without rebuilding
    the control was 0 and `jax.vmap` over it solved at the control's one time, silently).
    A ValueError (`FINAL_TIME_DIFFERS`) where the two differ. Where that is known only at run
    time (under `jit` or `vmap`): a ValueError with the message `refuse_traced` if given, else
    the returned control's final time raises it then (`eqx.error_if`: the check travels with
    what the solve reads)."""
    inner = control.control if isinstance(control, FreeInitialState) else control
    T = problem.final_time
    if T is None or not isinstance(inner, FixedFinalTime) or T is inner.final_time:
        return control
    traced = [isinstance(v, jax.core.Tracer) for v in (T, inner.final_time)]
    if not any(traced):  # (concrete ones: `check_problem_and_control`)
        return control
    T = jnp.asarray(T, dtype=jnp.float64) if traced[0] else inner.final_time
    differs = jnp.any(T != inner.final_time)
    try:  # (concrete under an eager jax.grad or jax.jvp)
        known = bool(differs)
    except jax.errors.ConcretizationTypeError:
        if refuse_traced is not None:
            raise ValueError(refuse_traced) from None
        T = eqx.error_if(T, differs, f"jt.solve: {FINAL_TIME_DIFFERS}")
    else:
        if known:
            raise ValueError(FINAL_TIME_DIFFERS)
    if isinstance(control, FreeInitialState):
        return eqx.tree_at(lambda c: c.control.final_time, control, T)
    return eqx.tree_at(lambda c: c.final_time, control, T)


def closed_over_tracer(problem: Problem) -> str | None:
    """The path of a function of `problem` that closes over a JAX tracer (`problem.dynamics...`),
    or None. Under `jax.jit` or `jax.vmap` such a closure works (the value is a constant of
    the user's trace); under a derivative the tracer escapes jaxtraj's compiled solve (JAX's
    UnexpectedTracerError, which names neither the function nor the remedy): `jt.solve`
    then names it."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(problem):  # (the user's functions are leaves)
        if _closes_over_tracer(leaf):
            return f"problem{jax.tree_util.keystr(path)}"
    return None


#: What to do about `closed_over_tracer`.
CLOSED_OVER_TRACER = (
    "closes over a value that JAX differentiates (a variable of the function under jax.grad or "
    "jax.jvp), which jaxtraj's compiled solve cannot carry. Pass it in the problem's `args` and "
    "read it there: jt.solve differentiates `args` by the implicit function theorem."
)


def _closes_over_tracer(fn, depth: int = 0) -> bool:
    """Whether the function `fn` (a closure, a `functools.partial`, nested up to 4 deep) holds
    a JAX tracer among the values it closes over. (Such a function in a problem leaked the
    tracer out of jaxtraj's compiled programs: JAX's UnexpectedTracerError, which named
    neither the function nor the remedy.)"""
    if depth > 4 or not callable(fn):
        return False
    if isinstance(fn, functools.partial):
        held = [fn.func, *fn.args, *fn.keywords.values()]
    else:
        held = []
        for cell in getattr(fn, "__closure__", None) or ():
            with contextlib.suppress(ValueError):  # (an empty cell)
                held.append(cell.cell_contents)
    for value in held:
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(value)):
            return True
        if callable(value) and _closes_over_tracer(value, depth + 1):
            return True
    return False


#: Why a problem's control-bound arrays must keep the values it was built with.
BOUNDS_CHANGED = (
    "The control bounds fix which rows the solvers build (a static copy of them, taken by "
    "jt.Problem), so new values put into `control_lower` / `control_upper` after construction "
    "(eqx.tree_at, jax.vmap over them) would be solved at the old ones: build a jt.Problem per "
    "bound value instead (their derivatives at the built values are exact)."
)


def _bounds_and_boxes(problem: Problem):
    """`(name, array, built values)` of the problem's declared control bounds."""
    pairs = zip(
        ("control_lower", "control_upper"), (problem.control_lower, problem.control_upper), problem._control_box
    )
    return [(name, value, box) for name, value, box in pairs if value is not None]


def bounds_changed(problem: Problem):
    """Whether the control-bound arrays (traced or not) differ from the values the problem was
    built with (`BOUNDS_CHANGED`): a traced bool."""
    changed = jnp.asarray(False)
    for _, value, box in _bounds_and_boxes(problem):
        changed = changed | jnp.any(jnp.asarray(value) != jnp.asarray(box))
    return changed


def traced_bounds(problem: Problem) -> bool:
    """Whether a control-bound array is a tracer (under the user's jit, vmap or grad), so that
    only the compiled program can compare it with the built values."""
    return any(isinstance(value, jax.core.Tracer) for _, value, _ in _bounds_and_boxes(problem))


def check_inputs(problem: Problem, control: AbstractControl, a, *, zero_tf: bool = False):
    """Outside-jit checks of the public entry points; returns `a` as a float64 array
    (`zero_tf`: see `AbstractControl.validate`)."""
    check_problem_and_control(problem, control)
    if isinstance(a, jax.core.Tracer):
        if a.shape != (control.num_params,):
            raise ValueError(f"`a` must have shape ({control.num_params},) for {control!r}; got {a.shape}.")
        return a.astype(jnp.float64)
    return jnp.asarray(control.validate(a, zero_tf=zero_tf))


def memory_limit() -> int:
    """Bytes of memory this process can still take on its first device: the `bytes_limit`
    less `bytes_in_use` where the device reports them (accelerators), else the machine's
    available memory (`MemAvailable` of /proc/meminfo, the physical memory where there is
    none)."""
    try:
        stats = jax.local_devices()[0].memory_stats() or {}
    except jax.errors.JaxRuntimeError:  # a backend that reports none
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _gb(nbytes) -> str:
    return f"{nbytes / 1e9:,.1f} GB"


def check_memory(argument: str, nbytes: int, what: str):
    """Raise a ValueError naming `argument` when `what` (its arrays: `nbytes`, a lower bound)
    cannot fit in `memory_limit()`: refused before the work, with both numbers."""
    if nbytes <= 2**30:  # (no system query on every solve: a gigabyte fits anywhere we run)
        return
    limit = memory_limit()
    if nbytes > limit:
        raise ValueError(
            f"`{argument}`: {what} needs at least {_gb(nbytes)}, more than the {_gb(limit)} of memory available."
        )


def check_solver_memory(control, lanes=1):
    """`check_memory` for the dense n x n matrices (Hessian, covariance, Jacobians; 4 at
    least) that every solver forms for the control's n parameters, `lanes` starts at once:
    a control family of 10**9 segments is refused before anything is allocated."""
    n = control.num_params
    lanes_at_once = "" if lanes == 1 else f" in each of {lanes:,} lanes"
    what = f"a solve (4 dense {n:,} x {n:,} matrices at least{lanes_at_once})"
    check_memory("control", lanes * 4 * 8 * n * n, what)


@contextlib.contextmanager
def memory_refusal(what: str, remedy: str):
    """Turn XLA's RESOURCE_EXHAUSTED (a compiled program that asks for more memory than the
    device has, before it runs) into a MemoryError that says how much, the limit and what to
    reduce."""
    try:
        yield
    except jax.errors.JaxRuntimeError as e:
        if "RESOURCE_EXHAUSTED" not in str(e):
            raise
        asked = re.search(r"allocating (\d+) bytes", str(e))
        asked = f" (one allocation of {_gb(int(asked.group(1)))} failed)" if asked else ""
        raise MemoryError(
            f"{what} needs more memory than the {_gb(memory_limit())} available{asked}; {remedy}."
        ) from None
