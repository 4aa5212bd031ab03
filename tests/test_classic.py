"""The classic-problem gallery (`jt.problems.classic`): its references against independent
computations, the restricted optimum by SciPy SLSQP (a second solver on the same
evaluation) within each problem's gap, and the default solver from the naive start."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize
from helpers import TRUST_REGION, load_benchmark, perturbed_starts

import jaxtraj as jt
from jaxtraj.baselines import solve_ipopt, solve_slsqp

CLASSIC = jt.problems.classic
SIM = jt.RK4(40)


def test_brachistochrone_reference_is_the_cycloid_and_dymos_value():
    # the cycloid x = R (phi - sin phi), y = -R (1 - cos phi) through (10, -5), by its own
    # parametrization: the time is phi_f sqrt(R / g); Dymos' documented optimum is 1.8016
    g = 9.80665

    def miss(v):
        R, phi = v
        return [R * (phi - np.sin(phi)) - 10.0, R * (1.0 - np.cos(phi)) - 5.0]

    R, phi = scipy.optimize.fsolve(miss, [4.0, 3.0], xtol=1e-14)
    np.testing.assert_allclose(CLASSIC.get("brachistochrone").reference, phi * np.sqrt(R / g), rtol=1e-12)
    assert abs(CLASSIC.get("brachistochrone").reference - 1.8016) < 5e-5


def test_hypersensitive_reference_matches_the_indirect_solution():
    assert abs(CLASSIC.hypersensitive_reference() - CLASSIC.HYPERSENSITIVE_REFERENCE) < 1e-7


def _collocation():
    """benchmarks/collocation.py: CasADi Hermite-Simpson collocation, independent of jaxtraj."""
    return load_benchmark("collocation")


@pytest.mark.parametrize(
    ("name", "published", "digits"),
    [("goddard", -1.01283, 1e-5), ("orbit-raising", -1.525, 5e-4), ("zermelo", 5.46, 5e-3)],  # printed digits
)
def test_literature_references_agree_with_collocation_and_publication(name, published, digits):
    """The reference against CasADi collocation (200 intervals; Goddard's singular arc
    converges slowly, from above) and against the published value to its printed digits."""
    reference = CLASSIC.get(name).reference
    value, status = _collocation().PROBLEMS[name][0](200)
    assert status == "Solve_Succeeded"
    assert abs(value - reference) < (3e-6 if name == "goddard" else 1e-7)
    assert abs(reference - published) <= digits


def test_orbit_raising_and_zermelo_references_are_their_indirect_solutions():
    assert abs(CLASSIC.orbit_raising_radius() - CLASSIC.ORBIT_RAISING_RADIUS) < 1e-7
    assert abs(CLASSIC.zermelo_time() - CLASSIC.ZERMELO_TIME) < 1e-8


def test_moon_lander_reference_is_the_coast_then_burn_landing():
    """Simulate the closed-form landing independently (scipy, exact polynomial motion):
    coast to the switch s, then full thrust; it must touch down at rest, with fuel sqrt(68)."""
    s = (-4.0 + np.sqrt(68.0)) / 3.0
    burn = (2.0 + 1.5 * s) / 1.5

    def rhs(t, y):
        u = 0.0 if t < s else 3.0
        return [y[1], u - 1.5, u]

    out = scipy.integrate.solve_ivp(rhs, (0.0, s + burn), [10.0, -2.0, 0.0], rtol=1e-12, atol=1e-12, t_eval=[s + burn])
    np.testing.assert_allclose(out.y[:2, -1], [0.0, 0.0], atol=1e-8)
    np.testing.assert_allclose(out.y[2, -1], CLASSIC.get("moon-lander").reference, rtol=1e-10)


def test_free_flying_robot_reference_is_a_feasible_control_of_that_cost():
    """The free-flying robot's reference (the best known restricted optimum, below the
    7.9101471 Betts publishes) is the cost of a stored control (IPOPT's node values,
    tests/data) integrated again by SciPy alone: it reaches rest at the origin, within the
    bounds, at that cost. So the continuous optimum is at most 7.789744."""
    U = np.loadtxt(os.path.join(os.path.dirname(__file__), "data", "free_flying_robot_best.txt"))
    assert U.shape == (31, 4) and U.min() >= -1e-9 and U.max() <= 1.0 + 1e-9
    nodes = np.linspace(0.0, 12.0, 31)

    def rhs(t, y):
        u = np.array([np.interp(t, nodes, U[:, i]) for i in range(4)])
        f1, f2 = u[0] - u[1], u[2] - u[3]
        th = y[2]
        return [y[3], y[4], y[5], (f1 + f2) * np.cos(th), (f1 + f2) * np.sin(th), 0.2 * (f1 - f2), u.sum()]

    y0 = [-10.0, -10.0, np.pi / 2, 0.0, 0.0, 0.0, 0.0]
    out = scipy.integrate.solve_ivp(rhs, (0.0, 12.0), y0, rtol=1e-11, atol=1e-11, max_step=0.05)
    np.testing.assert_allclose(out.y[:6, -1], 0.0, atol=1e-7)
    np.testing.assert_allclose(out.y[6, -1], CLASSIC.FREE_FLYING_ROBOT_COST, rtol=1e-8)


def test_gallery_lists_every_feature():
    features = {f for name in CLASSIC.names() for f in CLASSIC.get(name).features}
    for want in (
        "free tf, minimum time",
        "fixed tf, Mayer objective",
        "running cost",
        "bang-bang",
        "state path constraint",
        "singular arc",
        "several controls",
        "design parameter",
        "free initial state",
        "sensitive / unstable",
        "terminal inequality",
    ):
        assert want in features
    assert len(CLASSIC.names()) >= 10
    with pytest.raises(ValueError, match="`name` must be one of"):
        CLASSIC.get("nope")


# SLSQP stops at its iteration limit on Goddard (degenerate coast nodes) and orbit raising
# (the thrust direction's length is free), and at its first iteration on the free-flying robot
# ("singular matrix C in LSQ subproblem"); IPOPT is their second solver
@pytest.mark.slow
@pytest.mark.parametrize(
    "name", [n for n in CLASSIC.names() if n not in ("goddard", "orbit-raising", "free-flying-robot")]
)
def test_slsqp_reaches_each_reference_within_its_gap(name):
    entry = CLASSIC.get(name)
    res = solve_slsqp(entry.problem, entry.control, entry.start, simulator=SIM)
    assert res.success
    gap = res.objective - entry.reference
    assert -1e-6 * (1.0 + abs(entry.reference)) <= gap <= entry.gap
    traj = jt.simulate(entry.problem, entry.control, res.params, simulator=SIM)
    E = entry.problem.terminal(traj.tf, traj.xf, entry.problem.args)
    assert float(jnp.max(jnp.abs(E), initial=0.0)) < 1e-6


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in CLASSIC.names() if n != "free-flying-robot"])
def test_default_solver_reaches_the_reference_from_the_naive_start(name):
    """The default solver (the trust region) from the naive start and from round-off-sized
    perturbations of it (absolute, so the zero entries move too): SUCCESS at the reference
    every time, one optimum (measured iterations on the problems with inequality rows:
    Bryson-Denham 6, minimum-time double integrator 8-13, moon lander 7, singular arc 14,
    capped terminal 1, max-range 2-3, Goddard 7; Goddard's in at most 15: with the
    convexification of the whole W + c A^T A instead of `convexify_blockwise`, 69, the flip
    distorted a reduced Hessian of 1e-4). Orbit raising's thrust vector is normalized in the
    dynamics, so G and E do not change under a -> c a (W a = -grad L): the trust region drops
    that direction from its steps (`_kkt.scale_free`); before, steps at the radius shrank
    the scale to ~1e-4, the gradient grew as 1/|a| and the KKT test passed or failed by
    round-off (SUCCESS or STALLED at the same value). Its scale now stays within 0.1-10x of
    the start's."""
    entry = CLASSIC.get(name)
    objectives = []
    for start in perturbed_starts(entry.start, absolute=True):  # eps = 0 is the start itself
        sol = jt.solve(entry.problem, entry.control, start, simulator=SIM, max_steps=500)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert name != "goddard" or int(sol.iterations) <= 15
        if name == "orbit-raising":
            assert 0.1 <= float(jnp.linalg.norm(sol.params) / jnp.linalg.norm(start)) <= 10.0
        assert float(sol.max_constraint_error) <= jt.KalmanSQP().ctol
        gap = float(sol.objective) - entry.reference
        assert -1e-6 * (1.0 + abs(entry.reference)) <= gap <= entry.gap
        objectives.append(float(sol.objective))
    assert max(objectives) - min(objectives) <= 1e-7 * (1.0 + abs(entry.reference))


