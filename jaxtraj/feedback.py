"""Feedback around an optimized trajectory: linearization, LQR, closed-loop Monte Carlo.

Two layers:

* the generic linear-quadratic core: Riccati equations (`continuous_lqr`, `discrete_lqr`),
  zero-order hold (`zoh_discretize`), covariance propagation (`propagate_covariance*`);
* the trajectory layer: `linearize` (A(t), B(t) and the sampled-data Ad, Bd along the RK4
  solution of a parameter vector), `tracking_lqr` (the LQR law u = u_ref - K (x - x_ref)),
  `simulate_closed_loop` (one noisy run of the sampled-data loop) and `monte_carlo` (N runs
  in one vmapped call: terminal-error statistics and dispersion bands), with execution-error
  models `ThrustErrors`, `ControlErrors`, `ExecutionErrors`.

Equation numbers refer to seed 001 (lecture notes on synthesis of optimal control):

* discrete LQR, x_{i+1} = A_i x_i + B_i u_i (1.13), cost sum u^T W u + x_N^T Lambda x_N (1.14)
  solved by Bellman's recursion (1.5): u_i = -L_i x_i (1.22), gain (1.23), Riccati (1.24);
* continuous LQR, x' = A x + B u (1.37), cost (1.38): Riccati ODE (1.44) with S(T) = Lambda
  (1.45), u = -W^-1 B^T S x (1.46)-(1.47), stationary limit (1.48);
* stochastic LQR with multiplicative and additive control-realization errors (2.10)-(2.20).

Conventions (all functions): cost-to-go V_k(x) = x^T S_k x + c_k for the cost
sum_k (x_k^T Q x_k + u_k^T R u_k) + x_N^T Qf x_N (continuous: the integral of the same
integrand plus x(tf)^T Qf x(tf)); feedback u = -K x. The seed's cost has Q = 0; the state term
is its exercise (1.34)/(3.58) and only adds Q to the Riccati right-hand side.

Every function is pure JAX and returns float64; the numerical cores are jitted (repeated calls
with the same shapes, and for the continuous ones the same callables, do not recompile) and
may be called under jit / vmap. Differentiation: the discrete functions support forward and
reverse mode; the continuous ones forward mode by default (see `adjoint`). Shape errors are
`ValueError`s raised at call (trace) time, naming the argument.
"""

import abc
from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax

from ._simulate import RK4, check_inputs, rk4_step, segment_data, simulation_status
from ._status import Status

__all__ = [
    "AbstractExecutionErrors",
    "ClosedLoopTrajectory",
    "ControlErrors",
    "DiscreteLQRGains",
    "Dispersion",
    "ExecutionErrors",
    "LQRGains",
    "Linearization",
    "MonteCarloResult",
    "ThrustErrors",
    "bryson_weights",
    "continuous_lqr",
    "discrete_lqr",
    "linearize",
    "monte_carlo",
    "propagate_covariance",
    "propagate_covariance_continuous",
    "simulate_closed_loop",
    "tracking_lqr",
    "zoh_discretize",
]


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------

_FORWARD = diffrax.ForwardMode()  # default adjoint of the continuous solves


def _f64(x):
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "jaxtraj needs float64: `jax_enable_x64` was turned off after importing jaxtraj. "
            "Call jax.config.update('jax_enable_x64', True)."
        )
    return jnp.asarray(x, dtype=jnp.float64)


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def _shape(x, t=None):
    """Shape of an array, or of a callable's output at time t (without running it)."""
    return jax.eval_shape(x, t).shape if callable(x) else np.shape(x)


def _check(name, shape, *allowed):
    if tuple(shape) not in [tuple(a) for a in allowed]:
        want = " or ".join(str(tuple(a)) for a in allowed)
        raise ValueError(f"`{name}` must have shape {want}; got {tuple(shape)}.")


def _per_step(name, x, N, shape):
    """Broadcast a constant `shape` array, or check an `(N, *shape)` sequence."""
    x = _f64(x)
    _check(name, x.shape, shape, (N, *shape))
    return jnp.broadcast_to(x, (N, *shape))


def _interp(ts, ys, t):
    """Piecewise-linear interpolation of `ys` (leading axis on increasing `ts`), clamped at the
    ends."""
    i = jnp.clip(jnp.searchsorted(ts, t, side="right") - 1, 0, ts.shape[0] - 2)
    w = jnp.clip((t - ts[i]) / (ts[i + 1] - ts[i]), 0.0, 1.0)
    return ys[i] + w * (ys[i + 1] - ys[i])


# ---------------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------------


class LQRGains(eqx.Module):
    """Continuous-time LQR solution sampled on `ts` (increasing), u(t) = -K(t) x.

    - `ts`: `(T,)` sample times, t0 = ts[0] <= ... <= ts[-1] = tf (unless user-given).
    - `S`: `(T, n, n)` Riccati matrix (symmetric); cost-to-go x^T S(t) x + c(t).
    - `K`: `(T, m, n)` gain R^-1 B^T S (seed eq. 1.47).
    - `c`: `(T,)` cost offset from additive noise (zeros without noise; seed eq. 3.87).
    """

    ts: jax.Array
    S: jax.Array
    K: jax.Array
    c: jax.Array

    def gain(self, t):
        """K(t) by linear interpolation between samples (clamped outside [ts[0], ts[-1]])."""
        return _interp(self.ts, self.K, t)

    def riccati(self, t):
        """S(t) by linear interpolation between samples."""
        return _interp(self.ts, self.S, t)

    def control(self, t, x):
        """The feedback u = -K(t) x (seed eq. 1.46)."""
        return -self.gain(t) @ x

    def expected_cost(self, x0):
        """Optimal (expected) cost from x0 at ts[0]: x0^T S x0 + c."""
        return x0 @ self.S[0] @ x0 + self.c[0]


class DiscreteLQRGains(eqx.Module):
    """Discrete-time LQR solution, u_k = -K_k x_k (seed eq. 1.22 / 2.18).

    - `K`: `(N, m, n)` gains (seed eq. 1.23 / 2.19).
    - `S`: `(N + 1, n, n)` Riccati matrices, S_N = Qf (seed eq. 1.24 / 2.20).
    - `c`: `(N + 1,)` cost offsets, c_N = 0 (seed eq. 2.20); expected cost-to-go at step k is
      x^T S_k x + c_k.
    """

    K: jax.Array
    S: jax.Array
    c: jax.Array

    def control(self, k, x):
        return -self.K[k] @ x

    def expected_cost(self, x0):
        """Optimal expected cost from x0 at step 0: x0^T S_0 x0 + c_0."""
        return x0 @ self.S[0] @ x0 + self.c[0]


