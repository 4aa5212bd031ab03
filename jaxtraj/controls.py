"""Control parametrizations u(a, t): each family is one class.

Every family splits [0, tf] into `segments` intervals [t_k, t_{k+1}] (the *knots*, which may
be parameters) and defines the control on segment k as a function of the rescaled time
tau = (t - t_k) / (t_{k+1} - t_k) in [0, 1]. Control discontinuities therefore only occur on
segment boundaries, and the simulator integrates each segment on tau, so node times and tf
are smooth parameters of the final state (seed 000 sec. 5.3, seed 003 eq. 6-7).

Parameter layouts follow the thesis (seed 000, sec. 5.3 and Tables 5.1-5.13) where it defines
one; `time_indices` says which entries of `a` are times (node times, durations or tf).
"""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class AbstractControl(eqx.Module):
    """A parametrized control u(a, t) on [0, tf(a)], piecewise on `num_segments` segments."""

    @property
    @abc.abstractmethod
    def num_params(self) -> int:
        """Length of the parameter vector `a`."""

    @property
    @abc.abstractmethod
    def num_segments(self) -> int:
        """Number of segments between knots."""

    @property
    @abc.abstractmethod
    def time_indices(self) -> tuple[int, ...]:
        """Indices of the entries of `a` that are times (node/switch times, durations, tf)."""

    @property
    @abc.abstractmethod
    def time_layout(self) -> str:
        """How the entries `time_indices` make the knots: `"final_time"` (one entry, tf; equally
        spaced knots), `"knots"` (t_1 < ... < t_K = tf) or `"durations"` (h_1, ..., h_K >= 0,
        tf = their sum); for a fixed final time T (`FixedFinalTime`), `"fixed"` (no time
        entries) or `"interior_knots"` (t_1 < ... < t_{K-1} < T). Solvers and batching derive
        time bounds and random starts from it."""

    @property
    def num_controls(self) -> int:
        """Number of control channels."""
        return 1

    @property
    def value_indices(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """`(indices, channels)`: the entries of `a` that are control values (u at a node, a
        level, a spline coefficient), and the channel of each. Solvers impose a bound on u as
        the same bound on these entries: exact for piecewise linear and constant controls and
        splines, on the nodes only for parabolic arcs. Default: none."""
        return (), ()

    @property
    def limits(self) -> tuple[jax.Array, jax.Array] | None:
        """`(lower, upper)` `(num_controls,)` if the family saturates u by construction, else
        None."""
        return None

    #: u is, channel by channel, a convex combination of the `value_indices` entries (at every
    #: t): bounds on those entries are then exact bounds on u, which solvers use to honor a
    #: problem's control bounds. Declare it only when true (default False).
    value_bounds_exact: ClassVar[bool] = False

    #: `segment_data` (the knots and `segment_table`) is affine in `a`; the sensitivities then
    #: differentiate each integration step along fewer directions. Declare it only when true:
    #: the default, False, is always correct.
    affine: ClassVar[bool] = False

    @abc.abstractmethod
    def knots(self, a) -> jax.Array:
        """Segment boundaries `(num_segments + 1,)`: 0 = t_0 < t_1 < ... < t_K = tf."""

    @abc.abstractmethod
    def segment_table(self, a) -> jax.Array:
        """Per-segment shape coefficients, shape `(num_segments, m)`: row k holds everything
        (besides the knots) that the control on segment k depends on."""

    @abc.abstractmethod
    def local_control(self, row, h, tau) -> jax.Array:
        """Control `(num_controls,)` from one row of `segment_table`, the segment's duration
        `h` and the rescaled time tau in [0, 1]."""

    @abc.abstractmethod
    def initial_guess(self, tf, u_start, u_end) -> jax.Array:
        """Parameters approximating the straight line u = u_start + (u_end - u_start) t / tf
        with equally spaced nodes."""

    def _check_values(self, a: np.ndarray) -> None:
        """Family-specific value checks (outside jit); raise ValueError."""

    # ------------------------------------------------------------------ shared behaviour

    def tf(self, a) -> jax.Array:
        """Final time tf(a)."""
        return self.knots(a)[-1]

    def segment_control(self, a, k, tau) -> jax.Array:
        """Control `(num_controls,)` on segment `k` (may be traced) at rescaled time tau."""
        knots = self.knots(a)
        return self.local_control(self.segment_table(a)[k], knots[k + 1] - knots[k], tau)

    def __call__(self, a, t) -> jax.Array:
        """u(a, t) for scalar or array `t` in [0, tf]; right-continuous at knots, u(tf) is
        the left limit. Returns shape `t.shape + (num_controls,)`."""
        a = jnp.asarray(a)
        knots = self.knots(a)
        t = jnp.asarray(t, dtype=knots.dtype)
        k = jnp.clip(jnp.searchsorted(knots, t, side="right") - 1, 0, self.num_segments - 1)
        h = knots[k + 1] - knots[k]
        tau = jnp.where(h > 0, (t - knots[k]) / jnp.where(h > 0, h, 1.0), 0.0)
        flat_k, flat_tau = k.reshape(-1), tau.reshape(-1)
        u = jax.vmap(lambda kk, tt: self.segment_control(a, kk, tt))(flat_k, flat_tau)
        return u.reshape((*t.shape, self.num_controls))

    def validate(self, a) -> np.ndarray:
        """Check a concrete parameter vector outside jit; return it as float64 numpy.

        **Raises:** `ValueError` naming the argument, what was expected and what was received.
        """
        name = type(self).__name__
        arr = np.asarray(a)
        if arr.dtype == object or not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
            raise ValueError(f"`a` must be a real numeric array for {self!r}; got dtype {arr.dtype}.")
        arr = arr.astype(np.float64)
        if arr.shape != (self.num_params,):
            raise ValueError(f"`a` must have shape ({self.num_params},) for {self!r}; got shape {arr.shape}.")
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise ValueError(
                f"`a` must be finite; got non-finite entries at indices {bad.tolist()} (values {arr[bad].tolist()})."
            )
        # concrete values even when called while tracing (e.g. a constant `a` closed over
        # by a jitted function)
        with jax.ensure_compile_time_eval():
            self._check_values(arr)
            knots = np.asarray(self.knots(jnp.asarray(arr)))
        if not knots[-1] > 0:
            raise ValueError(f"`a`: the final time tf must be > 0 for {name}; got tf = {knots[-1]}.")
        return arr

    def _check_increasing(self, knots: np.ndarray, what: str) -> None:
        d = np.diff(knots)
        bad = np.flatnonzero(d <= 0)
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"`a`: {what} must be strictly increasing in (0, tf] with tf = {knots[-1]:g}; "
                f"expected t_{i} < t_{i + 1}, got t_{i} = {knots[i]:g}, t_{i + 1} = {knots[i + 1]:g} "
                f"(all knots: {np.array2string(knots, precision=6)})."
            )


