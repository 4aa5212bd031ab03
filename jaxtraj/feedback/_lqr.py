"""The linear-quadratic core: continuous and discrete (stochastic) LQR, zero-order hold,
covariance propagation."""

from collections.abc import Callable
from typing import cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax

from .._checks import as_float64
from ._common import FORWARD, check_shape, interp_rows, per_step, shape_of, symmetrize


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
        return interp_rows(self.ts, self.K, t)

    def riccati(self, t):
        """S(t) by linear interpolation between samples."""
        return interp_rows(self.ts, self.S, t)

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


def _at(x, t):
    return as_float64(x(t)) if callable(x) else x


class _RiccatiField(eqx.Module):
    """Right-hand side of (S, c)' for diffrax. A Module (rather than a closure) so that
    repeated calls with the same callables and array shapes reuse diffrax's compiled solve."""

    A_fn: Callable
    B_fn: Callable
    Q: Callable | jax.Array
    R: Callable | jax.Array
    W: Callable | jax.Array

    def gain(self, t, S):
        return jsl.solve(symmetrize(_at(self.R, t)), _at(self.B_fn, t).T @ S, assume_a="pos")

    def __call__(self, t, y, args):
        S = symmetrize(y[0])
        A, B = _at(self.A_fn, t), _at(self.B_fn, t)
        AS = A.T @ S
        dS = -(AS + AS.T - S @ B @ self.gain(t, S) + _at(self.Q, t))
        return symmetrize(dS), -jnp.trace(S @ _at(self.W, t))


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
    adjoint: diffrax.AbstractAdjoint = FORWARD,
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
    n = shape_of(A_fn, t0)
    if len(n) != 2 or n[0] != n[1]:
        raise ValueError(f"`A_fn` must return a square (n, n) matrix; got shape {tuple(n)}.")
    n = n[0]
    bs = shape_of(B_fn, t0)
    if len(bs) != 2 or bs[0] != n:
        raise ValueError(f"`B_fn` must return shape ({n}, m); got {tuple(bs)}.")
    m = bs[1]
    check_shape("Q", shape_of(Q, t0), (n, n))
    check_shape("R", shape_of(R, t0), (m, m))
    check_shape("Qf", shape_of(Qf, t0), (n, n))
    if noise is not None:
        check_shape("noise", shape_of(noise, t0), (n, n))
    t0, tf = as_float64(t0), as_float64(tf)
    ts = jnp.linspace(t0, tf, 101) if ts is None else as_float64(ts)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-d array of at least 2 times; got shape {ts.shape}.")
    cast = lambda x: x if callable(x) else as_float64(x)
    W = jnp.zeros((n, n)) if noise is None else noise
    field = _RiccatiField(A_fn, B_fn, cast(Q), cast(R), cast(W))
    step_ts = None if step_ts is None else as_float64(step_ts)
    return _continuous_riccati(field, as_float64(Qf), t0, tf, ts, rtol, atol, max_steps, adjoint, step_ts)


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
        y0=(symmetrize(Qf), jnp.zeros((), jnp.float64)),
        saveat=diffrax.SaveAt(ts=ts[::-1]),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
    )
    ys = cast(tuple[jax.Array, jax.Array], sol.ys)  # (not None: `saveat` asks for the states at `ts`)
    S = symmetrize(ys[0][::-1])
    K = jax.vmap(field.gain)(ts, S)
    return LQRGains(ts=ts, S=S, K=K, c=ys[1][::-1])


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
    As, Bs = as_float64(As), as_float64(Bs)
    if As.ndim != 3 or As.shape[1] != As.shape[2]:
        raise ValueError(f"`As` must have shape (N, n, n); got {As.shape}.")
    N, n = As.shape[:2]
    if Bs.ndim != 3 or Bs.shape[:2] != (N, n):
        raise ValueError(f"`Bs` must have shape ({N}, {n}, m); got {Bs.shape}.")
    m = Bs.shape[2]
    Qs = per_step("Q", Q, N, (n, n))
    Rs = per_step("R", R, N, (m, m))
    Qf = as_float64(Qf)
    check_shape("Qf", Qf.shape, (n, n))
    Ws = per_step("additive", jnp.zeros((n, n)) if additive is None else additive, N, (n, n))
    mult = as_float64(0.0 if multiplicative is None else multiplicative)
    if mult.ndim <= 1:
        sig2, Ds = per_step("multiplicative", mult, N, ()), jnp.zeros((N, 0, n, m))
    elif mult.ndim in (3, 4):
        p = mult.shape[-3]
        sig2, Ds = jnp.zeros((N,)), per_step("multiplicative", mult, N, (p, n, m))
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
        K = jsl.solve(symmetrize(R + BSB + M), B.T @ S @ A, assume_a="pos")
        F = A - B @ K
        S_new = symmetrize(Q + K.T @ (R + M) @ K + F.T @ S @ F)
        c_new = c + jnp.trace(S @ W)
        return (S_new, c_new), (K, S_new, c_new)

    init = (symmetrize(Qf), jnp.zeros((), jnp.float64))
    _, (K, S, c) = lax.scan(step, init, (As, Bs, Qs, Rs, sig2, Ds, Ws), reverse=True)
    S, c = jnp.concatenate([S, init[0][None]]), jnp.concatenate([c, init[1][None]])
    return DiscreteLQRGains(K=K, S=S, c=c)


