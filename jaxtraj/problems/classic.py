"""A gallery of classic optimal-control problems from the literature, each with its
reference optimum and where it comes from.

`get(name)` gives a `ClassicProblem`: the `jt.Problem`, a control family adapted to it
(`Problem.parametrize`), a naive start (a zero or constant control, what a new user would
try), and the reference objective of the *continuous* problem with its source. References
are independent of jaxtraj's code: closed-form solutions, or a second method (the cycloid of
the brachistochrone and Zermelo's steering law by root finding; the optimality conditions of
the hypersensitive and orbit-raising problems by `scipy.integrate.solve_bvp`; CasADi
collocation in `benchmarks/collocation.py`), recomputed in `tests/test_classic.py`. A
restricted control (K pieces) may stay above the continuous optimum by its restriction gap
(`gap`, the room a solver's objective is given above the reference).

Together they cover: free-tf minimum time, a fixed-tf Mayer objective, running costs,
bang-bang controls under control bounds, a state path constraint, singular arcs (Goddard's
rocket), a terminal inequality, several controls, a design parameter, a free initial state, a
sensitive (hypersensitive) problem, time-varying dynamics (orbit raising) and a
state-dependent field (Zermelo). `benchmarks/gallery.py` solves them all with every solver.
"""

import dataclasses
from typing import cast

import jax
import jax.numpy as jnp
import numpy as np

from .._problem import Problem
from ..controls import AbstractControl, PiecewiseConstant, PiecewiseLinear


@dataclasses.dataclass(frozen=True)
class ClassicProblem:
    """One gallery entry.

    - `name`; `problem`; `control` (for `problem`: `problem.parametrize(family)`); `start`:
      the naive starting vector.
    - `reference`: the continuous problem's optimal objective; `reference_method`: how it is
      known (closed form, or the independent method); `source`: the literature.
    - `gap`: how far above `reference` the restricted optimum may lie (restriction gap plus
      RK4 error), the tolerance of "at the reference optimum".
    - `features`: what the problem exercises.
    """

    name: str
    problem: Problem
    control: AbstractControl
    start: jax.Array
    reference: float
    reference_method: str
    source: str
    gap: float
    features: tuple[str, ...]


def _zero_start(problem, family, tf=1.0, u=0.0):
    control = problem.parametrize(family)
    return control, control.initial_guess(tf if problem.final_time is None else float(problem.final_time), u, u)


# -------------------------------------------------------------------- dynamics and costs


def _integrator(t, x, u, args):
    del t, args
    return u


def _double_integrator(t, x, u, args):
    del t, args
    return jnp.stack([x[1], u[0]])


def _planar_double_integrator(t, x, u, args):
    del t, args
    return jnp.concatenate([x[2:], u])


def _half_x2_u2(t, x, u, args):
    del t, args
    return 0.5 * (x[0] ** 2 + u[0] ** 2)


def _half_u2(t, x, u, args):
    del t, args
    return 0.5 * jnp.sum(u**2)


def _x2(t, x, u, args):
    del t, u, args
    return x[0] ** 2


def _no_terminal(tf, xf, args):
    del tf, xf, args
    return jnp.zeros(0)


def _to_target(tf, xf, args):
    del tf
    return xf - args["target"]


# -------------------------------------------------------------------- the problems


def lq() -> ClassicProblem:
    """min 1/2 int_0^1 (x^2 + u^2) dt, x' = u, x(0) = 1, x(1) free."""
    problem = Problem(_integrator, [1.0], _no_terminal, (), running_cost=_half_x2_u2, final_time=1.0, name="lq")
    control, start = _zero_start(problem, PiecewiseLinear(20))
    return ClassicProblem(
        "lq", problem, control, start, 0.5 * float(np.tanh(1.0)),
        "closed form: Riccati P(t) = tanh(1 - t), J* = P(0) x0^2 / 2",
        "textbook LQ regulator (Riccati equation)", 1e-6,
        ("running cost", "fixed tf"),
    )  # fmt: skip


