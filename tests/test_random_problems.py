"""The solvers against an independent oracle on random problems (benchmarks/fuzz.py): linear
dynamics with a quadratic cost and linear constraints, whose restricted problem on the RK4
grid is a convex QP solved by Clarabel (cvxpy). A convex QP has one optimal value, so a
SUCCESS anywhere else is a false SUCCESS; and a textbook minimum-time problem whose optimum
has as many active rows as parameters."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from helpers import LINE_SEARCH, TRUST_REGION, load_benchmark, perturbed_starts, reach_problem

import jaxtraj as jt


def test_oracle_affine_map_is_rk4_and_converges_to_the_matrix_exponential():
    """The oracle's x(tf) = M a + c: with many RK4 steps it tends to the exact solution of the
    linear system (scipy's matrix exponential, segment by segment), with RK4's h^4 rate; and on
    the solver's grid it equals jaxtraj's own evaluation (the two share only the dynamics)."""
    fuzz = load_benchmark("fuzz")
    rp = fuzz.make(3, n=3, m=2, K=3)
    A, B, x0 = rp.args["A"], rp.args["B"], rp.args["x0"]
    a = np.random.default_rng(0).standard_normal(rp.K * rp.m)
    h = rp.T / rp.K
    x = x0.copy()
    for k in range(rp.K):  # exact: x+ = e^{hA} x + A^-1 (e^{hA} - I) B u
        eA = scipy.linalg.expm(h * A)
        x = eA @ x + np.linalg.solve(A, (eA - np.eye(3)) @ B @ a[k * 2 : k * 2 + 2])
    errors = []
    for steps in (8, 16):
        M, c = fuzz.rk4_affine(A, B, x0, rp.T, rp.K, rp.m, steps)
        errors.append(np.max(np.abs(M @ a + c - x)))
    assert errors[1] < 1e-6 and 12.0 < errors[0] / errors[1] < 20.0  # fourth order
    params = np.append(a, rp.T) if rp.tf_equality else a
    ev = jt.evaluate(rp.problem, rp.control, jnp.asarray(params), simulator=jt.RK4(fuzz.STEPS))
    np.testing.assert_allclose(float(ev.G), rp.objective(params), rtol=1e-12)


# Three size classes (a compiled solver is shared by the problems of one class and one
# constraint layout); seeds fixed. benchmarks/fuzz.py --n 1000 runs every size.
CASES = [(seed, 2, 1, 3) for seed in range(4)] + [(seed, 3, 2, 4) for seed in range(4, 8)]
CASES += [(seed, 5, 3, 3) for seed in range(8, 10)]


# the default on every fourth problem of each sample in `make test` (one per size class),
# the rest and the line search in the slow tier (`make test-slow`, run by CI)
SOLVER_SAMPLES = [
    pytest.param(TRUST_REGION, lambda i: i % 4 == 0, id="default-quarter"),
    pytest.param(TRUST_REGION, lambda i: i % 4 != 0, id="default-rest", marks=pytest.mark.slow),
    pytest.param(LINE_SEARCH, lambda i: True, id="line-search", marks=pytest.mark.slow),
]


def _sample(items, pick):
    return [item for i, item in enumerate(items) if pick(i)]


@pytest.mark.parametrize("solver, sample", SOLVER_SAMPLES)
def test_solvers_reach_the_oracle_optimum_of_random_problems(solver, sample):
    """From zeros and from a random start inside the bounds: SUCCESS at the QP's optimal value
    (1e-8 relative) with every constraint met (1e-8), on every problem of the sample."""
    fuzz = load_benchmark("fuzz")
    outcomes = []
    for seed, n, m, K in _sample(CASES, sample):
        rp = fuzz.make(seed, n, m, K)
        reference, _ = rp.oracle()
        for kind, a0 in rp.starts(np.random.default_rng(10_000 + seed)).items():
            outcome, its, err = fuzz.check(rp, solver, a0, reference)
            outcomes.append((seed, kind, outcome, its, err))
    assert all(o[2] == "ok" for o in outcomes), [o for o in outcomes if o[2] != "ok"]


def test_mixed_oracle_model_is_jaxtraj_evaluation():
    """The `lq-mixed` oracle's model (its own numpy RK4 of the affine map through linear
    pieces, free initial states and design parameters; the running cost in closed form) gives
    jaxtraj's objective, terminal rows, and path and state-bound rows at every grid point."""
    fuzz = load_benchmark("fuzz")
    rp = fuzz.make_mixed(59)  # linear pieces, 2 channels, a design parameter, free states, every row kind
    assert rp.family == "linear" and rp.path and rp.state_upper is not None and len(rp.free) == 3
    a = rp.starts(np.random.default_rng(0))["random"]
    ev = jt.evaluate(rp.problem, rp.control, jnp.asarray(a), simulator=jt.RK4(fuzz.STEPS))
    rows = {
        kind: G @ a - h
        for kind, (G, h, _) in zip(("lo", "hi", "x0 lo", "x0 hi", "E", "D", "state", "path"), rp._rows())
    }
    np.testing.assert_allclose(float(ev.G), rp.objective(a), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(ev.E), rows["E"], atol=1e-12)
    np.testing.assert_allclose(np.asarray(ev.D), rows["D"], atol=1e-12)
    np.testing.assert_allclose(np.asarray(ev.C), np.stack([rows["path"], rows["state"]], axis=1), atol=1e-12)


