"""Bad input fails early, outside jit, with a ValueError naming the argument, the expected
and the received value."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import gain_reach

import jaxtraj as jt

C = jt.controls
PROB = jt.problems.earth_mars.problem()


def test_wrong_length():
    ctrl = C.PiecewiseLinear(5)
    with pytest.raises(ValueError, match=r"`a` must have shape \(7,\).*got shape \(6,\)"):
        jt.simulate(PROB, ctrl, jnp.zeros(6))
    with pytest.raises(ValueError, match=r"`a` must have shape \(7,\)"):
        jt.sensitivities(PROB, ctrl, jnp.zeros((7, 1)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_entries(bad):
    ctrl = C.PiecewiseLinear(5)
    a = np.array(ctrl.initial_guess(3.4, 0.0, 4.7))
    a[2] = bad
    with pytest.raises(ValueError, match=r"`a` must be finite.*indices \[2\]"):
        jt.evaluate(PROB, ctrl, a)


def test_node_times_out_of_order():
    ctrl = C.PiecewiseLinear(3, continuous=False, free_times=True)
    a = np.array(ctrl.initial_guess(3.4, 0.0, 4.7))
    a[5] = 0.5  # t_2 < t_1 = 1.133
    with pytest.raises(ValueError, match=r"node times must be increasing.*t_1 <= t_2, got t_1 = 1.13333, t_2 = 0.5"):
        jt.simulate(PROB, ctrl, a)


def test_node_time_beyond_tf():
    ctrl = C.PiecewiseLinear(4, continuous=True, free_times=True)
    a = np.array(ctrl.initial_guess(3.4, 0.0, 4.7))
    a[7] = 3.6  # last interior node after tf = 3.4
    with pytest.raises(ValueError, match=r"increasing in \[0, tf\] with tf = 3.4.*t_3 = 3.6"):
        jt.sensitivities(PROB, ctrl, a, "unit")


def test_switch_times_out_of_order_and_negative_tf():
    ctrl = C.PiecewiseConstant(2)
    with pytest.raises(ValueError, match="switch times"):
        jt.simulate(PROB, ctrl, jnp.array([0.0, 2.0, 1.0, 1.5]))
    with pytest.raises(ValueError, match="switch times"):
        jt.simulate(PROB, ctrl, jnp.array([0.0, -1.0, 1.0, 1.5]))
    fixed = C.PiecewiseConstant(2, free_times=False)
    with pytest.raises(ValueError, match=r"tf must be > 0.*got tf = -1"):
        jt.simulate(PROB, fixed, jnp.array([0.0, 1.0, -1.0]))


def test_a_collapsed_segment_is_a_valid_control():
    """Equal neighbouring knots (a collapsed segment, as solvers leave one at its bound) are
    accepted: with the switch of PiecewiseConstant(2) at tf the control is u_1 throughout, so
    x'' = u_1 = 1 from rest over tf = 2 ends at x = u tf^2 / 2 = 2, v = 2 (closed form); a switch
    before t = 0 still raises."""
    prob = jt.Problem(lambda t, x, u, args: jnp.array([x[1], u[0]]), [0.0, 0.0], lambda tf, xf, args: xf, ("x", "v"))
    ctrl = C.PiecewiseConstant(2)
    a = jnp.array([1.0, 2.0, -5.0, 2.0])  # [u_1, t_1, u_2, tf]: t_1 = tf
    traj = jt.simulate(prob, ctrl, a, simulator=jt.RK4(4))
    np.testing.assert_allclose(traj.xf, [2.0, 2.0], rtol=1e-12)
    ev = jt.evaluate(prob, ctrl, a, simulator=jt.RK4(4))
    assert np.all(np.isfinite(np.asarray(ev.H)))
    with pytest.raises(ValueError, match=r"switch times must be increasing.*t_0 <= t_1, got t_0 = 0, t_1 = -0.1"):
        jt.simulate(prob, ctrl, jnp.array([1.0, -0.1, -5.0, 2.0]))
    # a reversal at round-off (a switch pressed onto t = 0 came back from a solve as -4.8e-40)
    # is a collapsed segment too: the whole arc is u_2 = -5, x = -5 tf^2 / 2 = -10, v = -10
    traj = jt.simulate(prob, ctrl, jnp.array([1.0, -4.8e-40, -5.0, 2.0]), simulator=jt.RK4(4))
    np.testing.assert_allclose(traj.xf, [-10.0, -10.0], rtol=1e-12)
    with pytest.raises(ValueError, match=r"switch times must be increasing"):
        jt.simulate(prob, ctrl, jnp.array([1.0, -1e-9, -5.0, 2.0]))


def test_negative_durations():
    ctrl = C.SaturatedSpline(3, 2, -1.0, 1.0)
    a = np.array(ctrl.initial_guess(3.0, 0.0, 0.5))
    a[1] = -0.2
    with pytest.raises(ValueError, match=r"segment durations h_k \(a\[1\]\) must be >= 0; got a\[1\] = -0.2"):
        jt.simulate(PROB, ctrl, a)


@pytest.mark.parametrize("degree", [-1, 4, 1.5, True])
def test_degree_outside_range(degree):
    with pytest.raises(ValueError, match=r"`degree` must be an int in 0..3; got"):
        C.SaturatedSpline(3, degree, -1.0, 1.0)


@pytest.mark.parametrize("segments", [0, -2, 2.0, 2**40])
def test_bad_segment_count(segments):
    with pytest.raises(ValueError, match=r"`segments` must be an int >= 1"):
        C.PiecewiseLinear(segments)
    with pytest.raises(ValueError, match=r"`channels` must be an int >= 1"):
        C.PiecewiseConstant(2, channels=segments)


@pytest.mark.parametrize(
    "make",
    [
        lambda flag: C.PiecewiseLinear(2, continuous=flag, free_times=flag),
        lambda flag: C.PiecewiseParabolic(2, free_times=flag),
        lambda flag: C.PiecewiseConstant(2, free_times=flag),
        lambda flag: C.SaturatedSpline(2, 1, -1.0, 1.0, free_durations=flag),
    ],
)
def test_a_numpy_bool_flag_works_as_a_bool(make):
    """The fifth audit: a NumPy bool flag was accepted, then traced under jit (JAX's
    TracerBoolConversionError from jt.solve or jt.simulate)."""
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl = make(np.True_)
    assert ctrl == make(True)
    a = ctrl.initial_guess(1.0, 0.0, 0.0)
    np.testing.assert_array_equal(jt.simulate(prob, ctrl, a).x, jt.simulate(prob, make(True), a).x)


@pytest.mark.parametrize("bounds", [([], []), (False, True), (np.zeros(0), 1.0)])
def test_spline_bounds_of_no_channel_or_bools_are_refused(bounds):
    """The fifth audit: empty bounds made a spline of 0 channels, bools one in [0, 1]."""
    with pytest.raises(ValueError, match=r"`lower`/`upper` must be numbers, one per channel"):
        C.SaturatedSpline(3, 1, *bounds)


def test_bad_bounds_method_simulator_and_guess():
    with pytest.raises(ValueError, match=r"`lower` must be < `upper`"):
        C.SaturatedSpline(3, 1, 1.0, -1.0)
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    with pytest.raises(ValueError, match=r"`method` must be one of \('forward', 'unit', 'fd'\); got 'adjoint'"):
        jt.sensitivities(prob, ctrl, a0, "adjoint")
    with pytest.raises(ValueError, match=r"`simulator` must be"):
        jt.simulate(prob, ctrl, a0, simulator="rk4")
    with pytest.raises(ValueError, match=r"`steps` must be an int >= 1; got 0"):
        jt.RK4(0)
    with pytest.raises(ValueError, match=r"`tf` must be a finite number > 0"):
        ctrl.initial_guess(-1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match=r"`n` must be a thesis case in 1..7; got 8"):
        jt.problems.earth_mars.thesis_case(8)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        # a solver without an error estimate, or a name for one, failed inside diffrax at the
        # first simulation; a text tolerance gave Python's comparison error, an infinite one
        # was taken (issue 51, fourth audit)
        ({"solver": "tsit5"}, r"`solver` must be a diffrax solver with an error estimate .*got 'tsit5'"),
        ({"solver": None}, r"`solver` must be a diffrax solver with an error estimate"),
        ({"rtol": "1e-8"}, r"`rtol` must be a finite number > 0; got '1e-8'"),
        ({"atol": np.inf}, r"`atol` must be a finite number > 0; got inf"),
        ({"rtol": np.nan}, r"`rtol` must be a finite number > 0; got nan"),
        ({"max_steps": True}, r"`max_steps` must be an int >= 1; got True"),
        ({"max_steps": 2**40}, r"`max_steps` must be an int >= 1; got 1099511627776"),
        ({"dense_points": True}, r"`dense_points` must be an int >= 2; got True"),
    ],
)
def test_diffrax_settings_are_checked_when_made(kwargs, message):
    with pytest.raises(ValueError, match=message):
        jt.Diffrax(**kwargs)
    assert jt.Diffrax(rtol=np.float64(1e-8), atol=jnp.asarray(1e-9)).rtol == 1e-8


def test_a_diffrax_solver_without_error_estimate_is_refused_when_made():
    import diffrax

    with pytest.raises(ValueError, match=r"`solver` must be a diffrax solver with an error estimate .*Euler"):
        jt.Diffrax(diffrax.Euler())


@pytest.mark.parametrize(
    ("call", "message"),
    [
        # NumPy's or Python's messages, naming no argument (issue 51, fourth audit)
        (lambda: C.PiecewiseLinear(3).initial_guess("1.0", 0.0, 0.0), r"`tf` must be a finite number > 0; got '1.0'"),
        (lambda: C.PiecewiseLinear(3).initial_guess(None, 0.0, 0.0), r"`tf` must be a finite number > 0; got None"),
        (lambda: C.PiecewiseConstant(3).initial_guess(np.ones(2), 0.0, 0.0), r"`tf` must be a finite number > 0"),
        (
            lambda: C.PiecewiseLinear(3).initial_guess(1.0, [0.0, 1.0, 2.0], 0.0),
            r"`u_start` and `u_end` must each be a finite number or 1 \(one per channel\); got \[0\.0, 1\.0, 2\.0\]",
        ),
        (lambda: C.PiecewiseParabolic(2).initial_guess(1.0, "a", 0.0), r"`u_start` and `u_end` must each be"),
        (lambda: C.PiecewiseLinear(2).initial_guess(1.0, 0.0, np.nan), r"`u_start` and `u_end` must each be"),
        (lambda: C.SaturatedSpline(3, 1, [-1.0, -1.0], [1.0, 1.0, 1.0]), r"`lower`/`upper` must have one entry per"),
        (lambda: C.SaturatedSpline(3, 1, "a", 1.0), r"`lower`/`upper` must be numbers, one per channel; got 'a'"),
        # another length was evaluated as this family's entries, silently
        (lambda: C.PiecewiseLinear(3)(jnp.ones(7), 0.5), r"`a` must have shape \(5,\) .*got shape \(7,\)"),
    ],
)
def test_control_helpers_name_the_argument(call, message):
    with pytest.raises(ValueError, match=message):
        call()
    assert C.PiecewiseLinear(3).initial_guess(np.float64(1.0), jnp.asarray(0.5), [0.0])[-1] == 1.0


def test_bad_problem_definitions():
    with pytest.raises(ValueError, match=r"`dynamics\(t, x, u, args\)` must return an array of shape \(3,\)"):
        jt.Problem(lambda t, x, u, args: x[:2], [0.0, 1.0, 1.0], lambda tf, xf, args: xf, ("a", "b", "c"))
    with pytest.raises(ValueError, match=r"`terminal\(tf, xf, args\)` must return an array of shape \(2,\)"):
        jt.Problem(lambda t, x, u, args: x, [0.0, 1.0, 1.0], lambda tf, xf, args: xf, ("a", "b"))
    with pytest.raises(ValueError, match=r"`x0` must be finite"):
        jt.Problem(lambda t, x, u, args: x, [0.0, np.nan], lambda tf, xf, args: xf, ("a", "b"))
    with pytest.raises(ValueError, match=r"unknown Earth-Mars constant"):
        jt.problems.earth_mars.problem(gravity=2.0)


def test_an_index_past_an_arrays_end_is_refused():
    """Issue 51: JAX clamps u[3] of a 2-control u to u[1], silently; the problem refuses it
    (the same function with u[1] is accepted, as are in-range index arrays), and so does it
    an index array past the end or the terminal function's xf[5]."""

    def problem(rate, terminal=lambda tf, xf, args: xf[:2] - 1.0):
        dynamics = lambda t, x, u, args: jnp.stack([x[1], rate(u)])
        return jt.Problem(dynamics, [0.0, 0.0], terminal, ("x", "v"), num_controls=2)

    assert problem(lambda u: u[1]).num_controls == 2
    assert problem(lambda u: jnp.sum(u[jnp.array([0, 1])])).num_controls == 2
    dynamics = r"`dynamics\(t, x, u, args\)` indexes outside an array: "
    with pytest.raises(ValueError, match=dynamics + r".*index 3 is out of bounds for axis 0 with size 2"):
        problem(lambda u: u[3])
    with pytest.raises(ValueError, match=dynamics + r".*index 2 is out"):
        problem(lambda u: jnp.sum(u[jnp.array([0, 2])]))
    with pytest.raises(ValueError, match=r"`terminal\(tf, xf, args\)` indexes outside an array: .*index 5 is out"):
        problem(lambda u: u[0], lambda tf, xf, args: jnp.stack([xf[0], xf[5]]))