def bryson_denham() -> ClassicProblem:
    """x'' = u, (x, v): (0, 1) -> (0, -1) in time 1, x <= 1/9, min 1/2 int u^2."""
    problem = Problem(
        _double_integrator, [0.0, 1.0], _to_target, ("x", "v"),
        args={"target": jnp.array([0.0, -1.0])}, running_cost=_half_u2, final_time=1.0,
        state_names=("x", "v"), state_upper=[1.0 / 9.0, np.inf], name="bryson-denham",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(20))
    return ClassicProblem(
        "bryson-denham", problem, control, start, 4.0, "closed form: J* = 4 / (9 l), l = 1/9",
        "Bryson & Ho (1975), sec. 3.11", 2e-3, ("state path constraint", "running cost", "fixed tf"),
    )  # fmt: skip


def min_time_double_integrator() -> ClassicProblem:
    """x'' = u, |u| <= 1, rest at 0 to rest at 1, min tf: u = +1 then -1, tf* = 2."""
    problem = Problem(
        _double_integrator, [0.0, 0.0], _to_target, ("x", "v"), args={"target": jnp.array([1.0, 0.0])},
        control_lower=-1.0, control_upper=1.0, name="min-time-double-integrator",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseConstant(2, free_times=True), tf=1.0)
    return ClassicProblem(
        "min-time-double-integrator", problem, control, start, 2.0, "closed form: bang-bang, switch at tf/2",
        "textbook time-optimal control (e.g. Kirk, Optimal Control Theory, 1970, ch. 5)", 1e-6,
        ("free tf, minimum time", "bang-bang", "control bounds"),
    )  # fmt: skip


def _brachistochrone(t, x, u, args):
    del t
    s, c = jnp.sin(u[0]), jnp.cos(u[0])
    return jnp.stack([x[2] * s, -x[2] * c, args["g"] * c])


def _brachistochrone_terminal(tf, xf, args):
    del tf
    return xf[:2] - args["target"]


def brachistochrone_time(dx=10.0, dy=5.0, g=9.80665) -> float:
    """The analytic descent time along the cycloid through (0, 0) and (dx, -dy): phi_f solves
    (phi - sin phi) / (1 - cos phi) = dx / dy, R = dy / (1 - cos phi_f), T = phi_f sqrt(R / g)."""
    import scipy.optimize

    # (a float: without `full_output` brentq returns the root alone)
    phi = cast(
        float, scipy.optimize.brentq(lambda p: (p - np.sin(p)) / (1.0 - np.cos(p)) - dx / dy, 1e-6, 2 * np.pi - 1e-6)
    )
    return float(phi * np.sqrt(dy / (1.0 - np.cos(phi)) / g))


def brachistochrone() -> ClassicProblem:
    """Dymos' brachistochrone: from (0, 10) at rest to (10, 5) under g = 9.80665, min tf; the
    control is the angle from the downward vertical."""
    problem = Problem(
        _brachistochrone, [0.0, 10.0, 0.0], _brachistochrone_terminal, ("x", "y"),
        args={"g": jnp.asarray(9.80665), "target": jnp.array([10.0, 5.0])},
        state_names=("x", "y", "v"), control_names=("theta",), name="brachistochrone",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(10), tf=2.0, u=1.0)
    return ClassicProblem(
        "brachistochrone", problem, control, start, brachistochrone_time(),
        "the cycloid, by root finding (`brachistochrone_time`)",
        "Dymos documentation, brachistochrone example (tf = 1.8016)", 1e-4, ("free tf, minimum time",),
    )  # fmt: skip


def _lander(t, x, u, args):
    del t
    return jnp.stack([x[1], u[0] - args["g"]])


def _thrust(t, x, u, args):
    del t, x, args
    return u[0]


def moon_lander() -> ClassicProblem:
    """Soft landing with least fuel: h' = v, v' = u - g, g = 1.5, 0 <= u <= 3, (h, v): (10, -2)
    -> (0, 0), min int u dt, tf free. Optimal: free fall, then full thrust to touch down at
    rest; the switch s solves 1.5 s^2 + 4 s - 26/3 = 0 and J* = 3 (2 + 1.5 s) / 1.5 =
    sqrt(68)."""
    problem = Problem(
        _lander, [10.0, -2.0], _to_target, ("h", "v"),
        args={"g": jnp.asarray(1.5), "target": jnp.zeros(2)}, running_cost=_thrust,
        control_lower=0.0, control_upper=3.0, state_names=("h", "v"), name="moon-lander",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseConstant(2, free_times=True), tf=4.0, u=1.5)
    return ClassicProblem(
        "moon-lander", problem, control, start, float(np.sqrt(68.0)),
        "closed form: coast, then full thrust", "Meditch (1964), IEEE Trans. Autom. Control 9(4) (numbers chosen here)", 1e-6,
        ("bang-bang", "control bounds", "running cost", "free tf"),
    )  # fmt: skip


