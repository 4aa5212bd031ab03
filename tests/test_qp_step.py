"""KalmanSQP's inequality QP step (`dual_active_set` + the filter, `inequality_step`) against
an independent QP solver (qpOASES through CasADi) on random strictly convex QPs, with the
multipliers checked by the KKT conditions."""

import functools

import casadi as ca
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st

from jaxtraj import Evaluation, KalmanSQP
from jaxtraj._kalman import REFACTOR_EVERY, dual_active_set, inequality_step, sequential_update
from jaxtraj._kalman_sqp import ELASTIC_PINNED

R_REL = 1e-12  # KalmanSQP's default relative noise
_direction = eqx.filter_jit(KalmanSQP().direction)


def _equality_step(B, g, H, E, C_a):
    """The equality filter as `KalmanSQP._equality_step`: `(P, r, d, P1, prior_var, pinned)`,
    P = B^-1, r E's noise, d and P1 the step and covariance after E's rows, the rows' prior
    variances, and whether E's rows (nearly) pin a row."""
    P = jnp.linalg.inv(B)
    P = 0.5 * (P + P.T)
    r = R_REL * jnp.einsum("ip,pq,iq->i", H, P, H) + 1e-300
    d, _, _ = sequential_update(-P @ g, P, H, -E, r)
    d, P1, _ = sequential_update(d, P, H, -E, r)
    prior_var = jnp.einsum("ip,pq,iq->i", C_a, P, C_a)
    pinned = jnp.any(jnp.einsum("ip,pq,iq->i", C_a, P1, C_a) < ELASTIC_PINNED * prior_var)
    return P, r, d, P1, prior_var, pinned


@functools.cache
def _step(n, me, mi):
    """The equality filter, then `inequality_step`, jitted once per shape."""

    @jax.jit
    def step(B, g, H, E, C, C_a, warm):
        P, r, d, P1, prior_var, pinned = _equality_step(B, g, H, E, C_a)
        step = inequality_step(
            d, P1, H, C, C_a, R_REL * prior_var + 1e-300, prior_var, 1e-12, 1e-12, 4 * n + 20, (P, E, r), warm=warm
        )
        return (*step, pinned)

    return step


def _qpoases(B, g, H, E, C, C_a):
    A = np.vstack([H, C_a])
    qp = {"h": ca.DM(B).sparsity(), "a": ca.DM(A).sparsity()}
    solver = ca.conic("S", "qpoases", qp, {"printLevel": "none", "error_on_fail": False})
    lba = np.concatenate([-E, np.full(len(C), -np.inf)])
    uba = np.concatenate([-E, -C])
    out = solver(h=B, g=g, a=A, lba=lba, uba=uba, lbx=-np.inf, ubx=np.inf)
    assert solver.stats()["success"]
    return np.asarray(out["x"]).ravel()


