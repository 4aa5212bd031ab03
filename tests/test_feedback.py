"""Linear-quadratic core (jaxtraj.feedback) against closed forms and scipy: the continuous
Riccati ODE (seed 001 eq. 1.44), the discrete recursion (1.23-1.24) and its stationary limit,
the multiplicative-noise gain (2.19), the additive-noise cost (2.20 / 3.87), zero-order hold,
and covariance propagation; then the trajectory layer: linearization against finite
differences and zoh_discretize, closed-loop reproduction of the reference, and Monte Carlo
statistics against propagated covariances."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import jaxtraj as jt
from jaxtraj.feedback import (
    ControlErrors,
    DiscreteLQRGains,
    ExecutionErrors,
    LQRGains,
    ThrustErrors,
    bryson_weights,
    continuous_lqr,
    discrete_lqr,
    linearize,
    monte_carlo,
    propagate_covariance,
    propagate_covariance_continuous,
    simulate_closed_loop,
    tracking_lqr,
    zoh_discretize,
)


def _rel(got, want):
    got, want = np.asarray(got), np.asarray(want)
    return float(np.max(np.abs(got - want)) / np.max(np.abs(want)))


def _scalar_riccati(t, a, b, q, r, qf, tf):
    """Closed form of -s' = 2 a s - (b^2/r) s^2 + q, s(tf) = qf. With tau = tf - t,
    beta = b^2/r and roots s+- = (a +- lam)/beta of beta s^2 - 2 a s - q, lam = sqrt(a^2 + beta q):
    d/dtau ln((s - s+)/(s - s-)) = -2 lam, so w = (s - s+)/(s - s-) = w(tf) e^{-2 lam tau} and
    s = (s+ - s- w) / (1 - w)."""
    beta = b * b / r
    lam = np.sqrt(a * a + beta * q)
    sp, sm = (a + lam) / beta, (a - lam) / beta
    w = (qf - sp) / (qf - sm) * np.exp(-2 * lam * (tf - t))
    return (sp - sm * w) / (1 - w)


def _rand_system(seed, n, m, rho=None):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    if rho is not None:
        A *= rho / np.max(np.abs(np.linalg.eigvals(A)))
    B = rng.normal(size=(n, m))
    L = rng.normal(size=(n, n))
    Q = L @ L.T / n + 0.1 * np.eye(n)
    M = rng.normal(size=(m, m))
    R = M @ M.T / m + 0.5 * np.eye(m)
    return A, B, Q, R


# ---------------------------------------------------------------------------------------------
# Continuous Riccati
# ---------------------------------------------------------------------------------------------


def _scalar(a, b):
    return lambda t: jnp.array([[a]]), lambda t: jnp.array([[b]])


def test_scalar_continuous_matches_closed_form():
    """S, K against the closed form; additive noise (intensity w) leaves them unchanged and adds
    c(t0) = int_t0^tf tr(S W) dt to the expected cost (seed eq. 3.87)."""
    a, b, q, r, qf, tf, w = 0.7, 1.3, 2.0, 0.5, 0.3, 2.0, 0.3
    g = continuous_lqr(*_scalar(a, b), [[q]], [[r]], [[qf]], 0.0, tf, noise=[[w]])
    s = _scalar_riccati(np.asarray(g.ts), a, b, q, r, qf, tf)
    assert g.S.dtype == jnp.float64 and g.K.shape == (101, 1, 1)
    assert _rel(g.S[:, 0, 0], s) < 1e-8
    assert _rel(g.K[:, 0, 0], b * s / r) < 1e-8
    c, _ = scipy.integrate.quad(lambda t: w * _scalar_riccati(t, a, b, q, r, qf, tf), 0.0, tf, epsabs=1e-14)
    assert abs(float(g.c[0]) - c) < 1e-9 * c and float(g.c[-1]) == 0.0
    assert abs(float(g.expected_cost(jnp.array([2.0]))) - (4 * s[0] + c)) < 1e-8
    # u = -K x, linear interpolation of K between samples
    mid = 0.5 * (g.ts[3] + g.ts[4])
    np.testing.assert_allclose(g.gain(g.ts[3]), g.K[3], rtol=1e-14)
    np.testing.assert_allclose(g.gain(mid), 0.5 * (g.K[3] + g.K[4]), rtol=1e-14)
    np.testing.assert_allclose(g.control(mid, jnp.array([2.0])), -2.0 * g.gain(mid)[:, 0], rtol=1e-14)


def test_jit_and_vmap_through_continuous():
    a, b, r, qf, tf = -0.3, 1.0, 1.0, 0.0, 1.0
    qs = jnp.array([0.5, 2.0, 8.0])
    run = lambda q: continuous_lqr(*_scalar(a, b), q * jnp.eye(1), r * jnp.eye(1), qf * jnp.eye(1), 0.0, tf).S[:, 0, 0]
    got = jax.jit(jax.vmap(run))(qs)
    ts = np.linspace(0.0, tf, 101)
    for q, s in zip(np.asarray(qs), got):
        assert _rel(s, _scalar_riccati(ts, a, b, q, r, qf, tf)) < 1e-8


def _tv_system(xp):
    A = lambda t: xp.array([[0.0, 1.0], [-1.0 - 0.5 * xp.sin(t), -0.1 * t]])
    B = lambda t: xp.array([[0.0], [1.0 + 0.3 * xp.cos(2 * t)]])
    Q = lambda t: xp.diag(xp.array([1.0 + t, 0.5]))  # time-varying weight (callable)
    return A, B, Q


def test_time_varying_continuous_vs_solve_ivp():
    R = np.array([[0.2]])
    Qf = np.array([[2.0, 0.3], [0.3, 1.0]])
    t0, tf = 0.0, 3.0
    g = continuous_lqr(*_tv_system(jnp), R, Qf, t0, tf)
    A, B, Q = _tv_system(np)

    def rhs(t, s):
        S = s.reshape(2, 2)
        An, Bn = A(t), B(t)
        return -(An.T @ S + S @ An - S @ Bn @ np.linalg.solve(R, Bn.T @ S) + Q(t)).ravel()

    ts = np.asarray(g.ts)
    ref = scipy.integrate.solve_ivp(rhs, (tf, t0), Qf.ravel(), method="DOP853", t_eval=ts[::-1], rtol=1e-12, atol=1e-14)
    S_ref = ref.y.T[::-1].reshape(-1, 2, 2)
    assert _rel(g.S, S_ref) < 5e-9
    np.testing.assert_array_equal(g.S, np.swapaxes(g.S, 1, 2))
    K_ref = np.stack([np.linalg.solve(R, B(t).T @ S) for t, S in zip(ts, S_ref)])
    assert _rel(g.K, K_ref) < 5e-9


def test_continuous_is_the_limit_of_discrete_zoh():
    """Discrete LQR on zoh_discretize(A, B, dt) with weights Q dt, R dt -> continuous LQR, O(dt)."""
    A = np.array([[0.0, 1.0], [-2.0, -0.3]])
    B = np.array([[0.0], [1.0]])
    Q, R, Qf, T = np.diag([1.0, 0.2]), np.array([[0.5]]), np.eye(2), 2.0
    g = continuous_lqr(
        lambda t: jnp.asarray(A),
        lambda t: jnp.asarray(B),
        Q,
        R,
        Qf,
        0.0,
        T,
        ts=jnp.linspace(0.0, T, 201),
    )
    errs = []
    for N in (50, 100, 200):
        dt = T / N
        Ad, Bd = zoh_discretize(A, B, dt)
        d = discrete_lqr(jnp.broadcast_to(Ad, (N, 2, 2)), jnp.broadcast_to(Bd, (N, 2, 1)), Q * dt, R * dt, Qf)
        every = 200 // N
        errs.append(max(_rel(d.K, g.K[:-1:every]), _rel(d.S, g.S[::every])))
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    assert errs[-1] < 2e-2
    assert np.all((ratios > 1.8) & (ratios < 2.2)), (errs, ratios)


# ---------------------------------------------------------------------------------------------
# Discrete Riccati
# ---------------------------------------------------------------------------------------------


def test_discrete_converges_to_dare():
    A, B, Q, R = _rand_system(0, 4, 2)
    N = 400
    d = discrete_lqr(np.broadcast_to(A, (N, 4, 4)), np.broadcast_to(B, (N, 4, 2)), Q, R, np.zeros((4, 4)))
    X = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ X @ B, B.T @ X @ A)
    assert d.S.shape == (N + 1, 4, 4) and d.K.shape == (N, 2, 4)
    assert _rel(d.S[0], X) < 1e-10
    assert _rel(d.K[0], K) < 1e-10
    np.testing.assert_array_equal(d.S[-1], 0.0)
    np.testing.assert_array_equal(d.c, 0.0)


def test_discrete_time_varying_first_steps_by_hand():
    rng = np.random.default_rng(1)
    As, Bs = rng.normal(size=(2, 3, 3)), rng.normal(size=(2, 3, 2))
    _, _, Q, R = _rand_system(1, 3, 2)
    Qf = np.eye(3)
    d = discrete_lqr(As, Bs, Q, R, Qf)
    S = Qf
    for k in (1, 0):  # seed eq. 1.23-1.24
        K = np.linalg.solve(R + Bs[k].T @ S @ Bs[k], Bs[k].T @ S @ As[k])
        S = Q + As[k].T @ S @ (As[k] - Bs[k] @ K)
        assert _rel(d.K[k], K) < 1e-12 and _rel(d.S[k], S) < 1e-12


def _mult_scalar_fixed_point(a, b, q, r, s2):
    """Positive root of S = q + a^2 S - (a b S)^2 / (r + b^2 S (1 + s2)): with c = b^2 (1 + s2),
    [c (1 - a^2) + a^2 b^2] S^2 + [r (1 - a^2) - q c] S - q r = 0."""
    c = b * b * (1 + s2)
    roots = np.roots([c * (1 - a * a) + a * a * b * b, r * (1 - a * a) - q * c, -q * r])
    S = float(np.max(roots.real))
    return S, a * b * S / (r + c * S)


def test_multiplicative_scalar_closed_form_and_gain_shrinks():
    # a^2 sigma^2 / (1 + sigma^2) < 1: mean-square stabilizable, so the recursion converges
    a, b, q, r, N = 1.05, 0.8, 1.0, 0.5, 400
    sig2 = jnp.array([0.0, 0.25, 1.0, 2.0])
    run = lambda s2: discrete_lqr(
        jnp.full((N, 1, 1), a), jnp.full((N, 1, 1), b), [[q]], [[r]], [[0.0]], multiplicative=s2
    )
    d = jax.jit(jax.vmap(run))(sig2)
    gains = np.asarray(d.K[:, 0, 0, 0])
    for i, s2 in enumerate(np.asarray(sig2)):
        S, k = _mult_scalar_fixed_point(a, b, q, r, s2)
        assert abs(float(d.S[i, 0, 0, 0]) - S) < 1e-10 * S
        assert abs(gains[i] - k) < 1e-10 * k
    assert abs(float(d.S[0, 0, 0, 0]) - scipy.linalg.solve_discrete_are([[a]], [[b]], [[q]], [[r]])[0, 0]) < 1e-10
    assert np.all(np.diff(gains) < 0)  # larger control-realization error -> more cautious gain


def test_multiplicative_matrix_form_generalizes_sigma2():
    """D = sigma B (one channel) is the seed's (1 + xi) u model; K = (R + (1+s2) B^T S B)^-1 ..."""
    A, B, Q, R = _rand_system(2, 3, 2, rho=0.9)
    N, s2 = 30, 0.3
    As, Bs = np.broadcast_to(A, (N, 3, 3)), np.broadcast_to(B, (N, 3, 2))
    d1 = discrete_lqr(As, Bs, Q, R, np.eye(3), multiplicative=s2)
    d2 = discrete_lqr(As, Bs, Q, R, np.eye(3), multiplicative=np.sqrt(s2) * B[None])
    d3 = discrete_lqr(As, Bs, Q, R, np.eye(3), multiplicative=np.full(N, s2))
    assert _rel(d2.K, d1.K) < 1e-12 and _rel(d3.K, d1.K) < 1e-14
    S1 = np.asarray(d1.S[1])  # seed eq. 2.19 at step 0
    K0 = np.linalg.solve(R + (1 + s2) * B.T @ S1 @ B, B.T @ S1 @ A)
    assert _rel(d1.K[0], K0) < 1e-12