def test_control_channel_mismatch():
    ctrl = C.SaturatedSpline(2, 1, [-1.0, -1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match=r"2 channel\(s\) but `problem` 'earth-mars' expects num_controls=1"):
        jt.simulate(PROB, ctrl, ctrl.initial_guess(3.0, 0.0, 0.5))


def test_float64_is_enforced():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    assert jt.simulate(prob, ctrl, a0).xf.dtype == jnp.float64
    # a float32 input is promoted, never computed in float32
    assert jt.evaluate(prob, ctrl, np.asarray(a0, dtype=np.float32)).H.dtype == jnp.float64
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(RuntimeError, match="jaxtraj needs float64"):
            jt.simulate(prob, ctrl, a0)
    finally:
        jax.config.update("jax_enable_x64", True)


def test_constant_parameters_closed_over_by_jit():
    """A concrete `a` captured by a jitted function is still validated (and works)."""
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    xf = jax.jit(lambda: jt.simulate(prob, ctrl, a0, simulator=jt.RK4(10)).xf)()
    np.testing.assert_allclose(xf, jt.simulate(prob, ctrl, a0, simulator=jt.RK4(10)).xf, rtol=1e-13)
    bad = a0.at[0].set(jnp.nan)
    with pytest.raises(ValueError, match="finite"):
        jax.jit(lambda: jt.simulate(prob, ctrl, bad).xf)()


def _energy_problem(**kwargs):
    base = jt.problems.analytic.min_energy_double_integrator()
    fields = dict(objective=base.objective, args=base.args)
    return jt.Problem(
        base.dynamics, base.x0, base.terminal, kwargs.pop("names", base.constraint_names), **fields, **kwargs
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"control_lower": 1.0, "control_upper": -1.0}, r"`control_lower` must be <= `control_upper`"),
        ({"control_upper": [1.0, 2.0]}, r"`control_upper` must be a scalar or have 1 entries .*got shape \(2,\)"),
        ({"control_lower": "low"}, r"`control_lower` must be a number"),
        # impossible bounds were dropped as "free" and the solve said SUCCESS (issue 51)
        ({"control_lower": np.inf}, r"`control_lower` must not contain inf"),
        ({"control_upper": -np.inf}, r"`control_upper` must not contain -inf"),
        ({"state_upper": -np.inf}, r"`state_upper` must not contain -inf"),
        ({"state_lower": np.inf}, r"`state_lower` must not contain inf"),
        ({"names": "abc"}, r"`constraint_names` must be a sequence of names, not one string"),
        ({"names": ("a", "b", 3)}, r"`constraint_names` must contain strings"),
        ({"state_names": "xyz"}, r"`state_names` must be a sequence of names"),
        # a repeated name hid one row in saved results, which then did not load (issue 51)
        ({"names": ("p", "p")}, r"`constraint_names` must name each row once; \['p'\] repeat"),
        ({"control_names": ("a", "b")}, r"`control_names` must have 1 entries .*got 2"),
        # names without their function were accepted and ignored, or named the tf_bounds'
        # rows one off; a name that jt.Problem also gives a row it adds made a saved result
        # that did not load (issue 51, fourth audit)
        ({"path_names": ("speed",)}, r"`path_names` names the rows of `path`, which is None"),
        (
            {"terminal_inequality_names": ("late",), "tf_bounds": (0.5, 2.0)},
            r"`terminal_inequality_names` names the rows of `terminal_inequality`, which is None",
        ),
        (
            {"path": lambda t, x, u, a: x[1:2] - 2.0, "path_names": ("x2 upper bound",), "state_upper": 1.5},
            r"`path_names`: \['x2 upper bound'\] is also the name jt.Problem gives the rows of `state_lower`",
        ),
        (
            {
                "terminal_inequality": lambda tf, xf, a: jnp.stack([tf - 5.0]),
                "terminal_inequality_names": ("tf upper bound",),
                "tf_bounds": (0.1, 4.0),
            },
            r"`terminal_inequality_names`: \['tf upper bound'\] is also the name jt.Problem gives the rows of `tf_b",
        ),
        # the fifth audit: a text "12" was taken as the bounds (1, 2), bools as 0 and 1
        ({"tf_bounds": "12"}, r"`tf_bounds` must be a pair \(lower, upper\) of numbers; got '12'"),
        ({"tf_bounds": ("0.5", "2")}, r"`tf_bounds` must be a pair \(lower, upper\) of numbers"),
        ({"tf_bounds": (False, True)}, r"`tf_bounds` must be a pair \(lower, upper\) of numbers"),
        ({"tf_bounds": {0.5, 2.0}}, r"`tf_bounds` must be a pair \(lower, upper\) of numbers"),
        (
            {"state_names": ("running cost", "v", "e"), "running_cost": lambda t, x, u, a: u[0] ** 2},
            r"`state_names`: \['running cost'\] is also the name jt.Problem gives the accumulated `running_cost`",
        ),
    ],
)
def test_problem_arguments_are_checked(kwargs, message):
    with pytest.raises(ValueError, match=message):
        _energy_problem(**kwargs)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"x0": ["a", "b"]}, r"`x0` must be real numbers \(the initial state\); got \['a', 'b'\]"),
        # a complex x0 lost its imaginary part with a warning only (issue 51, third audit)
        ({"x0": np.array([1j, 0.0])}, r"`x0` must be real numbers \(the initial state\); got array\(\[0\.\+1\.j"),
        ({"num_controls": True}, r"`num_controls` must be an int in 1\.\.10000; got True"),
        ({"num_controls": 2**40}, r"`num_controls` must be an int in 1\.\.10000"),
    ],
)
def test_problem_sizes_and_states_name_the_argument(change, message):
    """Issue 51's re-audit: a string state and a bool or huge control count (the latter was
    killed for memory while building per-channel tables) are one-line errors."""
    base = jt.problems.analytic.min_energy_double_integrator()
    kwargs = {"x0": base.x0, "num_controls": 1, **change}
    with pytest.raises(ValueError, match=message):
        jt.Problem(base.dynamics, terminal=base.terminal, constraint_names=base.constraint_names, **kwargs)


