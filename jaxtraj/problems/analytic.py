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
