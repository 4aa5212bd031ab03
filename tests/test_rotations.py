"""Rotations (jaxtraj.rotations): kinematics, conversions, scipy cross-check, seed-002 data."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxtraj  # noqa: F401  (turns on float64)
from jaxtraj import rotations as rot

N = 2000  # random samples per round-trip test
RNG = np.random.default_rng(20240502)
QS = RNG.normal(size=(N, 4))
QS /= np.linalg.norm(QS, axis=1, keepdims=True)
# Special quaternions: identity, half-turns (q4 = 0, Shepperd's hard case), tiny angles, and
# attitudes at / next to gimbal lock (theta = +-90 deg, +-(90 - 1e-7) deg).
_gl = [
    (a, s * (np.pi / 2 - d), b) for a, b in [(0.3, -1.2), (2.0, 2.5)] for s in (1, -1) for d in (0, 1e-7 * np.pi / 180)
]
SPECIAL = np.concatenate(
    [
        np.eye(4),
        np.c_[RNG.normal(size=(5, 3)), np.zeros(5)],
        np.c_[1e-9 * RNG.normal(size=(5, 3)), np.ones(5)],
        np.array([[0.0, 0.0, 1.0, 1e-17], [1.0, 1e-17, 0.0, 0.0]]),
        np.stack([Rotation.from_euler("ZYX", e).as_quat() for e in _gl]),
    ]
)
SPECIAL /= np.linalg.norm(SPECIAL, axis=1, keepdims=True)
ALL_QS = np.concatenate([QS, SPECIAL])

# Seed 002, sec. 5: boundary attitudes of the satellite manoeuvre (as printed, not unit).
SEED_Q0 = np.array([0.0, 0.258, 0.993, 0.025])
SEED_QF = np.array([0.025, 0.025, 0.999, 0.025])


def same_up_to_sign(a, b):
    """Max distance between quaternion rows of `a` and `b`, either sign of `b` allowed."""
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.minimum(np.abs(a - b).max(-1), np.abs(a + b).max(-1)))


def wrap(x):
    """Angle differences mapped to [-pi, pi] without losing small values."""
    x = np.asarray(x)
    return np.arctan2(np.sin(x), np.cos(x))


def tumbling_w(t):
    """A tumbling body-frame angular velocity (rad/s), smooth in t."""
    return jnp.stack([0.3 * jnp.sin(0.7 * t), 0.2 * jnp.cos(0.3 * t) - 0.1, 0.15 + 0.05 * jnp.sin(t)])


# --------------------------------------------------------------------------------------------
# Omega(w) and the quaternion product
# --------------------------------------------------------------------------------------------


def test_omega_matrix_structure():
    ws = RNG.normal(size=(50, 3))
    om = jax.vmap(rot.omega_matrix)(ws)
    np.testing.assert_array_equal(om, -np.swapaxes(om, 1, 2))  # antisymmetric: |q| conserved
    sq = np.einsum("nij,njk->nik", om, om)
    np.testing.assert_allclose(sq, -np.sum(ws**2, 1)[:, None, None] * np.eye(4), atol=1e-14)
    w1, w2, w3 = ws[0]
    explicit = [[0, w3, -w2, w1], [-w3, 0, w1, w2], [w2, -w1, 0, w3], [-w1, -w2, -w3, 0]]
    np.testing.assert_array_equal(om[0], explicit)
    # The seed's OCR of eq. 4 differs in exactly one entry: (1, 3) printed +w2, which would
    # break antisymmetry.
    seed_ocr = [[0, w3, w2, w1], [-w3, 0, w1, w2], [w2, -w1, 0, w3], [-w1, -w2, -w3, 0]]
    assert np.argwhere(~np.isclose(om[0], seed_ocr)).tolist() == [[0, 2]]
    # Omega(w) q == q * (w, 0): body-frame w multiplies on the right.
    for q, w in zip(QS[:20], ws[:20]):
        right = rot.quaternion_multiply(q, jnp.append(w, 0.0))
        np.testing.assert_allclose(rot.omega_matrix(w) @ q, right, atol=1e-15)
        np.testing.assert_allclose(rot.quaternion_rate(q, w), 0.5 * right, atol=1e-15)


def test_quaternion_product_composes_matrices_and_conjugate_inverts():
    p, q = QS[:200], QS[200:400]
    pq = jax.vmap(rot.quaternion_multiply)(p, q)
    to_m = jax.vmap(rot.quaternion_to_matrix)
    np.testing.assert_allclose(to_m(pq), np.einsum("nij,njk->nik", to_m(p), to_m(q)), atol=1e-14)
    ident = jax.vmap(rot.quaternion_multiply)(q, jax.vmap(rot.quaternion_conjugate)(q))
    np.testing.assert_allclose(ident, np.tile([0.0, 0, 0, 1], (200, 1)), atol=1e-15)
    # R(q) v == vec(q * (v, 0) * conj(q)) and rotate_vector is R(q) v.
    v = RNG.normal(size=3)
    qvq = rot.quaternion_multiply(rot.quaternion_multiply(q[0], jnp.append(v, 0.0)), rot.quaternion_conjugate(q[0]))
    np.testing.assert_allclose(qvq[:3], to_m(q[:1])[0] @ v, atol=1e-14)
    np.testing.assert_allclose(rot.rotate_vector(q[0], v), qvq[:3], atol=1e-14)


# --------------------------------------------------------------------------------------------
# Kinematics: pointwise derivative identities
# --------------------------------------------------------------------------------------------


def test_quaternion_kinematics_give_matrix_kinematics():
    """d/dt R(q(t)) along q' = quaternion_rate(q, w) equals R skew(w) (jax.jvp)."""

    def residual(q, w):
        R, Rdot = jax.jvp(rot.quaternion_to_matrix, (q,), (rot.quaternion_rate(q, w),))
        return Rdot - R @ rot.skew(w)

    ws = RNG.normal(size=(300, 3))
    assert np.abs(jax.vmap(residual)(QS[:300], ws)).max() < 1e-14
    # Also for a non-unit q (quaternion_to_matrix normalizes): the radial part of q' is zero.
    assert np.abs(residual(3.0 * QS[0], ws[0])).max() < 1e-14