def test_complex_parameters_are_refused():
    ctrl = C.PiecewiseLinear(3)
    a = np.asarray(ctrl.initial_guess(1.2, 0.0, 0.0)) + 0j
    with pytest.raises(ValueError, match="`a` must be a real numeric array"):
        jt.simulate(_energy_problem(), ctrl, a)


@pytest.mark.parametrize(
    "make",
    [
        lambda: jt.KalmanSQP(ctol="1e-8"),
        lambda: jt.KalmanSearch(rho="fast"),
        lambda: jt.AugmentedLagrangian(gtol=None),
        lambda: jt.LineSearch(armijo="small"),
        lambda: jt.TrustRegion(eta=[1e-4]),
        lambda: jt.TrustRegion(feasibility_first="yes"),
        lambda: jt.TrustRegion(feasibility_first=True),  # a threshold since 2026-12-04
        # an infinite tolerance said SUCCESS at an infeasible start; 2**70 overflowed (issue 51)
        lambda: jt.KalmanSQP(ctol=float("inf")),
        lambda: jt.KalmanSQP(gtol=float("inf"), acceptable_gtol=float("inf")),
        lambda: jt.AugmentedLagrangian(ctol=float("inf")),
        lambda: jt.KalmanSQP(acceptable_steps=2**70),
        # accepted until the fourth audit (issue 51): `path_active` = "x" failed inside the
        # solve, inf or -1 ended STALLED; `flat_steps` = 2**40 STALLED far from the optimum
        lambda: jt.KalmanSQP(path_active="x"),
        lambda: jt.KalmanSQP(path_active=float("inf")),
        lambda: jt.KalmanSQP(path_active=-1.0),
        lambda: jt.KalmanSQP(a_t=float("inf")),
        lambda: jt.LineSearch(flat_steps=2**40),
        lambda: jt.LineSearch(flat_steps=True),
        lambda: jt.LineSearch(mu_max=float("inf")),
        lambda: jt.TrustRegion(radius=float("inf")),
        lambda: jt.TrustRegion(cap_progress=1.0),
        # accepted until the fifth audit: an array of shape (1,) failed inside the solve
        # (JAX's while_loop carry message); a bool was taken as 1 or 0
        lambda: jt.TrustRegion(radius=np.array([1.0])),
        lambda: jt.LineSearch(radius=np.array([0.5])),
        lambda: jt.TrustRegion(mu_max=True),
        lambda: jt.LineSearch(cap_progress=False),
        lambda: jt.TrustRegion(feasibility_first=np.True_),
    ],
)
def test_a_setting_of_the_wrong_type_names_the_field(make):
    fields = "ctol|rho|gtol|armijo|eta|feasibility_first|acceptable_steps|path_active|a_t|flat_steps|mu_max|radius|cap_progress"
    with pytest.raises(ValueError, match=rf"invalid `({fields})`"):
        make()


