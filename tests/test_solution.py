"""Batched Solutions: per-start access (`sols[i]`, iteration, masks) and status names;
problem names do not take part in compilation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from tests.helpers import counting_problem, reach_problem

SOLVER = jt.KalmanSearch()  # quick to compile


@pytest.fixture(scope="module")
def batch():
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl = jt.controls.PiecewiseLinear(3)
    a0 = jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0))
    a0s = jnp.stack([a0, a0 + 0.05, a0.at[1].set(jnp.nan)])  # the last start cannot be simulated
    sols = jax.vmap(lambda a: jt.solve(prob, ctrl, a, SOLVER, max_steps=300))(a0s)
    singles = [jt.solve(prob, ctrl, a, SOLVER, max_steps=300) for a in a0s[:2]]
    return sols, singles


A_STAR = np.array([6.0, 2.0, -2.0, -6.0, 1.0])  # u = 6 - 12 t at the nodes t = 0, 1/3, 2/3, 1; tf = 1


def _distance_bound(sol):
    """What KalmanSearch's SUCCESS guarantees on this convex quadratic problem: max |E| <=
    e_a and projected gradient pg <= max(gtol, e_a) (1 + |G|) (checked here), hence
    |a - a*| <= pg / lambda_min(Z^T M Z) + (E's share), with M = d2G/du2 the P1 mass matrix
    of the three segments (exact: G = 1/2 int u^2) and Z the null space of H (the
    constraints are linear in a; tf is fixed by its own row). pg is measured in the scale
    D = max(|a_i|, 1) >= 1: a - a* = D w with w in the null space of H D, and the projection
    of the scaled gradient D M D w on it is at least (D w)^T M (D w) / |w| >= lambda_min
    |D w|^2 / |D w| long, so the bound holds as for D = 1."""
    claimed = max(SOLVER.gtol, SOLVER.e_a) * (1.0 + abs(float(sol.objective)))
    assert float(sol.max_constraint_error) <= SOLVER.e_a and float(sol.projected_gradient) <= claimed
    h = 1.0 / 3.0
    M = np.zeros((5, 5))
    M[:4, :4] = h / 6.0 * np.array([[2, 1, 0, 0], [1, 4, 1, 0], [0, 1, 4, 1], [0, 0, 1, 2]])
    H = np.asarray(
        jt.evaluate(
            jt.problems.analytic.min_energy_double_integrator(), jt.controls.PiecewiseLinear(3), jnp.asarray(A_STAR)
        ).H
    )
    Z = np.linalg.svd(H)[2][H.shape[0] :].T
    lam_min = np.linalg.eigvalsh(Z.T @ M @ Z)[0]
    sigma_min = np.linalg.svd(H, compute_uv=False)[-1]
    return float(sol.projected_gradient) / lam_min + np.sqrt(3) * SOLVER.e_a / sigma_min


def test_status_name_of_batched_and_single_statuses(batch):
    sols, singles = batch
    names = jt.status_name(sols.status)
    assert isinstance(names, np.ndarray) and names.shape == (3,)
    assert names.tolist() == ["SUCCESS", "SUCCESS", "NONFINITE"]
    np.testing.assert_array_equal(names == "SUCCESS", np.asarray(sols.status == jt.Status.SUCCESS))
    assert jt.status_name(singles[0].status) == "SUCCESS" and isinstance(jt.status_name(singles[0].status), str)
    every = (
        "SUCCESS",
        "MAX_ITERATIONS",
        "STALLED",
        "NONFINITE",
        "SIMULATION_FAILED",
        "CONSTRAINT_STATIONARY",
        "DIVERGED",
    )
    for name in every:
        assert jt.status_name(getattr(jt.Status, name)) == name
    # iterating the enumeration gives every item once, in declaration order
    assert [jt.status_name(s) for s in jt.Status] == list(every) and len(list(jt.Status)) == len(jt.Status)
    assert jt.Status[list(jt.Status)[2]] == "The search could not make progress (repeated rejected steps)."
    with pytest.raises(ValueError, match="Status"):
        jt.status_name(0)
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda s: jt.status_name(s))(singles[0].status)


def test_indexing_a_batched_solution(batch):
    sols, singles = batch
    for i, single in enumerate(singles):
        s = sols[i]
        assert isinstance(s, jt.Solution) and jt.status_name(s.status) == "SUCCESS"
        assert s.params.shape == single.params.shape and s.history.objective.shape == single.history.objective.shape
        # the same as the tree.map idiom, and the same numbers as the unbatched solve
        ref = jax.tree.map(lambda x, i=i: x[i], sols)
        assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b, equal_nan=True)), s, ref))
        # vmapped and single solves are not bitwise equal (XLA compiles the batched program
        # differently): both meet KalmanSearch's SUCCESS guarantee, so both lie within the
        # distance that guarantee allows from the analytic optimum, hence from each other
        bounds = [_distance_bound(x) for x in (s, single)]
        for x, bound in zip((s, single), bounds):
            assert np.linalg.norm(np.asarray(x.params) - A_STAR) <= bound
        assert np.linalg.norm(np.asarray(s.params) - np.asarray(single.params)) <= sum(bounds)
    assert jt.status_name(sols[-1].status) == "NONFINITE"
    # slices, index arrays and boolean masks keep a batch
    ok = sols[sols.status == jt.Status.SUCCESS]
    assert ok.tf.shape == (2,) and jt.status_name(ok.status).tolist() == ["SUCCESS", "SUCCESS"]
    assert sols[1:].params.shape == (2, sols.params.shape[1])
    assert jt.status_name(sols[jnp.array([2, 0])].status).tolist() == ["NONFINITE", "SUCCESS"]
    # iteration yields the starts in order
    assert [jt.status_name(s.status) for s in sols] == ["SUCCESS", "SUCCESS", "NONFINITE"]
    with pytest.raises(IndexError, match="out of range"):
        sols[3]
    with pytest.raises(TypeError, match="batched"):
        singles[0][0]
    with pytest.raises(TypeError, match="batched"):
        list(singles[0])
    # inside jit, a traced index works too
    tf = jax.jit(lambda s, i: s[i].tf)(sols, 1)
    assert float(tf) == float(sols.tf[1])


def test_a_batched_status_indexes_like_its_solution(batch):
    sols, singles = batch
    names = ["SUCCESS", "SUCCESS", "NONFINITE"]
    assert [jt.status_name(sols.status[i]) for i in range(3)] == names
    assert [jt.status_name(s) for s in sols.status] == names
    assert jt.status_name(sols.status[-1]) == "NONFINITE" and isinstance(sols.status[0], jt.Status)
    assert bool(sols.status[1] == jt.Status.SUCCESS) and bool(sols.status[2] != jt.Status.SUCCESS)
    mask = sols.status == jt.Status.SUCCESS
    assert jt.status_name(sols.status[mask]).tolist() == ["SUCCESS", "SUCCESS"]
    assert jt.status_name(sols.status[1:]).tolist() == names[1:]
    # the same item as indexing the Solution, also after tree operations and inside jit
    assert bool(sols.status[2] == sols[2].status)
    assert bool(jax.tree.map(lambda x: x[2], sols).status == sols.status[2])
    assert bool(jax.jit(lambda s: s.status[2] == jt.Status.NONFINITE)(sols))
    # a Status works in Status.where as before
    picked = jt.Status.where(jnp.asarray(True), sols.status[2], jt.Status.SUCCESS)
    assert jt.status_name(picked) == "NONFINITE"
    with pytest.raises(IndexError, match="out of range"):
        sols.status[3]
    with pytest.raises(TypeError, match="batched"):
        singles[0].status[0]
    with pytest.raises(TypeError, match="batched"):
        list(singles[0].status)


def test_solve_batch_solution_is_indexable():
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl = jt.controls.PiecewiseLinear(3)
    a0 = jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0))
    sols = jt.solve_batch(prob, ctrl, jnp.stack([a0, a0 + 0.05]), solver=SOLVER, max_steps=300)
    assert [jt.status_name(s.status) for s in sols] == list(jt.status_name(sols.status))
    assert float(sols[1].objective) == float(sols.objective[1])
    assert jt.status_name(sols.status[1]) == jt.status_name(sols[1].status)
    # a batched simulation's status indexes the same way
    trajs = jax.vmap(lambda a: jt.simulate(prob, ctrl, a))(jnp.stack([a0, a0.at[0].set(jnp.nan)]))
    assert [jt.status_name(s) for s in trajs.status] == ["SUCCESS", "NONFINITE"]


def test_problem_name_does_not_recompile():
    base, counter = counting_problem(jt.problems.analytic.min_energy_double_integrator())
    ctrl = jt.controls.PiecewiseLinear(3)
    a0 = jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0))
    probs = [
        jt.Problem(base.dynamics, base.x0, base.terminal, base.constraint_names, args=base.args, name=name)
        for name in ("first", "second")
    ]
    assert [p.name for p in probs] == ["first", "second"]
    counter["traces"] = 0
    jt.simulate(probs[0], ctrl, a0)
    traced = counter["traces"]
    assert traced > 0
    traj = jt.simulate(probs[1], ctrl, a0)
    assert counter["traces"] == traced  # the second name reuses the compiled simulation
    assert traj.x.shape[1] == probs[1].num_states
    # the name survives pytree operations and stays a plain str
    p = jax.tree.map(lambda x: x, probs[1])
    assert p.name == "second" and isinstance(p.name, str)
    with pytest.raises(ValueError, match="name"):
        jt.Problem(base.dynamics, base.x0, base.terminal, base.constraint_names, args=base.args, name=3)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("solver", "details", "start_step"),
    [
        (jt.KalmanSearch(), {"rho", "phase"}, True),
        (jt.KalmanSQP(hessian="bfgs", globalization="line-search"), {"alpha", "kind"}, True),
        (jt.KalmanSQP(), {"radius", "kind"}, True),
        (jt.AugmentedLagrangian(), {"outer_iteration"}, False),
    ],
    ids=["KalmanSearch", "LineSearch", "TrustRegion", "AugmentedLagrangian"],
)
def test_history_fields_mean_the_same_for_every_solver(solver, details, start_step):
    """`step_norm` is the length of the integrated candidate: after one accepted step it is
    |params - a0|; the solver's own quantities are under `details` with its names. A solver
    whose first step evaluates the start (all but AugmentedLagrangian) records it as a step
    of length 0 (`kind` 0)."""
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl = jt.controls.PiecewiseLinear(3)
    a0 = jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0))
    n = 2 if start_step else 1
    sol = jt.solve(prob, ctrl, a0, solver, simulator=jt.RK4(4), max_steps=n)
    h = sol.history
    assert set(h.details) == details and int(sol.steps) == n
    if start_step:
        assert bool(h.accepted[0]) and float(h.step_norm[0]) == 0.0
        if "kind" in h.details:
            assert float(h.details["kind"][0]) == 0.0
    assert bool(h.accepted[n - 1])
    assert float(h.step_norm[n - 1]) == pytest.approx(float(jnp.linalg.norm(sol.params - a0)), rel=1e-12)
    assert float(h.max_constraint_error[n - 1]) == pytest.approx(float(sol.max_constraint_error), rel=1e-12)


UNBOUNDED = jt.Problem(
    lambda t, x, u, args: u,
    x0=[0.0],
    terminal=lambda tf, xf, args: jnp.stack([tf - 1.0]),
    constraint_names=("final time",),
    objective=lambda tf, xf, args: -jnp.exp(xf[0]),
    name="unbounded",
)


@pytest.mark.slow
@pytest.mark.parametrize(
    "solver", [jt.KalmanSQP(), jt.KalmanSearch(), jt.AugmentedLagrangian()], ids=lambda s: type(s).__name__
)
def test_an_unbounded_problem_ends_diverged(solver):
    """x' = u in time 1, minimize -exp(x(1)): unbounded below. Every solver ends DIVERGED
    (|G| past 1e20), not STALLED or MAX_ITERATIONS at -1e305; AugmentedLagrangian, which
    would otherwise run on to the step limit, stops at the first step past the limit."""
    ctrl = jt.controls.PiecewiseLinear(2)
    sol = jt.solve(UNBOUNDED, ctrl, ctrl.initial_guess(1.0, 0.0, 0.0), solver, simulator=jt.RK4(4), max_steps=300)
    assert jt.status_name(sol.status) == "DIVERGED"
    assert float(sol.objective) < -1e20
    if isinstance(solver, jt.AugmentedLagrangian):
        n = int(sol.steps)
        assert 1 < n < 300 and float(sol.history.objective[n - 2]) >= -1e20


@pytest.mark.slow
def test_a_start_without_a_finite_point_reports_nan_not_zeros():
    """A solve that ends NONFINITE before any accepted step (the start's trajectory is NaN)
    reported tf = 0, objective 0 and max_constraint_error 0, the placeholder evaluation's
    zeros, and a result file listed nothing as non-finite (issue 51): they are NaN now."""
    prob = jt.Problem(
        lambda t, x, u, args: jnp.stack([jnp.sqrt(x[0] - 1.0), u[0]]),
        [0.0, 0.0],
        lambda tf, xf, args: xf[1:] - 1.0,
        ("x2",),
    )
    ctrl = jt.controls.PiecewiseConstant(2)
    for solver in (jt.KalmanSQP(), jt.KalmanSQP(globalization="line-search"), jt.KalmanSearch()):
        sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.0, 0.5, 0.5), solver=solver)
        assert jt.status_name(sol.status) == "NONFINITE"
        assert np.isnan(float(sol.tf)) and np.isnan(float(sol.objective))
        assert np.isnan(float(sol.max_constraint_error)) and np.all(np.isnan(np.asarray(sol.constraints)))
        assert np.isnan(float(sol.projected_gradient)) and np.all(np.isnan(np.asarray(sol.multipliers)))


def test_a_start_without_a_finite_point_has_no_zeros_in_its_history_or_progress(capsys, tmp_path):
    """The same solve's history and progress line still held the placeholder's zeros
    (objective 0, max|E| 0; issue 51, third audit): NaN, and the result saves and loads."""
    prob = jt.Problem(
        lambda t, x, u, args: jnp.stack([jnp.sqrt(x[0] - 1.0), u[0]]),
        [0.0, 0.0],
        lambda tf, xf, args: xf[1:] - 1.0,
        ("x2",),
    )
    ctrl = jt.controls.PiecewiseConstant(2)
    sim = jt.RK4(4)
    sol = jt.solve(prob, ctrl, ctrl.initial_guess(1.0, 0.5, 0.5), simulator=sim, progress=1)
    assert jt.status_name(sol.status) == "NONFINITE" and int(sol.steps) == 1
    assert np.isnan(float(sol.history.objective[0])) and np.isnan(float(sol.history.max_constraint_error[0]))
    line = capsys.readouterr().out
    assert "objective nan" in line and "max|E| nan" in line, line
    jt.io.save(tmp_path / "r", prob, sol, jt.simulate(prob, ctrl, sol.params, simulator=sim))
    assert np.isnan(float(jt.io.load(tmp_path / "r")[0].history.objective[0]))


def test_progress_prints_the_last_step_when_max_steps_ends_the_run(capsys):
    """`progress=N` promises a line every N steps and one at the end: a run that `max_steps`
    ended between two multiples of N printed no final line (issue 51, fifth audit)."""
    prob, ctrl = reach_problem(), jt.controls.PiecewiseConstant(1)
    a0 = ctrl.initial_guess(2.0, -1.0, -1.0)
    sol = jt.solve(prob, ctrl, a0, solver=jt.KalmanSearch(), simulator=jt.RK4(4), max_steps=5, progress=3)
    assert jt.status_name(sol.status) == "MAX_ITERATIONS" and int(sol.steps) == 5
    steps = [int(line.split()[1]) for line in capsys.readouterr().out.splitlines() if line.strip().startswith("step")]
    assert steps == [3, 5], steps


def _reach_min_time(**kw):
    """x'' = u, |u| <= 1, reach x(tf) >= 1 (a terminal inequality), minimize tf."""
    return jt.Problem(
        lambda t, x, u, args: jnp.stack([x[1], u[0]]),
        jnp.zeros(2),
        lambda tf, xf, args: jnp.zeros(0),
        (),
        num_controls=1,
        control_lower=[-1.0],
        control_upper=[1.0],
        terminal_inequality=lambda tf, xf, args: jnp.array([1.0 - xf[0]]),
        terminal_inequality_names=["reach"],
        **kw,
    )


@pytest.mark.slow
@pytest.mark.parametrize("solver", [jt.KalmanSQP(), jt.KalmanSearch(), jt.AugmentedLagrangian()], ids=type)
def test_max_violation_covers_every_constraint_kind(solver):
    """Issue 51: `max_violation` says how infeasible the returned point is over every kind
    (here a terminal inequality violated by 0.5 at (u, tf) = (1, 1): x(1) = 1/2, where
    `max_constraint_error`, the equalities only, reads 0)."""
    prob = _reach_min_time()
    ctrl = jt.controls.PiecewiseConstant(1)
    start = jt.solve(prob, ctrl, np.array([1.0, 1.0]), solver, simulator=jt.RK4(4), max_steps=1)
    u, tf = np.asarray(start.params)
    assert float(start.max_constraint_error) == 0.0  # no equalities
    # x(tf) = u tf^2 / 2 (RK4 is exact on it); the bound rows |u| <= 1
    np.testing.assert_allclose(start.max_violation, max(1 - u * tf**2 / 2, abs(u) - 1, 0.0), rtol=1e-12)
    if not isinstance(solver, jt.AugmentedLagrangian):  # (which takes a step at once)
        np.testing.assert_array_equal(start.params, [1.0, 1.0])  # the start, evaluated
        np.testing.assert_allclose(start.max_violation, 0.5, rtol=1e-12)


@pytest.mark.slow
def test_max_violation_is_the_kkt_reports():
    """... and agrees with the KKT report's own row-by-row computation at points with path
    rows (a speed bound on the grid), bound rows and a terminal inequality, violated or met."""
    prob = _reach_min_time(state_upper=[jnp.inf, 0.8])
    ctrl = jt.controls.PiecewiseConstant(3)
    for a in (ctrl.initial_guess(2.5, 1.2, -0.5), ctrl.initial_guess(0.5, 0.2, 0.2)):
        sol = jt.solve(prob, ctrl, a, simulator=jt.RK4(4), max_steps=1)
        report = jt.kkt_report(prob, ctrl, sol.params, simulator=jt.RK4(4))
        assert float(sol.max_violation) > 0.1
        np.testing.assert_allclose(sol.max_violation, report.max_violation, rtol=1e-12)
    sol = jt.solve(prob, ctrl, a, simulator=jt.RK4(4), max_steps=200)
    report = jt.kkt_report(prob, ctrl, sol.params, simulator=jt.RK4(4))
    assert sol.status == jt.Status.SUCCESS and float(sol.max_violation) < 1e-8
    np.testing.assert_allclose(sol.max_violation, report.max_violation, rtol=1e-6, atol=1e-15)
