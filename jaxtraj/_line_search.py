"""KalmanSQP's merit line search (`KalmanSQP(globalization=jt.LineSearch())`; with BFGS,
`KalmanSQP(hessian="bfgs", globalization="line-search")`, jt.solve's default until 2026-12-04).

Backtracking on the augmented-Lagrangian merit function phi(a, lambda) = G + lambda^T E +
mu/2 |E|^2 (+ the PHR terms of the path constraints) over (a + alpha d, lambda + alpha
(lambda_qp - lambda)) (Schittkowski's merit function; unlike the l1 merit it accepts unit steps
near the solution, so the superlinear rate is not lost to the Maratos effect). The penalty mu
rises until d is a descent direction for the merit; a rejected full step is retried once with
a second-order correction.

(The algorithm, its history and measurements: docs/solvers/kalman-sqp.md, "Line search".)
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ._checks import check_settings, is_count
from ._driver import SolverState, only_where, start_counters
from ._kkt import (
    active_rows,
    inequality_rows,
    is_feasible,
    kkt_outcome,
    kkt_residual,
    lagrangian_gradient,
    least_squares_multipliers,
    locally_infeasible,
    merit,
    merit_value,
    scale_free,
    with_knot_gaps,
    without_scale,
)
from ._penalty import PenaltyCap, far_from_feasible, natural_scale, violation_of
from ._sensitivity import Evaluation, lagrangian_hessian
from ._status import Status, failed

#: Far from feasible (`_penalty.far_from_feasible` with this ratio, `TrustRegion`'s
#: `feasibility_first`) the penalty is never capped: the violation's descent needs it.
FAR = 0.1


def bfgs_update(B, s, y, damping=0.2):
    """Powell-damped BFGS update of a Hessian approximation B with step s, gradient change y.

    If s^T y < damping s^T B s, y is replaced by r = theta y + (1 - theta) B s with theta
    chosen so that s^T r = damping s^T B s; then B+ = B - B s s^T B / s^T B s + r r^T / s^T r,
    positive definite whenever B is (Nocedal & Wright, Procedure 18.2, with damping 0.2).
    The update is skipped (B returned) for a zero or non-finite step.
    """
    Bs = B @ s
    sBs = s @ Bs
    sy = s @ y
    theta = jnp.where(sy >= damping * sBs, 1.0, (1.0 - damping) * sBs / jnp.where(sBs - sy > 0, sBs - sy, 1.0))
    r = theta * y + (1.0 - theta) * Bs
    sr = s @ r
    ok = (sBs > 0) & (sr > 0) & jnp.isfinite(sBs) & jnp.all(jnp.isfinite(r))
    safe = lambda v: jnp.where(ok, v, 1.0)
    B1 = B - jnp.outer(Bs, Bs) / safe(sBs) + jnp.outer(r, r) / safe(sr)
    return jnp.where(ok, 0.5 * (B1 + B1.T), B)


def _bfgs_step(B, s, cand: Evaluation, ev: Evaluation, lam):
    """BFGS update with the change of the Lagrangian's gradient (multipliers `lam`)."""
    return bfgs_update(B, s, lagrangian_gradient(cand, lam) - lagrangian_gradient(ev, lam))


class LineSearchState(SolverState):
    """KalmanSQP's state with the line search."""

    a: jax.Array
    ev: Evaluation
    lam: jax.Array
    B: jax.Array
    mu: jax.Array
    cap: PenaltyCap  # where the penalty was last capped (`LineSearch.mu_max`)
    d: jax.Array  # search direction of the line search in progress
    dlam: jax.Array
    alpha: jax.Array
    phi0: jax.Array
    dphi0: jax.Array
    searching: jax.Array  # a line search is in progress (alpha < 1 pending)
    soc: jax.Array  # the pending candidate is a + d + d_soc (second-order correction)
    d_soc: jax.Array
    alpha_bt: jax.Array  # the backtracking step to try if the correction is rejected too
    radius: jax.Array  # step cap |d|_inf
    num_flat: jax.Array  # accepted steps in a row within the merit's round-off (see `step`)
    best_gradient: jax.Array  # the smallest projected gradient at an accepted point
    streak: jax.Array  # steps in a row at an acceptable point (`_kkt.kkt_outcome`)
    scale_free: jax.Array  # the problem cannot see the parameters' scale (`_kkt.scale_free`)