def test_expected_cost_exact_by_enumeration():
    """Two-point noises have the right first two moments, so enumerating every path gives the
    exact expected cost: it equals x0^T S0 x0 + c0 (seed eq. 2.14, 2.20), and perturbing any
    gain increases it (the gains are optimal among linear feedbacks)."""
    A = np.array([[1.0, 0.2], [-0.3, 0.9]])
    B = np.array([[0.1], [0.6]])
    Q, R, Qf = np.diag([1.0, 0.1]), np.array([[0.3]]), np.diag([4.0, 1.0])
    W = np.array([[0.04, 0.01], [0.01, 0.09]])
    Lw, s2, N, x0 = np.linalg.cholesky(W), 0.5, 3, np.array([1.0, -2.0])
    As, Bs = np.broadcast_to(A, (N, 2, 2)), np.broadcast_to(B, (N, 2, 1))
    d = discrete_lqr(As, Bs, Q, R, Qf, multiplicative=s2, additive=W)

    def expected_cost(Ks):
        total = 0.0
        outcomes = list(itertools.product([-1.0, 1.0], repeat=3))  # (xi, e1, e2) per step
        for path in itertools.product(outcomes, repeat=N):
            x, J = x0, 0.0
            for k, (xi, *e) in enumerate(path):
                u = -Ks[k] @ x
                J += x @ Q @ x + u @ R @ u
                x = A @ x + B @ ((1 + np.sqrt(s2) * xi) * u) + Lw @ np.array(e)
            total += J + x @ Qf @ x
        return total / len(outcomes) ** N

    K = np.asarray(d.K)
    J = expected_cost(K)
    assert abs(J - float(d.expected_cost(jnp.asarray(x0)))) < 1e-12 * J
    assert float(d.c[0]) > 0 and abs(float(d.c[0]) - sum(np.trace(d.S[k + 1] @ W) for k in range(N))) < 1e-14
    for k in range(N):
        for delta in (-1e-3, 1e-3):
            Kp = K.copy()
            Kp[k, 0, 0] += delta
            assert expected_cost(Kp) > J
    # additive noise changes only the cost, not the gains
    d0 = discrete_lqr(As, Bs, Q, R, Qf, multiplicative=s2)
    np.testing.assert_allclose(d0.K, d.K, rtol=1e-14)
    np.testing.assert_allclose(d0.S, d.S, rtol=1e-14)


