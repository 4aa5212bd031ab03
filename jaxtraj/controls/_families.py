"""The control families: piecewise linear, parabolic and constant, saturated splines."""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._base import AbstractControl


def _knots_or_final_time(free_times):
    return "knots" if free_times else "final_time"


def _values_but_times(control):
    """Every entry but the times is a control value; values come in groups of one per channel."""
    idx = tuple(i for i in range(control.num_params) if i not in set(control.time_indices))
    return idx, tuple(r % control.channels for r in range(len(idx)))


def _times(tf, K):
    """The K + 1 equally spaced times from 0 to `tf` (inf past float64's range: such a start
    is refused as a non-finite `a`, with the argument's name, not as NumPy's warning)."""
    with np.errstate(over="ignore"):
        return tf * np.arange(K + 1) / K


def _channel_line(tf, u_start, u_end, t, q):
    """The straight line at the times `t`, shape `(len(t), q)`; `u_start`, `u_end`: a number
    or one per channel."""
    try:
        us, ue = (np.broadcast_to(np.asarray(v, dtype=np.float64), (q,)) for v in (u_start, u_end))
    except (TypeError, ValueError):  # (NumPy's conversion or broadcast message named neither)
        us = ue = np.full(q, np.nan)
    if not (np.all(np.isfinite(us)) and np.all(np.isfinite(ue))):
        raise ValueError(
            f"`u_start` and `u_end` must each be a finite number or {q} (one per channel); got {u_start!r}, {u_end!r}."
        )
    with np.errstate(over="ignore", invalid="ignore"):  # (inf times: see `_times`)
        return _line(tf, us[None], ue[None], np.asarray(t)[:, None])


def _check_segments(segments, name="segments"):
    # (< 2**31: the solvers' loops count in int32)
    if not (isinstance(segments, int) and not isinstance(segments, bool) and 1 <= segments < 2**31):
        raise ValueError(f"`{name}` must be an int >= 1 and < 2**31; got {segments!r}.")


def _check_flag(name, value):
    """A family's True/False setting is a bool (a text "no" was taken as True)."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"`{name}` must be True or False; got {value!r}.")


def _flag(value):
    """A NumPy bool as a Python bool (an array leaf, it was traced under jit: JAX's error)."""
    return bool(value) if isinstance(value, np.bool_) else value


def _check_flags(family, *names):
    for name in names:
        _check_flag(name, getattr(family, name))


def _line(tf, u_start, u_end, t):
    return u_start + (u_end - u_start) * t / tf


def _check_guess(tf):
    try:  # (a text, None or an array gave NumPy's messages, naming no argument)
        ok = not isinstance(tf, str | bool) and np.ndim(tf) == 0 and bool(np.isfinite(tf) and tf > 0)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"`tf` must be a finite number > 0; got {tf!r}.")


