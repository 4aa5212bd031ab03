"""SciPy SLSQP baseline (`jaxtraj.baselines.solve_slsqp`) on Earth-Mars thesis case 4."""

import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.baselines import SLSQPResult, solve_ipopt, solve_slsqp

# Case 4 optimum with RK4(100), from benchmarks/reference_optima.md: all 8 starts agree to
# 1e-11, and re-solving with adaptive Tsit5 (rtol = atol = 1e-12) moves tf by only 7e-11.
CASE4_TF = 3.32488832


def test_slsqp_earth_mars_case4_optimum():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    res = solve_slsqp(prob, ctrl, a0)

    assert isinstance(res, SLSQPResult)
    assert res.success, res.message
    assert res.params.dtype == np.float64 and res.params.shape == (ctrl.num_params,)
    assert res.max_constraint_error <= 1e-10
    assert res.tf == res.objective  # minimum time
    assert abs(res.tf - res.params[-1]) < 1e-14  # tf is the last entry (up to tf * K / K rounding)
    # Bounds independent of the code under test: the restricted optimum can be no better
    # than the unrestricted one (3.31949, seed 000 sec. 5.2) and, at the optimum, no worse
    # than the thesis's own converged restricted result (3.32533, Table 5.7).
    assert jt.problems.earth_mars.TF_UNRESTRICTED - 1e-5 < res.tf < jt.problems.earth_mars.PUBLISHED[4][0]
    assert abs(res.tf - CASE4_TF) < 1e-6
    # one integration per distinct point: far fewer than SLSQP's fun + jac + constraint calls
    assert res.iterations <= res.evaluations <= 4 * res.iterations + 10

    # First-order optimality (KKT), checked with the library's evaluation, not SLSQP's:
    # G_a = H^T lambda for some multipliers lambda.
    ev = jt.evaluate(prob, ctrl, res.params)
    H, g = np.asarray(ev.H), np.asarray(ev.G_a)
    lam = np.linalg.lstsq(H.T, g, rcond=None)[0]
    assert np.max(np.abs(H.T @ lam - g)) < 1e-6

    # The terminal state reaches the Mars orbit also with an independent adaptive integrator.
    traj = jt.simulate(prob, ctrl, res.params, simulator=jt.Diffrax(rtol=1e-12, atol=1e-12))
    args = jt.problems.earth_mars.CONSTANTS
    want = np.array([0.0, args["rf"], np.sqrt(args["mu"] / args["rf"])])
    assert np.max(np.abs(np.asarray(traj.xf) - want)) < 1e-8


def test_ipopt_earth_mars_cases_4_and_5():
    """CasADi + IPOPT (`solve_ipopt`, the optional benchmark baseline) on the same compiled
    evaluation reaches the restricted optima of cases 4 and 5 found by SLSQP (3.32488832,
    3.32153651: benchmarks/reference_optima.md), feasible to 1e-10."""
    for case, tf_star in ((4, CASE4_TF), (5, 3.32153651)):
        prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
        res = solve_ipopt(prob, ctrl, a0)
        assert isinstance(res, SLSQPResult)
        assert res.success, res.message
        assert res.max_constraint_error <= 1e-10
        assert abs(res.tf - tf_star) < 1e-7
        assert res.iterations <= res.evaluations


@pytest.mark.parametrize("solve", [solve_slsqp, solve_ipopt])
def test_baselines_enforce_path_constraints(solve):
    """The speed limit x2 <= 1.2 on the min-energy double integrator (analytic energy 7.68,
    contained in PiecewiseLinear(4); unconstrained: 6 with peak speed 1.5) holds on the grid
    and the baselines find the analytic optimum."""
    prob = jt.problems.analytic.speed_limited_double_integrator(1.2)
    ctrl = jt.controls.PiecewiseLinear(4)
    res = solve(prob, ctrl, ctrl.initial_guess(1.2, 0.0, 0.0), simulator=jt.RK4(4))
    assert res.success, res.message
    assert res.max_path_constraint <= 1e-8
    assert res.max_constraint_error <= 1e-8
    assert abs(res.objective - jt.problems.analytic.speed_limited_energy(1.2)) < 1e-6
    free = solve_slsqp(
        jt.problems.analytic.min_energy_double_integrator(),
        ctrl,
        ctrl.initial_guess(1.2, 0.0, 0.0),
        simulator=jt.RK4(4),
    )
    assert free.max_path_constraint == -np.inf and abs(free.objective - 6.0) < 1e-6
