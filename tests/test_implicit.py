"""Derivatives of `jt.solve` by the implicit function theorem (issue 50), against answers
that do not come from jaxtraj: the restricted LQ problem's optimum by a NumPy linear solve,
minimum times in closed form, the multipliers of `jt.kkt_report`."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import gain_reach, load_benchmark, rel_err
from test_compilation import compilations

import jaxtraj as jt
from jaxtraj._implicit import kkt_point

SIM = jt.RK4(2)  # exact on every problem here: piecewise constant u, polynomial states


# ---------------------------------------------------------------- problems


def _double_integrator(t, x, u, args):
    return jnp.stack([x[1], args["g"] * u[0]])


def _reach_rest(tf, xf, args):
    return jnp.stack([xf[0] - args["d"], xf[1]])


def _energy(t, x, u, args):
    return 0.5 * args["w"] * u[0] ** 2


def _on_target(tf, xf, args):
    return xf - args["target"]


def _short_of(tf, xf, args):
    return jnp.stack([args["d"] - xf[0]])


LQ_T, LQ_K = 2.0, 3
LQ_X0 = np.array([0.3, -0.2])
LQ_ARGS = {"target": jnp.array([1.0, 0.5]), "w": jnp.asarray(2.0), "g": jnp.asarray(1.0)}
LQ = jt.Problem(
    _double_integrator, LQ_X0, _on_target, ("position", "velocity"), running_cost=_energy, args=LQ_ARGS, final_time=LQ_T
)
LQ_FAMILY = jt.controls.PiecewiseConstant(LQ_K, free_times=False)
LQ_START = LQ.parametrize(LQ_FAMILY).initial_guess(LQ_T, 0.0, 0.0)


def lq_problem(theta):
    """LQ with `theta` = {"target", "w", "x0", "T"} put into its arrays: the arguments, the
    initial state (the accumulated cost's 0 appended: the Mayer form) and the fixed final
    time (the problem's and its control's)."""
    prob = eqx.tree_at(
        lambda p: (p.args["target"], p.args["w"], p.x0, p.final_time),
        LQ,
        (theta["target"], theta["w"], jnp.append(theta["x0"], 0.0), theta["T"]),
    )
    return prob, prob.parametrize(LQ_FAMILY)


LQ_THETA = {"target": LQ_ARGS["target"], "w": LQ_ARGS["w"], "x0": jnp.asarray(LQ_X0), "T": jnp.asarray(LQ_T)}


def lq_solve(theta, **kwargs):
    prob, ctrl = lq_problem(theta)
    return jt.solve(prob, ctrl, LQ_START, simulator=SIM, **kwargs)


def lq_reference(target, w, x0, T):
    """`(J*, u*, A, M, r)` of the restricted LQ problem by NumPy: min 1/2 w h |u|^2 subject to
    A u = r, A's rows the final position and velocity per level, r = target - (x0 coasting):
    u* = A^T M^-1 r, M = A A^T, J* = 1/2 w h r^T M^-1 r."""
    h = T / LQ_K
    t = h * np.arange(LQ_K)
    A = np.stack([h * (T - t - h / 2), np.full(LQ_K, h)])
    r = np.asarray(target) - np.array([x0[0] + x0[1] * T, x0[1]])
    M = A @ A.T
    y = np.linalg.solve(M, r)
    return 0.5 * w * h * r @ y, A.T @ y, A, M, r


def min_time_problem(d=1.5, g=0.8, **changes):
    """x'' = g u, |u| <= 1, from rest at 0 to rest at `d` in least time: bang-bang,
    tf* = 2 sqrt(d / g)."""
    return jt.Problem(
        _double_integrator,
        jnp.zeros(2),
        _reach_rest,
        ("position", "velocity"),
        args={"d": jnp.asarray(d), "g": jnp.asarray(g)},
        control_lower=-1.0,
        control_upper=1.0,
        **changes,
    )


def reach_problem(d, g):
    """Reach x(tf) >= d (a terminal inequality) with x'' = g u, |u| <= 1, velocity free, in
    least time: u = 1 on both pieces, tf* = sqrt(2 d / g). `(problem, control, start)`."""
    prob = jt.Problem(
        _double_integrator,
        jnp.zeros(2),
        lambda tf, xf, args: jnp.zeros(0),
        (),
        args={"d": jnp.asarray(d), "g": jnp.asarray(g)},
        terminal_inequality=_short_of,
        terminal_inequality_names=("reach",),
        control_lower=-1.0,
        control_upper=1.0,
    )
    ctrl = jt.controls.PiecewiseConstant(2, free_times=False)
    return prob, ctrl, ctrl.initial_guess(2.0, 0.5, 0.5)


MT = min_time_problem()
MT_CONTROL = jt.controls.PiecewiseConstant(2)
MT_START = MT_CONTROL.initial_guess(2.5, 1.0, -1.0)


def min_time(args, control=MT_CONTROL, start=MT_START, problem=MT, **kwargs):
    return jt.solve(eqx.tree_at(lambda p: p.args, problem, args), control, start, simulator=SIM, **kwargs).tf


#: eager: it reuses the compiled solve of the plain `jt.solve` calls (a test-time saving)
MT_GRAD = jax.value_and_grad(min_time)


# ---------------------------------------------------------------- tests


@pytest.mark.slow
def test_lq_derivatives_match_the_linear_algebra():
    """dJ*/d(target, w, x0, T) and du*/d(target, x0) of the restricted LQ problem (fixed
    final time, running cost, terminal equalities) against NumPy's linear solve; dJ*/dT (the
    fixed final time, in the problem and its control) against central differences of it."""

    def objective_and_params(theta):
        sol = lq_solve(theta)
        return sol.objective, sol.params

    jac = jax.jit(jax.jacfwd(objective_and_params))(LQ_THETA)
    sol = jax.jit(lq_solve)(LQ_THETA)
    assert sol.status == jt.Status.SUCCESS
    J, u, A, M, r = lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, LQ_T)
    h = LQ_T / LQ_K
    assert rel_err(sol.objective, J) < 1e-9 and rel_err(sol.params, u) < 1e-9
    dJ_dr = 2.0 * h * np.linalg.solve(M, r)
    coast = np.array([[1.0, LQ_T], [0.0, 1.0]])  # r = target - coast @ x0
    dJ, du = jac
    assert rel_err(dJ["target"], dJ_dr) < 1e-7
    assert rel_err(dJ["x0"], -coast.T @ dJ_dr) < 1e-7
    assert rel_err(dJ["w"], J / 2.0) < 1e-7
    step = 1e-5
    fd = (
        lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, LQ_T + step)[0]
        - lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, LQ_T - step)[0]
    ) / (2 * step)
    assert rel_err(dJ["T"], fd) < 1e-6
    du_dr = A.T @ np.linalg.inv(M)
    assert rel_err(du["target"], du_dr) < 1e-7
    assert rel_err(du["x0"], -du_dr @ coast) < 1e-7
    # the multipliers are derivatives: dJ*/d(target) = -lambda (E = x(T) - target)
    report = jt.kkt_report(*lq_problem(LQ_THETA), sol.params, simulator=SIM)
    lam = np.array([report.multipliers["position"], report.multipliers["velocity"]])
    assert rel_err(dJ["target"], -lam) < 1e-7


@pytest.mark.slow
def test_minimum_time_derivatives_through_the_control_bounds():
    """tf* = 2 sqrt(d / g) at a vertex (both levels on their bounds, the switch and tf fixed
    by the terminal equalities): dtf*/dd = 1 / sqrt(d g), dtf*/dg = -sqrt(d) / g^1.5, and
    dtf*/dd = -lambda_position."""
    d, g = 1.5, 0.8
    args = dict(MT.args)
    tf, grad = MT_GRAD(args)
    assert rel_err(tf, 2 * np.sqrt(d / g)) < 1e-9
    assert rel_err(grad["d"], 1 / np.sqrt(d * g)) < 1e-7
    assert rel_err(grad["g"], -np.sqrt(d) / g**1.5) < 1e-7
    sol = jt.solve(MT, MT_CONTROL, MT_START, simulator=SIM)
    report = jt.kkt_report(MT, MT_CONTROL, sol.params, simulator=SIM)
    assert rel_err(grad["d"], -report.multipliers["position"]) < 1e-7

    # the bounds' arrays: accelerating at g U and braking at g B, tf = sqrt(2 d (1/(g U) + 1/(g B)))
    def tf_in_bounds(lower, upper):
        prob = eqx.tree_at(lambda p: (p.control_lower, p.control_upper), MT, (lower, upper))
        return jt.solve(prob, MT_CONTROL, MT_START, simulator=SIM).tf

    d_lower, d_upper = jax.grad(tf_in_bounds, argnums=(0, 1))(MT.control_lower, MT.control_upper)
    assert rel_err(d_upper, -d / (g * tf)) < 1e-7 and rel_err(d_lower, d / (g * tf)) < 1e-7


@pytest.mark.slow
def test_an_active_terminal_inequality():
    """Reach x(tf) >= d (a terminal inequality) with |u| <= 1, velocity free: u = 1 on both
    pieces, tf* = sqrt(2 d / g), its derivatives in d and g through the active inequality
    and bound rows."""
    d, g = 1.5, 0.8
    prob, ctrl, start = reach_problem(d, g)

    def tf(args):
        return jt.solve(eqx.tree_at(lambda p: p.args, prob, args), ctrl, start, simulator=SIM).tf

    value, grad = jax.jit(jax.value_and_grad(tf))(dict(prob.args))
    assert rel_err(value, np.sqrt(2 * d / g)) < 1e-9
    assert rel_err(grad["d"], 1 / np.sqrt(2 * d * g)) < 1e-7
    assert rel_err(grad["g"], -0.5 * np.sqrt(2 * d) / g**1.5) < 1e-7


@pytest.mark.slow
def test_forward_and_reverse_modes_agree():
    """jax.jacfwd and jax.jacrev (under jit) give the same Jacobian of the objective and the
    parameters; jax.grad and jax.jvp without jit give its row and column."""
    theta = jnp.array([1.0, 0.5])

    def objective_and_params(target):
        sol = lq_solve({**LQ_THETA, "target": target})
        return sol.objective, sol.params

    fwd = jax.jit(jax.jacfwd(objective_and_params))(theta)
    rev = jax.jit(jax.jacrev(objective_and_params))(theta)
    assert rel_err(rev[0], fwd[0]) < 1e-10 and rel_err(rev[1], fwd[1]) < 1e-10
    objective = lambda target: objective_and_params(target)[0]
    assert rel_err(jax.grad(objective)(theta), fwd[0]) < 1e-10
    assert rel_err(jax.jvp(objective, (theta,), (jnp.array([0.0, 1.0]),))[1], fwd[0][1]) < 1e-10


def test_multipliers_and_their_derivatives_in_closed_form():
    """`sol.multipliers` of the restricted LQ problem are -dJ*/d(target) = -w h M^-1 r
    (NumPy's linear algebra), and their Jacobians in the target, the initial state and the
    weight (forward and reverse mode) are -w h M^-1, w h M^-1 coast and -h M^-1 r."""
    sol = lq_solve(LQ_THETA)
    _, _, _, M, r = lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, LQ_T)
    h, Minv = LQ_T / LQ_K, np.linalg.inv(np.asarray(M))
    coast = np.array([[1.0, LQ_T], [0.0, 1.0]])
    assert rel_err(sol.multipliers, -2.0 * h * Minv @ r) < 1e-9
    multipliers = lambda theta: lq_solve(theta).multipliers
    for jac in (jax.jacfwd(multipliers)(LQ_THETA), jax.jacrev(multipliers)(LQ_THETA)):
        assert rel_err(jac["target"], -2.0 * h * Minv) < 1e-8
        assert rel_err(jac["x0"], 2.0 * h * Minv @ coast) < 1e-8
        assert rel_err(jac["w"], -h * Minv @ r) < 1e-8


@pytest.mark.slow
def test_multipliers_of_bounds_and_a_terminal_inequality_in_closed_form():
    """The minimum time to rest at d with |u| <= 1 (a vertex: both levels on their bounds):
    lambda_position = -dtf*/dd = -1 / sqrt(d g), its derivatives 1/2 d^-3/2 g^-1/2 and
    1/2 d^-1/2 g^-3/2; reaching x(tf) >= d (an active terminal inequality, velocity free):
    nu = dtf*/dd = 1 / sqrt(2 d g) = `sol.terminal_inequality_multipliers`, its derivatives
    -g (2 d g)^-3/2 and -d (2 d g)^-3/2."""
    d, g = 1.5, 0.8
    args = dict(MT.args)
    solve = lambda args: jt.solve(eqx.tree_at(lambda p: p.args, MT, args), MT_CONTROL, MT_START, simulator=SIM)
    assert rel_err(solve(args).multipliers[0], -1 / np.sqrt(d * g)) < 1e-9
    jac = jax.jacfwd(lambda args: solve(args).multipliers[0])(args)
    assert rel_err(jac["d"], 0.5 * d**-1.5 * g**-0.5) < 1e-7
    assert rel_err(jac["g"], 0.5 * d**-0.5 * g**-1.5) < 1e-7

    prob, ctrl, start = reach_problem(d, g)
    reach = lambda args: jt.solve(eqx.tree_at(lambda p: p.args, prob, args), ctrl, start, simulator=SIM)
    sol = reach(args)
    assert sol.multipliers.shape == (0,) and rel_err(sol.terminal_inequality_multipliers, 1 / np.sqrt(2 * d * g)) < 1e-9
    report = jt.kkt_report(prob, ctrl, sol.params, simulator=SIM)
    assert rel_err(sol.terminal_inequality_multipliers[0], report.multipliers["reach"]) < 1e-12
    grad = jax.grad(lambda args: reach(args).terminal_inequality_multipliers[0])(args)
    assert rel_err(grad["d"], -g * (2 * d * g) ** -1.5) < 1e-7
    assert rel_err(grad["g"], -d * (2 * d * g) ** -1.5) < 1e-7


@pytest.mark.slow
def test_an_active_final_time_bound_is_differentiable():
    """The LQ problem with a free final time bounded by `tf_bounds=(0.5, T)`: the energy falls
    as tf grows, so tf* = T and J*(T) is the fixed-time problem's (NumPy's linear algebra);
    dJ*/dT through the bound's array against central differences of that, and the bound's
    multiplier nu = -dJ*/dT. One compiled solve takes other bound values (vmap)."""
    prob = jt.Problem(
        _double_integrator,
        LQ_X0,
        _on_target,
        ("position", "velocity"),
        running_cost=_energy,
        args=LQ_ARGS,
        tf_bounds=(0.5, LQ_T),
    )
    ctrl = jt.controls.PiecewiseConstant(LQ_K, free_times=False)
    start = ctrl.initial_guess(1.5, 0.0, 0.0)

    def solve(T):
        return jt.solve(eqx.tree_at(lambda p: p.tf_bounds[1], prob, T), ctrl, start, simulator=SIM)

    reference = lambda T: lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, T)[0]
    step = 1e-5
    fd = (reference(LQ_T + step) - reference(LQ_T - step)) / (2 * step)
    sol = solve(jnp.asarray(LQ_T))
    assert sol.status == jt.Status.SUCCESS and rel_err(sol.objective, reference(LQ_T)) < 1e-9 and fd < 0
    assert rel_err(jax.grad(lambda T: solve(T).objective)(jnp.asarray(LQ_T)), fd) < 1e-6
    assert rel_err(sol.terminal_inequality_multipliers[-1], -fd) < 1e-6
    objectives = jax.vmap(lambda T: solve(T).objective)(jnp.array([1.5, 2.5]))
    assert rel_err(objectives, np.array([reference(1.5), reference(2.5)])) < 1e-9


@pytest.mark.slow
def test_vmap_of_gradients_is_one_program_and_equals_a_loop():
    """jax.vmap over a batch of targets gives the gradients of a loop of solves; once
    compiled, a new batch of the same size compiles nothing."""
    grad = jax.jit(jax.vmap(jax.grad(min_time)))
    batch = {"d": jnp.array([1.0, 1.5, 2.0]), "g": jnp.array([0.8, 1.0, 1.2])}
    got = grad(batch)
    for i in range(3):
        want = MT_GRAD({k: v[i] for k, v in batch.items()})[1]
        assert rel_err(got["d"][i], want["d"]) < 1e-10 and rel_err(got["g"][i], want["g"]) < 1e-10
        d, g = batch["d"][i], batch["g"][i]
        assert rel_err(got["d"][i], 1 / np.sqrt(d * g)) < 1e-7
    assert str(jax.make_jaxpr(jax.vmap(jax.grad(min_time)))(batch)).count("name=run") == 1  # the solve, once
    with compilations() as names:
        again = grad({"d": jnp.array([1.1, 1.6, 2.1]), "g": jnp.array([0.9, 1.0, 1.1])})
    assert names == []
    assert rel_err(again["d"], 1 / np.sqrt(np.array([1.1, 1.6, 2.1]) * np.array([0.9, 1.0, 1.1]))) < 1e-7


@pytest.mark.slow
def test_unsuccessful_or_singular_solves_give_nan():
    """A solve stopped short (max_steps=1) gives NaN derivatives; so does a SUCCESS whose
    KKT matrix is singular (three pieces for a bang-bang control: where the two equal
    pieces meet is free). NaN survives the transposition of reverse mode."""
    args = dict(MT.args)
    tangent = {"d": jnp.asarray(1.0), "g": jnp.asarray(0.0)}

    short = lambda a: min_time(a, max_steps=1)
    assert np.isnan(jax.jvp(short, (args,), (tangent,))[1])  # forward mode here, reverse below
    three = jt.controls.PiecewiseConstant(3)
    start = three.initial_guess(2.5, 1.0, -1.0)
    sol = jt.solve(MT, three, start, simulator=SIM)
    assert sol.status == jt.Status.SUCCESS and rel_err(sol.tf, 2 * np.sqrt(1.5 / 0.8)) < 1e-9
    grad = jax.grad(lambda a: min_time(a, three, start))(args)
    assert np.all(np.isnan(jax.tree.leaves(grad)))
    point = kkt_point(MT, three, sol, SIM)
    assert not point.curved and not point.differentiable


@pytest.mark.slow
def test_weakly_active_row_is_reported_and_let_go():
    """A bound met exactly at the unconstrained optimum (tf <= tf*, multiplier 0) is weakly
    active: `kkt_point` reports it, so does the Solution's flag (for every solver; and not
    with the bound 10 % looser, nor at the bang-bang vertex whose bound rows all carry
    multipliers), and the derivative is the one-sided one that lets it go (the unbounded
    problem's dtf*/dd = 1 / sqrt(d g))."""
    d, g = 1.5, 0.8
    prob = min_time_problem(d, g, tf_bounds=(0.0, 2 * np.sqrt(d / g)))
    sol = jt.solve(prob, MT_CONTROL, MT_START, simulator=SIM)
    assert sol.status == jt.Status.SUCCESS and bool(sol.weakly_active)
    for solver in (jt.KalmanSearch(), jt.AugmentedLagrangian()):
        other = jt.solve(prob, MT_CONTROL, MT_START, solver, simulator=SIM, max_steps=2000)
        assert other.status == jt.Status.SUCCESS and bool(other.weakly_active), type(solver)
    loose = min_time_problem(d, g, tf_bounds=(0.0, 2.2 * np.sqrt(d / g)))
    assert not bool(jt.solve(loose, MT_CONTROL, MT_START, simulator=SIM).weakly_active)
    assert not bool(jt.solve(MT, MT_CONTROL, MT_START, simulator=SIM).weakly_active)
    point = kkt_point(prob, MT_CONTROL, sol, SIM)
    assert point.differentiable and point.weakly_active[0] and np.sum(point.weakly_active) == 1
    grad = jax.grad(lambda args: min_time(args, problem=prob))(dict(prob.args))
    assert rel_err(grad["d"], 1 / np.sqrt(d * g)) < 1e-7


def test_bound_values_other_than_the_built_ones_are_refused():
    """The solvers take the control bounds' static copy: other values put into the arrays
    (concrete, or traced under vmap) are an error, not a solve at the old bounds; the
    built values themselves pass, traced or not."""

    def tf_in(upper):
        return jt.solve(eqx.tree_at(lambda p: p.control_upper, MT, upper), MT_CONTROL, MT_START, simulator=SIM).tf

    with pytest.raises(ValueError, match=r"`problem`: control_upper \[2\.\] \(built with \[1\.\]\)"):
        tf_in(jnp.array([2.0]))
    with pytest.raises(Exception, match=r"build a jt\.Problem per bound value"):
        jax.vmap(tf_in)(jnp.array([[1.0], [2.0]]))
    same = jax.vmap(tf_in)(jnp.array([[1.0], [1.0]]))
    assert rel_err(same, 2 * np.sqrt(1.5 / 0.8)) < 1e-9


def test_start_has_no_derivative_and_plain_solves_are_unchanged():
    """d(anything)/d(a0) = 0; a solve that is not differentiated returns the driver's result
    bit for bit."""
    from jaxtraj._driver import run

    grad = jax.jit(jax.grad(lambda a0: jt.solve(MT, MT_CONTROL, a0, simulator=SIM).tf))(MT_START)
    assert np.all(grad == 0.0)
    sol = jt.solve(MT, MT_CONTROL, MT_START, simulator=SIM)
    direct = run(jt.KalmanSQP(), MT, MT_CONTROL, MT_START, SIM, 5000, 0)
    assert jax.tree.structure(sol) == jax.tree.structure(direct)
    for got, want in zip(jax.tree.leaves(sol), jax.tree.leaves(direct)):
        np.testing.assert_array_equal(got, want)  # NaN where NaN (the unused history)


@pytest.mark.slow
def test_second_derivatives_forward_over_either_mode():
    """Second derivatives by forward mode over forward or reverse mode (`jax.hessian` is
    `jacfwd(jacrev)`), and reverse over reverse: the restricted LQ optimum J* = 1/2 w h r^T M^-1 r (r = target - C x0)
    has the Hessian w h [M^-1, -M^-1 C; -C^T M^-1, C^T M^-1 C] in (target, x0) and
    d2J*/(dw dtarget) = h M^-1 r (NumPy); the minimum time tf* = 2 sqrt(d / g) its closed-form
    second derivatives at a vertex (bounds active)."""
    J, _, _, M, r = lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, LQ_T)
    h, w = LQ_T / LQ_K, 2.0
    C = np.array([[1.0, LQ_T], [0.0, 1.0]])
    Minv = np.linalg.inv(M)

    def J_of(target, x0, weight):
        return lq_solve(dict(LQ_THETA, target=target, x0=x0, w=weight)).objective

    point = (LQ_ARGS["target"], jnp.asarray(LQ_X0), jnp.asarray(w))
    H = jax.hessian(J_of, argnums=(0, 1, 2))(*point)
    assert rel_err(H[0][0], w * h * Minv) < 1e-7
    assert rel_err(H[0][1], -w * h * Minv @ C) < 1e-7
    assert rel_err(H[1][1], w * h * C.T @ Minv @ C) < 1e-7
    assert rel_err(H[0][2], h * Minv @ r) < 1e-7
    assert abs(float(H[2][2])) < 1e-9 * J  # J* is linear in w
    H_ff = jax.jacfwd(jax.jacfwd(J_of, argnums=0), argnums=0)(*point)
    assert rel_err(H_ff, H[0][0]) < 1e-9

    d, g = 1.5, 0.8

    def tf_of(d, g):
        return min_time({"d": d, "g": g})

    (tdd, tdg), (_, tgg) = jax.hessian(tf_of, argnums=(0, 1))(jnp.asarray(d), jnp.asarray(g))
    assert rel_err(tdd, -0.5 * d**-1.5 * g**-0.5) < 1e-7
    assert rel_err(tdg, -0.5 * d**-0.5 * g**-1.5) < 1e-7
    assert rel_err(tgg, 1.5 * d**0.5 * g**-2.5) < 1e-7
    # reverse over reverse too (the docs said JAX refused it)
    H_rr = jax.jacrev(jax.jacrev(J_of, argnums=0), argnums=0)(*point)
    assert rel_err(H_rr, w * h * Minv) < 1e-7
    assert rel_err(jax.grad(jax.grad(tf_of))(jnp.asarray(d), jnp.asarray(g)), -0.5 * d**-1.5 * g**-0.5) < 1e-7