# ---------------------------------------------------------------------------------------------
# Continuous LQR
# ---------------------------------------------------------------------------------------------


def _at(x, t):
    return _f64(x(t)) if callable(x) else x


class _RiccatiField(eqx.Module):
    """Right-hand side of (S, c)' for diffrax. A Module (rather than a closure) so that
    repeated calls with the same callables and array shapes reuse diffrax's compiled solve."""

    A_fn: Callable
    B_fn: Callable
    Q: Callable | jax.Array
    R: Callable | jax.Array
    W: Callable | jax.Array

    def gain(self, t, S):
        return jsl.solve(_sym(_at(self.R, t)), _at(self.B_fn, t).T @ S, assume_a="pos")

    def __call__(self, t, y, args):
        S = _sym(y[0])
        A, B = _at(self.A_fn, t), _at(self.B_fn, t)
        AS = A.T @ S
        dS = -(AS + AS.T - S @ B @ self.gain(t, S) + _at(self.Q, t))
        return _sym(dS), -jnp.trace(S @ _at(self.W, t))


def continuous_lqr(
    A_fn: Callable,
    B_fn: Callable,
    Q,
    R,
    Qf,
    t0,
    tf,
    *,
    ts=None,
    noise=None,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    max_steps: int = 4096,
    step_ts=None,
    adjoint: diffrax.AbstractAdjoint = _FORWARD,
) -> LQRGains:
    """Finite-horizon continuous LQR by the Riccati ODE (seed eq. 1.44-1.47):

        -S' = A^T S + S A - S B R^-1 B^T S + Q,    S(tf) = Qf,    K = R^-1 B^T S,

    integrated backward in time, from tf down to t0 (diffrax with t1 < t0), with adaptive
    Dopri8; the vector field and the output are symmetrized.

    **Arguments:**

    - `A_fn`, `B_fn`: callables t -> `(n, n)`, `(n, m)`.
    - `Q`, `R`, `Qf`: `(n, n)`, `(m, m)`, `(n, n)`. `Q` and `R` may also be callables of t
      (time-varying weights); `R(t)` must be symmetric positive definite, `Q`, `Qf` PSD.
    - `t0`, `tf`: horizon, t0 < tf.
    - `ts`: increasing output times in [t0, tf]; default 101 uniform points.
    - `noise`: optional intensity W (`(n, n)` or callable) of additive white process noise,
      dx = (A x + B u) dt + dw, E[dw dw^T] = W dt. It does not change S or K (separation,
      seed §3.3); it adds c(t) to the expected cost-to-go, -c' = tr(S W), c(tf) = 0
      (seed eq. 3.87 with PH^T r^-1 HP -> W).
    - `rtol`, `atol`, `max_steps`: step-size control of the integration.
    - `step_ts`: optional times the integrator must step to (e.g. the kinks of interpolated
      A(t), B(t), such as `Linearization.t`; without them the error control resolves each
      kink with many rejected steps).
    - `adjoint`: diffrax adjoint. The default `ForwardMode()` (a plain while loop, about half
      the compile time) supports `jax.jvp`/`jax.jacfwd`; pass
      `diffrax.RecursiveCheckpointAdjoint()` to use `jax.grad`.

    **Returns:** `LQRGains`.
    """
    n = _shape(A_fn, t0)
    if len(n) != 2 or n[0] != n[1]:
        raise ValueError(f"`A_fn` must return a square (n, n) matrix; got shape {tuple(n)}.")
    n = n[0]
    bs = _shape(B_fn, t0)
    if len(bs) != 2 or bs[0] != n:
        raise ValueError(f"`B_fn` must return shape ({n}, m); got {tuple(bs)}.")
    m = bs[1]
    _check("Q", _shape(Q, t0), (n, n))
    _check("R", _shape(R, t0), (m, m))
    _check("Qf", _shape(Qf, t0), (n, n))
    if noise is not None:
        _check("noise", _shape(noise, t0), (n, n))
    t0, tf = _f64(t0), _f64(tf)
    ts = jnp.linspace(t0, tf, 101) if ts is None else _f64(ts)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-d array of at least 2 times; got shape {ts.shape}.")
    cast = lambda x: x if callable(x) else _f64(x)
    W = jnp.zeros((n, n)) if noise is None else noise
    field = _RiccatiField(A_fn, B_fn, cast(Q), cast(R), cast(W))
    step_ts = None if step_ts is None else _f64(step_ts)
    return _continuous_riccati(field, _f64(Qf), t0, tf, ts, rtol, atol, max_steps, adjoint, step_ts)


@eqx.filter_jit
def _continuous_riccati(field, Qf, t0, tf, ts, rtol, atol, max_steps, adjoint, step_ts=None):
    controller = diffrax.PIDController(rtol=rtol, atol=atol)
    if step_ts is not None:
        controller = diffrax.ClipStepSizeController(controller, step_ts=step_ts)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        diffrax.Dopri8(),
        t0=tf,
        t1=t0,
        dt0=None,
        y0=(_sym(Qf), jnp.zeros((), jnp.float64)),
        saveat=diffrax.SaveAt(ts=ts[::-1]),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
    )
    S = _sym(sol.ys[0][::-1])
    K = jax.vmap(field.gain)(ts, S)
    return LQRGains(ts=ts, S=S, K=K, c=sol.ys[1][::-1])


# ---------------------------------------------------------------------------------------------
# Discrete LQR (deterministic and stochastic)
# ---------------------------------------------------------------------------------------------


