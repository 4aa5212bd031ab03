"""Declared control bounds as inequality rows on the parameters.

A problem's `control_lower` / `control_upper` are honored in one of three ways:

* by construction: the family saturates u within them (`controls.saturates_within`, e.g. a
  `SaturatedSpline` whose limits lie inside the bounds): nothing to add;
* as bounds on the family's control-value parameters (`value_indices`), when the family
  declares them exact (`value_bounds_exact`: u is, channel by channel, a convex combination
  of those entries, so bounding them bounds u everywhere; piecewise linear and constant
  controls, saturated splines). KalmanSQP (either globalization), KalmanSearch and the SLSQP / IPOPT
  baselines take them as rows a_i - upper <= 0, lower - a_i <= 0 of the same inequality set as
  the path constraints (`Evaluation.V`); AugmentedLagrangian projects on its parameter box;
* otherwise a solver that relies on the rows raises a ValueError (`require_rows`): nothing
  is silently ignored.

Bounds on free initial-state components (`Problem(free_initial_state={name: (lo, hi)})`)
are rows of the same kind on their parameter entries.

The rows are built from the problem's static copy of the bounds (`Problem._control_box`):
which channels are bounded and whether a family saturates within the bounds fix the number
of rows at trace time.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .controls import saturates_within


def declared(problem) -> bool:
    """Whether the problem declares a finite control bound."""
    lo, hi = problem._control_box
    return bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))


def _control_rows(problem, control) -> bool:
    """Whether the declared control bounds need parameter rows (declared, and the family
    does not saturate within them)."""
    lo, hi = problem._control_box
    return declared(problem) and not saturates_within(control, np.asarray(lo), np.asarray(hi))


def needs_rows(problem, control) -> bool:
    """Whether the problem needs parameter rows: control bounds (`_control_rows`) or bounds
    on free initial-state components."""
    lo, hi = problem.initial_state_bounds
    return _control_rows(problem, control) or bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))


def _exact(control) -> bool:
    return bool(control.value_bounds_exact and len(control.value_indices[0]))


def require_rows(problem, control, who: str) -> None:
    """Raise a ValueError naming `who` if the declared bounds need parameter rows that the
    family cannot give (its value bounds are not exact)."""
    if _control_rows(problem, control) and not _exact(control):
        raise ValueError(
            f"`control`: {type(control).__name__} cannot take the problem's control_lower/control_upper "
            "as exact bounds on its parameters (`value_bounds_exact`) and does not saturate within them, "
            f"so {who} cannot honor them. Use PiecewiseLinear, PiecewiseConstant or a SaturatedSpline "
            "with limits inside the bounds (or jt.AugmentedLagrangian, which bounds the node values)."
        )


def _bound_table(problem, control):
    """The static layout of `bound_rows`: `(upper (idx, bound, names), lower (idx, bound,
    names))` over the control-value entries with a finite bound of their channel (when rows
    are needed and exact), then the free initial-state entries with a finite bound. Names:
    `"<control> upper bound at a[i]"`, `"<state> lower bound (initial)"`."""
    idx, lo, hi, what = np.zeros(0, int), np.zeros(0), np.zeros(0), []
    if _control_rows(problem, control) and _exact(control):
        idx, channel = (np.asarray(v, int) for v in control.value_indices)
        lo, hi = (np.asarray(b)[channel] for b in problem._control_box)
        names = problem.control_names or tuple(f"u{j}" for j in range(problem.num_controls))
        what = [f"{names[j]} {{}} bound at a[{i}]" for i, j in zip(idx, channel)]
    if problem.free_initial_state:
        lo0, hi0 = problem.initial_state_bounds
        idx = np.concatenate([idx, np.asarray(control.parameter_indices, int)])
        lo, hi = np.concatenate([lo, lo0]), np.concatenate([hi, hi0])
        states = problem.state_names or tuple(f"x{k}" for k in range(problem.x0.shape[0]))
        what += [f"{states[k]} {{}} bound (initial)" for k in problem.free_initial_state]
    upper, lower = np.isfinite(hi), np.isfinite(lo)
    return (
        (idx[upper], hi[upper], [w.format("upper") for w, u in zip(what, upper) if u]),
        (idx[lower], lo[lower], [w.format("lower") for w, l in zip(what, lower) if l]),
    )


def bound_rows(problem, control, a):
    """`(values (r,), Jacobian (r, np))` of the rows a_i - upper <= 0 and lower - a_i <= 0:
    over the control-value entries i (of channel j, bounds of channel j) with a finite
    bound, unless no row is needed or the family's value bounds are not exact
    (`require_rows` decides whether that is an error); then over the free initial-state
    entries with a finite bound. None without rows."""
    (iu, hi, _), (il, lo, _) = _bound_table(problem, control)
    if not (iu.size or il.size):
        return None
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    return jnp.concatenate([a[iu] - hi, lo - a[il]]), jnp.concatenate([eye[iu], -eye[il]])


def bound_excess(problem, control, a):
    """The correction that puts the entries of `a` past the bounds of `bound_rows` back on
    them: bound - a_i there, exactly 0 elsewhere (so that a + correction changes nothing
    inside the bounds, not even by round-off). A QP step meets its bound rows only to its
    round-off (~1e-9), which left a point on its bounds never feasible (RESULTS.md)."""
    (iu, hi, _), (il, lo, _) = _bound_table(problem, control)
    fix = jnp.zeros_like(a)
    return fix.at[iu].add(jnp.minimum(hi - a[iu], 0.0)).at[il].add(jnp.maximum(lo - a[il], 0.0))


def bound_row_names(problem, control) -> list[str]:
    """A name for each row of `bound_rows`, in its order."""
    (_, _, upper), (_, _, lower) = _bound_table(problem, control)
    return upper + lower


def knot_gap_names(control) -> list[str]:
    """A name for each row of `knot_gap_rows`: `"segment k length"`, or `"time span"` for
    equally spaced knots; none for fixed knots."""
    layout = control.time_layout
    if layout == "fixed":
        return []
    return ["time span"] if layout == "final_time" else [f"segment {k} length" for k in range(control.num_segments)]


def knot_gap_rows(control, a):
    """`(values, Jacobian)` of the rows that keep the time axis ordered: t_k - t_{k+1} <= 0
    (segments of nonnegative length, `(K,)`) for a family whose knots move with `a` (time
    layouts `"knots"`, `"durations"`, `"interior_knots"`), the one row t_0 - t_f <= 0 for
    equally spaced knots over a free final time (`"final_time"`); None for fixed knots. Rows
    of the same inequality set, so that a KKT test sees the multiplier of a collapsed segment,
    and the infeasibility test a final time pressed to t_0 (a minimum-time problem started
    heading away from its target: its violation is least at tf = t_0, a local minimum of it).

    The Jacobian is taken at `a` itself rather than reused from the step's linearization at
    the previous point: an own family may map parameters to knots nonlinearly, and this is
    one forward-mode pass through `knots` (no integration)."""
    layout = control.time_layout
    if layout == "fixed":
        return None

    def gap(a):
        knots = control.knots(a)
        return knots[:1] - knots[-1:] if layout == "final_time" else knots[:-1] - knots[1:]

    return gap(a), jax.jacfwd(gap)(a)
