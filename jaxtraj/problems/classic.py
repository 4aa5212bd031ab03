"""A gallery of classic optimal-control problems from the literature, each with its
reference optimum and where it comes from.

`get(name)` gives a `ClassicProblem`: the `jt.Problem`, a control family adapted to it
(`Problem.parametrize`), a naive start (a zero or constant control, what a new user would
try), and the reference objective of the *continuous* problem with its source. References
are independent of jaxtraj's code: closed-form solutions, or a second method (the cycloid of
the brachistochrone by root finding; the hypersensitive problem's optimality conditions by
`scipy.integrate.solve_bvp`), recomputed in `tests/test_classic.py`. A restricted control
(K pieces) may stay above the continuous optimum by its restriction gap (`gap`, the room a
solver's objective is given above the reference).

Together they cover: free-tf minimum time, a fixed-tf Mayer objective, running costs,
bang-bang controls under control bounds, a state path constraint, a singular arc, a terminal
inequality, several controls, a design parameter, a free initial state and a sensitive
(hypersensitive) problem. `benchmarks/gallery.py` solves them all with every solver.
"""

import dataclasses

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

    phi = scipy.optimize.brentq(lambda p: (p - np.sin(p)) / (1.0 - np.cos(p)) - dx / dy, 1e-6, 2 * np.pi - 1e-6)
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


def _minus_x(tf, xf, args):
    del tf, args
    return -xf[0]


def _at_rest(tf, xf, args):
    del tf, args
    return xf[1:2]


def max_range() -> ClassicProblem:
    """x'' = u, |u| <= 1, from rest, v(1) = 0, max x(1) (min -x(1)): u = +1 then -1, x(1) = 1/4."""
    problem = Problem(
        _double_integrator, [0.0, 0.0], _at_rest, ("v",), objective=_minus_x, final_time=1.0,
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
}


def names() -> tuple[str, ...]:
    """The gallery's problem names."""
    return tuple(_BUILDERS)


def get(name: str) -> ClassicProblem:
    """The gallery entry `name` (see `names()`)."""
    if name not in _BUILDERS:
        raise ValueError(f"`name` must be one of {names()}; got {name!r}.")
    return _BUILDERS[name]()
