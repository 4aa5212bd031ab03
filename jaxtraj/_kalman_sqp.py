"""A quasi-Newton Kalman SQP: the thesis's sequential filter update as the step of an SQP
method (ALGORITHM.md section 7).

The thesis's increment is the solution of an equality-constrained quadratic model whose
Hessian is the inverse of a fixed diagonal covariance. With the covariance P = B^-1, B an
approximation of the Hessian of the Lagrangian L = G + lambda^T E, the prior mean -P G_a^T
and the full correction z = -E observed with (almost) no noise, the same sequential update
returns the SQP step

    d = argmin G_a d + 1/2 d^T B d   subject to   E + H d = 0,

and the multipliers follow from its stationarity condition H^T lambda_qp = -(G_a + B d).

Design (each point measured on the seven Earth-Mars cases, benchmarks/compare_solvers.py):

* Hessian. `hessian="bfgs"` (default): B is the exact Hessian of the Lagrangian
  (forward-over-forward autodiff through the simulation) at a0 and at the candidates of the
  first `exact_iterations` (3) iterations, then Powell-damped BFGS updates on the
  Lagrangian gradient, which keep it positive definite. Measured on the seven cases: with
  pure BFGS from a0's Hessian (`exact_iterations=0`) case 3 ends in a worse local minimum
  (3.35114 instead of 3.32080) and cases 1, 2, 7 need 49, 51, 34 iterations; with 3 exact
  iterations all seven reach the best known optima in 11-31 iterations (24, 28, 21, 11, 14,
  31, 27 with the second-order correction below), at a similar wall time. `hessian="exact"`:
  the exact Hessian at every candidate (one second-order integration per step: fewer
  iterations, 12, 28, 16, 8, 9, 18, 16, more time per iteration). Either exact Hessian is
  made positive definite by `convexify` (B = nabla^2 L + c H^T H, which leaves the QP's
  solution unchanged, then lifted eigenvalues where that is not enough).
* Step rule: backtracking line search on the augmented-Lagrangian merit function
  phi(a, lambda) = G + lambda^T E + mu/2 |E|^2 over (a + alpha d, lambda + alpha
  (lambda_qp - lambda)) (Schittkowski's merit function; unlike the l1 merit it accepts unit
  steps near the solution, so the superlinear rate is not lost to the Maratos effect). The
  penalty mu rises (Newton steps on the slope, doubled for a margin) until the directional
  derivative is at most -1/2 d^T B d, but only while E or C violate `ctol`: once they are
  met (at round-off) the slope hardly depends on mu, and the Newton step asks for an
  enormous penalty (2e16-2e29 measured on the attitude slew) whose term mu/2 |E|^2 turns
  E's round-off into merit noise above any decrease, so that the line search fails at the
  optimum. The penalty is kept for the next direction unless it exceeds `mu_max` (1e8):
  then the next one starts from 0. Armijo factor `armijo`, relaxed by the merit's round-off
  (10 eps (1 + |phi|)); a rejected alpha is replaced by the minimizer of the quadratic
  through phi(0), phi'(0), phi(alpha), kept in [0.1, 0.5] alpha. Before that, a
  rejected *full* step is retried once with a second-order correction d + d_soc, H d_soc =
  -E(a + d) (the constraints' curvature along d; Nocedal & Wright sec. 15.4), the cheapest
  candidate in the long curved valleys of these problems: with it (and the monotone
  penalty of the time) the seven cases took 24, 28, 21, 11, 14, 31, 27 iterations instead of
  24, 32, 23, 11, 14, 37, 29 (BFGS) and 12, 28, 16, 8, 9, 18, 16 instead of 14, 34, 18, 8,
  9, 88, 16 (exact Hessian).
* Free knot times keep their order by the appendix-C observations (`keep_knots_ordered`,
  as in `KalmanSearch` but without its held half gap: the line search shortens the step).
* Path constraints C(t, x, u) <= 0 (on the integration grid), the appendix-C way: the grid
  points of an active set become observations C_a d = -C after the terminal ones. The active
  set (see `_direction`): the previous iteration's (positive multipliers), less rows whose
  multiplier turns negative, then the most violated predicted row one at a time (a primal
  active-set QP on the same rank-one updates), skipping rows nearly dependent on those
  already observed (adjacent grid points). The multipliers lambda = [lambda_E; nu >= 0] of
  all rows enter the Lagrangian (BFGS, exact Hessian) and the merit (PHR term
  (max(0, nu + mu C)^2 - nu^2) / (2 mu) per grid point). A fresh direction first sets to 0
  the multipliers of points that are strictly inactive (C < -`path_active`) and outside the
  QP's active set (`_release_inactive`): a leftover nu there adds dnu C > 0 to the merit's
  slope and, near the optimum, turned every direction into an ascent one. SUCCESS needs
  max C <= `ctol` and the projected gradient is taken against [H; C_a] of the points with
  C >= -`path_active`. Measured on the attitude slew with the sun cone
  (examples/attitude.py): from rest, both representations reach the augmented-Lagrangian
  optimum's energy to 1e-8 relative with SUCCESS (175 / 115 iterations, the first ones
  overshoot), also from starts perturbed by round-off.
* One `step` = one candidate integration (with first-, or with `hessian="exact"`
  second-order sensitivities), branch-free, so a batch under `vmap` runs the same work for
  every start.
* Termination. What SUCCESS guarantees: max |E_i| <= `ctol`, max C <= `ctol` on the grid,
  and the projected gradient |V G_a| (V: projection on the tangent space of E and of the
  path points with C >= -`path_active`) <= `acceptable_gtol` (1 + |G|). The search runs
  until |V G_a| <= `gtol` (1 + |G|) (the usual outcome: 1e-9, far below the guarantee) or
  until no measurable progress is left: the line search needs a step below `min_step`, the
  direction is no descent, the step is negligible against the parameter vector, or
  `flat_steps` accepted steps in a row decreased the merit by less than its round-off
  without halving the projected gradient (trust region: the radius or the step
  collapses). That point is SUCCESS if it meets the guarantee, otherwise STALLED. Why two
  levels: the projected gradient's floor is set by the round-off of the sensitivities, not
  by the method, and on the solar-sail and attitude problems it lies at 1e-9..1e-7
  (1 + |G|): a single test at 1e-9 turned SUCCESS into STALLED (or a long wander into
  MAX_ITERATIONS) with the last bits of the start, i.e. with the CPU (issue 17: 11 of 33
  sail starts perturbed by 1e-14..3e-10 relative; benchmarks/roundoff.py).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from . import _trust_region
from ._driver import AbstractSolver
from ._kalman import PATH_DEPENDENCE, keep_knots_ordered, observe_worst, sequential_update
from ._kkt import (
    active_rows,
    kkt_outcome,
    lagrangian_gradient,
    least_squares_multipliers,
    path_rows,
    projected_gradient,
)
from ._sensitivity import Evaluation, evaluate_restricted
from ._solution import History, Solution
from ._status import Status


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
    w = jnp.maximum(w, min_curvature * jnp.maximum(jnp.max(w), 1e-300))
    return (V * w[None, :]) @ V.T


def _covariance(B):
    """P = B^-1, exactly symmetric. (A Cholesky solve gives the same steps to round-off, but
    the attitude runs of examples/attitude.py are sensitive enough to round-off to end
    elsewhere: 2.2714 instead of 2.2648954 on the quaternion form.)"""
    P = jnp.linalg.inv(B)
    return 0.5 * (P + P.T)


def _bfgs_step(B, s, cand: Evaluation, ev: Evaluation, lam):
    """BFGS update with the change of the Lagrangian's gradient (multipliers `lam`)."""
    return bfgs_update(B, s, lagrangian_gradient(cand, lam) - lagrangian_gradient(ev, lam))