def _random_qp(seed, n, me, mi, neighbours):
    """A strictly convex QP with a known feasible point x0 (about 70 % of the inequality rows
    active there); with `neighbours`, rows 0 and 1 nearly dependent, as adjacent grid points."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    B = M @ M.T + 0.1 * np.eye(n)
    g, H, C_a = rng.normal(size=n), rng.normal(size=(me, n)), rng.normal(size=(mi, n))
    if neighbours and mi > 1:
        C_a[1] = C_a[0] + 1e-3 * rng.normal(size=n)
    x0 = rng.normal(size=n)
    C = -C_a @ x0 - rng.uniform(0.0, 1.0, mi) * (rng.uniform(size=mi) < 0.3)
    return B, g, H, -H @ x0, C, C_a


@settings(max_examples=150, deadline=None, derandomize=True)  # the same examples on every machine
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.sampled_from([3, 7]),  # few shapes: one compilation each
    me=st.sampled_from([0, 2]),
    mi=st.sampled_from([4, 13]),
    neighbours=st.booleans(),
    warm=st.sampled_from(["empty", "random", "all"]),
)
def test_inequality_step_is_the_qp_solution(seed, n, me, mi, neighbours, warm):
    """From an empty working set and from warm starts (`dual_active_set(warm=)`: a random
    subset of the rows, every row): the same solution."""
    B, g, H, E, C, C_a = _random_qp(seed, n, me, mi, neighbours)
    rng = np.random.default_rng(seed + 1)
    start = {"empty": np.zeros(mi, bool), "random": rng.uniform(size=mi) < 0.5, "all": np.ones(mi, bool)}[warm]
    d, _, W, u, excess, pinned = _step(n, me, mi)(*(jnp.asarray(v) for v in (B, g, H, E, C, C_a, start)))
    # a row that E's rows (nearly) pin makes KalmanSQP take its elastic step instead
    assume(not pinned)
    d, W, u = np.asarray(d), np.asarray(W), np.asarray(u)
    x = _qpoases(B, g, H, E, C, C_a)
    scale = 1.0 + np.max(np.abs(x))
    assert np.max(np.abs(d - x)) <= 1e-6 * scale
    # the KKT conditions of the filter's own step, to the same tolerance: feasible, the
    # multipliers u >= 0 only on the working set, stationarity with some lambda_E. (The
    # filter's relative noise r_rel = 1e-12 costs accuracy where a row keeps a small part of
    # its variance: up to 3e-7 measured where 2 equalities fix 3 parameters to a line and
    # up to 13 rows meet at its end; a row skipped at such a degenerate vertex is violated
    # by that much: `excess`, the largest C + C_a d outside the working set.)
    tol = 1e-6 * scale
    assert np.max(C + C_a @ d) <= tol
    assert np.max(np.abs(E + H @ d), initial=0.0) <= tol
    assert np.max(np.asarray(excess)) <= tol
    assert np.all(u >= 0.0) and np.all(u[~W] == 0.0)
    assert np.all(np.abs((C + C_a @ d)[W]) <= tol)
    residual = B @ d + g + C_a.T @ u
    lam_E = np.linalg.lstsq(H.T, -residual, rcond=None)[0] if me else np.zeros(0)
    assert np.max(np.abs(residual + H.T @ lam_E)) <= 1e-7 * (1.0 + np.max(np.abs(g)) + np.max(np.abs(u), initial=0.0))


@pytest.mark.parametrize("seed", range(3))
def test_a_qp_with_many_departures_is_the_qp_solution(seed):
    """30 parameters, 2 equalities, 120 rows from an empty working set: rows leave W 40-55
    times, so P_W and M go through many rank-one downdates between their refactorizations
    (`REFACTOR_EVERY`); the step is still qpOASES's."""
    n, me, mi = 30, 2, 120
    B, g, H, E, C, C_a = _random_qp(seed, n, me, mi, False)
    args = [jnp.asarray(v) for v in (B, g, H, E, C, C_a)]
    _, (W, _, _, rounds, _), _ = _dual(n, me, mi)(*args, jnp.zeros(mi, bool), jnp.inf)
    departures = (int(rounds) - int(jnp.sum(W))) // 2  # each round adds a row or drops one
    assert departures >= 4 * REFACTOR_EVERY
    d = np.asarray(_step(n, me, mi)(*args, jnp.zeros(mi, bool))[0])
    x = _qpoases(B, g, H, E, C, C_a)
    assert np.max(np.abs(d - x)) <= 1e-6 * (1.0 + np.max(np.abs(x)))


