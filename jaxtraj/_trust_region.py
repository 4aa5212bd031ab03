"""KalmanSQP's trust-region globalization (`KalmanSQP()`'s and `jt.solve`'s default:
`hessian="exact"`, `globalization=jt.TrustRegion()`): a Byrd-Omojokun composite-step SQP with
the exact Hessian of the Lagrangian (Nocedal & Wright sec. 18.5), its constraint parts
computed by the sequential Kalman update.

Without inequality constraints each step is d = v + u within |d|_2 <= radius: the normal step
v is the filter's minimum-norm step towards the linearized constraints H v = -E (or Powell's
dogleg), the tangential step u = V w solves the trust-region subproblem on the null space of H
exactly (More and Sorensen), so it follows negative curvature; far from feasible the step is
v alone. With inequalities the step is the line search's QP (`KalmanSQP.direction`) in the box
|d_i| <= radius. A candidate is accepted on the ratio of the actual to the predicted decrease
of an augmented-Lagrangian merit (a rejected one is retried with a second-order correction),
and the radius follows that ratio.

(The algorithm, its history and measurements: docs/solvers/kalman-sqp.md, "Trust region".)
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ._bounds import bound_excess, knot_gap_rows
from ._checks import check_settings
from ._driver import SolverState, only_where, start_counters
from ._kalman import sequential_update
from ._kkt import (
    active_rows,
    curvature_error,
    inequality_rows,
    is_feasible,
    kkt_outcome,
    kkt_residual,
    least_squares_multipliers,
    locally_infeasible,
    merit,
    merit_value,
    scale_free,
    with_knot_gaps,
    without_scale,
)
from ._penalty import PenaltyCap, far_from_feasible, natural_scale, violation, violation_of
from ._sensitivity import Evaluation, evaluate_jitted, lagrangian_hessian
from ._status import Status, failed

_BISECTIONS = 64  # of the trust-region shift sigma (a scalar; 2^-64 of the bracket)


def _curvature_floor(ev: Evaluation, lam, a):
    """The curvature an exact Hessian of the Lagrangian must exceed to count: sqrt(eps)
    (|G_a| + |[H; C_a]^T lambda|) / (1 + |a|), relative to the curvature the gradient's terms
    would have over the parameters' scale. Below it `convexify_blockwise` sees no curvature. A
    Hessian of round-off (max-range's start: the two terms of W cancel to 5e-16) has random
    directions, and the QP's B made of it misjudged which rows the equalities pin (an elastic
    step on consistent constraints: a false SUCCESS at a saddle, docs/history.md). So does one
    of a perturbation's size: at a start at rest (u = 0) W is 0, and the start moved by eps
    has W ~ 9 eps along the perturbation's direction; B made of it (eigenvalues eps x 1e-3 ..
    1e-16) sent the first steps along the last bits (the minimum-time double integrator 6-14
    iterations over round-off perturbations and ISA settings; docs/history.md, session 40)."""
    rows = active_rows(ev, jnp.inf)  # E's rows and every inequality row, as lam is laid out
    natural = (jnp.linalg.norm(ev.G_a) + jnp.linalg.norm(rows.T @ lam)) / (1.0 + jnp.linalg.norm(a))
    return jnp.sqrt(jnp.finfo(a.dtype).eps) * natural


def _multipliers(ev: Evaluation, path_active):
    """Least-squares multipliers of E and of the near-active inequality rows (`nu >= 0`)."""
    lam = least_squares_multipliers(ev, path_active)
    return jnp.where(jnp.all(jnp.isfinite(lam)), lam, 0.0)


def min_norm_step(rows, target, active=None):
    """The minimum-norm d with rows d = target (masked rows skipped) and the projector onto
    the null space of the rows: the filter update from prior 0 with covariance I, noise-free
    up to 1e-14 of each row's variance, and one refinement pass."""
    n = rows.shape[1]
    eye = jnp.eye(n, dtype=rows.dtype)
    r = 1e-14 * jnp.sum(rows**2, axis=1) + 1e-300
    d, V, _ = sequential_update(jnp.zeros(n, rows.dtype), eye, rows, target, r, active)
    d, V, _ = sequential_update(d, eye, rows, target, r, active)
    return d, 0.5 * (V + V.T)


