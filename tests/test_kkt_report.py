"""`jt.kkt_report`: residuals and multipliers by constraint name against closed-form
sensitivities of the optimal value (lambda = -dG*/db for a constraint c(a) - b, equality or
inequality), at optima that the restricted control contains exactly."""

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import reach_problem

import jaxtraj as jt


def test_equality_multipliers_are_the_value_sensitivities():
    """Minimum energy x'' = u from rest at 0 to (p, v) = (1, 0) in T = 1: J*(p, v, T) =
    2 (3 p^2 - 3 p v T + v^2 T^2) / T^3, so lambda = -dJ*/d(p, v, T) = (-12, 6, 18)."""
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl, sim = jt.controls.PiecewiseLinear(3), jt.RK4(4)
    sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.2, 0.0, 0.0), simulator=sim)
    report = jt.kkt_report(prob, ctrl, sol.params, simulator=sim)
    assert report.satisfied()
    p, v, T = 1.0, 0.0, 1.0
    dJ = (2 * (6 * p - 3 * v * T) / T**3, 2 * (-3 * p * T + 2 * v * T**2) / T**3, -6 * 3 * p**2 / T**4)
    for name, d in zip(("position", "velocity", "final time"), dJ):
        np.testing.assert_allclose(report.multipliers[name], -d, rtol=1e-6)
    # the time span t0 - tf <= 0 of the equally spaced knots: an inactive row, no multiplier
    assert set(report.violation) == {"position", "velocity", "final time", "time span"}
    assert float(report.multipliers["time span"]) == 0.0
    assert float(report.complementarity) == 0.0 and float(report.max_violation) < 1e-12
    assert "final time" in str(report) and "multiplier" in str(report)


def test_bound_and_knot_rows_are_named_with_their_multipliers():
    """Minimum-time x'' = u, |u| <= 1, rest at 0 to rest at p = 1: tf* = t1 + t2 with
    accelerations a1 (up) and a2 (down), tf* = sqrt(2 p (1/a1 + 1/a2)) = 2. dtf*/da1 = -1/2, so
    each active bound row has nu = 1/2; dtf*/dp = 1 gives lambda_x = -1, and a target speed v
    shortens the braking arc one for one (dtf*/dv = -1): lambda_v = +1. The knot gaps are
    inactive rows (nu = 0)."""
    c = jt.problems.classic.min_time_double_integrator()
    sol = jt.solve(c.problem, c.control, c.start)
    report = jt.kkt_report(c.problem, c.control, sol.params)
    assert report.satisfied()
    m = report.multipliers
    np.testing.assert_allclose([m["x"], m["v"]], [-1.0, 1.0], rtol=1e-8)
    # the first level is at its upper bound, the second at its lower one
    np.testing.assert_allclose([m["u1 upper bound at a[0]"], m["u1 lower bound at a[2]"]], [0.5, 0.5], rtol=1e-8)
    assert float(m["u1 lower bound at a[0]"]) == 0.0 and float(m["u1 upper bound at a[2]"]) == 0.0
    assert float(m["segment 0 length"]) == 0.0 and float(m["segment 1 length"]) == 0.0
    # the start: infeasible, not stationary, named violations
    start = jt.kkt_report(c.problem, c.control, c.start)
    assert not start.satisfied() and float(start.violation["x"]) == pytest.approx(1.0)


def _bryson_denham(limit):
    return jt.Problem(
        lambda t, x, u, args: jnp.stack([x[1], u[0]]),
        [0.0, 1.0],
        lambda tf, xf, args: xf - jnp.array([0.0, -1.0]),
        ("x", "v"),
        running_cost=lambda t, x, u, args: 0.5 * u[0] ** 2,
        final_time=1.0,
        state_names=("x", "v"),
        state_upper=[limit, np.inf],
    )