@pytest.mark.parametrize("field", ["tf", "constraints", "max_constraint_error"])
def test_every_float_field_has_a_derivative(field):
    """tf, the constraints (zero: they stay met) and max |E| (zero) of the LQ problem along
    its final time: the constrained fields' tangents vanish, tf's is 1."""
    T = jnp.asarray(LQ_T)
    tangent = jax.jvp(lambda T: getattr(lq_solve({**LQ_THETA, "T": T}), field), (T,), (jnp.ones(()),))[1]
    want = {"tf": 1.0, "constraints": np.zeros(2), "max_constraint_error": 0.0}[field]
    np.testing.assert_allclose(tangent, want, atol=1e-9)


BD = jt.problems.classic.get("bryson-denham")


@pytest.mark.slow
@pytest.mark.parametrize("bound", [1.0 / 9.0, 0.2])
def test_state_bound_on_the_grid(bound):
    """Bryson-Denham, x <= l on the integration grid (a path constraint): dJ*/dl against
    central differences of re-solves, for a boundary arc (l = 1/9: also near the closed
    form -4 / (9 l^2) of the unrestricted problem) and a touch point (l = 0.2, at a knot,
    where the grid holds the point twice)."""
    sim = jt.RK4(4)

    def objective(l):
        prob = eqx.tree_at(lambda p: p.path.fn.upper, BD.problem, jnp.reshape(l, (1,)))
        return jt.solve(prob, BD.control, BD.start, simulator=sim).objective

    value_and_grad = jax.jit(jax.value_and_grad(objective))
    J, grad = value_and_grad(jnp.asarray(bound))
    step = 1e-4
    fd = (value_and_grad(bound + step)[0] - value_and_grad(bound - step)[0]) / (2 * step)
    assert rel_err(grad, fd) < 1e-6
    if bound < 1.0 / 6.0:
        assert rel_err(J, 4.0 / (9.0 * bound)) < 2e-3 and rel_err(grad, -4.0 / (9.0 * bound**2)) < 1e-2