def normal_step(v, rows, target, radius):
    """The normal step within `radius`: the minimum-norm solution `v` of rows v = target,
    cut to the radius, unless the cut step lowers the linearized violation 1/2 |rows v -
    target|^2 by less than a tenth of what Powell's dogleg step (from the Cauchy point
    towards `v`, on the boundary) does; then the dogleg step. Where the rows are nearly rank
    deficient, `v` runs along the near-null direction (1 / its singular value) and, cut to a
    small radius, lowers the violation by nothing: the fraction of the Cauchy decrease that
    the convergence theory of the composite step asks for (Byrd and Omojokun; Nocedal &
    Wright sec. 18.5) is then missing, and the iteration crawled (Zermelo, RESULTS.md)."""
    g = -rows.T @ target  # the violation's gradient at 0
    Jg = rows @ g
    cauchy = -(g @ g) / jnp.maximum(Jg @ Jg, 1e-300) * g
    # the dogleg path cauchy + tau (v - cauchy), 0 <= tau <= 1, where it meets the boundary
    w = v - cauchy
    b, c = cauchy @ w, cauchy @ cauchy - radius**2
    tau = (jnp.sqrt(jnp.maximum(b**2 - (w @ w) * c, 0.0)) - b) / jnp.maximum(w @ w, 1e-300)
    bent = cauchy + jnp.clip(tau, 0.0, 1.0) * w
    steepest = -g * radius / jnp.maximum(jnp.linalg.norm(g), 1e-300)
    dogleg = jnp.where(jnp.linalg.norm(cauchy) >= radius, steepest, bent)
    cut = v * jnp.minimum(1.0, radius / jnp.maximum(jnp.linalg.norm(v), 1e-300))
    decrease = lambda d: target @ target - jnp.sum((rows @ d - target) ** 2)
    return jnp.where(decrease(cut) >= 0.1 * decrease(dogleg), cut, dogleg)


def eigh_within(M, P):
    """Eigenvalues (ascending) and eigenvectors of M restricted to the range of the orthogonal
    projector P, first: the directions outside P get the eigenvalue |M| + 1, above every one
    within, so they come last."""
    return jnp.linalg.eigh(P @ M @ P + (jnp.linalg.norm(M) + 1.0) * (jnp.eye(M.shape[0], dtype=M.dtype) - P))


def convexify_blockwise(W, A, min_curvature, negligible=0.0):
    """The QP's positive definite B from the exact Hessian of the Lagrangian W and the active
    rows A: `convexify`'s W + c A^T A (c = |W| / |A^T A|) where that is positive definite;
    where it is not, the repair is split along the null space Z of A and its range Y
    (orthonormal, from the SVD of A; singular values below 1e-10 of the largest count as zero)
    instead of flipping eigenvalues of the whole: the null-space block Z^T W Z with eigenvalues
    made positive (|.|, floored at `min_curvature` x the largest or |W|), the cross blocks
    Z^T W Y kept, and the Schur complement of the range block, Y^T (W + c A^T A) Y less the
    cross term through the new null-space block, made positive the same way. B is positive
    definite, and its reduced Hessian is W's wherever W's is positive definite. Flipping the
    whole W + c A^T A mixes the two spaces: at Goddard's optimum W has an eigenvalue -2.56 and
    the reduced Hessian 6.8e-5 and 7.7e-4, which the flip distorted into short steps (69
    iterations from the naive start, 7 with this B; docs/history.md). Where |W| <= `negligible`
    (no curvature: W = 0, or W at its round-off or a perturbation's, `_curvature_floor`) B is
    the identity."""
    p = W.shape[0]
    _, s, Vt = jnp.linalg.svd(A, full_matrices=False)
    in_range = s > 1e-10 * jnp.max(s, initial=0.0)
    rank = jnp.sum(in_range)
    PY = (Vt.T * in_range[None, :].astype(Vt.dtype)) @ Vt
    PZ = jnp.eye(p, dtype=W.dtype) - PY
    # no curvature at all: |W| <= `negligible` (0, or the round-off of W's terms)
    W = jnp.where(jnp.linalg.norm(W) <= negligible, 0.0, W)
    scale = jnp.linalg.norm(W)

    def positive(M, P, n_in):
        """M within the range of the projector P (of rank n_in) with its eigenvalues made
        positive, and its inverse there."""
        w, U = eigh_within(M, P)
        inside = jnp.arange(p) < n_in
        U = U * inside[None, :].astype(U.dtype)
        w = jnp.abs(w)
        top = jnp.maximum(jnp.max(jnp.where(inside, w, 0.0)), scale)
        # no curvature at all (W = 0; within P eigh leaves round-off): the identity there
        w = jnp.where(scale > 0.0, jnp.maximum(w, min_curvature * top), 1.0)
        return (U * w[None, :]) @ U.T, (U / w[None, :]) @ U.T

    null_block, null_inverse = positive(W, PZ, p - rank)
    cross = PZ @ W @ PY
    through = cross.T @ null_inverse @ cross
    AtA = A.T @ A
    c = scale / jnp.maximum(jnp.linalg.norm(AtA), 1e-300)
    schur, _ = positive(W + c * AtA - through, PY, rank)
    B = null_block + cross + cross.T + through + schur
    return 0.5 * (B + B.T)