@pytest.mark.slow
def test_a_path_constraint_multiplier_is_the_value_sensitivity():
    """Bryson-Denham with x <= l, 1/6 < l < 1/4: the optimum touches the bound once, at t =
    1/2, with u = alpha + beta t on [0, 1/2] (mirrored), beta = 24 - 96 l, alpha = 24 l - 8, and
    J*(l) = alpha^2 / 2 + alpha beta / 4 + beta^2 / 24. PiecewiseLinear(2) contains it and RK4
    is exact on it, so the grid multipliers of "x upper bound" sum to -dJ*/dl (9.6 at l = 0.2)."""
    limit = 0.2
    prob, sim = _bryson_denham(limit), jt.RK4(4)
    ctrl = prob.parametrize(jt.controls.PiecewiseLinear(2))
    sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.0, -2.0, -2.0), simulator=sim)
    report = jt.kkt_report(prob, ctrl, sol.params, simulator=sim)
    alpha, beta = 24 * limit - 8, 24 - 96 * limit
    np.testing.assert_allclose(report.objective, alpha**2 / 2 + alpha * beta / 4 + beta**2 / 24, rtol=1e-9)
    dJ = alpha * 24 + (24 * beta - 96 * alpha) / 4 - 96 * beta / 12
    assert report.satisfied()
    np.testing.assert_allclose(report.multipliers["x upper bound"], -dJ, rtol=1e-6)
    assert float(report.violation["x upper bound"]) < 1e-10 and float(report.complementarity) < 1e-8


def test_bad_arguments_are_named():
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl = jt.controls.PiecewiseLinear(3)
    with pytest.raises(ValueError, match="`active`"):
        jt.kkt_report(prob, ctrl, ctrl.initial_guess(1.0, 0.0, 0.0), active=0.0)
    with pytest.raises(ValueError, match="`active` must be a finite number > 0; got inf"):  # (was accepted)
        jt.kkt_report(prob, ctrl, ctrl.initial_guess(1.0, 0.0, 0.0), active=float("inf"))
    with pytest.raises(ValueError, match="shape"):
        jt.kkt_report(prob, ctrl, jnp.zeros(3))


@pytest.mark.parametrize("seed", range(6))
def test_start_multipliers_with_nearly_dependent_rows(seed):
    """The start's least-squares multipliers (`least_squares_multipliers`: lambda free, nu >= 0
    on the near-active rows) against scipy's bounded least squares on rows like neighbouring
    grid points of a path constraint (pairs nearly dependent, 1e-9 apart). One unbounded
    solve with its negative nu clipped afterwards left residuals of 1e10 and multipliers of
    6e10 at a random start of the attitude slew with the cone."""
    from scipy.optimize import lsq_linear

    from jaxtraj import Evaluation
    from jaxtraj._kkt import least_squares_multipliers

    rng = np.random.default_rng(seed)
    n, me, pairs = 12, 3, 4
    H = rng.normal(size=(me, n))
    base = rng.normal(size=(pairs, n))
    C_a = np.concatenate([base, base + 1e-9 * rng.normal(size=(pairs, n)), rng.normal(size=(2, n))])
    C = np.concatenate([np.zeros(2 * pairs), [-1e-9, -0.5]])  # the last row is not near-active
    g = rng.normal(size=n)
    ev = Evaluation(
        xf=None, xf_a=None, tf=None, G=0.0, G_a=jnp.asarray(g), E=jnp.zeros(me), H=jnp.asarray(H), status=None,
        D=jnp.asarray(C), D_a=jnp.asarray(C_a),
    )  # fmt: skip
    lam = np.asarray(least_squares_multipliers(ev, 1e-6))
    near = C >= -1e-6
    A = np.concatenate([H, C_a[near]])
    lo = np.concatenate([np.full(me, -np.inf), np.zeros(near.sum())])
    ref = lsq_linear(A.T, -g, bounds=(lo, np.inf), tol=1e-14)
    best = np.linalg.norm(A.T @ ref.x + g)
    assert np.all(lam[me:] >= 0.0) and np.all(lam[me:][~near] == 0.0)
    res = np.linalg.norm(np.concatenate([H, C_a]).T @ lam + g)
    # the rounds (dropping every row with a negative multiplier at once) bound the minimum
    # from above, measured within 1 % of it here
    assert res <= 1.05 * best + 1e-9, (res, best)
    assert np.max(np.abs(lam)) <= 10.0 * (1.0 + np.max(np.abs(ref.x))), (lam, ref.x)


