"""Minimum-time planar solar-sail transfers from Earth's orbit to Mercury's, Venus's or Mars's
(seed 003; Kelley's Earth-to-Mars-orbit sail problem as the anchor).

States (normalized units: 1 AU, mu = 1, 1 time unit = 1 / (2 pi) year): r, theta, u, v.
Control alpha: the sail's pitch angle in [-pi/2, pi/2] (from the Sun-line to the normal of the
sail's back side, positive towards the motion). Ideal flat sail with characteristic
acceleration a0:

    r'     = u
    theta' = v / r
    u'     = v^2 / r - mu / r^2 + a0 cos^3(alpha) / r^2
    v'     = -u v / r + a0 cos^2(alpha) sin(alpha) / r^2

(`dynamics` writes cos -> |cos|: the same on [-pi/2, pi/2], pi-periodic outside.) From Earth's
circular orbit to the target's at the free final time tf, theta free; minimize tf.

Besides the constrained problem (`problem`) the module has the seed's penalty functional
(eq. 5, `penalty_objective`) and the parameter box (`box`) for the metaheuristics, the
diagnostics that flag spurious outcomes (`terminal_miss`, `feathered_fraction`,
`diagnose`), Kelley's anchor (`kelley_case`) and an independent indirect (Pontryagin)
solution of the unrestricted problem (`solve_indirect`).

(The model, its conventions and why: docs/examples.md, "Solar-sail transfers".)
"""

import math

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .._checks import check_problem_and_control
from .._problem import Problem
from .._simulate import RK4, AbstractSimulator, check_simulator, final_state
from .._status import Status
from ..controls import AbstractControl, SaturatedSpline
from ._sail_indirect import DAYS_PER_UNIT, IndirectResult, optimal_pitch, shoot

#: Mean orbital radii of the targets [AU] (circular, coplanar orbits). Seed 003 Table 1
#: rounds them to 0.39, 0.72, 1.52.
TARGET_RADII = {"mercury": 0.387098, "venus": 0.723332, "mars": 1.523679}

#: Kelley's sail: characteristic acceleration 0.17 (~1.0 mm/s^2 at 1 AU: 0.17 * mu_sun / AU^2
#: = 0.17 * 5.93 mm/s^2) and Mars's radius as Kelley rounds it.
KELLEY_A0 = 0.17
KELLEY_RF = 1.5237

#: Kelley's published minimum time Earth -> Mars orbit for the unrestricted control (~406 d).
TF_KELLEY = 6.9925

#: Our own unrestricted optimum for Kelley's case, from `solve_indirect` (Pontryagin
#: shooting, DOP853 at rtol = atol = 1e-12, boundary residual < 1e-13; restarts from other
#: pitch guesses land on the same extremal): 0.01 % above the published 6.9925 (= 406.52 d vs
#: 406.48 d). Every feasible restricted control we measured lies above it.
TF_KELLEY_INDIRECT = 6.993186

#: Default weights (lambda_1, ..., lambda_4) of the penalty functional (seed eq. 5; the seed
#: leaves them open): 1 on tf in days, 1e10 on each squared terminal error. Measured on
#: Kelley's case (SaturatedSpline(10, 1), J minimized by L-BFGS-B from the constrained
#: optimum 406.54 d), the penalized minimum with weights w on the errors:
#:   w = 1e4: 245.2 d, miss 5.6e-2 (the issue's trap: 40 % "faster", not a transfer);
#:   w = 1e6: 402.1 d, miss 1.3e-3;  w = 1e8: 406.48 d, miss 1.4e-5;
#:   w = 1e10: 406.54 d, miss 1.4e-7 (the miss scales as ~1.4e3 / w).
DEFAULT_WEIGHTS = (1.0, 1.0e10, 1.0e10, 1.0e10)

STATE_NAMES = ("radius", "polar angle", "radial velocity", "tangential velocity")
CONSTRAINT_NAMES = ("radius", "radial velocity", "tangential velocity")
CONTROL_LOWER = -0.5 * math.pi
CONTROL_UPPER = 0.5 * math.pi