@functools.cache
def _dual(n, me, mi):
    """E's step d0 (`_equality_step`), then `dual_active_set` alone, with a
    `dual_bound` or none (inf)."""

    @jax.jit
    def dual(B, g, H, E, C, C_a, warm, bound):
        _, _, d, P1, prior_var, pinned = _equality_step(B, g, H, E, C_a)
        args = (C, C_a, R_REL * prior_var + 1e-300, prior_var, 1e-12, 1e-12, 4 * n + 20)
        return d, dual_active_set(d, P1, H, *args, warm=warm, dual_bound=bound), pinned

    return dual


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 2**31 - 1),
    me=st.sampled_from([0, 2]),  # (one shape of n and mi: two compilations)
    warm=st.sampled_from(["empty", "random"]),
)
def test_the_duals_rise_is_the_optimal_value_over_es_step(seed, me, warm):
    """Weak duality, which `dual_bound` relies on: the dual objective's rise that the dual
    active set tracks (Goldfarb and Idnani's increments, half of u^T s at a warm start) ends
    at f(x*) - f(d0) on feasible QPs, x* qpOASES's minimizer of f = d^T B d / 2 + g^T d and
    d0 the minimizer on E's rows alone."""
    n, mi = 7, 13
    B, g, H, E, C, C_a = _random_qp(seed, n, me, mi, False)
    rng = np.random.default_rng(seed + 1)
    start = {"empty": np.zeros(mi, bool), "random": rng.uniform(size=mi) < 0.5}[warm]
    args = (jnp.asarray(v) for v in (B, g, H, E, C, C_a, start))
    d0, (_, _, excess, _, rise), pinned = _dual(n, me, mi)(*args, jnp.inf)
    assume(not pinned)
    assert float(jnp.max(excess)) <= 1e-9
    x, d0 = _qpoases(B, g, H, E, C, C_a), np.asarray(d0)
    f = lambda d: 0.5 * d @ B @ d + g @ d
    gap = f(x) - f(d0)
    assert abs(float(rise) - gap) <= 1e-6 * (1.0 + abs(gap) + abs(f(x)))


@pytest.mark.slow  # (48 parameters: ~5 s a seed)
@pytest.mark.parametrize("seed", range(3))
def test_an_infeasible_qp_ends_where_the_dual_passes_its_bound(seed):
    """E's rows ask for a step 10 n times longer than the box |d_i| <= 1 allows: infeasible.
    With the bound of KalmanSQP's trust region (5 |B| (|d0| + sqrt(n))^2, the model's rise
    over the box) the dual ends in fewer rounds, past the bound, unfinished (a row left
    violated), as it ends without one (the rows run out or a row is skipped)."""
    rng = np.random.default_rng(seed)
    n, me = 48, 6
    M = rng.normal(size=(n, n))
    B = M @ M.T + 0.1 * np.eye(n)
    g, H, E = rng.normal(size=n), rng.normal(size=(me, n)), 10.0 * n * rng.normal(size=me)
    C, C_a = -np.ones(2 * n), np.vstack([np.eye(n), -np.eye(n)])
    args = [jnp.asarray(v) for v in (B, g, H, E, C, C_a, np.zeros(2 * n, bool))]
    d0, (_, _, excess, rounds, rise), _ = _dual(n, me, 2 * n)(*args, jnp.inf)
    bound = 5.0 * np.linalg.norm(B) * (np.linalg.norm(d0) + np.sqrt(n)) ** 2
    _, (_, _, excess_b, rounds_b, rise_b), _ = _dual(n, me, 2 * n)(*args, bound)
    assert float(rise) > bound and float(rise_b) > bound
    assert int(rounds_b) < int(rounds) and float(jnp.max(excess_b)) > 1.0 and float(jnp.max(excess)) > 1.0


@functools.cache
def _steps_without_equalities(n, me, mi):
    """`inequality_step` with no equality rows, and with `me` rows of zeros counted as none
    (`num_equalities=0`: KalmanSQP's elastic round, compiled with the hard one's shapes)."""

    @jax.jit
    def steps(B, g, H, C, C_a):
        P = jnp.linalg.inv(B)
        P = 0.5 * (P + P.T)
        prior_var = jnp.einsum("ip,pq,iq->i", C_a, P, C_a)
        args = (C, C_a, R_REL * prior_var + 1e-300, prior_var, 1e-12, 1e-12, 4 * n + 20)
        no_rows = (P, jnp.zeros(0, g.dtype), jnp.zeros(0, g.dtype))
        none = inequality_step(-P @ g, P, H[:0], *args, no_rows)
        zero_rows = (P, jnp.zeros(H.shape[0], g.dtype), jnp.ones(H.shape[0], g.dtype))
        zeros = inequality_step(-P @ g, P, jnp.zeros_like(H), *args, zero_rows, num_equalities=0)
        return none, zeros

    return steps


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), n=st.sampled_from([3, 7]), mi=st.sampled_from([4, 13]))
def test_zero_equality_rows_counted_as_none_are_no_rows(seed, n, mi):
    """The elastic round's QP (zero equality rows, none counted) against the same QP without
    the rows and against qpOASES: the same step, working set and multipliers."""
    B, g, H, _, C, C_a = _random_qp(seed, n, 2, mi, True)
    none, zeros = _steps_without_equalities(n, 2, mi)(*(jnp.asarray(v) for v in (B, g, H, C, C_a)))
    x = _qpoases(B, g, H[:0], np.zeros(0), C, C_a)
    scale = 1.0 + np.max(np.abs(x))
    assert np.max(np.abs(np.asarray(zeros[0]) - x)) <= 1e-6 * scale
    np.testing.assert_array_equal(np.asarray(zeros[2]), np.asarray(none[2]))  # working set
    np.testing.assert_allclose(np.asarray(zeros[0]), np.asarray(none[0]), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(np.asarray(zeros[3]), np.asarray(none[3]), rtol=1e-9, atol=1e-12)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), n=st.sampled_from([3, 7]), mi=st.sampled_from([4, 13]))