def test_report_prints_its_own_verdict():
    """Issue 49: at a point that is not a KKT point the table was headed "KKT report
    (SUCCESS)" (the evaluation's status). A minimum time with |u| <= 1 that must reach x >= 1
    (x'' = u): at u = 1, tf = 1.5 the reach row is inactive and nothing balances d tf (the
    stationarity residual is |D e_tf| = 1.5); at tf = sqrt(2) the reach and the bound hold it."""
    prob = reach_problem()
    ctrl = jt.controls.PiecewiseConstant(1)
    report = jt.kkt_report(prob, ctrl, jnp.array([1.0, 1.5]))
    assert not report.satisfied() and float(report.stationarity) == pytest.approx(1.5, rel=1e-9)
    assert str(report).startswith("KKT report, NOT a KKT point: stationarity 1.50e+00 > gtol")
    optimum = jt.kkt_report(prob, ctrl, jnp.array([1.0, np.sqrt(2.0)]))
    assert optimum.satisfied() and str(optimum).startswith("KKT report, KKT point")
    with pytest.raises(ValueError, match="ctol"):
        optimum.satisfied(ctol="x")
    # infinite tolerances made the infeasible start a KKT point (issue 51, third audit)
    start = jt.kkt_report(prob, ctrl, jnp.array([0.0, 1.0]))
    for bad in ({"ctol": float("inf"), "gtol": float("inf")}, {"gtol": float("inf")}):
        with pytest.raises(ValueError, match="must be a finite number > 0; got inf"):
            start.satisfied(**bad)


def test_report_counts_complementarity_in_its_verdict():
    """A point 1e-7 inside the reach row with u on its bound: within `active` of the row, so
    its multiplier balances d tf (stationarity ~0), but nu |C| = 1e-7 (1/sqrt2) is what the
    row still costs the objective, above gtol (1 + |G|) = 2.4e-8 for gtol 1e-8: not a KKT
    point at that tolerance, and at 1e-6 it is."""
    prob = reach_problem()
    ctrl = jt.controls.PiecewiseConstant(1)
    tf = np.sqrt(2.0 * (1.0 + 1e-7))  # x(tf) = tf^2 / 2 = 1 + 1e-7
    report = jt.kkt_report(prob, ctrl, jnp.array([1.0, tf]))
    assert float(report.stationarity) < 1e-12
    assert float(report.complementarity) == pytest.approx(1e-7 / np.sqrt(2.0), rel=1e-3)
    assert not report.satisfied(gtol=1e-8) and report.failures(gtol=1e-8)[0].startswith("complementarity")
    assert report.satisfied(gtol=1e-6)


@pytest.mark.parametrize("seed", range(6))
def test_signed_multipliers_are_the_exact_non_negative_least_squares(seed):
    """min |g + H^T lambda + C_a^T nu| over free lambda and nu >= 0 against SciPy's bounded
    least squares (`lsq_linear`, an independent solver): the residual agrees to round-off,
    also at degenerate vertices (more rows than parameters, dependent rows, a gradient in
    the cone of some of them), where the rounds alone (drop every negative multiplier at
    once) overstated it: the robot arm's KKT point was rejected (tests/test_user_problems.py)."""
    import scipy.optimize

    from jaxtraj._kkt import signed_multipliers

    rng = np.random.default_rng(seed)
    n, m, r = 8, int(rng.integers(0, 3)), int(rng.integers(6, 14))
    H = rng.standard_normal((m, n))
    C_a = rng.standard_normal((r, n))
    C_a[: r // 3] = C_a[r // 3 : 2 * (r // 3)] * rng.uniform(0.5, 2.0, (r // 3, 1))  # dependent pairs
    nu = np.where(rng.uniform(size=r) < 0.5, rng.uniform(0.1, 2.0, r), 0.0)
    g = -(H.T @ rng.standard_normal(m) + C_a.T @ nu) + 1e-3 * (seed % 2) * rng.standard_normal(n)
    keep = rng.uniform(size=r) < 0.9
    A = np.concatenate([H, C_a[keep]]).T
    lo = np.concatenate([np.full(m, -np.inf), np.zeros(int(keep.sum()))])
    exact = scipy.optimize.lsq_linear(A, -g, bounds=(lo, np.inf), lsmr_tol="auto", tol=1e-14, method="bvls")
    residual, lam = signed_multipliers(jnp.asarray(g), jnp.asarray(H), jnp.asarray(C_a), jnp.asarray(keep))
    assert np.all(np.asarray(lam)[m:] >= 0.0) and np.all(np.asarray(lam)[m:][~keep] == 0.0)
    assert abs(float(residual) - np.linalg.norm(A @ exact.x + g)) <= 1e-9 * (1.0 + np.linalg.norm(g))
