"""Attitude representations: unit quaternions and ZYX (yaw-pitch-roll) Euler angles.

Pure-JAX functions on single samples (`(4,)` quaternions, `(3,)` angle or rate vectors,
`(3, 3)` matrices); all of them can be used under `jax.jit`, `jax.vmap` and `jax.jacfwd`, and
return float64 (inputs are cast up). Each array function is itself wrapped in `jax.jit`, so
eager calls compile once per input shape and dtype instead of dispatching op by op. Written
for the satellite-reorientation problem of seed 002.

Conventions: `R` maps *body* to *inertial* coordinates, `x_I = R @ x_B`, and `w` is the
body's angular velocity in body axes, `R' = R @ skew(w)`. Quaternions are scalar-LAST with
the Hamilton product (scipy's convention), `q' = 1/2 Omega(w) q`, returned with `q4 >= 0`.
ZYX angles are `e = (psi, theta, phi)` with `R = Rz(psi) @ Ry(theta) @ Rx(phi)` (scipy's
`from_euler("ZYX", ...)`); their kinematics divide by `cos(theta)` (gimbal lock at
`theta = +-90 deg`, `euler_singularity_margin`).

(The conventions in full, the kinematics derived and the sign of seed eq. 4: docs/library.md,
"Attitude conventions".)
"""

import jax
import jax.numpy as jnp
import numpy as np


def _f64(x) -> jax.Array:
    return jnp.asarray(x, dtype=jnp.float64)


# --------------------------------------------------------------------------------------------
# Quaternions
# --------------------------------------------------------------------------------------------


@jax.jit
def skew(w) -> jax.Array:
    """Cross-product matrix: `skew(w) @ v == cross(w, v)`; antisymmetric `(3, 3)`."""
    w1, w2, w3 = _f64(w)
    z = jnp.zeros_like(w1)
    return jnp.stack([jnp.stack([z, -w3, w2]), jnp.stack([w3, z, -w1]), jnp.stack([-w2, w1, z])])


@jax.jit
def omega_matrix(w) -> jax.Array:
    """The `(4, 4)` antisymmetric `Omega(w)` of `q' = 1/2 Omega(w) q` (scalar-last `q`,
    body-frame `w`; see docs/library.md, "Attitude conventions", for the derivation)."""
    w1, w2, w3 = _f64(w)
    z = jnp.zeros_like(w1)
    return jnp.stack(
        [
            jnp.stack([z, w3, -w2, w1]),
            jnp.stack([-w3, z, w1, w2]),
            jnp.stack([w2, -w1, z, w3]),
            jnp.stack([-w1, -w2, -w3, z]),
        ]
    )


@jax.jit
def quaternion_rate(q, w) -> jax.Array:
    """`q' = 1/2 Omega(w) q = 1/2 q * (w, 0)` for body-frame angular velocity `w`."""
    return 0.5 * omega_matrix(w) @ _f64(q)


@jax.jit
def quaternion_multiply(p, q) -> jax.Array:
    """Hamilton product `p * q`, scalar-last: `(ps qv + qs pv + pv x qv, ps qs - pv . qv)`.

    Rotation by `q` followed by rotation by `p` (both body->inertial):
    `quaternion_to_matrix(p * q) == quaternion_to_matrix(p) @ quaternion_to_matrix(q)`.
    """
    p, q = _f64(p), _f64(q)
    pv, ps, qv, qs = p[:3], p[3], q[:3], q[3]
    return jnp.concatenate([ps * qv + qs * pv + jnp.cross(pv, qv), (ps * qs - pv @ qv)[None]])


@jax.jit
def quaternion_conjugate(q) -> jax.Array:
    """`(-q1, -q2, -q3, q4)`: the inverse rotation for a unit quaternion."""
    q = _f64(q)
    return jnp.concatenate([-q[:3], q[3:]])


@jax.jit
def normalize(q) -> jax.Array:
    """`q / |q|` (any vector; nan for the zero vector)."""
    q = _f64(q)
    return q / jnp.linalg.norm(q)


@jax.jit
def quaternion_to_matrix(q) -> jax.Array:
    """Body->inertial rotation matrix `R(q)`. `q` need not be unit: it is normalized implicitly
    (`R = I + 2 (s skew(v) + skew(v)^2) / |q|^2`), so `R` is orthogonal for any nonzero `q`."""
    q = _f64(q)
    K = skew(q[:3])
    return jnp.eye(3) + (2.0 / (q @ q)) * (q[3] * K + K @ K)