def dynamics(t, x, u, args):
    """f(t, x, alpha, args) of the planar sail (see the module docstring)."""
    del t
    r, v_r, v_t = x[0], x[2], x[3]
    alpha = u[0]
    c, s = jnp.cos(alpha), jnp.sin(alpha)
    # |cos| extends the seed's formula pi-periodically beyond [-pi/2, pi/2] (identical inside).
    c_abs = jnp.abs(c)
    sail = args["a0"] / r**2
    return jnp.stack(
        [
            v_r,
            v_t / r,
            v_t**2 / r - args["mu"] / r**2 + sail * c_abs**3,
            -v_r * v_t / r + sail * c * c_abs * s,
        ]
    )


def terminal(tf, xf, args):
    """M = (r - r_f, u, v - sqrt(mu / r_f)); theta is free."""
    del tf
    r_f = args["r_f"]
    return jnp.stack([xf[0] - r_f, xf[2], xf[3] - jnp.sqrt(args["mu"] / r_f)])


def _target_radius(target, r_f):
    if r_f is not None:
        r_f = float(r_f)
        if not (math.isfinite(r_f) and r_f > 0):
            raise ValueError(f"`r_f` must be a finite radius > 0 [AU]; got {r_f!r}.")
        return r_f
    if not isinstance(target, str) or target.lower() not in TARGET_RADII:
        raise ValueError(f"`target` must be one of {sorted(TARGET_RADII)}; got {target!r}.")
    return TARGET_RADII[target.lower()]


def problem(target: str = "mars", a0: float = KELLEY_A0, *, r_f: float | None = None, mu: float = 1.0) -> Problem:
    """The constrained minimum-time sail transfer from Earth's orbit to `target`'s.

    **Arguments:**

    - `target`: `"mars"`, `"venus"` or `"mercury"` (radius from `TARGET_RADII`).
    - `a0`: characteristic acceleration of the sail (normalized; default Kelley's 0.17).
    - `r_f`: keyword-only, overrides the target radius (e.g. `KELLEY_RF` = 1.5237).
    - `mu`: keyword-only, the Sun's gravitational parameter (1 in normalized units).

    **Returns:** a `jt.Problem` with x0 = (1, 0, 0, sqrt(mu)) (Earth's circular orbit; (1, 0, 0, 1)
    for the default mu = 1; set at construction), terminal constraints (radius,
    radial velocity, tangential velocity), objective tf, control bounds [-pi/2, pi/2] and
    `args = {"a0", "r_f", "mu"}` (float64 arrays: change them without recompiling) and the
    name `"solar-sail-<target>"` (`"solar-sail-r<r_f>"` with `r_f`). The problems of
    different targets differ only in `args` and names, which take no part in compilation:
    a solver compiled for one target runs the others without recompiling.
    """
    radius = _target_radius(target, r_f)
    a0 = float(a0)
    if not (math.isfinite(a0) and a0 >= 0):
        raise ValueError(f"`a0` must be a finite characteristic acceleration >= 0; got {a0!r}.")
    mu = float(mu)
    if not (math.isfinite(mu) and mu > 0):
        raise ValueError(f"`mu` must be finite and > 0; got {mu!r}.")
    args = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in (("a0", a0), ("r_f", radius), ("mu", mu))}
    name = f"solar-sail-{target.lower()}" if r_f is None else f"solar-sail-r{radius:g}"
    return Problem(
        dynamics,
        x0=[1.0, 0.0, 0.0, math.sqrt(mu)],
        terminal=terminal,
        constraint_names=CONSTRAINT_NAMES,
        args=args,
        state_names=STATE_NAMES,
        control_names=("pitch angle [rad]",),
        control_lower=CONTROL_LOWER,
        control_upper=CONTROL_UPPER,
        name=name,
    )