def saturates_within(control: AbstractControl, lower=None, upper=None) -> bool:
    """Whether the family's own `limits` keep u within `lower`/`upper` (a problem's control
    bounds; None: unbounded). False for traced bounds (not decidable at trace time)."""
    if control.limits is None:
        return False
    try:
        lo, hi = (np.asarray(x) for x in control.limits)
        inside_lo = lower is None or np.all(lo >= np.asarray(lower))
        inside_hi = upper is None or np.all(hi <= np.asarray(upper))
    except jax.errors.TracerArrayConversionError:
        return False
    return bool(inside_lo and inside_hi)


def value_bounds(control: AbstractControl, lower=None, upper=None):
    """`(indices, lo, hi)`: the entries of `a` that are control values (`value_indices`) and
    their bounds, from `lower`/`upper` `(num_controls,)` (a problem's control bounds; None:
    unbounded) intersected with the family's own `limits`. Traceable (jnp)."""
    idx, channel = control.value_indices
    q = control.num_controls
    lo = jnp.full(q, -jnp.inf) if lower is None else jnp.broadcast_to(jnp.asarray(lower, jnp.float64), (q,))
    hi = jnp.full(q, jnp.inf) if upper is None else jnp.broadcast_to(jnp.asarray(upper, jnp.float64), (q,))
    if control.limits is not None:
        lo, hi = jnp.maximum(lo, control.limits[0]), jnp.minimum(hi, control.limits[1])
    channel = np.asarray(channel, int)
    return np.asarray(idx, int), lo[channel], hi[channel]


def _knots_or_final_time(free_times):
    return "knots" if free_times else "final_time"


