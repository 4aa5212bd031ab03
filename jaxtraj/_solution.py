"""Results of a solve: `Solution` and its per-iteration `History`."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._bounds import knot_gap_rows
from ._kkt import inequality_rows, stationarity_multipliers, weak_rows, with_knot_gaps
from ._status import Status, as_indexable, diverged, without_point


class History(eqx.Module):
    """Fixed-length per-step records (length `max_steps`; entries past `steps` are unused
    and hold NaN / False). One entry per integration of a candidate step. Each field means
    the same for every solver:

    - `objective`, `max_constraint_error`: G and max |E_i| at the current accepted point after
      the step;
    - `step_norm`: |a_candidate - a|, the length of the candidate step that was integrated;
    - `accepted`: whether the candidate was accepted;
    - `constraint_tolerance`: the tolerance on max |E_i| in force (KalmanSearch's e_a
      schedule; the fixed `ctol` of the others);
    - `details`: the solver's own per-step quantities under its own names, float64 (NaN where
      unused): KalmanSearch `rho` (gradient weight) and `phase` (0 constraint capture, 1
      minimum search); KalmanSQP with `LineSearch` `alpha` (step fraction) and `kind` (1 new
      direction, 2 backtracking, 3 second-order correction; 0 the start), with `TrustRegion`
      `radius` and `kind` (0 the start, 1 new step, 3 second-order correction);
      AugmentedLagrangian `outer_iteration`.
    """

    objective: jax.Array
    max_constraint_error: jax.Array
    step_norm: jax.Array
    accepted: jax.Array
    constraint_tolerance: jax.Array
    details: dict[str, jax.Array]

    @classmethod
    def empty(cls, max_steps: int, details: tuple[str, ...] = ()) -> "History":
        """Unused records (NaN / False) for `max_steps` steps, with the named `details`."""
        nan = jnp.full(max_steps, jnp.nan, jnp.float64)
        return cls(
            objective=nan,
            max_constraint_error=nan,
            step_norm=nan,
            accepted=jnp.zeros(max_steps, bool),
            constraint_tolerance=nan,
            details={name: nan for name in details},
        )

    def record(self, i, *, details=None, **values) -> "History":
        """A copy with entry `i` of every field set from `values` (one keyword per field) and
        of every detail from `details` (a dict with the names given to `empty`); an index past
        the end is dropped, and a zero-length history (no history kept) stays as it is."""
        if self.objective.shape[-1] == 0:
            return self
        # (a value in the record's dtype: a detail such as an int32 phase goes into float64)
        put = lambda h, v: h.at[i].set(jnp.asarray(v).astype(h.dtype), mode="drop")
        return History(
            **{k: put(getattr(self, k), v) for k, v in values.items()},
            details={k: put(self.details[k], v) for k, v in (details or {}).items()},
        )

    def clear_from(self, steps) -> "History":
        """A copy with the entries from `steps` on reset to unused."""
        unused = History.empty(self.objective.shape[-1], tuple(self.details))
        index = jnp.arange(self.objective.shape[-1])
        kept = index < jnp.asarray(steps).astype(index.dtype)  # (int32 steps, an int64 index)
        return jax.tree.map(lambda h, e: jnp.where(kept, h, e), self, unused)


def max_violation(ev, control, a):
    """`Solution.max_violation` at `a` from its evaluation `ev`: max |E| and the positive
    part of every inequality row (path, terminal, bound rows, knot gaps)."""
    gaps = knot_gap_rows(control, a)
    rows = [r.reshape(-1) for r in (ev.C, ev.D, ev.V, None if gaps is None else gaps[0]) if r is not None]
    worst = jnp.max(jnp.abs(ev.E), initial=0.0)
    for r in rows:
        worst = jnp.maximum(worst, jnp.max(r, initial=0.0))
    return worst


def weakly_active(ev, control, a, tol, multipliers=None):
    """`Solution.weakly_active` at `a` from its evaluation `ev` (knot gaps added here) and
    the multipliers [lambda; nu] of `stationarity_multipliers` (computed if not given)."""
    ev = with_knot_gaps(control, ev, a)
    rows = inequality_rows(ev)
    if rows is None:
        return jnp.asarray(False)
    if multipliers is None:
        _, multipliers = stationarity_multipliers(ev, a, tol)
    return jnp.any(weak_rows(ev.G_a, ev.H, rows[1], rows[0], multipliers, tol))


class Solution(eqx.Module):
    """Outcome of `jt.solve`. Under `vmap` every field gains a leading batch axis.

    - `params`: the final parameter vector a.
    - `tf`: final time tf(a).
    - `objective`: G at `params`.
    - `constraints`: E = M(tf, x(tf)) at `params` (named by `problem.constraint_names`).
    - `max_constraint_error`: max |E_i| (the terminal equalities).
    - `multipliers`: the Lagrange multipliers lambda of the terminal equalities at
      `params` (named as `constraints`; L = G + lambda^T E + nu^T C, least squares with nu >=
      0 on the near-active inequality rows): lambda_i = -dJ*/d(target_i) for E_i = x_i(tf) -
      target_i. Derivatives of a solve carry theirs (docs/differentiable.md).
    - `weakly_active`: whether an inequality row (path point, terminal inequality, bound,
      knot gap) is active within the solver's activity tolerance while its multiplier is
      about zero (`_kkt.WEAK_TOL` of the stationarity balance): the optimum as a function of
      the problem's data may have a kink there, and its derivative (docs/differentiable.md)
      is the one-sided one that lets the row go.
    - `max_violation`: how infeasible `params` is, over every constraint the problem
      declares: the largest of max |E_i|, the positive part of the terminal inequalities, of
      the path constraints and state bounds on the grid, of the control and initial-state
      bounds, and of the knot gaps (segments of negative length); 0 at a feasible point.
      The per-kind values are `max_constraint_error`, `terminal_inequality`,
      `max_path_constraint`; `jt.kkt_report` names every row.
    - `iterations`: accepted steps; `integrations`: trajectory integrations (each with
      sensitivities), including rejected candidates and the initial one.
    - `status`: a `jt.Status`; `sol.status == jt.Status.SUCCESS`.
    - `projected_gradient`: |V G_a| with V the projection on the constraints' tangent space
      in the scaled parameters a_i / max(|a_i|, 1) (the KKT stationarity residual of the
      restricted problem; `jt.kkt_report(problem,
      control, sol.params)` gives every residual and multiplier by constraint name).
    - `history`: a `History`; `steps`: how many of its entries are filled.
    - `max_path_constraint`, `max_path_time`: for problems with path constraints C <= 0
      (solvers that handle them), the largest C on the integration grid (<= 0: satisfied;
      minus the worst margin) and where it occurs; None otherwise.
    - `terminal_inequality`: for problems with terminal inequalities, their values D at
      `params` (<= 0: satisfied; named by `problem.terminal_inequality_names`); None otherwise.
    - `terminal_inequality_multipliers`: their multipliers nu >= 0 (0 on an inactive one;
      nu_j = dJ*/d(b_j) for a row D_j = c(xf) - b_j); None without terminal inequalities.
      `jt.kkt_report` names the multipliers of every other row (path points, bounds, knot
      gaps).

    **Batched solutions.** `sols[i]` is start i's `Solution` (the same as
    `jax.tree.map(lambda x: x[i], sols)`; a slice, index array or boolean mask selects
    several starts; `sols.tf.shape[0]` is the number of starts) and `for s in sols` iterates
    over the starts:

        sols = jt.solve_batch(prob, ctrl, a0s)      # or jax.vmap(jt.solve ...)(a0s)
        jt.status_name(sols[3].status)              # "SUCCESS" (or sols.status[3])
        jt.status_name(sols.status)                 # array of names, one per start
        ok = sols[sols.status == jt.Status.SUCCESS]

    An unbatched Solution raises `TypeError` on `[]` and iteration.
    """

    params: jax.Array
    tf: jax.Array
    objective: jax.Array
    constraints: jax.Array
    max_constraint_error: jax.Array
    max_violation: jax.Array
    multipliers: jax.Array
    weakly_active: jax.Array
    projected_gradient: jax.Array
    iterations: jax.Array
    integrations: jax.Array
    steps: jax.Array
    status: Status = eqx.field(converter=as_indexable)
    history: History
    max_path_constraint: jax.Array | None = None
    max_path_time: jax.Array | None = None
    terminal_inequality: jax.Array | None = None
    terminal_inequality_multipliers: jax.Array | None = None

    @classmethod
    def from_evaluation(
        cls,
        ev,
        params,
        *,
        control,
        active_tol,
        projected_gradient,
        iterations,
        integrations,
        steps,
        done,
        status,
        history,
        multipliers=None,
    ):
        """A solver's result at its final point: the values of the restricted evaluation `ev`
        there (an `Evaluation`; with path constraints, their worst value and its time), and
        `status` if the solver stopped (`done`), else MAX_ITERATIONS; DIVERGED instead of
        either failure when |G| or a parameter is past `DIVERGENCE` (a NONFINITE or SUCCESS
        status stays). A solve that ended NONFINITE without an accepted step has no finite
        point: its values are NaN (not the zeros of a placeholder evaluation). `multipliers`:
        [lambda; nu] of `_kkt.stationarity_multipliers` at `params` with the knot gaps
        (computed if not given). Shared by every solver's `postprocess`."""
        final = Status.where(
            diverged(ev.G, params) & (status != Status.SUCCESS) & (status != Status.NONFINITE),
            Status.DIVERGED,
            Status.where(done, status, Status.MAX_ITERATIONS),
        )
        blank = without_point(final, iterations)
        ev = jax.tree.map(lambda x: jnp.where(blank, jnp.nan, x) if jnp.issubdtype(x.dtype, jnp.floating) else x, ev)
        if multipliers is None:
            multipliers = stationarity_multipliers(with_knot_gaps(control, ev, params), params, active_tol)[1]
        multipliers = jnp.where(blank, jnp.nan, multipliers)
        history = eqx.tree_at(  # (its first record held the placeholder's zeros too)
            lambda h: (h.objective, h.max_constraint_error),
            history,
            tuple(jnp.where(blank, jnp.nan, x) for x in (history.objective, history.max_constraint_error)),
        )
        m = ev.E.shape[0]
        path = {}
        if ev.C is not None:
            worst = jnp.max(ev.C, axis=1)
            path = {"max_path_constraint": jnp.max(worst), "max_path_time": ev.path_t[jnp.argmax(worst)]}
        if ev.D is not None:
            path["terminal_inequality"] = ev.D
            start = m + (0 if ev.C is None else ev.C.size)  # (the rows: path points, then D)
            path["terminal_inequality_multipliers"] = multipliers[start : start + ev.D.shape[0]]
        return cls(
            params=params,
            tf=ev.tf,
            objective=ev.G,
            constraints=ev.E,
            max_constraint_error=jnp.max(jnp.abs(ev.E), initial=0.0),
            max_violation=max_violation(ev, control, params),
            multipliers=multipliers[:m],
            weakly_active=weakly_active(ev, control, params, active_tol, multipliers),
            projected_gradient=jnp.where(blank, jnp.nan, projected_gradient),
            iterations=iterations,
            integrations=integrations,
            steps=steps,
            status=final,
            history=history,
            **path,
        )

    def _batch_size(self, what: str) -> int:
        shape = jnp.shape(self.tf)
        if not shape:
            raise TypeError(
                f"{what} needs a batched Solution (from jax.vmap of a solve or jt.solve_batch); "
                "this one is a single solve."
            )
        return shape[0]

    def __getitem__(self, index) -> "Solution":
        n = self._batch_size("Indexing")
        if isinstance(index, int | np.integer):
            if not -n <= index < n:
                raise IndexError(f"start {index} out of range for a batch of {n}.")
        elif isinstance(index, tuple):
            raise TypeError("index a batched Solution along its start axis only: sols[i], sols[i:j] or sols[mask].")
        return jax.tree.map(lambda x: x[index], self)

    def __iter__(self):
        for i in range(self._batch_size("Iteration")):
            yield self[i]