def zoh_discretize(A, B, dt):
    """Zero-order-hold discretization of x' = A x + B u over a step dt:

        Ad = e^{A dt},  Bd = int_0^dt e^{A s} ds B,  from  expm([[A, B], [0, 0]] dt).

    (The cost weights of the matching discrete problem are Q dt, R dt to first order, which is
    how the discrete recursion approximates seed eq. 1.44, cf. the discretization 1.27-1.30.)
    For a time-varying sequence, `jax.vmap(zoh_discretize, (0, 0, None))`.

    **Returns:** `(Ad, Bd)`, shapes `(n, n)`, `(n, m)`.
    """
    A, B, dt = as_float64(A), as_float64(B), as_float64(dt)
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
    P0, Fs = as_float64(P0), as_float64(Fs)
    if Fs.ndim != 3 or Fs.shape[1] != Fs.shape[2]:
        raise ValueError(f"`Fs` must have shape (N, n, n); got {Fs.shape}.")
    N, n = Fs.shape[:2]
    check_shape("P0", P0.shape, (n, n))
    G = jnp.eye(n) if G is None else as_float64(G)
    q = G.shape[-1]
    Gs = per_step("G", G, N, (n, q))
    Ws = per_step("W", W, N, (q, q))

    return _propagate(symmetrize(P0), Fs, Gs, Ws)


@jax.jit
def _propagate(P0, Fs, Gs, Ws):
    def step(P, x):
        F, G, W = x
        P = symmetrize(F @ P @ F.T + G @ W @ G.T)
        return P, P

    return jnp.concatenate([P0[None], lax.scan(step, P0, (Fs, Gs, Ws))[1]])


class _LyapunovField(eqx.Module):
    F_fn: Callable
    W: Callable | jax.Array

    def __call__(self, t, P, args):
        FP = _at(self.F_fn, t) @ P
        return symmetrize(FP + FP.T + _at(self.W, t))


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
    adjoint: diffrax.AbstractAdjoint = FORWARD,
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
    P0, fs = as_float64(P0), shape_of(F_fn, t0)
    if len(fs) != 2 or fs[0] != fs[1]:
        raise ValueError(f"`F_fn` must return a square (n, n) matrix; got shape {tuple(fs)}.")
    check_shape("P0", P0.shape, fs)
    check_shape("W", shape_of(W, t0), fs)
    t0, tf = as_float64(t0), as_float64(tf)
    ts = jnp.linspace(t0, tf, 101) if ts is None else as_float64(ts)
    field = _LyapunovField(F_fn, W if callable(W) else as_float64(W))
    return ts, _lyapunov(field, symmetrize(P0), t0, tf, ts, rtol, atol, max_steps, adjoint)


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
    return symmetrize(sol.ys)