def test_what_is_computed_from_the_solution_follows():
    """A trajectory simulated at `sol.params` (`jt.simulate`) gets its derivative: the final
    state meets the target, so dx(T)/d(target) = I, and the accumulated cost's row is
    dJ*/d(target)."""

    def final_state(target):
        theta = {**LQ_THETA, "target": target}
        prob, ctrl = lq_problem(theta)
        return jt.simulate(prob, ctrl, lq_solve(theta).params, simulator=SIM).xf

    jac = jax.jit(jax.jacfwd(final_state))(LQ_ARGS["target"])
    np.testing.assert_allclose(jac[:2], np.eye(2), atol=1e-9)
    _, _, _, M, r = lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, LQ_T)
    assert rel_err(jac[2], 2.0 * (LQ_T / LQ_K) * np.linalg.solve(M, r)) < 1e-7


def test_riccati_lq_in_the_initial_state():
    """The gallery's LQ regulator (min 1/2 int (x^2 + u^2), x(1) free: no constraint at all):
    J* = tanh(1) x0^2 / 2 by Riccati, so dJ*/dx0 = tanh(1) x0; the restricted J* is exactly
    quadratic in x0 too, so its derivative is 2 J* / x0 to round-off."""
    entry = jt.problems.classic.get("lq")
    sim = jt.RK4(10)

    def objective(x0):
        prob = eqx.tree_at(lambda p: p.x0, entry.problem, jnp.stack([x0, 0.0]))
        return jt.solve(prob, entry.control, entry.start, simulator=sim).objective

    J, grad = jax.jit(jax.value_and_grad(objective))(jnp.asarray(1.3))
    assert rel_err(grad, 2.0 * J / 1.3) < 1e-8
    assert rel_err(grad, np.tanh(1.0) * 1.3) < 1e-5