def subproblem(grad, W, V, radius, newton_grad=None):
    """min grad^T u + 1/2 u^T W u over u = V u, |u| <= radius (V: the null-space projector),
    solved exactly by the eigenvalues of V W V (More and Sorensen; in the hard case the
    eigenvector of the smallest eigenvalue is added to reach the boundary). With
    `newton_grad`, also the length of the unconstrained minimizer for that gradient (the
    reduced Newton step, by the same eigenvalues; inf where V W V is not positive definite)."""
    # Range directions of V get an eigenvalue above every reduced one and no gradient.
    lam, Q = eigh_within(W, V)
    gt = Q.T @ (V @ grad)
    norm_at = lambda s: jnp.linalg.norm(gt / (lam + s))
    lo = jnp.maximum(0.0, -lam[0])
    lo = lo + 1e-13 * (jnp.abs(lam[0]) + jnp.abs(lam[-1]) + 1e-300)
    # (a curvature within round-off of zero counts as flat, not negative: no run to the boundary
    # along a direction with neither curvature nor gradient)
    flat = 1e-12 * (jnp.abs(lam[0]) + jnp.abs(lam[-1]))
    inside = (lam[0] > -flat) & (norm_at(0.0) <= radius)
    hard = ~inside & (norm_at(lo) <= radius)
    hi = lo + jnp.linalg.norm(gt) / radius + 1e-300  # |u(hi)| <= radius

    def bisect(_, bracket):
        a, b = bracket
        mid = 0.5 * (a + b)
        long = norm_at(mid) > radius
        return jnp.where(long, mid, a), jnp.where(long, b, mid)

    _, sigma = lax.fori_loop(0, _BISECTIONS, bisect, (lo, hi))
    sigma = jnp.where(inside, 0.0, jnp.where(hard, lo, sigma))
    u = -Q @ (gt / (lam + sigma))
    q0 = Q[:, 0] * jnp.where(Q[:, 0] @ grad > 0, -1.0, 1.0)
    c = u @ q0  # u's round-off component along q0: tau is the root that lands on the boundary
    tau = jnp.sqrt(jnp.maximum(c**2 + radius**2 - u @ u, 0.0)) - c
    u = V @ jnp.where(hard, u + tau * q0, u)
    if newton_grad is None:
        return u
    newton = jnp.linalg.norm(Q.T @ (V @ newton_grad) / lam)
    return u, jnp.where(lam[0] > flat, newton, jnp.inf)