def test_euler_rate_is_seed_eq5_and_matches_its_derivation():
    es = np.c_[RNG.uniform(-np.pi, np.pi, 300), RNG.uniform(-1.4, 1.4, 300), RNG.uniform(-np.pi, np.pi, 300)]
    ws = RNG.normal(size=(300, 3))
    rates = jax.vmap(rot.euler_zyx_rate)(es, ws)
    for (_psi, th, ph), w, r in zip(es[:50], ws[:50], rates[:50]):
        M = np.array(  # seed eq. 5, vector (phi, theta, psi)
            [
                [1, np.tan(th) * np.sin(ph), np.tan(th) * np.cos(ph)],
                [0, np.cos(ph), -np.sin(ph)],
                [0, np.sin(ph) / np.cos(th), np.cos(ph) / np.cos(th)],
            ]
        )
        np.testing.assert_allclose(r[::-1], M @ w, rtol=1e-13, atol=1e-13)

    def residual(e, w):
        R, Rdot = jax.jvp(rot.euler_zyx_to_matrix, (e,), (rot.euler_zyx_rate(e, w),))
        return R.T @ Rdot - rot.skew(w)

    assert np.abs(jax.vmap(residual)(es, ws)).max() < 1e-12


# --------------------------------------------------------------------------------------------
# Kinematics: integrated with diffrax (one jitted solve for quaternion, matrix and Euler ODEs)
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tumble():
    e0 = jnp.array([0.4, 0.3, -0.5])
    y0 = {"q": rot.euler_zyx_to_quaternion(e0), "R": rot.euler_zyx_to_matrix(e0), "e": e0}
    ts = jnp.linspace(0.0, 20.0, 81)

    def field(t, y, args):
        w = tumbling_w(t)
        return {
            "q": rot.quaternion_rate(y["q"], w),
            "R": y["R"] @ rot.skew(w),
            "e": rot.euler_zyx_rate(y["e"], w),
        }

    @jax.jit
    def solve(y0):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(field),
            diffrax.Tsit5(),
            0.0,
            20.0,
            0.05,
            y0,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
            max_steps=100_000,
        )

    sol = solve(y0)
    assert sol.result == diffrax.RESULTS.successful
    return sol.ys


def test_integrated_quaternion_keeps_unit_norm(tumble):
    assert np.abs(np.linalg.norm(tumble["q"], axis=1) - 1.0).max() < 1e-10


def test_integrated_quaternion_matches_matrix_ode(tumble):
    Rq = jax.vmap(rot.quaternion_to_matrix)(tumble["q"])
    assert np.abs(Rq - tumble["R"]).max() < 1e-9
    # The attitude really tumbles (the test is not trivially near the identity).
    assert np.degrees(float(rot.quaternion_angle(tumble["q"][0], tumble["q"][-1]))) > 30


