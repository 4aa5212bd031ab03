"""Shared helpers of the feedback modules: float64 arrays, shape checks, interpolation."""

import diffrax
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .._checks import as_float64

FORWARD = diffrax.ForwardMode()  # default adjoint of the continuous solves


def symmetrize(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def shape_of(x, t=None):
    """Shape of an array, or of a callable's output at time t (without running it)."""
    return jax.eval_shape(x, t).shape if callable(x) else np.shape(x)


def numbers(name, x):
    """`x` as a float64 array, or a ValueError naming `name` (None or text gave JAX's message,
    which names no argument)."""
    try:
        return as_float64(x)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be an array of numbers; got {x!r}.") from None


def check_shape(name, shape, *allowed):
    if tuple(shape) not in [tuple(a) for a in allowed]:
        want = " or ".join(str(tuple(a)) for a in allowed)
        raise ValueError(f"`{name}` must have shape {want}; got {tuple(shape)}.")


def check_weight(name, M, definite=False):
    """A cost weight (concrete; a traced one is left to the caller): finite, symmetric and
    positive semidefinite (`definite`: positive definite), within round-off of its norm."""
    if isinstance(M, jax.core.Tracer):
        return
    M = np.asarray(M)
    if not np.all(np.isfinite(M)):
        raise ValueError(f"`{name}` must be finite; got {M}.")
    scale = max(float(np.max(np.abs(M), initial=0.0)), 1e-300)
    if np.max(np.abs(M - M.T), initial=0.0) > 1e-12 * scale:
        raise ValueError(f"`{name}` must be symmetric; got {M}.")
    least = float(np.min(np.linalg.eigvalsh(M), initial=np.inf))
    if (least <= 0.0) if definite else (least < -1e-12 * scale):
        kind = "positive definite" if definite else "positive semidefinite"
        raise ValueError(f"`{name}` must be {kind}; its least eigenvalue is {least:.3g}.")


def per_step(name, x, N, shape):
    """Broadcast a constant `shape` array, or check an `(N, *shape)` sequence."""
    x = as_float64(x)
    check_shape(name, x.shape, shape, (N, *shape))
    return jnp.broadcast_to(x, (N, *shape))


def interp_rows(ts, ys, t):
    """Piecewise-linear interpolation of `ys` (leading axis on increasing `ts`), clamped at the
    ends."""
    i = jnp.clip(jnp.searchsorted(ts, t, side="right") - 1, 0, ts.shape[0] - 2)
    w = jnp.clip((t - ts[i]) / (ts[i + 1] - ts[i]), 0.0, 1.0)
    return ys[i] + w * (ys[i + 1] - ys[i])