def singular_arc() -> ClassicProblem:
    """x' = u, |u| <= 1, x(0) = 1, tf = 2, min int x^2 dt: u = -1 until x = 0 at t = 1, then the
    singular arc u = 0; J* = 1/3."""
    problem = Problem(
        _integrator, [1.0], _no_terminal, (), running_cost=_x2, final_time=2.0,
        control_lower=-1.0, control_upper=1.0, name="singular-arc",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseConstant(4))
    return ClassicProblem(
        "singular-arc", problem, control, start, 1.0 / 3.0, "closed form: bang, then singular u = 0",
        "textbook singular arc (constructed numbers)", 1e-6,
        ("singular arc", "control bounds", "running cost", "fixed tf"),
    )  # fmt: skip


def _maximize_first_state(tf, xf, args):
    del tf, args
    return -xf[0]


def _at_rest(tf, xf, args):
    del tf, args
    return xf[1:2]


def max_range() -> ClassicProblem:
    """x'' = u, |u| <= 1, from rest, v(1) = 0, max x(1) (min -x(1)): u = +1 then -1, x(1) = 1/4."""
    problem = Problem(
        _double_integrator, [0.0, 0.0], _at_rest, ("v",), objective=_maximize_first_state, final_time=1.0,
        control_lower=-1.0, control_upper=1.0, name="max-range",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseConstant(2))
    return ClassicProblem(
        "max-range", problem, control, start, -0.25, "closed form: bang-bang, switch at 1/2",
        "textbook bang-bang (constructed numbers)", 1e-6,
        ("fixed tf, Mayer objective", "bang-bang", "control bounds"),
    )  # fmt: skip


def two_channel() -> ClassicProblem:
    """x'' = u in the plane, rest at 0 to rest at (1, 2) in time 1, min 1/2 int |u|^2: each
    channel u = d (6 - 12 t), J* = 6 |d|^2 = 30."""
    problem = Problem(
        _planar_double_integrator, np.zeros(4), _to_target, ("x", "y", "vx", "vy"), num_controls=2,
        args={"target": jnp.array([1.0, 2.0, 0.0, 0.0])}, running_cost=_half_u2, final_time=1.0,
        name="two-channel",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(4, channels=2))
    return ClassicProblem(
        "two-channel", problem, control, start, 30.0, "closed form (each channel: min-energy rest to rest)",
        "textbook minimum-energy transfer", 1e-8, ("several controls", "running cost", "fixed tf"),
    )  # fmt: skip


def _with_design(t, x, u, args):
    del t, args
    return jnp.stack([u[0], jnp.zeros_like(u[0])])


def _reach_p(tf, xf, args):
    del tf, args
    return xf[:1] - xf[1:]


def _p_cost(tf, xf, args):
    del tf, args
    return 0.5 * (xf[1] - 2.0) ** 2


def design_parameter() -> ClassicProblem:
    """x' = u, x(0) = 0, x(1) = p with p a design parameter in [0, 5], min 1/2 int u^2 +
    (p - 2)^2 / 2: u = p, so p* = 1, J* = 1."""
    problem = Problem(
        _with_design, [0.0, 0.0], _reach_p, ("x(1) = p",), objective=_p_cost, running_cost=_half_u2,
        final_time=1.0, state_names=("x", "p"), free_initial_state={"p": (0.0, 5.0)}, name="design-parameter",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(2))
    return ClassicProblem(
        "design-parameter", problem, control, start, 1.0, "closed form", "constructed (design-parameter check)",
        1e-8, ("design parameter", "running cost", "fixed tf"),
    )  # fmt: skip


def _x_is_one(tf, xf, args):
    del tf, args
    return xf[:1] - 1.0


def free_initial_state() -> ClassicProblem:
    """x' = u, x(0) free, x(1) = 1, min 1/2 int (x^2 + u^2): lambda(0) = 0 gives
    x = cosh(t) / cosh(1), J* = tanh(1) / 2."""
    problem = Problem(
        _integrator, [1.0], _x_is_one, ("x(1)",), running_cost=_half_x2_u2, final_time=1.0,
        free_initial_state=(0,), name="free-initial-state",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(20))
    return ClassicProblem(
        "free-initial-state", problem, control, start, 0.5 * float(np.tanh(1.0)),
        "closed form (transversality: lambda(0) = 0)", "textbook transversality condition (constructed numbers)",
        1e-6, ("free initial state", "running cost", "fixed tf"),
    )  # fmt: skip


