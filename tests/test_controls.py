"""Control families: layouts, initial guesses, evaluation, the seed-003 spline basis."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.controls import spline_kernel

C = jt.controls
LINE_FAMILIES = [
    C.PiecewiseLinear(5),
    C.PiecewiseLinear(4, continuous=True, free_times=True),
    C.PiecewiseLinear(3, continuous=False, free_times=True),
    C.PiecewiseLinear(3, continuous=False, free_times=False),
    C.PiecewiseParabolic(2),
    C.PiecewiseParabolic(3, free_times=False),
    C.SaturatedSpline(4, 1, -10.0, 10.0),
    C.SaturatedSpline(4, 1, -10.0, 10.0, free_durations=False),
]


@pytest.mark.parametrize("ctrl", LINE_FAMILIES, ids=repr)
def test_initial_guess_is_the_straight_line(ctrl):
    a = ctrl.initial_guess(3.4, 0.0, 1.5 * np.pi)
    assert a.shape == (ctrl.num_params,) and a.dtype == jnp.float64
    t = jnp.linspace(0.0, 3.4, 57)
    np.testing.assert_allclose(ctrl(a, t)[:, 0], 1.5 * np.pi * t / 3.4, atol=1e-13)
    np.testing.assert_allclose(ctrl.knots(a), 3.4 * np.arange(ctrl.num_segments + 1) / ctrl.num_segments, atol=1e-15)
    assert float(ctrl.tf(a)) == pytest.approx(3.4, abs=1e-14)
    times = np.asarray(a)[list(ctrl.time_indices)]
    assert np.all((times > 0) & (times <= 3.4 + 1e-14))


def test_piecewise_constant_guess_uses_midpoints():
    ctrl = C.PiecewiseConstant(4)
    a = ctrl.initial_guess(4.0, 0.0, 4.0)
    np.testing.assert_allclose(a, [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0])
    np.testing.assert_allclose(ctrl(a, jnp.array([0.2, 1.0, 3.99, 4.0]))[:, 0], [0.5, 1.5, 3.5, 3.5])


def test_thesis_layouts_match_the_tables():
    # Table 5.1 (test 1): per segment [u_start, u_end, t_end]; Table 5.7 (test 4): nodes + tf.
    _, c1, a1 = jt.problems.earth_mars.thesis_case(1)
    assert c1.num_params == 12 and c1.time_indices == (2, 5, 8, 11)
    np.testing.assert_allclose(c1.knots(a1), [0.0, 0.85, 1.7, 2.55, 3.4])
    _, c4, _a4 = jt.problems.earth_mars.thesis_case(4)
    assert c4.num_params == 7 and c4.time_indices == (6,)
    _, c3, a3 = jt.problems.earth_mars.thesis_case(3)
    assert c3.num_params == 8 and c3.time_indices == (3, 7)
    _, c7, _a7 = jt.problems.earth_mars.thesis_case(7)
    assert c7.num_params == 10 and c7.time_indices == (1, 3, 5, 7, 9)
    # the published test-3 start is the straight line u = 1.5 pi t / 3.4 (slope parameter 1.386)
    t = jnp.linspace(0, 3.4, 21)
    np.testing.assert_allclose(c3(a3, t)[:, 0], 1.5 * np.pi * t / 3.4, atol=2e-4)


def test_discontinuous_linear_jumps_at_nodes():
    ctrl = C.PiecewiseLinear(2, continuous=False, free_times=True)
    a = jnp.array([0.0, 1.0, 1.0, 5.0, 7.0, 3.0])
    u = ctrl(a, jnp.array([0.5, 1.0 - 1e-12, 1.0, 2.0, 3.0]))[:, 0]
    np.testing.assert_allclose(u, [0.5, 1.0, 5.0, 6.0, 7.0], atol=1e-11)


def test_parabola_interpolates_its_end_values_and_slope():
    ctrl = C.PiecewiseParabolic(1)
    a = jnp.array([1.0, -2.0, 3.0, 2.0])  # u(0)=1, u'(0)=-2, u(2)=3
    u = lambda t: ctrl(a, t)[0]
    assert float(u(0.0)) == pytest.approx(1.0)
    assert float(u(2.0)) == pytest.approx(3.0)
    assert float(jax.grad(u)(0.0)) == pytest.approx(-2.0)
    # exact parabola: u = 1 - 2t + c t^2 with 1 - 4 + 4c = 3 -> c = 1.5
    assert float(u(0.7)) == pytest.approx(1 - 1.4 + 1.5 * 0.49)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spline_matches_the_seed_global_formula(degree):
    """Seed 003: g(tau) = sum_i c_i Sp*(tau P - i) on the global tau in [0, 1]."""
    P = 5
    ctrl = C.SaturatedSpline(P, degree, -100.0, 100.0)
    rng = np.random.default_rng(degree)
    h = rng.uniform(0.5, 1.5, P)
    c = rng.normal(size=P + 1)
    a = jnp.asarray(np.concatenate([h, c]))
    knots = np.concatenate([[0.0], np.cumsum(h)])
    for k in range(P):
        for s in (0.05, 0.3, 0.5, 0.77, 0.95):
            t = knots[k] + s * h[k]
            tau_g = (k + s) / P
            want = sum(c[i] * float(spline_kernel(tau_g * P - i, degree)) for i in range(P + 1))
            assert float(ctrl(a, t)[0]) == pytest.approx(want, abs=1e-13)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spline_kernel_partition_of_unity_and_continuity(degree):
    s = jnp.linspace(0.0, 1.0, 101)
    total = spline_kernel(s, degree) + spline_kernel(s - 1.0, degree)
    np.testing.assert_allclose(total, 1.0, atol=1e-14)
    if degree >= 1:
        eps = 1e-9
        for t in (-0.5, 0.5):
            assert abs(float(spline_kernel(t - eps, degree) - spline_kernel(t + eps, degree))) < 1e-8
        assert float(spline_kernel(1.0, degree)) == 0.0 and float(spline_kernel(0.0, degree)) == 1.0


def test_spline_saturates_and_has_channels():
    ctrl = C.SaturatedSpline(2, 1, [-1.0, 0.0], [1.0, 0.5])
    assert ctrl.num_controls == 2 and ctrl.num_params == 2 + 2 * 3
    a = jnp.array([1.0, 1.0, -3.0, 0.0, 3.0, 0.2, 0.2, 0.9])
    u = ctrl(a, jnp.array([0.0, 1.0, 2.0]))
    np.testing.assert_allclose(u, [[-1.0, 0.2], [0.0, 0.2], [1.0, 0.5]])