# ---------------------------------------------------------------------------------------------
# Zero-order hold and covariance
# ---------------------------------------------------------------------------------------------


def test_zoh_double_integrator():
    dt = 0.3
    Ad, Bd = zoh_discretize(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), dt)
    np.testing.assert_allclose(Ad, [[1.0, dt], [0.0, 1.0]], atol=1e-15)
    np.testing.assert_allclose(Bd, [[dt * dt / 2], [dt]], atol=1e-15)
    A = np.array([[-0.5, 2.0], [-1.0, 0.1]])
    Ad, Bd = zoh_discretize(A, np.eye(2), dt)  # Bd = A^-1 (e^{A dt} - I)
    np.testing.assert_allclose(Bd, np.linalg.solve(A, scipy.linalg.expm(A * dt) - np.eye(2)), rtol=1e-13)


def test_propagate_covariance_stationary_is_discrete_lyapunov():
    rng = np.random.default_rng(3)
    F = rng.normal(size=(3, 3))
    F *= 0.8 / np.max(np.abs(np.linalg.eigvals(F)))
    G, W = rng.normal(size=(3, 2)), np.array([[0.5, 0.1], [0.1, 0.2]])
    Ps = propagate_covariance(np.eye(3), np.broadcast_to(F, (300, 3, 3)), W, G)
    assert Ps.shape == (301, 3, 3)
    np.testing.assert_allclose(Ps[1], F @ F.T + G @ W @ G.T, rtol=1e-14)
    assert _rel(Ps[-1], scipy.linalg.solve_discrete_lyapunov(F, G @ W @ G.T)) < 1e-10


