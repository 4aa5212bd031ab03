"""`jt.kkt_report`: the first-order optimality conditions of the restricted problem at one
parameter vector, each residual by constraint name, with the multipliers that give them."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from ._bounds import bound_row_names, knot_gap_names
from ._checks import check_inputs
from ._kkt import inequality_rows, stationarity_multipliers, with_knot_gaps
from ._problem import Problem
from ._sensitivity import evaluate_restricted
from ._simulate import RK4, AbstractSimulator, check_simulator
from ._status import Status, as_indexable, status_name


class KKTReport(eqx.Module):
    """First-order KKT residuals of the restricted problem at `params` (`jt.kkt_report`).

    - `objective`: G.
    - `stationarity`: |D (G_a + H^T lambda + J^T nu)| with free lambda on the terminal
      equalities and nu >= 0 on the inequality rows within `active` of their bound (nu = 0 on
      the others), D = diag(max(|a_i|, 1)) (the scaled parameters a_i / max(|a_i|, 1)): the
      residual every solver's SUCCESS tests (`Solution.projected_gradient`).
    - `complementarity`: max |nu_i g_i| over the inequality rows (a multiplier on a row that is
      not at its bound).
    - `violation`: by constraint name, how far it is violated (>= 0): |E_i| for a terminal
      equality, max(g, 0) for an inequality; for a path constraint the largest over the
      integration grid. Names: `constraint_names`, `path_names`, `terminal_inequality_names`,
      `"<control> upper bound at a[i]"` for a control-bound row, `"<state> lower bound
      (initial)"` for a free initial state, `"segment k length"` for free knots, `"time
      span"` (t_0 - tf <= 0) for equally spaced knots over a free final time.
    - `multipliers`: by the same names: lambda_i of an equality, nu >= 0 of an inequality;
      either is -dG*/db, the sensitivity of the optimal objective to the constraint's bound b
      (E = c(a) - b, g = c(a) - b <= 0); for a path constraint the sum over the grid points
      (its total effect on the optimum).
    - `max_violation`: the largest entry of `violation` (0 without constraints).
    - `status`: the evaluation's status (NONFINITE, SIMULATION_FAILED or SUCCESS).
    """

    objective: jax.Array
    stationarity: jax.Array
    complementarity: jax.Array
    max_violation: jax.Array
    violation: dict[str, jax.Array]
    multipliers: dict[str, jax.Array]
    status: Status = eqx.field(converter=as_indexable)

    def satisfied(self, ctol: float = 1e-8, gtol: float = 1e-6) -> bool:
        """Whether the point is a first-order KKT point within the tolerances: the status is
        SUCCESS, `max_violation` <= `ctol`, and `stationarity` and `complementarity` <= `gtol`
        (1 + |G|) (KalmanSQP's SUCCESS rule with its `acceptable_gtol`)."""
        return not self.failures(ctol, gtol)

    def failures(self, ctol: float = 1e-8, gtol: float = 1e-6) -> list[str]:
        """What keeps the point from `satisfied(ctol, gtol)`, one phrase each (empty if it is)."""
        for name, value in (("ctol", ctol), ("gtol", gtol)):
            # (an infinite tolerance: any point, however infeasible, was a KKT point)
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < float("inf"):
                raise ValueError(f"KKTReport: `{name}` must be a finite number > 0; got {value!r}.")
        out = []
        if self.status != Status.SUCCESS:
            out.append(f"evaluation {status_name(self.status)}")
        if not self.max_violation <= ctol:
            out.append(f"max violation {float(self.max_violation):.2e} > ctol {ctol:.0e}")
        limit = gtol * (1.0 + abs(float(self.objective)))
        if not self.stationarity <= limit:
            out.append(f"stationarity {float(self.stationarity):.2e} > gtol (1 + |G|) = {limit:.2e}")
        if not self.complementarity <= limit:
            out.append(f"complementarity {float(self.complementarity):.2e} > gtol (1 + |G|) = {limit:.2e}")
        return out

    def __str__(self):
        # the report's own verdict at the default tolerances (not the evaluation's status)
        failures = self.failures()
        verdict = "KKT point (ctol 1e-8, gtol 1e-6)" if not failures else "NOT a KKT point: " + "; ".join(failures)
        lines = [
            f"KKT report, {verdict}\n  objective {float(self.objective):.10g}, "
            f"stationarity {float(self.stationarity):.2e}, complementarity {float(self.complementarity):.2e}, "
            f"max violation {float(self.max_violation):.2e}"
        ]
        width = max((len(k) for k in self.violation), default=0)
        lines += [
            f"  {k:<{width}}  violation {float(v):.2e}  multiplier {float(self.multipliers[k]):+.6e}"
            for k, v in self.violation.items()
        ]
        return "\n".join(lines)


def _row_names(problem: Problem, control) -> tuple[list[str], list[str], list[str]]:
    """Names of the equality rows, of the path channels and of the other inequality rows
    (terminal, bounds, knot gaps) in `_kkt.inequality_rows` order."""
    other = list(problem.terminal_inequality_names) + bound_row_names(problem, control) + knot_gap_names(control)
    return list(problem.constraint_names), list(problem.path_names), other


@eqx.filter_jit
def _residuals(problem, control, a, simulator, active):
    ev = with_knot_gaps(control, evaluate_restricted(problem, control, a, simulator), a)
    m = ev.E.shape[0]
    rows = inequality_rows(ev)
    g = jnp.zeros(0) if rows is None else rows[0]
    residual, lam = stationarity_multipliers(ev, a, active)
    return ev.G, ev.E, g, lam[:m], lam[m:], residual, ev.status


def kkt_report(
    problem: Problem,
    control,
    params,
    *,
    simulator: AbstractSimulator = RK4(),
    active: float = 1e-6,
) -> KKTReport:
    """Check the first-order optimality conditions at `params`, constraint by constraint.

    An independent look at a result (`jt.kkt_report(prob, ctrl, sol.params)`): a fresh
    evaluation at `params` with `simulator`, the inequality rows within `active` of their
    bound taken as active (KalmanSQP's `path_active`), multipliers of the right sign by the
    same least-squares rounds as the solvers' stationarity test, and every residual by
    constraint name. `print(report)` gives a table; `report.satisfied(ctol, gtol)` the verdict.

    **Raises:** `ValueError` for `params` of the wrong shape or an `active` that is not finite and > 0.
    """
    a = check_inputs(problem, control, params)
    check_simulator(simulator)
    if not (isinstance(active, int | float) and not isinstance(active, bool) and 0 < active < math.inf):
        raise ValueError(f"`active` must be a finite number > 0; got {active!r}.")
    G, E, g, lam, nu, residual, status = _residuals(problem, control, a, simulator, float(active))
    eq_names, path_names, other_names = _row_names(problem, control)
    violation = {n: jnp.abs(e) for n, e in zip(eq_names, E)}
    multipliers = dict(zip(eq_names, lam))
    q = len(path_names)
    n_path = g.shape[0] - len(other_names)
    if q:
        C, nu_C = g[:n_path].reshape(-1, q), nu[:n_path].reshape(-1, q)
        for j, name in enumerate(path_names):
            violation[name] = jnp.maximum(jnp.max(C[:, j]), 0.0)
            multipliers[name] = jnp.sum(nu_C[:, j])
    for name, gi, ni in zip(other_names, g[n_path:], nu[n_path:]):
        violation[name] = jnp.maximum(gi, 0.0)
        multipliers[name] = ni
    return KKTReport(
        objective=G,
        stationarity=residual,
        complementarity=jnp.max(jnp.abs(nu * g), initial=0.0),
        max_violation=jnp.max(jnp.asarray(list(violation.values()) or [0.0])),
        violation=violation,
        multipliers={k: jnp.asarray(v) for k, v in multipliers.items()},
        status=status,
    )