def trust_region_step(ev: Evaluation, W, radius, knots, dknots, zeta, gap_floor, normal_only=False):
    """The composite step d = v + u (docs/solvers/kalman-sqp.md), with the knot gaps kept above `gap_floor`
    of their length by observations added one per round; where `normal_only` (a boolean,
    traced or not), the normal step alone while it is cut to `zeta` x radius. Returns d and
    the length of the model's own minimizer, the composite step without the radius (inf where
    the reduced Hessian is not positive definite)."""
    g, E, H = ev.G_a, ev.E, ev.H
    gaps = knots[1:] - knots[:-1]
    R = dknots[1:] - dknots[:-1]  # d(gap)/da
    movable = jnp.linalg.norm(R, axis=1) > 0
    rows = jnp.concatenate([H, R])
    target = jnp.concatenate([-E, -(1.0 - gap_floor) * gaps])
    m = E.shape[0]

    def solve(active):
        mask = jnp.concatenate([jnp.ones(m, bool), active])
        v, V = min_norm_step(rows, target, mask)
        v_full, v_norm = v, jnp.linalg.norm(v)
        v = normal_step(v, jnp.where(mask[:, None], rows, 0.0), jnp.where(mask, target, 0.0), zeta * radius)
        rest = jnp.sqrt(jnp.maximum(radius**2 - v @ v, 0.0))
        u, u_newton = subproblem(g + W @ v, W, V, rest, newton_grad=g + W @ v_full)
        d = jnp.where(normal_only & (v_norm > zeta * radius), v, v + u)
        return d, jnp.sqrt(v_norm**2 + u_newton**2)  # v_full is in the rows' range, u in V's

    def violations(d, active):
        short = movable & ~active & (gaps + R @ d < gap_floor * gaps)
        return short, jnp.where(short, gap_floor * gaps - gaps - R @ d, -jnp.inf)

    # round 0 solves without gap rows; each later round adds the most violated gap's row (one
    # trace of `solve` in the loop body, so that the program holds the subproblem once)
    def add_row(carry):
        (d, _), active, rounds = carry
        _short, excess = violations(d, active)
        active = jnp.where(rounds == 0, active, active.at[jnp.argmax(excess)].set(True))
        return solve(active), active, rounds + 1

    def pending(carry):
        (d, _), active, rounds = carry
        return (rounds == 0) | (jnp.any(violations(d, active)[0]) & (rounds <= gaps.shape[0]))

    active = jnp.zeros(gaps.shape, bool)
    start = (jnp.zeros_like(g), jnp.asarray(jnp.inf, g.dtype))
    step, _, _ = lax.while_loop(pending, add_row, (start, active, 0))
    return step


class TRState(SolverState):
    a: jax.Array
    ev: Evaluation
    lam: jax.Array  # multipliers at a: of E, then of the inequality rows
    W: jax.Array  # Hessian of the Lagrangian at a
    radius: jax.Array
    mu: jax.Array  # merit penalty
    cap: PenaltyCap  # where the penalty was last capped (`TrustRegion.mu_max`)
    streak: jax.Array  # steps in a row at an acceptable point (`_kkt.kkt_outcome`)
    d: jax.Array  # the step of the pending second-order correction
    d_soc: jax.Array
    lam_qp: jax.Array  # the QP's multipliers of the pending step (problems with inequalities)
    soc: jax.Array  # the next candidate is a + d + d_soc
    pred: jax.Array
    phi0: jax.Array


def _model(ev: Evaluation, lam, mu, d, B):
    """The merit's model at step d: the quadratic model of the Lagrangian's objective part
    (curvature B) and the linearized constraints in the merit's terms."""
    rows = inequality_rows(ev)
    C = None if rows is None else rows[0] + rows[1] @ d
    return merit_value(ev.G + ev.G_a @ d + 0.5 * d @ B @ d, ev.E + ev.H @ d, C, lam, mu)


def _penalty(ev: Evaluation, lam, mu, d, B):
    """The smallest penalty >= `mu` (never lowered) with a predicted merit decrease of at
    least 0.3 mu x the linearized decrease of the violation |E|^2/2 + |max(C, 0)|^2/2, where
    the step lowers it: Newton steps on that condition (one is exact without inequalities,
    where the predicted decrease is affine in mu), with a relative margin of 1e-4."""
    rows = inequality_rows(ev)
    C, C_d = (None, None) if rows is None else (rows[0], rows[0] + rows[1] @ d)
    linear = violation(ev.E, C) - violation(ev.E + ev.H @ d, C_d)
    excess = lambda mu: merit(ev, lam, mu) - _model(ev, lam, mu, d, B) - 0.3 * mu * linear

    def newton(_, mu):
        f, df = jax.jvp(excess, (mu,), (jnp.ones_like(mu),))
        # at mu = 0 the PHR terms of violated rows are off and their slope is missing: then
        # the slope of the equality-like part, 0.7 x the linearized decrease
        slope = jnp.where(df > 0, df, 0.7 * linear)
        needed = (mu - f / jnp.where(slope > 0, slope, 1.0)) * 1.0001
        return jnp.where((linear > 1e-300) & (f < 0), jnp.maximum(mu, needed), mu)

    return lax.fori_loop(0, 1 if rows is None else 4, newton, mu)