def _minus_2x(tf, xf, args):
    del tf, args
    return -2.0 * xf[0]


def _cap(tf, xf, args):
    del tf, args
    return xf[:1] - 1.0


def capped_terminal() -> ClassicProblem:
    """x' = u, x(0) = 0, tf = 1, min 1/2 int u^2 - 2 x(1) with x(1) <= 1: the cap binds, u = 1,
    J* = -1.5."""
    problem = Problem(
        _integrator, [0.0], _no_terminal, (), objective=_minus_2x, running_cost=_half_u2, final_time=1.0,
        terminal_inequality=_cap, terminal_inequality_names=("x(1) cap",), name="capped-terminal",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(3))
    return ClassicProblem(
        "capped-terminal", problem, control, start, -1.5, "closed form (KKT, cap active)", "constructed",
        1e-8, ("terminal inequality", "running cost", "fixed tf"),
    )  # fmt: skip


def _zermelo(t, x, u, args):
    del t, args
    return jnp.stack([jnp.cos(u[0]) - x[1], jnp.sin(u[0])])


#: `zermelo_time()`, recomputed in tests/test_classic.py
ZERMELO_TIME = 5.45786526


def zermelo_time(start=(3.66, -1.86)) -> float:
    """The closed-form steering law, by root finding: with the current -y along x the costate
    gives tan(theta) = c + t, theta = pi + atan(c + t) (the branch heading against the
    current); c and tf are found so that the ship reaches the origin, its path integrated by
    `scipy.integrate.solve_ivp`."""
    import scipy.integrate
    import scipy.optimize

    def miss(p):
        c, tf = p

        def rhs(t, s):
            theta = np.pi + np.arctan(c + t)
            return [np.cos(theta) - s[1], np.sin(theta)]

        return scipy.integrate.solve_ivp(rhs, (0.0, tf), list(start), rtol=1e-12, atol=1e-12).y[:, -1]

    (_, tf), _, ok, msg = scipy.optimize.fsolve(miss, [-2.0, 4.0], xtol=1e-13, full_output=True)
    if ok != 1:  # pragma: no cover - a reference that cannot be computed is an error
        raise RuntimeError(f"zermelo reference: {msg}")
    return float(tf)


def zermelo() -> ClassicProblem:
    """Bryson & Ho's Zermelo problem with a linear current: x' = cos(theta) - y, y' =
    sin(theta) (ship speed 1, current -y along x), from (3.66, -1.86) to the origin in least
    time; the heading turns from 105 to 240 degrees, tf* = 5.4579."""
    problem = Problem(
        _zermelo, [3.66, -1.86], _to_target, ("x", "y"), args={"target": jnp.zeros(2)}, state_names=("x", "y"),
        control_names=("theta",), name="zermelo",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(8), tf=5.0, u=np.pi)
    return ClassicProblem(
        "zermelo", problem, control, start, ZERMELO_TIME, "closed-form steering law, by root finding (`zermelo_time`)",
        "Bryson & Ho (1975), sec. 2.7 (tf = 5.46 h/V)", 2e-4, ("free tf, minimum time", "state-dependent field"),
    )  # fmt: skip


def _goddard(t, x, u, args):
    del t
    h, v, m = x[0], x[1], x[2]
    drag = args["drag"] * v**2 * jnp.exp(-args["h_c"] * (h - 1.0))
    return jnp.stack([v, (u[0] - drag) / m - 1.0 / h**2, -u[0] / args["c"]])


def _goddard_mass(tf, xf, args):
    del tf
    return xf[2:3] - args["final_mass"]


#: `orbit_raising_radius()`, recomputed in tests/test_classic.py
ORBIT_RAISING_RADIUS = 1.5252777


