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