def _values_but_times(control):
    """Every entry but the times is a control value; values come in groups of one per channel."""
    idx = tuple(i for i in range(control.num_params) if i not in set(control.time_indices))
    return idx, tuple(r % control.channels for r in range(len(idx)))


def _channel_line(tf, u_start, u_end, t, q):
    """The straight line at the times `t`, shape `(len(t), q)`; `u_start`, `u_end`: a number
    or one per channel."""
    us, ue = (np.broadcast_to(np.asarray(v, dtype=np.float64), (q,)) for v in (u_start, u_end))
    return _line(tf, us[None], ue[None], np.asarray(t)[:, None])


def _check_segments(segments, name="segments"):
    if not (isinstance(segments, int) and not isinstance(segments, bool) and segments >= 1):
        raise ValueError(f"`{name}` must be an int >= 1; got {segments!r}.")


def _line(tf, u_start, u_end, t):
    return u_start + (u_end - u_start) * t / tf


def _check_guess(tf):
    if not (np.isfinite(tf) and tf > 0):
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
    continuous: bool = True
    free_times: bool = False
    channels: int = 1
    affine: ClassVar[bool] = True
    value_bounds_exact: ClassVar[bool] = True

    def __check_init__(self):
        _check_segments(self.segments)
        _check_segments(self.channels, "channels")

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
        t = tf * np.arange(K + 1) / K
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
            self._check_increasing(np.asarray(self.knots(jnp.asarray(a))), "node times")


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
    free_times: bool = True
    channels: int = 1
    affine: ClassVar[bool] = True

    def __check_init__(self):
        _check_segments(self.segments)
        _check_segments(self.channels, "channels")

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
        t = tf * np.arange(K + 1) / K
        u = _channel_line(tf, u_start, u_end, t, q)  # (K + 1, q)
        slope = np.broadcast_to((u[-1] - u[0]) / tf, (K, q))
        arcs = np.concatenate([u[:-1], slope, u[1:]], axis=1)
        if self.free_times:
            return jnp.asarray(np.concatenate([arcs, t[1:, None]], axis=1).reshape(-1))
        return jnp.asarray(np.concatenate([arcs.reshape(-1), [tf]]))

    def _check_values(self, a):
        if self.free_times:
            self._check_increasing(np.asarray(self.knots(jnp.asarray(a))), "node times")


class PiecewiseConstant(AbstractControl):
    """Constant levels with (free) switch times (thesis tests 6, 7, sec. 5.3.5).

    Per piece `[level, t_end]` (`free_times=True`; the last t_end is tf), or
    `[level_1, ..., level_K, tf]` with equally spaced switches (`free_times=False`). With
    `channels` = q > 1 each level is q consecutive entries.
    """

    segments: int
    free_times: bool = True
    channels: int = 1
    affine: ClassVar[bool] = True
    value_bounds_exact: ClassVar[bool] = True

    def __check_init__(self):
        _check_segments(self.segments)
        _check_segments(self.channels, "channels")

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
        t = tf * np.arange(K + 1) / K
        levels = _channel_line(tf, u_start, u_end, 0.5 * (t[:-1] + t[1:]), self.channels)  # (K, q)
        if self.free_times:
            return jnp.asarray(np.concatenate([levels, t[1:, None]], axis=1).reshape(-1))
        return jnp.asarray(np.concatenate([levels.reshape(-1), [tf]]))

    def _check_values(self, a):
        if self.free_times:
            self._check_increasing(np.asarray(self.knots(jnp.asarray(a))), "switch times")


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
        if not (isinstance(degree, int) and not isinstance(degree, bool) and 0 <= degree <= 3):
            raise ValueError(f"`degree` must be an int in 0..3; got {degree!r}.")
        lo = np.atleast_1d(np.asarray(lower, dtype=np.float64))
        hi = np.atleast_1d(np.asarray(upper, dtype=np.float64))
        if lo.ndim != 1 or hi.ndim != 1:
            raise ValueError(f"`lower`/`upper` must be scalars or 1-D; got shapes {lo.shape}, {hi.shape}.")
        lo, hi = np.broadcast_arrays(lo, hi)
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo >= hi):
            raise ValueError(f"`lower` must be < `upper` component-wise; got lower={lo}, upper={hi}.")
        self.segments = segments
        self.degree = degree
        self.lower = jnp.asarray(lo.copy())
        self.upper = jnp.asarray(hi.copy())
        self._limits = (tuple(map(float, lo)), tuple(map(float, hi)))
        self.free_durations = free_durations

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