def discrete_lqr(As, Bs, Q, R, Qf, *, multiplicative=None, additive=None) -> DiscreteLQRGains:
    """Finite-horizon discrete LQR by the backward Riccati recursion (lax.scan, seed eq.
    1.22-1.24 and 2.18-2.20):

        K_k = (R + B^T S B + M(S))^-1 B^T S A,
        S_k = Q + A^T S (A - B K_k)   (evaluated in the PSD "Joseph" form
              Q + K^T (R + M(S)) K + (A - B K)^T S (A - B K)),
        c_k = c_{k+1} + tr(S W_k),

    with S = S_{k+1}, S_N = Qf, c_N = 0.

    **Noise model** (seed eq. 2.10, decided here): the step is

        x_{k+1} = A_k x_k + B_k u_k + sum_j xi_j D_{k,j} u_k + w_k,

    xi_j independent, zero mean, unit variance, independent of w_k (zero mean, covariance W_k)
    and across steps. The multiplicative term gives M(S) = sum_j D_j^T S D_j.

    - `multiplicative` = sigma^2 (a scalar, or `(N,)` per step) is the seed's model: the control
      is executed as (1 + xi) u with one scalar error xi of variance sigma^2 (the error grows
      with the commanded control, seed footnote 1), i.e. D = sigma B and
      M(S) = sigma^2 B^T S B, so K = (R + (1 + sigma^2) B^T S B)^-1 B^T S A (seed eq. 2.19).
      Larger sigma -> smaller gain.
    - `multiplicative` = matrices D of shape `(p, n, m)` (or `(N, p, n, m)`) is the general
      model; per-channel errors u -> u + sum_j xi_j C_j u are D_j = sigma_j B C_j.
    - `additive` = W (`(n, n)` or `(N, n, n)`): does not change K or S (certainty
      equivalence, seed §2.2 after eq. 2.20); it only adds c_k to the expected cost.

    **Arguments:** `As` `(N, n, n)`, `Bs` `(N, n, m)`; `Q` `(n, n)` or `(N, n, n)`; `R`
    `(m, m)` or `(N, m, m)` (R + B^T S B + M must be positive definite); `Qf` `(n, n)`.

    **Returns:** `DiscreteLQRGains`.
    """
    As, Bs = _f64(As), _f64(Bs)
    if As.ndim != 3 or As.shape[1] != As.shape[2]:
        raise ValueError(f"`As` must have shape (N, n, n); got {As.shape}.")
    N, n = As.shape[:2]
    if Bs.ndim != 3 or Bs.shape[:2] != (N, n):
        raise ValueError(f"`Bs` must have shape ({N}, {n}, m); got {Bs.shape}.")
    m = Bs.shape[2]
    Qs = _per_step("Q", Q, N, (n, n))
    Rs = _per_step("R", R, N, (m, m))
    Qf = _f64(Qf)
    _check("Qf", Qf.shape, (n, n))
    Ws = _per_step("additive", jnp.zeros((n, n)) if additive is None else additive, N, (n, n))
    mult = _f64(0.0 if multiplicative is None else multiplicative)
    if mult.ndim <= 1:
        sig2, Ds = _per_step("multiplicative", mult, N, ()), jnp.zeros((N, 0, n, m))
    elif mult.ndim in (3, 4):
        p = mult.shape[-3]
        sig2, Ds = jnp.zeros((N,)), _per_step("multiplicative", mult, N, (p, n, m))
    else:
        raise ValueError(
            "`multiplicative` must be sigma^2 (scalar or (N,)) or matrices (p, n, m) / "
            f"(N, p, n, m); got shape {mult.shape}."
        )

    return _discrete_riccati(As, Bs, Qs, Rs, Qf, sig2, Ds, Ws)


@jax.jit
def _discrete_riccati(As, Bs, Qs, Rs, Qf, sig2, Ds, Ws):
    def step(carry, x):
        S, c = carry
        A, B, Q, R, s2, D, W = x
        BSB = B.T @ S @ B
        M = s2 * BSB + jnp.einsum("jia,ik,jkb->ab", D, S, D)
        K = jsl.solve(_sym(R + BSB + M), B.T @ S @ A, assume_a="pos")
        F = A - B @ K
        S_new = _sym(Q + K.T @ (R + M) @ K + F.T @ S @ F)
        c_new = c + jnp.trace(S @ W)
        return (S_new, c_new), (K, S_new, c_new)

    init = (_sym(Qf), jnp.zeros((), jnp.float64))
    _, (K, S, c) = lax.scan(step, init, (As, Bs, Qs, Rs, sig2, Ds, Ws), reverse=True)
    S, c = jnp.concatenate([S, init[0][None]]), jnp.concatenate([c, init[1][None]])
    return DiscreteLQRGains(K=K, S=S, c=c)


# ---------------------------------------------------------------------------------------------
# Discretization and covariance propagation
# ---------------------------------------------------------------------------------------------


def zoh_discretize(A, B, dt):
    """Zero-order-hold discretization of x' = A x + B u over a step dt:

        Ad = e^{A dt},  Bd = int_0^dt e^{A s} ds B,  from  expm([[A, B], [0, 0]] dt).

    (The cost weights of the matching discrete problem are Q dt, R dt to first order, which is
    how the discrete recursion approximates seed eq. 1.44, cf. the discretization 1.27-1.30.)
    For a time-varying sequence, `jax.vmap(zoh_discretize, (0, 0, None))`.

    **Returns:** `(Ad, Bd)`, shapes `(n, n)`, `(n, m)`.
    """
    A, B, dt = _f64(A), _f64(B), _f64(dt)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"`A` must have shape (n, n); got {A.shape}.")
    n = A.shape[0]
    if B.ndim != 2 or B.shape[0] != n:
        raise ValueError(f"`B` must have shape ({n}, m); got {B.shape}.")
    if dt.ndim != 0:
        raise ValueError(f"`dt` must be a scalar; got shape {dt.shape}.")
    m = B.shape[1]
    top = jnp.concatenate([A, B], axis=1)
    E = jsl.expm(jnp.concatenate([top, jnp.zeros((m, n + m))], axis=0) * dt)
    return E[:n, :n], E[:n, n:]


def propagate_covariance(P0, Fs, W, G=None):
    """Covariance of x_{k+1} = F_k x_k + G_k w_k, w_k ~ (0, W_k) independent of x_k:

        P_{k+1} = F_k P_k F_k^T + G_k W_k G_k^T.

    For an LQR closed loop, F_k = A_k - B_k K_k (with a mean that follows x_{k+1} = F_k x_k).

    **Arguments:** `P0` `(n, n)`; `Fs` `(N, n, n)`; `W` `(q, q)` or `(N, q, q)`; `G` `(n, q)`
    or `(N, n, q)`, default identity (q = n).

    **Returns:** `(N + 1, n, n)`, P_0 ... P_N.
    """
    P0, Fs = _f64(P0), _f64(Fs)
    if Fs.ndim != 3 or Fs.shape[1] != Fs.shape[2]:
        raise ValueError(f"`Fs` must have shape (N, n, n); got {Fs.shape}.")
    N, n = Fs.shape[:2]
    _check("P0", P0.shape, (n, n))
    G = jnp.eye(n) if G is None else _f64(G)
    q = G.shape[-1]
    Gs = _per_step("G", G, N, (n, q))
    Ws = _per_step("W", W, N, (q, q))

    return _propagate(_sym(P0), Fs, Gs, Ws)