@pytest.mark.parametrize(
    "field, value",
    [
        ("e_a", float("inf")),
        ("gtol", float("inf")),
        ("gtol", -1.0),
        ("gtol", float("nan")),
        ("rho", float("inf")),
        ("max_rejections", -1),
        ("max_retunings", -5),
        ("rho_max", float("nan")),
        ("e_m", float("inf")),
        ("rho_decrease", 2.0),
        ("max_rejections", 2**40),
    ],
)
def test_kalman_search_refuses_meaningless_settings(field, value):
    """KalmanSearch checked only some fields (issue 51, third audit): `e_a = inf` said SUCCESS
    at the infeasible start, `gtol = inf` at a point short of the optimum, a negative
    `max_rejections` or NaN `rho_max` ended STALLED or CONSTRAINT_STATIONARY after 0 steps."""
    kwargs = {field: value, **({"e_a_start": value} if field == "e_a" else {})}
    with pytest.raises(ValueError, match=f"KalmanSearch: invalid `{field}`"):
        jt.KalmanSearch(**kwargs)
    assert jt.KalmanSearch(max_rejections=np.int64(5)).max_rejections == 5


def test_numpy_integers_count_as_ints():
    """`max_steps` and `RK4(steps)` take NumPy integers (e.g. from an array of settings) and
    give what Python ints give."""
    prob, ctrl = _energy_problem(), C.PiecewiseLinear(3)
    a0 = ctrl.initial_guess(1.2, 0.0, 0.0)
    assert jt.RK4(np.int64(4)) == jt.RK4(4)
    one = jt.solve(
        prob, ctrl, a0, jt.KalmanSearch(), simulator=jt.RK4(np.int64(4)), max_steps=np.int64(3), progress=np.int64(0)
    )
    two = jt.solve(prob, ctrl, a0, jt.KalmanSearch(), simulator=jt.RK4(4), max_steps=3)
    assert int(one.steps) == int(two.steps) <= 3
    np.testing.assert_array_equal(one.params, two.params)
    for bad in (0, 2.0, True, np.float64(3.0)):
        with pytest.raises(ValueError, match="`max_steps` must be an int >= 1"):
            jt.solve(prob, ctrl, a0, max_steps=bad)
    # the fifth audit: True printed every step, 2**40 (wrapped in int32) too
    for bad in (True, 2**40, -1, 2.0):
        with pytest.raises(ValueError, match="`progress` must be an int >= 0"):
            jt.solve(prob, ctrl, a0, progress=bad)