class LineSearch(eqx.Module):
    """KalmanSQP's merit line search (docs/solvers/kalman-sqp.md). Fields:

    - `radius`: initial cap on a step's largest component |d_i| (parameter units, 0.5).
    - `armijo`: sufficient-decrease factor (1e-4).
    - `min_step`: smallest step before no progress is declared (1e-8).
    - `mu_max`, `cap_progress`: near feasibility the penalty carried over to the next
      direction is capped at `mu_max` x |B|_F / |A|_F^2 (100; B the QP's Hessian, A the rows
      of E and the active inequality rows), by `TrustRegion`'s rule (the same two settings):
      a penalty kept at what a step that traded objective for a little feasibility once
      asked for made the merit crawl (orbit raising with BFGS: 114-399 iterations over a start
      and its round-off perturbations, a penalty of 5e4 at |E| ~ 5e-5).
    - `flat_steps`: accepted steps in a row within the merit's round-off (and without halving
      the projected gradient) that count as no progress (10).
    """

    radius: float = 0.5
    armijo: float = 1e-4
    min_step: float = 1e-8
    mu_max: float = 100.0
    cap_progress: float = 0.01
    flat_steps: int = 10

    def __check_init__(self):
        checks = {
            "radius": lambda: 0 < self.radius < math.inf,
            "armijo": lambda: 0 < self.armijo < 0.5,
            "min_step": lambda: 0 < self.min_step < 1,
            "mu_max": lambda: 0 < self.mu_max < math.inf,
            "cap_progress": lambda: 0 <= self.cap_progress < 1,
            "flat_steps": lambda: is_count(self.flat_steps, 1),
        }
        check_settings("LineSearch", self, checks)

    def start(self, sqp, ev, lam, mu, B, d, lam_qp):
        """Penalty update and the merit's value and slope at alpha = 0."""
        dlam = lam_qp - lam
        m = ev.E.shape[0]
        rows = inequality_rows(ev)
        C, Cd = (None, None) if rows is None else (rows[0], rows[1] @ d)
        Gd, Hd = ev.G_a @ d, ev.H @ d

        def slope(mu, raising=False):
            # d/dalpha of the merit of the linearized constraints along (d, dlam), one-sided
            # (alpha -> 0+): a row takes the PHR branch nu C + mu/2 C^2 where nu + mu C > 0,
            # or = 0 and growing along the step. At mu = 0 a row whose multiplier is 0 and
            # rises (a violated row entering the QP's active set) adds dnu C; the two-sided
            # rule missed it (Bryson-Denham from random starts: slope -24 against +87 by
            # finite differences, so no step length was accepted). `raising`: the branch of
            # mu -> 0+ instead, for the penalty's Newton steps: a violated row with nu = 0 is
            # on for every mu > 0, so its C C_a d lowers the slope as mu grows; at mu = 0 it
            # was off, the slope flat in mu, and the penalty never left 0 (an elastic step
            # whose softened reach row had no multiplier: STALLED, issue 49).
            on = None
            if C is not None:
                s, ds = lam[m:] + mu * C, dlam[m:] + mu * Cd
                on = (s > 0) | ((s == 0) & ((ds > 0) | (raising & (C > 0))))

            def phi(alpha):
                C_alpha = None if C is None else C + alpha * Cd
                return merit_value(ev.G + alpha * Gd, ev.E + alpha * Hd, C_alpha, lam + alpha * dlam, mu, on)

            return jax.jvp(phi, (jnp.zeros_like(mu),), (jnp.ones_like(mu),))[1]

        # The penalty rises until the slope is at most -1/2 d^T B d, where raising it lowers
        # the slope (the slope is affine in mu for the terminal part, piecewise for the PHR
        # terms): Newton steps on slope(mu) = target, doubled for a margin.
        target = -0.5 * (d @ B @ d)
        # Only a violation above `ctol` raises it: with E and C met (at round-off), the slope
        # hardly depends on mu, and the Newton step would ask for an enormous penalty whose
        # term mu/2 |E|^2 turns E's round-off into merit noise above any decrease.
        infeasible = jnp.max(jnp.abs(ev.E), initial=0.0) > sqp.ctol
        if C is not None:
            infeasible = infeasible | (jnp.max(C) > sqp.ctol)

        def raise_mu(_, mu):
            value, c1 = jax.jvp(lambda mu: slope(mu, raising=True), (mu,), (jnp.ones_like(mu),))
            needed = mu + (value - target) / jnp.where(c1 < 0, -c1, 1.0)
            return jnp.where((value > target) & (c1 < 0) & infeasible, jnp.maximum(2.0 * needed, mu), mu)

        mu = lax.fori_loop(0, 1 if rows is None else 4, raise_mu, mu)
        return dlam, mu, merit(ev, lam, mu), slope(mu)

    def init(self, sqp, problem, control, a0, simulator, max_steps):
        # Nothing is integrated here: the first `step` evaluates the start as its candidate
        # (its least-squares multipliers, the exact Hessian), so the compiled program
        # holds the evaluation kernels once, in the step (issue 21).
        ev, lam = sqp.unevaluated(problem, control, a0, simulator)
        f = jnp.float64
        zero = jnp.zeros_like(a0)
        return LineSearchState(
            a=a0,
            ev=ev,
            lam=lam,
            B=jnp.eye(a0.shape[0], dtype=f),
            mu=jnp.asarray(0.0, f),
            cap=PenaltyCap.none(),
            d=zero,
            dlam=jnp.zeros_like(lam),
            alpha=jnp.asarray(1.0, f),
            phi0=jnp.asarray(0.0, f),
            dphi0=jnp.asarray(0.0, f),
            searching=jnp.array(True),  # no direction before the start is evaluated
            soc=jnp.array(False),
            d_soc=zero,
            alpha_bt=jnp.asarray(1.0, f),
            radius=jnp.asarray(self.radius, f),
            num_flat=jnp.array(0, jnp.int32),
            best_gradient=jnp.asarray(jnp.inf, f),
            streak=jnp.array(0, jnp.int32),
            scale_free=jnp.array(False),
            **start_counters(max_steps, ("alpha", "kind")),
        )

    def step(self, sqp, problem, control, simulator, state: LineSearchState):
        ev, a, lam = state.ev, state.a, state.lam
        knots, dknots = control.knots(a), jax.jacfwd(control.knots)(a)

        def start(B):
            d, lam_qp = sqp.direction(ev, B, lam, knots, dknots, state.radius)
            d = without_scale(d, a, state.scale_free)  # (`_kkt.scale_free`)
            d_max = jnp.max(jnp.abs(d))
            capped = d_max > state.radius
            cut = jnp.where(capped, state.radius / jnp.where(capped, d_max, 1.0), 1.0)
            d = d * cut
            base = sqp.release_inactive(ev, lam)
            # Without inequality rows the QP has no box (`KalmanSQP.direction`): its step and
            # multipliers are the unbounded QP's, and the multipliers' step is cut with d, as
            # (d, lambda_qp - lambda) is one direction of the merit's search: a cut d beside
            # the whole multiplier step made a slope of dlam^T E alone (orbit raising, BFGS:
            # steps of 1e-5 in a accepted for the merit's multiplier term, multipliers 2e4
            # where they are 1.4, STALLED; issue 49). With rows the box is in the QP, whose
            # multipliers belong to its bounded step (cut again, a least-time problem of the
            # random-problem oracle STALLED).
            if inequality_rows(ev) is None:
                lam_qp = base + cut * (lam_qp - base)
            return (d, base, *self.start(sqp, ev, base, carried, B, d, lam_qp))

        # A fresh direction (no integration) unless a search is pending; if B's step is no
        # descent direction for the merit (B degenerated, or the knot ordering bent the step),
        # once more from a scaled identity. A loop of at most two rounds, so that the QP is
        # compiled once; under vmap a lane whose loop ended keeps its result.
        fresh = ~state.searching
        # the penalty carries over, capped near feasibility (`mu_max`, `cap_progress`); never
        # at an acceptable point (`_kkt.kkt_outcome`)
        rows = ev.H if inequality_rows(ev) is None else active_rows(ev, sqp.path_active)
        viol = violation_of(ev)
        eligible = fresh & ~far_from_feasible(ev, a, FAR) & (state.streak == 0)
        carried, cap = state.cap.carried(
            state.mu, natural_scale(state.B, rows), viol, ev.G, eligible, self.mu_max, self.cap_progress, sqp.ctol
        )
        B_reset = jnp.trace(state.B) / a.shape[0] * jnp.eye(a.shape[0])

        def round_(carry):
            tries, _, _ = carry
            B = jnp.where(tries == 0, state.B, B_reset)
            return tries + 1, B, start(B)

        def again(carry):
            tries, _, out = carry
            return fresh & ((tries == 0) | ((tries == 1) & ~(out[5] < 0)))

        f0 = jnp.zeros((), a.dtype)
        unused = (jnp.zeros_like(a), lam, jnp.zeros_like(lam), state.mu, f0, f0)
        _, B, (d_new, lam_new, dlam_new, mu_new, phi0_new, dphi0_new) = lax.while_loop(
            again, round_, (jnp.array(0), state.B, unused)
        )
        pick = lambda new, old: jnp.where(fresh, new, old)
        d, dlam, lam = pick(d_new, state.d), pick(dlam_new, state.dlam), pick(lam_new, lam)
        mu, phi0, dphi0 = pick(mu_new, state.mu), pick(phi0_new, state.phi0), pick(dphi0_new, state.dphi0)
        raised = fresh & (mu_new > carried)
        alpha = jnp.where(fresh, 1.0, state.alpha)

        # one integration: the candidate (the first step's is the start, weighed with its
        # least-squares multipliers)
        first = state.num_steps == 0
        soc = state.soc
        step_taken = alpha * d + jnp.where(soc, state.d_soc, 0.0)
        lam_c = lam + alpha * dlam

        cand = sqp.restricted(problem, control, a + step_taken, simulator)
        least_squares = lambda cand: jnp.nan_to_num(
            least_squares_multipliers(cand, sqp.path_active), nan=0.0, posinf=0.0, neginf=0.0
        )
        lam_c = only_where(first, least_squares, lam_c, cand)
        phi = merit(cand, lam_c, mu)
        finite = (cand.status == Status.SUCCESS) & jnp.isfinite(phi)
        descent = dphi0 < 0
        # Armijo, relaxed by the merit's round-off (10 eps |phi|): near the solution the
        # predicted decrease falls below what float64 can resolve.
        slack = 10.0 * jnp.finfo(phi.dtype).eps * (1.0 + jnp.abs(phi0))
        accept = finite & (first | (descent & (phi <= phi0 + self.armijo * alpha * dphi0 + slack)))

        # accepted: the Hessian at the new point, exact (the trust region's kernel: a second
        # integration) or, with BFGS, updated
        if sqp.hessian == "bfgs":
            # exact at the start, for the first `exact_iterations` iterations and (unless pure
            # BFGS, `exact_iterations=0`) at the accepted candidate of a line search that
            # backtracked: a BFGS model whose full step was rejected is replaced by the exact
            # one (BFGS cannot learn a free scale of the parameters, e.g. a control vector
            # normalized in the dynamics; measurements in benchmarks/RESULTS.md)
            early = first | (state.num_iterations < sqp.exact_iterations)
            if sqp.exact_iterations > 0:
                early = early | ~fresh
        else:
            early = jnp.array(True)
        # rejected: a shorter step (quadratic interpolation of the merit, safeguarded)
        curv = (phi - phi0 - dphi0 * alpha) / alpha**2
        alpha_q = jnp.where(curv > 0, -dphi0 / (2.0 * jnp.where(curv > 0, curv, 1.0)), 0.1 * alpha)
        alpha_q = jnp.where(finite, jnp.clip(alpha_q, 0.1 * alpha, 0.5 * alpha), 0.1 * alpha)
        # A rejected full step is first retried with a second-order correction (the
        # constraints' curvature: the candidate's E observed from the same point), and the
        # backtracking step is kept for the case that the correction fails too.
        try_soc = fresh & ~accept & finite & descent
        alpha_next = jnp.where(soc, state.alpha_bt, jnp.where(try_soc, 1.0, alpha_q))
        d_soc = sqp.correction(ev, B, cand.E, knots, dknots, d)

        new_a = jnp.where(accept, a + step_taken, a)
        new_ev = jax.tree.map(lambda c, o: jnp.where(accept, c, o), cand, ev)
        new_lam = jnp.where(accept, lam_c, lam)
        maxE = jnp.max(jnp.abs(new_ev.E), initial=0.0)
        kkt_ev = with_knot_gaps(control, new_ev, new_a)
        pg = kkt_residual(kkt_ev, new_a, sqp.path_active)
        feasible = is_feasible(new_ev, sqp.ctol)
        # No measurable progress is left: the line search failed, the direction is no
        # descent, the step is negligible, or `flat_steps` steps in a row were accepted only
        # within the merit's round-off without halving the projected gradient.
        improved = pg < 0.5 * state.best_gradient
        unresolved = accept & ~first & (phi > phi0 - slack) & ~improved
        flat = jnp.where(accept, jnp.where(unresolved, state.num_flat + 1, 0), state.num_flat)
        negligible = jnp.linalg.norm(step_taken) <= 1e-15 * (1.0 + jnp.linalg.norm(a))
        no_progress = ~first & (
            (~accept & ~try_soc & (alpha_next < self.min_step))
            | ~descent
            | (accept & negligible)
            | (flat >= self.flat_steps)
        )
        converged, stalled, streak = kkt_outcome(
            feasible, pg, new_ev.G, sqp.gtol, sqp.acceptable_gtol, no_progress, state.streak, sqp.acceptable_steps
        )
        bad_start = first & ~accept
        done = converged | stalled | bad_start
        infeasible = stalled & ~feasible  # tested only there (least squares over every row)
        live = ~state.done  # (under `vmap` a finished lane still runs the step: no extra work)
        infeasible = only_where(
            infeasible & live,
            lambda ev: locally_infeasible(ev, sqp.path_active, sqp.acceptable_gtol),
            infeasible,
            kkt_ev,
        )

        exact = accept & early & ~done  # (none at the last point)

        # (with the exact Hessian, whether the problem sees the parameters' scale: a property of
        # the problem, tested where the raw Hessian is at hand)
        def exact_hessian(a, cand, lam):
            W = lagrangian_hessian(problem, control, a, simulator, lam)
            return sqp.qp_hessian(W, cand.H), scale_free(cand, a, W, lam)

        B_acc, free = only_where(
            exact & live,
            exact_hessian,
            (_bfgs_step(B, step_taken, cand, ev, lam_c) if sqp.hessian == "bfgs" else B, state.scale_free),
            a + step_taken,
            cand,
            lam_c,
        )
        i = state.num_steps
        history = state.history.record(
            i,
            objective=new_ev.G,
            max_constraint_error=maxE,
            step_norm=jnp.linalg.norm(step_taken),
            accepted=accept,
            constraint_tolerance=sqp.ctol,
            details={"alpha": alpha, "kind": jnp.where(first, 0, jnp.where(fresh, 1, jnp.where(soc, 3, 2)))},
        )
        return LineSearchState(
            a=new_a,
            ev=new_ev,
            lam=new_lam,
            B=jnp.where(accept, B_acc, B),
            mu=mu,
            cap=state.cap.update(cap, viol, ev.G, raised),
            d=d,
            dlam=dlam,
            alpha=jnp.where(accept, 1.0, alpha_next),
            phi0=phi0,
            dphi0=dphi0,
            searching=~accept,
            soc=~accept & try_soc,
            d_soc=d_soc,
            alpha_bt=jnp.where(try_soc, alpha_q, state.alpha_bt),
            radius=jnp.where(
                accept & ~first,
                jnp.where(alpha < 1.0, alpha * jnp.max(jnp.abs(d)), jnp.minimum(2.0 * state.radius, 1e3)),
                state.radius,
            ),
            num_flat=flat.astype(jnp.int32),
            best_gradient=jnp.where(accept & improved, pg, state.best_gradient),
            streak=streak,
            scale_free=free,
            num_iterations=state.num_iterations + (accept & ~first).astype(jnp.int32),
            num_integrations=state.num_integrations + 1 + exact.astype(jnp.int32),
            num_steps=i + 1,
            done=done,
            status=Status.where(
                bad_start,
                failed(cand.status),
                Status.where(
                    converged,
                    Status.SUCCESS,
                    Status.where(infeasible, Status.CONSTRAINT_STATIONARY, Status.STALLED),
                ),
            ),
            history=history,
        )

    def progress(self, state: LineSearchState):
        return {"alpha": state.alpha, "mu": state.mu}