def spline_control(segments: int = 10, degree: int = 1, *, free_durations: bool = True) -> SaturatedSpline:
    """The seed's control: `SaturatedSpline(segments, degree, -pi/2, pi/2)`."""
    return SaturatedSpline(segments, degree, CONTROL_LOWER, CONTROL_UPPER, free_durations=free_durations)


def kelley_case(segments: int = 10, degree: int = 1, *, pitch_deg: float = 35.0, tf: float = 7.0):
    """`(problem, control, a)` for Kelley's Earth-to-Mars-orbit anchor.

    `problem(r_f=KELLEY_RF, a0=KELLEY_A0)`, the seed's `SaturatedSpline(segments, degree,
    -pi/2, pi/2)` with free durations, and the starting vector with equal durations tf / P
    and a constant pitch of `pitch_deg` (a prograde push). `a` is the parameter vector (not
    the sail's acceleration, which is `KELLEY_A0`).

    !!! note "SLSQP from this start (measured, `jaxtraj.baselines.solve_slsqp`, RK4(100))"
        With the defaults (P = 10, p = 1, 35 deg, tf = 7) SLSQP reaches tf = 6.99345
        (0.004 % above the unrestricted optimum) in 150 iterations but never reports
        convergence: it collapses some segments to the minimum duration 1e-6, whose
        coefficients then no longer matter (a singular, degenerate optimum), and it runs to
        its iteration limit. P = 8 from 35 deg stalls at 7.1225 (+1.8 %); P = 6 ends
        0.04-0.5 % above. Check results with `diagnose`.
    """
    prob = problem("mars", KELLEY_A0, r_f=KELLEY_RF)
    ctrl = spline_control(segments, degree)
    alpha = math.radians(pitch_deg)
    return prob, ctrl, jnp.asarray(ctrl.validate(ctrl.initial_guess(tf, alpha, alpha)))


#: `jt.KalmanSearch` tuning for these transfers (see `kalman_search_solver`).
KALMAN_SEARCH_TUNING = {"rho": 0.1, "gtol": 1e-4}


def kalman_search_solver(**overrides):
    """`jt.KalmanSearch` tuned for the sail transfers with `SaturatedSpline(10, 1)`:
    `rho = 0.1` and `gtol = 1e-4` (`KALMAN_SEARCH_TUNING`), the other fields at the
    thesis's published defaults; keyword arguments override any field.

    Why these values (measured, RK4(100), starts of `test_kalman_search_reaches_each_target`):

    - `rho = 0.1` (published: 1). The prior mean -rho G_a shortens every one of the P free
      durations by rho (G_a = 1 on each duration, 0 on the pitch coefficients), and the prior
      variance of a pitch coefficient is beta_p0 rho^2 |G_a|^2 = 2 P rho^2 (std 4.5 rad at
      rho = 1). The published rho = 1 fits the Earth-Mars cases (one time parameter,
      |G_a| = 1); here it proposes tf - 10 on tf ~ 7. The first capture steps then throw
      the last Mars coefficient beyond -90 deg: that segment is edge-on, it shrinks towards
      zero length (a degenerate optimum: projected gradient ~1.4, never SUCCESS), and the
      search crawls along the first tolerance band (tf 403.0 d at |E| = 1e-3 after 3000
      steps). rho = 0.1 (a first step of about one time unit in tf, pitch std 0.45 rad)
      keeps every segment; 0.05 and 0.2 work as well but need more steps on some starts.
    - `gtol = 1e-4` (published: 1e-5). The method is first order, and the reduced Hessian
      of the Lagrangian at the optimum has a condition number of 1e5 (Venus) to 3e6
      (Mercury): along its flattest directions (redistributions of the durations) the
      projected gradient falls slowly while tf no longer moves. With gtol = 1e-5 Mars and
      Mercury end at the 3000-step limit with a projected gradient of ~1e-4, their tf
      only 0.0004 % / 0.0008 % below where gtol = 1e-4 stops (364 / 134 steps).

    Result: SUCCESS with max |E| <= 1e-9 and tf within 0.004 % above the indirect optimum
    (Mars from 20 deg, Venus and Mercury from -50 deg, tf = TF_BOX / 2, 134-402 steps).
    Of the example's nine starts per target (pitch 20/35/50 deg x tf factor 0.8/1/1.3) all
    nine reach Mars, seven Venus and five Mercury (the search stalls from the shallow
    -20 deg starts, and ends short of 1e-8 from two of the -35 deg Mercury starts); start
    inward transfers at -50 deg, or prefer `jt.KalmanSQP`, faster and tighter (|E| ~ 1e-13).
    """
    from .._kalman_search import KalmanSearch

    return KalmanSearch(**{**KALMAN_SEARCH_TUNING, **overrides})


