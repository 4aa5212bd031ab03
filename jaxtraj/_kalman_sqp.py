"""A quasi-Newton Kalman SQP: the thesis's sequential filter update as the step of an SQP
method (ALGORITHM.md section 7).

With the covariance P = B^-1 (B an approximation of the Hessian of the Lagrangian
L = G + lambda^T E), the prior mean -P G_a^T and the full correction z = -E observed with
(almost) no noise, the thesis's sequential update returns the SQP step

    d = argmin G_a d + 1/2 d^T B d   subject to   E + H d = 0,

and the multipliers follow from its stationarity condition H^T lambda_qp = -(G_a + B d).
Inequality rows (path constraints on the grid, terminal inequalities, control bounds) join
as observations through Goldfarb & Idnani's dual active set on the same rank-one updates
(`direction`); free knot times keep their order by the appendix-C observations.

The globalization is a module of its own: `jt.TrustRegion` (`jaxtraj._trust_region`, the
default, exact Hessian) or `jt.LineSearch` (`jaxtraj._line_search`, exact Hessian or BFGS).
This module holds what both share: the QP step by the filter, its multipliers, the
second-order correction, the Hessians.

(The algorithm, its history and measurements: docs/solvers/kalman-sqp.md.)
"""

import math

import equinox as eqx
import jax.numpy as jnp
from jax import lax

from ._bounds import require_rows
from ._checks import check_settings, is_count
from ._driver import AbstractSolver
from ._kalman import inequality_step, keep_knots_ordered, sequential_update
from ._kkt import (
    curvature_error,
    inequality_rows,
    kkt_residual,
    least_squares_multipliers,
    multipliers,
    with_knot_gaps,
)
from ._line_search import LineSearch
from ._sensitivity import Evaluation, evaluate_jitted, lagrangian_hessian, unevaluated
from ._solution import Solution
from ._trust_region import TrustRegion


def convexify(hessian, H, min_curvature):
    """A positive definite B for the QP from an exact Hessian of the Lagrangian.

    B = hessian + c H^T H, with c scaling H^T H to the Hessian (c = |hessian| / |H^T H|,
    Frobenius norms), then eigenvalues replaced by their absolute values, floored at
    `min_curvature` x the largest. The added term is the constant c/2 |E|^2 on the QP's
    feasible set, so where it alone makes B positive definite (near a minimum with a
    positive definite reduced Hessian) the QP's solution is the Newton-SQP step. A larger
    c would guarantee that more often, but it also enters the merit's penalty rule through
    d^T B d, and the penalty then grows with it: measured on the seven Earth-Mars cases,
    trying c, 10c, 100c in turn made both Hessian modes fail from most published starts.
    """
    HtH = H.T @ H
    c = jnp.linalg.norm(hessian) / jnp.maximum(jnp.linalg.norm(HtH), 1e-300)
    w, V = jnp.linalg.eigh(hessian + c * HtH)
    w = jnp.abs(w)
    # No curvature at all (a linear objective with zero multipliers, e.g. minimum time at a
    # start where the constraints are indifferent to the times): the identity, not 1e-300 I
    # (whose inverse overflows); the line search's radius bounds the step.
    w = jnp.where(jnp.max(w) > 0.0, jnp.maximum(w, min_curvature * jnp.max(w)), 1.0)
    return (V * w[None, :]) @ V.T


#: A row whose variance left by the terminal equalities is below this fraction of its prior
#: variance is pinned by them (far above the filter's relative noise `r_rel`, 1e-12, which is
#: all such a row keeps): violated, it makes the linearized constraints inconsistent.
ELASTIC_PINNED = 1e-8