def test_elastic_step_is_the_penalty_qp_solution(seed, n, mi):
    """Equalities inconsistent with the inequalities (row 0 asks H_0 d >= 1 - E_0 while
    H_0 d = -E_0): `KalmanSQP.direction` takes its elastic step, the minimizer of
    g d + 1/2 d^T B d + |H d + E|^2 / (2 r) over the inequalities, r = `elastic` x the mean of
    h B^-1 h^T; against qpOASES on that QP. (A refinement pass of the noisy equality rows
    had moved it off: 26 % past the Gauss-Newton step on a locally infeasible problem.)"""
    B, g, H, E, C, C_a = _random_qp(seed, n, 2, mi, False)
    # feasible at x1 (about 70 % of the rows active there), x1 off H's solutions by H_0 x1 = 2 - E_0
    x1 = np.linalg.lstsq(H, -E, rcond=None)[0] + 2.0 * H[0] / (H[0] @ H[0])
    C_a[0] = -H[0]
    C = -C_a @ x1 - np.random.default_rng(seed).uniform(0.0, 1.0, mi) * (np.arange(mi) % 3 == 0)
    C[0] = 1.0 - E[0]  # -H_0 d + 1 - E_0 <= 0
    solver = KalmanSQP()
    ev = Evaluation(
        xf=None, xf_a=None, tf=None, G=0.0, G_a=jnp.asarray(g), E=jnp.asarray(E), H=jnp.asarray(H), status=None,
        D=jnp.asarray(C), D_a=jnp.asarray(C_a),
    )  # fmt: skip
    d, _ = _direction(ev, jnp.asarray(B), jnp.zeros(2 + mi), jnp.array([0.0, 1.0]), jnp.zeros((2, n)))
    P = np.linalg.inv(B)
    r = solver.elastic * np.mean(np.einsum("ip,pq,iq->i", H, P, H))
    # that QP with the residual as variables, s = (H d + E) / sqrt(r): well conditioned
    m = H.shape[0]
    xs = _qpoases(
        np.block([[B, np.zeros((n, m))], [np.zeros((m, n)), np.eye(m)]]),
        np.concatenate([g, np.zeros(m)]),
        np.hstack([H, -np.sqrt(r) * np.eye(m)]),
        E,
        C,
        np.hstack([C_a, np.zeros((mi, m))]),
    )
    x = xs[:n]
    assert np.max(C + C_a @ x) <= 1e-9 and np.max(np.abs(E + H @ x)) > 0.1  # inconsistent rows
    np.testing.assert_allclose(np.asarray(d), x, rtol=0, atol=1e-6 * (1.0 + np.max(np.abs(x))))