def _init(tr, sqp, problem, control, a0, simulator, max_steps):
    # Nothing is integrated here: the first `_step` evaluates the start as its candidate
    # (then its Hessian), so the compiled program holds each evaluation kernel once (issue 21).
    ev, lam = sqp.unevaluated(problem, control, a0, simulator)
    f = jnp.float64
    zero = jnp.zeros_like(a0)
    return TRState(
        a=a0,
        ev=ev,
        lam=lam,
        W=jnp.zeros((a0.shape[0], a0.shape[0]), f),
        radius=jnp.asarray(tr.radius, f),
        mu=jnp.asarray(0.0, f),
        cap=PenaltyCap.none(),
        streak=jnp.array(0, jnp.int32),
        d=zero,
        d_soc=zero,
        lam_qp=lam,
        soc=jnp.array(True),  # no new step before the start is evaluated: its candidate is a0
        pred=jnp.asarray(0.0, f),
        phi0=jnp.asarray(0.0, f),
        **start_counters(max_steps, ("radius", "kind")),
    )


def _step(tr, sqp, problem, control, simulator, state: TRState):
    ev, a, W = state.ev, state.a, state.W
    knots, dknots = control.knots(a), jax.jacfwd(control.knots)(a)
    fresh = ~state.soc
    # (under `vmap` a finished lane still runs the step, its result discarded: it asks
    # `only_where` for no work)
    live = ~state.done
    with_rows = inequality_rows(ev) is not None
    # far from feasible: the linearized constraints ask for a relative change of the
    # parameters of at least `feasibility_first` (docs/solvers/kalman-sqp.md)
    far = far_from_feasible(ev, a, tr.feasibility_first)

    # a new step (no integration); only where no correction is pending
    if with_rows:
        # the QP of the line search with the convexified Hessian, the radius as the box
        # |d_i| <= radius (docs/solvers/kalman-sqp.md)
        A = active_rows(ev, sqp.path_active)
        B = convexify_blockwise(W, A, sqp.min_curvature, _curvature_floor(ev, state.lam, a))
        gaps = knot_gap_rows(control, a)  # the knot order as rows of the same QP (docs/solvers/kalman-sqp.md)

        def new_step(ev, B, lam, radius, gaps):
            d, lam_qp = sqp.direction(ev, B, lam, knots, dknots, radius, gaps)
            return d * jnp.minimum(1.0, radius / jnp.maximum(jnp.max(jnp.abs(d)), 1e-300)), lam_qp

        d, lam_qp = only_where(fresh & live, new_step, (state.d, state.lam_qp), ev, B, state.lam, state.radius, gaps)
        newton = jnp.asarray(jnp.inf, a.dtype)  # (the QP's own minimizer is not formed)
        lam = sqp.release_inactive(ev, state.lam)
        size = lambda d: jnp.max(jnp.abs(d))
    else:
        B = W
        d, newton = only_where(
            fresh & live,
            lambda ev, W, radius: trust_region_step(ev, W, radius, knots, dknots, tr.zeta, tr.gap_floor, far),
            (state.d, jnp.asarray(jnp.inf, a.dtype)),
            ev,
            W,
            state.radius,
        )
        lam, lam_qp = state.lam, state.lam_qp  # (QP multipliers only with inequality rows)
        size = jnp.linalg.norm
    d = jnp.where(fresh, without_scale(d, a, scale_free(ev, a, W, state.lam)), d)  # (`scale_free`)
    # the penalty carries over; near feasibility it is capped at `mu_max` x its natural scale,
    # once the violation has halved since the last cap, or where no step has raised it since
    # and the objective has fallen by `cap_progress` (`TrustRegion`); never at an acceptable
    # point (`_kkt.kkt_outcome`)
    natural = natural_scale(W, A if with_rows else ev.H)
    viol = violation_of(ev)
    eligible = fresh & ~far & (state.streak == 0)
    carried, cap = state.cap.carried(state.mu, natural, viol, ev.G, eligible, tr.mu_max, tr.cap_progress, sqp.ctol)
    mu_new = _penalty(ev, lam, carried, d, B)
    raised = fresh & (mu_new > carried)
    mu = jnp.where(fresh, mu_new, state.mu)
    pred = jnp.where(fresh, merit(ev, lam, mu_new) - _model(ev, lam, mu_new, d, B), state.pred)
    phi0 = jnp.where(fresh, merit(ev, lam, mu_new), state.phi0)

    # one integration: the candidate (the first step's is the start)
    first = state.num_steps == 0
    total = d + jnp.where(fresh, 0.0, state.d_soc)
    # entries past their bound rows by the QP's round-off are put back on them (`bound_excess`)
    total = total + bound_excess(problem, control, a + total)
    cand = evaluate_jitted(problem, control, a + total, simulator, "forward")
    # the candidate's multipliers: the QP's with inequalities (least squares at the start)
    if with_rows:
        lam_c = only_where(first, lambda cand: _multipliers(cand, sqp.path_active), lam_qp, cand)
    else:
        lam_c = _multipliers(cand, sqp.path_active)
    phi = merit(cand, lam, mu)
    new_knots = control.knots(a + total)
    # knots in order, up to the round-off a collapsed segment (gap 0, held by its row) leaves
    ordered = jnp.all(jnp.diff(new_knots) >= -1e-12 * jnp.sum(jnp.abs(jnp.diff(knots))))
    finite = (cand.status == Status.SUCCESS) & jnp.isfinite(phi) & ordered
    slack = 10.0 * jnp.finfo(phi.dtype).eps * (1.0 + jnp.abs(phi0))  # the merit's round-off
    ared = phi0 - phi
    accept = finite & (first | (ared + slack >= tr.eta * pred))
    ratio = ared / jnp.maximum(pred, 1e-300)

    # rejected full step: retry once with the second-order correction
    try_soc = fresh & ~accept & finite
    if with_rows:
        d_soc = sqp.correction(ev, B, cand.E, knots, dknots, d)
    else:
        d_soc, _ = min_norm_step(ev.H, -curvature_error(ev, cand.E, d))
    d_norm = jnp.where(accept, size(total), size(d))
    # on the boundary: |d| >= 0.8 radius, with a margin for round-off: a normal step cut to
    # the default zeta x radius and taken alone (no tangential part, or feasibility first)
    # is exactly that long, and the doubling would be decided by its last bit. A step that the
    # correction saved does not double it (the uncorrected model failed at that length: the
    # minimum-time double integrator's fresh steps were rejected after every doubling)
    edge = 0.8 * (1.0 - 1e-9) * state.radius
    # A model exact along the step (ratio 1 to 1e-9: linear constraints and a quadratic
    # objective, the round-off of the merit at 1e-13) is trusted up to its own minimizer, with
    # room for its normal part within zeta x radius
    exact = jnp.abs(ratio - 1.0) <= 1e-9
    grown = jnp.maximum(2.0 * d_norm, jnp.where(exact & jnp.isfinite(newton), newton / tr.zeta, 0.0))
    radius = jnp.where(
        accept & ~first,
        jnp.where(
            (ratio > 0.75) & (d_norm >= edge) & fresh,
            jnp.maximum(state.radius, grown),
            jnp.where(ratio < 0.25, 0.5 * d_norm, state.radius),
        ),
        jnp.where(try_soc | first, state.radius, 0.25 * d_norm),
    )

    new = lambda c, o: jax.tree.map(lambda x, y: jnp.where(accept, x, y), c, o)
    new_a, new_ev, new_lam = new((a + total, cand, lam_c), (a, ev, state.lam))
    maxE = jnp.max(jnp.abs(new_ev.E), initial=0.0)
    feasible = is_feasible(new_ev, sqp.ctol)
    # the knot gaps are rows of the KKT test with or without inequality rows (a collapsed
    # duration is held by its gap: a saturated spline's optimum, RESULTS.md)
    kkt_ev = with_knot_gaps(control, new_ev, new_a)
    # the stationarity test only where it can decide (SUCCESS needs feasibility): with
    # inequalities it is rounds of least squares over every near-active or violated row
    pg = only_where(
        feasible & live,
        lambda ev, a: kkt_residual(ev, a, sqp.path_active),
        jnp.asarray(jnp.inf, a.dtype),
        kkt_ev,
        new_a,
    )
    tiny = 1e-15 * (1.0 + jnp.linalg.norm(a))
    # No measurable progress: the radius or the step is negligible (a NaN radius too), or, at
    # a feasible point, a fresh step inside the radius (the model's own minimizer) predicts a
    # merit decrease below the merit's round-off. (Not at an infeasible one: there a step
    # that lowers a violation of 1e-9 still counts, though the merit cannot resolve it.)
    flat = fresh & (size(d) < 0.8 * state.radius) & (pred <= slack) & is_feasible(ev, sqp.ctol)
    no_progress = ~first & (~(radius > tiny) | (accept & (jnp.linalg.norm(total) <= tiny)) | flat)
    converged, stalled, streak = kkt_outcome(
        feasible, pg, new_ev.G, sqp.gtol, sqp.acceptable_gtol, no_progress, state.streak, sqp.acceptable_steps
    )
    bad_start = first & ~accept
    infeasible = stalled & ~feasible  # tested only there (least squares over every row)
    infeasible = only_where(
        infeasible & live,
        lambda ev: locally_infeasible(ev, sqp.path_active, sqp.acceptable_gtol),
        infeasible,
        kkt_ev,
    )
    # The Hessian only at an accepted point that is not the last: a rejected candidate costs a
    # first-order integration alone.
    hessian = accept & ~converged & ~stalled
    new_W = only_where(
        hessian & live, lambda a, lam: lagrangian_hessian(problem, control, a, simulator, lam), W, new_a, new_lam
    )
    i = state.num_steps
    history = state.history.record(
        i,
        objective=new_ev.G,
        max_constraint_error=maxE,
        step_norm=jnp.linalg.norm(total),
        accepted=accept,
        constraint_tolerance=sqp.ctol,
        details={"radius": state.radius, "kind": jnp.where(first, 0, jnp.where(fresh, 1, 3))},
    )
    return TRState(
        a=new_a,
        ev=new_ev,
        lam=new_lam,
        W=new_W,
        radius=radius,
        mu=mu,
        cap=state.cap.update(cap, viol, ev.G, raised),
        streak=streak,
        d=d,
        d_soc=jnp.where(jnp.all(jnp.isfinite(d_soc)), d_soc, 0.0),
        lam_qp=lam_qp,
        soc=try_soc,
        pred=pred,
        phi0=phi0,
        num_iterations=state.num_iterations + (accept & ~first).astype(jnp.int32),
        num_integrations=state.num_integrations + 1 + hessian.astype(jnp.int32),
        num_steps=i + 1,
        done=converged | stalled | bad_start,
        status=Status.where(
            bad_start,
            failed(cand.status),
            Status.where(
                converged, Status.SUCCESS, Status.where(infeasible, Status.CONSTRAINT_STATIONARY, Status.STALLED)
            ),
        ),
        history=history,
    )


