"""Results of a solve: `Solution` and its per-iteration `History`."""

import equinox as eqx
import jax

from ._status import Status


class History(eqx.Module):
    """Fixed-length per-step records (length `max_steps`; entries past `steps` are unused
    and hold NaN / -1). One entry per integration of a candidate step."""

    objective: jax.Array  # objective at the current accepted point after the step
    max_constraint_error: jax.Array  # max |E_i| at the current accepted point
    rho: jax.Array  # the gradient-step weight rho used for the candidate
    phase: jax.Array  # 0 = constraint capture, 1 = minimum search, -1 = unused
    accepted: jax.Array  # whether the candidate was accepted
    constraint_tolerance: jax.Array  # e_a in force


class Solution(eqx.Module):
    """Outcome of `jt.solve`. Under `vmap` every field gains a leading batch axis.

    - `params`: the final parameter vector a.
    - `tf`: final time tf(a).
    - `objective`: G at `params`.
    - `constraints`: E = M(tf, x(tf)) at `params` (named by `problem.constraint_names`).
    - `max_constraint_error`: max |E_i|.
    - `iterations`: accepted steps; `integrations`: trajectory integrations (each with
      sensitivities), including rejected candidates and the initial one.
    - `status`: a `jt.Status`; `sol.status == jt.Status.SUCCESS`.
    - `projected_gradient`: |V G_a| with V the projection on the constraints' tangent space
      (the KKT stationarity residual of the restricted problem).
    - `history`: a `History`; `steps`: how many of its entries are filled.
    - `max_path_constraint`, `max_path_time`: for problems with path constraints C <= 0
      (solvers that handle them), the largest C on the integration grid (<= 0: satisfied;
      minus the worst margin) and where it occurs; None otherwise.
    """

    params: jax.Array
    tf: jax.Array
    objective: jax.Array
    constraints: jax.Array
    max_constraint_error: jax.Array
    projected_gradient: jax.Array
    iterations: jax.Array
    integrations: jax.Array
    steps: jax.Array
    status: Status
    history: History
    max_path_constraint: jax.Array | None = None
    max_path_time: jax.Array | None = None