# ---------------------------------------------------------------------- penalty functional


def penalty_objective(
    problem: Problem,
    control: AbstractControl,
    *,
    simulator: AbstractSimulator = RK4(),
    weights=DEFAULT_WEIGHTS,
    time_scale: float = DAYS_PER_UNIT,
):
    """The seed's penalty functional (eq. 5) as a pure function of the parameters:

        J(a) = lambda_1 time_scale tf(a) + lambda_2 (r(tf) - r_f)^2 + lambda_3 u(tf)^2
               + lambda_4 (v(tf) - v_f)^2,

    the squared terms being the problem's terminal constraints M(tf, x(tf)). With the
    default `time_scale = DAYS_PER_UNIT` the first term counts days, as the seed's tf / 86400
    (tf in seconds) does. A failed or non-finite simulation gives J = +inf.

    **Arguments:**

    - `problem`, `control`: as for `jt.solve` (any problem with 3 terminal constraints).
    - `simulator`: keyword-only, default `jt.RK4()` (100 steps per segment).
    - `weights`: keyword-only, `(lambda_1, lambda_2, lambda_3, lambda_4)`, default
      `DEFAULT_WEIGHTS`; a jnp array may be passed to trace or vmap over them.
    - `time_scale`: keyword-only, multiplies tf in the first term (1.0: normalized units).

    **Returns:** `J(a) -> scalar`, a pure, `jax.jit`-wrapped function: vmap- and grad-able;
    for the metaheuristics, `jax.vmap(J)` evaluates a population.
    """
    if not isinstance(problem, Problem):
        raise ValueError(f"`problem` must be a jaxtraj.Problem; got {type(problem).__name__}.")
    if not isinstance(control, AbstractControl):
        raise ValueError(f"`control` must be a jaxtraj control; got {type(control).__name__}.")
    check_simulator(simulator)
    l = problem.num_constraints
    w_shape = np.shape(weights)
    if w_shape != (l + 1,):
        raise ValueError(
            f"`weights` must have {l + 1} entries (time, then one per terminal constraint); got shape {w_shape}."
        )
    if not isinstance(weights, jax.Array | jax.core.Tracer):
        w = np.asarray(weights, dtype=np.float64)
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError(f"`weights` must be finite and >= 0; got {w}.")
    weights = jnp.asarray(weights, dtype=jnp.float64)

    def J(a):
        a = jnp.asarray(a, dtype=jnp.float64)
        xf, status = final_state(problem, control, a, simulator)
        tf = control.tf(a)
        E = problem.terminal(tf, xf, problem.args)
        value = weights[0] * time_scale * tf + jnp.sum(weights[1:] * E**2)
        ok = (status == Status.SUCCESS) & jnp.isfinite(value)
        return jnp.where(ok, value, jnp.inf)

    return jax.jit(J)