def test_a_max_steps_past_the_int32_step_counter_is_refused():
    """A batch without history (no memory check) wrapped 2**31 to a negative limit: every
    start ended MAX_ITERATIONS after 0 steps, silently."""
    ctrl = C.PiecewiseLinear(3)
    a0 = ctrl.initial_guess(3.4, 0.0, 0.0)
    for max_steps in (2**31, 2**40):
        with pytest.raises(ValueError, match=r"^`max_steps` must be < 2\*\*31 \(the solvers count steps in int32\)"):
            jt.solve_batch(PROB, ctrl, np.stack([a0, a0]), max_steps=max_steps, history=False, progress=False)


def test_what_cannot_fit_in_memory_is_refused_before_the_work():
    """Issue 51: sizes whose arrays alone exceed any machine's memory are refused up front
    with the number and the limit (they used to end in XLA's RESOURCE_EXHAUSTED, or the
    process killed for memory); a compiled solve that asks XLA for more than the device has
    is a MemoryError that says so, not a raw XLA error."""
    ctrl = C.PiecewiseLinear(3)
    a0 = ctrl.initial_guess(3.4, 0.0, 0.0)
    limit = r"more than the [\d,.]+ GB of memory available"
    with pytest.raises(
        ValueError, match=r"`max_steps`: the history of 1,000,000,000,000 steps needs at least 33,000\.0 GB, " + limit
    ):
        jt.solve(PROB, ctrl, a0, max_steps=10**12)
    with pytest.raises(ValueError, match=r"`max_steps`: the history of 2 starts x 10,000,000,000,000 steps"):
        jt.solve_batch(PROB, ctrl, np.stack([a0, a0]), max_steps=10**13, progress=False)
    with pytest.raises(
        ValueError, match=r"`n`: 10,000,000,000,000 starts of 5 parameters needs at least 400,000\.0 GB"
    ):
        jt.random_starts(PROB, ctrl, jax.random.key(0), 10**13, a0)
    with pytest.raises(ValueError, match=r"`n`: 1,000,000,000,000 runs"):
        jt.monte_carlo(PROB, ctrl, a0, jax.random.key(0), 10**12, sigma_thrust=0.01, simulator=jt.RK4(4))
    with pytest.raises(ValueError, match=r"`simulator`: 30,000,000,003 trajectory points"):
        jt.simulate(PROB, ctrl, a0, simulator=jt.RK4(10**10))
    with pytest.raises(MemoryError, match=r"jt.solve needs more memory than the [\d,.]+ GB available \(one allocation"):
        jt.solve(PROB, ctrl, a0, simulator=jt.RK4(10**10), max_steps=3)
    # a control of 10**5 segments (its start fits: 0.8 MB) whose solver matrices cannot
    big = C.PiecewiseLinear(10**5)
    start = big.initial_guess(3.4, 0.0, 0.0)
    with pytest.raises(
        ValueError,
        match=r"`control`: a solve \(4 dense 100,002 x 100,002 matrices at least\) needs at least 320\.0 GB, " + limit,
    ):
        jt.solve(PROB, big, start)
    with pytest.raises(
        ValueError, match=r"`control`: a solve \(4 dense 100,002 x 100,002 matrices at least in each of 2 lanes\)"
    ):
        jt.solve_batch(PROB, big, np.stack([start, start]), progress=False, devices=jax.devices()[:1], lanes=2)