def test_propagate_covariance_continuous_stationary_is_lyapunov():
    F = np.array([[-1.0, 2.0], [-0.5, -1.5]])
    W = np.array([[0.3, 0.05], [0.05, 0.2]])
    _, Ps = propagate_covariance_continuous(np.zeros((2, 2)), lambda t: jnp.asarray(F), W, 0.0, 40.0)
    assert _rel(Ps[-1], scipy.linalg.solve_continuous_lyapunov(F, -W)) < 1e-9


def test_closed_loop_covariance_matches_monte_carlo():
    A, B, Q, R = _rand_system(4, 2, 1)
    N, W = 20, np.diag([0.01, 0.04])
    As, Bs = np.broadcast_to(A, (N, 2, 2)), np.broadcast_to(B, (N, 2, 1))
    d = discrete_lqr(As, Bs, Q, R, np.eye(2), additive=W)
    Ps = propagate_covariance(np.zeros((2, 2)), As - Bs @ d.K, W)

    def rollout(key):
        def step(x, inp):
            K, e = inp
            return A @ x - B @ (K @ x) + e, None

        e = jax.random.normal(key, (N, 2)) @ jnp.sqrt(jnp.asarray(W))
        return jax.lax.scan(step, jnp.ones(2), (d.K, e))[0]

    xs = jax.vmap(rollout)(jax.random.split(jax.random.key(0), 20000))
    np.testing.assert_allclose(
        np.mean(xs, 0), np.ones(2) @ np.linalg.multi_dot(list((As - Bs @ d.K)[::-1])).T, atol=0.01
    )
    assert _rel(np.cov(np.asarray(xs).T), Ps[-1]) < 0.05


# ---------------------------------------------------------------------------------------------
# Transforms and errors
# ---------------------------------------------------------------------------------------------


def test_shape_errors_name_the_argument():
    A, B = jnp.eye(2)[None], jnp.ones((1, 2, 1))
    ok = {"Q": jnp.eye(2), "R": jnp.eye(1), "Qf": jnp.eye(2)}
    with pytest.raises(ValueError, match="`Bs`"):
        discrete_lqr(A, jnp.ones((1, 3, 1)), **ok)
    with pytest.raises(ValueError, match="`R`"):
        discrete_lqr(A, B, jnp.eye(2), jnp.eye(2), jnp.eye(2))
    with pytest.raises(ValueError, match="`Qf`"):
        discrete_lqr(A, B, jnp.eye(2), jnp.eye(1), jnp.eye(3))
    with pytest.raises(ValueError, match="`multiplicative`"):
        discrete_lqr(A, B, **ok, multiplicative=jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="`additive`"):
        discrete_lqr(A, B, **ok, additive=jnp.eye(3))
    with pytest.raises(ValueError, match="`B_fn`"):
        continuous_lqr(
            lambda t: jnp.eye(2),
            lambda t: jnp.ones((3, 1)),
            jnp.eye(2),
            jnp.eye(1),
            jnp.eye(2),
            0.0,
            1.0,
        )
    with pytest.raises(ValueError, match="`Q`"):
        continuous_lqr(
            lambda t: jnp.eye(2),
            lambda t: jnp.ones((2, 1)),
            jnp.eye(3),
            jnp.eye(1),
            jnp.eye(2),
            0.0,
            1.0,
        )
    with pytest.raises(ValueError, match="`B`"):
        zoh_discretize(jnp.eye(2), jnp.ones((3, 1)), 0.1)
    with pytest.raises(ValueError, match="`W`"):
        propagate_covariance(jnp.eye(2), A, jnp.eye(3))


# ---------------------------------------------------------------------------------------------
# Linearization, closed-loop simulation, Monte Carlo
# ---------------------------------------------------------------------------------------------
#
# Statistical bound used below: for n i.i.d. Gaussian samples of x ~ N(mu, P), the sample mean
# has standard deviation sqrt(P_ii / n) and the unbiased sample covariance S has
# Var(S_ij) = (P_ij^2 + P_ii P_jj) / (n - 1) (Wishart). We require every entry within 5 of
# these standard deviations (a false alarm per entry has probability < 6e-7 for a fresh seed;
# the seeds are fixed, so the tests are deterministic).


