"""The unrestricted minimum-time sail transfer by Pontryagin's principle and single shooting:
an independent reference for `jaxtraj.problems.solar_sail` (NumPy and SciPy only, none of
jaxtraj's simulation or derivatives)."""

import dataclasses
import math
import time

import numpy as np

#: Days per normalized time unit (1 year = 2 pi units).
DAYS_PER_UNIT = 365.25 / (2.0 * math.pi)


def optimal_pitch(lam_u, lam_v):
    """The pitch minimizing lam_u cos^3(alpha) + lam_v cos^2(alpha) sin(alpha) over
    [-pi/2, pi/2] (Pontryagin's minimum principle for this sail; NumPy scalars).

    Stationary points (besides the edge-on +-pi/2) solve 2 lam_v t^2 + 3 lam_u t - lam_v = 0,
    t = tan(alpha); the candidates are compared directly.
    """
    a, b, c = 2.0 * lam_v, 3.0 * lam_u, -lam_v
    disc = math.sqrt(b * b - 4.0 * a * c)  # = sqrt(9 lam_u^2 + 8 lam_v^2) >= 0
    q = -0.5 * (b + math.copysign(disc, b))  # stable quadratic formula
    cands = [0.5 * math.pi, -0.5 * math.pi]
    if a != 0.0:
        cands.append(math.atan(q / a))
    if q != 0.0:
        cands.append(math.atan(c / q))
    vals = [lam_u * math.cos(x) ** 3 + lam_v * math.cos(x) ** 2 * math.sin(x) for x in cands]
    return cands[int(np.argmin(vals))]


def _state_costate_rhs(a0, mu):
    def rhs(t, y):
        r, _, u, v, lr, lu, lv = y
        al = optimal_pitch(lu, lv)
        c, s = math.cos(al), math.sin(al)
        thrust_r, thrust_t = a0 * c**3, a0 * c * c * s
        return [
            u,
            v / r,
            v * v / r - mu / r**2 + thrust_r / r**2,
            -u * v / r + thrust_t / r**2,
            # lambda' = -dH/dx (lambda_theta = 0: theta is free and absent from f)
            -(
                lu * (-v * v / r**2 + 2.0 * mu / r**3 - 2.0 * thrust_r / r**3)
                + lv * (u * v / r**2 - 2.0 * thrust_t / r**3)
            ),
            -(lr - lv * v / r),
            -(2.0 * lu * v / r - lv * u / r),
        ]

    return rhs


def _hamiltonian(y, a0, mu):
    r, _, u, v, lr, lu, lv = y
    al = optimal_pitch(lu, lv)
    c, s = math.cos(al), math.sin(al)
    return 1.0 + lr * u + lu * (v * v / r - mu / r**2 + a0 * c**3 / r**2) + lv * (-u * v / r + a0 * c * c * s / r**2)


@dataclasses.dataclass(frozen=True)
class IndirectResult:
    """Outcome of `solve_indirect`: `tf`, `tf_days`, the initial costates
    `(lambda_r, lambda_u, lambda_v)` (lambda_theta = 0), the shooting `residual`
    (r - r_f, u, v - v_f, H(0)), `success` (max |residual| <= 1e-9), the dense solution
    (`t`, `x` of shape (N, 4), `alpha`), the number of `starts` tried and `wall_time` [s]."""

    tf: float
    tf_days: float
    costates: np.ndarray
    residual: np.ndarray
    success: bool
    t: np.ndarray
    x: np.ndarray
    alpha: np.ndarray
    starts: int
    wall_time: float


def shoot(radius, a0, mu, tf_guess, pitch_guesses_deg, rtol, dense_points) -> IndirectResult:
    """Solve the shooting equations for a transfer to the circular orbit `radius` (the
    arguments checked by `solar_sail.solve_indirect`, which documents them)."""
    import scipy.integrate  # here, not at import: SciPy's import is ~0.4 s of `import jaxtraj`
    import scipy.optimize

    start = time.perf_counter()
    v_f = math.sqrt(mu / radius)
    rhs = _state_costate_rhs(a0, mu)

    def integrate(z, dense=False):
        y0 = [1.0, 0.0, 0.0, math.sqrt(mu), z[0], z[1], z[2]]
        return scipy.integrate.solve_ivp(
            rhs, (0.0, z[3]), y0, method="DOP853", rtol=rtol, atol=rtol, dense_output=dense
        )

    def residual(z):
        if not z[3] > 0:
            return np.full(4, 1e3)
        sol = integrate(z)
        if not sol.success:
            return np.full(4, 1e3)
        yf = sol.y[:, -1]
        y0 = [1.0, 0.0, 0.0, math.sqrt(mu), z[0], z[1], z[2]]
        return np.array([yf[0] - radius, yf[2], yf[3] - v_f, _hamiltonian(y0, a0, mu)])

    best = None
    tried = 0
    for deg in pitch_guesses_deg:
        tried += 1
        al = math.radians(deg)
        t = math.tan(al)
        lv = -math.copysign(1.0, t)  # lambda_v < 0 pushes prograde, > 0 retrograde
        lu = lv * (1.0 - 2.0 * t * t) / (3.0 * t)  # alpha stationary: 2 lv t^2 + 3 lu t - lv = 0
        g = lu * math.cos(al) ** 3 + lv * math.cos(al) ** 2 * math.sin(al)
        scale = -1.0 / (a0 * g)  # H(0) = 1 + a0 g = 0
        z0 = np.array([0.0, lu * scale, lv * scale, float(tf_guess)])
        sol = scipy.optimize.root(residual, z0, method="hybr", options={"xtol": 1e-13})
        res = residual(sol.x)
        if best is None or np.max(np.abs(res)) < np.max(np.abs(best[1])):
            best = (sol.x, res)
        if np.max(np.abs(res)) <= 1e-9:
            break
    assert best is not None  # (`pitch_guesses_deg` is not empty: `solve_indirect` checks it)
    z, res = best
    dense = integrate(z, dense=True)
    t = np.linspace(0.0, z[3], dense_points)
    y = dense.sol(t)
    alpha = np.array([optimal_pitch(lu, lv) for lu, lv in zip(y[5], y[6])])
    return IndirectResult(
        tf=float(z[3]),
        tf_days=float(z[3]) * DAYS_PER_UNIT,
        costates=np.asarray(z[:3], dtype=np.float64),
        residual=res,
        success=bool(np.max(np.abs(res)) <= 1e-9),
        t=t,
        x=y[:4].T.copy(),
        alpha=alpha,
        starts=tried,
        wall_time=time.perf_counter() - start,
    )