def test_gtol_above_acceptable_gtol_names_both():
    with pytest.raises(ValueError, match=r"`gtol` = 1e-05 must be <= `acceptable_gtol` = 1e-06"):
        jt.KalmanSQP(gtol=1e-5)
    assert jt.KalmanSQP(gtol=1e-5, acceptable_gtol=1e-5).gtol == 1e-5


def test_compilation_cache_folder_of_the_wrong_type_is_named():
    """Issue 51's fourth audit: os' TypeError named no argument; nothing changes."""
    before = jax.config.jax_compilation_cache_dir
    with pytest.raises(ValueError, match=r"`folder` must be None or a path .*got int"):
        jt.enable_compilation_cache(5)
    assert jax.config.jax_compilation_cache_dir == before


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: C.PiecewiseLinear(3, continuous="no"), "continuous"),
        (lambda: C.PiecewiseLinear(3, free_times=None), "free_times"),
        (lambda: C.PiecewiseConstant(3, free_times="x"), "free_times"),
        (lambda: C.PiecewiseParabolic(3, free_times=1), "free_times"),
        (lambda: C.SaturatedSpline(3, 1, -1.0, 1.0, free_durations="x"), "free_durations"),
    ],
)
def test_a_family_flag_must_be_a_bool(make, field):
    """The fourth audit (issue 51): a text "no" was taken as True (a family other than the
    one asked for, silently)."""
    with pytest.raises(ValueError, match=rf"`{field}` must be True or False"):
        make()