def _within_5_sigma(samples, mu, P):
    n = samples.shape[0]
    mean, S = np.mean(samples, axis=0), np.cov(samples.T)
    d = np.diag(P)
    assert np.all(np.abs(mean - mu) <= 5 * np.sqrt(d / n)), (mean, mu)
    sd = np.sqrt((P**2 + np.outer(d, d)) / (n - 1))
    assert np.all(np.abs(S - P) <= 5 * sd), (S, P, sd)


def _linear_dynamics(t, x, u, args):
    return args["A"] @ x + args["B"] @ u


def _identity_terminal(tf, xf, args):
    return xf


def _linear_problem(A, B):
    return jt.Problem(
        _linear_dynamics,
        x0=[1.0, 0.0],
        terminal=_identity_terminal,
        constraint_names=("x1", "x2"),
        args={"A": jnp.asarray(A), "B": jnp.asarray(B)},
    )


# Double integrator (neutrally stable: open-loop dispersion grows like t^3), sampled at 50
# control samples over tf = 2 (RK4(25) on 2 segments).
_DI_A, _DI_B = np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]])
_DI_CTRL, _DI_PARAMS, _DI_SIM = jt.controls.PiecewiseLinear(2), [0.5, -0.3, 0.2, 2.0], jt.RK4(25)
_DI_W, _DI_P0, _DI_SIGMA_U = np.diag([0.01, 0.04]), np.diag([0.01, 0.02]), 0.1


@pytest.fixture(scope="module")
def double_integrator():
    prob = _linear_problem(_DI_A, _DI_B)
    lin = linearize(prob, _DI_CTRL, _DI_PARAMS, simulator=_DI_SIM, execution=ControlErrors(additive=_DI_SIGMA_U))
    gains = tracking_lqr(lin, np.eye(2), 0.1 * np.eye(1), 10 * np.eye(2))
    noise = {
        "execution": ControlErrors(additive=_DI_SIGMA_U),
        "process_noise": _DI_W,
        "initial_covariance": _DI_P0,
        "simulator": _DI_SIM,
    }
    key = jax.random.key(42)
    runs = {
        "open": monte_carlo(prob, _DI_CTRL, _DI_PARAMS, key, 4000, **noise),
        "closed": monte_carlo(prob, _DI_CTRL, _DI_PARAMS, key, 4000, gains=gains, **noise),
    }
    return prob, lin, gains, runs


def _propagated(lin, K):
    """Covariance of the sampled loop from the independent ZOH matrices (expm):
    x_{k+1} = (Ad - Bd K_k) x_k + Gd w_k + Bd sigma xi_k, w_k ~ N(0, W / dt) (process noise
    held over a sample), xi_k ~ N(0, 1)."""
    dt = float(lin.dt[0])
    Ad, Bd = zoh_discretize(_DI_A, _DI_B, dt)
    _, Gd = zoh_discretize(_DI_A, np.eye(2), dt)
    G = jnp.concatenate([Gd, Bd], axis=1)
    Wk = scipy.linalg.block_diag(_DI_W / dt, [[_DI_SIGMA_U**2]])
    N = lin.dt.shape[0]
    F = jnp.broadcast_to(Ad, (N, 2, 2)) - (0.0 if K is None else Bd @ K)
    return propagate_covariance(_DI_P0, F, Wk, G)[-1], (Ad, Bd, Gd)


@pytest.mark.parametrize("loop", ["open", "closed"])
def test_monte_carlo_of_linear_system_matches_propagated_covariance(double_integrator, loop):
    """Mean = the noise-free reference, covariance = propagate_covariance, within 5 sigma of
    the sample estimators (see the bound above)."""
    _, lin, gains, runs = double_integrator
    r = runs[loop]
    P, (Ad, Bd, Gd) = _propagated(lin, gains.K if loop == "closed" else None)
    # the sampled-data linearization is the ZOH discretization (RK4 vs expm: O(dt^5) per step)
    assert _rel(lin.Ad, np.broadcast_to(Ad, lin.Ad.shape)) < 1e-8
    assert _rel(lin.Bd, np.broadcast_to(Bd, lin.Bd.shape)) < 1e-8
    assert _rel(lin.Gd, np.broadcast_to(Gd, lin.Gd.shape)) < 1e-8
    assert int(r.num_failed) == 0 and r.final_states.shape == (4000, 2)
    _within_5_sigma(np.asarray(r.final_states), np.asarray(lin.x[-1]), np.asarray(P))
    np.testing.assert_allclose(r.terminal_errors, r.final_states)  # E = x(tf) here
    np.testing.assert_allclose(r.terminal_covariance, np.cov(np.asarray(r.final_states).T))
    # the library's own linear covariance analysis agrees with the independent one
    Pl = lin.predict_covariance(gains if loop == "closed" else None, initial_covariance=_DI_P0, process_noise=_DI_W)
    assert Pl.shape == (51, 2, 2) and _rel(Pl[-1], P) < 1e-7


