"""Declared control bounds as inequality rows on the parameters.

A problem's `control_lower` / `control_upper` are honored in one of three ways:

* by construction: the family saturates u within them (`controls.saturates_within`, e.g. a
  `SaturatedSpline` whose limits lie inside the bounds): nothing to add;
* as bounds on the family's control-value parameters (`value_indices`), when the family
  declares them exact (`value_bounds_exact`: u is, channel by channel, a convex combination
  of those entries, so bounding them bounds u everywhere; piecewise linear and constant
  controls, saturated splines). KalmanSQP (line search), KalmanSearch and the SLSQP / IPOPT
  baselines take them as rows a_i - upper <= 0, lower - a_i <= 0 of the same inequality set as
  the path constraints (`Evaluation.V`); AugmentedLagrangian projects on its parameter box;
* otherwise a solver that relies on the rows raises a ValueError (`require_rows`): nothing
  is silently ignored.

The rows are built from the problem's static copy of the bounds (`Problem._control_box`):
which channels are bounded and whether a family saturates within the bounds fix the number
of rows at trace time.
"""

import jax.numpy as jnp
import numpy as np

from .controls import saturates_within


def declared(problem) -> bool:
    """Whether the problem declares a finite control bound."""
    lo, hi = problem._control_box
    return bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))


def needs_rows(problem, control) -> bool:
    """Whether the declared bounds need parameter rows (declared, and the family does not
    saturate within them)."""
    lo, hi = problem._control_box
    return declared(problem) and not saturates_within(control, np.asarray(lo), np.asarray(hi))


def _exact(control) -> bool:
    return bool(control.value_bounds_exact and len(control.value_indices[0]))


def require_rows(problem, control, who: str) -> None:
    """Raise a ValueError naming `who` if the declared bounds need parameter rows that the
    family cannot give (its value bounds are not exact)."""
    if needs_rows(problem, control) and not _exact(control):
        raise ValueError(
            f"`control`: {type(control).__name__} cannot take the problem's control_lower/control_upper "
            "as exact bounds on its parameters (`value_bounds_exact`) and does not saturate within them, "
            f"so {who} cannot honor them. Use PiecewiseLinear, PiecewiseConstant or a SaturatedSpline "
            "with limits inside the bounds (or jt.AugmentedLagrangian, which bounds the node values)."
        )


def bound_rows(problem, control, a):
    """`(values (r,), Jacobian (r, np))` of the rows a_i - upper_j <= 0 and lower_j - a_i <= 0
    over the control-value entries i (of channel j) with a finite bound, or None when no row
    is needed or the family's value bounds are not exact (`require_rows` decides whether that
    is an error)."""
    if not (needs_rows(problem, control) and _exact(control)):
        return None
    idx, channel = (np.asarray(v, int) for v in control.value_indices)
    lo, hi = (np.asarray(b) for b in problem._control_box)
    upper = np.isfinite(hi[channel])
    lower = np.isfinite(lo[channel])
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    values = jnp.concatenate([a[idx[upper]] - hi[channel[upper]], lo[channel[lower]] - a[idx[lower]]])
    return values, jnp.concatenate([eye[idx[upper]], -eye[idx[lower]]])