@pytest.mark.slow
def test_line_search_drops_orbit_raisings_free_scale():
    """The line search (BFGS) on orbit raising from the naive start and its round-off
    perturbations: with the exact Hessian at the start it recognizes the free scale
    (`_kkt.scale_free`) and drops it from its steps, so the scale does not collapse (before:
    0.059x, in 297 iterations; it grows instead, as steps orthogonal to the parameters do:
    7-24x measured), and it ends SUCCESS at the reference. With the multiplier step cut
    together with a step cut to the radius (`LineSearch`): before, the naive start STALLED at
    -1.48999 on a 2-core EPYC (its merit's slope made of the multipliers' term alone,
    multipliers 2e4 where they are 1.4) and its perturbations ended SUCCESS; now SUCCESS from
    all three under the default, SSE4.2 and AVX arithmetic (77-518 iterations)."""
    entry = CLASSIC.get("orbit-raising")
    solver = jt.KalmanSQP(hessian="bfgs", globalization="line-search")
    for start in perturbed_starts(entry.start):
        sol = jt.solve(entry.problem, entry.control, start, solver, simulator=SIM)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert -1e-6 * (1.0 + abs(entry.reference)) <= float(sol.objective) - entry.reference <= entry.gap
        assert 0.1 <= float(jnp.linalg.norm(sol.params) / jnp.linalg.norm(entry.start)) <= 100.0