def orbit_raising_radius(tf=3.32, thrust=0.1405, mass_flow=0.0749) -> float:
    """r(tf) by the indirect method, an independent second method: states (r, vr, vt),
    costates (lr, lu, lv), the thrust direction minimizes the Hamiltonian, (sin phi, cos phi)
    = -(lu, lv) / |(lu, lv)|; transversality of -r(tf) + nu (vt - r^-1/2): lr(tf) = -1 +
    lv(tf) / (2 r(tf)^3/2). Solved by `scipy.integrate.solve_bvp` (tolerance 1e-10)."""
    import scipy.integrate

    def rhs(t, y):
        r, vr, vt, lr, lu, lv = y
        a = thrust / (1.0 - mass_flow * t)
        norm = np.hypot(lu, lv)
        return np.vstack([
            vr, vt**2 / r - 1.0 / r**2 - a * lu / norm, -vr * vt / r - a * lv / norm,
            -(lu * (2.0 / r**3 - vt**2 / r**2) + lv * vr * vt / r**2), lv * vt / r - lr, (lv * vr - 2.0 * lu * vt) / r,
        ])  # fmt: skip

    def bc(ya, yb):
        r, vr, vt, lr, _, lv = yb
        return np.array([ya[0] - 1.0, ya[1], ya[2] - 1.0, vr, vt - r**-0.5, lr + 1.0 - lv / (2.0 * r**1.5)])

    tau = np.linspace(0.0, 1.0, 201)
    phi = 0.5 + 2.5 * tau  # outward-forward, turning to outward-backward
    r = 1.0 + 0.5 * tau**2 * (3.0 - 2.0 * tau)
    guess = np.vstack([r, 3.0 * tau * (1.0 - tau) / tf, r**-0.5, -np.ones_like(tau), -np.sin(phi), -np.cos(phi)])
    with np.errstate(divide="ignore", invalid="ignore"):  # trial Newton iterates may reach r = 0
        sol = scipy.integrate.solve_bvp(rhs, bc, tf * tau, guess, tol=1e-6, max_nodes=100000)
        sol = scipy.integrate.solve_bvp(rhs, bc, sol.x, sol.y, tol=1e-10, max_nodes=200000)
    if sol.status != 0:  # pragma: no cover - a reference that cannot be computed is an error
        raise RuntimeError(f"orbit-raising reference: solve_bvp failed ({sol.message})")
    return float(sol.sol(tf)[0])


#: the final height by CasADi Hermite-Simpson collocation (`benchmarks/collocation.py`, 1600
#: intervals, converging from above); COPS 3.0 (Dolan, More & Munson 2004) gives 1.01283
GODDARD_HEIGHT = 1.012837


def goddard() -> ClassicProblem:
    """COPS' Goddard rocket: the greatest height of a rocket under height-dependent drag and
    inverse-square gravity. (h, v, m) = (1, 0, 1), thrust 0 <= T <= 3.5, h' = v, v' = (T -
    D) / m - 1 / h^2, m' = -T / c, D = 310 v^2 exp(-500 (h - 1)), c = 1/2, final mass 0.6, tf
    free, min -h(tf). The optimum is bang (full thrust), a singular arc, then a coast."""
    problem = Problem(
        _goddard, [1.0, 0.0, 1.0], _goddard_mass, ("m(tf) = 0.6",), objective=_maximize_first_state,
        args={"drag": jnp.asarray(310.0), "h_c": jnp.asarray(500.0), "c": jnp.asarray(0.5),
              "final_mass": jnp.asarray(0.6)},
        control_lower=0.0, control_upper=3.5, state_names=("h", "v", "m"), control_names=("T",), name="goddard",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(10), tf=0.2, u=1.0)
    return ClassicProblem(
        "goddard", problem, control, start, -GODDARD_HEIGHT, "CasADi collocation (benchmarks/collocation.py); COPS 3.0 publishes 1.01283",
        "Dolan, More & Munson (2004), COPS 3.0, ANL/MCS-TM-246, Goddard rocket", 1e-4,
        ("singular arc", "control bounds", "free tf, Mayer objective"),
    )  # fmt: skip


def _orbit_raising(t, x, u, args):
    r, vr, vt = x[0], x[1], x[2]
    accel = args["thrust"] / (1.0 - args["mass_flow"] * t) * u / jnp.sqrt(jnp.sum(u**2))
    return jnp.stack([vr, vt**2 / r - 1.0 / r**2 + accel[0], -vr * vt / r + accel[1]])


def _circular(tf, xf, args):
    del tf, args
    return jnp.stack([xf[1], xf[2] - 1.0 / jnp.sqrt(xf[0])])