def box(control: AbstractControl, target: str = "mars", *, h_max=None, tf_max=None, c_lower=None, c_upper=None):
    """Lower/upper parameter bounds for the metaheuristics, from the family's declared layout
    (`time_layout`, `value_indices`, `limits`); the seed's control is a `SaturatedSpline`.

    Durations h_k in [0, h_max], by default h_max = 2 tf_max / P with tf_max = `TF_BOX[target]`
    (about 2x the unrestricted minimum time tf*): a segment may last up to 4x its share
    tf* / P of the optimal transfer (the optimal durations are unequal: the optimal Mars pitch
    rises steeply early on, then varies slowly). A lone final time (equally spaced knots) is
    in [0, tf_max]. Control values (spline coefficients, node values) in the family's limits,
    else the sail's pitch bounds [-pi/2, pi/2]: spline coefficients beyond the limits are
    saturated anyway, so for degree 0/1 the box loses no control; for degree 2/3 it excludes
    only curves that come back from beyond the bounds.

    **Returns:** `(lower, upper)`, float64 arrays of shape `(control.num_params,)`.

    **Raises:** `ValueError` for a family with free knot times (a box cannot keep them
    ordered) or with parameters that are neither times nor control values.
    """
    if not isinstance(control, AbstractControl):
        raise ValueError(f"`control` must be a jaxtraj control; got {type(control).__name__}.")
    times = np.asarray(control.time_indices, int)
    values, channels = (np.asarray(x, int) for x in control.value_indices)
    other = np.setdiff1d(np.arange(control.num_params), np.concatenate([times, values]))
    if control.time_layout == "knots" or other.size:
        raise ValueError(
            f"`control`: a box needs durations or one final time, and control values for every other "
            f"parameter (as the seed's SaturatedSpline); {control!r} has "
            + ("free knot times." if control.time_layout == "knots" else f"other parameters at {other.tolist()}.")
        )
    if tf_max is None:
        if not isinstance(target, str) or target.lower() not in TF_BOX:
            raise ValueError(f"`target` must be one of {sorted(TF_BOX)}; got {target!r}.")
        tf_max = TF_BOX[target.lower()]
    tf_max = float(tf_max)
    P = control.num_segments
    if h_max is None:
        h_max = 2.0 * tf_max / P
    h_max = float(h_max)
    if not (math.isfinite(tf_max) and tf_max > 0 and math.isfinite(h_max) and h_max > 0):
        raise ValueError(f"`tf_max` and `h_max` must be finite and > 0; got tf_max={tf_max!r}, h_max={h_max!r}.")
    q = control.num_controls
    limits = control.limits or (CONTROL_LOWER, CONTROL_UPPER)
    lo_c = np.broadcast_to(np.asarray(limits[0] if c_lower is None else c_lower, dtype=np.float64), (q,))
    hi_c = np.broadcast_to(np.asarray(limits[1] if c_upper is None else c_upper, dtype=np.float64), (q,))
    if np.any(~(lo_c < hi_c)):
        raise ValueError(f"`c_lower` must be < `c_upper`; got {lo_c}, {hi_c}.")
    lower, upper = np.zeros(control.num_params), np.zeros(control.num_params)
    upper[times] = h_max if control.time_layout == "durations" else tf_max
    lower[values], upper[values] = lo_c[channels], hi_c[channels]
    return jnp.asarray(lower), jnp.asarray(upper)


# ---------------------------------------------------------------------- diagnostics


@eqx.filter_jit
def _terminal_errors(problem, control, a, simulator):
    xf, status = final_state(problem, control, a, simulator)
    return problem.terminal(control.tf(a), xf, problem.args), status


def _check_params(problem, control, a):
    """Like the library's input checks, but a point a search may return (tf = 0, zero-length
    segments) is accepted: shape, finiteness and non-decreasing knots only."""
    check_problem_and_control(problem, control)
    if isinstance(a, jax.core.Tracer):
        if a.shape != (control.num_params,):
            raise ValueError(f"`a` must have shape ({control.num_params},) for {control!r}; got {a.shape}.")
        return a.astype(jnp.float64)
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape != (control.num_params,):
        raise ValueError(f"`a` must have shape ({control.num_params},) for {control!r}; got shape {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`a` must be finite; got non-finite entries at {np.flatnonzero(~np.isfinite(arr)).tolist()}.")
    knots = np.asarray(control.knots(jnp.asarray(arr)))
    if np.any(np.diff(knots) < 0) or knots[0] < 0:
        raise ValueError(f"`a`: the knots (segment boundaries) must be >= 0 and non-decreasing; got {knots}.")
    return jnp.asarray(arr)