class PiecewiseLinear(AbstractControl):
    """Straight-line segments.

    Layouts of `a` (K = `segments`; with `channels` = q > 1 each value u is q consecutive
    entries, one per channel, e.g. `[u_0^1, ..., u_0^q, u_1^1, ...]`):

    - `continuous=True, free_times=False` (thesis tests 4, 5, sec. 5.3.2):
      `[u_0, ..., u_K, tf]`, node t_j = j tf / K.
    - `continuous=True, free_times=True`: `[u_0, ..., u_K, t_1, ..., t_{K-1}, tf]`.
    - `continuous=False, free_times=True` (thesis tests 1, 2, sec. 5.3.3): per segment
      `[u_start, u_end, t_end]`; the last t_end is tf.
    - `continuous=False, free_times=False`: per segment `[u_start, u_end]`, then `tf`.
    """

    segments: int
    continuous: bool = eqx.field(default=True, converter=_flag)
    free_times: bool = eqx.field(default=False, converter=_flag)
    channels: int = 1
    affine: ClassVar[bool] = True
    value_bounds_exact: ClassVar[bool] = True

    def __check_init__(self):
        _check_segments(self.segments)
        _check_segments(self.channels, "channels")
        _check_flags(self, "continuous", "free_times")

    @property
    def num_controls(self):
        return self.channels

    @property
    def time_layout(self):
        return _knots_or_final_time(self.free_times)

    @property
    def value_indices(self):
        return _values_but_times(self)

    @property
    def num_segments(self):
        return self.segments

    @property
    def num_params(self):
        K, q = self.segments, self.channels
        if self.continuous:
            return (K + 1) * q + (K - 1 if self.free_times else 0) + 1
        return K * (2 * q + 1) if self.free_times else 2 * K * q + 1

    @property
    def time_indices(self):
        K, q = self.segments, self.channels
        if self.continuous:
            return tuple(range((K + 1) * q, self.num_params))
        if self.free_times:
            return tuple((2 * q + 1) * k + 2 * q for k in range(K))
        return (2 * K * q,)

    def _unpack(self, a):
        K, q = self.segments, self.channels
        if self.continuous:
            u = a[: (K + 1) * q].reshape(K + 1, q)
            ends = jnp.concatenate([u[:-1], u[1:]], axis=1)
            if self.free_times:
                inner = a[(K + 1) * q : (K + 1) * q + K - 1]
                knots = jnp.concatenate([jnp.zeros(1, a.dtype), inner, a[-1:]])
            else:
                knots = a[-1] * jnp.arange(K + 1, dtype=a.dtype) / K
            return ends, knots
        if self.free_times:
            blocks = a.reshape(K, 2 * q + 1)
            return blocks[:, : 2 * q], jnp.concatenate([jnp.zeros(1, a.dtype), blocks[:, 2 * q]])
        ends = a[: 2 * K * q].reshape(K, 2 * q)
        return ends, a[-1] * jnp.arange(K + 1, dtype=a.dtype) / K

    def knots(self, a):
        return self._unpack(a)[1]

    def segment_table(self, a):
        """Row k = [u_start (q), u_end (q)] of segment k."""
        return self._unpack(a)[0]

    def local_control(self, row, h, tau):
        q = self.channels
        return row[:q] + (row[q:] - row[:q]) * tau

    def initial_guess(self, tf, u_start, u_end):
        """`u_start`, `u_end`: a number or one per channel."""
        _check_guess(tf)
        K = self.segments
        t = _times(tf, K)
        u = _channel_line(tf, u_start, u_end, t, self.channels)  # (K + 1, q)
        if self.continuous:
            parts = [u.reshape(-1)] + ([t[1:-1]] if self.free_times else []) + [[tf]]
            return jnp.asarray(np.concatenate(parts), dtype=jnp.float64)
        ends = np.concatenate([u[:-1], u[1:]], axis=1)
        if self.free_times:
            return jnp.asarray(np.concatenate([ends, t[1:, None]], axis=1).reshape(-1))
        return jnp.asarray(np.concatenate([ends.reshape(-1), [tf]]))

    def _check_values(self, a):
        if self.free_times:
            self._check_increasing(self.concrete_knots(a), "node times")