@jax.jit
def matrix_to_quaternion(R) -> jax.Array:
    """Unit quaternion (scalar-last, `q4 >= 0`) of a rotation matrix, by Shepperd's method.

    Each of the four candidates below equals `4 q_k q` for one component `k`; the one whose
    `4 q_k^2` (`1 + R00 - R11 - R22`, ..., `1 + trace`) is largest is used, so the divisor is at
    least 1 and the result is accurate for every rotation, half-turns included. Branch-free
    (`jnp.where`), so it works under jit/vmap.
    """
    R = _f64(R)
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    tr = r00 + r11 + r22
    c1 = jnp.stack([1 + r00 - r11 - r22, r01 + r10, r02 + r20, r21 - r12])  # 4 q1 q
    c2 = jnp.stack([r01 + r10, 1 - r00 + r11 - r22, r12 + r21, r02 - r20])  # 4 q2 q
    c3 = jnp.stack([r02 + r20, r12 + r21, 1 - r00 - r11 + r22, r10 - r01])  # 4 q3 q
    c4 = jnp.stack([r21 - r12, r02 - r20, r10 - r01, 1 + tr])  # 4 q4 q
    k = jnp.argmax(jnp.stack([r00, r11, r22, tr]))
    c = jnp.where(k == 0, c1, jnp.where(k == 1, c2, jnp.where(k == 2, c3, c4)))
    q = c / jnp.linalg.norm(c)
    return jnp.where(q[3] < 0, -q, q)


@jax.jit
def rotate_vector(q, v) -> jax.Array:
    """Body-frame vector `v` in inertial coordinates: `R(q) @ v` (e.g. the keep-out cone axis
    `y_I` of seed eq. 6)."""
    return quaternion_to_matrix(q) @ _f64(v)


@jax.jit
def quaternion_angle(p, q) -> jax.Array:
    """Rotation angle in `[0, pi]` taking attitude `p` to attitude `q` (sign-blind; inputs are
    normalized). Computed with `atan2`, accurate for small angles; its gradient is nan at 0."""
    d = quaternion_multiply(quaternion_conjugate(normalize(p)), normalize(q))
    return 2.0 * jnp.arctan2(jnp.linalg.norm(d[:3]), jnp.abs(d[3]))


# --------------------------------------------------------------------------------------------
# ZYX Euler angles (psi, theta, phi) = (yaw, pitch, roll)
# --------------------------------------------------------------------------------------------


@jax.jit
def euler_zyx_to_matrix(euler) -> jax.Array:
    """`R = Rz(psi) @ Ry(theta) @ Rx(phi)` (body->inertial) for `euler = (psi, theta, phi)`."""
    psi, theta, phi = _f64(euler)
    cps, sps = jnp.cos(psi), jnp.sin(psi)
    cth, sth = jnp.cos(theta), jnp.sin(theta)
    cph, sph = jnp.cos(phi), jnp.sin(phi)
    return jnp.stack(
        [
            jnp.stack([cps * cth, cps * sth * sph - sps * cph, cps * sth * cph + sps * sph]),
            jnp.stack([sps * cth, sps * sth * sph + cps * cph, sps * sth * cph - cps * sph]),
            jnp.stack([-sth, cth * sph, cth * cph]),
        ]
    )


@jax.jit
def matrix_to_euler_zyx(R) -> jax.Array:
    """`(psi, theta, phi)` with `euler_zyx_to_matrix(.) == R`; `psi, phi` in `[-pi, pi]`,
    `theta` in `[-pi/2, pi/2]`.

    `psi = atan2(R10, R00)`; then `theta, phi` are read off `Rz(psi)^T R = Ry(theta) Rx(phi)`,
    so the triple reproduces `R` to rounding even near gimbal lock, where `psi` alone is
    ill-determined. At `cos(theta) = 0` exactly, `psi` is whatever `atan2` gives for the
    (rounding-level) first column and `phi` compensates; derivatives there are huge or nan.
    """
    R = _f64(R)
    psi = jnp.arctan2(R[1, 0], R[0, 0])
    c, s = jnp.cos(psi), jnp.sin(psi)
    m00 = c * R[0, 0] + s * R[1, 0]  # cos(theta) >= 0
    m11 = -s * R[0, 1] + c * R[1, 1]  # cos(phi)
    m12 = -s * R[0, 2] + c * R[1, 2]  # -sin(phi)
    theta = jnp.arctan2(-R[2, 0], m00)
    phi = jnp.arctan2(-m12, m11)
    return jnp.stack([psi, theta, phi])