def terminal_miss(problem: Problem, control: AbstractControl, a, *, simulator: AbstractSimulator = RK4()):
    """The seed's residual (|r(tf) - r_f|, |u(tf) - u_f|, |v(tf) - v_f|), shape `(3,)`
    (NaN where the simulation failed). Accepts any point of a search box, tf = 0 included."""
    a = _check_params(problem, control, a)
    check_simulator(simulator)
    E, status = _terminal_errors(problem, control, a, simulator)
    return jnp.where(status == Status.SUCCESS, jnp.abs(E), jnp.nan)


def feathered_fraction(control: AbstractControl, a, *, tol_deg: float = 5.0, samples: int = 4000):
    """Fraction of the transfer time [0, tf] with |alpha| >= 90 deg - `tol_deg`: the sail
    nearly edge-on, its thrust a0 cos^2(alpha) / r^2 below a0 sin^2(tol) / r^2 (0.8 % of
    a0 for 5 deg). Angles outside
    [-90, 90] deg are first reduced modulo 180 deg (the same flat sail, see `dynamics`).

    Measured on `samples` midpoints of equal time intervals (resolution 1 / samples); 0 when
    tf = 0. Pure (jit/vmap-able over `a`).
    """
    if not (isinstance(samples, int) and samples >= 1):
        raise ValueError(f"`samples` must be an int >= 1; got {samples!r}.")
    return _feathered_fraction(
        control, jnp.asarray(a, dtype=jnp.float64), jnp.asarray(tol_deg, dtype=jnp.float64), samples
    )


@eqx.filter_jit
def _feathered_fraction(control, a, tol_deg, samples):
    tf = control.tf(a)
    t = tf * (jnp.arange(samples, dtype=jnp.float64) + 0.5) / samples
    alpha = control(a, t)[..., 0]
    folded = jnp.abs(jnp.remainder(alpha + 0.5 * jnp.pi, jnp.pi) - 0.5 * jnp.pi)  # in [0, pi/2]
    # +-90 deg fold to 90 deg up to round-off; the 1e-9 keeps them on the edge-on side.
    frac = jnp.mean(folded >= 0.5 * jnp.pi - jnp.deg2rad(tol_deg) - 1e-9)
    return jnp.where(tf > 0, frac, 0.0)  # no transfer time, nothing feathered


def diagnose(
    problem: Problem,
    control: AbstractControl,
    a,
    *,
    simulator: AbstractSimulator = RK4(),
    miss_tol: float = 1e-6,
    tol_deg: float = 5.0,
    feathered_max: float = 0.02,
    tf_floor: float | None = None,
) -> dict:
    """Flags for a claimed optimum: a dict with `tf`, `tf_days`, `miss` (per constraint),
    `max_miss`, `feathered_fraction` and `flags`, a list of strings, empty when nothing is
    suspicious:

    - `"misses target"`: max miss > `miss_tol` (not a transfer; e.g. weak penalty weights);
    - `"feathered arcs"`: more than `feathered_max` of the time edge-on (a spurious
      stationary point of the pitch-angle formulation);
    - `"below unrestricted optimum"`: tf < `tf_floor` (if given), which no restricted
      control can achieve.
    """
    a = _check_params(problem, control, a)
    miss = np.asarray(terminal_miss(problem, control, a, simulator=simulator))
    tf = float(control.tf(a))
    frac = float(feathered_fraction(control, a, tol_deg=tol_deg))
    flags = []
    if not np.all(np.isfinite(miss)) or float(np.max(miss)) > miss_tol:
        flags.append("misses target")
    if frac > feathered_max:
        flags.append("feathered arcs")
    if tf_floor is not None and tf < tf_floor:
        flags.append("below unrestricted optimum")
    return {
        "tf": tf,
        "tf_days": tf * DAYS_PER_UNIT,
        "miss": miss,
        "max_miss": float(np.max(miss)),
        "feathered_fraction": frac,
        "flags": flags,
    }


