"""A family adapted to a problem (`Problem.parametrize`): a fixed final time, free initial
states."""

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from ._base import AbstractControl


class _Adapted(AbstractControl):
    """A family adapted to a problem: the segments, channels, limits and the control on a
    segment are the family's; subclasses change the parameter vector."""

    control: eqx.AbstractVar[AbstractControl]

    @property
    def num_segments(self):
        return self.control.num_segments

    @property
    def num_controls(self):
        return self.control.num_controls

    @property
    def limits(self):
        return self.control.limits

    @property
    def value_bounds_exact(self):
        return self.control.value_bounds_exact

    @property
    def affine(self):
        return self.control.affine

    def local_control(self, row, h, tau):
        return self.control.local_control(row, h, tau)


class FixedFinalTime(_Adapted):
    """`control` on [0, T] with the final time T fixed: its parameter vector without the tf
    entry, so that tf is no decision parameter at all.

    `problem.parametrize(family)` builds it for a problem with `final_time=T`; use it for
    every entry point and to evaluate u(a, t) (`sol.params` has no tf entry). From a family
    with equally spaced knots (`time_layout` `"final_time"`) it drops tf (layout `"fixed"`: no time entries); from
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
    def time_indices(self):
        return self._shift(self.control.time_indices)

    @property
    def time_layout(self):
        return "fixed" if self.control.time_layout == "final_time" else "interior_knots"

    @property
    def value_indices(self):
        idx, channel = self.control.value_indices
        return self._shift(idx), tuple(channel)

    def knots(self, a):
        return self.control.knots(self.expand(a))

    def segment_table(self, a):
        return self.control.segment_table(self.expand(a))

    def initial_guess(self, tf, u_start, u_end):
        """The family's straight-line guess on [0, T] without tf; `tf` must be T."""
        T = float(self.final_time)
        if not np.isclose(float(tf), T, rtol=1e-12, atol=0.0):
            raise ValueError(f"`tf` must be the fixed final time {T:g}; got {tf!r}.")
        return self.reduce(self.control.initial_guess(T, u_start, u_end))

    def _check_values(self, a):
        self.control._check_values(np.asarray(self.expand(jnp.asarray(a))))


class FreeInitialState(_Adapted):
    """`control` with free initial-state components appended to its parameter vector:
    `a = [control's parameters, x0[indices]]`.

    `problem.parametrize(family)` builds it for a problem with `free_initial_state` (which
    gives the start values and bounds); a static design parameter p is such a component of a state
    with dp/dt = 0. The sensitivities of x(tf) to these entries start from the unit vectors
    dx0/da (exact, forward-mode or unit-solution alike).
    """

    control: AbstractControl
    indices: tuple[int, ...] = eqx.field(static=True)
    start: jax.Array  # x0[indices]: the start values `initial_guess` appends

    def __init__(self, control, indices, start):
        if not isinstance(control, AbstractControl) or isinstance(control, FreeInitialState):
            raise ValueError(f"`control` must be a control family (jt.controls.*); got {type(control).__name__}.")
        self.control = control
        self.indices = tuple(int(i) for i in indices)
        self.start = jnp.asarray(start, dtype=jnp.float64).reshape(len(self.indices))

    @property
    def parameter_indices(self) -> tuple[int, ...]:
        """The entries of `a` that are initial-state components (the last ones)."""
        m = self.control.num_params
        return tuple(range(m, m + len(self.indices)))

    def extend(self, a_control):
        """`a_control` (the wrapped control's vector) with the start values appended."""
        return jnp.concatenate([jnp.asarray(a_control, jnp.float64), self.start])

    @property
    def num_params(self):
        return self.control.num_params + len(self.indices)

    @property
    def time_indices(self):
        return self.control.time_indices

    @property
    def time_layout(self):
        return self.control.time_layout

    @property
    def value_indices(self):
        return self.control.value_indices

    def knots(self, a):
        return self.control.knots(a[: self.control.num_params])

    def segment_table(self, a):
        return self.control.segment_table(a[: self.control.num_params])

    def initial_guess(self, tf, u_start, u_end):
        """The wrapped control's guess, then the start values of the free components."""
        return self.extend(self.control.initial_guess(tf, u_start, u_end))

    def _check_values(self, a):
        self.control._check_values(a[: self.control.num_params])

    def initial_state(self, x0, a):
        return x0.at[np.asarray(self.indices, int)].set(a[self.control.num_params :].astype(x0.dtype))
