"""KalmanSearch (the thesis's method): analytic optimum, restricted optima of Earth-Mars
cases 4 and 5 checked against scipy SLSQP on the same simulate/Jacobian, jit/vmap
consistency, no recompilation, failure statuses."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ROUNDOFF_EPS, counting_problem, perturbed_starts

import jaxtraj as jt
from jaxtraj.baselines import solve_slsqp


def test_min_energy_double_integrator_analytic_optimum():
    """u* = 6 - 12 t, energy 6 (tf = 1); RK4 is exact on this polynomial system. One segment
    holds u* exactly; gtol = 1e-9 is reached from the start and its round-off perturbations
    (measured 15-17 steps). With three segments a stationarity 1e-4 x tighter than the
    default is not: the first-order search STALLED at 1e-6..1e-5 from 4 of 9 such starts on
    an AVX-without-AVX2 CPU (the class docstring); the default tolerance's guarantee there
    is `test_solution.py`'s distance bound."""
    prob = jt.problems.analytic.min_energy_double_integrator(1.0)
    ctrl = jt.controls.PiecewiseLinear(1)
    solver = jt.KalmanSearch(gtol=1e-9)
    a0 = ctrl.initial_guess(1.2, 0.0, 0.0)
    for start in perturbed_starts(a0, absolute=True):
        sol = jt.solve(prob, ctrl, start, solver, simulator=jt.RK4(4))
        assert sol.status == jt.Status.SUCCESS
        assert abs(float(sol.objective) - 6.0) < 1e-8
        assert float(sol.max_constraint_error) < 1e-8
        assert float(sol.projected_gradient) < 1e-7
        np.testing.assert_allclose(sol.params[:-1], [6.0, -6.0], atol=1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("case", [4, 5])
def test_thesis_cases_reach_the_restricted_optimum(case):
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
    sol = jt.solve(prob, ctrl, a0, jt.KalmanSearch())
    assert sol.status == jt.Status.SUCCESS
    assert float(sol.max_constraint_error) <= 1e-8
    ref = solve_slsqp(prob, ctrl, a0)  # independent optimizer, same simulate/Jacobian
    assert ref.max_constraint_error <= 1e-10
    assert abs(float(sol.tf) - ref.tf) < 1e-6, (float(sol.tf), ref.tf)
    # and not worse than the thesis's published value (which stopped at e_a = 1e-4)
    assert float(sol.tf) < jt.problems.earth_mars.PUBLISHED[case][0]


def test_vmap_over_starts_matches_single_solves():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    rng = np.random.default_rng(0)
    starts = np.asarray(a0)[None, :] + 0.05 * rng.standard_normal((8, ctrl.num_params))
    starts[:, -1] = 3.4 + 0.1 * rng.standard_normal(8)
    batch = jt.solve_batch(prob, ctrl, starts, jt.KalmanSearch(), max_steps=600)
    assert batch.params.shape == (8, ctrl.num_params)
    for i in range(8):
        single = jt.solve(prob, ctrl, starts[i], jt.KalmanSearch(), max_steps=600)
        # Batched XLA kernels round differently in the last bits, and accept/reject
        # decisions can then differ near convergence: equal to the solver's tolerance.
        assert bool((batch.status == jt.Status.SUCCESS)[i]) and single.status == jt.Status.SUCCESS
        assert abs(float(batch.tf[i]) - float(single.tf)) < 1e-9
        np.testing.assert_allclose(batch.params[i], single.params, atol=1e-5)


def test_bad_start_in_a_batch_does_not_spoil_the_others():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    starts = jnp.stack([a0, a0.at[2].set(jnp.nan), a0 + 0.01])
    sols = jt.solve_batch(prob, ctrl, starts, jt.KalmanSearch(), max_steps=600)
    np.testing.assert_array_equal(sols.status == jt.Status.NONFINITE, [False, True, False])
    np.testing.assert_array_equal(sols.status == jt.Status.SUCCESS, [True, False, True])
    assert abs(float(sols.tf[0]) - float(sols.tf[2])) < 1e-6


def test_solve_compiles_once_for_new_starting_values():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    prob, counter = counting_problem(prob)
    jt.solve(prob, ctrl, a0, max_steps=50)
    traced = counter["traces"]
    assert traced > 0
    jt.solve(prob, ctrl, a0 + 0.02, max_steps=50)
    jt.solve(prob, ctrl, a0 - 0.02, max_steps=50)
    assert counter["traces"] == traced


def test_iteration_limit_is_a_status_and_history_is_recorded():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(5)
    sol = jt.solve(prob, ctrl, a0, jt.KalmanSearch(), max_steps=5)
    assert sol.status == jt.Status.MAX_ITERATIONS
    assert int(sol.steps) == 5 and int(sol.integrations) == 5
    h = sol.history
    assert h.objective.shape == (5,)
    assert np.all(np.isfinite(np.asarray(h.objective)))
    # the first step evaluates the start (length 0); then the recorded constraint error of
    # accepted capture steps decreases
    assert bool(h.accepted[0]) and float(h.step_norm[0]) == 0.0
    assert float(h.max_constraint_error[0]) == pytest.approx(0.318669, abs=1e-6)
    acc = np.asarray(h.accepted) & (np.asarray(h.details["phase"]) == 0)
    acc[0] = False
    errs = np.concatenate([[0.318669], np.asarray(h.max_constraint_error)[acc]])
    assert np.all(np.diff(errs) < 0)


def test_bad_solver_settings():
    with pytest.raises(ValueError, match="beta_p"):
        jt.KalmanSearch(beta_p=0.5)
    with pytest.raises(ValueError, match="e_a_start"):
        jt.KalmanSearch(e_a=1e-3, e_a_start=1e-4)
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    with pytest.raises(ValueError, match="`solver` must be"):
        jt.solve(prob, ctrl, a0, solver="kalman")
    with pytest.raises(ValueError, match=r"`max_steps` must be an int >= 1"):
        jt.solve(prob, ctrl, a0, max_steps=0)


# Restricted optima of the seven parametrizations computed independently with scipy SLSQP
# from 8-20 starts each (benchmarks/reference_optima.md; RK4(100), max|E| <= 1e-10).
SLSQP_OPTIMA = {1: 3.32009723, 2: 3.32075166, 3: 3.32079812, 4: 3.32488832, 5: 3.32153651, 6: 3.36688418, 7: 3.33474663}


@pytest.mark.slow
@pytest.mark.parametrize("case", range(1, 8))
def test_all_seven_published_cases_converge_to_the_restricted_optimum(case):
    """The published start and tuning, and the start perturbed by round-off-sized relative
    changes (1e-12, 1e-10: another CPU's last bits): SUCCESS every time, with what SUCCESS
    guarantees (max |E| <= e_a, projected gradient <= max(gtol, e_a) (1 + |G|)), at the SLSQP
    optimum (measured: a few 1e-6; spread between the starts <= 2e-14). Before `gap_keep`,
    case 7 closed a level to zero length and STALLED from 1 of 11 such starts
    (benchmarks/roundoff.py)."""
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
    solver = jt.problems.earth_mars.thesis_solver(case)
    sols = jt.solve_batch(prob, ctrl, perturbed_starts(a0), solver, progress=False, history=False)
    assert jt.status_name(sols.status).tolist() == ["SUCCESS"] * len(ROUNDOFF_EPS)
    assert np.all(np.asarray(sols.max_constraint_error) <= solver.e_a)
    assert np.all(np.asarray(sols.projected_gradient) <= solver.gtol * (1.0 + np.abs(np.asarray(sols.objective))))
    # issue target: 1e-3 (5e-3 for the many-minima cases 6, 7); reached: a few 1e-6
    assert np.all(np.abs(np.asarray(sols.tf) - SLSQP_OPTIMA[case]) < 1e-5)


def test_nonfinite_candidate_is_a_rejected_step_not_a_nan_result():
    """x' = x^2 + u escapes to infinity at t = 1: a candidate with tf = 5 integrates to
    inf/NaN; the step must be rejected and shrunk, the current point left untouched."""
    prob = jt.Problem(lambda t, x, u, args: x**2 + u, [1.0], lambda tf, xf, args: xf - 1.5, ("x",))
    ctrl = jt.controls.PiecewiseConstant(1)
    solver, sim = jt.KalmanSearch(), jt.RK4(20)
    a = jnp.array([0.0, 0.2])
    step = eqx.filter_jit(lambda s: solver.step(prob, ctrl, sim, s))  # one program (eagerly: op by op)
    state = step(solver.init(prob, ctrl, a, sim, 10))  # the start
    assert bool(state.history.accepted[0]) and not bool(state.done)
    state = eqx.tree_at(lambda s: (s.da_pending, s.has_pending), state, (jnp.array([0.0, 4.8]), jnp.array(True)))
    new = step(state)
    assert not bool(new.history.accepted[1]) and not bool(new.done)
    np.testing.assert_array_equal(new.a, a)
    assert np.all(np.isfinite(np.asarray(new.ev.E))) and np.all(np.isfinite(np.asarray(new.ev.H)))
    np.testing.assert_allclose(new.da_pending, 0.25 * np.array([0.0, 4.8]))  # shrunk, retried next
    assert bool(new.has_pending) and float(new.rho) < float(state.rho)


def test_path_constraint_analytic_optimum():
    """Speed limit x2 <= 1.2 on the min-energy double integrator (analytic energy 7.68, contained
    in PiecewiseLinear(4); unconstrained 6 at peak speed 1.5): the thesis's method with the path
    points observed at their boundary, the appendix-C way, reaches it with SUCCESS (measured
    7.6799999998 in 18 steps, max C 7e-13 on the grid)."""
    prob = jt.problems.analytic.speed_limited_double_integrator(1.2)
    ctrl = jt.controls.PiecewiseLinear(4)
    sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.2, 0.0, 0.0), jt.KalmanSearch(), simulator=jt.RK4(4), max_steps=200)
    assert sol.status == jt.Status.SUCCESS
    assert abs(float(sol.objective) - jt.problems.analytic.speed_limited_energy(1.2)) < 1e-8
    assert float(sol.max_path_constraint) <= 1e-10 and float(sol.max_constraint_error) <= 1e-8
    assert 0.25 - 1e-9 <= float(sol.max_path_time) <= 0.75 + 1e-9  # on the coast arc
    np.testing.assert_allclose(sol.params, [9.6, 0.0, 0.0, 0.0, -9.6, 1.0], atol=1e-6)