# linear and constant pieces, free initial states, design parameters, path rows on states and
# controls, state bounds (benchmarks/fuzz.py --classes lq-mixed runs many more)
MIXED = [46, 52, 1, 4, 5]


@pytest.mark.parametrize("solver, sample", SOLVER_SAMPLES)
def test_solvers_reach_the_oracle_optimum_of_mixed_problems(solver, sample):
    """Every start of each `lq-mixed` sample problem (zeros, random, the straight line for
    linear pieces): SUCCESS at the QP's optimal value (1e-8 relative) with every constraint
    met (1e-8)."""
    fuzz = load_benchmark("fuzz")
    outcomes = []
    for seed in _sample(MIXED, sample):
        rp = fuzz.make_mixed(seed)
        reference, _ = rp.oracle()
        for kind, a0 in rp.starts(np.random.default_rng(10_000 + seed)).items():
            outcome, its, err = fuzz.check(rp, solver, a0, reference)
            outcomes.append((seed, kind, outcome, its, err))
    assert all(o[2] == "ok" for o in outcomes), [o for o in outcomes if o[2] != "ok"]


@pytest.mark.parametrize("segments", [1, 2, 3])
@pytest.mark.parametrize(
    "solver",
    [TRUST_REGION, pytest.param(jt.KalmanSQP(globalization="line-search"), marks=pytest.mark.slow)],
    ids=["default", "line-search"],
)
def test_minimum_time_reach_with_a_terminal_inequality_at_a_vertex(segments, solver):
    """Issue 49's textbook case: the default STALLED after 2 iterations at tf = 1.5 (the
    merit kept the multiplier of the reach row, strictly inactive at the new point, and
    predicted an increase for the step towards it); the line search at 1.41444 (SUCCESS
    within `path_active` of the vertex, before complementarity was part of the test). From
    every control on its lower bound (x(tf) < 0, the reach unreachable by the linearization
    within the bounds) both ended far off (tf 3.84 STALLED, multipliers 1e97; tf 0.24
    MAX_ITERATIONS) before the elastic step softened violated inequality rows. Now SUCCESS at
    sqrt(2) from the issue's starts, from u = -1 and u = 1, and their round-off
    perturbations, with the exact Hessian and either globalization. (BFGS with the line
    search still ends STALLED from u = -1 with two segments: its penalty stays 0 while a step
    trades the reach for a shorter tf.)"""
    prob = reach_problem()
    ctrl = jt.controls.PiecewiseConstant(segments)
    for tf, u in ((2.0, 0.5), (2.0, 0.0), (3.0, -1.0), (1.0, 1.0)):
        for a0 in perturbed_starts(ctrl.initial_guess(tf, u, u), absolute=True):
            sol = jt.solve(prob, ctrl, a0, solver=solver)
            assert jt.status_name(sol.status) == "SUCCESS", (u, a0)
            assert abs(float(sol.tf) - np.sqrt(2.0)) <= 1e-8 * np.sqrt(2.0), (u, float(sol.tf))