def _merit_value(G, E, C, lam, mu):
    """G + lambda^T E + mu/2 |E|^2 + sum_j psi(C_j, nu_j) with the PHR inequality term
    psi = (max(0, nu + mu C)^2 - nu^2) / (2 mu) (= nu C + mu/2 C^2 where nu + mu C > 0)."""
    m = E.shape[0]
    value = G + lam[:m] @ E + 0.5 * mu * (E @ E)
    if C is not None:
        nu = lam[m:]
        on = nu + mu * C > 0
        off = jnp.where(nu > 0, -(nu**2) / (2.0 * jnp.where(mu > 0, mu, 1.0)), 0.0)  # nu > 0 here implies mu > 0
        value = value + jnp.sum(jnp.where(on, nu * C + 0.5 * mu * C**2, off))
    return value


def _merit(ev: Evaluation, lam, mu):
    rows = path_rows(ev)
    return _merit_value(ev.G, ev.E, None if rows is None else rows[0], lam, mu)


def _follow_maximum(active, C, tol):
    """Near the boundary (C >= -tol), move each active path row (flattened `(N q,)`) to the grid
    neighbour (same component, previous or next point) with the largest C, if that is larger
    than its own: a touching point travels along the grid as the iterates converge."""
    N, q = C.shape
    padded = jnp.pad(C, ((1, 1), (0, 0)), constant_values=-jnp.inf)
    shift = jnp.argmax(jnp.stack([padded[:-2], padded[1:-1], padded[2:]]), axis=0) - 1  # (N, q)
    shift = jnp.where(C >= -tol, shift, 0)
    rows = jnp.arange(N)[:, None] + shift
    moved = jnp.zeros((N, q), bool).at[rows, jnp.arange(q)[None, :]].max(active.reshape(N, q))
    return moved.reshape(-1)


