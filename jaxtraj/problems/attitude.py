"""Minimum-energy satellite reorientation with a sun keep-out cone (seed 002; Kim & Mesbahi
2004), in quaternion or ZYX Euler-angle form.

A rigid satellite, J = diag(100, 200, 300) kg m^2, turns in tf = 500 s from rest to rest
through 26.4 deg under Euler's equations J w' = u - w x (J w), while its instrument boresight
y stays out of the cone of half-angle 50 deg around the sun direction s:
C = s . (R(q) y) - cos(50 deg) <= 0. The objective is the control energy, carried as an extra
state (Mayer form). The grid constraint uses a cone widened by `cone_backoff_deg`, so that the
cone itself holds between grid points (`cone_margin` checks it on a finer grid). The Euler
form keeps |theta| <= `pitch_limit_deg` (gimbal lock) by a "gimbal" path constraint. Units
are chosen so that the parameters are O(1) (`time_unit`, `torque_unit`).

(The model, its representations, units and controls: docs/examples.md, "Attitude slew with a
sun keep-out cone".)
"""

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import rotations
from .._checks import check_inputs
from .._problem import Problem
from .._simulate import RK4, AbstractSimulator, Diffrax, check_simulator, simulate
from ..controls import SaturatedSpline

#: Default sun direction (inertial, unit): both end attitudes 0.5 deg outside a 50 deg cone.
SUN = (0.005034358, -0.286391342, 0.958099501)
#: Instrument boresight in body axes (seed 002), normalized by `problem`.
BORESIGHT = (0.750, 0.433, 0.500)
#: End attitudes (seed 002, scalar-last), normalized by `problem`.
Q0 = (0.0, 0.258, 0.993, 0.025)
QF = (0.025, 0.025, 0.999, 0.025)
#: Principal moments of inertia [kg m^2] (seed 002).
INERTIA = (100.0, 200.0, 300.0)
#: Default torque bound per axis [N m] (our choice; the seed gives none).
TORQUE_MAX = 0.01
#: Default solver units.
TIME_UNIT = 100.0
TORQUE_UNIT = 1e-3

REPRESENTATIONS = ("quaternion", "euler")
_SINGULAR_COS = 1e-6