def test_trust_region_keeps_the_knot_order_in_its_qp():
    """A singular-arc start (random start 13 of the gallery's 32) whose QP step would carry t_2
    past t_3 = tf: with appendix C's observation of that gap alone, t_3 moved past tf and the
    scaling for that gap cut every step 20x (STALLED at J = 0.4798 with u_3 3e-4 above its
    bound). With the gaps as rows of the trust region's QP: SUCCESS at J* = 1/3 from the start
    and its round-off perturbations."""
    entry = CLASSIC.get("singular-arc")
    a0 = np.array([-0.01527, 0.453958, 0.797583, 0.776824, -0.244859, 1.421309, 0.397972])
    for start in perturbed_starts(a0):
        sol = jt.solve(entry.problem, entry.control, start, TRUST_REGION, simulator=SIM, max_steps=500)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert abs(float(sol.objective) - entry.reference) <= entry.gap
        assert float(sol.max_constraint_error) <= TRUST_REGION.ctol


@pytest.mark.slow
def test_feasibility_first_reaches_zermelo_from_far_starts():
    """Zermelo's ship from the 16 of the gallery's 32 random starts (key 0, spread 0.5) that
    are farthest from the target (initial max |E| 11-30): with the composite step alone
    (`feasibility_first=inf`), minimum time pulls tf down while the target is still far and
    the iterates stall at max |E| ~ 4.5 (4 of 16 at the reference); the trust region's default
    takes the normal step alone while it is cut and the start is far (|E| > 0.1 |H| |a|):
    11 of 16 measured under every round-off perturbation of the starts tried (relative 1e-14
    to 3e-10, and with XLA_FLAGS=--xla_cpu_max_isa=AVX), at least 8 required; every SUCCESS
    passes the independent KKT check. The others end at another KKT point or, heading away
    with tf run to 0, CONSTRAINT_STATIONARY within 97 steps under those perturbations; before
    the normal step's Cauchy safeguard (`_trust_region.normal_step`) the cut minimum-norm step
    ran along the rows' near-null direction and crawled: STALLED after 128-198 steps or
    MAX_ITERATIONS at 500."""
    entry = CLASSIC.get("zermelo")
    starts = jt.random_starts(
        entry.problem, entry.control, jax.random.key(0), 32, around=entry.start, spread=0.5, simulator=SIM
    )
    violation = [float(jnp.max(jnp.abs(jt.evaluate(entry.problem, entry.control, a, simulator=SIM).E))) for a in starts]
    far = np.asarray(starts)[np.argsort(violation)[16:]]
    solver = TRUST_REGION
    sols = jt.solve_batch(entry.problem, entry.control, far, solver, simulator=SIM, max_steps=500, progress=False)
    names, J = jt.status_name(sols.status), np.asarray(sols.objective)
    at = (names == "SUCCESS") & (np.abs(J - entry.reference) <= entry.gap)
    assert at.sum() >= 8
    assert set(names) <= {"SUCCESS", "CONSTRAINT_STATIONARY"}
    assert int(np.max(sols.steps)) <= 150
    for i in np.flatnonzero(names == "SUCCESS"):
        report = jt.kkt_report(entry.problem, entry.control, sols.params[i], simulator=SIM)
        assert report.satisfied(solver.ctol, solver.acceptable_gtol)