def _max_path(ev: Evaluation):
    if ev.C is None:
        return jnp.asarray(-jnp.inf)
    return jnp.max(ev.C)


class _State(eqx.Module):
    a: jax.Array
    ev: Evaluation
    lam: jax.Array
    B: jax.Array
    mu: jax.Array
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
    num_iterations: jax.Array
    num_integrations: jax.Array
    num_steps: jax.Array
    done: jax.Array
    status: Status
    history: History


class KalmanSQP(AbstractSolver):
    """Quasi-Newton SQP whose step is the sequential Kalman update (see the module docs).

    Fields:

    - `hessian`: `"bfgs"` (exact Hessian of the Lagrangian at the start and for the first
      `exact_iterations` iterations, then damped BFGS) or `"exact"` (exact Hessian at every
      candidate).
    - `exact_iterations`: see `hessian` (int >= 0, 3).
    - `ctol`: constraint tolerance on max |E_i| and on max C (1e-10).
    - `gtol`: projected-gradient target, relative to 1 + |G| (1e-9): the search stops when
      it is met.
    - `acceptable_gtol`: what SUCCESS guarantees of the projected gradient (relative to
      1 + |G|, 1e-6) when round-off ends the progress before `gtol` is met (module docs).
    - `flat_steps`: accepted steps in a row within the merit's round-off (and without
      halving the projected gradient) that count as no progress (10).
    - `a_t`: knot approach ratio of the appendix-C ordering observations (as KalmanSearch).
    - `armijo`: sufficient-decrease factor of the merit line search.
    - `min_step`: smallest line-search step before STALLED.
    - `min_curvature`: relative eigenvalue floor of the convexified exact Hessian.
    - `mu_max`: a merit penalty above this is not carried over to the next direction (see
      the module docs).
    - `globalization`: `"line-search"` (the merit line search described in the module docs) or
      `"trust-region"` (a composite-step trust region, `hessian="exact"` and problems without
      path constraints only: see `jaxtraj._trust_region`; fewer iterations on every
      Earth-Mars case).
    - `radius`: line search: initial cap on a step's largest component |d_i| (parameter
      units; default 0.5), doubled after every full step it limited, reset to the accepted
      length after a shortened one. Trust region: initial radius of |d|_2 (default 1.0).
    - `zeta`, `gap_floor`, `eta` (trust region): the normal step's share of the radius (0.8);
      the fraction of a knot gap one step must leave (0.5); the least ratio of actual to
      predicted merit decrease that accepts a step (1e-4).
    - `r_rel`: observation noise of the correction, relative to h P h^T (the QP's
      constraints are met to about this fraction of the innovation).
    - `path_active`: path points with C >= -`path_active` count as active constraints in
      the projected gradient (the KKT test).
    - `path_dependence`: a path point joins the active set only if the step can still move
      it independently: its variance left by the rows already observed is at least this
      fraction of its prior variance (adjacent grid points are nearly dependent).
    - `method`: sensitivity method, `"forward"` or `"unit"` (`"unit"` only with BFGS).
    """

    hessian: str = "bfgs"
    ctol: float = 1e-10
    gtol: float = 1e-9
    acceptable_gtol: float = 1e-6
    flat_steps: int = 10
    a_t: float = 10.0
    armijo: float = 1e-4
    min_step: float = 1e-8
    min_curvature: float = 1e-8
    r_rel: float = 1e-12
    exact_iterations: int = 3
    path_active: float = 1e-6
    globalization: str = "line-search"
    radius: float | None = None
    zeta: float = 0.8
    gap_floor: float = 0.5
    eta: float = 1e-4
    mu_max: float = 1e8
    path_dependence: float = PATH_DEPENDENCE
    method: str = "forward"

    def __check_init__(self):
        if self.hessian not in ("bfgs", "exact"):
            raise ValueError(f"KalmanSQP: `hessian` must be 'bfgs' or 'exact'; got {self.hessian!r}.")
        if self.method not in ("forward", "unit"):
            raise ValueError(f"KalmanSQP: `method` must be 'forward' or 'unit'; got {self.method!r}.")
        if self.globalization not in ("line-search", "trust-region"):
            raise ValueError(
                f"KalmanSQP: `globalization` must be 'line-search' or 'trust-region'; got {self.globalization!r}."
            )
        if self.globalization == "trust-region" and self.hessian != "exact":
            raise ValueError("KalmanSQP: `globalization='trust-region'` needs `hessian='exact'`.")
        if self.hessian == "exact" and self.method != "forward":
            raise ValueError("KalmanSQP: `hessian='exact'` needs `method='forward'`.")
        checks = {
            "ctol": self.ctol > 0,
            "gtol": self.gtol > 0,
            "acceptable_gtol": self.acceptable_gtol >= self.gtol,
            "flat_steps": isinstance(self.flat_steps, int) and self.flat_steps >= 1,
            "a_t": self.a_t >= 1,
            "armijo": 0 < self.armijo < 0.5,
            "min_step": 0 < self.min_step < 1,
            "min_curvature": 0 < self.min_curvature < 1,
            "r_rel": 0 < self.r_rel < 1,
            "radius": self.radius is None or self.radius > 0,
            "zeta": 0 < self.zeta < 1,
            "gap_floor": 0 < self.gap_floor < 1,
            "eta": 0 < self.eta < 0.25,
            "mu_max": self.mu_max > 0,
            "path_dependence": 0 < self.path_dependence < 1,
            "exact_iterations": isinstance(self.exact_iterations, int) and self.exact_iterations >= 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"KalmanSQP: invalid `{name}` = {getattr(self, name)!r} (see the field docs).")

    @property
    def initial_radius(self):
        if self.radius is not None:
            return self.radius
        return 1.0 if self.globalization == "trust-region" else 0.5

    # ------------------------------------------------------------------ evaluations

    def _evaluate(self, problem, control, a, simulator, lam):
        """The restricted problem at `a`, and (hessian="exact") the convexified Hessian of
        the Lagrangian with multipliers `lam`, from one integration."""
        if self.hessian == "bfgs":
            return self._restricted(problem, control, a, simulator), None
        return self._hessian(problem, control, a, simulator, lam)

    def _restricted(self, problem, control, a, simulator):
        return evaluate_restricted(problem, control, a, simulator, self.method)

    def _hessian(self, problem, control, a, simulator, lam):
        def grad_lagrangian(a):
            ev = self._restricted(problem, control, a, simulator)
            return lagrangian_gradient(ev, lam), ev

        hess, ev = jax.jacfwd(grad_lagrangian, has_aux=True)(a)
        B = convexify(0.5 * (hess + hess.T), ev.H, self.min_curvature)
        return ev, jnp.where(jnp.all(jnp.isfinite(B)), B, jnp.eye(a.shape[0]))

    # ------------------------------------------------------------------ the QP step

    def _direction(self, ev: Evaluation, B, lam, knots, dknots):
        """The SQP step by the sequential filter: prior -P G_a with P = B^-1, observations
        H d = -E with noise `r_rel` h P h^T; then the appendix-C knot ordering."""
        P = _covariance(B)
        prior = -P @ ev.G_a
        hph = jnp.einsum("ip,pq,iq->i", ev.H, P, ev.H)
        r = self.r_rel * hph + 1e-300
        d, P1, _ = sequential_update(prior, P, ev.H, -ev.E, r)
        # One refinement pass (the same update with the first estimate as prior mean: its
        # B-metric projection onto H d = -E). When H P H^T is ill-conditioned (rows nearly
        # dependent in the metric of P), the residual left by a noise r relative to the
        # diagonal h P h^T is not small (measured 8e-7 = 1.5 |E| on case 7 near its optimum,
        # cond B 2e7); one pass brings it to 1e-13.
        d, P1, _ = sequential_update(d, P, ev.H, -ev.E, r)
        rows, m = path_rows(ev), ev.E.shape[0]
        if rows is not None:
            # Path inequalities C + C_a d <= 0 on the grid points, the appendix-C way: the
            # points of the active set become observations C_a d = -C (the boundary),
            # filtered after the terminal ones (each filtering with a refinement pass).
            C, C_a = rows
            prior_var = jnp.einsum("ip,pq,iq->i", C_a, P, C_a)  # before any observation
            r_c = self.r_rel * prior_var + 1e-300
            d_eq = d

            def filtered(active):
                d, P2, _ = sequential_update(d_eq, P1, C_a, -C, r_c, active=active)
                d, P2, _ = sequential_update(d, P1, C_a, -C, r_c, active=active)
                return d, P2

            # Active set. First the rows active at the previous iteration (positive
            # multiplier; near the boundary moved to the grid neighbour with the largest C), less
            # those whose multiplier turns negative for this QP (inequalities the step should
            # leave). Then, one row per round (a primal active-set QP), the row the step would
            # violate most, absorbed by the same rank-one update, until none is left (at most
            # np rounds): a whole violated arc (96 of 168 grid points on the attitude
            # problem's unconstrained optimum, against 21 degrees of freedom) is met through
            # its worst points instead of being observed all at once. A row (nearly)
            # dependent on E's and the active ones (its variance left below
            # `path_dependence` of its prior variance: neighbouring grid points, or the last
            # ones, which the terminal constraints fix) is skipped: it would add no freedom,
            # only ill-conditioned gains and multipliers.
            threshold = 0.01 * self.ctol

            def solve_active(warm):
                d, _ = filtered(warm)
                active = warm & (self._stationary_multipliers(ev, B, d, warm)[m:] >= 0)
                d, P2 = filtered(active)
                d, P2, active = observe_worst(
                    d, P2, C, C_a, r_c, prior_var, self.path_dependence, threshold, active, active, d.shape[0]
                )
                return d, P2, active, jnp.max(C + C_a @ d)

            # With the warm start, a violated row can be left out as dependent on a warm row
            # that no longer touches (the touching point moved to the next grid point): then
            # the active set rebuilt from the violations alone is used if it leaves less than
            # half the violation.
            warm = solve_active(_follow_maximum(lam[m:] > 0, ev.C, self.path_active))
            cold = solve_active(jnp.zeros(C.shape, bool))
            use_cold = (warm[3] > threshold) & (cold[3] < 0.5 * warm[3])
            d, P1, active, _ = jax.tree.map(lambda w, c: jnp.where(use_cold, c, w), warm, cold)
        d, _ = keep_knots_ordered(d, P1, knots, dknots, self.a_t)
        # multipliers of [E; active C] from stationarity (nu >= 0, zero off the active set)
        lam_qp = self._stationary_multipliers(ev, B, d, None if rows is None else active)
        if rows is not None:
            lam_qp = lam_qp.at[m:].set(jnp.where(active, jnp.maximum(lam_qp[m:], 0.0), 0.0))
        return d, lam_qp

    def _release_inactive(self, ev: Evaluation, lam, lam_qp):
        """`lam` with the multipliers of the path points that are strictly inactive (C <
        -`path_active`) and left out of the QP's active set set to 0 (complementarity). A
        multiplier kept there from a shortened step ((1 - alpha) of its old value) adds
        dnu C > 0 to the merit's slope along (d, lambda_qp - lambda); near the optimum that
        term outweighs -d^T B d and no direction is a descent one (measured on the attitude
        slew: nu = 9.5e-3 at C = -3.4e-6 made the slope +3.5e-8, STALLED)."""
        if ev.C is None:
            return lam
        m = ev.E.shape[0]
        stale = (lam_qp[m:] == 0.0) & (path_rows(ev)[0] < -self.path_active)
        return lam.at[m:].set(jnp.where(stale, 0.0, lam[m:]))

    @staticmethod
    def _stationary_multipliers(ev, B, d, active):
        """Least-squares solution of [H; C_a(active)]^T lam = -(G_a + B d)."""
        A = ev.H if active is None else jnp.concatenate([ev.H, jnp.where(active[:, None], path_rows(ev)[1], 0.0)])
        return jnp.linalg.lstsq(A.T, -(ev.G_a + B @ d))[0]

    def _correction(self, ev: Evaluation, B, E_cand, knots, dknots, d):
        """Second-order correction of a full step d: the smallest step (metric B) with
        H d_soc = -E(a + d), H at the current point, so that d + d_soc absorbs the
        constraints' curvature along d (Nocedal & Wright sec. 15.4); knot order kept."""
        P = _covariance(B)
        r = self.r_rel * jnp.einsum("ip,pq,iq->i", ev.H, P, ev.H) + 1e-300
        dc, _, _ = sequential_update(jnp.zeros_like(d), P, ev.H, -E_cand, r)
        dc, _, _ = sequential_update(dc, P, ev.H, -E_cand, r)
        total, _ = keep_knots_ordered(d + dc, P, knots, dknots, self.a_t)
        return jnp.where(jnp.all(jnp.isfinite(total)), total - d, 0.0)

    def _line_search_start(self, ev, lam, mu, B, d, lam_qp):
        """Penalty update and the merit's value and slope at alpha = 0."""
        dlam = lam_qp - lam
        rows = path_rows(ev)
        C, Cd = (None, None) if rows is None else (rows[0], rows[1] @ d)
        Gd, Hd = ev.G_a @ d, ev.H @ d

        def slope(mu):
            # d/dalpha of the merit of the linearized constraints along (d, dlam)
            def phi(alpha):
                C_alpha = None if C is None else C + alpha * Cd
                return _merit_value(ev.G + alpha * Gd, ev.E + alpha * Hd, C_alpha, lam + alpha * dlam, mu)

            return jax.jvp(phi, (jnp.zeros_like(mu),), (jnp.ones_like(mu),))[1]

        # The penalty rises until the slope is at most -1/2 d^T B d, where raising it lowers
        # the slope (the slope is affine in mu for the terminal part, piecewise for the PHR
        # terms): Newton steps on slope(mu) = target, doubled for a margin.
        target = -0.5 * (d @ B @ d)
        # Only a violation above `ctol` raises it: with E and C met (at round-off), the slope
        # hardly depends on mu, and the Newton step would ask for an enormous penalty whose
        # term mu/2 |E|^2 turns E's round-off into merit noise above any decrease.
        infeasible = jnp.max(jnp.abs(ev.E)) > self.ctol
        if C is not None:
            infeasible = infeasible | (jnp.max(C) > self.ctol)

        def raise_mu(_, mu):
            value, c1 = jax.jvp(slope, (mu,), (jnp.ones_like(mu),))
            needed = mu + (value - target) / jnp.where(c1 < 0, -c1, 1.0)
            return jnp.where((value > target) & (c1 < 0) & infeasible, jnp.maximum(2.0 * needed, mu), mu)

        mu = lax.fori_loop(0, 1 if rows is None else 4, raise_mu, mu)
        return dlam, mu, _merit(ev, lam, mu), slope(mu)

    # ------------------------------------------------------------------ state machine

    def init(self, problem, control, a0, simulator, max_steps):
        if self.globalization == "trust-region":
            return _trust_region.init(self, problem, control, a0, simulator, max_steps)
        lam = least_squares_multipliers(self._restricted(problem, control, a0, simulator), self.path_active)
        ev, B = self._hessian(problem, control, a0, simulator, lam)
        f = jnp.float64
        hist = History.empty(max_steps)
        ok0 = (ev.status == Status.SUCCESS) & jnp.all(jnp.isfinite(lam))
        zero = jnp.zeros_like(a0)
        return _State(
            a=a0,
            ev=ev,
            lam=jnp.where(jnp.isfinite(lam), lam, 0.0),
            B=B,
            mu=jnp.asarray(0.0, f),
            d=zero,
            dlam=jnp.zeros_like(lam),
            alpha=jnp.asarray(1.0, f),
            phi0=jnp.asarray(0.0, f),
            dphi0=jnp.asarray(0.0, f),
            searching=jnp.array(False),
            soc=jnp.array(False),
            d_soc=zero,
            alpha_bt=jnp.asarray(1.0, f),
            radius=jnp.asarray(self.initial_radius, f),
            num_flat=jnp.array(0, jnp.int32),
            best_gradient=jnp.asarray(jnp.inf, f),
            num_iterations=jnp.array(0, jnp.int32),
            num_integrations=jnp.array(2, jnp.int32),
            num_steps=jnp.array(0, jnp.int32),
            done=~ok0,
            status=Status.where(
                ok0, Status.SUCCESS, Status.where(ev.status == Status.SUCCESS, Status.NONFINITE, ev.status)
            ),
            history=hist,
        )

    def step(self, problem, control, simulator, state: _State):
        if self.globalization == "trust-region":
            return _trust_region.step(self, problem, control, simulator, state)
        ev, a, lam = state.ev, state.a, state.lam
        # A fresh direction (cheap: no integration); kept only when no search is pending.
        knots, dknots = control.knots(a), jax.jacfwd(control.knots)(a)

        def start(B):
            d, lam_qp = self._direction(ev, B, lam, knots, dknots)
            d_max = jnp.max(jnp.abs(d))
            capped = d_max > state.radius
            d = d * jnp.where(capped, state.radius / jnp.where(capped, d_max, 1.0), 1.0)
            # the penalty carries over unless it ran past `mu_max` (see the module docs)
            mu = jnp.where(state.mu > self.mu_max, 0.0, state.mu)
            base = self._release_inactive(ev, lam, lam_qp)
            return (d, base, *self._line_search_start(ev, base, mu, B, d, lam_qp))

        # If B's step is no descent direction for the merit (B degenerated, or the knot
        # ordering bent the step), restart from a scaled identity. Both are cheap (no
        # integration), so both are computed: no branch under vmap.
        B_reset = jnp.trace(state.B) / a.shape[0] * jnp.eye(a.shape[0])
        from_B, from_reset = start(state.B), start(B_reset)
        reset = ~(from_B[5] < 0)
        d_new, lam_new, dlam_new, mu_new, phi0_new, dphi0_new = jax.tree.map(
            lambda r, b: jnp.where(reset, r, b), from_reset, from_B
        )
        fresh = ~state.searching
        B = jnp.where(fresh & reset, B_reset, state.B)
        pick = lambda new, old: jnp.where(fresh, new, old)
        d, dlam, lam = pick(d_new, state.d), pick(dlam_new, state.dlam), pick(lam_new, lam)
        mu, phi0, dphi0 = pick(mu_new, state.mu), pick(phi0_new, state.phi0), pick(dphi0_new, state.dphi0)
        alpha = jnp.where(fresh, 1.0, state.alpha)

        # one integration: the candidate
        soc = state.soc
        step_taken = alpha * d + jnp.where(soc, state.d_soc, 0.0)
        lam_c = lam + alpha * dlam
        if self.hessian == "bfgs" and self.exact_iterations > 0:
            # exact Hessians for the first `exact_iterations` iterations, then BFGS
            early = state.num_iterations < self.exact_iterations
            cand, B_exact = lax.cond(
                early,
                lambda: self._hessian(problem, control, a + step_taken, simulator, lam_c),
                lambda: (self._restricted(problem, control, a + step_taken, simulator), B),
            )
        else:
            cand, B_exact = self._evaluate(problem, control, a + step_taken, simulator, lam_c)
            early = True
        phi = _merit(cand, lam_c, mu)
        finite = (cand.status == Status.SUCCESS) & jnp.isfinite(phi)
        descent = dphi0 < 0
        # Armijo, relaxed by the merit's round-off (10 eps |phi|): near the solution the
        # predicted decrease falls below what float64 can resolve.
        slack = 10.0 * jnp.finfo(phi.dtype).eps * (1.0 + jnp.abs(phi0))
        accept = finite & descent & (phi <= phi0 + self.armijo * alpha * dphi0 + slack)

        # accepted: Hessian update at the new point
        if B_exact is None:
            B_acc = _bfgs_step(B, step_taken, cand, ev, lam_c)
        elif self.hessian == "bfgs":
            B_acc = jnp.where(early, B_exact, _bfgs_step(B, step_taken, cand, ev, lam_c))
        else:
            B_acc = B_exact
        # rejected: a shorter step (quadratic interpolation of the merit, safeguarded)
        curv = (phi - phi0 - dphi0 * alpha) / alpha**2
        alpha_q = jnp.where(curv > 0, -dphi0 / (2.0 * jnp.where(curv > 0, curv, 1.0)), 0.1 * alpha)
        alpha_q = jnp.where(finite, jnp.clip(alpha_q, 0.1 * alpha, 0.5 * alpha), 0.1 * alpha)
        # A rejected full step is first retried with a second-order correction (the
        # constraints' curvature: the candidate's E observed from the same point), and the
        # backtracking step is kept for the case that the correction fails too.
        try_soc = fresh & ~accept & finite & descent
        alpha_next = jnp.where(soc, state.alpha_bt, jnp.where(try_soc, 1.0, alpha_q))
        d_soc = self._correction(ev, B, cand.E, knots, dknots, d)

        new_a = jnp.where(accept, a + step_taken, a)
        new_ev = jax.tree.map(lambda c, o: jnp.where(accept, c, o), cand, ev)
        new_lam = jnp.where(accept, lam_c, lam)
        maxE = jnp.max(jnp.abs(new_ev.E))
        pg = projected_gradient(new_ev.G_a, active_rows(new_ev, self.path_active))
        feasible = (maxE <= self.ctol) & (_max_path(new_ev) <= self.ctol)
        # No measurable progress is left: the line search failed, the direction is no
        # descent, the step is negligible, or `flat_steps` steps in a row were accepted only
        # within the merit's round-off without halving the projected gradient.
        improved = pg < 0.5 * state.best_gradient
        unresolved = accept & (phi > phi0 - slack) & ~improved
        flat = jnp.where(accept, jnp.where(unresolved, state.num_flat + 1, 0), state.num_flat)
        negligible = jnp.linalg.norm(step_taken) <= 1e-15 * (1.0 + jnp.linalg.norm(a))
        no_progress = (
            (~accept & ~try_soc & (alpha_next < self.min_step))
            | ~descent
            | (accept & negligible)
            | (flat >= self.flat_steps)
        )
        converged, stalled = kkt_outcome(feasible, pg, new_ev.G, self.gtol, self.acceptable_gtol, no_progress)
        done = converged | stalled

        i = state.num_steps
        history = state.history.record(
            i,
            objective=new_ev.G,
            max_constraint_error=maxE,
            rho=alpha,
            phase=jnp.where(fresh, 1, jnp.where(soc, 3, 2)).astype(jnp.int32),
            accepted=accept,
            constraint_tolerance=self.ctol,
        )
        return _State(
            a=new_a,
            ev=new_ev,
            lam=new_lam,
            B=jnp.where(accept, B_acc, B),
            mu=mu,
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
                accept,
                jnp.where(alpha < 1.0, alpha * jnp.max(jnp.abs(d)), jnp.minimum(2.0 * state.radius, 1e3)),
                state.radius,
            ),
            num_flat=flat.astype(jnp.int32),
            best_gradient=jnp.where(accept & improved, pg, state.best_gradient),
            num_iterations=state.num_iterations + accept.astype(jnp.int32),
            num_integrations=state.num_integrations + 1,
            num_steps=i + 1,
            done=done,
            status=Status.where(converged, Status.SUCCESS, Status.STALLED),
            history=history,
        )

    def progress(self, state: _State):
        if self.globalization == "trust-region":
            steps = {"radius": state.radius, "nu": state.nu}
        else:
            steps = {"alpha": state.alpha, "mu": state.mu}
        return {
            "iterations": state.num_iterations,
            "objective": state.ev.G,
            "max|E|": jnp.max(jnp.abs(state.ev.E)),
            **steps,
        }

    def postprocess(self, problem, control, simulator, state: _State) -> Solution:
        return Solution.from_evaluation(
            state.ev,
            state.a,
            projected_gradient=projected_gradient(state.ev.G_a, active_rows(state.ev, self.path_active)),
            iterations=state.num_iterations,
            integrations=state.num_integrations,
            steps=state.num_steps,
            done=state.done,
            status=state.status,
            history=state.history,
        )