def _redundant_simple_rows(C, C_a, n_rows, radius):
    """The rows of a QP with the step box |d_i| <= `radius` (rows n_rows..n_rows + 2n, after
    the problem's n_rows) that a parallel row makes redundant: of a simple bound on one d_i
    (one nonzero entry: a parameter bound) and the box's row on the same side of d_i, the
    looser one. Parallel rows are dependent, so in the dual active set the tighter one
    could only replace the looser one, a drop and a refactor each (issue 49: most of the
    500 rounds of the free-flying robot's QPs, 124 bounded parameters)."""
    n = C_a.shape[1]
    A = C_a[:n_rows]
    simple = jnp.sum(A != 0.0, axis=1) == 1
    col = jnp.argmax(jnp.abs(A), axis=1)
    coef = jnp.take_along_axis(A, col[:, None], axis=1)[:, 0]
    bound = -C[:n_rows] / jnp.where(simple, coef, 1.0)  # d_col <= bound (coef > 0) or >= bound
    upper, lower = simple & (coef > 0.0), simple & (coef < 0.0)
    ub = jnp.full(n, jnp.inf, C.dtype).at[col].min(jnp.where(upper, bound, jnp.inf))
    lb = jnp.full(n, -jnp.inf, C.dtype).at[col].max(jnp.where(lower, bound, -jnp.inf))
    rows = (upper & (bound > radius)) | (lower & (bound < -radius))
    box = jnp.concatenate([ub <= radius, lb >= -radius])
    return jnp.concatenate([rows, box, jnp.zeros(C.shape[0] - n_rows - 2 * n, bool)])


def _covariance(B):
    """P = B^-1, exactly symmetric. (A Cholesky solve gives the same steps to round-off, but
    the attitude runs of examples/attitude.py are sensitive enough to round-off to end
    elsewhere: 2.2714 instead of 2.2648954 on the quaternion form.)"""
    P = jnp.linalg.inv(B)
    return 0.5 * (P + P.T)


def _globalization(value):
    """`KalmanSQP.globalization` from a module or its name (the default settings)."""
    if isinstance(value, str):
        return {"line-search": LineSearch, "trust-region": TrustRegion}.get(value, lambda: value)()
    return value