class FixedFinalTime(AbstractControl):
    """`control` on [0, T] with the final time T fixed: its parameter vector without the tf
    entry, so that tf is no decision parameter at all.

    Built by every entry point (`jt.solve`, `jt.simulate`, ...) for a problem with
    `final_time=T` from the family it is given; build it yourself to evaluate u(a, t) of a
    solution (`sol.a` has no tf entry). From a family with equally spaced knots
    (`time_layout` `"final_time"`) it drops tf (layout `"fixed"`: no time entries); from
    free knot times (`"knots"`) it drops the last knot t_K = T (layout `"interior_knots"`).
    Families whose durations are the times (`SaturatedSpline(free_durations=True)`) are
    refused: tf = sum h_k is no single entry (use `free_durations=False`).
    """

    control: AbstractControl
    final_time: jax.Array

    def __init__(self, control, final_time):
        if not isinstance(control, AbstractControl) or isinstance(control, FixedFinalTime):
            raise ValueError(f"`control` must be a control family (jt.controls.*); got {type(control).__name__}.")
        if control.time_layout not in ("final_time", "knots"):
            raise ValueError(
                f"`control`: {control!r} has time layout {control.time_layout!r}; a fixed final time needs "
                "tf as one entry (layout 'final_time' or 'knots'), e.g. SaturatedSpline(free_durations=False)."
            )
        T = np.asarray(final_time, dtype=np.float64) if not isinstance(final_time, jax.core.Tracer) else final_time
        if isinstance(T, np.ndarray) and not (T.shape == () and np.isfinite(T) and T > 0):
            raise ValueError(f"`final_time` must be a finite number > 0; got {final_time!r}.")
        self.control = control
        self.final_time = jnp.asarray(T, dtype=jnp.float64)

    @property
    def tf_index(self) -> int:
        """Index of tf in the family's vector (the lone time entry, or the last knot)."""
        return self.control.time_indices[-1]

    def expand(self, a):
        """The family's vector: `a` with tf = T inserted."""
        i = self.tf_index
        return jnp.concatenate([a[:i], jnp.reshape(self.final_time, (1,)).astype(a.dtype), a[i:]])

    def reduce(self, a_full):
        """`a_full` (the family's vector) without its tf entry."""
        return jnp.delete(jnp.asarray(a_full), self.tf_index)

    def _shift(self, indices):
        i = self.tf_index
        return tuple(j if j < i else j - 1 for j in indices if j != i)

    @property
    def num_params(self):
        return self.control.num_params - 1

    @property
    def num_segments(self):
        return self.control.num_segments

    @property
    def num_controls(self):
        return self.control.num_controls

    @property
    def time_indices(self):
        return self._shift(self.control.time_indices)

    @property
    def time_layout(self):
        return "fixed" if self.control.time_layout == "final_time" else "interior_knots"

    @property
    def value_indices(self):
        idx, channel = self.control.value_indices
        return self._shift(idx), tuple(channel)

    @property
    def limits(self):
        return self.control.limits

    @property
    def value_bounds_exact(self):
        return self.control.value_bounds_exact

    @property
    def affine(self):
        return self.control.affine

    def knots(self, a):
        return self.control.knots(self.expand(a))

    def segment_table(self, a):
        return self.control.segment_table(self.expand(a))

    def local_control(self, row, h, tau):
        return self.control.local_control(row, h, tau)

    def initial_guess(self, tf, u_start, u_end):
        """The family's straight-line guess on [0, T] without tf; `tf` must be T."""
        T = float(self.final_time)
        if not np.isclose(float(tf), T, rtol=1e-12, atol=0.0):
            raise ValueError(f"`tf` must be the fixed final time {T:g}; got {tf!r}.")
        return self.reduce(self.control.initial_guess(T, u_start, u_end))

    def _check_values(self, a):
        self.control._check_values(np.asarray(self.expand(jnp.asarray(a))))


__all__ = [
    "AbstractControl",
    "FixedFinalTime",
    "PiecewiseConstant",
    "PiecewiseLinear",
    "PiecewiseParabolic",
    "SaturatedSpline",
    "saturates_within",
    "spline_kernel",
    "value_bounds",
]