def test_multistart_tol_must_be_a_finite_number():
    prob = _energy_problem()
    ctrl = C.PiecewiseLinear(3)
    for tol in (True, float("inf")):
        with pytest.raises(ValueError, match=r"`tol` must be a finite number >= 0"):
            jt.multistart(prob, ctrl, jax.random.key(0), 2, around=ctrl.initial_guess(1.2, 0.0, 0.0), tol=tol)


def test_simulate_and_evaluate_run_op_by_op_under_disable_jit():
    """Under `jax.disable_jit()` (a user debugging with prints) the control's knots ran a
    program compiled ahead of time, which JAX refuses there ("Disable jit is not supported in
    the AOT path"): every call raised. Now op by op, with the jitted results."""
    problem, control = gain_reach()
    a = np.linspace(0.1, 0.5, control.num_params)
    sim = jt.RK4(5)
    traj, ev = jt.simulate(problem, control, a, simulator=sim), jt.evaluate(problem, control, a, simulator=sim)
    with jax.disable_jit():
        traj_eager, ev_eager = (
            jt.simulate(problem, control, a, simulator=sim),
            jt.evaluate(problem, control, a, simulator=sim),
        )
    np.testing.assert_allclose(np.asarray(traj_eager.x), np.asarray(traj.x), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(ev_eager.E), np.asarray(ev.E), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(ev_eager.H), np.asarray(ev.H), rtol=1e-12, atol=1e-14)


@pytest.mark.slow  # (op by op: about a minute)
def test_solve_runs_op_by_op_under_disable_jit():
    problem, control = gain_reach()
    a = np.linspace(0.1, 0.5, control.num_params)
    with jax.disable_jit():
        sol = jt.solve(problem, control, a, simulator=jt.RK4(5))
    assert jt.status_name(sol.status) == "SUCCESS"
    assert float(sol.objective) == pytest.approx(0.125, rel=1e-10)