def orbit_raising() -> ClassicProblem:
    """Bryson & Ho's orbit raising: the largest circular orbit reached in time 3.32 (mu = 1)
    from the unit circular orbit with constant thrust 0.1405 and mass 1 - 0.0749 t. The
    control is the thrust direction as a vector (radial, tangential), normalized in the
    dynamics: an angle would need the right turn (about 5 rad through the retrograde
    direction) from the start, and from a constant start ends at a local optimum with one
    segment turning the wrong way. States (r, vr, vt); the terminal orbit is circular (vr =
    0, vt = r^-1/2); min -r(tf)."""
    problem = Problem(
        _orbit_raising, [1.0, 0.0, 1.0], _circular, ("vr", "vt - r^-1/2"), objective=_maximize_first_state,
        args={"thrust": jnp.asarray(0.1405), "mass_flow": jnp.asarray(0.0749)}, final_time=3.32,
        num_controls=2, state_names=("r", "vr", "vt"), control_names=("radial", "tangential"), name="orbit-raising",
    )  # fmt: skip
    control = problem.parametrize(PiecewiseLinear(10, channels=2))
    start = control.initial_guess(3.32, [0.0, 1.0], [0.0, 1.0])  # tangential thrust
    return ClassicProblem(
        "orbit-raising", problem, control, start, -ORBIT_RAISING_RADIUS,
        "indirect method by scipy.integrate.solve_bvp (`orbit_raising_radius`); CasADi collocation",
        "Bryson & Ho (1975), sec. 2.5 (r(tf) = 1.525)", 2e-5, ("fixed tf, Mayer objective", "time-varying dynamics"),
    )  # fmt: skip


def _hyper(t, x, u, args):
    del t, args
    return -(x[:1] ** 3) + u


HYPERSENSITIVE_TF = 20.0
#: `hypersensitive_reference()` (tf = 20), recomputed in tests/test_classic.py
HYPERSENSITIVE_REFERENCE = 1.3308069


def hypersensitive_reference(tf=HYPERSENSITIVE_TF) -> float:
    """The optimum by the indirect method, an independent second method: the optimality
    conditions x' = -x^3 - lambda, lambda' = -x + 3 x^2 lambda (u = -lambda), x(0) = 1.5,
    x(tf) = 1, solved by `scipy.integrate.solve_bvp`, then J = 1/2 int (x^2 + lambda^2)."""
    import scipy.integrate

    def rhs(t, y):
        x, lam = y
        return np.vstack([-(x**3) - lam, -x + 3.0 * x**2 * lam])

    def bc(ya, yb):
        return np.array([ya[0] - 1.5, yb[0] - 1.0])

    t = np.linspace(0.0, tf, 2001)
    guess = np.vstack([1.5 * np.exp(-t) + np.exp(t - tf), np.zeros_like(t)])
    sol = scipy.integrate.solve_bvp(rhs, bc, t, guess, tol=1e-10, max_nodes=200000)
    if not sol.success:  # pragma: no cover - a reference that cannot be computed is an error
        raise RuntimeError(f"hypersensitive reference: solve_bvp failed ({sol.message})")
    fine = np.linspace(0.0, tf, 200001)
    x, lam = sol.sol(fine)
    return float(scipy.integrate.simpson(0.5 * (x**2 + lam**2), x=fine))


def hypersensitive() -> ClassicProblem:
    """Rao & Mease's hypersensitive problem: x' = -x^3 + u, x(0) = 1.5, x(tf) = 1, min 1/2 int
    (x^2 + u^2), here with tf = 20 (boundary layers at both ends, an unstable costate)."""
    problem = Problem(
        _hyper, [1.5], _x_is_one, ("x(tf)",), running_cost=_half_x2_u2, final_time=HYPERSENSITIVE_TF,
        name="hypersensitive",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(40))
    return ClassicProblem(
        "hypersensitive", problem, control, start, HYPERSENSITIVE_REFERENCE,
        "indirect method by scipy.integrate.solve_bvp (`hypersensitive_reference`)",
        "Rao & Mease (2000), Optimal Control Appl. Methods 21; GPOPS-II examples", 5e-3,
        ("sensitive / unstable", "running cost", "fixed tf"),
    )  # fmt: skip


# ------------------------------------------------------------------- free-flying robot

