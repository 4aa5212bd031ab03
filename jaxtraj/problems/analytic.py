"""Small problems with answers known in closed form, for tests and examples."""

import jax.numpy as jnp

from .._problem import Problem


def _double_integrator_dynamics(t, x, u, args):
    del t, args
    return jnp.stack([x[1], u[0]])


def _double_integrator_terminal(tf, xf, args):
    del tf
    return xf - args["target"]


def double_integrator(target=(1.0, 0.0)) -> Problem:
    """x1' = x2, x2' = u from rest at the origin; terminal x(tf) = target; minimize tf.

    With a piecewise-polynomial control of degree <= 2 the state is a polynomial of degree
    <= 4 on every segment, which RK4 integrates exactly.
    """
    return Problem(
        _double_integrator_dynamics,
        x0=[0.0, 0.0],
        terminal=_double_integrator_terminal,
        constraint_names=("position", "velocity"),
        args={"target": jnp.asarray(target, dtype=jnp.float64)},
        state_names=("position", "velocity"),
        control_names=("acceleration",),
        name="double-integrator",
    )


def _energy_dynamics(t, x, u, args):
    del t, args
    return jnp.stack([x[1], u[0], 0.5 * u[0] ** 2])


def _energy_terminal(tf, xf, args):
    return jnp.stack([xf[0] - 1.0, xf[1], tf - args["tf"]])


def _energy_objective(tf, xf, args):
    del tf, args
    return xf[2]


def min_energy_double_integrator(tf=1.0) -> Problem:
    """Minimize the control energy 1/2 int u^2 dt moving x'' = u from rest at 0 to rest at 1
    in the fixed time `tf` (imposed as the terminal constraint tf - T = 0).

    Analytic optimum: u(t) = 6/T^2 - 12 t/T^3, energy 6/T^3. Any continuous piecewise-linear
    control contains it, and RK4 is exact on this polynomial system.
    """
    return Problem(
        _energy_dynamics,
        x0=[0.0, 0.0, 0.0],
        terminal=_energy_terminal,
        constraint_names=("position", "velocity", "final time"),
        objective=_energy_objective,
        args={"tf": jnp.asarray(float(tf), dtype=jnp.float64)},
        state_names=("position", "velocity", "energy"),
        control_names=("acceleration",),
        name="min-energy-double-integrator",
    )


def _speed_limit(t, x, u, args):
    del t, u
    return jnp.stack([x[1] - args["vmax"]])


def speed_limited_double_integrator(vmax=1.2, tf=1.0) -> Problem:
    """`min_energy_double_integrator` with the path constraint x2 <= vmax (C = x2 - vmax).

    For tf = 1 and 1 < vmax < 1.5 (1.5 is the unconstrained peak speed) the optimum
    accelerates with u = a (1 - t/t1) to reach vmax at t1 = 3 (vmax - 1) / (2 vmax), coasts
    on the constraint and brakes symmetrically; energy `speed_limited_energy(vmax)` =
    8 vmax^3 / (9 (vmax - 1)) (6 at vmax = 1.5). For vmax = 1.2, t1 = 1/4: u is piecewise
    linear with nodes at 0, 1/4, 3/4, 1, so `PiecewiseLinear(4)` contains the optimum
    exactly (node values 9.6, 0, 0, 0, -9.6).
    """
    base = min_energy_double_integrator(tf)
    return Problem(
        base.dynamics,
        x0=base.x0,
        terminal=base.terminal,
        constraint_names=base.constraint_names,
        objective=base.objective,
        args={**base.args, "vmax": jnp.asarray(float(vmax), dtype=jnp.float64)},
        state_names=base.state_names,
        control_names=base.control_names,
        path=_speed_limit,
        path_names=("speed",),
        name="speed-limited-double-integrator",
    )


def speed_limited_energy(vmax):
    """Optimal energy of `speed_limited_double_integrator(vmax, tf=1)`, 1 < vmax <= 1.5."""
    if not 1.0 < vmax <= 1.5:
        raise ValueError(f"`vmax` must be in (1, 1.5]; got {vmax}.")
    return 8.0 * vmax**3 / (9.0 * (vmax - 1.0))
