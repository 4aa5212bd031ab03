"""A control family defined here, outside the package, runs through every solver, batching,
multistart and declared control bounds: what a family declares (`time_layout`,
`value_indices`, `affine`) is all the package needs to know about it."""

import math
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import energy_problem

import jaxtraj as jt
from jaxtraj._sensitivity import affine_segment_basis
from jaxtraj._simulate import segment_data

SIM = jt.RK4(20)


class LinearByDurations(jt.controls.AbstractControl):
    """Continuous piecewise-linear u with free segment durations: `[h_1..h_K, u_0..u_K]`."""

    segments: int
    affine: ClassVar[bool] = True
    value_bounds_exact: ClassVar[bool] = True  # linear between the node values

    @property
    def num_params(self):
        return 2 * self.segments + 1

    @property
    def num_segments(self):
        return self.segments

    @property
    def time_indices(self):
        return tuple(range(self.segments))

    @property
    def time_layout(self):
        return "durations"

    @property
    def value_indices(self):
        return tuple(range(self.segments, self.num_params)), (0,) * (self.segments + 1)

    def knots(self, a):
        return jnp.concatenate([jnp.zeros(1, a.dtype), jnp.cumsum(a[: self.segments])])

    def segment_table(self, a):
        u = a[self.segments :]
        return jnp.stack([u[:-1], u[1:]], axis=1)

    def local_control(self, row, h, tau):
        return (row[0] + (row[1] - row[0]) * tau)[None]

    def initial_guess(self, tf, u_start, u_end):
        K = self.segments
        return jnp.asarray(np.concatenate([np.full(K, tf / K), np.linspace(u_start, u_end, K + 1)]))


CTRL = LinearByDurations(2)
# u = 6 - 12 t (the analytic optimum, energy 6) has nodes (6, u(h_1), -6) for any h_1
A0 = jnp.asarray([0.4, 0.55, 4.0, 0.5, -3.0])


def _energy_problem(bound=None):
    return energy_problem(
        control_lower=None if bound is None else -bound,
        control_upper=bound,
        name="min-energy, own family",
    )


def _energy_on_line(sol):
    """The optimum is u = 6 - 12 t (energy 6) on [0, 1]: check u on a grid, and the energy.
    Any h_1 holds it, h_1 = 0 or 1 too (a segment of length 0 at the bound h >= 0, whose
    far node then does not matter): check the function, not the nodes.

    The energy is checked to what the solver's feasibility tolerance allows: reaching
    (x, v) at time T costs V = (6 x^2 - 6 x v T + 2 v^2 T^2) / T^3, whose gradient at (1, 0,
    1) is (12, -6, -18), so a point within E of the constraints is within 36 E of 6."""
    t = np.linspace(0.0, 1.0, 41)[1:-1]
    np.testing.assert_allclose(np.asarray(CTRL(sol.params, t))[:, 0], 6.0 - 12.0 * t, atol=2e-4)
    tol = 36.0 * float(sol.max_constraint_error) + 1e-10
    assert float(sol.objective) == pytest.approx(6.0, abs=tol)


def test_declared_affinity_matches_a_probe():
    """`affine` is declared, not probed: check each declaration (this family's and the
    package's) against the Jacobian of segment_data at two random points."""
    families = [
        CTRL,
        jt.controls.PiecewiseLinear(3, continuous=False, free_times=True),
        jt.controls.PiecewiseParabolic(2),
        jt.controls.PiecewiseConstant(3, free_times=False),
        jt.controls.SaturatedSpline(4, 1, -1.0, 1.0),
    ]
    rng = np.random.default_rng(1)
    for ctrl in families:
        jac = jax.jacfwd(segment_data, argnums=1)
        j1, j2 = (np.asarray(jac(ctrl, jnp.asarray(rng.uniform(0.5, 2.0, ctrl.num_params)))) for _ in range(2))
        assert ctrl.affine == bool(np.allclose(j1, j2, rtol=1e-12, atol=1e-12)), ctrl
        assert (affine_segment_basis(ctrl, jnp.zeros(ctrl.num_params)) is not None) <= ctrl.affine