def test_closed_loop_shrinks_terminal_covariance_of_neutrally_stable_system(double_integrator):
    _, _, _, runs = double_integrator
    open_, closed = runs["open"], runs["closed"]
    assert np.trace(closed.terminal_covariance) < 0.1 * np.trace(open_.terminal_covariance)
    assert np.all(open_.correction_rms == 0.0) and np.all(closed.correction_rms > 0.0)
    # percentiles bracket the median, which is near the mean for a Gaussian
    pct = np.asarray(closed.terminal_percentiles)
    assert pct.shape == (5, 2) and np.all(np.diff(pct, axis=0) > 0)
    assert np.all(np.abs(pct[2] - closed.terminal_mean) < 0.1 * closed.terminal_std)


def test_monte_carlo_reproducible_and_run_i_independent_of_n():
    prob = _linear_problem(_DI_A, _DI_B)
    kw = {"process_noise": _DI_W, "simulator": _DI_SIM, "return_trajectories": True}
    a = monte_carlo(prob, _DI_CTRL, _DI_PARAMS, jax.random.key(7), 20, **kw)
    b = monte_carlo(prob, _DI_CTRL, _DI_PARAMS, jax.random.key(7), 20, **kw)
    np.testing.assert_array_equal(a.final_states, b.final_states)
    d = a.dispersion
    assert d.percentiles.shape == (5, 51, 2) and d.mean.shape == (51, 2)
    e = monte_carlo(prob, _DI_CTRL, _DI_PARAMS, jax.random.key(7), 20, dispersion_stride=20, **kw)
    np.testing.assert_array_equal(e.dispersion.t, d.t[np.array([0, 20, 40, 50])])
    np.testing.assert_array_equal(e.dispersion.percentiles, d.percentiles[:, [0, 20, 40, 50]])
    np.testing.assert_allclose(d.mean[-1], np.mean(a.final_states, axis=0), rtol=1e-12)
    np.testing.assert_array_equal(d.mean[0], prob.x0)  # no initial dispersion
    # run i = simulate_closed_loop with the key fold_in(key, i): it does not depend on n
    one = simulate_closed_loop(
        prob,
        _DI_CTRL,
        _DI_PARAMS,
        jax.random.fold_in(jax.random.key(7), 3),
        process_noise=_DI_W,
        simulator=_DI_SIM,
    )
    np.testing.assert_allclose(one.xf, a.final_states[3], rtol=1e-13)
    np.testing.assert_allclose(one.x[-1], one.xf, rtol=0)


def test_bias_execution_error_and_user_execution_model():
    """correlation_time = inf: xi is drawn once per run, so the terminal deviation of a
    linear system is a fixed vector times one scalar: a rank-one covariance. A user-defined
    ExecutionErrors with the same formula gives the same runs."""
    prob = _linear_problem(_DI_A, _DI_B)
    args = (prob, _DI_CTRL, _DI_PARAMS, jax.random.key(1), 4000)
    # zero process noise and initial covariance: the open-loop configuration of the fixture
    # (compiled once; correlation_time is traced)
    zero = np.zeros((2, 2))
    kw = {"correlation_time": jnp.inf, "simulator": _DI_SIM, "process_noise": zero}
    kw["initial_covariance"] = zero
    r = monte_carlo(*args, execution=ControlErrors(additive=_DI_SIGMA_U), **kw)
    ev = np.linalg.eigvalsh(np.asarray(r.terminal_covariance))
    assert ev[0] < 1e-12 * ev[1] and ev[1] > 0
    custom = ExecutionErrors(lambda t, u, xi, args: (u + _DI_SIGMA_U * xi[1:], args), 2)
    c = monte_carlo(*args, execution=custom, **kw)
    np.testing.assert_allclose(c.final_states, r.final_states, rtol=1e-14)


_EM_SIM = jt.RK4(10)  # 70 control samples on case 5: cheap, enough for these checks


@pytest.fixture(scope="module")
def earth_mars():
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(5)
    lin = linearize(prob, ctrl, a0, simulator=_EM_SIM, execution=ThrustErrors(0.002, 0.2))
    return prob, ctrl, a0, lin


def test_linearization_matches_finite_differences(earth_mars):
    prob, ctrl, a0, lin = earth_mars
    ref = jt.simulate(prob, ctrl, a0, simulator=_EM_SIM)
    # the reference is jt.simulate's RK4 solution (bit for bit), on the step boundaries
    np.testing.assert_array_equal(lin.x[-1], ref.xf)
    np.testing.assert_array_equal(lin.x[10], ref.x[11])  # ref.x repeats each knot
    assert lin.status == jt.Status.SUCCESS
    f = lambda t, x, u: np.asarray(prob.dynamics(t, jnp.asarray(x), jnp.asarray(u), prob.args))
    for k in (0, 13, 35, 70):
        t, x, u = float(lin.t[k]), np.asarray(lin.x[k]), np.asarray(lin.u[k])
        A = np.stack([(f(t, x + e, u) - f(t, x - e, u)) / 2e-6 for e in 1e-6 * np.eye(3)], 1)
        B = ((f(t, x, u + 1e-6) - f(t, x, u - 1e-6)) / 2e-6)[:, None]
        assert _rel(lin.A[k], A) < 1e-8 and _rel(lin.B[k], B) < 1e-8
    np.testing.assert_allclose(lin.A_fn(0.5 * (lin.t[3] + lin.t[4])), 0.5 * (lin.A[3] + lin.A[4]))
    assert lin.Ed.shape == (70, 3, 2) and lin.Gd.shape == (70, 3, 3)