@pytest.mark.slow
def test_earth_mars_against_re_solves():
    """Earth-Mars case 4: dtf*/d(thrust acceleration) and dtf*/d(target radius) against
    central differences of re-solves warm-started at the optimum (issue 50's acceptance)."""
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    start = jt.solve(prob, ctrl, a0).params

    def tf(args):
        return jt.solve(eqx.tree_at(lambda p: p.args, prob, args), ctrl, start).tf

    value_and_grad = jax.jit(jax.value_and_grad(tf))
    _, grad = value_and_grad(dict(prob.args))
    for name in ("thrust", "rf"):
        step = 1e-5 * float(prob.args[name])
        up, down = dict(prob.args), dict(prob.args)
        up[name], down[name] = prob.args[name] + step, prob.args[name] - step
        fd = (value_and_grad(up)[0] - value_and_grad(down)[0]) / (2 * step)
        assert rel_err(grad[name], fd) < 1e-6


@pytest.mark.slow  # 13 s of CPU, mostly compiling diffrax's loops
def test_adaptive_diffrax_simulation_in_both_modes():
    """With a diffrax simulator (adaptive steps in while loops, which reverse mode cannot
    transpose) the tangent goes through explicit Jacobians: jax.grad and jax.jvp both give
    the minimum-energy transfer's dJ*/dT = -18 / T^4 (J* = 6 / T^3, the final time T an
    equality target in `args`)."""
    base = jt.problems.analytic.min_energy_double_integrator(1.0)
    ctrl = jt.controls.PiecewiseLinear(3)
    sim = jt.Diffrax(dense_points=3)

    def objective(T):
        prob = eqx.tree_at(lambda p: p.args["tf"], base, T)
        return jt.solve(prob, ctrl, ctrl.initial_guess(1.0, 0.0, 0.0), simulator=sim).objective

    T = jnp.asarray(1.0)
    assert rel_err(jax.grad(objective)(T), -18.0) < 1e-8
    assert rel_err(jax.jvp(objective, (T,), (jnp.ones(()),))[1], -18.0) < 1e-8