class PiecewiseParabolic(AbstractControl):
    """Parabolic arcs, possibly discontinuous at the nodes (thesis test 3, sec. 5.3.4).

    Per arc `[u_start, slope, u_end, t_end]` (`free_times=True`; the last t_end is tf) or
    `[u_start, slope, u_end]` followed by `tf` (`free_times=False`, equally spaced nodes).
    On arc k of duration h: u = u_start + slope h tau + (u_end - u_start - slope h) tau^2.
    With `channels` = q > 1, u_start, slope and u_end are q consecutive entries each.

    !!! note "OCR decision"
        The thesis's formula for the arc is garbled in the OCR. The second parameter of
        each arc is the *initial slope du/dt* of the arc: with it the published starting
        vector of test 3 (Table 5.5: a_2 = a_6 = 1.386 = 2.35619 / 1.7) reproduces the
        straight starting control u = 1.5 pi t / 3.4 exactly, as its initial constraint
        error (0.318669, the same as tests 1, 2, 4, 5) requires.
    """

    segments: int
    free_times: bool = eqx.field(default=True, converter=_flag)
    channels: int = 1
    affine: ClassVar[bool] = True

    def __check_init__(self):
        _check_segments(self.segments)
        _check_segments(self.channels, "channels")
        _check_flags(self, "free_times")

    @property
    def num_controls(self):
        return self.channels

    @property
    def time_layout(self):
        return _knots_or_final_time(self.free_times)

    @property
    def value_indices(self):
        """u_start and u_end of each arc (the slopes are not control values)."""
        q = self.channels
        stride = 3 * q + (1 if self.free_times else 0)
        offsets = [*range(q), *range(2 * q, 3 * q)]
        idx = tuple(stride * k + j for k in range(self.segments) for j in offsets)
        return idx, tuple(j % q for _ in range(self.segments) for j in offsets)

    @property
    def num_segments(self):
        return self.segments

    @property
    def num_params(self):
        K, q = self.segments, self.channels
        return K * (3 * q + 1) if self.free_times else 3 * K * q + 1

    @property
    def time_indices(self):
        K, q = self.segments, self.channels
        if self.free_times:
            return tuple((3 * q + 1) * k + 3 * q for k in range(K))
        return (3 * K * q,)

    def _unpack(self, a):
        K, q = self.segments, self.channels
        if self.free_times:
            blocks = a.reshape(K, 3 * q + 1)
            return blocks[:, : 3 * q], jnp.concatenate([jnp.zeros(1, a.dtype), blocks[:, 3 * q]])
        return a[: 3 * K * q].reshape(K, 3 * q), a[-1] * jnp.arange(K + 1, dtype=a.dtype) / K

    def knots(self, a):
        return self._unpack(a)[1]

    def segment_table(self, a):
        """Row k = [u_start (q), slope (q), u_end (q)] of arc k."""
        return self._unpack(a)[0]

    def local_control(self, row, h, tau):
        q = self.channels
        u0, slope, u1 = row[:q], row[q : 2 * q], row[2 * q :]
        return u0 + slope * h * tau + (u1 - u0 - slope * h) * tau**2

    def initial_guess(self, tf, u_start, u_end):
        """`u_start`, `u_end`: a number or one per channel."""
        _check_guess(tf)
        K, q = self.segments, self.channels
        t = _times(tf, K)
        u = _channel_line(tf, u_start, u_end, t, q)  # (K + 1, q)
        slope = np.broadcast_to((u[-1] - u[0]) / tf, (K, q))
        arcs = np.concatenate([u[:-1], slope, u[1:]], axis=1)
        if self.free_times:
            return jnp.asarray(np.concatenate([arcs, t[1:, None]], axis=1).reshape(-1))
        return jnp.asarray(np.concatenate([arcs.reshape(-1), [tf]]))

    def _check_values(self, a):
        if self.free_times:
            self._check_increasing(self.concrete_knots(a), "node times")


class PiecewiseConstant(AbstractControl):
    """Constant levels with (free) switch times (thesis tests 6, 7, sec. 5.3.5).

    Per piece `[level, t_end]` (`free_times=True`; the last t_end is tf), or
    `[level_1, ..., level_K, tf]` with equally spaced switches (`free_times=False`). With
    `channels` = q > 1 each level is q consecutive entries.
    """

    segments: int
    free_times: bool = eqx.field(default=True, converter=_flag)
    channels: int = 1
    affine: ClassVar[bool] = True
    value_bounds_exact: ClassVar[bool] = True

    def __check_init__(self):
        _check_segments(self.segments)
        _check_segments(self.channels, "channels")
        _check_flags(self, "free_times")

    @property
    def num_controls(self):
        return self.channels

    @property
    def time_layout(self):
        return _knots_or_final_time(self.free_times)

    @property
    def value_indices(self):
        return _values_but_times(self)

    @property
    def num_segments(self):
        return self.segments

    @property
    def num_params(self):
        K, q = self.segments, self.channels
        return K * (q + 1) if self.free_times else K * q + 1

    @property
    def time_indices(self):
        K, q = self.segments, self.channels
        if self.free_times:
            return tuple((q + 1) * k + q for k in range(K))
        return (K * q,)

    def _unpack(self, a):
        K, q = self.segments, self.channels
        if self.free_times:
            blocks = a.reshape(K, q + 1)
            return blocks[:, :q], jnp.concatenate([jnp.zeros(1, a.dtype), blocks[:, q]])
        return a[: K * q].reshape(K, q), a[-1] * jnp.arange(K + 1, dtype=a.dtype) / K

    def knots(self, a):
        return self._unpack(a)[1]

    def segment_table(self, a):
        """Row k = the levels (q) of piece k."""
        return self._unpack(a)[0]

    def local_control(self, row, h, tau):
        return row + 0.0 * tau

    def initial_guess(self, tf, u_start, u_end):
        """Levels = the straight line's value at each piece's midpoint (`u_start`, `u_end`: a
        number or one per channel)."""
        _check_guess(tf)
        K = self.segments
        t = _times(tf, K)
        levels = _channel_line(tf, u_start, u_end, 0.5 * (t[:-1] + t[1:]), self.channels)  # (K, q)
        if self.free_times:
            return jnp.asarray(np.concatenate([levels, t[1:, None]], axis=1).reshape(-1))
        return jnp.asarray(np.concatenate([levels.reshape(-1), [tf]]))

    def _check_values(self, a):
        if self.free_times:
            self._check_increasing(self.concrete_knots(a), "switch times")


