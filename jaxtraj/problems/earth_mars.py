"""Minimum-time low-thrust planar Earth-Mars transfer (seed 000, chapter 5; Bryson & Ho).

States (normalized units r0 = mu = m0 = 1): x1 radial velocity, x2 radius, x3 tangential
velocity. Control u: thrust angle from the local horizontal.

    x1' = x3^2/x2 - mu/x2^2 + T sin(u) / (m0 - mdot t)
    x2' = x1
    x3' = -x1 x3 / x2 + T cos(u) / (m0 - mdot t)

x(0) = (0, 1, 1); at free tf: x1 = 0, x2 = rf, x3 = sqrt(mu / rf); minimize tf.
"""

import jax.numpy as jnp

from .._problem import Problem
from ..controls import PiecewiseConstant, PiecewiseLinear, PiecewiseParabolic

#: Constants of the "Viking II" case (seed 000 sec. 5.2).
CONSTANTS = {
    "mu": 1.0,
    "m0": 1.0,
    "mdot": 0.074800391,
    "thrust": 0.14012969,
    "rf": 1.523679,
}

#: Unrestricted optimum of the continuous-control problem (seed 000 sec. 5.2).
TF_UNRESTRICTED = 3.31949
#: One normalized time unit in days (seed 000: 3.31949 units ~ 193 days; 5.022642e6 s).
DAYS_PER_UNIT = 5.022642e6 / 86400.0

#: Published results of the seven tests: case -> (tf, iterations) (seed 000 Tables 5.1-5.14).
PUBLISHED = {
    1: (3.31943, 11),
    2: (3.32366, 15),
    3: (3.32250, 12),
    4: (3.32533, 14),
    5: (3.32161, 17),
    6: (3.36526, 15),
    7: (3.35146, 19),
}

STATE_NAMES = ("radial velocity", "radius", "tangential velocity")
CONSTRAINT_NAMES = ("radial velocity", "radius", "tangential velocity")


def dynamics(t, x, u, args):
    vr, r, vt = x[0], x[1], x[2]
    accel = args["thrust"] / (args["m0"] - args["mdot"] * t)
    return jnp.stack(
        [
            vt**2 / r - args["mu"] / r**2 + accel * jnp.sin(u[0]),
            vr,
            -vr * vt / r + accel * jnp.cos(u[0]),
        ]
    )


def terminal(tf, xf, args):
    del tf
    return jnp.stack([xf[0], xf[1] - args["rf"], xf[2] - jnp.sqrt(args["mu"] / args["rf"])])


def problem(**constants) -> Problem:
    """The Earth-Mars problem; keyword arguments override entries of `CONSTANTS`."""
    unknown = set(constants) - set(CONSTANTS)
    if unknown:
        raise ValueError(f"unknown Earth-Mars constant(s) {sorted(unknown)}; expected some of {sorted(CONSTANTS)}.")
    args = {k: jnp.asarray(float(v), dtype=jnp.float64) for k, v in {**CONSTANTS, **constants}.items()}
    return Problem(
        dynamics,
        x0=[0.0, 1.0, 1.0],
        terminal=terminal,
        constraint_names=CONSTRAINT_NAMES,
        args=args,
        state_names=STATE_NAMES,
        control_names=("thrust angle [rad]",),
        name="earth-mars",
    )


# Published starting vectors (seed 000, Tables 5.1, 5.3, 5.5, 5.7, 5.9, 5.11, 5.13).
_CASES = {
    1: (
        lambda: PiecewiseLinear(4, continuous=False, free_times=True),
        [0.0, 1.17810, 0.85, 1.17810, 2.35619, 1.70, 2.35619, 3.53429, 2.55, 3.53429, 4.71239, 3.40],
    ),
    2: (
        lambda: PiecewiseLinear(3, continuous=False, free_times=True),
        [0.0, 1.57080, 1.13333, 1.57080, 3.14159, 2.26666, 3.14159, 4.71239, 3.40],
    ),
    3: (
        lambda: PiecewiseParabolic(2, free_times=True),
        [0.0, 1.38600, 2.35619, 1.70, 2.35619, 1.38600, 4.71239, 3.40],
    ),
    4: (
        lambda: PiecewiseLinear(5),
        [0.0, 0.942478, 1.88496, 2.82743, 3.76991, 4.71239, 3.40],
    ),
    5: (
        lambda: PiecewiseLinear(7),
        [0.0, 0.673198, 1.34640, 2.01960, 2.69279, 3.36599, 4.03919, 4.71239, 3.40],
    ),
    6: (
        lambda: PiecewiseConstant(3, free_times=True),
        [0.0, 1.13333, 0.0, 2.26666, 0.0, 3.40],
    ),
    7: (
        lambda: PiecewiseConstant(5, free_times=True),
        [0.0, 0.68, 0.0, 1.36, 0.0, 2.04, 0.0, 2.72, 0.0, 3.40],
    ),
}


def thesis_case(n: int):
    """`(problem, control, a0)` for published test `n` in 1..7 with the thesis's starting vector.

    Tests 1-5 start from u = 1.5 pi t / 3.4 (as printed, to 5-6 digits); tests 6 and 7
    from zero levels with equally spaced switches (Tables 5.11, 5.13).
    """
    if n not in _CASES:
        raise ValueError(f"`n` must be a thesis case in 1..7; got {n!r}.")
    make, a0 = _CASES[n]
    ctrl = make()
    return problem(), ctrl, jnp.asarray(ctrl.validate(a0))


# Published tuning per test (seed 000, headers of Tables 5.1-5.13): rho and beta_p0 (beta =
# beta_p = beta_0 = 1 throughout). Where the OCR lost the value (tests 4 and 6) the default
# beta_p0 = 2 of the neighbouring tests is used.
_TUNING = {1: (1.0, 2.0), 2: (1.0, 2.0), 3: (1.0, 4.0), 4: (1.0, 2.0), 5: (1.0, 1.0), 6: (1.0, 2.0), 7: (0.8, 4.0)}


def thesis_solver(n: int, **overrides):
    """`jt.KalmanSearch` with the thesis's published tuning for test `n` (rho, beta_p0);
    keyword arguments override any field."""
    from .._kalman_search import KalmanSearch

    if n not in _TUNING:
        raise ValueError(f"`n` must be a thesis case in 1..7; got {n!r}.")
    rho, beta_p0 = _TUNING[n]
    return KalmanSearch(**{"rho": rho, "beta_p0": beta_p0, **overrides})