def _unseen_problem(name):
    """A problem of benchmarks/unseen.py (problems the solvers were not tuned on): (problem,
    control, start)."""
    ((prob, family, tf, u),) = [p[1:] for p in load_benchmark("unseen").problems() if p[0] == name]
    ctrl = prob.parametrize(family)
    return prob, ctrl, ctrl.initial_guess(tf, u, u)


@pytest.mark.slow
def test_penalty_capped_near_feasibility_on_a_cart_pole_swing_up():
    """A cart-pole swing-up from rest to the upright rest (benchmarks/unseen.py), a problem the
    solver was not tuned on. With the merit penalty carried over whatever its size (6.7e3 x
    its natural scale |W| / |A|^2 after the steps that bought a little feasibility with
    objective) the trust region crawled along the curved terminal constraints: 1092-1165
    iterations at RK4(10..100), IPOPT 260-453. With the penalty capped near feasibility
    (`TrustRegion.mu_max`): SUCCESS at IPOPT's optimum on the same evaluation (an independent
    NLP solver), in at most 1.5x its iterations (measured 268 against 260 at RK4(20)), from a
    round-off perturbation of the start too."""
    prob, ctrl, a0 = _unseen_problem("cart-pole")
    sim = jt.RK4(20)
    ipopt = solve_ipopt(prob, ctrl, a0, simulator=sim)
    assert ipopt.success
    for start in perturbed_starts(a0, absolute=True)[:2]:
        sol = jt.solve(prob, ctrl, start, simulator=sim, max_steps=1000)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert abs(float(sol.objective) - ipopt.objective) <= 1e-8 * ipopt.objective
        assert int(sol.iterations) <= 1.5 * ipopt.iterations


@pytest.mark.slow
def test_penalty_cap_follows_progress_on_a_cart_pole_with_the_final_time_as_an_equality():
    """The same cart-pole swing-up stated as a user may state it: the final time free and fixed
    by a terminal equality tf - 2 = 0, started at tf = 3. The merit penalty was capped once,
    at the first nearly feasible point (violation 1e-7, objective 5x the optimum); the
    violation never halved below that again on the way to the optimum, so the 4e4 x its
    scale carried over stayed, and the trust region crawled: MAX_ITERATIONS after 2053
    iterations. A cap now also applies where no step has raised the penalty since the last
    one and the objective has fallen 1 % (`TrustRegion.cap_progress`): SUCCESS at IPOPT's
    optimum of the fixed-time statement (an independent NLP solver; the same restricted
    problem), from a round-off perturbation of the start too."""
    fixed, fixed_ctrl, fixed_a0 = _unseen_problem("cart-pole")
    ipopt = solve_ipopt(fixed, fixed_ctrl, fixed_a0, simulator=jt.RK4(20))
    assert ipopt.success
    target = jnp.array([0.0, np.pi, 0.0, 0.0])
    prob = jt.Problem(
        load_benchmark("unseen")._cart_pole,
        np.zeros(4),
        lambda tf, xf, args: jnp.concatenate([xf[:4] - target, jnp.stack([tf - 2.0])]),
        ("x", "theta", "v", "omega", "tf = 2"),
        running_cost=fixed.running_cost,
        control_lower=-20.0,
        control_upper=20.0,
    )
    ctrl = jt.controls.PiecewiseLinear(20)
    for start in perturbed_starts(ctrl.initial_guess(3.0, 0.0, 0.0), absolute=True)[:2]:
        sol = jt.solve(prob, ctrl, start, simulator=jt.RK4(20), max_steps=1500)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert abs(float(sol.objective) - ipopt.objective) <= 1e-8 * ipopt.objective