@jax.jit
def _propagate(P0, Fs, Gs, Ws):
    def step(P, x):
        F, G, W = x
        P = _sym(F @ P @ F.T + G @ W @ G.T)
        return P, P

    return jnp.concatenate([P0[None], lax.scan(step, P0, (Fs, Gs, Ws))[1]])


class _LyapunovField(eqx.Module):
    F_fn: Callable
    W: Callable | jax.Array

    def __call__(self, t, P, args):
        FP = _at(self.F_fn, t) @ P
        return _sym(FP + FP.T + _at(self.W, t))


def propagate_covariance_continuous(
    P0,
    F_fn: Callable,
    W,
    t0,
    tf,
    *,
    ts=None,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    max_steps: int = 4096,
    adjoint: diffrax.AbstractAdjoint = _FORWARD,
):
    """Covariance of dx = F(t) x dt + dw, E[dw dw^T] = W(t) dt (continuous counterpart of
    `propagate_covariance`, cf. seed eq. 3.72 without measurements):

        P' = F P + P F^T + W,   P(t0) = P0,

    integrated forward with adaptive Dopri8. For an LQR closed loop,
    `F_fn = lambda t: A_fn(t) - B_fn(t) @ gains.gain(t)`.

    **Arguments:** `P0` `(n, n)`; `F_fn` t -> `(n, n)`; `W` `(n, n)` or callable of t;
    `ts` increasing output times in [t0, tf] (default 101 uniform points); `rtol`, `atol`,
    `max_steps`, `adjoint` as in `continuous_lqr`.

    **Returns:** `(ts, Ps)` with `Ps` of shape `(T, n, n)`.
    """
    P0, fs = _f64(P0), _shape(F_fn, t0)
    if len(fs) != 2 or fs[0] != fs[1]:
        raise ValueError(f"`F_fn` must return a square (n, n) matrix; got shape {tuple(fs)}.")
    _check("P0", P0.shape, fs)
    _check("W", _shape(W, t0), fs)
    t0, tf = _f64(t0), _f64(tf)
    ts = jnp.linspace(t0, tf, 101) if ts is None else _f64(ts)
    field = _LyapunovField(F_fn, W if callable(W) else _f64(W))
    return ts, _lyapunov(field, _sym(P0), t0, tf, ts, rtol, atol, max_steps, adjoint)


@eqx.filter_jit
def _lyapunov(field, P0, t0, tf, ts, rtol, atol, max_steps, adjoint):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        diffrax.Dopri8(),
        t0=t0,
        t1=tf,
        dt0=None,
        y0=P0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        adjoint=adjoint,
    )
    return _sym(sol.ys)


# ---------------------------------------------------------------------------------------------
# Execution errors
# ---------------------------------------------------------------------------------------------


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
    value = _f64(value)
    if value.ndim != 0:
        raise ValueError(f"`{name}` must be a scalar; got shape {value.shape}.")
    if not isinstance(value, jax.core.Tracer) and not bool(value >= 0):
        raise ValueError(f"`{name}` must be >= 0; got {float(value)}.")
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

    def __init__(self, sigma_magnitude=0.01, sigma_pointing_deg=1.0, *, thrust_key="thrust", angle_index=0):
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
        self.multiplicative = _f64(multiplicative)
        self.additive = _f64(additive)

    def num_noise(self, num_controls):
        return 2 * num_controls

    def check(self, problem):
        m = problem.num_controls
        _check("multiplicative", self.multiplicative.shape, (), (m,))
        _check("additive", self.additive.shape, (), (m,))

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


class _Exact(AbstractExecutionErrors):
    """No execution errors."""

    def num_noise(self, num_controls):
        return 0

    def check(self, problem):
        pass

    def __call__(self, t, u, xi, args):
        return u, args


# ---------------------------------------------------------------------------------------------
# The control-sample grid and one sampled-data step
# ---------------------------------------------------------------------------------------------


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


def _bounded(problem, u):
    if problem.control_lower is not None:
        u = jnp.maximum(u, problem.control_lower)
    if problem.control_upper is not None:
        u = jnp.minimum(u, problem.control_upper)
    return u


def _sample_step(problem, control, execution, dtau, theta, tau, x, du, xi, w):
    """One RK4 step over a control sample: feedforward u_ref(t) at every stage, the feedback
    correction `du`, the execution noise `xi` and the process noise `w` (added to dx/dt) all
    held constant over the step."""
    row, t_k, h = theta[:-2], theta[-2], theta[-1]

    def field(s, y):
        t = t_k + h * s
        u = _bounded(problem, control.local_control(row, h, s) + du)
        u, args = execution(t, u, xi, problem.args)
        return h * (problem.dynamics(t, y, u, args) + w)

    return rk4_step(field, tau, dtau, x)


class _Noise(eqx.Module):
    execution: AbstractExecutionErrors
    num_xi: int
    correlation_time: jax.Array
    Lw: jax.Array | None  # square root of the process-noise intensity W
    L0: jax.Array | None  # square root of the initial-state covariance


def _rollout(problem, control, noise, grid, x_ref, K, key, save):
    """One run over the sample grid. `K=None`: no feedback; `key=None`: no noise.

    Returns `(x0, xf, xs (N, n) or None, dus (N, m) or None, int du^2 dt (m,))`.
    """
    n, m, p = problem.num_states, problem.num_controls, noise.num_xi
    x0 = problem.x0
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
        x1 = _sample_step(problem, control, noise.execution, grid.dtau, theta, tau, x, du, xi, w)
        return (x1, xi, du2 + du * du * dt), ((x1, du) if save else None)

    inputs = (grid.theta, grid.tau, x_ref, K_seq, grid.dt, phi, q, dt_safe, jnp.arange(N))
    (xf, _, du2), out = lax.scan(body, (x0, xi, jnp.zeros((m,))), inputs)
    xs, dus = out if save else (None, None)
    return x0, xf, xs, dus, du2


def _noise_free(problem, control, a, steps):
    """The reference: the sampled run without noise (the same arithmetic as jt.simulate with
    RK4(steps)). Returns `(grid, x_ref (N + 1, n))`."""
    grid = _grid(control, a, steps)
    exact = _Noise(_Exact(), 0, jnp.zeros(()), None, None)
    no_ref = jnp.zeros((grid.tau.shape[0], 0))  # not used without feedback
    _, _, xs, _, _ = _rollout(problem, control, exact, grid, no_ref, None, None, True)
    return grid, jnp.concatenate([problem.x0[None], xs])