def test_zero_noise_closed_loop_reproduces_reference(earth_mars):
    prob, ctrl, a0, lin = earth_mars
    T = float(lin.t[-1])
    Q, R, Qf = bryson_weights(lin, 1e-3, 0.05, [1e-4, 1e-4, 1e-4])
    np.testing.assert_allclose(Q, np.eye(3) / (T * 1e-6), rtol=1e-14)
    np.testing.assert_allclose(R, np.eye(1) / (T * 0.05**2), rtol=1e-14)
    np.testing.assert_allclose(Qf, np.eye(3) / 1e-8, rtol=1e-14)
    gains = tracking_lqr(lin, Q, R, Qf)
    assert isinstance(gains, DiscreteLQRGains) and gains.K.shape == (70, 1, 3)
    xf = jt.simulate(prob, ctrl, a0, simulator=_EM_SIM).xf
    r = monte_carlo(prob, ctrl, a0, jax.random.key(0), 3, gains=gains, simulator=_EM_SIM)
    assert np.max(np.abs(np.asarray(r.final_states) - np.asarray(xf))) < 1e-8
    assert np.max(np.abs(r.correction_rms)) < 1e-8
    one = simulate_closed_loop(prob, ctrl, a0, None, gains=gains, simulator=_EM_SIM)
    assert np.max(np.abs(one.x - lin.x)) < 1e-8 and one.u.shape == (70, 1)


def test_earth_mars_open_loop_covariance_matches_linear_analysis(earth_mars):
    """Small thrust errors (0.2 %, 0.2 deg): the nonlinear Monte Carlo agrees with the linear
    covariance analysis (lin.Ad, lin.Ed) within the 5-sigma sampling bound; this checks the
    execution-error model and its Jacobian Ed."""
    prob, ctrl, a0, lin = earth_mars
    r = monte_carlo(
        prob,
        ctrl,
        a0,
        jax.random.key(3),
        4000,
        sigma_thrust=0.002,
        sigma_pointing_deg=0.2,
        simulator=_EM_SIM,
    )
    P = np.asarray(lin.predict_covariance())[-1]
    _within_5_sigma(np.asarray(r.final_states), np.asarray(lin.x[-1]), P)


def test_continuous_gains_close_to_sampled_gains(double_integrator):
    _, lin, gains, _ = double_integrator
    g = tracking_lqr(lin, np.eye(2), 0.1 * np.eye(1), 10 * np.eye(2), discrete=False)
    assert isinstance(g, LQRGains) and g.K.shape == (51, 1, 2)
    A, B, Q, R = _DI_A, _DI_B, np.eye(2), 0.1 * np.eye(1)

    def rhs(t, s):
        S = s.reshape(2, 2)
        return -(A.T @ S + S @ A - S @ B @ np.linalg.solve(R, B.T @ S) + Q).ravel()

    ts = np.asarray(lin.t)
    sol = scipy.integrate.solve_ivp(
        rhs, (2.0, 0.0), 10 * np.eye(2).ravel(), "DOP853", t_eval=ts[::-1], rtol=1e-12, atol=1e-14
    )
    K = np.stack([np.linalg.solve(R, B.T @ S.reshape(2, 2)) for S in sol.y.T[::-1]])
    assert _rel(g.K, K) < 1e-8
    # the sampled (ZOH) gains differ from the continuous ones by O(dt |A - B K|) (dt = 0.04,
    # |A - B K| ~ 5 here; convergence in dt: test_continuous_is_the_limit_of_discrete_zoh)
    assert _rel(gains.K, g.K[:-1]) < 0.15


def test_monte_carlo_argument_errors():
    prob = _linear_problem(_DI_A, _DI_B)
    args = (prob, _DI_CTRL, _DI_PARAMS, jax.random.key(0))
    with pytest.raises(ValueError, match="`n`"):
        monte_carlo(*args, 1)
    with pytest.raises(ValueError, match="`simulator`"):
        monte_carlo(*args, 10, simulator=jt.Diffrax())
    with pytest.raises(ValueError, match="`gains`"):
        monte_carlo(*args, 10, gains=np.zeros((7, 1, 2)))
    with pytest.raises(ValueError, match="thrust"):
        monte_carlo(*args, 10, sigma_thrust=0.01)
    with pytest.raises(ValueError, match="not both"):
        monte_carlo(*args, 10, sigma_pointing_deg=1.0, execution=ControlErrors(0.1))
    with pytest.raises(ValueError, match="`process_noise`"):
        monte_carlo(*args, 10, process_noise=-np.eye(2))
    with pytest.raises(ValueError, match="`additive`"):
        monte_carlo(*args, 10, execution=ControlErrors(additive=[0.1, 0.2]))
    # a zero shorthand given as an array is no declared error (it was refused: "not both")
    zero = dict(sigma_thrust=jnp.asarray(0.0), sigma_pointing_deg=np.float64(0.0))
    mc = monte_carlo(*args, 10, execution=ControlErrors(0.1), **zero)
    assert np.all(np.isfinite(np.asarray(mc.final_states)))