def test_a_gain_closed_over_under_grad_is_named_and_the_same_gain_in_args_differentiates():
    """x' = k u to x(1) = 1 at least energy: J = 1 / (2 k^2), dJ/dk = -1 / k^3. A `k` closed
    over by the dynamics under `jax.grad` escaped the compiled solve (JAX's
    UnexpectedTracerError, naming neither the function nor the remedy); in `args` it is
    differentiated."""

    def objective(k, in_args):
        problem = jt.Problem(
            (lambda t, x, u, args: args[0] * u) if in_args else (lambda t, x, u, args: k * u),
            np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",), num_controls=1,
            running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0,
            args=jnp.stack([k]) if in_args else None,
        )  # fmt: skip
        control = problem.parametrize(jt.controls.PiecewiseLinear(4))
        return jt.solve(problem, control, np.zeros(control.num_params), simulator=jt.RK4(5)).objective

    with pytest.raises(ValueError, match=r"`problem\.dynamics.*` closes over a value that JAX differentiates.*`args`"):
        jax.grad(lambda k: objective(k, False))(2.0)
    assert float(jax.grad(lambda k: objective(k, True))(2.0)) == pytest.approx(-0.125, rel=1e-8)
    assert float(jax.jit(lambda k: objective(k, False))(2.0)) == pytest.approx(0.125, rel=1e-10)  # (works: a constant)


@pytest.mark.parametrize("label", ["x0", "final_time"])
def test_a_traced_x0_or_final_time_names_the_tree_at_route(label):
    """Under `jax.grad`, `jt.Problem(x0=traced)` said "`x0` must be real numbers" and
    `final_time=traced` "must be a finite number > 0": both are real numbers; the route that
    differentiates them (docs/differentiable.md) is `eqx.tree_at` on a built problem."""

    def build(k):
        return jt.Problem(
            lambda t, x, u, args: 2.0 * u, jnp.stack([k]) if label == "x0" else np.zeros(1),
            lambda tf, xf, args: xf - 1.0, ("x(1) = 1",), num_controls=1,
            running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=k if label == "final_time" else 1.0,
        ).x0[0]  # fmt: skip

    with pytest.raises(ValueError, match=rf"`{label}` is traced .*eqx\.tree_at\(lambda p: p\.{label}"):
        jax.grad(build)(1.0)


@pytest.mark.parametrize("x0", [[0.0, 0.0], 0.0, np.zeros(1), np.zeros((2, 1))])
def test_an_x0_put_in_that_is_no_state_array_is_named(x0):
    """`eqx.tree_at(lambda p: p.x0, problem, x0)` with a list, a scalar or another shape (the
    Mayer form's x0 holds the running cost too): an AttributeError or a scan's carry mismatch
    deep inside the integration, plain or under `jax.grad`."""
    problem, control = gain_reach()

    def objective(x0):
        prob = eqx.tree_at(lambda p: p.x0, problem, x0)
        return jt.solve(prob, control, np.zeros(control.num_params), simulator=jt.RK4(5)).objective

    message = r"^`problem\.x0` must be an array of shape \(2,\) \(the states \('x1', 'running cost'\)\); got "
    with pytest.raises(ValueError, match=message):
        objective(x0)
    with pytest.raises(ValueError, match=message):
        jax.grad(objective)(jax.tree.map(jnp.asarray, x0))


def test_bound_arrays_put_in_with_another_shape_are_named():
    """A state bound with more entries than bounded states was more path rows, silently
    (Bryson-Denham's x <= l as two equal rows: a SUCCESS, then NaN derivatives); a `tf_bounds`
    side of shape (2,) failed in a reshape inside the solve."""
    bd = jt.problems.classic.get("bryson-denham")
    prob = eqx.tree_at(lambda p: p.path.fn.upper, bd.problem, jnp.full(2, 1 / 9))
    with pytest.raises(ValueError, match=r"^`problem\.path\.fn\.upper` must have shape \(1,\) .* got shape \(2,\)"):
        jt.solve(prob, bd.control, bd.start, simulator=jt.RK4(4))
    problem = jt.Problem(
        lambda t, x, u, args: u, np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(tf) = 1",), tf_bounds=(0.5, 2.0),
        control_lower=-1.0, control_upper=1.0,
    )  # fmt: skip
    control = jt.controls.PiecewiseConstant(2)
    prob = eqx.tree_at(lambda p: p.tf_bounds[1], problem, jnp.ones(2))
    with pytest.raises(ValueError, match=r"^`problem\.tf_bounds\[1\]` must have shape \(\); got shape \(2,\)"):
        jt.solve(prob, control, control.initial_guess(1.0, 1.0, 1.0))