def _gain_sequence(gains, t):
    """Per-sample gains `(N, m, n)` at the sample times `t` (`(N + 1,)`), or None."""
    if gains is None:
        return None
    if isinstance(gains, LQRGains):
        return jax.vmap(gains.gain)(t[:-1])
    if isinstance(gains, DiscreteLQRGains):
        return gains.K
    return gains


def _check_gains(gains, N, m, n):
    """Outside-jit check of `gains`; returns it (arrays as float64)."""
    if gains is None or isinstance(gains, LQRGains):
        if gains is not None:
            _check("gains.K", gains.K.shape[1:], (m, n))
        return gains
    K = gains.K if isinstance(gains, DiscreteLQRGains) else _f64(gains)
    if K.shape != (N, m, n):
        raise ValueError(
            f"`gains` must be None, LQRGains, or DiscreteLQRGains / an array with one gain per "
            f"control sample, K of shape ({N}, {m}, {n}) (num_segments * RK4 steps = {N}); "
            f"got K of shape {K.shape}."
        )
    return gains if isinstance(gains, DiscreteLQRGains) else K


# ---------------------------------------------------------------------------------------------
# Linearization along a trajectory
# ---------------------------------------------------------------------------------------------


class Linearization(eqx.Module):
    """The reference trajectory of `a` on the control-sample grid and its linearization.

    Grid: one sample per RK4 step of the simulator, `N = num_segments * steps`, sample times
    `t` (`(N + 1,)`, t_N = tf).

    - `x` `(N + 1, n)`: reference states (the RK4 solution, as `jt.simulate`).
    - `u` `(N + 1, m)`: reference control at the sample times (right-continuous at knots; the
      last entry is the left limit at tf).
    - `A` `(N + 1, n, n)`, `B` `(N + 1, n, m)`: df/dx, df/du at (t_k, x_k, u_k) by `jax.jacfwd`;
      `A_fn(t)`, `B_fn(t)` interpolate them linearly (for `continuous_lqr`).
    - `Ad` `(N, n, n)`, `Bd` `(N, n, m)`: the sampled-data (zero-order hold) linearization,
      x_{k+1} - xref_{k+1} = Ad_k (x_k - xref_k) + Bd_k du_k, as the exact Jacobians of the
      simulator's RK4 step with a correction du_k held over the sample (for linear
      time-invariant dynamics, `zoh_discretize(A, B, dt)` up to RK4's O(dt^5) per step).
    - `Gd` `(N, n, n)`: Jacobian of the step with respect to a process noise w added to dx/dt
      and held over the sample (~ dt I).
    - `Ed` `(N, n, p)`: Jacobian of the step with respect to the execution noise xi (p = 0
      without `execution`).
    - `dt` `(N,)`: sample durations; `status`: `Status.NONFINITE` if the reference is not finite.
    """

    t: jax.Array
    x: jax.Array
    u: jax.Array
    A: jax.Array
    B: jax.Array
    Ad: jax.Array
    Bd: jax.Array
    Gd: jax.Array
    Ed: jax.Array
    dt: jax.Array
    status: Status

    def A_fn(self, t):
        """A(t) by linear interpolation between samples (clamped outside [0, tf])."""
        return _interp(self.t, self.A, t)

    def B_fn(self, t):
        """B(t) by linear interpolation between samples (clamped outside [0, tf])."""
        return _interp(self.t, self.B, t)

    def predict_covariance(self, gains=None, *, initial_covariance=None, process_noise=None):
        """Linear covariance analysis of the sampled closed loop (white execution noise,
        `correlation_time=0`): P_{k+1} = F_k P_k F_k^T + Gd_k (W / dt_k) Gd_k^T + Ed_k Ed_k^T,
        F_k = Ad_k - Bd_k K_k. Valid while the dispersion is small enough for the
        linearization. `gains` as in `monte_carlo`. **Returns:** `(N + 1, n, n)`."""
        N, n = self.Ad.shape[:2]
        m, p = self.Bd.shape[2], self.Ed.shape[2]
        gains = _check_gains(gains, N, m, n)
        K = _gain_sequence(gains, self.t)
        F = self.Ad if K is None else self.Ad - self.Bd @ K
        P0 = jnp.zeros((n, n)) if initial_covariance is None else _f64(initial_covariance)
        _check("initial_covariance", P0.shape, (n, n))
        W = jnp.zeros((n, n)) if process_noise is None else _f64(process_noise)
        _check("process_noise", W.shape, (n, n))
        dt = jnp.where(self.dt > 0, self.dt, 1.0)
        Ws = jnp.zeros((N, n + p, n + p))
        Ws = Ws.at[:, :n, :n].set(W[None] / dt[:, None, None]).at[:, n:, n:].set(jnp.eye(p))
        return propagate_covariance(P0, F, Ws, jnp.concatenate([self.Gd, self.Ed], axis=2))


def _check_simulator_rk4(simulator):
    if not isinstance(simulator, RK4):
        raise ValueError(
            "`simulator` must be a fixed-step jt.RK4(steps) here (one control sample per RK4 "
            f"step); got {type(simulator).__name__}."
        )


def _check_execution(execution, problem):
    if execution is None:
        return _Exact()
    if not isinstance(execution, AbstractExecutionErrors):
        raise ValueError(
            f"`execution` must be None, ThrustErrors, ControlErrors or ExecutionErrors; got {type(execution).__name__}."
        )
    execution.check(problem)
    return execution


def linearize(problem, control, a, *, simulator=RK4(), execution=None) -> Linearization:
    """Linearize the dynamics along the trajectory of the parameters `a`.

    The reference is the RK4 solution on the simulator's grid (the same arithmetic as
    `jt.simulate(problem, control, a, simulator=simulator)` at the step boundaries). A(t),
    B(t) are `jax.jacfwd` of `problem.dynamics` there; the discrete `Ad`, `Bd` (and the noise
    inputs `Gd`, `Ed`) are `jax.jacfwd` of one sampled RK4 step, i.e. of the map that
    `simulate_closed_loop` and `monte_carlo` iterate.

    **Arguments:**

    - `problem`, `control`, `a`: as in `jt.simulate` (typically `a = sol.params`).
    - `simulator`: keyword-only, `jt.RK4(steps)`: one control sample per RK4 step.
    - `execution`: keyword-only execution-error model for `Ed` (default: none, p = 0).

    **Returns:** a `Linearization`. Jit-compiled; usable under `jax.vmap` over `a`.
    Feed it to `tracking_lqr` (or to `continuous_lqr` / `discrete_lqr` directly).
    """
    a = check_inputs(problem, control, a)
    _check_simulator_rk4(simulator)
    execution = _check_execution(execution, problem)
    p = execution.num_noise(problem.num_controls)
    return _linearize(problem, control, a, execution, p, simulator.steps)


