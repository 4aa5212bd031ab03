"""Input checks of the public entry points (outside jit): float64 mode, problem and control
types, the parameter vector. Errors name the argument."""

import jax
import jax.numpy as jnp
import numpy as np

from ._problem import Problem
from .controls import AbstractControl, FixedFinalTime


def require_float64():
    """Raise a RuntimeError unless JAX's float64 mode is on (jaxtraj turns it on at import)."""
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "jaxtraj needs float64: `jax_enable_x64` was turned off after importing jaxtraj. "
            "Call jax.config.update('jax_enable_x64', True)."
        )


def check_settings(owner: str, obj, rules: dict):
    """Raise a ValueError naming `owner` and the field for the first rule (field name ->
    callable returning bool) that fails or cannot be evaluated (a wrong type, e.g. a string
    tolerance)."""
    for name, rule in rules.items():
        try:
            ok = bool(rule())
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{owner}: invalid `{name}` = {getattr(obj, name)!r} (see the field docs).")


def as_float64(x):
    """`x` as a float64 array, after `require_float64`."""
    require_float64()
    return jnp.asarray(x, dtype=jnp.float64)


def check_problem_and_control(problem: Problem, control: AbstractControl) -> AbstractControl:
    """Outside-jit type and compatibility checks of the public entry points; returns the
    control the solvers work with: for a problem with a fixed `final_time`, the family
    wrapped in `FixedFinalTime` (its vector without tf)."""
    require_float64()
    if not isinstance(problem, Problem):
        raise ValueError(f"`problem` must be a jaxtraj.Problem; got {type(problem).__name__}.")
    if not isinstance(control, AbstractControl):
        raise ValueError(f"`control` must be a jaxtraj control (jt.controls.*); got {type(control).__name__}.")
    if control.num_controls != problem.num_controls:
        raise ValueError(
            f"`control` has {control.num_controls} channel(s) but `problem` {problem.name!r} "
            f"expects num_controls={problem.num_controls}."
        )
    if problem.final_time is None:
        return control
    if not isinstance(control, FixedFinalTime):
        return FixedFinalTime(control, problem.final_time)
    if not isinstance(control.final_time, jax.core.Tracer) and not isinstance(problem.final_time, jax.core.Tracer):
        if float(control.final_time) != float(problem.final_time):
            raise ValueError(
                f"`control` fixes the final time at {float(control.final_time):g} but `problem` "
                f"{problem.name!r} has final_time={float(problem.final_time):g}."
            )
    return control


def check_inputs(problem: Problem, control: AbstractControl, a):
    """Outside-jit checks of the public entry points; returns the control the solvers work
    with (`check_problem_and_control`) and `a` as a float64 array. For a fixed final time,
    `a` may also be the family's own vector with tf = T (its tf entry is dropped)."""
    given = control
    control = check_problem_and_control(problem, control)
    if isinstance(a, jax.core.Tracer):
        if a.shape != (control.num_params,):
            raise ValueError(f"`a` must have shape ({control.num_params},) for {control!r}; got {a.shape}.")
        return control, a.astype(jnp.float64)
    if control is not given and np.shape(a) == (given.num_params,):
        full = given.validate(a)
        tf, T = full[control.tf_index], float(control.final_time)
        if not np.isclose(tf, T, rtol=1e-12, atol=0.0):
            raise ValueError(
                f"`a` has tf = {tf:g} (entry {control.tf_index}) but the problem fixes final_time={T:g}; "
                f"pass a vector without tf ({control.num_params} entries) or one with tf = {T:g}."
            )
        a = control.reduce(full)
    return control, jnp.asarray(control.validate(a))