def spline_kernel(t, degree: int):
    """The compact spline Sp*(t) of seed 003 (support [-1, 1]):

    2^(p-1) (1+t)^p on [-1, -1/2], 1 - 2^(p-1) |t|^p on [-1/2, 1/2], 2^(p-1) (1-t)^p on
    [1/2, 1]. Degree 0 is 1/2 on [-1, 1], degree 1 the hat function; for every degree the
    shifted copies sum to 1 (a partition of unity)."""
    c = 2.0 ** (degree - 1)
    at = jnp.abs(t)
    inner = 1.0 - c * at**degree
    outer = c * (1.0 - at) ** degree
    return jnp.where(at <= 0.5, inner, jnp.where(at <= 1.0, outer, 0.0))


class SaturatedSpline(AbstractControl):
    """Saturated spline expansion of seed 003 (eq. 6-8).

    The global rescaled time tau_g in [0, 1] is split into P = `segments` equal parts; part k
    is flown in physical duration h_k, so tf = sum h_k. Each control channel j is
    u_j = clip(g_j, lower_j, upper_j), g_j(tau_g) = sum_{i=0..P} c_i^j Sp*(tau_g P - i).
    On segment k only c_k and c_{k+1} are active: g = c_k Sp*(tau) + c_{k+1} Sp*(tau - 1).

    Layout (the seed's): `[h_1, ..., h_P, c_0^1, ..., c_P^1, ..., c_0^q, ..., c_P^q]` with
    `free_durations=True`; with `free_durations=False` the durations are equal and the
    first entry is tf: `[tf, c_0^1, ..., c_P^q]`.

    Where the clip is active, du/da = 0 (the derivative of `jnp.clip`), which is the
    saturation rule of seed 000 appendix A [A.31-A.34] for box bounds.

    !!! note
        For degree >= 1 the control has a kink where it enters or leaves saturation, in the
        middle of a segment. A fixed-step integrator that steps across the kink loses its
        order there (O(h) local error), so RK4 results and the forward/unit sensitivities
        agree only to O(h) on such trajectories; use more steps or `jt.Diffrax` (adaptive).
    """

    segments: int
    degree: int
    lower: jax.Array
    upper: jax.Array
    free_durations: bool = True
    # the limits as static data: whether the family saturates within a problem's bounds is
    # decided at trace time (`_bounds.py`), when `lower` and `upper` are traced
    _limits: tuple[tuple[float, ...], tuple[float, ...]] = eqx.field(static=True, default=((), ()), repr=False)
    affine: ClassVar[bool] = True  # the knots and coefficient rows (the clip acts inside local_control)
    value_bounds_exact: ClassVar[bool] = True  # the kernels are >= 0 and sum to 1

    def __init__(self, segments, degree, lower, upper, free_durations=True):
        _check_segments(segments)
        _check_flag("free_durations", free_durations)
        if not (isinstance(degree, int) and not isinstance(degree, bool) and 0 <= degree <= 3):
            raise ValueError(f"`degree` must be an int in 0..3; got {degree!r}.")
        try:  # (empty bounds made a family of no channels; bools were taken as 0 and 1)
            if np.asarray(lower).dtype == bool or np.asarray(upper).dtype == bool:
                raise TypeError
            lo = np.atleast_1d(np.asarray(lower, dtype=np.float64))
            hi = np.atleast_1d(np.asarray(upper, dtype=np.float64))
            if lo.size == 0 or hi.size == 0:
                raise ValueError
        except (TypeError, ValueError):
            raise ValueError(f"`lower`/`upper` must be numbers, one per channel; got {lower!r}, {upper!r}.") from None
        if lo.ndim != 1 or hi.ndim != 1:
            raise ValueError(f"`lower`/`upper` must be scalars or 1-D; got shapes {lo.shape}, {hi.shape}.")
        if lo.shape != hi.shape and 1 not in (lo.size, hi.size):
            raise ValueError(
                f"`lower`/`upper` must have one entry per channel each; got shapes {lo.shape}, {hi.shape}."
            )
        lo, hi = np.broadcast_arrays(lo, hi)
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo >= hi):
            raise ValueError(f"`lower` must be < `upper` component-wise; got lower={lo}, upper={hi}.")
        self.segments = segments
        self.degree = degree
        self.lower = jnp.asarray(lo.copy())
        self.upper = jnp.asarray(hi.copy())
        self._limits = (tuple(map(float, lo)), tuple(map(float, hi)))
        self.free_durations = _flag(free_durations)

    @property
    def num_segments(self):
        return self.segments

    @property
    def num_controls(self):
        return int(self.lower.shape[0])

    @property
    def time_layout(self):
        return "durations" if self.free_durations else "final_time"

    @property
    def value_indices(self):
        """The coefficients c_i^j: u_j = c_i^j at tau_g = i / P for degree >= 1 (within the limits)."""
        start, P = self._num_times, self.segments
        idx = tuple(range(start, self.num_params))
        return idx, tuple(j for j in range(self.num_controls) for _ in range(P + 1))

    @property
    def limits(self):
        return np.asarray(self._limits[0]), np.asarray(self._limits[1])

    @property
    def _num_times(self):
        return self.segments if self.free_durations else 1

    @property
    def num_params(self):
        return self._num_times + (self.segments + 1) * self.num_controls

    @property
    def time_indices(self):
        return tuple(range(self._num_times))

    def durations(self, a):
        P = self.segments
        if self.free_durations:
            return a[:P]
        return jnp.full(P, a[0] / P, dtype=a.dtype)

    def coefficients(self, a):
        """Spline coefficients, shape `(num_controls, segments + 1)`."""
        return a[self._num_times :].reshape(self.num_controls, self.segments + 1)

    def knots(self, a):
        return jnp.concatenate([jnp.zeros(1, a.dtype), jnp.cumsum(self.durations(a))])

    def segment_table(self, a):
        """Row k = [c_k^1..c_k^q, c_{k+1}^1..c_{k+1}^q]."""
        c = self.coefficients(a)
        return jnp.concatenate([c[:, :-1].T, c[:, 1:].T], axis=1)

    def local_control(self, row, h, tau):
        # On [0, 1], Sp*(tau) + Sp*(tau - 1) = 1, so g = c_{k+1} + (c_k - c_{k+1}) Sp*(tau),
        # written with one-sided polynomials (no |tau|, whose derivative at the knots would be 0).
        q = self.num_controls
        c_k, c_next = row[:q], row[q:]
        if self.degree == 0:
            left = 0.5
        else:
            half = 2.0 ** (self.degree - 1)
            left = jnp.where(tau <= 0.5, 1.0 - half * tau**self.degree, half * (1.0 - tau) ** self.degree)
        g = c_next + (c_k - c_next) * left
        return jnp.clip(g, self.lower, self.upper)

    def initial_guess(self, tf, u_start, u_end):
        """Durations tf / P; coefficients on the straight line at the nodes (exact for
        degree 1), clipped to the bounds."""
        _check_guess(tf)
        P, q = self.segments, self.num_controls
        c = _channel_line(1.0, u_start, u_end, np.arange(P + 1) / P, q).T  # (q, P + 1)
        c = np.clip(c, np.asarray(self.lower)[:, None], np.asarray(self.upper)[:, None])
        times = np.full(P, tf / P) if self.free_durations else np.array([tf])
        return jnp.asarray(np.concatenate([times, c.reshape(-1)]))

    def _check_values(self, a):
        h = a[: self.segments] if self.free_durations else a[:1]
        # A collapsed segment comes back from a solver at h_k = 0 up to round-off (-6e-17 seen):
        # tolerated, so that a solution can be a starting vector again.
        bad = np.flatnonzero(h < -1e-12 * max(1.0, float(np.sum(np.abs(h)))))
        if bad.size:
            i = int(bad[0])
            what = "segment durations h_k" if self.free_durations else "the final time tf"
            raise ValueError(f"`a`: {what} (a[{i}]) must be >= 0; got a[{i}] = {h[i]:g} (all: {h.tolist()}).")