@eqx.filter_jit
def _linearize(problem, control, a, execution, p, steps):
    grid, x = _noise_free(problem, control, a, steps)
    rows, h = grid.theta[:, :-2], grid.theta[:, -1]
    u = jax.vmap(control.local_control)(rows, h, grid.tau)
    u = jnp.concatenate([u, control.local_control(rows[-1], h[-1], 1.0)[None]])
    u = _bounded(problem, u)
    jac = jax.jacfwd(problem.dynamics, argnums=(1, 2))
    A, B = jax.vmap(lambda t, x, u: jac(t, x, u, problem.args))(grid.t, x, u)

    n, m = problem.num_states, problem.num_controls

    def step(theta, tau, x, du, xi, w):
        return _sample_step(problem, control, execution, grid.dtau, theta, tau, x, du, xi, w)

    N = grid.tau.shape[0]
    Ad, Bd, Ed, Gd = jax.vmap(jax.jacfwd(step, argnums=(2, 3, 4, 5)))(
        grid.theta, grid.tau, x[:-1], jnp.zeros((N, m)), jnp.zeros((N, p)), jnp.zeros((N, n))
    )
    status = simulation_status(jnp.array(True), x, A, B)
    return Linearization(t=grid.t, x=x, u=u, A=A, B=B, Ad=Ad, Bd=Bd, Gd=Gd, Ed=Ed, dt=grid.dt, status=status)


def bryson_weights(lin: Linearization, state_scale, control_scale, terminal_scale):
    """LQR weights by Bryson's rule for the cost int (dx^T Q dx + du^T R du) dt
    + dx(tf)^T Qf dx(tf) of `tracking_lqr`: each term is about 1 when a deviation stays at its
    acceptable size over [0, tf],

        Q = diag(1 / (tf state_scale^2)),  R = diag(1 / (tf control_scale^2)),
        Qf = diag(1 / terminal_scale^2),

    with tf = `lin.t[-1]`. The scales are scalars or per-component vectors (`(n,)`, `(m,)`,
    `(n,)`). **Returns:** `(Q, R, Qf)`."""
    n, m = lin.B.shape[1:]
    tf = lin.t[-1]

    def diag(name, scale, k):
        scale = _f64(scale)
        _check(name, scale.shape, (), (k,))
        return jnp.diag(jnp.broadcast_to(1.0 / scale**2, (k,)))

    return (
        diag("state_scale", state_scale, n) / tf,
        diag("control_scale", control_scale, m) / tf,
        diag("terminal_scale", terminal_scale, n),
    )


def tracking_lqr(lin: Linearization, Q, R, Qf, *, discrete=True, multiplicative=None, **kwargs):
    """The LQR tracking law around a linearized trajectory, u = u_ref - K (x - x_ref), for the
    cost int (dx^T Q dx + du^T R du) dt + dx(tf)^T Qf dx(tf).

    - `discrete=True` (default): `discrete_lqr` on the sampled-data model (`lin.Ad`,
      `lin.Bd`) with per-sample weights Q dt_k, R dt_k (rectangle rule): the gains of the
      sampled controller that `monte_carlo` simulates. `multiplicative` is passed on (seed eq.
      2.19). **Returns:** `DiscreteLQRGains` (one gain per sample).
    - `discrete=False`: `continuous_lqr` on `lin.A_fn`, `lin.B_fn` over [0, tf], sampled at
      `lin.t`, stepping to every sample time (`step_ts`, where the interpolated A, B have
      kinks); other keyword arguments are passed on. **Returns:** `LQRGains`.

    `Q`, `Qf`: `(n, n)` PSD; `R`: `(m, m)` positive definite.
    """
    n, m = lin.B.shape[1:]
    Q, R, Qf = _f64(Q), _f64(R), _f64(Qf)
    _check("Q", Q.shape, (n, n))
    _check("R", R.shape, (m, m))
    _check("Qf", Qf.shape, (n, n))
    if discrete:
        if kwargs:
            raise ValueError(f"unexpected keyword(s) {sorted(kwargs)} for discrete=True.")
        dt = lin.dt[:, None, None]
        return discrete_lqr(lin.Ad, lin.Bd, Q[None] * dt, R[None] * dt, Qf, multiplicative=multiplicative)
    if multiplicative is not None:
        raise ValueError("`multiplicative` needs discrete=True (seed eq. 2.19).")
    kwargs = {"step_ts": lin.t, "max_steps": 8 * lin.t.shape[0] + 4096, **kwargs}
    return continuous_lqr(lin.A_fn, lin.B_fn, Q, R, Qf, lin.t[0], lin.t[-1], ts=lin.t, **kwargs)


# ---------------------------------------------------------------------------------------------
# Closed-loop simulation and Monte Carlo
# ---------------------------------------------------------------------------------------------


def _psd_sqrt(name, M, n):
    """A square root L (L L^T = M) of a symmetric PSD `(n, n)` matrix, by eigh (M may be
    singular)."""
    if M is None:
        return None
    M = _f64(M)
    _check(name, M.shape, (n, n))
    w, V = jnp.linalg.eigh(_sym(M))
    if not isinstance(M, jax.core.Tracer):
        scale = max(float(jnp.max(jnp.abs(M))), 1e-300)
        if float(jnp.max(jnp.abs(M - M.T))) > 1e-12 * scale or float(jnp.min(w)) < -1e-12 * scale:
            raise ValueError(f"`{name}` must be a symmetric positive semidefinite matrix.")
    return V * jnp.sqrt(jnp.maximum(w, 0.0))[None, :]


def _noise_model(problem, execution, process_noise, initial_covariance, correlation_time):
    execution = _check_execution(execution, problem)
    c = _f64(correlation_time)
    if c.ndim != 0:
        raise ValueError(f"`correlation_time` must be a scalar; got shape {c.shape}.")
    if not isinstance(c, jax.core.Tracer) and not bool(c >= 0):
        raise ValueError(f"`correlation_time` must be >= 0 (0: white, inf: bias); got {float(c)}.")
    n = problem.num_states
    return _Noise(
        execution=execution,
        num_xi=execution.num_noise(problem.num_controls),
        correlation_time=c,
        Lw=_psd_sqrt("process_noise", process_noise, n),
        L0=_psd_sqrt("initial_covariance", initial_covariance, n),
    )


def _as_key(key):
    if isinstance(key, int) and not isinstance(key, bool):
        return jax.random.key(key)
    return key