# ---------------------------------------------------------------------- indirect method


def solve_indirect(
    target: str = "mars",
    a0: float = KELLEY_A0,
    *,
    r_f: float | None = None,
    mu: float = 1.0,
    tf_guess: float | None = None,
    pitch_guesses_deg=None,
    rtol: float = 1e-12,
    dense_points: int = 401,
) -> IndirectResult:
    """The unrestricted minimum-time transfer by Pontryagin's principle and single shooting,
    independent of jaxtraj's simulation and derivatives (NumPy, `scipy.integrate.solve_ivp`
    DOP853 and `scipy.optimize.root`).

    H = 1 + lambda . f, lambda_theta = 0, alpha = `optimal_pitch(lambda_u, lambda_v)`.
    Unknowns (lambda_r(0), lambda_u(0), lambda_v(0), tf); equations r(tf) = r_f, u(tf) = 0,
    v(tf) = v_f and H(0) = 0 (free tf; H is constant along the extremal). Starting costates
    come from a guessed initial pitch (the costate direction that makes it optimal, scaled so
    that H(0) = 0) and lambda_r(0) = 0; the starts are tried in turn until one converges.

    **Arguments:** `target`, `a0`, `r_f`, `mu` as in `problem`; `tf_guess` (default
    `TF_BOX[target] / 2`; 7 or 4 with `r_f` given, for outward/inward transfers);
    `pitch_guesses_deg` (default +-35, +-20, +-50 degrees, sign by outward/inward transfer);
    `rtol` of the integration (atol = rtol); `dense_points`, the number of equally spaced
    times of the returned `t`, `x`, `alpha`.

    **Returns:** an `IndirectResult`; check `success` (the best start is returned either way).
    """
    radius = _target_radius(target, r_f)
    a0, mu = float(a0), float(mu)
    if not a0 > 0:
        raise ValueError(f"`a0` must be > 0 for a transfer; got {a0!r}.")
    if tf_guess is None:
        tf_guess = TF_BOX[target.lower()] / 2.0 if r_f is None else (7.0 if radius > 1.0 else 4.0)
    sign = 1.0 if radius > 1.0 else -1.0
    if pitch_guesses_deg is None:
        pitch_guesses_deg = [sign * d for d in (35.0, 20.0, 50.0)]
    pitch_guesses_deg = [float(d) for d in pitch_guesses_deg]
    if not pitch_guesses_deg or not all(0.0 < abs(d) < 90.0 for d in pitch_guesses_deg):
        raise ValueError(
            f"`pitch_guesses_deg` must be non-empty, each in (-90, 0) or (0, 90); got {pitch_guesses_deg}."
        )
    if not (isinstance(dense_points, int) and dense_points >= 2):
        raise ValueError(f"`dense_points` must be an int >= 2; got {dense_points!r}.")
    return shoot(radius, a0, mu, tf_guess, pitch_guesses_deg, rtol, dense_points)


#: Upper ends of the transfer-time boxes [normalized units] (`box`, `solve_indirect`'s
#: default tf guess = half of it): about 2x the unrestricted minimum times for a0 = 0.17.
TF_BOX = {"mars": 14.0, "venus": 7.0, "mercury": 9.0}


__all__ = [
    "CONSTRAINT_NAMES",
    "DAYS_PER_UNIT",
    "DEFAULT_WEIGHTS",
    "KALMAN_SEARCH_TUNING",
    "KELLEY_A0",
    "KELLEY_RF",
    "STATE_NAMES",
    "TARGET_RADII",
    "TF_BOX",
    "TF_KELLEY",
    "TF_KELLEY_INDIRECT",
    "IndirectResult",
    "box",
    "diagnose",
    "dynamics",
    "feathered_fraction",
    "kalman_search_solver",
    "kelley_case",
    "optimal_pitch",
    "penalty_objective",
    "problem",
    "solve_indirect",
    "spline_control",
    "terminal",
    "terminal_miss",
]
