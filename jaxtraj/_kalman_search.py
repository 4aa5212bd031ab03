"""The Kalman-filter direct search of the source thesis (seed 000, chapters 3-4, appendices
B and C; restated in ALGORITHM.md sections 3-5) as a jittable, vmappable state machine.

One `step` = one candidate: compute the search increment Da with the sequential Kalman
update (prior -rho G_a, observations -s_i E_i), run the *preliminary* linearized checks
(re-tuning rho and the betas and recomputing Da, without integrating, until they pass), add
the node-time ordering observations of appendix C, integrate a + Da with sensitivities, and
run the *final* checks: accept, or shrink Da by the quadratic-model factor and retry. The
first step's candidate is the start itself (`init` integrates nothing, so the program holds
the evaluation kernel once).

Each decision where the OCR of the source is ambiguous or silent is marked "OCR:" below; the
list of them, our extensions (held knot gaps, path constraints) and the convergence tests:
docs/solvers/kalman-search.md (the algorithm, its history and measurements).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._bounds import require_rows
from ._checks import check_settings, is_count
from ._driver import AbstractSolver, SolverState, only_where, start_counters
from ._kalman import PATH_DEPENDENCE, keep_knots_ordered, observe_worst, sequential_update
from ._kkt import ACTIVE_TOL, constraint_rows, inequality_rows, stationarity
from ._sensitivity import Evaluation, evaluate_jitted, unevaluated
from ._solution import Solution
from ._status import Status

_ALPHAS = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.15, 0.1, 0.07, 0.05, 0.03, 0.02, 0.01])


class _State(SolverState):
    a: jax.Array
    ev: Evaluation
    rho: jax.Array
    beta: jax.Array
    beta_p: jax.Array
    phase: jax.Array  # 0 capture, 1 minimum search
    e_a: jax.Array
    da_pending: jax.Array
    has_pending: jax.Array
    since_reject: jax.Array
    num_rejections: jax.Array


def _values(ev: Evaluation):
    """[E; C (flattened)]: the terminal constraints and the path constraints on the grid."""
    rows = inequality_rows(ev)
    return ev.E if rows is None else jnp.concatenate([ev.E, rows[0]])


def _errors(ev: Evaluation, values):
    """The error vector of constraint values [E; C]: E and max(C, 0) (met: zero)."""
    m = ev.E.shape[0]
    return values if values.shape[0] == m else jnp.concatenate([values[:m], jnp.maximum(values[m:], 0.0)])


def _largest_alpha(ok_of_alpha, fallback):
    """Largest alpha of the grid with `ok_of_alpha(alpha)`, else `fallback`."""
    alphas = jnp.asarray(_ALPHAS)
    ok = jax.vmap(ok_of_alpha)(alphas)
    return jnp.where(jnp.any(ok), alphas[jnp.argmax(ok)], fallback)


class KalmanSearch(AbstractSolver):
    """The thesis's Kalman-filter direct search, with its published tuning defaults.

    Fields (seed 000 appendix B, "inputs of the method"; defaults = the Earth-Mars tests):

    - `rho`: initial weight of the gradient prior -rho G_a (1.0; 0.8 in test 7).
    - `beta`, `beta_p`, `beta_0`, `beta_p0`: prior covariance factors (1, 1, 1, 2).
    - `e_m`: negligible numerical error (integration error level), 1e-10.
    - `e_a`: final constraint tolerance (1e-8); `e_a_start` (1e-3) and `e_a_shrink` (100)
      the tolerance schedule; `f_ea` (1) the minimum-search band factor.
    - `gtol`: projected-gradient tolerance (relative to 1 + |G|).
    - `a_t`: node-time approach ratio of appendix C (>= 1; not printed in the thesis).
      10 lets two knots close at most ~1/10 of their gap per step: with 2, a piece of
      case 7 collapses before the other parameters adapt and the search stalls at tf
      3.3431; with 10 it keeps all five pieces and converges to the best known optimum.
    - `rho_increase`, `rho_decrease`, `beta_increase`, `beta_decrease`: adaptation ratios;
      `rho_max` caps rho (beyond ~1e3 the ratio P / R exceeds what float64 can filter).
    - `linearity_ratio`: e_gamma of [B.2] in (0, 1).
    - `max_rejections`: consecutive rejected candidates before STALLED (MAXREJ);
      `max_retunings`: preliminary re-tunings per candidate.
    - `min_shrink`: smallest step-shrink factor.
    - `gap_keep`: the least fraction of a knot gap one increment keeps (0.5; docs/solvers/kalman-search.md).

    What SUCCESS guarantees: max |E_i| <= `e_a`, max C <= `e_a` on the grid, and the
    projected gradient |V G_a| (scaled parameters, docs/solvers/kalman-search.md) <= max(`gtol`, `e_a`) (1 + |G|)
    (1e-5 relative by default: a first-order method, it stops at the first point that passes). It bounds the
    distance to the optimum only through the curvature: |a - a*| <= |V G_a| / lambda_min(reduced
    Hessian) on a convex quadratic problem (3e-4 on the min-energy double integrator with
    `PiecewiseLinear(3)`, tested). A `gtol` far below the default may not be reached: the
    search zigzags inside the constraint band and ends STALLED at a point that depends on
    the round-off (gtol = 1e-9 there: 4 of 9 round-off-perturbed starts). For stationarity
    to 1e-9 use `jt.KalmanSQP`. A batch
    (`jax.vmap`, `jt.solve_batch`) is not bitwise equal to single solves (XLA compiles the
    batched program differently); both meet the same guarantee.
    """

    rho: float = 1.0
    beta: float = 1.0
    beta_p: float = 1.0
    beta_0: float = 1.0
    beta_p0: float = 2.0
    e_m: float = 1e-10
    e_a: float = 1e-8
    e_a_start: float = 1e-3
    e_a_shrink: float = 10.0
    f_ea: float = 1.0
    gtol: float = 1e-5
    a_t: float = 10.0
    rho_increase: float = 2.0
    rho_max: float = 1e3
    rho_decrease: float = 0.5
    beta_increase: float = 2.0
    beta_decrease: float = 0.5
    linearity_ratio: float = 0.5
    max_rejections: int = 12
    max_retunings: int = 30
    min_shrink: float = 0.05
    gap_keep: float = 0.5
    method: str = "forward"

    def __check_init__(self):
        inf = math.inf  # (every setting finite: e_a or gtol = inf was SUCCESS at any point)
        checks = {
            "rho": lambda: 0 < self.rho < inf,
            "beta": lambda: 0 < self.beta < inf,
            "beta_p": lambda: 1 <= self.beta_p < inf,
            "beta_0": lambda: self.beta <= self.beta_0 < inf,
            "beta_p0": lambda: self.beta_p <= self.beta_p0 < inf,
            "e_m": lambda: 0 < self.e_m < inf,
            "e_a": lambda: 0 < self.e_a < inf,
            "e_a_start": lambda: self.e_a <= self.e_a_start < inf,
            "e_a_shrink": lambda: 1 < self.e_a_shrink < inf,
            "f_ea": lambda: 1 <= self.f_ea < inf,
            "gtol": lambda: 0 < self.gtol < inf,
            "a_t": lambda: 1 <= self.a_t < inf,
            "rho_increase": lambda: 1 <= self.rho_increase < inf,
            "rho_max": lambda: 0 < self.rho_max < inf,
            "rho_decrease": lambda: 0 < self.rho_decrease <= 1,
            "beta_increase": lambda: 1 <= self.beta_increase < inf,
            "beta_decrease": lambda: 0 < self.beta_decrease <= 1,
            "linearity_ratio": lambda: 0 < self.linearity_ratio < 1,
            "max_rejections": lambda: is_count(self.max_rejections, 1),
            "max_retunings": lambda: is_count(self.max_retunings, 0),
            "min_shrink": lambda: 0 < self.min_shrink < 1,
            "gap_keep": lambda: 0 < self.gap_keep < 1,
        }
        check_settings("KalmanSearch", self, checks)
        if self.method not in ("forward", "unit"):
            raise ValueError(f"KalmanSearch: `method` must be 'forward' or 'unit'; got {self.method!r}.")

    # ------------------------------------------------------------------ the increment

    def _increment(self, ev: Evaluation, rho, beta, beta_p, phase, knots, dknots):
        """Da by the sequential filter (sections 3-4 of ALGORITHM.md) and appendix C."""
        G_a, H, E = ev.G_a, ev.H, ev.E
        e_m2 = self.e_m**2
        r = e_m2 / 3.0  # [4.2]
        hh = jnp.sum(H * H, axis=1)
        e_ei = e_m2 / (3.0 * jnp.maximum(hh, 1e-300))  # [4.4]
        # (0 without terminal constraints: the prior is then the gradient step's alone)
        e_e2 = jnp.where(phase == 0, jnp.max(e_ei, initial=0.0), jnp.sum(e_ei) / max(e_ei.size, 1))
        uncorrelated = G_a == 0
        b = jnp.where(uncorrelated, self.beta_0 * beta / self.beta, beta)
        bp = jnp.where(uncorrelated, self.beta_p0 * beta_p / self.beta_p, beta_p)
        g2 = jnp.sum(G_a * G_a)
        P = jnp.diag(2.0 * b * e_e2 + bp * rho**2 * g2)  # [4.3]  (OCR: full |G_a|^2)
        prior = -rho * G_a  # [4.1]
        # desired correction fractions [3.35-3.36]
        c = rho * (H @ G_a)
        q = r + jnp.einsum("ip,p,ip->i", H, jnp.diag(P), H)
        absE = jnp.maximum(jnp.abs(E), 1e-300)
        s_bar = (c * jnp.sign(E) + jnp.sqrt(q)) / absE
        s = jnp.where(s_bar <= 2.0, 0.5 * s_bar, 1.0)
        z = -s * E  # [4.6]
        # R = e_m^2/3 [4.2], floored at 1e-14 h P h^T: beyond a ratio P/R of ~1e14 the
        # sequential update loses the covariance to round-off (the floor changes the
        # absorbed correction by at most 1e-14 of itself).
        r_obs = jnp.maximum(r, 1e-14 * (q - r))
        da, P1, _ = sequential_update(prior, P, H, z, r_obs)
        rows = inequality_rows(ev)
        if rows is not None:  # path constraints: predicted violations observed at their boundary
            C, C_a = rows
            prior_var = jnp.einsum("ip,pq,iq->i", C_a, P, C_a)
            none = jnp.zeros(C.shape, bool)
            r_c = jnp.maximum(r, 1e-14 * prior_var)  # floored as r_obs
            da, P1, _ = observe_worst(da, P1, C, C_a, r_c, prior_var, PATH_DEPENDENCE, 0.0, none, none, da.shape[0])
        da2, P2 = keep_knots_ordered(da, P1, knots, dknots, self.a_t, self.gap_keep)  # appendix C
        return da2, P2, s_bar

    def _preliminary(self, ev, rho, beta, beta_p, phase, e_a, knots, dknots):
        """Recompute Da, re-tuning rho and the betas, until the linearized checks pass
        (capture: [4.9]; minimum search: [4.14], [4.19]); then cap the predicted change of
        the constraints [4.27-4.28]. Returns (da, rho, beta, beta_p, stationary)."""
        E, G_a = ev.E, ev.G_a
        err_abs = jnp.abs(_errors(ev, _values(ev)))
        nE = jnp.linalg.norm(err_abs)

        def attempt(rho, beta, beta_p):
            da, _P1, s_bar = self._increment(ev, rho, beta, beta_p, phase, knots, dknots)
            err_lin = _errors(ev, _values(ev) + constraint_rows(ev) @ da)  # [E; max(C, 0)], linearized
            capture_ok = jnp.all(jnp.abs(err_lin) <= err_abs + 10.0 * self.e_m) & (jnp.linalg.norm(err_lin) < nE)
            band_ok = jnp.all(jnp.abs(err_lin) <= self.f_ea * e_a)  # [4.14]
            descent_ok = G_a @ da < 0.0  # [4.19]
            ok = jnp.where(phase == 0, capture_ok, band_ok & descent_ok)
            return da, s_bar, ok, band_ok, descent_ok

        def cond(carry):
            _, _, _, _, ok, tries, _ = carry
            return ~ok & (tries < self.max_retunings)

        def body(carry):
            rho, beta, beta_p, _, _, tries, _ = carry
            da, s_bar, ok, band_ok, descent_ok = attempt(rho, beta, beta_p)
            some_small = jnp.any(s_bar < 2.0)
            # capture [4.9 failure]: lower rho; raise the betas when some s_bar < 2
            c_rho = rho * self.rho_decrease
            c_beta = jnp.where(some_small, beta * self.beta_increase, beta)
            c_betap = jnp.where(some_small, beta_p * self.beta_increase, beta_p)
            # minimum search [4.14 failure]: raise the betas up to beta_0, beta_p0, then lower rho
            at_cap = (beta >= self.beta_0) & (beta_p >= self.beta_p0)
            m_rho = jnp.where(~band_ok & at_cap, rho * self.rho_decrease, rho)
            m_beta = jnp.where(~band_ok, jnp.minimum(beta * self.beta_increase, self.beta_0), beta)
            m_betap = jnp.where(~band_ok, jnp.minimum(beta_p * self.beta_increase, self.beta_p0), beta_p)
            # minimum search [4.19 failure]: lower the betas (floor 1). Once they are at 1 the
            # constraint correction costs more objective than the gradient prior gains; a
            # smaller rho would only make that worse, so rho is *raised* (our decision).
            low = ~descent_ok & band_ok
            at_floor = (beta <= 1.0) & (beta_p <= 1.0)
            m_rho = jnp.where(low & at_floor, rho * self.rho_increase, m_rho)
            m_beta = jnp.where(low, jnp.maximum(beta * self.beta_decrease, 1.0), m_beta)
            m_betap = jnp.where(low, jnp.maximum(beta_p * self.beta_decrease, 1.0), m_betap)
            new = [jnp.where(phase == 0, cv, mv) for cv, mv in ((c_rho, m_rho), (c_beta, m_beta), (c_betap, m_betap))]
            new[0] = jnp.minimum(new[0], self.rho_max)
            keep = [jnp.where(ok, old, nv) for old, nv in zip((rho, beta, beta_p), new)]
            return (*keep, da, ok, tries + 1, s_bar)

        npar = G_a.shape[0]
        init = (rho, beta, beta_p, jnp.zeros(npar), jnp.array(False), jnp.array(0), jnp.zeros(E.shape))
        rho, beta, beta_p, da, ok, _, _ = lax.while_loop(cond, body, init)
        # [4.27-4.28] minimum search: cap the predicted change of each constraint component.
        # OCR: |m'_i - m_i| <= 2 (f_ea e_a - |m_i|) / 3. Read literally it forbids any change,
        # the correction of E towards 0 included, once E sits at the band's edge, and the
        # search crawls (case 7 did not converge in 3000 steps). We allow the move to E = 0
        # plus 2/3 of the remaining band: room = 2/3 (f_ea e_a - |E_i|) + |E_i|.
        dE = jnp.abs(ev.H @ da)
        room = 2.0 * jnp.maximum(self.f_ea * e_a - jnp.abs(E), 0.0) / 3.0 + jnp.abs(E)
        cap = jnp.where(dE > room, room / jnp.maximum(dE, 1e-300), 1.0)
        da = jnp.where(phase == 1, da * jnp.min(cap, initial=1.0), da)
        return da, rho, beta, beta_p, ~ok

    # ------------------------------------------------------------------ state machine

    def check(self, problem, control):
        require_rows(problem, control, "KalmanSearch")

    def init(self, problem, control, a0, simulator, max_steps):
        self.check(problem, control)
        # Nothing is integrated here: the first `step` evaluates the start (a pending
        # increment of zero), so the compiled program holds the evaluation kernel once.
        f = jnp.float64
        return _State(
            a=a0,
            ev=unevaluated(lambda a: evaluate_jitted(problem, control, a, simulator, self.method), a0),
            rho=jnp.asarray(self.rho, f),
            beta=jnp.asarray(self.beta, f),
            beta_p=jnp.asarray(self.beta_p, f),
            phase=jnp.array(0, jnp.int32),
            e_a=jnp.asarray(self.e_a_start, f),
            da_pending=jnp.zeros_like(a0),
            has_pending=jnp.array(True),
            since_reject=jnp.array(2, jnp.int32),
            num_rejections=jnp.array(0, jnp.int32),
            **start_counters(max_steps, ("rho", "phase")),
        )

    def step(self, problem, control, simulator, state: _State):
        ev, a, phase, e_a = state.ev, state.a, state.phase, state.e_a
        knots = control.knots(a)
        dknots = jax.jacfwd(control.knots)(a)
        # A shrunk candidate from a rejected step is retried as it is; only a fresh step
        # runs the filter and the preliminary re-tuning loop (and, under `vmap`, a finished
        # lane, which still runs the step, nothing).
        da, rho, beta, beta_p, stationary = only_where(
            ~state.has_pending & ~state.done,
            lambda ev, rho, beta, beta_p, e_a: self._preliminary(ev, rho, beta, beta_p, phase, e_a, knots, dknots),
            (state.da_pending, state.rho, state.beta, state.beta_p, jnp.array(False)),
            ev,
            state.rho,
            state.beta,
            state.beta_p,
            e_a,
        )

        # integrate the candidate (one integration with sensitivities; the first step's is
        # the start, accepted when finite, with the phase its errors give)
        first = state.num_steps == 0
        cand = evaluate_jitted(problem, control, a + da, simulator, self.method)
        finite = cand.status == Status.SUCCESS
        # the checks on the error vector [E; max(C, 0)], its models on the raw values
        y, y_star, y_lin = _values(ev), _values(cand), _values(ev) + constraint_rows(ev) @ da
        E, E_star, E_lin = _errors(ev, y), _errors(ev, y_star), _errors(ev, y_lin)
        G, G_star, dG_lin = ev.G, cand.G, ev.G_a @ da
        nE = jnp.linalg.norm(E)
        band = self.f_ea * e_a

        # final checks [4.39] / [4.43, 4.45]
        capture_ok = jnp.linalg.norm(E_star) < nE
        min_ok = jnp.all(jnp.abs(E_star) <= band) & (G_star < G)
        accept = finite & (first | jnp.where(phase == 0, capture_ok, min_ok))

        # shrink factor from the quadratic models [4.40], [4.44], [4.47]
        def model(al):
            return _errors(ev, y + al * (y_lin - y) + al**2 * (y_star - y_lin))

        def capture_model(al):
            return jnp.linalg.norm(model(al)) < nE

        def min_model(al):
            e_ok = jnp.all(jnp.abs(model(al)) <= band)
            g_ok = G + al * dG_lin + al**2 * (G_star - G - dG_lin) < G
            return e_ok & g_ok

        fallback = jnp.asarray(self.min_shrink * 2.0)
        alpha = jnp.where(phase == 0, _largest_alpha(capture_model, fallback), _largest_alpha(min_model, fallback))
        alpha = jnp.where(finite, jnp.maximum(alpha, self.min_shrink), 0.25)

        # adaptation after acceptance [B.1, B.2, B.5] (on E alone)
        E, E_star, E_lin = ev.E, cand.E, ev.E + ev.H @ da
        nonlin_E = jnp.abs(E_star - E_lin)
        lin_capture = jnp.linalg.norm(E_star - E_lin) < self.linearity_ratio * jnp.linalg.norm(E_lin - E)
        lin_min = (jnp.abs(G_star - G - dG_lin) < self.linearity_ratio * jnp.abs(dG_lin)) & jnp.all(
            nonlin_E <= self.linearity_ratio * jnp.maximum(jnp.abs(E_lin - E), band - jnp.abs(E_lin))
        )
        linear = jnp.where(phase == 0, lin_capture, lin_min) & (state.since_reject >= 2) & ~first
        rho_acc = jnp.where(linear, rho * self.rho_increase, rho)
        reduced_all = jnp.all(jnp.abs(E_star) < jnp.abs(E))
        lower_betas = (phase == 1) & reduced_all
        beta_acc = jnp.where(lower_betas, jnp.maximum(beta * self.beta_decrease, 1.0), beta)
        betap_acc = jnp.where(lower_betas, jnp.maximum(beta_p * self.beta_decrease, 1.0), beta_p)

        # the new current point
        new_a = jnp.where(accept, a + da, a)
        new_ev = jax.tree.map(lambda c, o: jnp.where(accept, c, o), cand, ev)
        maxE = jnp.max(jnp.abs(_errors(new_ev, _values(new_ev))), initial=0.0)
        new_phase = jnp.where(accept & (phase == 0) & (maxE <= e_a), 1, phase).astype(jnp.int32)
        n_rej = jnp.where(accept, 0, state.num_rejections + 1)

        # convergence of the minimum search at this tolerance [3.62, 4.26, 4.48]
        # (the projected gradient only where it can decide: least-squares rounds over the
        # near-active rows)
        in_band = (new_phase == 1) & (maxE <= e_a)
        pg = only_where(
            in_band & ~state.done,
            lambda ev, a: stationarity(ev, a, e_a),
            jnp.asarray(jnp.inf, a.dtype),
            new_ev,
            new_a,
        )
        gnorm_tol = jnp.maximum(self.gtol, e_a) * (1.0 + jnp.abs(new_ev.G))
        negligible = ~accept & (jnp.linalg.norm(alpha * da) <= self.e_m * (1.0 + jnp.linalg.norm(a)))
        converged_here = in_band & (pg <= gnorm_tol)
        final_stage = e_a <= self.e_a * (1.0 + 1e-12)
        # A loose stage is also over when the preliminary checks found no increment that
        # decreases G inside the band [4.14, 4.19]: the search rides the band's edge, where
        # the correction of E costs as much as the gradient step gains.
        no_descent = (phase == 1) & stationary
        converged_here = converged_here | (no_descent & ~final_stage & (new_phase == 1))
        next_e_a = jnp.maximum(e_a / self.e_a_shrink, self.e_a)
        advance = converged_here & ~final_stage
        success = converged_here & final_stage
        # MAXREJ or a negligible step without the projected-gradient test [3.62] passing: the
        # thesis only calls that convergence when 3.62 holds; otherwise we report STALLED.
        stalled = ~converged_here & ((n_rej > self.max_rejections) | negligible)
        stationary_fail = stationary & (phase == 0) & ~accept
        stalled = stalled | (no_descent & final_stage & ~converged_here)
        new_e_a = jnp.where(advance, next_e_a, e_a)
        new_phase = jnp.where(advance, jnp.where(maxE <= next_e_a, 1, 0), new_phase).astype(jnp.int32)

        bad_start = first & ~finite
        done = success | stalled | stationary_fail | bad_start
        status = Status.where(
            success,
            Status.SUCCESS,
            Status.where(
                stalled, Status.STALLED, Status.where(stationary_fail, Status.CONSTRAINT_STATIONARY, Status.SUCCESS)
            ),
        )
        status = Status.where(bad_start, cand.status, status)
        i = state.num_steps
        history = state.history.record(
            i,
            objective=new_ev.G,
            max_constraint_error=maxE,
            step_norm=jnp.linalg.norm(da),
            accepted=accept,
            constraint_tolerance=e_a,
            details={"rho": rho, "phase": phase},
        )
        return _State(
            a=new_a,
            ev=new_ev,
            rho=jnp.minimum(
                jnp.where(advance, self.rho, jnp.where(accept, rho_acc, rho * jnp.where(finite, alpha, 0.25))),
                self.rho_max,
            ),
            beta=jnp.where(accept, beta_acc, beta),
            beta_p=jnp.where(accept, betap_acc, beta_p),
            phase=new_phase,
            e_a=new_e_a,
            da_pending=jnp.where(accept, jnp.zeros_like(da), alpha * da),
            has_pending=~accept & ~advance,
            since_reject=jnp.where(first, state.since_reject, jnp.where(accept, state.since_reject + 1, 0)).astype(
                jnp.int32
            ),
            num_rejections=n_rej.astype(jnp.int32),
            num_iterations=state.num_iterations + (accept & ~first).astype(jnp.int32),
            num_integrations=state.num_integrations + 1,
            num_steps=i + 1,
            done=done,
            status=status,
            history=history,
        )

    def progress(self, state: _State):
        return {
            "accepted": state.num_iterations,
            "objective": state.ev.G,
            "max|E|": jnp.max(jnp.abs(state.ev.E), initial=0.0),
            "e_a": state.e_a,
            "rho": state.rho,
        }

    def postprocess(self, problem, control, simulator, state: _State) -> Solution:
        return Solution.from_evaluation(
            state.ev,
            state.a,
            control=control,
            active_tol=ACTIVE_TOL,
            projected_gradient=stationarity(state.ev, state.a, state.e_a),
            iterations=state.num_iterations,
            integrations=state.num_integrations,
            steps=state.num_steps,
            done=state.done,
            status=state.status,
            history=state.history,
        )