class ClosedLoopTrajectory(eqx.Module):
    """One closed-loop run on the control-sample grid.

    - `t` `(N + 1,)` sample times; `x` `(N + 1, n)` states; `x_ref` `(N + 1, n)` reference.
    - `u` `(N, m)`: commanded control at the start of each sample, u_ref(t_k) + du_k (before
      execution errors; the feedforward u_ref(t) itself varies inside the sample).
    - `du` `(N, m)`: feedback corrections -K_k (x_k - x_ref_k).
    - `xf` `(n,)`: x(tf); `status`: `Status.NONFINITE` if the run blew up.
    """

    t: jax.Array
    x: jax.Array
    x_ref: jax.Array
    u: jax.Array
    du: jax.Array
    xf: jax.Array
    status: Status


def simulate_closed_loop(
    problem,
    control,
    a,
    key=None,
    *,
    gains=None,
    execution=None,
    process_noise=None,
    initial_covariance=None,
    correlation_time=0.0,
    simulator=RK4(),
) -> ClosedLoopTrajectory:
    """One run of u = u_ref(t) - K_k (x_k - x_ref_k) with noise; see `monte_carlo` for the
    model and the arguments. `key=None` runs without noise. Pure and jit-compiled; vmap it
    over keys for a batch (or use `monte_carlo`)."""
    a = check_inputs(problem, control, a)
    _check_simulator_rk4(simulator)
    N, n, m = control.num_segments * simulator.steps, problem.num_states, problem.num_controls
    gains = _check_gains(gains, N, m, n)
    noise = _noise_model(problem, execution, process_noise, initial_covariance, correlation_time)
    return _closed_loop(problem, control, a, _as_key(key), gains, noise, simulator.steps)


@eqx.filter_jit
def _closed_loop(problem, control, a, key, gains, noise, steps):
    grid, x_ref = _noise_free(problem, control, a, steps)
    K = _gain_sequence(gains, grid.t)
    x0, xf, xs, du, _ = _rollout(problem, control, noise, grid, x_ref[:-1], K, key, True)
    rows, h = grid.theta[:, :-2], grid.theta[:, -1]
    u = _bounded(problem, jax.vmap(control.local_control)(rows, h, grid.tau) + du)
    return ClosedLoopTrajectory(
        t=grid.t,
        x=jnp.concatenate([x0[None], xs]),
        x_ref=x_ref,
        u=u,
        du=du,
        xf=xf,
        status=simulation_status(jnp.array(True), xf),
    )


class Dispersion(eqx.Module):
    """Dispersion of the states over the runs at T band times (the sample times, every
    `dispersion_stride`-th, and tf).

    `t` `(T,)`; `reference`, `mean`, `std` `(T, n)`; `percentiles` `(P, T, n)` at the levels
    `levels` `(P,)` (in percent). Runs that blew up are left out.
    """

    t: jax.Array
    reference: jax.Array
    mean: jax.Array
    std: jax.Array
    percentiles: jax.Array
    levels: jax.Array


class MonteCarloResult(eqx.Module):
    """Terminal statistics of `monte_carlo` runs.

    Per run (leading axis = the runs, in the order of their keys):

    - `final_states` `(runs, n)`: x(tf) at the nominal tf;
    - `terminal_errors` `(runs, l)`: E = M(tf, x(tf)) (`problem.terminal`), 0 = on target;
    - `correction_rms` `(runs, m)`: root mean square over [0, tf] of the feedback correction
      du (zeros in open loop);
    - `finite` `(runs,)`: False for a run whose final state or E is not finite.

    Statistics over the finite runs (`num_failed` = the others): `terminal_mean` `(l,)`,
    `terminal_covariance` `(l, l)` (unbiased), `terminal_std` `(l,)`, `terminal_percentiles`
    `(P, l)` at `levels` (percent); `state_mean` `(n,)`, `state_covariance` `(n, n)` of
    x(tf). `reference_final_state`, `reference_terminal`: the noise-free run. `tf`: the
    nominal final time. `dispersion`: a `Dispersion` if `return_trajectories=True`, else None.
    """

    tf: jax.Array
    reference_final_state: jax.Array
    reference_terminal: jax.Array
    final_states: jax.Array
    terminal_errors: jax.Array
    correction_rms: jax.Array
    finite: jax.Array
    num_failed: jax.Array
    terminal_mean: jax.Array
    terminal_covariance: jax.Array
    terminal_std: jax.Array
    terminal_percentiles: jax.Array
    state_mean: jax.Array
    state_covariance: jax.Array
    levels: jax.Array
    dispersion: Dispersion | None