@pytest.mark.slow
def test_solar_sail_minimum_time_in_the_characteristic_acceleration():
    """Kelley's sail transfer to Mars' orbit (the pitch bounds left out, as in
    test_solar_sail; PiecewiseLinear(6), RK4(20)): dtf*/da0 (a0 the characteristic
    acceleration, in `args`) against central differences of re-solves warm-started at the
    optimum (measured 3e-9 relative)."""
    import jaxtraj.problems.solar_sail as ss

    sail = ss.problem("mars", ss.KELLEY_A0, r_f=ss.KELLEY_RF)
    prob = jt.Problem(sail.dynamics, sail.x0, sail.terminal, sail.constraint_names, args=sail.args, name="unbounded")
    ctrl = jt.controls.PiecewiseLinear(6)
    alpha = np.radians(35.0)
    sim = jt.RK4(20)

    def tf(a0, start):
        sol = jt.solve(eqx.tree_at(lambda p: p.args["a0"], prob, a0), ctrl, start, simulator=sim, max_steps=300)
        return sol.tf, (sol.params, sol.status)

    value_and_grad = jax.jit(jax.value_and_grad(tf, has_aux=True))
    a0 = prob.args["a0"]
    (_, (start, status)), _ = value_and_grad(a0, ctrl.initial_guess(7.0, alpha, alpha))
    assert status == jt.Status.SUCCESS
    (_, (_, status)), grad = value_and_grad(a0, start)
    assert status == jt.Status.SUCCESS and grad < 0.0  # a stronger sail arrives sooner
    step = 1e-5 * float(a0)
    up, down = value_and_grad(a0 + step, start)[0], value_and_grad(a0 - step, start)[0]
    assert up[1][1] == jt.Status.SUCCESS and down[1][1] == jt.Status.SUCCESS
    assert rel_err(grad, (up[0] - down[0]) / (2 * step)) < 1e-6


