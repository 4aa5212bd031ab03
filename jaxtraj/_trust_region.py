"""KalmanSQP's trust-region globalization (`KalmanSQP(hessian="exact",
globalization=jt.TrustRegion())`): a Byrd-Omojokun composite-step SQP with the exact Hessian of
the Lagrangian (Nocedal & Wright sec. 18.5), its constraint parts computed by the sequential
Kalman update.

Each step d = v + u, within |d|_2 <= radius:

* normal step v: the minimum-norm solution of the linearized constraints H v = -E, i.e. the
  sequential filter update from the prior 0 with covariance I (the thesis's update with unit
  weights), cut to `zeta` x radius. The same filter's posterior covariance is the projector V
  onto the null space of H, where the tangential step lives.
* tangential step u = V w: the trust-region subproblem of the reduced model
  min (g + W v)^T u + 1/2 u^T W u over |u| <= sqrt(radius^2 - |v|^2), solved exactly (More and
  Sorensen): the eigenvalues of the reduced Hessian V W V give the shift sigma >= 0 with
  (V W V + sigma I) u = -V (g + W v) and |u| on the boundary (or sigma = 0 inside); with
  negative curvature the step runs to the boundary along it instead of being convexified away.
  This is what the line search cannot do: near a saddle of the reduced problem (Earth-Mars
  case 2) the line-search SQP, with its eigenvalues made positive, crawls.
* free knot times: a gap t_{i+1} - t_i may shrink to no less than `gap_floor` of its length in
  one step; a step that would shrink it further observes the gap's change at that bound, as one
  more row of the filter, one row per round, rows added until none is violated. This is appendix
  C's observation of the approach of two knots with a_t = 1 / (1 - gap_floor), noise-free (so
  the trust region's step meets it), and entered as soon as the step would take more than that
  share of the gap, not only when the knots would cross.

Step rule: the ratio of the actual to the predicted decrease of the augmented-Lagrangian merit
G + lambda^T E + nu/2 |E|^2 (least-squares multipliers at the current point; nu raised so that
the predicted decrease is at least 0.3 nu/2 (|E|^2 - |E + H d|^2), never lowered). A candidate
with ratio >= `eta` is accepted; a rejected one is first retried with a second-order
correction (the minimum-norm step onto H d_c = -E(a + d), by the same filter); the radius
doubles after a good step on the boundary (ratio > 0.75), halves to |d| / 2 after a poor one
(ratio < 0.25) and falls to |d| / 4 after a rejection. Every step integrates one candidate with
first-order sensitivities; an accepted one that does not end the solve is integrated once more
for the Hessian of the Lagrangian with its own least-squares multipliers (`lagrangian_hessian`;
both count in `integrations`).

Only exact Hessians: with damped BFGS or SR1 the same trust region needed far more iterations
(benchmarks/RESULTS.md).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ._bounds import needs_rows
from ._checks import check_settings
from ._kalman import sequential_update
from ._kkt import kkt_outcome, lagrangian_gradient, least_squares_multipliers, projected_gradient
from ._sensitivity import Evaluation, evaluate_restricted
from ._simulate import RK4, final_state
from ._solution import History
from ._status import Status

_BISECTIONS = 64  # of the trust-region shift sigma (a scalar; 2^-64 of the bracket)


def lagrangian_hessian(problem, control, a, simulator, lam):
    """Hessian of the Lagrangian G + lambda^T E at `a` (zero if not finite): forward over
    reverse autodiff of the plain simulation with RK4 (faster than forward over the forward
    sensitivities; benchmarks/RESULTS.md), forward over forward for other simulators (diffrax
    runs with forward-mode adjoints only)."""
    if isinstance(simulator, RK4):

        def lagrangian(a):
            xf, _ = final_state(problem, control, a, simulator)
            tf = control.tf(a)
            return problem.objective(tf, xf, problem.args) + lam @ problem.terminal(tf, xf, problem.args)

        W = jax.jacfwd(jax.grad(lagrangian))(a)
    else:

        def gradient(a):
            return lagrangian_gradient(evaluate_restricted(problem, control, a, simulator, "forward"), lam)

        W = jax.jacfwd(gradient)(a)
    W = 0.5 * (W + W.T)
    return jnp.where(jnp.all(jnp.isfinite(W)), W, 0.0)  # a failed integration: no curvature


def _multipliers(ev: Evaluation):
    lam = least_squares_multipliers(ev, 0.0)  # no path rows here: the multipliers of E alone
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


def subproblem(grad, W, V, radius):
    """min grad^T u + 1/2 u^T W u over u = V u, |u| <= radius (V: the null-space projector),
    solved exactly by the eigenvalues of V W V (More and Sorensen; in the hard case the
    eigenvector of the smallest eigenvalue is added to reach the boundary)."""
    n = W.shape[0]
    # Range directions of V get an eigenvalue above every reduced one and no gradient.
    top = jnp.linalg.norm(W) + 1.0
    lam, Q = jnp.linalg.eigh(V @ W @ V + top * (jnp.eye(n) - V))
    gt = Q.T @ (V @ grad)
    norm_at = lambda s: jnp.linalg.norm(gt / (lam + s))
    lo = jnp.maximum(0.0, -lam[0])
    lo = lo + 1e-13 * (jnp.abs(lam[0]) + jnp.abs(lam[-1]) + 1e-300)
    # (a curvature within round-off of zero counts as flat, not negative: no run to the boundary
    # along a direction with neither curvature nor gradient)
    inside = (lam[0] > -1e-12 * (jnp.abs(lam[0]) + jnp.abs(lam[-1]))) & (norm_at(0.0) <= radius)
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
    return V @ jnp.where(hard, u + tau * q0, u)


def trust_region_step(ev: Evaluation, W, radius, knots, dknots, zeta, gap_floor):
    """The composite step d = v + u (module docs), with the knot gaps kept above `gap_floor`
    of their length by observations added one per round."""
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
        v_norm = jnp.linalg.norm(v)
        v = v * jnp.minimum(1.0, zeta * radius / jnp.maximum(v_norm, 1e-300))
        rest = jnp.sqrt(jnp.maximum(radius**2 - v @ v, 0.0))
        return v + subproblem(g + W @ v, W, V, rest)

    def violations(d, active):
        short = movable & ~active & (gaps + R @ d < gap_floor * gaps)
        return short, jnp.where(short, gap_floor * gaps - gaps - R @ d, -jnp.inf)

    def add_row(carry):
        d, active, rounds = carry
        _short, excess = violations(d, active)
        active = active.at[jnp.argmax(excess)].set(True)
        return solve(active), active, rounds + 1

    def pending(carry):
        d, active, rounds = carry
        return jnp.any(violations(d, active)[0]) & (rounds < gaps.shape[0])

    active = jnp.zeros(gaps.shape, bool)
    d, _, _ = lax.while_loop(pending, add_row, (solve(active), active, 0))
    return d


class TRState(eqx.Module):
    a: jax.Array
    ev: Evaluation
    lam: jax.Array  # least-squares multipliers at a
    W: jax.Array  # Hessian of the Lagrangian at a
    radius: jax.Array
    nu: jax.Array  # merit penalty
    d: jax.Array  # the step of the pending second-order correction
    d_soc: jax.Array
    soc: jax.Array  # the next candidate is a + d + d_soc
    pred: jax.Array
    phi0: jax.Array
    num_iterations: jax.Array
    num_integrations: jax.Array
    num_steps: jax.Array
    done: jax.Array
    status: Status
    history: History


def _merit(ev: Evaluation, lam, nu):
    return ev.G + lam @ ev.E + 0.5 * nu * (ev.E @ ev.E)


def _init(tr, sqp, problem, control, a0, simulator, max_steps):
    if problem.path is not None or problem.terminal_inequality is not None or needs_rows(problem, control):
        raise ValueError(
            "KalmanSQP: the trust region (`globalization`) does not handle inequality constraints "
            "(path, state bounds, terminal inequalities, control bounds the family does not saturate "
            "within); use jt.LineSearch()."
        )
    ev = evaluate_restricted(problem, control, a0, simulator, "forward")
    lam = _multipliers(ev)
    W = lagrangian_hessian(problem, control, a0, simulator, lam)
    ok0 = ev.status == Status.SUCCESS
    f = jnp.float64
    zero = jnp.zeros_like(a0)
    return TRState(
        a=a0,
        ev=ev,
        lam=lam,
        W=W,
        radius=jnp.asarray(tr.radius, f),
        nu=jnp.asarray(0.0, f),
        d=zero,
        d_soc=zero,
        soc=jnp.array(False),
        pred=jnp.asarray(0.0, f),
        phi0=jnp.asarray(0.0, f),
        num_iterations=jnp.array(0, jnp.int32),
        num_integrations=jnp.array(2, jnp.int32),
        num_steps=jnp.array(0, jnp.int32),
        done=~ok0,
        status=Status.where(ok0, Status.SUCCESS, ev.status),
        history=History.empty(max_steps, ("radius", "kind")),
    )


def _step(tr, sqp, problem, control, simulator, state: TRState):
    ev, a, lam, W, nu = state.ev, state.a, state.lam, state.W, state.nu
    knots, dknots = control.knots(a), jax.jacfwd(control.knots)(a)
    fresh = ~state.soc

    # a new step (cheap: no integration); used unless a correction is pending
    d_new = trust_region_step(ev, W, state.radius, knots, dknots, tr.zeta, tr.gap_floor)
    Hd = ev.H @ d_new
    model = (ev.G_a + ev.H.T @ lam) @ d_new + 0.5 * d_new @ W @ d_new  # change of the Lagrangian's model
    linear = 0.5 * (ev.E @ ev.E - (ev.E + Hd) @ (ev.E + Hd))  # decrease of |E|^2 / 2, linearized
    needed = model / (0.7 * jnp.where(linear > 0, linear, 1.0)) * 1.0001
    nu_new = jnp.where((linear > 1e-300) & (model > 0), jnp.maximum(nu, needed), nu)
    nu = jnp.where(fresh, nu_new, nu)
    d = jnp.where(fresh, d_new, state.d)
    pred = jnp.where(fresh, -model + nu_new * linear, state.pred)
    phi0 = jnp.where(fresh, _merit(ev, lam, nu_new), state.phi0)

    # one integration: the candidate
    total = d + jnp.where(fresh, 0.0, state.d_soc)
    cand = evaluate_restricted(problem, control, a + total, simulator, "forward")
    lam_c = _multipliers(cand)
    phi = _merit(cand, lam, nu)
    new_knots = control.knots(a + total)
    # knots in order, up to the round-off a collapsed segment (gap 0, held by its row) leaves
    ordered = jnp.all(jnp.diff(new_knots) >= -1e-12 * jnp.sum(jnp.abs(jnp.diff(knots))))
    finite = (cand.status == Status.SUCCESS) & jnp.isfinite(phi) & ordered
    slack = 10.0 * jnp.finfo(phi.dtype).eps * (1.0 + jnp.abs(phi0))  # the merit's round-off
    ared = phi0 - phi
    accept = finite & (ared + slack >= tr.eta * pred)
    ratio = ared / jnp.maximum(pred, 1e-300)

    # rejected full step: retry once with the second-order correction
    try_soc = fresh & ~accept & finite
    d_soc, _ = min_norm_step(ev.H, -cand.E)
    d_norm = jnp.where(accept, jnp.linalg.norm(total), jnp.linalg.norm(d))
    radius = jnp.where(
        accept,
        jnp.where(
            (ratio > 0.75) & (d_norm >= 0.8 * state.radius),
            jnp.maximum(state.radius, 2.0 * d_norm),
            jnp.where(ratio < 0.25, 0.5 * d_norm, state.radius),
        ),
        jnp.where(try_soc, state.radius, 0.25 * d_norm),
    )

    new = lambda c, o: jax.tree.map(lambda x, y: jnp.where(accept, x, y), c, o)
    new_a, new_ev, new_lam = new((a + total, cand, lam_c), (a, ev, lam))
    maxE = jnp.max(jnp.abs(new_ev.E), initial=0.0)
    pg = projected_gradient(new_ev.G_a, new_ev.H)
    tiny = 1e-15 * (1.0 + jnp.linalg.norm(a))
    no_progress = ~(radius > tiny) | (accept & (jnp.linalg.norm(total) <= tiny))  # NaN radius too
    converged, stalled = kkt_outcome(maxE <= sqp.ctol, pg, new_ev.G, sqp.gtol, sqp.acceptable_gtol, no_progress)
    # The Hessian only at an accepted point that is not the last: a rejected candidate costs a
    # first-order integration alone (in a single solve; under vmap both branches run).
    hessian = accept & ~converged & ~stalled
    new_W = lax.cond(
        hessian,
        lambda: lagrangian_hessian(problem, control, new_a, simulator, new_lam),
        lambda: W,
    )
    i = state.num_steps
    history = state.history.record(
        i,
        objective=new_ev.G,
        max_constraint_error=maxE,
        step_norm=jnp.linalg.norm(total),
        accepted=accept,
        constraint_tolerance=sqp.ctol,
        details={"radius": state.radius, "kind": jnp.where(fresh, 1, 3)},
    )
    return TRState(
        a=new_a,
        ev=new_ev,
        lam=new_lam,
        W=new_W,
        radius=radius,
        nu=nu,
        d=d,
        d_soc=jnp.where(jnp.all(jnp.isfinite(d_soc)), d_soc, 0.0),
        soc=try_soc,
        pred=pred,
        phi0=phi0,
        num_iterations=state.num_iterations + accept.astype(jnp.int32),
        num_integrations=state.num_integrations + 1 + hessian.astype(jnp.int32),
        num_steps=i + 1,
        done=converged | stalled,
        status=Status.where(converged, Status.SUCCESS, Status.STALLED),
        history=history,
    )


class TrustRegion(eqx.Module):
    """KalmanSQP's composite-step trust region (module docs). Fields:

    - `radius`: initial radius of |d|_2 (parameter units, 1.0).
    - `zeta`: the normal step's share of the radius (0.8).
    - `gap_floor`: the fraction of a knot gap one step must leave (0.5).
    - `eta`: the least ratio of actual to predicted merit decrease that accepts a step (1e-4).
    """

    radius: float = 1.0
    zeta: float = 0.8
    gap_floor: float = 0.5
    eta: float = 1e-4

    def __check_init__(self):
        checks = {
            "radius": lambda: self.radius > 0,
            "zeta": lambda: 0 < self.zeta < 1,
            "gap_floor": lambda: 0 < self.gap_floor < 1,
            "eta": lambda: 0 < self.eta < 0.25,
        }
        check_settings("TrustRegion", self, checks)

    def init(self, sqp, problem, control, a0, simulator, max_steps):
        return _init(self, sqp, problem, control, a0, simulator, max_steps)

    def step(self, sqp, problem, control, simulator, state: TRState):
        return _step(self, sqp, problem, control, simulator, state)

    def progress(self, state: TRState):
        return {"radius": state.radius, "nu": state.nu}