def monte_carlo(
    problem,
    control,
    a,
    key,
    n: int,
    *,
    gains=None,
    sigma_thrust=0.0,
    sigma_pointing_deg=0.0,
    execution=None,
    process_noise=None,
    initial_covariance=None,
    correlation_time=0.0,
    percentiles=(2.5, 16.0, 50.0, 84.0, 97.5),
    return_trajectories: bool = False,
    dispersion_stride: int = 1,
    simulator=RK4(),
) -> MonteCarloResult:
    """Statistical simulation of the open or closed loop around the trajectory of `a` (how
    seed 001 §2 estimates the terminal accuracy of a synthesized control): `n` noisy runs in
    one jitted, vmapped call.

    **Model.** One control sample = one step of `simulator` (`jt.RK4(steps)`, the default
    100 steps per segment; case-5 Earth-Mars: 700 samples of ~0.8 day). On sample k,
    [t_k, t_{k+1}], one classical RK4 step integrates

        x' = f(t, x, u_actual, args_actual) + w_k,
        (u_actual, args_actual) = execution(t, u_ref(t) + du_k, xi_k, args),
        du_k = -K_k (x_k - x_ref_k)       (0 in open loop),

    with the feedforward u_ref(t) evaluated at every RK4 stage and du_k, xi_k, w_k held
    constant over the sample (a sampled-data controller with zero-order hold, which measures
    the full state at t_k). The commanded control is clipped to the problem's control bounds,
    if any. The runs end at the nominal tf (also for free-final-time problems).

    - Execution noise xi_k ~ N(0, I): white across samples (`correlation_time=0`), or the
      stationary first-order Gauss-Markov sequence xi_k = phi_k xi_{k-1} +
      sqrt(1 - phi_k^2) eta_k, phi_k = exp(-dt_k / correlation_time); `inf` is a constant
      bias per run.
    - Process noise: w_k ~ N(0, W / dt_k), white, so its effect over one sample has covariance
      ~ W dt_k: the discretization of white noise of intensity W on dx/dt.
    - Initial state x0 ~ N(problem.x0, initial_covariance) (optional).
    - Reference x_ref: the same sampled run without noise (the arithmetic of `jt.simulate`'s
      RK4 solution; bit for bit on CPU), so a noise-free closed loop reproduces it exactly.

    **Randomness.** Run i uses `jax.random.fold_in(key, i)`: results are reproducible, and the
    first runs of a larger study are the same runs.

    **Arguments:**

    - `problem`, `control`, `a`: the nominal (typically `a = sol.params`).
    - `key`: a JAX PRNG key (or an int seed); `n`: number of runs (static; >= 2).
    - `gains`: None (open loop), `LQRGains` (K(t_k) at the sample times), `DiscreteLQRGains`
      or an array `(N, m, n)` with one gain per sample (see `tracking_lqr`).
    - `sigma_thrust`, `sigma_pointing_deg`: shorthand for
      `execution=ThrustErrors(sigma_thrust, sigma_pointing_deg)` (relative thrust-magnitude
      error and pointing error in degrees, 1 sigma; the thrust magnitude is
      `problem.args["thrust"]`, the angle `u[0]`). With `sigma_thrust=0` the pointing error
      needs no thrust entry.
    - `execution`: an `AbstractExecutionErrors` (`ThrustErrors`, `ControlErrors`,
      `ExecutionErrors`); not together with the shorthand.
    - `process_noise`: W `(n, n)` PSD, the intensity of white noise on dx/dt.
    - `initial_covariance`: `(n, n)` PSD.
    - `correlation_time`: of the execution noise (0: white per sample; `jnp.inf`: bias).
    - `percentiles`: levels in percent for the statistics.
    - `return_trajectories`: also return `Dispersion` bands (keeps all `n` trajectories in
      memory inside the call: n (N + 1) n_x float64).
    - `dispersion_stride`: bands on every `dispersion_stride`-th sample time (and tf); the
      percentiles are a sort over the runs at each band time, the costliest part of the call
      with bands (e.g. 7 on 700 samples: 101 band times).
    - `simulator`: `jt.RK4(steps)`; it sets the sample rate.

    **Returns:** `MonteCarloResult`.
    """
    a = check_inputs(problem, control, a)
    _check_simulator_rk4(simulator)
    if not (isinstance(n, int) and not isinstance(n, bool) and n >= 2):
        raise ValueError(f"`n` must be an int >= 2; got {n!r}.")
    shorthand = [not (isinstance(s, int | float) and s == 0) for s in (sigma_thrust, sigma_pointing_deg)]
    if any(shorthand):
        if execution is not None:
            raise ValueError("pass either `execution` or `sigma_thrust` / `sigma_pointing_deg`, not both.")
        execution = ThrustErrors(sigma_thrust, sigma_pointing_deg, thrust_key="thrust" if shorthand[0] else None)
    N, nx, m = control.num_segments * simulator.steps, problem.num_states, problem.num_controls
    gains = _check_gains(gains, N, m, nx)
    noise = _noise_model(problem, execution, process_noise, initial_covariance, correlation_time)
    levels = _f64(percentiles)
    if levels.ndim != 1 or not bool(jnp.all((levels >= 0) & (levels <= 100))):
        raise ValueError(f"`percentiles` must be a 1-d sequence in [0, 100]; got {percentiles!r}.")
    if not (isinstance(dispersion_stride, int) and dispersion_stride >= 1):
        raise ValueError(f"`dispersion_stride` must be an int >= 1; got {dispersion_stride!r}.")
    return _monte_carlo(
        problem,
        control,
        a,
        _as_key(key),
        n,
        gains,
        noise,
        simulator.steps,
        levels,
        dispersion_stride if return_trajectories else 0,
    )


def _masked_stats(values, finite, levels):
    """Mean, unbiased covariance and percentiles over the leading axis of `values` `(R, d)`,
    leaving out the rows where `finite` is False."""
    count = jnp.sum(finite)
    keep = finite[:, None]
    mean = jnp.sum(jnp.where(keep, values, 0.0), axis=0) / count
    d = jnp.where(keep, values - mean[None], 0.0)
    cov = _sym(d.T @ d / (count - 1))
    pct = jnp.nanpercentile(jnp.where(keep, values, jnp.nan), levels, axis=0)
    return mean, cov, pct


@eqx.filter_jit
def _monte_carlo(problem, control, a, key, n, gains, noise, steps, levels, stride):
    """`stride` (static): 0 = no dispersion bands, else bands every `stride` samples."""
    save = stride > 0
    grid, x_ref = _noise_free(problem, control, a, steps)
    K = _gain_sequence(gains, grid.t)
    tf = grid.t[-1]

    def run(i):
        x0, xf, xs, _, du2 = _rollout(problem, control, noise, grid, x_ref[:-1], K, jax.random.fold_in(key, i), save)
        return xf, (jnp.concatenate([x0[None], xs]) if save else None), du2

    xfs, xs, du2 = jax.vmap(run)(jnp.arange(n))
    E = jax.vmap(lambda xf: problem.terminal(tf, xf, problem.args))(xfs)
    finite = jnp.all(jnp.isfinite(xfs), axis=1) & jnp.all(jnp.isfinite(E), axis=1)
    E_mean, E_cov, E_pct = _masked_stats(E, finite, levels)
    x_mean, x_cov, _ = _masked_stats(xfs, finite, levels[:0])
    dispersion = None
    if save:
        N = grid.tau.shape[0]
        idx = np.unique(np.append(np.arange(0, N + 1, stride), N))
        xs = jnp.where(finite[:, None, None], xs[:, idx], jnp.nan)
        dispersion = Dispersion(
            t=grid.t[idx],
            reference=x_ref[idx],
            mean=jnp.nanmean(xs, axis=0),
            std=jnp.nanstd(xs, axis=0, ddof=1),
            percentiles=jnp.nanpercentile(xs, levels, axis=0),
            levels=levels,
        )
    return MonteCarloResult(
        tf=tf,
        reference_final_state=x_ref[-1],
        reference_terminal=problem.terminal(tf, x_ref[-1], problem.args),
        final_states=xfs,
        terminal_errors=E,
        correction_rms=jnp.sqrt(du2 / tf),
        finite=finite,
        num_failed=n - jnp.sum(finite),
        terminal_mean=E_mean,
        terminal_covariance=E_cov,
        terminal_std=jnp.sqrt(jnp.diag(E_cov)),
        terminal_percentiles=E_pct,
        state_mean=x_mean,
        state_covariance=x_cov,
        levels=levels,
        dispersion=dispersion,
    )
