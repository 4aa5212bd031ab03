"""The control-sample grid and one sampled-data step of the closed loop."""

from typing import Literal, cast, overload

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from .._checks import as_float64
from .._simulate import initial_state, rk4_step, segment_data
from ._common import check_shape
from ._errors import AbstractExecutionErrors, Exact
from ._lqr import DiscreteLQRGains, LQRGains


class _Grid(eqx.Module):
    """One control sample = one RK4 step of the simulator: `N = num_segments * steps`."""

    theta: jax.Array  # (N, r) the sample's segment row of `segment_data`
    tau: jax.Array  # (N,) rescaled start of the step within its segment
    t: jax.Array  # (N + 1,) sample times, t_N = tf
    dt: jax.Array  # (N,) sample durations h_k / steps
    dtau: float  # 1 / steps


def _grid(control, a, steps):
    data = segment_data(control, a)
    dtau = 1.0 / steps
    # the same tau values as RK4.integrate (j * dt, j a float64 counter), so that a noise-free
    # run repeats jt.simulate's arithmetic
    tau = jnp.tile(jnp.arange(steps, dtype=jnp.float64) * dtau, data.shape[0])
    theta = jnp.repeat(data, steps, axis=0)
    t = jnp.concatenate([theta[:, -2] + theta[:, -1] * tau, control.knots(a)[-1:]])
    return _Grid(theta=theta, tau=tau, t=t, dt=theta[:, -1] * dtau, dtau=dtau)


def bounded_control(problem, u):
    if problem.control_lower is not None:
        u = jnp.maximum(u, problem.control_lower)
    if problem.control_upper is not None:
        u = jnp.minimum(u, problem.control_upper)
    return u


def sample_step(problem, control, execution, dtau, theta, tau, x, du, xi, w):
    """One RK4 step over a control sample: feedforward u_ref(t) at every stage, the feedback
    correction `du`, the execution noise `xi` and the process noise `w` (added to dx/dt) all
    held constant over the step."""
    row, t_k, h = theta[:-2], theta[-2], theta[-1]

    def field(s, y):
        t = t_k + h * s
        u = bounded_control(problem, control.local_control(row, h, s) + du)
        u, args = execution(t, u, xi, problem.args)
        return h * (problem.dynamics(t, y, u, args) + w)

    return rk4_step(field, tau, dtau, x)


class Noise(eqx.Module):
    execution: AbstractExecutionErrors
    num_xi: int
    correlation_time: jax.Array
    Lw: jax.Array | None  # square root of the process-noise intensity W
    L0: jax.Array | None  # square root of the initial-state covariance


# (the overloads: `xs` and `dus` are arrays when `save` is True, else None)
@overload
def rollout(
    problem, control, noise, grid, x_start, x_ref, K, key, save: Literal[True]
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]: ...
@overload
def rollout(
    problem, control, noise, grid, x_start, x_ref, K, key, save: bool
) -> tuple[jax.Array, jax.Array, jax.Array | None, jax.Array | None, jax.Array]: ...
def rollout(problem, control, noise, grid, x_start, x_ref, K, key, save: bool):
    """One run over the sample grid from the nominal initial state `x_start` (dispersed by
    the noise). `K=None`: no feedback; `key=None`: no noise.

    Returns `(x0, xf, xs (N, n) or None, dus (N, m) or None, int du^2 dt (m,))`.
    """
    n, m, p = problem.num_states, problem.num_controls, noise.num_xi
    x0 = x_start
    xi = jnp.zeros((p,))
    noisy = key is not None and (p > 0 or noise.Lw is not None)
    if key is not None:
        k_x0, k_xi, k_steps = jax.random.split(key, 3)
        if noise.L0 is not None:
            x0 = x0 + noise.L0 @ jax.random.normal(k_x0, (n,), jnp.float64)
        xi = jax.random.normal(k_xi, (p,), jnp.float64)  # stationary start of the Markov model
    c = noise.correlation_time
    phi = jnp.where(c > 0, jnp.exp(-grid.dt / jnp.where(c > 0, c, 1.0)), 0.0)
    q = jnp.sqrt(1.0 - phi * phi)
    dt_safe = jnp.where(grid.dt > 0, grid.dt, 1.0)
    nw = 0 if noise.Lw is None else n
    N = grid.tau.shape[0]
    K_seq = jnp.zeros((N, 0)) if K is None else K

    def body(carry, inp):
        x, xi, du2 = carry
        theta, tau, xr, Kk, dt, ph, qk, dts, k = inp
        du = jnp.zeros((m,)) if K is None else -(Kk @ (x - xr))
        w = jnp.zeros((n,))
        if noisy:
            z = jax.random.normal(jax.random.fold_in(k_steps, k), (p + nw,), jnp.float64)
            xi = ph * xi + qk * z[:p]
            if nw:
                w = (noise.Lw @ z[p:]) / jnp.sqrt(dts)
        x1 = sample_step(problem, control, noise.execution, grid.dtau, theta, tau, x, du, xi, w)
        return (x1, xi, du2 + du * du * dt), ((x1, du) if save else None)

    inputs = (grid.theta, grid.tau, x_ref, K_seq, grid.dt, phi, q, dt_safe, jnp.arange(N))
    (xf, _, du2), out = lax.scan(body, (x0, xi, jnp.zeros((m,))), inputs)
    xs, dus = cast("tuple[jax.Array, jax.Array]", out) if save else (None, None)  # (`body` saves a pair if save)
    return x0, xf, xs, dus, du2


def noise_free(problem, control, a, steps):
    """The reference: the sampled run without noise (the same arithmetic as jt.simulate with
    RK4(steps)). Returns `(grid, x_ref (N + 1, n))`."""
    grid = _grid(control, a, steps)
    exact = Noise(Exact(), 0, jnp.zeros(()), None, None)
    no_ref = jnp.zeros((grid.tau.shape[0], 0))  # not used without feedback
    x0 = initial_state(problem, control, a)  # free initial-state components from `a`
    _, _, xs, _, _ = rollout(problem, control, exact, grid, x0, no_ref, None, None, True)
    return grid, jnp.concatenate([x0[None], xs])


def gain_sequence(gains, t):
    """Per-sample gains `(N, m, n)` at the sample times `t` (`(N + 1,)`), or None."""
    if gains is None:
        return None
    if isinstance(gains, LQRGains):
        return jax.vmap(gains.gain)(t[:-1])
    if isinstance(gains, DiscreteLQRGains):
        return gains.K
    return gains


def check_gains(gains, N, m, n):
    """Outside-jit check of `gains`; returns it (arrays as float64)."""
    if gains is None or isinstance(gains, LQRGains):
        if gains is not None:
            check_shape("gains.K", gains.K.shape[1:], (m, n))
        return gains
    K = gains.K if isinstance(gains, DiscreteLQRGains) else as_float64(gains)
    if K.shape != (N, m, n):
        raise ValueError(
            f"`gains` must be None, LQRGains, or DiscreteLQRGains / an array with one gain per "
            f"control sample, K of shape ({N}, {m}, {n}) (num_segments * RK4 steps = {N}); "
            f"got K of shape {K.shape}."
        )
    return gains if isinstance(gains, DiscreteLQRGains) else K