class KalmanSQP(AbstractSolver):
    """Quasi-Newton SQP whose step is the sequential Kalman update (see docs/solvers/kalman-sqp.md).

    Fields:

    - `hessian`: `"exact"` (default; the exact Hessian of the Lagrangian at every accepted
      point) or `"bfgs"` (with `globalization="line-search"` only: exact at the start, for
      the first `exact_iterations` iterations and after a rejected step, then damped BFGS).
    - `exact_iterations`: see `hessian` (int >= 0, 3; BFGS only).
    - `ctol`: constraint tolerance on max |E_i| and on max C (1e-10).
    - `gtol`: projected-gradient target, relative to 1 + |G| (1e-9): the search stops when
      it is met.
    - `acceptable_gtol`: what SUCCESS guarantees of the projected gradient (relative to
      1 + |G|, 1e-6) when round-off ends the progress before `gtol` is met (docs/solvers/kalman-sqp.md).
    - `acceptable_steps`: a point that stays acceptable (feasible, projected gradient <=
      `acceptable_gtol`) for this many steps in a row ends the search with SUCCESS (15, as
      IPOPT's `acceptable_iter`): along a degenerate valley whose steps move only the
      discretization's error the endgame would otherwise crawl for as long as the last bits
      of the start and the CPU make it (`_kkt.kkt_outcome`).
    - `a_t`: knot approach ratio of the appendix-C ordering observations (as KalmanSearch).
    - `min_curvature`: relative eigenvalue floor of the convexified exact Hessian.
    - `globalization`: `jt.TrustRegion()` (default; a composite-step trust region with the
      QP's step in a box where there are inequalities; `hessian="exact"`: see
      `jaxtraj._trust_region`) or `jt.LineSearch()` (the merit line search of
      `jaxtraj._line_search`, with its own settings; needed for BFGS). The strings
      `"trust-region"` and `"line-search"` stand for their defaults.
    - `r_rel`: observation noise of the correction, relative to h P h^T (the QP's
      constraints are met to about this fraction of the innovation).
    - `path_active`: path points with C >= -`path_active` count as active constraints in
      the projected gradient (the KKT test).
    - `path_dependence`: an inequality row joins the active set as one more row only if the
      step can still move it independently: its variance left by the rows already observed
      is at least this fraction of its prior variance; a (nearly) dependent one (adjacent
      grid points) can only replace a working row (`dual_active_set`).
    - `elastic`: when the linearized constraints are inconsistent with the inequalities, the
      terminal equalities of that step are observed with noise `elastic` x the mean of
      h P h^T (an l2 elastic step on |H d + E|^2 that honours every inequality).
    - `method`: sensitivity method, `"forward"` or `"unit"` (`"unit"` only with BFGS).
    """

    hessian: str = "exact"
    ctol: float = 1e-10
    gtol: float = 1e-9
    acceptable_gtol: float = 1e-6
    acceptable_steps: int = 15
    a_t: float = 10.0
    min_curvature: float = 1e-8
    r_rel: float = 1e-12
    exact_iterations: int = 3
    path_active: float = 1e-6
    globalization: LineSearch | TrustRegion = eqx.field(default="trust-region", converter=_globalization)
    path_dependence: float = 1e-12
    elastic: float = 1e-6
    method: str = "forward"

    def __check_init__(self):
        if self.hessian not in ("bfgs", "exact"):
            raise ValueError(f"KalmanSQP: `hessian` must be 'bfgs' or 'exact'; got {self.hessian!r}.")
        if self.method not in ("forward", "unit"):
            raise ValueError(f"KalmanSQP: `method` must be 'forward' or 'unit'; got {self.method!r}.")
        if not isinstance(self.globalization, LineSearch | TrustRegion):
            raise ValueError(
                "KalmanSQP: `globalization` must be jt.LineSearch(), jt.TrustRegion(), 'line-search' or "
                f"'trust-region'; got {self.globalization!r}."
            )
        if isinstance(self.globalization, TrustRegion) and self.hessian != "exact":
            raise ValueError(
                "KalmanSQP: the trust region (`globalization`, the default) needs `hessian='exact'`; "
                "BFGS runs with globalization='line-search'."
            )
        if self.hessian == "exact" and self.method != "forward":
            raise ValueError("KalmanSQP: `hessian='exact'` needs `method='forward'`.")
        gtols = (self.gtol, self.acceptable_gtol)
        if all(isinstance(g, int | float) and not isinstance(g, bool) and g > 0 for g in gtols) and gtols[0] > gtols[1]:
            raise ValueError(
                f"KalmanSQP: `gtol` = {self.gtol!r} must be <= `acceptable_gtol` = {self.acceptable_gtol!r} "
                "(what SUCCESS guarantees); pass a larger acceptable_gtol with it."
            )
        checks = {
            "ctol": lambda: 0 < self.ctol < math.inf,  # (an infinite tolerance would promise nothing)
            "gtol": lambda: 0 < self.gtol < math.inf,
            "acceptable_gtol": lambda: self.gtol <= self.acceptable_gtol < math.inf,
            "a_t": lambda: 1 <= self.a_t < math.inf,
            "path_active": lambda: 0 < self.path_active < math.inf,
            "min_curvature": lambda: 0 < self.min_curvature < 1,
            "r_rel": lambda: 0 < self.r_rel < 1,
            "path_dependence": lambda: 0 < self.path_dependence < 1,
            "elastic": lambda: 0 < self.elastic < 1,
            "exact_iterations": lambda: is_count(self.exact_iterations, 0),
            "acceptable_steps": lambda: is_count(self.acceptable_steps, 1),
        }
        check_settings("KalmanSQP", self, checks)

    # ------------------------------------------------------------------ evaluations

    def restricted(self, problem, control, a, simulator):
        return evaluate_jitted(problem, control, a, simulator, self.method)

    def qp_hessian(self, W, H):
        """The QP's positive definite B from an exact Hessian of the Lagrangian W (`convexify`);
        the identity where it is not finite."""
        B = convexify(W, H, self.min_curvature)
        return jnp.where(jnp.all(jnp.isfinite(B)), B, jnp.eye(W.shape[0]))

    def exact_hessian(self, problem, control, a, simulator, ev, lam):
        """The QP's B at `a` (evaluated as `ev`): `qp_hessian` of the Hessian of the
        Lagrangian with multipliers `lam` (`lagrangian_hessian`, the trust region's kernel)."""
        return self.qp_hessian(lagrangian_hessian(problem, control, a, simulator, lam), ev.H)

    def unevaluated(self, problem, control, a0, simulator):
        """Zeros shaped as the evaluation at `a0` and its least-squares multipliers, for an
        initial state whose start the first `step` evaluates (traced by `jax.eval_shape`,
        neither compiled nor integrated)."""

        def shapes(a):
            ev = self.restricted(problem, control, a, simulator)
            return ev, least_squares_multipliers(ev, self.path_active)

        return unevaluated(shapes, a0)

    # ------------------------------------------------------------------ the QP step

    def direction(self, ev: Evaluation, B, lam, knots, dknots, radius=None, gap_rows=None):
        """The SQP step by the sequential filter: prior -P G_a with P = B^-1, observations
        H d = -E with noise `r_rel` h P h^T, the inequalities by a dual active set; then the
        appendix-C knot ordering. With `radius`, a problem with inequalities bounds the step
        in the QP, |d_i| <= radius (2 np more rows of the active set), so that a direction of
        nearly zero curvature cannot take the step over and leave the inequalities' part of
        it at round-off once the step is scaled down to the radius. `gap_rows` (the
        trust region: `_bounds.knot_gap_rows`, the rows of the KKT test) are more rows of
        that QP (multipliers not returned, but those of its active set enter the estimate of
        the others: `_stationary_multipliers`); appendix C then keeps a share of each gap the QP
        closes. The rows with positive multipliers in `lam` (the last QP's) start the active
        set (`dual_active_set(warm=)`), and a parameter bound and the box's row on the same
        side of the same parameter enter as one row, the tighter (`_redundant_simple_rows`)."""
        P = _covariance(B)
        prior = -P @ ev.G_a
        hph = jnp.einsum("ip,pq,iq->i", ev.H, P, ev.H)
        r = self.r_rel * hph + 1e-300
        d, P1 = self._equality_step(prior, P, ev, r)
        rows, m = inequality_rows(ev), ev.E.shape[0]
        gaps_held = None  # the knot-gap rows in the QP's final active set
        if rows is not None:
            # Inequalities C + C_a d <= 0 (path ones on the grid points, then terminal ones) by
            # the dual active-set method (`dual_active_set`): from the equality-constrained
            # step, the most violated row joins, or replaces a working row whose multiplier
            # would turn negative; a row (nearly) dependent on the working ones (its variance
            # left below `path_dependence` of its prior variance: neighbouring grid points)
            # can only replace one (`inequality_step`). The step is then the filter's on E's
            # and the working rows (noise-free as E's: `r_rel`).
            C, C_a = rows
            n_rows = C.shape[0]
            n_checked = n_rows + (2 * d.shape[0] if radius is not None else 0)
            box_slack = 0.0 if radius is None else 1e-3 * radius  # (the rows are d_i - radius)
            if radius is not None:
                eye = jnp.eye(d.shape[0], dtype=d.dtype)
                C = jnp.concatenate([C, jnp.full(2 * d.shape[0], -radius, d.dtype)])
                C_a = jnp.concatenate([C_a, eye, -eye])
            if gap_rows is not None:
                C = jnp.concatenate([C, gap_rows[0]])
                C_a = jnp.concatenate([C_a, gap_rows[1]])
            redundant = jnp.zeros(C.shape, bool)
            if radius is not None:
                redundant = _redundant_simple_rows(C, C_a, n_rows, radius)
            prior_var = jnp.einsum("ip,pq,iq->i", C_a, P, C_a)  # before any observation
            r_c = self.r_rel * prior_var + 1e-300
            threshold = 0.01 * self.ctol
            max_rounds = 4 * d.shape[0] + 20
            # the rows active in the last QP (their multipliers in `lam`) start the active set
            warm = jnp.concatenate([lam[m:] > 0, jnp.zeros(C.shape[0] - n_rows, bool)])
            # Within the box the model rises above its value at E's step d by at most
            # |B| |e|^2 / 2, |e| <= |d| + sqrt(n) radius (d minimizes it on E's rows): a dual
            # objective past 10 x that (a margin for the filter's noisy rows) proves the hard
            # QP infeasible (`dual_active_set(dual_bound=)`). No bound without the box.
            dual_bound = jnp.inf
            if radius is not None:
                reach = jnp.linalg.norm(d) + math.sqrt(d.shape[0]) * radius
                dual_bound = 5.0 * jnp.linalg.norm(B) * reach**2

            # Elastic mode. If the linearized constraints are inconsistent (the hard step is,
            # as defined below; or a row that E's rows alone pin, its variance left by them below
            # `ELASTIC_PINNED` of its prior: at a start at rest, the bounds of a control that
            # E's rows alone fix), the equalities are filtered again with one noise for
            # all, `elastic` x the mean of h P h^T: a penalty on |H d + E|^2 (E as the user
            # scaled it, so that repeated elastic steps end at a stationary point of that
            # violation, which `locally_infeasible` recognizes) instead of hard rows. The step
            # honours every inequality and meets E as far as they allow (the filter's form of
            # an l2 elastic / feasibility-restoration step). There the QP's Hessian is
            # B + H^T R^-1 H (R the equalities' noise) and it has no equality rows. If the
            # inequalities are inconsistent by themselves (that step is too: a reach x(tf) >= 1
            # that no bounded control meets at the current tf; with no E to soften, the hard
            # QP's step went past its bounds, multipliers 1e97, STALLED; issue 49), a third
            # round also softens the path and terminal inequality rows violated now (C >
            # `ctol`) and those that held the elastic step (`held` below), observed at their
            # boundary with one noise for all softened rows (a penalty on (C + C_a d)^2), while
            # the bounds on the parameters, the step's box and the knot gaps stay hard; its
            # Hessian is B + A^T R^-1 A over all softened rows.
            pinned = jnp.einsum("ip,pq,iq->i", C_a, P1, C_a) < ELASTIC_PINNED * prior_var
            pinned_violated = jnp.any((pinned & (C + C_a @ d > self.ctol))[:n_rows])
            r_soft = jnp.full_like(hph, self.elastic * jnp.mean(hph) + 1e-300)
            n_soft = n_rows - (0 if ev.V is None else ev.V.shape[0])  # path and terminal rows
            C_s, C_as = C[:n_soft], C_a[:n_soft]
            violated = C_s > self.ctol

            # Inconsistent: the active set's own excess over the problem's rows is above `ctol`
            # and the final step confirms it (a row outside the working set past `ctol` there:
            # the dual's iterate drifts from the refiltered step where its multipliers are large,
            # 1.7e-6 over a row that the final step met to 2e-11 sent a random QP to the third
            # round in one test process and not in another; issue 49),
            # or the final step (its working rows refiltered) leaves a problem's row past 100
            # `ctol` or a step bound past 1e-3 of the radius. Refiltered through a nearly
            # singular covariance the working rows can leave the step past a bound the active
            # set met (the moon lander's start: a flat switch time of variance 1e8 took E's
            # step of 2 in tf past a radius of 1 and moved by -1, by -0.2 after a 1e-13
            # perturbation; the scaled step followed round-off; RESULTS.md). That excess is of
            # the order of the radius; the margin of 1e-3 of it is far above the round-off of a
            # consistent step (1.5e-6 of the radius on a QP with two directions of curvature
            # 1e-8: a margin of 1e-6 sent it to the elastic step, which left E as large as it
            # was; `test_qp_step.py`). The margin of 100 `ctol` leaves the refiltering's
            # round-off at a degenerate vertex alone (a unicycle with every control on its
            # bound: past `ctol` by round-off, and an elastic step there stalled; a pendulum's
            # minimum time needs the rows' final excess counted).
            # The hard step, then (only if it is needed) the elastic one, then (only if that is
            # inconsistent too) the one with the violated inequalities softened: rounds of one loop,
            # so that the dual active set is compiled once (issue 21); the elastic round's
            # equality rows are zeros, and it counts none of them in the rank of the working set.
            def round_(carry):
                k, (*_, before, _, held) = carry
                elastic, softer = k >= 1, k == 2
                # the third round softens the violated rows, and those that held the elastic step
                soft = softer & (violated | (held & before[:n_soft]))
                noise = self.elastic * (jnp.sum(hph) + jnp.sum(jnp.where(soft, prior_var[:n_soft], 0.0)))
                noise = noise / jnp.maximum(m + jnp.sum(soft), 1).astype(noise.dtype) + 1e-300
                r_eq = jnp.where(softer, noise, jnp.where(elastic, r_soft, r))
                d_eq, P_eq = self._equality_step(prior, P, ev, r_eq, refine=~elastic)
                # (their observations only in that round: a scan over every path row otherwise)
                d_eq, P_eq = lax.cond(
                    softer,
                    lambda: sequential_update(d_eq, P_eq, C_as, -C_s, jnp.full_like(C_s, noise), active=soft)[:2],
                    lambda: (d_eq, P_eq),
                )
                soft = jnp.concatenate([soft, jnp.zeros(C.shape[0] - n_soft, bool)])
                d, P2, active, _, excess = inequality_step(
                    d_eq,
                    P_eq,
                    jnp.where(elastic, 0.0, ev.H),
                    jnp.where(soft | redundant, -jnp.inf, C),  # (a softened row is no hard row)
                    C_a,
                    r_c,
                    prior_var,
                    self.path_dependence,
                    threshold,
                    max_rounds,
                    (jnp.where(elastic, P_eq, P), ev.E, r),
                    num_equalities=jnp.where(elastic, 0, m),
                    warm=warm,
                    pinned=pinned & ~elastic,  # (E's rows are soft in the elastic rounds)
                    dual_bound=jnp.where(elastic, jnp.inf, dual_bound),
                )
                final = C + C_a @ d
                outside = jnp.where(active, -jnp.inf, final)  # the rows the active set left out
                inconsistent = (
                    (
                        (jnp.max(excess[:n_rows], initial=-jnp.inf) > self.ctol)
                        & (jnp.max(outside[:n_rows], initial=-jnp.inf) > self.ctol)
                    )
                    | (jnp.max(final[:n_rows], initial=-jnp.inf) > 100.0 * self.ctol)
                    | (jnp.max(final[n_rows:n_checked], initial=-jnp.inf) > box_slack)
                )
                # Held: the elastic step lowers E's linear model by less than 1 % while met
                # path or terminal rows, not the step's box, hold it (a stationary point of
                # |E|^2 with those rows hard is none of the violation, where a row at its bound
                # costs only (C + C_a d)^2: a least time whose half-space held the level at its
                # bound and tf at 0.07 of the least ended CONSTRAINT_STATIONARY; issue 49)
                held = (
                    elastic
                    & ~softer
                    & ~jnp.any(violated)
                    & (jnp.sum((ev.E + ev.H @ d) ** 2) > 0.98 * jnp.sum(ev.E**2))
                    & jnp.any(active[:n_soft])
                    & ~jnp.any(active[n_rows:n_checked])
                )
                return k + 1, (d, P2, active, inconsistent, held)

            def again(carry):
                k, (*_, inconsistent, held) = carry
                # (the third round only where it softens a row: else it repeats the second)
                third = (k == 2) & ((inconsistent & jnp.any(violated)) | held)
                return (k == 0) | ((k == 1) & (pinned_violated | inconsistent)) | third

            unused = (d, P1, jnp.zeros(C.shape, bool), jnp.array(False), jnp.array(False))
            _, (d, P1, active, _, _) = lax.while_loop(again, round_, (jnp.array(0), unused))
            if gap_rows is not None:
                gaps_held = jnp.where(active[C.shape[0] - gap_rows[0].shape[0] :, None], gap_rows[1], 0.0)
            active = active[:n_rows]
        d, _ = keep_knots_ordered(d, P1, knots, dknots, self.a_t, collapse=self.path_active)
        # multipliers of [E; active C] from stationarity (nu >= 0, zero off the active set)
        lam_qp = self._stationary_multipliers(ev, B, d, None if rows is None else active, gaps_held)
        if rows is not None:
            lam_qp = lam_qp.at[m:].set(jnp.where(active, jnp.maximum(lam_qp[m:], 0.0), 0.0))
        return d, lam_qp

    def release_inactive(self, ev: Evaluation, lam):
        """`lam` with the multipliers of the inequality rows that are inactive by more than
        `ctol` (C < -`ctol`) set to 0 (complementarity at the current point), whether or not
        the QP's step makes them active again. A multiplier kept there from a shortened step
        ((1 - alpha) of its old value) adds dnu C > 0 to the merit's slope along (d, lambda_qp -
        lambda); near the optimum that term outweighs -d^T B d and no direction is a descent
        one (measured on the attitude slew: nu = 9.5e-3 at C = -3.4e-6 made the slope +3.5e-8,
        STALLED). One kept on a row that the last step over-satisfied (a minimum time whose
        reach row ended at C = -0.125 with nu = 1.16) made the merit's model predict an
        increase for the QP's step back to the row: STALLED at tf = 1.5 (sqrt(2) optimal); one
        kept on a row 2.5e-7 inside its bound made the step to the vertex merit-neutral (its
        objective gain nu |C| cancelled by the nu C term), STALLED 1.7e-7 above the optimum."""
        rows = inequality_rows(ev)
        if rows is None:
            return lam
        m = ev.E.shape[0]
        stale = rows[0] < -self.ctol
        return lam.at[m:].set(jnp.where(stale, 0.0, lam[m:]))

    def _equality_step(self, prior, P, ev, r, refine=True):
        """The filter on H d = -E with noise `r`, plus (where `refine`) one refinement pass
        (the same update with the first estimate as prior mean: its B-metric projection onto
        H d = -E). When H P H^T is ill-conditioned (rows nearly dependent in the metric of P),
        the residual left by a noise r relative to the diagonal h P h^T is not small
        (measured 8e-7 = 1.5 |E| on case 7 near its optimum, cond B 2e7); one pass brings it
        to 1e-13. Not for the elastic step's noisy rows: the second pass weighs E twice while
        the covariance counts it once, and the inequality rows, conditioned through that
        covariance, then move the step off the penalty's minimizer (26 % past the
        Gauss-Newton step of a locally infeasible problem, whose trust region then stalled
        1e-6 short of the violation's stationary point; docs/history.md)."""
        d1, _, _ = sequential_update(prior, P, ev.H, -ev.E, r)
        d2, P1, _ = sequential_update(d1, P, ev.H, -ev.E, r)  # (P1 does not depend on the mean)
        return jnp.where(refine, d2, d1), P1

    @staticmethod
    def _stationary_multipliers(ev, B, d, active, held=None):
        """Least-squares solution of [H; C_a(active); held]^T lam = -(G_a + B d), returned
        without the multipliers of `held` (the knot gaps in the QP's active set). A collapsed
        segment is held by its gap (a positive multiplier, the objective's pull on the knot):
        left out of the solve, that pull goes into the multipliers of E, and the merit's
        minimum with a capped penalty lies a violation of ~|delta lambda| / mu away from the
        optimum (docs/history.md, session 39). Row combinations within sqrt(eps) of dependent
        (relative singular values) carry no multiplier: at a start at rest, E's columns of the
        switch times and tf are 0, and after a perturbation eps they are ~eps: the residual
        along them, which the QP's box and knot rows leave, went into E's multipliers as
        ~1/eps (1e12 from a 1e-12 perturbation, 1.2 without; docs/history.md, session 40)."""
        rows = inequality_rows(ev)
        A = (
            ev.H
            if active is None or rows is None
            else jnp.concatenate([ev.H, jnp.where(active[:, None], rows[1], 0.0)])
        )
        n = A.shape[0]
        if held is not None:
            A = jnp.concatenate([A, held])
        return multipliers(A, ev.G_a + B @ d, rcond=jnp.sqrt(jnp.finfo(d.dtype).eps))[:n]

    def correction(self, ev: Evaluation, B, E_cand, knots, dknots, d):
        """Second-order correction of a step d: the smallest step (metric B) with
        H d_soc = -(E(a + d) - (E + H d)), H at the current point, so that d + d_soc absorbs
        the constraints' curvature along d (Nocedal & Wright sec. 15.4); knot order kept.
        The target is the linear model's error, not E(a + d) itself: the two agree for a step
        that meets the linearized constraints, but a step cut short (a radius, a box, a normal
        step cut to the trust region) leaves part of E by design, and a correction to
        E(a + d) = 0 took the rest of the feasibility step without the cut, 100x longer than
        d (orbit raising under the line search STALLED: docs/history.md, session 40).
        The parameter rows (bounds, `Evaluation.V`: linear, never crossed) stay honoured: those
        that d meets or holds are observed as C_a d_soc = 0, and the correction is scaled back
        so that it crosses no other (a correction that ignored them took a pendulum's level
        2e-2 past its bound under the line search, which then STALLED there)."""
        P = _covariance(B)
        r = self.r_rel * jnp.einsum("ip,pq,iq->i", ev.H, P, ev.H) + 1e-300
        rows, target = ev.H, -curvature_error(ev, E_cand, d)
        on = jnp.ones(target.shape, bool)
        V_a = ev.V_a
        at = None if ev.V is None or V_a is None else ev.V + V_a @ d  # the parameter rows at the step
        if at is not None and V_a is not None:
            rows, target = jnp.concatenate([rows, V_a]), jnp.concatenate([target, jnp.zeros_like(at)])
            r = jnp.concatenate([r, self.r_rel * jnp.einsum("ip,pq,iq->i", V_a, P, V_a) + 1e-300])
            on = jnp.concatenate([on, at >= -self.ctol])
        dc, _, _ = sequential_update(jnp.zeros_like(d), P, rows, target, r, active=on)
        dc, _, _ = sequential_update(dc, P, rows, target, r, active=on)
        if at is not None and V_a is not None:
            rate, room = V_a @ dc, jnp.maximum(-at, 0.0) + self.ctol
            dc = jnp.min(jnp.where(rate > room, room / rate, 1.0), initial=1.0) * dc
        total, _ = keep_knots_ordered(d + dc, P, knots, dknots, self.a_t, collapse=self.path_active)
        return jnp.where(jnp.all(jnp.isfinite(total)), total - d, 0.0)

    # ------------------------------------------------------------------ state machine

    def check(self, problem, control):
        require_rows(problem, control, "KalmanSQP")

    def init(self, problem, control, a0, simulator, max_steps):
        self.check(problem, control)
        return self.globalization.init(self, problem, control, a0, simulator, max_steps)

    def step(self, problem, control, simulator, state):
        return self.globalization.step(self, problem, control, simulator, state)

    def progress(self, state):
        return {
            "iterations": state.num_iterations,
            "objective": state.ev.G,
            "max|E|": jnp.max(jnp.abs(state.ev.E), initial=0.0),
            **self.globalization.progress(state),
        }

    def postprocess(self, problem, control, simulator, state) -> Solution:
        ev = with_knot_gaps(control, state.ev, state.a)
        residual, multipliers = kkt_residual(ev, state.a, self.path_active, with_multipliers=True)
        return Solution.from_evaluation(
            state.ev,
            state.a,
            control=control,
            active_tol=self.path_active,
            multipliers=multipliers,
            projected_gradient=residual,
            iterations=state.num_iterations,
            integrations=state.num_integrations,
            steps=state.num_steps,
            done=state.done,
            status=state.status,
            history=state.history,
        )