@pytest.mark.parametrize("seed", [1080, pytest.param(1106, marks=pytest.mark.slow)])
def test_minimum_time_with_a_reach_row_that_the_terminal_equalities_imply(seed):
    """Random least-time problems (`fuzz.make_min_time`) whose terminal equalities fix every
    state, so that their half-space rows are met exactly where the equalities are: a
    degenerate vertex, one active row more than the parameters. The default ended STALLED
    3.7e-7 and 1.1e-6 below the least time, stationary to 1e-15 with a violation of 3.6e-5
    left: the implied row entered the dual active set on round-off (rho of 1e-13 dropped a
    bound from the full working set), the refiltered step went 0.6 past that bound, and the
    elastic step raised the violation (`dual_active_set(pinned=)`). Now every start ends
    SUCCESS at the oracle's least time (HiGHS LPs and bisection)."""
    fuzz = load_benchmark("fuzz")
    rp = fuzz.make_min_time(seed)
    assert rp.args["Pe"].shape[0] == rp.n and rp.args["Ci"].shape[0] >= 1
    reference, _ = rp.oracle()
    outcomes = [
        (kind, *fuzz.check(rp, TRUST_REGION, a0, reference))
        for kind, a0 in rp.starts(np.random.default_rng(10_000 + seed)).items()
    ]
    assert all(o[1] == "ok" for o in outcomes), outcomes


@pytest.mark.parametrize("seed", [1198, pytest.param(1211, marks=pytest.mark.slow)])
def test_minimum_time_whose_met_half_space_held_the_elastic_step(seed):
    """Random least-time problems where the first step runs tf far below the least time and a
    half-space row, met at its bound, then holds the elastic step (E soft, the rows hard):
    |E|^2 is stationary there with that row hard, but crossing the row costs the violation
    only (C + C_a d)^2, so the point is no stationary point of the violation. The default
    ended CONSTRAINT_STATIONARY at tf 0.056 (least 0.769; zeros and random starts of 1198) and
    1.70 (least 0.80; 1211's random start). Now a third QP round softens the rows that held
    the elastic step, and the infeasibility test lets only the parameter rows hold a point:
    those starts end SUCCESS at the oracle's least time (HiGHS LPs and bisection), the others
    there or at a local minimum (1198's outside start: tf 0.15 above, as before; an LP finds
    no shorter time in its window)."""
    fuzz = load_benchmark("fuzz")
    rp = fuzz.make_min_time(seed)
    reference, _ = rp.oracle()
    outcomes = {
        kind: fuzz.check(rp, TRUST_REGION, a0, reference)[0]
        for kind, a0 in rp.starts(np.random.default_rng(10_000 + seed)).items()
    }
    assert outcomes["random"] == "ok" and outcomes["zeros" if seed == 1198 else "random"] == "ok", outcomes
    assert set(outcomes.values()) <= {"ok", "local minimum"}, outcomes