class TrustRegion(eqx.Module):
    """KalmanSQP's composite-step trust region (docs/solvers/kalman-sqp.md). Fields:

    - `radius`: initial radius of |d|_2 (parameter units, 1.0; with inequalities the half-width
      of the box |d_i| <= radius).
    - `zeta`: the normal step's share of the radius (0.8).
    - `gap_floor`: the fraction of a knot gap one step must leave (0.5).
    - `eta`: the least ratio of actual to predicted merit decrease that accepts a step (1e-4).
    - `mu_max`: near feasibility (not far in the sense of `feasibility_first`) the penalty
      carried over to the next step is at most `mu_max` x |W|_F / |A|_F^2 (100; W the
      Hessian of the Lagrangian, A the rows of E and the active inequality rows; the step
      raises it again as far as it needs). |W| / |A|^2 is the penalty at which mu A^T A
      weighs as much as W, a scale invariant to the units of the objective, the constraints
      and the parameters. Near a feasible point a step that trades objective for a little
      feasibility asks for mu ~ dJ / |E|^2, and such a penalty, kept, makes the merit crawl
      along curved constraints (a cart-pole swing-up from rest: 1092-1165 iterations with
      6.7e3 x the scale carried over, 267-268 with this cap, IPOPT 260-453; the minimum-time
      double integrator 11 -> 8). Far from feasible it is kept: the violation's descent needs
      a penalty that does not fall with the objective's curvature (a locally infeasible
      problem with a zero objective: W -> 0 there, and the capped merit vanished into
      round-off). The seven Earth-Mars cases keep theirs (at most 7 x the scale). A cap
      lowers the merit's penalty, and so changes the merit under the iterates: it applies only
      once the violation |E|^2/2 + |max(C, 0)|^2/2 has halved since the last cap, so that it
      happens finitely often on the way to feasibility, or is below one row's at `ctol` (a
      violation at round-off cannot halve: a least time capped at 2.5e-30 kept 1e18 and
      crawled). Capping at every step let a pendulum's minimum time (benchmarks/unseen.py)
      cycle through 8 accepted points (MAX_ITERATIONS). benchmarks/RESULTS.md.
    - `cap_progress`: a cap applies too where no step has raised the penalty since the last
      one and the objective has fallen by `cap_progress` x (1 + |G|) since then (0.01): the
      iterates have left the region that penalty was set for, and it has held every step
      since. The violation need not fall on the way to an optimum far from the first
      near-feasible point, and the halving rule alone then never capped again: a cart-pole
      whose final time is fixed by a terminal equality `tf - 2` (bounded force, start tf = 3)
      capped once at a violation of 1e-7, then crawled with 4e4 x the scale carried over
      (MAX_ITERATIONS after 2053 iterations at 1e-4 violations; 307 iterations with this
      rule). Each such cap needs the objective 1 % below the last one's, so they too are
      finitely many; a cap while violations swing 2x (the pendulum above) needs the halving.
      No cap applies at an acceptable point (`_kkt.kkt_outcome`): there the endgame has
      begun, and a lowered penalty sent the pendulum away from its optimum again.
    - `feasibility_first`: far from feasible, |E| > feasibility_first x |H|_F |a|, the normal
      step is taken alone while it is cut (the linearized constraints out of the radius's
      reach), without the tangential step (0.1; 0: wherever the normal step is cut; inf:
      never). Problems without inequality rows (with them the step is the QP's). It keeps the
      objective from steering the iterates into a region where the violation stalls
      (Zermelo's ship, 32 random starts: 15 at the reference with inf, 26 with 0.1 or 0:
      minimum time runs tf towards 0 while the target is still far). The threshold spares good
      starts: with 0, Earth-Mars cases 1 and 2 took 12 and 18 iterations instead of 10 and 9
      (the normal step cut near a saddle at max |E| ~ 1e-3); with 0.1 (their starts are at
      0.04) 10 and 9, and 0.05-0.1 give the same counts. benchmarks/RESULTS.md.
    """

    radius: float = 1.0
    zeta: float = 0.8
    gap_floor: float = 0.5
    eta: float = 1e-4
    mu_max: float = 100.0
    cap_progress: float = 0.01
    feasibility_first: float = 0.1

    def __check_init__(self):
        checks = {
            "radius": lambda: 0 < self.radius < math.inf,
            "zeta": lambda: 0 < self.zeta < 1,
            "gap_floor": lambda: 0 < self.gap_floor < 1,
            "eta": lambda: 0 < self.eta < 0.25,
            "mu_max": lambda: 0 < self.mu_max < math.inf,
            "cap_progress": lambda: 0 <= self.cap_progress < 1,
            "feasibility_first": lambda: not isinstance(self.feasibility_first, bool) and self.feasibility_first >= 0,
        }
        check_settings("TrustRegion", self, checks)

    def init(self, sqp, problem, control, a0, simulator, max_steps):
        return _init(self, sqp, problem, control, a0, simulator, max_steps)

    def step(self, sqp, problem, control, simulator, state: TRState):
        return _step(self, sqp, problem, control, simulator, state)

    def progress(self, state: TRState):
        return {"radius": state.radius, "mu": state.mu}
