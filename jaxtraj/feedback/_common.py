"""Shared helpers of the feedback modules: float64 arrays, shape checks, interpolation."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float64

FORWARD = diffrax.ForwardMode()  # default adjoint of the continuous solves


def symmetrize(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def shape_of(x, t=None):
    """Shape of an array, or of a callable's output at time t (without running it)."""
    return jax.eval_shape(x, t).shape if callable(x) else np.shape(x)


def check_shape(name, shape, *allowed):
    if tuple(shape) not in [tuple(a) for a in allowed]:
        want = " or ".join(str(tuple(a)) for a in allowed)
        raise ValueError(f"`{name}` must have shape {want}; got {tuple(shape)}.")


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