@pytest.mark.parametrize("seed", range(4))
def test_elastic_step_softens_inequalities_that_contradict_the_bounds(seed):
    """Inequality rows inconsistent with the parameter bounds by themselves, no E (a reach
    x(tf) >= 1 that no bounded control meets at the current tf): softening E changes nothing,
    so a third round also softens the violated rows, 5 - d_0 <= 0 against d_0 <= 1 here: the
    step is the minimizer of g d + 1/2 d^T B d + (C_v + C_v,a d)^2 / (2 r) under the bounds
    and the other rows, r = `elastic` x C_v,a B^-1 C_v,a^T; against qpOASES. (The hard QP's
    step went past its bounds: multipliers 1e97 on the minimum-time reach, issue 49.)"""
    rng = np.random.default_rng(seed)
    n = 4
    M = rng.normal(size=(n, n))
    B, g = M @ M.T + 0.1 * np.eye(n), rng.normal(size=n)
    D, D_a = np.array([5.0, -1.0]), np.vstack([-np.eye(n)[0], rng.normal(size=n)])  # needs d_0 >= 5
    V, V_a = np.array([-1.0, -1.0]), np.vstack([np.eye(n)[0], -np.eye(n)[0]])  # |d_0| <= 1
    ev = Evaluation(
        xf=None, xf_a=None, tf=None, G=0.0, G_a=jnp.asarray(g), E=jnp.zeros(0), H=jnp.zeros((0, n)), status=None,
        D=jnp.asarray(D), D_a=jnp.asarray(D_a), V=jnp.asarray(V), V_a=jnp.asarray(V_a),
    )  # fmt: skip
    d, _ = _direction(ev, jnp.asarray(B), jnp.zeros(4), jnp.array([0.0, 1.0]), jnp.zeros((2, n)))
    r = KalmanSQP().elastic * float(D_a[0] @ np.linalg.solve(B, D_a[0]))
    # that QP with the softened row's residual as a variable s = (C_0 + C_0,a d) / sqrt(r)
    x = _qpoases(
        np.block([[B, np.zeros((n, 1))], [np.zeros((1, n)), np.eye(1)]]),
        np.concatenate([g, [0.0]]),
        np.hstack([D_a[:1], -np.sqrt(r) * np.eye(1)]),
        D[:1],
        np.concatenate([D[1:], V]),
        np.hstack([np.vstack([D_a[1:], V_a]), np.zeros((3, 1))]),
    )[:n]
    assert abs(x[0] - 1.0) < 1e-9  # on its bound, as near the reach as the bounds allow
    np.testing.assert_allclose(np.asarray(d), x, rtol=0, atol=1e-6 * (1.0 + np.max(np.abs(x))))


@pytest.mark.parametrize("seed", range(6))
def test_step_meets_the_equalities_through_nearly_flat_directions(seed):
    """B with two directions of curvature 1e-8 (its floor: a collapsed segment's level, a
    switch time between equal levels) and a gradient of 1e-6: the unconstrained step is ~100,
    the box |d_i| <= 1e-7 takes it back, and E ~ 1e-10 (the endgame of a minimum-time
    problem). Filtered through the covariance after E's rows only, the working rows left
    H d + E at up to 5 |E| (a pendulum's minimum time stalled at |E| = 1.9e-10 > ctol); E's
    rows and the working rows refined together from B^-1 meet both: H d = -E to 1e-2 |E|
    (measured <= 2e-3), the box to 1e-3 of its radius (`KalmanSQP.direction`'s test of a
    consistent step; the trust region scales the step to its radius)."""
    rng = np.random.default_rng(seed)
    n, radius = 8, 1e-7
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    B = Q @ np.diag([1.0, 2.0, 0.5, 3.0, 1e-8, 1e-8, 1.5, 1.0]) @ Q.T
    g, H, E = 1e-6 * rng.normal(size=n), rng.normal(size=(2, n)), 1e-10 * rng.normal(size=2)
    ev = Evaluation(
        xf=None, xf_a=None, tf=None, G=0.0, G_a=jnp.asarray(g), E=jnp.asarray(E), H=jnp.asarray(H), status=None,
        D=jnp.array([-1.0]), D_a=jnp.asarray(rng.normal(size=(1, n))),
    )  # fmt: skip
    d, _ = _direction(ev, jnp.asarray(B), jnp.zeros(3), jnp.array([0.0, 1.0]), jnp.zeros((2, n)), radius)
    d = np.asarray(d)
    assert np.max(np.abs(H @ d + E)) <= 1e-2 * np.max(np.abs(E))
    assert np.max(np.abs(d)) <= radius * (1 + 1e-3)