@pytest.mark.slow
def test_penalty_cap_waits_for_the_violation_to_halve_on_a_pendulum_min_time():
    """A pendulum's least time to the inverted rest with |u| <= 0.5 and six constant pieces
    with free switch times (benchmarks/unseen.py): more pieces than switches, so the optimum
    collapses a segment. History (docs/history.md): with the carried penalty capped at every
    step near feasibility, an 8-step cycle of accepted points (MAX_ITERATIONS); the cap now
    waits until the violation has halved since the last one. The QP's multipliers of E then
    left out the knot gaps it held: the collapsed segment's pull went into lambda_E, and the
    augmented-Lagrangian merit's minimum with the capped penalty lay a violation of ~|delta
    lambda| / mu away from the optimum: cycles out and back, 28-3789 iterations over the
    naive start, its round-off perturbations and XLA's ISA settings (issue 49). With the held
    gaps in that least-squares solve: 23-54.

    From the naive start and its 1e-12 / 1e-10 perturbations for twelve random directions
    (25 starts, at most 1000 steps, one vmapped solve): every SUCCESS is a verified KKT point
    (an independent report), the naive start and at least 22 of them within 1e-5 of IPOPT's
    objective (an independent NLP solver on the same evaluation; neighbouring local optima
    split the same arcs differently among the pieces, so RK4's error differs by ~3e-6), in
    at most 250 iterations. Measured (2-core AMD EPYC): 25 of 25 at IPOPT's optimum in
    17-109 iterations under XLA's default and AVX code; under SSE4.2 23, one SUCCESS at
    another local optimum (tf 14.19, a longer swing) and one CONSTRAINT_STATIONARY (a
    stationary point of the violation). Which basin a start's global phase falls into
    follows its last bits; the endgame no longer does. A single solve of one of those starts
    ended MAX_ITERATIONS in a trap far from the optimum: the first piece collapsed, the last
    coasting at u ~ 0.01 towards the unstable upright rest, which it approaches only as tf
    grows without bound (tf 17 and rising, |E| ~1e-2 falling slowly)."""
    prob, ctrl, a0 = _unseen_problem("pendulum-min-time")
    ipopt = solve_ipopt(prob, ctrl, a0, simulator=SIM)
    assert ipopt.success
    starts = [a0] + [s for seed in range(12) for s in perturbed_starts(a0, seed=seed, absolute=True)[1:]]
    solve = jax.jit(jax.vmap(lambda a: jt.solve(prob, ctrl, a, simulator=SIM, max_steps=1000)))
    sols = solve(jnp.stack(starts))
    ok = np.asarray(sols.status == jt.Status.SUCCESS)
    at_ipopt = ok & (np.abs(np.asarray(sols.objective) - ipopt.objective) <= 1e-5)
    assert at_ipopt[0] and at_ipopt.sum() >= 22, (jt.status_name(sols.status), sols.objective)
    assert np.all(np.asarray(sols.iterations)[at_ipopt] <= 250), sols.iterations
    for sol in sols[ok]:
        assert jt.kkt_report(prob, ctrl, sol.params, simulator=SIM).satisfied(1e-9, 1e-6)


def test_collapsed_durations_count_in_the_trust_regions_kkt_test():
    """The moon lander's least fuel with a saturated spline (0 <= u <= 3, free durations;
    benchmarks/unseen.py) from random start 1 of 32 (key 0, spread 0.5): the optimum (coast,
    then full thrust: J* = sqrt(68), closed form) collapses durations to 0 (three of eight).
    The trust region tested stationarity with the knot gaps only for problems with
    inequality rows, and this one has none (the spline saturates within its limits): at the
    optimum, held by the gaps of the collapsed durations, its residual stayed 4e-7..6e-3 and
    10 of 32 random starts ended STALLED at J* (now 4). With the gaps in its test as in
    every solver's final report: SUCCESS, from the start's round-off perturbations too."""
    prob, ctrl, _ = _unseen_problem("lander-spline")
    a0 = np.array([
        0.22851977748357688, 0.5787906663103681, 1.1654510544812466, 0.8200034092064445, 0.7520190200396671,
        0.3152440884697181, 0.42528950139820226, 0.722504451951532, 3.0, 1.748881928213346, 2.5353824201937227,
        1.9077422605175336, 2.206936082001609, 1.3376433697433783, 1.1095061061072704, 0.31862202658245486,
        1.9388898729151514,
    ])  # fmt: skip
    for start in perturbed_starts(a0):
        sol = jt.solve(prob, ctrl, start, simulator=SIM, max_steps=1000)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert abs(float(sol.objective) - np.sqrt(68.0)) <= 1e-8
        # two durations collapsed (to 3.6e-12 where `acceptable_steps` ends the endgame)
        assert np.sum(np.asarray(sol.params)[:8] < 1e-10) >= 2