@jax.jit
def euler_zyx_rate(euler, w) -> jax.Array:
    """`(psi', theta', phi')` for body-frame angular velocity `w` (seed eq. 5, reordered).

    Divides by `cos(theta)`: singular at gimbal lock (`theta = +-90 deg`), huge next to it; see
    `euler_singularity_margin` / `check_euler_away_from_singularity`.
    """
    _, theta, phi = _f64(euler)
    w1, w2, w3 = _f64(w)
    a = jnp.sin(phi) * w2 + jnp.cos(phi) * w3
    return jnp.stack([a / jnp.cos(theta), jnp.cos(phi) * w2 - jnp.sin(phi) * w3, w1 + jnp.tan(theta) * a])


@jax.jit
def euler_zyx_to_quaternion(euler) -> jax.Array:
    """Unit quaternion (scalar-last, `q4 >= 0`) of `euler = (psi, theta, phi)`:
    `qz(psi) * qy(theta) * qx(phi)` in closed form."""
    h = 0.5 * _f64(euler)
    c1, c2, c3 = jnp.cos(h)
    s1, s2, s3 = jnp.sin(h)
    q = jnp.stack(
        [
            c1 * c2 * s3 - s1 * s2 * c3,
            c1 * s2 * c3 + s1 * c2 * s3,
            s1 * c2 * c3 - c1 * s2 * s3,
            c1 * c2 * c3 + s1 * s2 * s3,
        ]
    )
    return jnp.where(q[3] < 0, -q, q)


@jax.jit
def quaternion_to_euler_zyx(q) -> jax.Array:
    """`(psi, theta, phi)` of a (not necessarily unit) quaternion, via the rotation matrix, so
    it inherits the accuracy and gimbal-lock behaviour of `matrix_to_euler_zyx`."""
    return matrix_to_euler_zyx(quaternion_to_matrix(q))


@jax.jit
def euler_singularity_margin(euler) -> jax.Array:
    """`cos(theta)` of `euler = (..., 3)`: 1 at level pitch, 0 at gimbal lock (`theta = +-90
    deg`), where the ZYX kinematics are singular. jit-friendly; use it as a status or a path
    constraint (`margin >= min_cos`) instead of raising inside traced code. Negative for a
    `theta` outside `[-pi/2, pi/2]` (not produced by this module); use `abs` for those."""
    return jnp.cos(_f64(euler)[..., 1])


def check_euler_away_from_singularity(euler, min_cos: float = 1e-6, name: str = "euler"):
    """Raise `ValueError` if any concrete `euler` (shape `(..., 3)`) has `|cos(theta)| <
    min_cos`; return it as a float64 numpy array otherwise. Outside jit only: under a
    transformation, use `euler_singularity_margin` as a status instead.

    **Raises:** `ValueError` naming `name` and the offending pitch; `TypeError` for traced
    input.
    """
    try:
        e = np.asarray(euler, dtype=np.float64)
    except jax.errors.TracerArrayConversionError as err:
        raise TypeError(
            f"check_euler_away_from_singularity needs a concrete `{name}`; inside jit use "
            "euler_singularity_margin(...) as a status instead"
        ) from err
    if e.shape[-1:] != (3,):
        raise ValueError(f"`{name}` must have shape (..., 3) = (psi, theta, phi), got {e.shape}")
    margin = np.abs(np.cos(e[..., 1]))
    bad = ~(margin >= min_cos)  # also catches nan
    if np.any(bad):
        i = tuple(int(k) for k in np.unravel_index(np.argmax(bad), bad.shape))
        raise ValueError(
            f"`{name}` is at or too close to the ZYX Euler singularity (gimbal lock, theta = "
            f"+-90 deg): theta = {np.degrees(e[i][1]):.10g} deg at index {i} has |cos(theta)| = "
            f"{margin[i]:.3g} < min_cos = {min_cos:g}; only psi -+ phi is defined there and the "
            "Euler-rate kinematics divide by cos(theta). Use quaternions instead."
        )
    return e
