"""dx(tf)/da three ways: forward-mode autodiff, the unit-solution method of seed 000
appendix A, and central finite differences."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ALL_CASES, counting_problem, family_examples, moved_start, rel_err

import jaxtraj as jt
from jaxtraj._sensitivity import affine_segment_basis, segment_hessian
from jaxtraj._simulate import final_state

# The unit-solution method differentiates the ODE, forward mode the RK4 map; they differ by
# the O(h^4) derivative of the step with respect to the knots (16x smaller per halving of h,
# seen in development). 200 steps per segment put that below 1e-9.
SIM = jt.RK4(200)
FAMILIES = family_examples()


def _ids(examples):
    return [repr(c) for _, c, _ in examples]


@pytest.mark.slow
@pytest.mark.parametrize("prob, ctrl, a", FAMILIES, ids=_ids(FAMILIES))
def test_families_forward_unit_fd_agree(prob, ctrl, a):
    xf_f, J_f = jt.sensitivities(prob, ctrl, a, "forward", simulator=SIM)
    xf_u, J_u = jt.sensitivities(prob, ctrl, a, "unit", simulator=SIM)
    _xf_d, J_d = jt.sensitivities(prob, ctrl, a, "fd", simulator=SIM)
    assert J_f.shape == (3, ctrl.num_params)
    assert rel_err(xf_u, xf_f) < 1e-13
    assert rel_err(J_u, J_f) < 1e-9
    assert rel_err(J_d, J_f) < 1e-6
    # every column matters (no parameter silently ignored); saturated splines excepted
    if not isinstance(ctrl, jt.controls.SaturatedSpline):
        assert np.all(np.max(np.abs(np.asarray(J_f)), axis=0) > 1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("case", ALL_CASES)
def test_thesis_cases_forward_unit_fd_agree(case):
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
    _, J_f = jt.sensitivities(prob, ctrl, a0, "forward", simulator=SIM)
    _, J_u = jt.sensitivities(prob, ctrl, a0, "unit", simulator=SIM)
    _, J_d = jt.sensitivities(prob, ctrl, a0, "fd", simulator=SIM)
    assert rel_err(J_u, J_f) < 1e-9
    assert rel_err(J_d, J_f) < 1e-6


def test_unit_solution_converges_to_forward_at_fourth_order():
    """The forward/unit gap is the O(h^4) step-size derivative, not a modelling error."""
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(3)
    gaps = []
    for n in (50, 100, 200):
        sim = jt.RK4(n)
        gaps.append(
            rel_err(
                jt.sensitivities(prob, ctrl, a0, "unit", simulator=sim)[1],
                jt.sensitivities(prob, ctrl, a0, "forward", simulator=sim)[1],
            )
        )
    ratios = np.array(gaps[:-1]) / np.array(gaps[1:])
    assert np.all((ratios > 12) & (ratios < 20)), gaps


def test_saturated_columns_vanish():
    """du/da_j = 0 where the control saturates: a coefficient whose whole support is
    clipped has a zero sensitivity column, by every method."""
    prob = jt.problems.earth_mars.problem()
    ctrl = jt.controls.SaturatedSpline(3, 1, 0.0, 1.0)
    a = jnp.array([1.1, 1.1, 1.2, 5.0, 6.0, 0.5, 0.7])  # c_0 = 5, c_1 = 6 -> clipped on segment 0
    for method in ("forward", "unit", "fd"):
        J = jt.sensitivities(prob, ctrl, a, method, simulator=jt.RK4(50))[1]
        assert float(jnp.max(jnp.abs(J[:, 3]))) < 1e-12, method
        assert float(jnp.max(jnp.abs(J[:, 6]))) > 1e-3, method


def test_evaluate_chain_rule_matches_fd_of_constraints():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(1)
    ev = jt.evaluate(prob, ctrl, a0, simulator=SIM)
    assert ev.status == jt.Status.SUCCESS
    eps = 1e-6

    def E_of(a):
        return jt.evaluate(prob, ctrl, a, simulator=SIM).E

    H_fd = np.stack(
        [(E_of(a0.at[j].add(eps)) - E_of(a0.at[j].add(-eps))) / (2 * eps) for j in range(ctrl.num_params)],
        axis=1,
    )
    assert rel_err(ev.H, H_fd) < 1e-6
    # minimum time: G = tf = last parameter
    assert float(ev.G) == float(a0[-1])
    np.testing.assert_array_equal(np.asarray(ev.G_a), np.eye(ctrl.num_params)[-1])


def test_jit_and_vmap_match_single_calls():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    a0s = a0[None, :] + 0.01 * jax.random.normal(jax.random.PRNGKey(0), (5, ctrl.num_params))
    for method in ("forward", "unit"):
        fn = lambda a, method=method: jt.sensitivities(prob, ctrl, a, method)
        batched = jax.jit(jax.vmap(fn))(a0s)
        for i in range(5):
            single = fn(a0s[i])
            np.testing.assert_allclose(batched[0][i], single[0], rtol=1e-13, atol=1e-15)
            np.testing.assert_allclose(batched[1][i], single[1], rtol=1e-11, atol=1e-14)


def test_no_recompilation_when_values_change():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(5)
    prob, counter = counting_problem(prob)
    jt.evaluate(prob, ctrl, a0)
    jt.simulate(prob, ctrl, a0)
    traced = counter["traces"]
    assert traced > 0
    for s in range(3):
        jt.evaluate(prob, ctrl, a0 + 0.01 * (s + 1))
        jt.simulate(prob, ctrl, a0 - 0.01 * (s + 1))
    assert counter["traces"] == traced  # new values, same compiled code


@pytest.mark.parametrize("case", [1, 5])
def test_forward_equals_naive_jacfwd_of_the_simulation(case):
    """The "forward" path is jacfwd through `final_state`; check it against jacfwd of the
    dense `simulate` (a different code path through the same integrator). Case 5's control is
    affine with rank-3 segment rows, so it takes the reduced-tangent path."""
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
    assert (affine_segment_basis(ctrl, a0) is None) == (case == 1)
    sim = jt.RK4(40)
    J = jt.sensitivities(prob, ctrl, a0, "forward", simulator=sim)[1]
    J_dense = jax.jacfwd(lambda a: jt.simulate(prob, ctrl, a, simulator=sim).x[-1])(a0)
    np.testing.assert_allclose(J, J_dense, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize(
    "ctrl",
    [
        jt.controls.FixedFinalTime(jt.controls.PiecewiseLinear(3), 2.0),
        jt.controls.FreeInitialState(jt.controls.PiecewiseLinear(3), (1,), [0.5]),
        jt.controls.SaturatedSpline(3, 2, -1.0, 1.0, free_durations=False),
        jt.controls.FixedFinalTime(jt.controls.SaturatedSpline(3, 1, -1.0, 1.0, free_durations=False), 2.0),
    ],
    ids=repr,
)
def test_affine_basis_inside_a_jit_equals_the_basis_outside(ctrl):
    """A control's arrays (a fixed final time, free start values, spline limits) are traced
    inside a jit; the segment Jacobian does not use them, so the reduced-tangent basis is
    found there too, from one compiled program (not op by op, which fails on them)."""
    a = jnp.linspace(0.2, 0.9, ctrl.num_params)
    outside = affine_segment_basis(ctrl, a)
    inside = eqx.filter_jit(affine_segment_basis)(ctrl, a)
    assert outside is not None and inside is not None
    np.testing.assert_array_equal(np.asarray(inside), np.asarray(outside))


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["case-4", "hypersensitive", "brachistochrone", "orbit-raising", "free-initial-state", "design-parameter"]
)
def test_segment_hessian_matches_forward_over_reverse(name):
    """The Hessian of a terminal function by segments (chained segment Jacobians, costates,
    local Hessians under vmap) against forward over reverse autodiff of the whole RK4
    simulation: free and fixed tf, several controls, a free initial state, a design
    parameter, time-varying dynamics."""
    prob, ctrl, a0 = moved_start(name, 7)
    sim = jt.RK4(5)
    w = jnp.asarray(np.random.default_rng(8).normal(size=prob.num_constraints))

    def terminal(tf, xf):
        return prob.objective(tf, xf, prob.args) + w @ prob.terminal(tf, xf, prob.args) + 0.3 * tf**2

    basis = affine_segment_basis(ctrl, a0)
    assert basis is not None
    W = jax.jit(lambda a: segment_hessian(prob, ctrl, a, sim, terminal, basis))(a0)
    ref = jax.jit(jax.hessian(lambda a: terminal(ctrl.tf(a), final_state(prob, ctrl, a, sim)[0])))(a0)
    assert float(jnp.abs(ref).max()) > 1e-3
    np.testing.assert_allclose(W, ref, rtol=1e-10, atol=1e-10 * float(jnp.abs(ref).max()))