@pytest.mark.slow
def test_solar_sail_derivative_approaches_the_indirect_solutions():
    """dtf*/da0 of the restricted sail transfer (PiecewiseLinear(12), 6.9946 against the
    unrestricted 6.9925) against central differences of the indirect (Pontryagin) solution,
    NumPy and SciPy only: the restricted problem's derivative is within its restriction
    error of the continuous one (measured 1.6e-3 relative)."""
    import jaxtraj.problems.solar_sail as ss

    sail = ss.problem("mars", ss.KELLEY_A0, r_f=ss.KELLEY_RF)
    prob = jt.Problem(sail.dynamics, sail.x0, sail.terminal, sail.constraint_names, args=sail.args, name="unbounded")
    ctrl = jt.controls.PiecewiseLinear(12)
    start = ctrl.initial_guess(7.0, np.radians(35.0), np.radians(35.0))

    def tf(a0):
        sol = jt.solve(eqx.tree_at(lambda p: p.args["a0"], prob, a0), ctrl, start, simulator=jt.RK4(20), max_steps=300)
        return sol.tf, sol.status

    (value, status), grad = jax.value_and_grad(tf, has_aux=True)(prob.args["a0"])
    assert status == jt.Status.SUCCESS and rel_err(value, ss.TF_KELLEY_INDIRECT) < 1e-3
    a0 = float(prob.args["a0"])
    step = 1e-5 * a0
    up, down = (ss.solve_indirect("mars", a0 + s, r_f=ss.KELLEY_RF) for s in (step, -step))
    assert up.success and down.success
    assert rel_err(grad, (up.tf - down.tf) / (2 * step)) < 5e-3


@pytest.mark.slow  # 16 s of CPU, mostly compiling
def test_attitude_slew_in_the_keep_out_half_angle():
    """The minimum-energy slew with the sun keep-out cone active (KalmanSQP, 8 segments,
    RK4(20)): dJ*/d(cone half-angle) against central differences of warm-started re-solves
    (measured 3e-9 relative). The half-angle enters through the array
    `args["cos_cone_enforced"]` = cos(half-angle + backoff)."""
    from jaxtraj.problems import attitude

    prob, ctrl, a0 = attitude.case("quaternion", 8)
    sim = jt.RK4(20)
    backoff = 1e-3  # the default `cone_backoff_deg`

    def energy(deg, start):
        cos_cone = jnp.cos(jnp.deg2rad(deg + backoff))
        p = eqx.tree_at(lambda p: p.args["cos_cone_enforced"], prob, cos_cone)
        sol = jt.solve(p, ctrl, start, simulator=sim, max_steps=600)
        return sol.objective, (sol.params, sol.status)

    value_and_grad = jax.jit(jax.value_and_grad(energy, has_aux=True))
    deg = jnp.asarray(50.0)
    (_, (start, status)), _ = value_and_grad(deg, a0)
    assert status == jt.Status.SUCCESS
    (J, (_, status)), grad = value_and_grad(deg, start)
    assert status == jt.Status.SUCCESS and rel_err(J, 2.2652046) < 1e-7
    assert grad > 0.0  # a wider cone costs energy
    step = 1e-3
    up, down = value_and_grad(deg + step, start)[0], value_and_grad(deg - step, start)[0]
    assert up[1][1] == jt.Status.SUCCESS and down[1][1] == jt.Status.SUCCESS
    assert rel_err(grad, (up[0] - down[0]) / (2 * step)) < 1e-6


@pytest.mark.slow
def test_a_boundary_arc_has_derivatives_where_its_rows_move_together():
    """x'' = u from rest to x(1) = 1 at least energy with v <= b + q t + c t^3 (b = 1.2, q = c
    = 0): the speed meets the bound at t = 0.5 and rides it, so the path rows of ten grid
    points are active and dependent (rank 6 with the equality, 7 parameters): the KKT matrix is
    singular and every derivative was NaN. The rows keep a solution as b or q moves (the arc
    follows a constant or a ramp, which the linear pieces hold) and, linear in the parameters,
    curve alike whatever the multipliers: the parameters' and the objective's derivatives in b
    and q equal central differences of re-solves, d2J/db2 too (forward over reverse and
    reverse over reverse). Along c (a cubic that no linear piece can ride) some rows leave:
    the one-sided differences differ by 1e-2, and the derivative is NaN. The multipliers of
    dependent rows are not unique: their tangents NaN."""
    problem = jt.Problem(
        lambda t, x, u, args: jnp.stack([x[1], u[0]]), np.zeros(2), lambda tf, xf, args: xf[:1] - 1.0, ("x(1)=1",),
        running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0, args={"b": 1.2, "q": 0.0, "c": 0.0},
        path=lambda t, x, u, args: jnp.stack([x[1] - args["b"] - args["q"] * t - args["c"] * t**3]),
        path_names=("v <= b + q t + c t^3",),
    )  # fmt: skip
    control = problem.parametrize(jt.controls.PiecewiseLinear(6))
    sim = jt.RK4(5)
    base = {"b": 1.2, "q": 0.0, "c": 0.0}

    def solve(key, value):
        prob = eqx.tree_at(lambda p: p.args, problem, {**base, key: value})
        return jt.solve(prob, control, np.zeros(control.num_params), simulator=sim)

    sol = solve("b", 1.2)
    assert sol.status == jt.Status.SUCCESS and abs(float(sol.objective) - 1.92) < 1e-12
    k = kkt_point(problem, control, sol, sim)
    assert not bool(k.independent) and int(jnp.sum(k.active)) >= 10
    h = 1e-6
    for key in ("b", "q"):
        x = jnp.asarray(base[key])
        da = jax.jacfwd(lambda v, key=key: solve(key, v).params)(x)
        fd = (solve(key, base[key] + h).params - solve(key, base[key] - h).params) / (2 * h)
        assert rel_err(da, fd) < 1e-6, key
        dJ = jax.grad(lambda v, key=key: solve(key, v).objective)(x)
        dJ_fd = (solve(key, base[key] + h).objective - solve(key, base[key] - h).objective) / (2 * h)
        assert rel_err(dJ, dJ_fd) < 1e-6, key
    grad = jax.grad(lambda b: solve("b", b).objective)
    d2_fd = (grad(1.2 + 1e-5) - grad(1.2 - 1e-5)) / 2e-5
    assert rel_err(jax.hessian(lambda b: solve("b", b).objective)(1.2), d2_fd) < 1e-6
    assert rel_err(jax.grad(grad)(1.2), d2_fd) < 1e-6
    assert np.all(np.isnan(jax.jacfwd(lambda c: solve("c", c).params)(0.0)))
    assert np.all(np.isnan(jax.jacfwd(lambda b: solve("b", b).multipliers)(1.2)))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 6, 9, 18])