#: The best known objective of the free-flying robot on 30 linear pieces: IPOPT's from the
#: start u = 0.5 perturbed by 1e-12 (`tests/test_classic.py`, which integrates its control
#: again with SciPy). It is below the 7.9101471 that Betts (2010, ex. 6.13) publishes for the
#: continuous problem, a local optimum there.
FREE_FLYING_ROBOT_COST = 7.789744305


def _free_flying_robot(t, x, u, args):
    thrust = (u[0] - u[1]) + (u[2] - u[3])  # F1 + F2
    return jnp.stack(
        [
            x[3],
            x[4],
            x[5],
            thrust * jnp.cos(x[2]),
            thrust * jnp.sin(x[2]),
            args["arm"] * ((u[0] - u[1]) - (u[2] - u[3])),
        ]
    )


def _sum_u(t, x, u, args):
    return jnp.sum(u)


def free_flying_robot(segments: int = 30) -> ClassicProblem:
    """A free-flying robot (Sakawa 1999; Betts 2010, example 6.13): two thrusters, each a pair
    of controls 0 <= u <= 1 (F1 = u0 - u1, F2 = u2 - u3), (x, y, theta, vx, vy, omega) from
    (-10, -10, pi/2, 0, 0, 0) to rest at the origin in tf = 12, min int u0 + u1 + u2 + u3.
    Four bounded controls on `segments` pieces (30: 124 parameters, 248 bound rows): the size
    study of issue 49 (the cost of an iteration as parameters and rows grow). The optimum is
    bang-bang, and the restricted problem (30 pieces, RK4) has several local optima: 7.78974
    (the reference, the best known: `FREE_FLYING_ROBOT_COST`), 7.97519 (IPOPT from the zero
    start), 8.01782 (the default solver from the zero start and its round-off perturbations,
    under each ISA setting: RESULTS.md, roundoff.py --gallery), 8.01819 and 8.02074 (where
    earlier versions went from perturbed starts). `gap` (0.25) admits those, not 10.11 (the
    default from u = 0.5 perturbed by 1e-10)."""
    problem = Problem(
        _free_flying_robot, [-10.0, -10.0, np.pi / 2, 0.0, 0.0, 0.0], _at_origin, tuple(f"{n}(tf) = 0" for n in _FFR_STATES),
        num_controls=4, args={"arm": jnp.asarray(0.2)}, running_cost=_sum_u, final_time=12.0,
        control_lower=[0.0] * 4, control_upper=[1.0] * 4, state_names=_FFR_STATES,
        control_names=("u1+", "u1-", "u2+", "u2-"), name="free-flying-robot",
    )  # fmt: skip
    control, start = _zero_start(problem, PiecewiseLinear(segments, channels=4))
    return ClassicProblem(
        "free-flying-robot", problem, control, start, FREE_FLYING_ROBOT_COST,
        "best known restricted optimum (IPOPT, checked by SciPy integration); Betts publishes 7.9101471",
        "Sakawa (1999), Trajectory planning of a free-flying robot by using the optimal control, "
        "Optimal Control Appl. Methods 20; Betts (2010), Practical Methods for Optimal Control, ex. 6.13", 0.25,
        ("several controls", "control bounds", "running cost", "fixed tf", "size: 124 parameters"),
    )  # fmt: skip


_FFR_STATES = ("x", "y", "theta", "vx", "vy", "omega")


def _at_origin(tf, xf, args):
    return xf


_BUILDERS = {
    "lq": lq,
    "bryson-denham": bryson_denham,
    "min-time-double-integrator": min_time_double_integrator,
    "brachistochrone": brachistochrone,
    "moon-lander": moon_lander,
    "singular-arc": singular_arc,
    "max-range": max_range,
    "two-channel": two_channel,
    "design-parameter": design_parameter,
    "free-initial-state": free_initial_state,
    "capped-terminal": capped_terminal,
    "hypersensitive": hypersensitive,
    "zermelo": zermelo,
    "goddard": goddard,
    "orbit-raising": orbit_raising,
    "free-flying-robot": free_flying_robot,
}


def names() -> tuple[str, ...]:
    """The gallery's problem names."""
    return tuple(_BUILDERS)


def get(name: str) -> ClassicProblem:
    """The gallery entry `name` (see `names()`)."""
    if name not in _BUILDERS:
        raise ValueError(f"`name` must be one of {names()}; got {name!r}.")
    return _BUILDERS[name]()