@pytest.mark.slow
@pytest.mark.parametrize(
    "solver",
    [
        jt.KalmanSearch(),
        jt.KalmanSQP(),
        jt.KalmanSQP(globalization="trust-region", hessian="exact"),
        jt.AugmentedLagrangian(),
    ],
    ids=["KalmanSearch", "KalmanSQP", "KalmanSQP-trust-region", "AugmentedLagrangian"],
)
def test_every_solver_reaches_the_analytic_optimum(solver):
    prob = _energy_problem(bound=10.0)  # declared, inactive at the optimum (|u| <= 6)
    sol = jt.solve(prob, CTRL, A0, solver, simulator=SIM, max_steps=3000)
    assert jt.status_name(sol.status) == "SUCCESS"
    _energy_on_line(sol)


@pytest.mark.slow
def test_solve_batch_and_multistart():
    prob = _energy_problem(bound=10.0)
    starts = jt.random_starts(prob, CTRL, jax.random.key(3), 4, around=A0, spread=2.0)
    # durations stay positive, node values are clipped into the declared bounds
    assert bool(jnp.all(starts[:, :2] > 0)) and bool(jnp.all(jnp.abs(starts[:, 2:]) <= 10.0))
    assert float(jnp.max(jnp.abs(starts[:, 2:]))) == 10.0  # spread 2 pushes some past the bound
    sols = jt.solve_batch(prob, CTRL, starts, simulator=SIM, max_steps=300)
    for sol in sols:
        assert jt.status_name(sol.status) == "SUCCESS"
        _energy_on_line(sol)
    res = jt.multistart(prob, CTRL, jax.random.key(4), 3, around=A0, simulator=SIM, max_steps=300)
    assert res.success_rate == 1.0 and len(res.optima) == 1
    assert res.optima[0][0] == pytest.approx(6.0, rel=1e-8)


def test_declared_bounds_are_honored():
    """|u| <= B = 5 cuts the optimum (|u| = 6 at the ends). The constrained optimum is
    u = sat_B(linear): B on [0, 1/2 - c], linear down to -B, -B on [1/2 + c, 1], with
    c^2 = 3 (B/4 - 1) / B (x(1) = 1), energy B^2 (1/2 - 2c/3); three segments hold it
    exactly. AugmentedLagrangian bounds the node values (the family's `value_indices`)."""
    B = 5.0
    c = math.sqrt(3.0 * (B / 4.0 - 1.0) / B)
    prob = _energy_problem(bound=B)
    ctrl = LinearByDurations(3)
    a0 = jnp.asarray([0.3, 0.4, 0.3, 4.0, 2.0, -2.0, -4.0])
    sol = jt.solve(prob, ctrl, a0, jt.AugmentedLagrangian(), simulator=SIM, max_steps=5000)
    assert jt.status_name(sol.status) == "SUCCESS"
    assert float(jnp.max(jnp.abs(sol.params[3:]))) <= B
    np.testing.assert_allclose(np.asarray(sol.params), [0.5 - c, 2 * c, 0.5 - c, B, B, -B, -B], atol=1e-4)
    assert float(sol.objective) == pytest.approx(B**2 * (0.5 - 2 * c / 3), rel=1e-7)
    # a family with no control-value parameters cannot take declared bounds: an error, not silence

    class NoValues(LinearByDurations):
        @property
        def value_indices(self):
            return (), ()

    with pytest.raises(ValueError, match="value_indices"):
        jt.solve(prob, NoValues(2), A0, jt.AugmentedLagrangian(), simulator=SIM, max_steps=10)

    # nor can one whose own saturation limits are wider than the declared bounds
    class WideLimits(NoValues):
        @property
        def limits(self):
            return jnp.array([-8.0]), jnp.array([8.0])

    with pytest.raises(ValueError, match="does not saturate within the bounds"):
        jt.solve(prob, WideLimits(2), A0, jt.AugmentedLagrangian(), simulator=SIM, max_steps=10)
    spline = jt.controls.SaturatedSpline(2, 1, -1.0, 1.0)
    assert jt.controls.saturates_within(spline, -1.0, 2.0) and jt.controls.saturates_within(spline)
    assert not jt.controls.saturates_within(spline, -0.5, 2.0) and not jt.controls.saturates_within(CTRL, -9.0, 9.0)
