"""Simulation: exactness on polynomials, RK4 order, RK4 vs diffrax, dense output, transforms."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt


def test_double_integrator_exact_with_piecewise_linear_control():
    """x'' = u with u piecewise linear: x(tf) in closed form; RK4 is exact on cubics."""
    prob = jt.problems.analytic.double_integrator()
    ctrl = jt.controls.PiecewiseLinear(2, continuous=False, free_times=True)
    a = jnp.array([1.0, 3.0, 0.7, -2.0, 0.5, 1.9])
    xf = jt.simulate(prob, ctrl, a, simulator=jt.RK4(3)).xf
    # segment 1: u = 1 + 2t/0.7 on [0, 0.7]; segment 2: u = -2 + 2.5 s/1.2, s = t - 0.7 on [0, 1.2]
    v1 = 0.7 + 0.7  # int u = 0.7 + (2/0.7) 0.7^2/2
    x1 = 0.7**2 / 2 + (2 / 0.7) * 0.7**3 / 6
    h = 1.2
    v2 = v1 - 2 * h + 2.5 / h * h**2 / 2
    x2 = x1 + v1 * h - 2 * h**2 / 2 + (2.5 / h) * h**3 / 6
    np.testing.assert_allclose(xf, [x2, v2], rtol=1e-14)


def _earth_mars_xf(case, sim):
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
    return np.asarray(jt.simulate(prob, ctrl, a0, simulator=sim).xf)


@pytest.mark.parametrize("case", [1, 4, 6])
def test_rk4_is_fourth_order(case):
    ref = _earth_mars_xf(case, jt.RK4(800))
    errs = [np.max(np.abs(_earth_mars_xf(case, jt.RK4(n)) - ref)) for n in (10, 20, 40)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all((orders > 3.7) & (orders < 4.4)), (errs, orders)


@pytest.mark.parametrize("case", [3, 5, 7])
def test_rk4_agrees_with_diffrax_tsit5(case):
    tsit = _earth_mars_xf(case, jt.Diffrax(diffrax.Tsit5(), rtol=1e-12, atol=1e-12))
    rk4 = _earth_mars_xf(case, jt.RK4(400))
    np.testing.assert_allclose(rk4, tsit, rtol=0, atol=1e-8)


def test_diffrax_failure_is_a_status_not_an_exception():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    traj = jt.simulate(prob, ctrl, a0, simulator=jt.Diffrax(rtol=1e-12, atol=1e-12, max_steps=3))
    assert traj.status == jt.Status.SIMULATION_FAILED


def test_blow_up_is_reported_as_nonfinite():
    """x' = x^2 + u from x(0) = 1 escapes to infinity at t = 1: Status.NONFINITE, no exception."""
    prob = jt.Problem(lambda t, x, u, args: x**2 + u, [1.0], lambda tf, xf, args: xf, ("x",), name="blow-up")
    ctrl = jt.controls.PiecewiseConstant(1)
    a = jnp.array([0.0, 5.0])
    assert jt.simulate(prob, ctrl, a, simulator=jt.RK4(50)).status == jt.Status.NONFINITE
    assert jt.evaluate(prob, ctrl, a, simulator=jt.RK4(50)).status == jt.Status.NONFINITE
    assert jt.evaluate(prob, ctrl, jnp.array([0.0, 0.5]), simulator=jt.RK4(50)).status == jt.Status.SUCCESS


def test_dense_trajectory_shapes_and_consistency():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(1)
    traj = jt.simulate(prob, ctrl, a0, simulator=jt.RK4(30))
    K = ctrl.num_segments
    assert traj.t.shape == (K * 31,) and traj.x.shape == (K * 31, 3) and traj.u.shape == (K * 31, 1)
    assert traj.t.dtype == traj.x.dtype == jnp.float64
    np.testing.assert_allclose(traj.x[-1], traj.xf)
    np.testing.assert_allclose(traj.x[0], prob.x0)
    assert float(traj.t[-1]) == pytest.approx(3.4)
    assert np.all(np.diff(np.asarray(traj.t)) >= 0)
    # inside segments the dense u equals the control evaluated at t
    inner = np.asarray([i % 31 not in (0, 30) for i in range(K * 31)])
    np.testing.assert_allclose(traj.u[inner, 0], ctrl(a0, traj.t[inner])[:, 0], atol=1e-12)


def test_simulate_jit_vmap_match_single_calls():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(2)
    a0s = a0[None, :] + 0.01 * jax.random.normal(jax.random.PRNGKey(1), (4, ctrl.num_params))
    batched = jax.jit(jax.vmap(lambda a: jt.simulate(prob, ctrl, a).xf))(a0s)
    for i in range(4):
        np.testing.assert_allclose(batched[i], jt.simulate(prob, ctrl, a0s[i]).xf, rtol=1e-14)


def test_a_collapsed_final_time_simulates_but_starts_nothing():
    """Issue 51's fourth audit: a solve from tf = 1e-300 ends STALLED at tf = 0 (every knot
    gap at its bound h_k >= 0); `jt.simulate` refused that result, so `jaxtraj solve` died
    with a traceback before writing it. It simulates (time stands still at x0); as
    a start, tf = 0 is still refused."""
    prob = jt.problems.analytic.double_integrator()
    ctrl = jt.controls.PiecewiseLinear(3)
    a = jnp.asarray([1.0, 0.5, 0.0, -1.0, 0.0])
    traj = jt.simulate(prob, ctrl, a)
    assert traj.status == jt.Status.SUCCESS
    assert np.all(np.asarray(traj.t) == 0) and np.all(np.asarray(traj.x) == np.asarray(prob.x0))
    with pytest.raises(ValueError, match=r"the final time tf must be > 0"):
        jt.solve(prob, ctrl, a)
    with pytest.raises(ValueError, match=r"the final time tf must be > 0"):
        jt.simulate(prob, ctrl, a.at[-1].set(-1e-3))