def test_random_qp_against_the_oracle(seed):
    """Random convex problems of benchmarks/fuzz.py (3 states, 2 controls, 4 pieces; seed 2:
    2 terminal equalities, 6 control-bound rows active; 6: 1 equality, a state bound on the
    grid, 5 bound rows active; 9: tf a parameter fixed by an equality; 18: an active terminal
    inequality): d(objective*)/d(target) and d(objective*)/d(xe) from jax.grad through
    jt.solve against central differences of the QP optimum by Clarabel (cvxpy), re-solved
    with the perturbed data (measured <= 2e-11 relative: on a fixed active set the optimal
    value is quadratic in the data, so central differences are exact but for the QP
    solver's round-off). (Seed 19: the next test.)"""
    import dataclasses

    fuzz = load_benchmark("fuzz")
    rp = fuzz.make(seed, 3, 2, 4)
    prob, ctrl = rp.problem, rp.control
    start = jnp.asarray(rp.starts(np.random.default_rng(0))["zeros"])

    def objective(target, xe):
        p = eqx.tree_at(lambda p: (p.args["target"], p.args["xe"]), prob, (target, xe))
        sol = jt.solve(p, ctrl, start, simulator=jt.RK4(fuzz.STEPS))
        return sol.objective, sol.status

    (J, status), grad = jax.value_and_grad(objective, argnums=(0, 1), has_aux=True)(
        prob.args["target"], prob.args["xe"]
    )
    assert status == jt.Status.SUCCESS and rel_err(J, rp.oracle()[0]) < 1e-9
    step = 1e-4
    for name, got in zip(("target", "xe"), grad):
        fd = np.zeros(rp.args[name].shape)
        for i in range(fd.size):
            e = step * np.eye(fd.size)[i]
            up = dataclasses.replace(rp, args={**rp.args, name: rp.args[name] + e}).oracle()[0]
            down = dataclasses.replace(rp, args={**rp.args, name: rp.args[name] - e}).oracle()[0]
            fd[i] = (up - down) / (2 * step)
        assert got.shape == fd.shape and fd.size and rel_err(got, fd) < 1e-5


@pytest.mark.slow
def test_a_bound_and_an_equality_on_one_state_keep_the_derivatives_they_share():
    """Random convex problem 19 of benchmarks/fuzz.py (3 states, 2 controls, 4 pieces) ends
    with a state bound and a terminal equality on the same final state, both active: two
    identical rows, which made every derivative NaN. Along the target of the cost both stay
    active: dJ*/d(target) from jax.grad equals central differences of the QP optimum by
    Clarabel (cvxpy). Along the equality's value xe they cannot both stay (the bound does not
    move): NaN."""
    import dataclasses

    fuzz = load_benchmark("fuzz")
    rp = fuzz.make(19, 3, 2, 4)
    prob, ctrl = rp.problem, rp.control
    start = jnp.asarray(rp.starts(np.random.default_rng(0))["zeros"])

    def objective(target, xe):
        p = eqx.tree_at(lambda p: (p.args["target"], p.args["xe"]), prob, (target, xe))
        return jt.solve(p, ctrl, start, simulator=jt.RK4(fuzz.STEPS)).objective

    target, xe = prob.args["target"], prob.args["xe"]
    got = jax.grad(objective, argnums=0)(target, xe)
    fd = np.zeros(rp.args["target"].shape)
    for i in range(fd.size):
        e = 1e-4 * np.eye(fd.size)[i]
        up = dataclasses.replace(rp, args={**rp.args, "target": rp.args["target"] + e}).oracle()[0]
        down = dataclasses.replace(rp, args={**rp.args, "target": rp.args["target"] - e}).oracle()[0]
        fd[i] = (up - down) / 2e-4
    assert rel_err(got, fd) < 1e-5
    assert np.all(np.isnan(jax.grad(objective, argnums=1)(target, xe)))


@pytest.mark.slow
def test_solve_batch_derivatives_are_the_per_start_ones():
    """jt.solve_batch is differentiable the same way, lane by lane (the problem, and its
    tangent, shared): jax.jacfwd and jax.jacrev of the objectives and parameters of 3 starts
    of the LQ problem with respect to all its arrays equal jt.solve's per-start Jacobian (and
    NumPy's dJ*/d(target)); jax.grad of their sum is the sum; a start that fails (a NaN row)
    gets NaN derivatives, the others numbers."""
    starts = jnp.stack([LQ_START, LQ_START + 0.3, LQ_START - 0.5])

    def batch(theta, a0s=starts):
        prob, ctrl = lq_problem(theta)
        sols = jt.solve_batch(prob, ctrl, a0s, simulator=SIM, progress=False, history=False)
        return sols.objective, sols.params

    fwd = jax.jacfwd(batch)(LQ_THETA)
    rev = jax.jacrev(batch)(LQ_THETA)
    one = jax.jit(jax.jacfwd(lambda theta: (lq_solve(theta).objective, lq_solve(theta).params)))(LQ_THETA)
    for name in LQ_THETA:
        for got, back, want in zip((fwd[0][name], fwd[1][name]), (rev[0][name], rev[1][name]), one):
            want = np.broadcast_to(want[name], got.shape)
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(back, got, rtol=1e-10, atol=1e-12)
    _, _, _, M, r = lq_reference(LQ_ARGS["target"], 2.0, LQ_X0, LQ_T)
    assert rel_err(fwd[0]["target"], np.tile(2.0 * (LQ_T / LQ_K) * np.linalg.solve(M, r), (3, 1))) < 1e-7
    grad = jax.grad(lambda theta: jnp.sum(batch(theta)[0]))(LQ_THETA)
    assert all(rel_err(grad[name], 3.0 * one[0][name]) < 1e-10 for name in LQ_THETA)
    failed = starts.at[1].set(jnp.nan)
    grad = jax.jacfwd(lambda target: batch({**LQ_THETA, "target": target}, failed)[0])(LQ_THETA["target"])
    with pytest.raises(ValueError, match=r"outside jax\.jit"):
        jax.jit(batch)(LQ_THETA)
    assert np.all(np.isnan(grad[1])) and rel_err(grad[np.array([0, 2])], fwd[0]["target"][np.array([0, 2])]) < 1e-10


