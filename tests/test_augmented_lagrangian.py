"""AugmentedLagrangian: analytic optima (with and without a path constraint), Earth-Mars case 4
against the SQP optimum, the custom-VJP gradient against finite differences, the parameter
box (projection and reduced gradient), control bounds against SLSQP, the Adam option, batch
(vmap) against single solves, and bad settings."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from helpers import energy_problem, perturbed_starts

import jaxtraj as jt
from jaxtraj._augmented_lagrangian import (
    AugmentedLagrangian,
    Metric,
    Multipliers,
    al_value,
    augmented_lagrangian,
    parameter_box,
)
from jaxtraj._sensitivity import evaluate_restricted

C = jt.controls
AL = AugmentedLagrangian()
CASE_4_TF = 3.32488832  # SLSQP optimum (benchmarks/reference_optima.md), = KalmanSQP's


def test_speed_limited_analytic_optimum():
    """x2 <= 1.2 on the min-energy double integrator: energy 7.68, contained exactly in
    PiecewiseLinear(4) (nodes 9.6, 0, 0, 0, -9.6); the limit is active on [1/4, 3/4]."""
    prob = jt.problems.analytic.speed_limited_double_integrator(1.2)
    ctrl = C.PiecewiseLinear(4)
    sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.2, 0.0, 0.0), AL, simulator=jt.RK4(4), max_steps=1000)
    assert sol.status == jt.Status.SUCCESS
    assert abs(float(sol.objective) - jt.problems.analytic.speed_limited_energy(1.2)) < 1e-7  # measured 7e-9
    assert float(sol.max_path_constraint) <= 1e-9  # measured 2.6e-10
    assert 0.25 - 1e-9 <= float(sol.max_path_time) <= 0.75 + 1e-9
    assert float(sol.max_constraint_error) <= 1e-9
    np.testing.assert_allclose(sol.params, [9.6, 0.0, 0.0, 0.0, -9.6, 1.0], atol=1e-6)
    # the history is filled up to `steps`; its outer_iteration detail never decreases
    n = int(sol.steps)
    assert np.all(np.isfinite(np.asarray(sol.history.objective[:n])))
    assert np.all(np.diff(np.asarray(sol.history.details["outer_iteration"][:n])) >= 0)
    assert int(sol.integrations) >= n


def test_min_energy_analytic_optimum():
    """u* = 6 - 12 t, energy 6 (tf = 1), no path constraint."""
    prob = jt.problems.analytic.min_energy_double_integrator(1.0)
    ctrl = C.PiecewiseLinear(3)
    sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.2, 0.0, 0.0), AL, simulator=jt.RK4(4))
    assert sol.status == jt.Status.SUCCESS
    assert sol.max_path_constraint is None
    assert abs(float(sol.objective) - 6.0) < 1e-7  # measured 6e-9
    np.testing.assert_allclose(sol.params[:-1], 6.0 - 12.0 * np.linspace(0, 1, 4), atol=1e-5)  # measured 2.3e-6
    assert float(sol.max_constraint_error) <= 1e-9


def test_earth_mars_case_4_matches_the_sqp_optimum():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    sol = jt.solve(prob, ctrl, a0, AL)
    assert sol.status == jt.Status.SUCCESS
    assert abs(float(sol.tf) - CASE_4_TF) < 2e-8  # measured 2.8e-9 (the reference has 8 decimals)
    assert float(sol.max_constraint_error) <= 1e-9
    assert int(sol.steps) < 200  # measured 61 steps, 130 integrations


def test_gradient_is_the_sensitivity_gradient():
    """`al_value`'s custom VJP (assembled from G_a, H, C_a) against central differences of its
    own values, in preconditioned coordinates, with active path terms."""
    prob = jt.problems.analytic.speed_limited_double_integrator(1.2)
    ctrl, sim = C.PiecewiseLinear(4), jt.RK4(4)
    a = jnp.array([9.0, 1.5, 0.5, -1.0, -9.0, 1.05])
    ev = jax.jit(lambda a: evaluate_restricted(prob, ctrl, a, sim))(a)
    assert float(jnp.max(ev.C)) > 0  # the speed limit is violated: the PHR term is active
    box = parameter_box(prob, ctrl)
    rng = np.random.default_rng(0)
    m = Multipliers(
        lam=jnp.asarray(rng.normal(size=3)),
        rho=jnp.full(3, 7.0),
        nu=jnp.asarray(np.abs(rng.normal(size=ev.C.size))),
        sigma=jnp.full(1, 3.0),
        e_scale=jnp.asarray(rng.uniform(0.5, 2.0, 3)),
        c_scale=jnp.full(1, 0.7),
    )
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    metric = Metric(center=a + 0.01, L=jnp.asarray(np.tril(Q @ np.diag([1, 2, 3, 4, 5, 6]) @ Q.T + 6 * np.eye(6))))
    z = metric.to_z(a)
    vg = jax.jit(jax.value_and_grad(al_value(prob, ctrl, sim, box, m, metric)))
    value, grad = vg(z)
    assert np.isclose(float(value), float(augmented_lagrangian(ev, m)[0]), rtol=1e-13)
    eps = 1e-5
    fd = np.array([(vg(z + eps * e)[0] - vg(z - eps * e)[0]) / (2 * eps) for e in np.eye(6)])
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


def test_parameter_box_projection_and_reduced_gradient():
    prob = jt.problems.earth_mars.problem()
    # free switch times: kept ordered with gaps >= min_duration; levels unbounded
    ctrl = C.PiecewiseConstant(3)
    box = parameter_box(prob, ctrl, 1e-3)
    a = jnp.array([5.0, 2.0, 1.0, 1.5, -7.0, 3.0])  # t_1 = 2 > t_2 = 1.5
    p = np.asarray(box.project(a))
    t = p[list(ctrl.time_indices)]
    assert np.all(np.diff(np.concatenate([[0.0], t])) >= 1e-3 - 1e-15)
    np.testing.assert_array_equal(p[[0, 2, 4]], [5.0, 1.0, -7.0])
    np.testing.assert_array_equal(box.project(jnp.asarray(p)), p)  # idempotent
    # at a collapsed segment a gradient pushing it shut is zeroed on the duration, the other
    # duration components survive: d/dh = reverse cumsum of d/dt
    g = jnp.array([0.0, 1.0, 0.0, -3.0, 0.0, 0.5])  # d/dh = (-1.5, -2.5, 0.5)
    q = jnp.array([0.0, 1.0, 0.0, 1.0 + 1e-3, 0.0, 3.0])  # h_2 = 1e-3 (binding when d/dh_2 > 0)
    np.testing.assert_allclose(box.reduce(q, g), g, atol=1e-15)  # d/dh_2 < 0: opening, free
    g2 = jnp.array([0.0, -1.0, 0.0, 3.0, 0.0, 0.5])  # d/dh = (2.5, 3.5, 0.5): shut h_2 -> zeroed
    r = np.asarray(box.reduce(q, g2))
    g_h = np.cumsum(r[[1, 3, 5]][::-1])[::-1]
    np.testing.assert_allclose(g_h, [2.5, 0.0, 0.5], atol=1e-15)
    # spline coefficients within both the spline's and the problem's bounds, durations >= min
    spline = C.SaturatedSpline(2, 1, -1.0, 1.0)
    bounded = jt.Problem(
        prob.dynamics,
        prob.x0,
        prob.terminal,
        prob.constraint_names,
        args=prob.args,
        control_lower=-0.5,
        control_upper=2.0,
    )
    box = parameter_box(bounded, spline, 1e-4)
    p = np.asarray(box.project(jnp.array([-1.0, 2.0, -3.0, 0.2, 3.0])))
    np.testing.assert_array_equal(p, [1e-4, 2.0, -0.5, 0.2, 1.0])
    # parabolic arcs: end values bounded, slopes free; fixed tf kept >= K min_duration
    para = C.PiecewiseParabolic(2, free_times=False)
    box = parameter_box(bounded, para, 1e-4)
    p = np.asarray(box.project(jnp.array([-9.0, -9.0, 9.0, 9.0, 9.0, -9.0, -1.0])))
    np.testing.assert_array_equal(p, [-0.5, -9.0, 2.0, 2.0, 9.0, -0.5, 2e-4])


def test_control_bounds_against_slsqp():
    """|u| <= 5 on the min-energy double integrator (the free optimum peaks at 6; |u| <= 4
    would need bang-bang): the bound is active; the result equals SLSQP with the same bounds
    on the same restricted problem; from the start and its round-off perturbations (before
    the metric's tolerance band at the bounds, `BOUND_TOLERANCE`, a node 1.6e-11 inside its
    bound made every step fail from 3 of 9 such starts on an AVX-without-AVX2 CPU:
    MAX_ITERATIONS)."""
    prob = energy_problem(control_lower=-5.0, control_upper=5.0)
    ctrl, sim = C.PiecewiseLinear(4), jt.RK4(4)
    a0 = ctrl.initial_guess(1.2, 0.0, 0.0)
    sols = [jt.solve(prob, ctrl, start, AL, simulator=sim) for start in perturbed_starts(a0, absolute=True)]
    assert [jt.status_name(s.status) for s in sols] == ["SUCCESS"] * len(sols)
    sol = sols[0]
    assert float(jnp.max(jnp.abs(sol.params[:-1]))) <= 5.0
    ev = jax.jit(lambda a: evaluate_restricted(prob, ctrl, a, sim))
    ref = scipy.optimize.minimize(
        lambda a: float(ev(a).G),
        np.asarray(a0),
        jac=lambda a: np.asarray(ev(a).G_a),
        method="SLSQP",
        bounds=[(-5.0, 5.0)] * 5 + [(0.1, 2.0)],
        constraints={"type": "eq", "fun": lambda a: np.asarray(ev(a).E), "jac": lambda a: np.asarray(ev(a).H)},
        options={"ftol": 1e-14, "maxiter": 500},
    )
    assert ref.success
    assert ref.fun > 6.0 + 1e-3  # the bound costs energy
    for sol in sols:
        assert abs(float(sol.objective) - ref.fun) < 1e-7
        np.testing.assert_allclose(sol.params, ref.x, atol=1e-4)


def test_adam_option():
    prob = jt.problems.analytic.min_energy_double_integrator(1.0)
    ctrl = C.PiecewiseLinear(3)
    solver = AugmentedLagrangian(inner="adam", learning_rate=0.01, ctol=1e-6, gtol=1e-4)
    sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.2, 0.0, 0.0), solver, simulator=jt.RK4(4), max_steps=5000)
    assert sol.status == jt.Status.SUCCESS  # measured 1901 steps
    assert abs(float(sol.objective) - 6.0) < 1e-4
    assert int(sol.integrations) == int(sol.steps) + 1  # one integration per Adam step


def test_batch_matches_single_solves_and_isolates_a_bad_start():
    prob = jt.problems.analytic.speed_limited_double_integrator(1.2)
    ctrl, sim = C.PiecewiseLinear(4), jt.RK4(4)
    a0 = ctrl.initial_guess(1.2, 0.0, 0.0)
    a1 = a0.at[:-1].set(jnp.array([2.0, 1.0, 0.0, -1.0, -2.0]))
    starts = jnp.stack([a0, a0.at[0].set(jnp.nan), a1])
    sols = jt.solve_batch(prob, ctrl, starts, AL, simulator=sim, max_steps=1000)
    np.testing.assert_array_equal(sols.status == jt.Status.SUCCESS, [True, False, True])
    np.testing.assert_array_equal(sols.status == jt.Status.NONFINITE, [False, True, False])
    for i, a in ((0, a0), (2, a1)):
        single = jt.solve(prob, ctrl, a, AL, simulator=sim, max_steps=1000)
        np.testing.assert_allclose(sols.params[i], single.params, rtol=1e-9, atol=1e-9)
        assert int(sols.steps[i]) == int(single.steps)
        assert abs(float(sols.objective[i]) - 7.68) < 1e-7


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"inner": "sgd"}, "inner"),
        ({"method": "exact"}, "method"),
        ({"ctol": 0.0}, "ctol"),
        ({"gtol": -1.0}, "gtol"),
        ({"max_inner": 0}, "max_inner"),
        ({"max_outer": 2.5}, "max_outer"),
        ({"penalty_init": -1.0}, "penalty_init"),
        ({"penalty_growth": 1.0}, "penalty_growth"),
        ({"feasibility_ratio": 1.5}, "feasibility_ratio"),
        ({"inner_tol_shrink": 0.0}, "inner_tol_shrink"),
        ({"learning_rate": 0.0}, "learning_rate"),
        ({"memory_size": 0}, "memory_size"),
        ({"min_duration": 0.0}, "min_duration"),
        ({"max_step": -1.0}, "max_step"),
        ({"curvature": 0.0}, "curvature"),
        ({"precondition": "yes"}, "precondition"),
    ],
)
def test_bad_settings(kwargs, field):
    with pytest.raises(ValueError, match=f"AugmentedLagrangian: .*`{field}`"):
        AugmentedLagrangian(**kwargs)


def test_path_problems_need_forward_sensitivities():
    prob = jt.problems.analytic.speed_limited_double_integrator(1.2)
    ctrl = C.PiecewiseLinear(4)
    with pytest.raises(ValueError, match="method='forward'"):
        jt.solve(prob, ctrl, ctrl.initial_guess(1.0, 0.0, 0.0), AugmentedLagrangian(method="unit"), simulator=jt.RK4(4))