@pytest.mark.slow
def test_control_values_put_back_on_their_bounds_end_a_round_off_tail():
    """A unicycle's least time to (1, 1, pi/2) with 0 <= v <= 1, |omega| <= 1
    (benchmarks/unseen.py): the quarter circle at full speed and turn rate, tf* = pi/2. Its
    last QP steps left bound rows violated by ~1e-9 (the QP's round-off), so the point never
    counted as feasible and four steps went to round-off (12 iterations, IPOPT 10); with the
    candidate's control values put back on their bounds: SUCCESS at pi/2 in fewer iterations
    than IPOPT on the same evaluation (measured 7), from a round-off perturbation too."""
    prob, ctrl, a0 = _unseen_problem("unicycle-min-time")
    ipopt = solve_ipopt(prob, ctrl, a0, simulator=SIM)
    assert ipopt.success
    for start in perturbed_starts(a0, absolute=True)[:2]:
        sol = jt.solve(prob, ctrl, start, simulator=SIM)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert abs(float(sol.tf) - np.pi / 2) <= 1e-8
        assert int(sol.iterations) < ipopt.iterations


def test_an_exact_model_opens_the_trust_region_to_its_own_minimizer():
    """The two-channel transfer is linear-quadratic: the trust region's model is exact (ratio 1
    to 1e-13), so after the first step the radius opens to the model's minimizer and the second
    step is the optimum. Fewer iterations than IPOPT's on the same evaluation (3; before the
    rule the radius grew 1.6x per step from 1.0: 7 iterations), J* = 30 in closed form, and the
    same from round-off perturbations of the start."""
    entry = CLASSIC.get("two-channel")
    ipopt = solve_ipopt(entry.problem, entry.control, entry.start, simulator=SIM)
    assert ipopt.success
    for start in perturbed_starts(entry.start, absolute=True):
        sol = jt.solve(entry.problem, entry.control, start, simulator=SIM)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert int(sol.iterations) < ipopt.iterations
        assert abs(float(sol.objective) - 30.0) <= 1e-8


@pytest.mark.parametrize("name", ["lq", "capped-terminal", "goddard", "free-flying-robot"])
def test_ipopt_reaches_the_reference(name):
    """Problems without terminal equality constraints, and SLSQP's failures (Goddard, the
    free-flying robot)."""
    entry = CLASSIC.get(name)
    res = solve_ipopt(entry.problem, entry.control, entry.start, simulator=SIM)
    assert res.success
    assert -1e-6 * (1.0 + abs(entry.reference)) <= res.objective - entry.reference <= entry.gap


@pytest.mark.slow
def test_free_flying_robot_from_the_zero_start_and_its_round_off():
    """The size study of issue 49: 4 bounded controls x 30 pieces (124 parameters, 248 bound
    rows). From the zero start and its round-off perturbations: SUCCESS within the entry's gap
    of the published continuous optimum, and an independent KKT check (`jt.kkt_report`) holds
    at the end point. (Its cost per iteration is measured in `benchmarks/gallery.py`.) The
    local optimum reached moved with the start's last bits (8.01782, 8.01819 or 8.02074) until
    session 40; now 8.01782 from the three starts under three ISA settings (`roundoff.py
    --gallery`; IPOPT 7.97519, another local optimum)."""
    entry = CLASSIC.get("free-flying-robot")
    assert entry.start.shape == (124,)
    for start in perturbed_starts(entry.start, absolute=True):
        sol = jt.solve(entry.problem, entry.control, start, simulator=SIM, max_steps=200)
        assert jt.status_name(sol.status) == "SUCCESS"
        assert 0.0 <= float(sol.objective) - entry.reference <= entry.gap
        report = jt.kkt_report(entry.problem, entry.control, sol.params, simulator=SIM)
        assert report.satisfied(ctol=1e-8, gtol=1e-6)
