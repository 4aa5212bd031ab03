"""Execution-error models of the sampled-data loop: thrust and control realization errors."""

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp

from .._checks import as_float64
from ._common import check_shape, numbers


class AbstractExecutionErrors(eqx.Module):
    """How a commanded control is executed: `(u_actual, args_actual) = errors(t, u, xi, args)`.

    `xi ~ N(0, I)` has `num_noise(num_controls)` entries and is held constant over one control
    sample (see `monte_carlo` for the sample model). At `xi = 0` the command must be executed
    exactly. Errors that are not part of `u` (a thrust magnitude held in `problem.args`) enter
    through the returned `args_actual`, which is passed to `problem.dynamics`.
    """

    @abc.abstractmethod
    def num_noise(self, num_controls: int) -> int:
        """Number of standard normal variables drawn per control sample."""

    @abc.abstractmethod
    def check(self, problem) -> None:
        """Outside-jit compatibility check with `problem`; raises `ValueError`."""

    @abc.abstractmethod
    def __call__(self, t, u, xi, args):
        """`(u_actual, args_actual)` for the commanded `u` and the sample's noise `xi`."""


def _sigma(name, value):
    value = as_float64(value)
    if value.ndim != 0:
        raise ValueError(f"`{name}` must be a scalar; got shape {value.shape}.")
    if not isinstance(value, jax.core.Tracer) and not bool((value >= 0) & jnp.isfinite(value)):
        raise ValueError(f"`{name}` must be finite and >= 0; got {float(value)}.")
    return value


def _sigmas(name, value):
    """Standard deviations, a scalar or a vector: finite and >= 0, or a ValueError naming `name`."""
    value = numbers(name, value)
    if not isinstance(value, jax.core.Tracer) and not bool(jnp.all((value >= 0) & jnp.isfinite(value))):
        raise ValueError(f"`{name}` must be finite and >= 0; got {value}.")
    return value


class ThrustErrors(AbstractExecutionErrors):
    """Thrust-magnitude and pointing errors of an engine whose control is a thrust angle:

        thrust -> thrust (1 + sigma_magnitude xi_0),     angle -> angle + sigma_pointing xi_1,

    where `angle = u[angle_index]` and `thrust = args[thrust_key]` (as in
    `jt.problems.earth_mars`). The defaults are 1 % (1 sigma) of thrust magnitude and 1 degree
    (1 sigma) of pointing. `thrust_key=None` applies the pointing error only (e.g. a sail
    angle).

    **Arguments:** `sigma_magnitude` (relative), `sigma_pointing_deg` (degrees); keyword-only
    `thrust_key`, `angle_index`.
    """

    sigma_magnitude: jax.Array
    sigma_pointing: jax.Array  # radians
    thrust_key: str | None
    angle_index: int

    def __init__(
        self, sigma_magnitude=0.01, sigma_pointing_deg=1.0, *, thrust_key: str | None = "thrust", angle_index=0
    ):
        self.sigma_magnitude = _sigma("sigma_magnitude", sigma_magnitude)
        self.sigma_pointing = jnp.deg2rad(_sigma("sigma_pointing_deg", sigma_pointing_deg))
        self.thrust_key = thrust_key
        self.angle_index = angle_index

    def num_noise(self, num_controls):
        return 2

    def check(self, problem):
        if not (isinstance(self.angle_index, int) and 0 <= self.angle_index < problem.num_controls):
            raise ValueError(f"`angle_index` must be an int in [0, {problem.num_controls}); got {self.angle_index!r}.")
        if self.thrust_key is not None and not (isinstance(problem.args, dict) and self.thrust_key in problem.args):
            raise ValueError(
                f"ThrustErrors: `problem.args` must be a dict with the thrust magnitude under "
                f"{self.thrust_key!r} (problem {problem.name!r}); pass thrust_key=None for "
                "pointing errors only, or use ControlErrors / ExecutionErrors."
            )

    def __call__(self, t, u, xi, args):
        u = u.at[self.angle_index].add(self.sigma_pointing * xi[1])
        if self.thrust_key is not None:
            k = self.thrust_key
            args = {**args, k: args[k] * (1.0 + self.sigma_magnitude * xi[0])}
        return u, args


class ControlErrors(AbstractExecutionErrors):
    """Per-channel relative and absolute execution errors of the control itself:

        u_j -> u_j (1 + multiplicative_j xi_j) + additive_j xi_{m + j},   j = 1..m

    (2m noise variables per sample). `multiplicative` is the seed's model (1 + xi) u (eq.
    2.10) channel by channel; `additive` alone is e.g. a pointing error on an angle control.

    **Arguments:** `multiplicative`, `additive`: standard deviations, scalars or `(m,)`.
    """

    multiplicative: jax.Array
    additive: jax.Array

    def __init__(self, multiplicative=0.0, additive=0.0):
        # (a NaN or inf sigma failed every run; a negative one is no standard deviation)
        self.multiplicative = _sigmas("multiplicative", multiplicative)
        self.additive = _sigmas("additive", additive)

    def num_noise(self, num_controls):
        return 2 * num_controls

    def check(self, problem):
        m = problem.num_controls
        check_shape("multiplicative", self.multiplicative.shape, (), (m,))
        check_shape("additive", self.additive.shape, (), (m,))

    def __call__(self, t, u, xi, args):
        m = u.shape[0]
        return u * (1.0 + self.multiplicative * xi[:m]) + self.additive * xi[m:], args


class ExecutionErrors(AbstractExecutionErrors):
    """A user-defined execution model `fn(t, u, xi, args) -> (u_actual, args_actual)` with
    `num` standard normal variables per sample; `fn` must be the identity at `xi = 0`.
    Parameters that are swept should live in `args` or in an `eqx.Module` `fn` (arrays are
    traced; a new Python closure recompiles)."""

    fn: Callable
    num: int

    def num_noise(self, num_controls):
        return self.num

    def check(self, problem):
        if not (isinstance(self.num, int) and self.num >= 0):
            raise ValueError(f"`num` must be an int >= 0; got {self.num!r}.")
        m = problem.num_controls
        t = jax.ShapeDtypeStruct((), jnp.float64)
        u = jax.ShapeDtypeStruct((m,), jnp.float64)
        xi = jax.ShapeDtypeStruct((self.num,), jnp.float64)
        out = jax.eval_shape(lambda t, u, xi: self.fn(t, u, xi, problem.args), t, u, xi)
        if not (isinstance(out, tuple) and len(out) == 2 and getattr(out[0], "shape", None) == (m,)):
            raise ValueError(f"`fn(t, u, xi, args)` must return (u_actual of shape ({m},), args_actual).")

    def __call__(self, t, u, xi, args):
        return self.fn(t, u, xi, args)


class Exact(AbstractExecutionErrors):
    """No execution errors."""

    def num_noise(self, num_controls):
        return 0

    def check(self, problem):
        pass

    def __call__(self, t, u, xi, args):
        return u, args