def test_integrated_euler_matches_quaternion(tumble):
    margin = rot.euler_singularity_margin(tumble["e"])
    assert 0.1 < margin.min() < 0.5  # clear of gimbal lock, but pitched well over 60 deg
    Re = jax.vmap(rot.euler_zyx_to_matrix)(tumble["e"])
    Rq = jax.vmap(rot.quaternion_to_matrix)(tumble["q"])
    assert np.abs(Re - Rq).max() < 1e-9


# --------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------


def test_quaternion_matrix_round_trip():
    back = jax.jit(jax.vmap(lambda q: rot.matrix_to_quaternion(rot.quaternion_to_matrix(q))))(ALL_QS)
    assert same_up_to_sign(back, ALL_QS) < 1e-12
    assert np.all(back[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)


def test_euler_matrix_round_trip():
    es = np.c_[RNG.uniform(-np.pi, np.pi, N), RNG.uniform(-1.48, 1.48, N), RNG.uniform(-np.pi, np.pi, N)]
    back = jax.jit(jax.vmap(lambda e: rot.matrix_to_euler_zyx(rot.euler_zyx_to_matrix(e))))(es)
    assert np.abs(wrap(back - es)).max() < 1e-12


def test_euler_round_trips_near_gimbal_lock_reproduce_the_attitude():
    """Next to theta = +-90 deg, psi and phi are individually ill-conditioned, but the returned
    triple still reproduces the matrix to rounding; exactly at it, a valid triple comes back."""
    es = np.array(_gl)
    Rs = jax.vmap(rot.euler_zyx_to_matrix)(es)
    back = jax.vmap(rot.matrix_to_euler_zyx)(Rs)
    assert np.all(np.isfinite(back))
    assert np.abs(jax.vmap(rot.euler_zyx_to_matrix)(back) - Rs).max() < 1e-14
    np.testing.assert_allclose(np.abs(back[:, 1]), np.abs(es[:, 1]), atol=1e-7)


def test_quaternion_euler_round_trip():
    to_e = jax.jit(jax.vmap(rot.quaternion_to_euler_zyx))
    es = to_e(ALL_QS)
    back = jax.jit(jax.vmap(rot.euler_zyx_to_quaternion))(es)
    assert same_up_to_sign(back, ALL_QS) < 1e-12
    assert np.all(back[:, 3] >= 0)
    assert np.all(np.abs(es[:, 1]) <= np.pi / 2) and np.all(np.abs(es[:, [0, 2]]) <= np.pi)
    # euler_zyx_to_quaternion is qz(psi) * qy(theta) * qx(phi).
    for psi, th, ph in es[:20]:
        axis_q = lambda i, a: np.r_[np.sin(a / 2) * np.eye(3)[i], np.cos(a / 2)]
        composed = rot.quaternion_multiply(rot.quaternion_multiply(axis_q(2, psi), axis_q(1, th)), axis_q(0, ph))
        assert same_up_to_sign(composed[None], rot.euler_zyx_to_quaternion(np.array([psi, th, ph]))[None]) < 1e-15


# --------------------------------------------------------------------------------------------
# Independent reference: scipy.spatial.transform.Rotation
# --------------------------------------------------------------------------------------------


def test_against_scipy():
    """scipy: `from_quat`/`as_quat` are scalar-last Hamilton quaternions like ours (body->
    inertial `as_matrix`); our (psi, theta, phi) is scipy's intrinsic "ZYX" sequence."""
    R_sp = Rotation.from_quat(ALL_QS)
    np.testing.assert_allclose(jax.vmap(rot.quaternion_to_matrix)(ALL_QS), R_sp.as_matrix(), atol=1e-12, rtol=0)
    got = jax.vmap(rot.matrix_to_quaternion)(R_sp.as_matrix())
    assert same_up_to_sign(got, R_sp.as_quat()) < 1e-12
    P, Q = Rotation.from_quat(QS[:1000]), Rotation.from_quat(QS[1000:])
    assert same_up_to_sign(jax.vmap(rot.quaternion_multiply)(QS[:1000], QS[1000:]), (P * Q).as_quat()) < 1e-12
    np.testing.assert_allclose(
        jax.vmap(rot.quaternion_angle)(QS[:1000], QS[1000:]), (P.inv() * Q).magnitude(), atol=1e-12, rtol=0
    )

    es = np.c_[RNG.uniform(-np.pi, np.pi, N), RNG.uniform(-1.5, 1.5, N), RNG.uniform(-np.pi, np.pi, N)]
    E_sp = Rotation.from_euler("ZYX", es)
    np.testing.assert_allclose(jax.vmap(rot.euler_zyx_to_matrix)(es), E_sp.as_matrix(), atol=1e-12, rtol=0)
    assert same_up_to_sign(jax.vmap(rot.euler_zyx_to_quaternion)(es), E_sp.as_quat()) < 1e-12
    # Away from gimbal lock the angles themselves agree (both unique there).
    qs_ok = QS[np.abs(Rotation.from_quat(QS).as_euler("ZYX")[:, 1]) < 1.4]
    assert (
        np.abs(wrap(jax.vmap(rot.quaternion_to_euler_zyx)(qs_ok) - Rotation.from_quat(qs_ok).as_euler("ZYX"))).max()
        < 1e-12
    )


# --------------------------------------------------------------------------------------------
# Singularity, transforms, dtype
# --------------------------------------------------------------------------------------------


def test_singularity_margin_and_check():
    e = np.array([0.1, np.pi / 2 - 1e-9, 0.2])
    np.testing.assert_allclose(rot.euler_singularity_margin(e), 1e-9, rtol=1e-6)
    with pytest.raises(ValueError, match=r"`attitude0`.*gimbal lock.*min_cos"):
        rot.check_euler_away_from_singularity(e, name="attitude0")
    with pytest.raises(ValueError, match=r"`euler`.*theta = -90 deg at index \(1,\)"):
        rot.check_euler_away_from_singularity(np.array([[0.0, 0.3, 0.0], [0.0, -np.pi / 2, 1.0]]))
    with pytest.raises(ValueError, match="shape"):
        rot.check_euler_away_from_singularity(np.zeros(4))
    ok = rot.check_euler_away_from_singularity(e, min_cos=1e-10)
    assert ok.dtype == np.float64
    with pytest.raises(TypeError, match="euler_singularity_margin"):
        jax.jit(rot.check_euler_away_from_singularity)(e)
    # jit-friendly status: the margin under jit/vmap.
    m = jax.jit(jax.vmap(rot.euler_singularity_margin))(np.array([[0.0, 0.0, 0.0], [0.0, np.pi / 2, 0.0]]))
    np.testing.assert_allclose(m, [1.0, 0.0], atol=1e-15)


def test_transforms_and_float64():
    q = jnp.asarray(QS[0], dtype=jnp.float32)
    for f, x in [
        (rot.quaternion_to_matrix, q),
        (rot.quaternion_to_euler_zyx, q),
        (rot.euler_zyx_to_quaternion, q[:3]),
        (rot.euler_zyx_to_matrix, q[:3]),
        (rot.normalize, q),
    ]:
        assert f(x).dtype == jnp.float64
        J = jax.jit(jax.jacfwd(f))(x.astype(jnp.float64))
        assert np.all(np.isfinite(J))
    # jacfwd of matrix_to_quaternion agrees with a central difference along a rotation.
    R0, dW = rot.quaternion_to_matrix(QS[1]), rot.skew(RNG.normal(size=3))
    # R(s) = R0 expm(s dW), exact: Rodrigues' formula for the unit-speed rotation about dW.
    n = jnp.sqrt(-0.5 * jnp.trace(dW @ dW))
    path = jax.jit(
        lambda s: rot.matrix_to_quaternion(
            R0 @ (jnp.eye(3) + jnp.sin(s * n) / n * dW + (1 - jnp.cos(s * n)) / n**2 * dW @ dW)
        )
    )
    d_ad = jax.jit(jax.jacfwd(path))(0.3)
    d_fd = (path(0.3 + 1e-6) - path(0.3 - 1e-6)) / 2e-6
    np.testing.assert_allclose(d_ad, d_fd, atol=1e-8)


# --------------------------------------------------------------------------------------------
# Seed 002 boundary attitudes
# --------------------------------------------------------------------------------------------


def test_seed_attitudes():
    q0, qf = rot.normalize(SEED_Q0), rot.normalize(SEED_QF)
    np.testing.assert_allclose([jnp.linalg.norm(q0), jnp.linalg.norm(qf)], 1.0, atol=1e-15)
    # As printed, q0 has |q0| = 1.026 (2.6 % off unit), qf |qf| = 0.99994.
    np.testing.assert_allclose(np.linalg.norm(SEED_Q0), 1.02627, atol=1e-5)
    angle = np.degrees(float(rot.quaternion_angle(SEED_Q0, SEED_QF)))
    assert angle == pytest.approx(26.407, abs=1e-3)  # 26.4071 deg
    # Both are about 177-180 deg of yaw, far from gimbal lock: the Euler form applies.
    for q in (q0, qf):
        e = rot.quaternion_to_euler_zyx(q)
        rot.check_euler_away_from_singularity(e, min_cos=0.99)
        assert same_up_to_sign(rot.euler_zyx_to_quaternion(e)[None], q[None]) < 1e-15
