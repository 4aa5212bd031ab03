"""The control interface (`AbstractControl`) and the bounds helpers solvers use."""

import abc
import contextlib
from typing import ClassVar

import equinox as eqx
import jax
import jax.core
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

    def initial_state(self, x0, a) -> jax.Array:
        """The initial state for parameters `a`: `x0` (a problem's), unless some of its
        components are parameters too (`FreeInitialState`)."""
        del a
        return x0

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
        if a.shape != (self.num_params,):  # (static: another length evaluated other entries, silently)
            raise ValueError(f"`a` must have shape ({self.num_params},) for {self!r}; got shape {a.shape}.")
        knots = self.knots(a)
        t = jnp.asarray(t, dtype=knots.dtype)
        k = jnp.clip(jnp.searchsorted(knots, t, side="right") - 1, 0, self.num_segments - 1)
        h = knots[k + 1] - knots[k]
        tau = jnp.where(h > 0, (t - knots[k]) / jnp.where(h > 0, h, 1.0), 0.0)
        flat_k, flat_tau = k.reshape(-1), tau.reshape(-1)
        u = jax.vmap(lambda kk, tt: self.segment_control(a, kk, tt))(flat_k, flat_tau)
        return u.reshape((*t.shape, self.num_controls))

    def validate(self, a, *, zero_tf: bool = False) -> np.ndarray:
        """Check a concrete parameter vector outside jit; return it as float64 numpy.
        `zero_tf=True` accepts tf = 0 (every segment collapsed: a point a solver may end at,
        which `jt.simulate` shows as a trajectory that stays at x0); a start needs tf > 0.

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
        self._check_values(arr)
        knots = self.concrete_knots(arr)
        if not (knots[-1] > 0 or (zero_tf and knots[-1] == 0)):
            raise ValueError(f"`a`: the final time tf must be > 0 for {name}; got tf = {knots[-1]}.")
        return arr

    def concrete_knots(self, a) -> np.ndarray:
        """`knots(a)` of a concrete `a` as NumPy, by one compiled program (`run_concretely`)."""
        return run_concretely(_knots, self, np.asarray(a, np.float64))

    def _check_increasing(self, knots: np.ndarray, what: str) -> None:
        """Knots in order in [0, tf]. Equal neighbours (a collapsed segment, as a solver leaves
        one at the bound t_k <= t_{k+1}, like a SaturatedSpline duration at 0) are allowed: the
        integration runs on normalized segment time and the control's evaluation guards h = 0,
        so a solver's own result can be simulated and checked; so is a reversal within 1e-12 of
        the knots' span, the round-off a solver accepts in its steps (a switch time pressed onto
        t_0 = 0 came back as -4.8e-40)."""
        d = np.diff(knots)
        bad = np.flatnonzero(d < -1e-12 * np.sum(np.abs(d)))
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"`a`: {what} must be increasing in [0, tf] with tf = {knots[-1]:g} (equal neighbours, "
                f"a collapsed segment, allowed); expected t_{i} <= t_{i + 1}, got t_{i} = {knots[i]:g}, "
                f"t_{i + 1} = {knots[i + 1]:g} (all knots: {np.array2string(knots, precision=6)})."
            )


def _knots(control, a):
    return control.knots(a)


_COMPILED = {}  # (fn, control structure, shapes) -> compiled program, for run_concretely


def run_concretely(fn, control, *args) -> np.ndarray:
    """`fn(control, *args)` of concrete arguments as NumPy, also while a transform traces
    (e.g. a constant `a` closed over by a jitted function): one program per family and shape,
    lowered and compiled apart from the enclosing trace. (Run op by op under
    `jax.ensure_compile_time_eval`, every jnp operation compiled a program of its own.) A
    control holding traced arrays (under a jit: a fixed final time, free start values, a
    spline's limits) runs with zeros in their place where `fn` provably does not use them
    (`_concrete_stand_in`), otherwise op by op, which fails where `fn` uses them (a
    `jax.errors.JAXTypeError`)."""
    if jax.config.jax_disable_jit:  # pyright: ignore[reportAttributeAccessIssue]  (op by op: no program to compile)
        return np.asarray(fn(control, *(jnp.asarray(x) for x in args)))
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(control)):
        stand_in = _concrete_stand_in(fn, control, args)
        if stand_in is None:
            with jax.ensure_compile_time_eval():
                return np.asarray(fn(control, *(jnp.asarray(x) for x in args)))
        control = stand_in
    # the compiled program takes the control's arrays as inputs: it serves every control of
    # the same structure and array shapes (e.g. another fixed final time)
    arrays, structure = eqx.partition(control, eqx.is_array)
    shapes = tuple((jnp.shape(x), jnp.result_type(x)) for x in (*jax.tree.leaves(arrays), *args))
    key = (fn, structure, shapes)
    try:
        compiled = _COMPILED[key]
    except (KeyError, TypeError):  # new, or an unhashable structure: compiled, not kept
        compiled = eqx.filter_jit(fn).lower(control, *args).compile()
        with contextlib.suppress(TypeError):
            _COMPILED[key] = compiled
    with jax.ensure_compile_time_eval():
        return np.asarray(compiled(control, *args))


def _concrete_stand_in(fn, control, args):
    """`control` with its traced arrays replaced by zeros if `fn(control, *args)` provably
    does not use them (a fixed final time or free start values inserted into a vector whose
    Jacobian is taken, a family's limits that act only inside `local_control`), so that it
    runs as one compiled program instead of op by op; None otherwise. (JAX's own dead-code
    pass, `partial_eval.dce_jaxpr`, is private API; `_used_inputs` reads only the documented
    jaxpr structure.)"""
    leaves, treedef = jax.tree.flatten(control)
    traced = [isinstance(leaf, jax.core.Tracer) for leaf in leaves]
    stand_in = [np.zeros(x.shape, x.dtype) if t else x for x, t in zip(leaves, traced)]
    dynamic = [i for i, t in enumerate(traced) if t]

    def on_arrays(arrays, *args):
        full = list(stand_in)
        for i, x in zip(dynamic, arrays):
            full[i] = x
        return fn(jax.tree.unflatten(treedef, full), *args)

    try:
        closed = jax.make_jaxpr(on_arrays)([stand_in[i] for i in dynamic], *args)
    except jax.errors.JAXTypeError:  # Python control flow on a traced array: op by op, as before
        return None
    used = _used_inputs(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    return None if any(used[: len(dynamic)]) else jax.tree.unflatten(treedef, stand_in)


def _is_var(v):
    return not hasattr(v, "val")  # a jaxpr variable, not a literal constant


def _used_inputs(jaxpr, used_outputs):
    """Which inputs of `jaxpr` its used outputs depend on: a backward pass over the equations,
    into nested `jit` calls, every input of any other equation with a used output counted
    (conservative: a False is certain)."""
    used = {v for v, u in zip(jaxpr.outvars, used_outputs) if u and _is_var(v)}
    for eqn in reversed(jaxpr.eqns):
        outs = [_is_var(v) and v in used for v in eqn.outvars]
        if not any(outs):
            continue
        inner = eqn.params.get("jaxpr") if eqn.primitive.name in ("jit", "pjit") else None
        need = _used_inputs(inner.jaxpr, outs) if inner is not None else [True] * len(eqn.invars)
        used.update(v for v, n in zip(eqn.invars, need) if n and _is_var(v))
    return [v in used for v in jaxpr.invars]


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