def test_a_python_float_differentiated_as_args_has_its_derivative():
    """x' = k u to x(1) = 1 at least energy: J = 1 / (2 k^2), dJ/dk = -1 / k^3 = -0.125 at
    k = 2. `jax.grad(f)(2.0)` hands the solve's derivative rule a Python float for `args = k`
    (a weakly typed input), which was no inexact array of the problem: the derivative was 0,
    silently, from `jt.solve` and `jt.solve_batch`; a `jnp.float64(2.0)` gave -0.125."""

    def build(k):
        problem = jt.Problem(
            lambda t, x, u, args: args * u, np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",),
            num_controls=1, running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0, args=k,
        )  # fmt: skip
        return problem, problem.parametrize(jt.controls.PiecewiseLinear(4))

    def single(k):
        problem, control = build(k)
        return jt.solve(problem, control, np.zeros(control.num_params), simulator=jt.RK4(5)).objective

    def batch(k):
        problem, control = build(k)
        starts = np.zeros((2, control.num_params))
        sols = jt.solve_batch(problem, control, starts, simulator=jt.RK4(5), progress=False, history=False)
        return jnp.sum(sols.objective)

    assert float(jax.grad(single)(2.0)) == pytest.approx(-0.125, rel=1e-8)
    assert float(jax.jvp(single, (2.0,), (1.0,))[1]) == pytest.approx(-0.125, rel=1e-8)
    assert float(jax.grad(batch)(2.0)) == pytest.approx(-0.25, rel=1e-8)


@pytest.mark.slow
def test_hessian_where_the_parameters_outnumber_the_active_rows_by_two():
    """x' = g u to x(1) = d at least energy on 4 linear pieces (5 parameters, one active row):
    J = d^2 / (2 g^2), against its closed-form Hessian. The tangent computation took the SVD
    of the active rows, whose derivative is infinite at repeated zero singular values (three
    here): `jax.hessian` was NaN. Now pseudo-inverses with Golub and Pereyra's derivative."""
    problem = jt.Problem(
        lambda t, x, u, args: args["g"] * u, np.zeros(1), lambda tf, xf, args: xf - args["d"], ("x(1) = d",),
        running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0,
        args={"g": jnp.asarray(2.0), "d": jnp.asarray(1.0)},
    )  # fmt: skip
    control = problem.parametrize(jt.controls.PiecewiseLinear(4))

    def J(g, d):
        prob = eqx.tree_at(lambda p: p.args, problem, {"g": g, "d": d})
        return jt.solve(prob, control, np.zeros(control.num_params), simulator=SIM).objective

    g, d = 2.0, 1.0
    H = jax.hessian(J, argnums=(0, 1))(jnp.asarray(g), jnp.asarray(d))
    want = [[3 * d**2 / g**4, -2 * d / g**3], [-2 * d / g**3, 1 / g**2]]
    np.testing.assert_allclose(np.array(H), want, rtol=1e-8)


@pytest.mark.slow
def test_hessian_with_inactive_inequality_rows():
    """x' = u to x(tf) = d, min c tf + int u^2 / 2 with tf <= T active (and x <= 10, inactive
    on every grid point): J = d^2 / (2 T) + c T, Hessian [[1 / T, -d / T^2], [-d / T^2,
    d^2 / T^3]] in (d, T). The multipliers' least squares zeroes the columns of the rows
    out of the active set, and its derivative was infinite with two of them: NaN."""
    problem = jt.Problem(
        lambda t, x, u, args: u, np.zeros(1), lambda tf, xf, args: xf - args["d"], ("x = d",),
        running_cost=lambda t, x, u, args: 0.5 * (u @ u), objective=lambda tf, xf, args: args["c"] * tf,
        args={"d": jnp.asarray(1.0), "c": jnp.asarray(0.25)}, tf_bounds=(0.1, 1.0), state_upper=10.0,
    )  # fmt: skip
    control = jt.controls.PiecewiseConstant(2, free_times=False)

    def J(d, T):
        prob = eqx.tree_at(lambda p: (p.args["d"], p.tf_bounds[1]), problem, (d, T))
        return jt.solve(prob, control, control.initial_guess(0.9, 1.0, 1.0), simulator=SIM).objective

    d, T = 1.0, 1.0
    H = jax.hessian(J, argnums=(0, 1))(jnp.asarray(d), jnp.asarray(T))
    np.testing.assert_allclose(np.array(H), [[1 / T, -d / T**2], [-d / T**2, d**2 / T**3]], rtol=1e-8)


def test_a_final_time_changed_in_the_problem_only_is_followed_or_refused():
    """x' = 2 u to x(T) = 1 at least energy: J = 1 / (8 T), dJ/dT = -1/8 at T = 1. A traced
    `problem.final_time` without `problem.parametrize(family)` again (the control keeps its
    own copy, the one the solve reads): `jax.grad` was 0 and `jax.vmap` over T solved every
    T at the control's, silently. Now the control follows the traced one where the values
    agree, and other values are an error."""
    problem, control = gain_reach()

    def objective(T):
        prob = eqx.tree_at(lambda p: p.final_time, problem, T)
        return jt.solve(prob, control, np.zeros(control.num_params), simulator=jt.RK4(5)).objective

    def batch(T):
        prob = eqx.tree_at(lambda p: p.final_time, problem, T)
        starts = np.zeros((1, control.num_params))
        return jt.solve_batch(prob, control, starts, simulator=jt.RK4(5), progress=False, history=False).objective[0]

    assert float(jax.grad(objective)(1.0)) == pytest.approx(-0.125, rel=1e-8)
    assert float(jax.grad(batch)(1.0)) == pytest.approx(-0.125, rel=1e-8)
    differ = r"`problem\.final_time` and the final time of `control` differ"
    with pytest.raises(ValueError, match=differ):
        jax.grad(objective)(2.0)
    with pytest.raises(Exception, match=differ):
        jax.vmap(objective)(jnp.array([1.0, 2.0]))
    with pytest.raises(Exception, match=differ):  # (known at run time only: on the control's final time)
        jax.jit(objective)(2.0)
    # the batch runs on the host: a final time known at run time only is refused up front
    with pytest.raises(ValueError, match=r"solve_batch runs outside jax\.jit and jax\.vmap"):
        jax.vmap(batch)(jnp.array([1.0, 2.0]))