def test_minimum_time_whose_penalty_was_set_far_from_feasibility_does_not_crawl():
    """Random least-time problem 1407 from its random start: far from feasibility (violation
    80) the exact Hessian and with it the penalty's natural scale grew to 1e33; the penalty was
    capped at 1e18 where the violation reached 2.5e-30, and no later cap could follow, since a
    violation at round-off never halves again. With the penalty 1e18 times the Hessian's new
    scale, every fresh step failed on its 1e-17 linearization error and the correction saved
    steps of 3e-5 in tf: MAX_ITERATIONS 0.3 % above the least time. A violation below one
    row's at `ctol` now counts as halved: SUCCESS at the oracle's least time (HiGHS LPs and
    bisection) in a few dozen steps."""
    fuzz = load_benchmark("fuzz")
    rp = fuzz.make_min_time(1407)
    reference, _ = rp.oracle()
    a0 = rp.starts(np.random.default_rng(10_000 + 1407))["random"]
    outcome, iterations, _ = fuzz.check(rp, TRUST_REGION, a0, reference)
    assert outcome == "ok" and iterations <= 60, (outcome, iterations)


def test_a_met_terminal_row_does_not_hold_an_infeasible_point():
    """The old stop of least-time problem 1198 (level on its upper bound, tf = 0.0556, the
    equality violated by 0.434, half-space 1 met at its bound): the violation |E| + max(D, 0)
    falls along tf (the direct evaluation of the oracle's affine map), so the point is not
    locally infeasible; with the half-space's row declared a parameter bound instead (hard
    for every solver) the same gradient is held and it is."""
    from jaxtraj._kkt import locally_infeasible
    from jaxtraj._sensitivity import evaluate_jitted

    fuzz = load_benchmark("fuzz")
    rp = fuzz.make_min_time(1198)
    a = np.array([rp.upper[0], 0.05555109947524627])

    def violation(a):
        M, c = fuzz.rk4_affine(rp.args["A"], rp.args["B"], rp.args["x0"], a[-1], rp.K, rp.m)
        xf = M @ a[:-1] + c
        D = rp.args["Ci"] @ xf - rp.args["di"]
        return np.sum(np.abs(rp.args["Pe"] @ xf - rp.args["xe"])) + np.sum(np.maximum(D, 0.0)), D

    v0, D = violation(a)
    assert abs(D[1]) < 1e-9 and D[0] < -0.5  # the half-space met at its bound
    assert violation(a + np.array([0.0, 1e-3]))[0] < v0 - 1e-4  # through it: less violation
    ev = evaluate_jitted(rp.problem, rp.control, jnp.asarray(a), jt.RK4(fuzz.STEPS))
    assert not bool(locally_infeasible(ev, 1e-6, 1e-6))
    # the same row as a parameter row (V) holds the point: the test itself can say "infeasible"
    held = eqx.tree_at(
        lambda e: (e.V, e.V_a, e.D, e.D_a),
        ev,
        (jnp.concatenate([ev.V, ev.D[1:]]), jnp.concatenate([ev.V_a, ev.D_a[1:]]), ev.D[:1], ev.D_a[:1]),
    )
    assert bool(locally_infeasible(held, 1e-6, 1e-6))


@pytest.mark.parametrize(
    "argv, named",
    [
        (["--n", "0"], "--n"),
        (["--n", "-1"], "--n"),
        (["--seed", "-5"], "--seed"),
        (["--solvers"], "--solvers"),
        (["--classes"], "--classes"),
        (["--classes", "nope"], "--classes"),
    ],
)
def test_fuzz_command_line_refuses_a_bad_argument_in_one_line_naming_it(argv, named, capsys):
    """No traceback (a negative seed reached NumPy) and no silent empty run (no problems, no
    solvers, no classes): argparse's one-line error, exit status 2."""
    fuzz = load_benchmark("fuzz")
    with pytest.raises(SystemExit) as exit_:
        fuzz.main(argv)
    assert exit_.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert f": error: argument {named}:" in last


def test_fuzz_command_line_runs_a_class_or_solver_named_twice_once():
    """`--solvers default default` solved each start twice into one table row (twice the
    problems the run had)."""
    fuzz = load_benchmark("fuzz")
    args = fuzz.parse_args(["--classes", "lq", "lq", "--solvers", "default", "line-search", "default"])
    assert args.classes == ["lq"] and args.solvers == ["default", "line-search"]
    assert fuzz.parse_args([]).solvers == ["default"] and fuzz.parse_args([]).n == 100