@pytest.mark.parametrize(
    ("weights", "message"),
    [
        ((np.full((2, 2), np.nan), 0.1 * np.eye(1), np.eye(2)), r"`Q` must be finite"),
        ((np.eye(2), -np.eye(1), np.eye(2)), r"`R` must be positive definite; its least eigenvalue is -1"),
        ((-np.eye(2), np.eye(1), np.eye(2)), r"`Q` must be positive semidefinite"),
        ((np.eye(2), np.eye(1), np.array([[1.0, 2.0], [0.0, 1.0]])), r"`Qf` must be symmetric"),
        # None or text gave JAX's "None is not a valid value for jnp.array" (issue 51, third audit)
        ((np.eye(2), np.eye(1), None), r"`Qf` must be an array of numbers; got None"),
        (("Q", np.eye(1), np.eye(2)), r"`Q` must be an array of numbers; got 'Q'"),
    ],
)
def test_lqr_weights_are_checked(weights, message):
    """Issue 51's re-audit: NaN or indefinite weights gave NaN or meaningless gains, and every
    Monte Carlo run then failed without a word."""
    lin = linearize(_linear_problem(_DI_A, _DI_B), _DI_CTRL, _DI_PARAMS, simulator=_DI_SIM)
    with pytest.raises(ValueError, match=message):
        tracking_lqr(lin, *weights)
    with pytest.raises(ValueError, match=r"`state_scale` must be finite and > 0"):
        bryson_weights(lin, 0.0, 0.05, 1e-4)


@pytest.mark.parametrize(
    ("noise", "message"),
    [
        ({"initial_covariance": np.full((2, 2), np.nan)}, r"`initial_covariance` must be finite"),
        ({"process_noise": -np.eye(2)}, r"`process_noise` must be positive semidefinite"),
        ({"execution": ControlErrors(additive=0.1), "process_noise": np.eye(2)}, None),
    ],
)
def test_monte_carlo_noise_is_checked(noise, message):
    """Issue 51's re-audit: a NaN covariance made every run fail and reported the spread as
    -0; it is refused, and a spread without two finite runs is NaN, never 0."""
    prob = _linear_problem(_DI_A, _DI_B)
    if message is not None:
        with pytest.raises(ValueError, match=message):
            monte_carlo(prob, _DI_CTRL, _DI_PARAMS, jax.random.key(0), 4, simulator=_DI_SIM, **noise)
        return
    with pytest.raises(ValueError, match=r"`sigma_pointing_deg` must be finite and >= 0; got inf"):
        ThrustErrors(0.01, np.inf)
    # ControlErrors took NaN (every run failed), inf and negative sigmas (issue 51, third audit)
    for kwargs, text in (
        ({"multiplicative": np.nan}, r"`multiplicative` must be finite and >= 0; got nan"),
        ({"additive": [0.1, -0.1]}, r"`additive` must be finite and >= 0; got \[ 0\.1 -0\.1\]"),
        ({"additive": np.inf}, r"`additive` must be finite and >= 0; got inf"),
        ({"multiplicative": "x"}, r"`multiplicative` must be an array of numbers; got 'x'"),
    ):
        with pytest.raises(ValueError, match=text):
            ControlErrors(**kwargs)
    for key, text in (
        (2**70, r"`key` as an int seed must be in 0\.\.2\*\*64 - 1"),
        ("k", r"`key` must be a JAX PRNG key"),
        # None gave JAX's "unexpected PRNG key type" from inside the runs (issue 51, fourth audit)
        (None, r"`key` must be a JAX PRNG key .*got None"),
    ):
        with pytest.raises(ValueError, match=text):
            monte_carlo(prob, _DI_CTRL, _DI_PARAMS, key, 4, simulator=_DI_SIM, **noise)
    runs = monte_carlo(prob, _DI_CTRL, _DI_PARAMS, jax.random.key(0), 4, simulator=_DI_SIM, **noise)
    assert int(runs.num_failed) == 0 and np.all(np.asarray(runs.terminal_std) > 0)
    from jaxtraj.feedback._monte_carlo import masked_stats

    one_finite = np.array([True, False, False])
    _, cov, _ = masked_stats(jnp.ones((3, 2)), jnp.asarray(one_finite), jnp.array([50.0]))
    assert np.all(np.isnan(np.asarray(cov)))


def test_closed_loop_and_monte_carlo_name_what_jax_would_not():
    """Issue 51's fourth audit: `simulate_closed_loop(key=None)` dropped declared noise
    without a word, and a text or None `correlation_time` gave JAX's messages."""
    prob = _linear_problem(_DI_A, _DI_B)
    with pytest.raises(ValueError, match=r"`key` is None .*`initial_covariance` declare\(s\) noise"):
        simulate_closed_loop(prob, _DI_CTRL, _DI_PARAMS, None, initial_covariance=np.eye(2), simulator=_DI_SIM)
    quiet = simulate_closed_loop(prob, _DI_CTRL, _DI_PARAMS, None, simulator=_DI_SIM)  # (no noise: as before)
    assert np.all(np.isfinite(np.asarray(quiet.x)))
    for value in ("x", None):
        with pytest.raises(ValueError, match=r"`correlation_time` must be a number >= 0"):
            monte_carlo(prob, _DI_CTRL, _DI_PARAMS, 0, 4, simulator=_DI_SIM, correlation_time=value)