def _unit(v, name, size):
    v = np.asarray(v, dtype=np.float64)
    if v.shape != (size,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        raise ValueError(f"`{name}` must be a finite nonzero vector of length {size}; got {v!r}.")
    return v / np.linalg.norm(v)


# --------------------------------------------------------------------------------------------
# Problem functions (module level: problems built twice compare equal and share compilations)
# --------------------------------------------------------------------------------------------


def _rate_dynamics(w, u, args):
    J = args["inertia"]
    return (args["gain"] * u - jnp.cross(w, J * w)) / J


def quaternion_dynamics(t, x, u, args):
    del t
    q, w = x[:4], x[4:7]
    return jnp.concatenate([rotations.quaternion_rate(q, w), _rate_dynamics(w, u, args), (u @ u)[None]])


def euler_dynamics(t, x, u, args):
    del t
    e, w = x[:3], x[3:6]
    rate = rotations.euler_zyx_rate(e, w)
    rate = jnp.where(jnp.abs(jnp.cos(e[1])) < _SINGULAR_COS, jnp.nan, rate)  # gimbal lock: a status, not garbage
    return jnp.concatenate([rate, _rate_dynamics(w, u, args), (u @ u)[None]])


def quaternion_terminal(tf, xf, args):
    err = rotations.quaternion_multiply(rotations.quaternion_conjugate(args["qf"]), xf[:4])
    return jnp.concatenate([err[:3], xf[4:7], (tf - args["tf"])[None]])


def euler_terminal(tf, xf, args):
    d = xf[:3] - args["euler_f"]
    wrapped = jnp.arctan2(jnp.sin(d), jnp.cos(d))
    return jnp.concatenate([wrapped, xf[3:6], (tf - args["tf"])[None]])


def quaternion_energy(tf, xf, args):
    del tf, args
    return xf[7]


def euler_energy(tf, xf, args):
    del tf, args
    return xf[6]


def _cone(R, args):
    return args["sun"] @ (R @ args["boresight"]) - args["cos_cone_enforced"]


def quaternion_path(t, x, u, args):
    del t, u
    return _cone(rotations.quaternion_to_matrix(x[:4]), args)[None]


def euler_path(t, x, u, args):
    del t, u
    return _cone(rotations.euler_zyx_to_matrix(x[:3]), args)[None]


def euler_path_with_gimbal(t, x, u, args):
    del t, u
    cone = _cone(rotations.euler_zyx_to_matrix(x[:3]), args)
    return jnp.stack([cone, args["cos_pitch_limit"] - jnp.cos(x[1])])


def _euler_gimbal_only(t, x, u, args):
    del t, u
    return (args["cos_pitch_limit"] - jnp.cos(x[1]))[None]


# --------------------------------------------------------------------------------------------
# Public constructors
# --------------------------------------------------------------------------------------------


def problem(
    representation: str = "quaternion",
    sun=SUN,
    cone_deg: float = 50.0,
    tf: float = 500.0,
    *,
    cone: bool = True,
    q0=Q0,
    qf=QF,
    boresight=BORESIGHT,
    inertia=INERTIA,
    torque_max: float | None = TORQUE_MAX,
    time_unit: float = TIME_UNIT,
    torque_unit: float = TORQUE_UNIT,
    pitch_limit_deg: float | None = 80.0,
    cone_backoff_deg: float = 1e-3,
) -> Problem:
    """The reorientation problem (docs/examples.md) as a `jt.Problem` in solver units.

    **Arguments:**

    - `representation`: `"quaternion"` or `"euler"` (ZYX).
    - `sun`: sun direction, inertial (normalized here); `cone_deg`: keep-out half-angle.
    - `tf`: maneuver time [s] (fixed through the terminal constraint tf - T = 0).
    - `cone`: False drops the keep-out constraint (the unconstrained slew).
    - `q0`, `qf`: end attitudes (scalar-last quaternions, normalized here); `boresight`:
      instrument axis in body coordinates; `inertia`: principal moments [kg m^2].
    - `torque_max`: bound per axis [N m] (None: unbounded).
    - `time_unit` [s], `torque_unit` [N m]: the solver units.
    - `cone_backoff_deg`: the grid constraint's cone is wider by this angle, so that the
      cone holds between grid points too (docs/examples.md; 0: the cone itself at the grid).
    - `pitch_limit_deg`: Euler form only: |theta| bound kept as the "gimbal" path constraint
      (None: no such constraint).

    Every number lives in `problem.args` (arrays), so changing it does not recompile.

    **Raises:** `ValueError` for an unknown representation, bad vectors or scalars, or (Euler
    form) an end attitude at or beyond the pitch limit.
    """
    if representation not in REPRESENTATIONS:
        raise ValueError(f"`representation` must be one of {REPRESENTATIONS}; got {representation!r}.")
    for name, value in (("cone_deg", cone_deg), ("tf", tf), ("time_unit", time_unit), ("torque_unit", torque_unit)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"`{name}` must be a finite number > 0; got {value!r}.")
    if not (np.isfinite(cone_backoff_deg) and cone_backoff_deg >= 0):
        raise ValueError(f"`cone_backoff_deg` must be a finite number >= 0; got {cone_backoff_deg!r}.")
    if not cone_deg + cone_backoff_deg < 90:
        raise ValueError(f"`cone_deg` + `cone_backoff_deg` must be < 90; got {cone_deg!r} + {cone_backoff_deg!r}.")
    if torque_max is not None and not (np.isfinite(torque_max) and torque_max > 0):
        raise ValueError(f"`torque_max` must be None or a finite number > 0; got {torque_max!r}.")
    J = np.asarray(inertia, dtype=np.float64)
    if J.shape != (3,) or not np.all(J > 0):
        raise ValueError(f"`inertia` must be three positive moments [kg m^2]; got {inertia!r}.")
    q0, qf = _unit(q0, "q0", 4), _unit(qf, "qf", 4)
    f64 = lambda v: jnp.asarray(v, dtype=jnp.float64)
    args = {
        "inertia": f64(J),
        "gain": f64(time_unit**2 * torque_unit),
        "qf": f64(qf),
        "euler_f": f64(rotations.quaternion_to_euler_zyx(qf)),
        "sun": f64(_unit(sun, "sun", 3)),
        "boresight": f64(_unit(boresight, "boresight", 3)),
        "cos_cone": f64(math.cos(math.radians(cone_deg))),
        "cos_cone_enforced": f64(math.cos(math.radians(cone_deg + cone_backoff_deg))),
        "tf": f64(tf / time_unit),
        "time_unit": f64(time_unit),
        "torque_unit": f64(torque_unit),
    }
    bound = None if torque_max is None else torque_max / torque_unit
    common: dict[str, Any] = dict(
        num_controls=3,
        control_names=tuple(f"torque {i} [{torque_unit:g} N m]" for i in (1, 2, 3)),
        control_lower=None if bound is None else -bound,
        control_upper=bound,
    )
    rates = ("w1", "w2", "w3")
    names = ("attitude 1", "attitude 2", "attitude 3", "rate 1", "rate 2", "rate 3", "final time")
    if representation == "quaternion":
        path, path_names = (quaternion_path, ("cone",)) if cone else (None, ())
        return Problem(
            quaternion_dynamics,
            x0=np.concatenate([q0, np.zeros(4)]),
            terminal=quaternion_terminal,
            constraint_names=names,
            objective=quaternion_energy,
            args=args,
            state_names=("q1", "q2", "q3", "q4", *rates, "energy"),
            path=path,
            path_names=path_names,
            name="attitude-quaternion",
            **common,
        )
    e0 = np.asarray(rotations.quaternion_to_euler_zyx(q0))
    ef = np.asarray(args["euler_f"])
    if pitch_limit_deg is not None:
        if not (0 < pitch_limit_deg < 90):
            raise ValueError(f"`pitch_limit_deg` must be in (0, 90) or None; got {pitch_limit_deg!r}.")
        for label, e in (("q0", e0), ("qf", ef)):
            if abs(math.degrees(e[1])) >= pitch_limit_deg:
                raise ValueError(
                    f"`{label}` has pitch theta = {math.degrees(e[1]):.6g} deg, at or beyond "
                    f"`pitch_limit_deg` = {pitch_limit_deg:g} (ZYX gimbal lock at +-90 deg); "
                    "use representation='quaternion'."
                )
        args["cos_pitch_limit"] = f64(math.cos(math.radians(pitch_limit_deg)))
    for label, e in (("q0", e0), ("qf", ef)):
        rotations.check_euler_away_from_singularity(e, 1e-3, label)
    if cone and pitch_limit_deg is not None:
        path, path_names = euler_path_with_gimbal, ("cone", "gimbal")
    elif cone:
        path, path_names = euler_path, ("cone",)
    elif pitch_limit_deg is not None:
        path, path_names = _euler_gimbal_only, ("gimbal",)
    else:
        path, path_names = None, ()
    return Problem(
        euler_dynamics,
        x0=np.concatenate([e0, np.zeros(4)]),
        terminal=euler_terminal,
        constraint_names=names,
        objective=euler_energy,
        args=args,
        state_names=("psi", "theta", "phi", *rates, "energy"),
        path=path,
        path_names=path_names,
        name="attitude-euler",
        **common,
    )


def case(representation: str = "quaternion", segments: int = 8, **problem_kwargs):
    """`(problem, control, a0)`: `problem(representation, **problem_kwargs)`, a continuous
    piecewise-linear torque per axis on `segments` equal segments
    (`SaturatedSpline(segments, 1, -umax, umax, free_durations=False)`), and a0 = (T, zero
    torques): the satellite at rest, every terminal attitude and time constraint to be met by
    the solver."""
    prob = problem(representation, **problem_kwargs)
    umax = np.inf if prob.control_upper is None else float(prob.control_upper[0])
    lower, upper = (-1e300, 1e300) if not np.isfinite(umax) else (-umax, umax)
    ctrl = SaturatedSpline(segments, 1, [lower] * 3, [upper] * 3, free_durations=False)
    a0 = np.zeros(ctrl.num_params)
    a0[0] = float(prob.args["tf"])
    return prob, ctrl, jnp.asarray(ctrl.validate(a0))


# --------------------------------------------------------------------------------------------
# Diagnostics
# --------------------------------------------------------------------------------------------


def _representation(problem: Problem) -> str:
    if problem.name == "attitude-quaternion":
        return "quaternion"
    if problem.name == "attitude-euler":
        return "euler"
    raise ValueError(f"`problem` must come from jt.problems.attitude.problem; got {problem.name!r}.")


def attitude_matrix(problem: Problem, x) -> jax.Array:
    """Body->inertial matrix R of one state `x` (either representation)."""
    if _representation(problem) == "quaternion":
        return rotations.quaternion_to_matrix(x[:4])
    return rotations.euler_zyx_to_matrix(x[:3])


def quaternion_of(problem: Problem, x) -> jax.Array:
    """Unit quaternion (scalar-last, q4 >= 0) of one state `x` (either representation)."""
    if _representation(problem) == "quaternion":
        q = rotations.normalize(x[:4])
        return jnp.where(q[3] < 0, -q, q)
    return rotations.euler_zyx_to_quaternion(x[:3])


def boresight_margin(problem: Problem, x) -> jax.Array:
    """Angle [deg] between the sun and the boresight at state `x`, minus the cone half-angle:
    > 0 outside the keep-out cone (allowed), < 0 inside."""
    args = problem.args
    y_inertial = attitude_matrix(problem, x) @ args["boresight"]
    s = args["sun"]
    angle = jnp.arctan2(jnp.linalg.norm(jnp.cross(s, y_inertial)), s @ y_inertial)
    return jnp.degrees(angle - jnp.arccos(args["cos_cone"]))


def _finer(simulator: AbstractSimulator, factor: int) -> AbstractSimulator:
    if isinstance(simulator, RK4):
        return RK4(simulator.steps * factor)
    if isinstance(simulator, Diffrax):
        return Diffrax(
            simulator.solver,
            simulator.rtol,
            simulator.atol,
            simulator.max_steps,
            (simulator.dense_points - 1) * factor + 1,
        )
    raise ValueError(f"`simulator` must be jt.RK4 or jt.Diffrax; got {type(simulator).__name__}.")


def cone_margin(problem: Problem, control, a, grid_factor: int = 10, simulator: AbstractSimulator = RK4()):
    """Worst keep-out margin [deg] along the trajectory of `a`, on a grid `grid_factor` times
    finer than `simulator`'s (RK4: `grid_factor` x the steps per segment, the same knots).

    **Returns:** `(margin_deg, t)` as floats: the smallest `boresight_margin` and where it
    occurs in solver time units (>= 0: the cone was never entered on that grid).
    """
    if not (isinstance(grid_factor, int) and grid_factor >= 1):
        raise ValueError(f"`grid_factor` must be an int >= 1; got {grid_factor!r}.")
    _representation(problem)
    check_simulator(simulator)
    a = check_inputs(problem, control, a)
    traj = simulate(problem, control, a, simulator=_finer(simulator, grid_factor))
    margins = np.asarray(jax.vmap(lambda x: boresight_margin(problem, x))(traj.x))
    i = int(np.argmin(margins))
    return float(margins[i]), float(traj.t[i])


def energy_si(problem: Problem, energy) -> float:
    """The energy state (solver units) in N^2 m^2 s."""
    return float(energy) * float(problem.args["torque_unit"]) ** 2 * float(problem.args["time_unit"])
