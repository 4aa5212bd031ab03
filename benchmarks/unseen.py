"""Problems the solvers were not tuned on (issue 20): fourteen textbook problems written as a new
user would write them, each from a zero or constant start, with the default solver, IPOPT and
SLSQP on the same evaluation (RK4(40) per segment).

Unlike the gallery (`gallery.py`) these carry no continuous reference: the table compares the
solvers with each other (the same optimum, iterations). With `--random N` the default solver
also runs N random starts per problem (`jt.random_starts`, spread 0.5, key 0, `jt.solve_batch`)
and a second table counts them: SUCCESS at the naive start's optimum, SUCCESS at another point
(better or worse; each passes `jt.kkt_report` or is counted false), the other statuses.

Problems: Van der Pol to the origin in 5 s (min int x1^2 + x2^2 + u^2) and with a free end;
Rayleigh's problem with |u| <= 1; the minimum-time double integrator with the velocity capped
at 0.5 on the grid (tf* = 2.5); a cart-pole swing-up from rest to the upright rest in 2 s
(cart 1 kg, pole 0.3 kg / 0.5 m, |F| <= 20, min 1/2 int F^2); a unicycle's minimum time to
(1, 1, pi/2) with 0 <= v <= 1, |omega| <= 1 (pi/2); the double integrator to x(1) >= 1 at rest
(a terminal inequality, J* = 6); minimum tf + 1/2 int u^2 to rest at 1 (J* = 18^(1/4) + 6 /
18^(3/4)); the unicycle into a circle of radius 0.5 in least time (a terminal inequality).
Added in session 29: the moon lander's least fuel with a saturated spline (0 <= u <= 3)
instead of free switch times (J* = sqrt(68)); Bryson-Denham's x <= 1/9 with a free tf and
min tf + 1/2 int u^2; linear tangent steering (thrust angle, unit acceleration) to y = 5,
vx = 45, vy = 0 in least time; a pendulum swing-up with |u| <= 1 in 5 s (min 1/2 int u^2), and
with |u| <= 0.5 in least time with six constant pieces and free switch times (more pieces than switches: the
optimum collapses a segment).

Run: `python benchmarks/unseen.py [--problems cart-pole] [--random 32]`.
"""

import argparse
import collections
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxtraj as jt
from jaxtraj.baselines import solve_ipopt, solve_slsqp
from jaxtraj.controls import PiecewiseConstant, PiecewiseLinear, SaturatedSpline

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

SIM = jt.RK4(40)


def _van_der_pol(t, x, u, args):
    return jnp.stack([x[1], -x[0] + (1 - x[0] ** 2) * x[1] + u[0]])


def _rayleigh(t, x, u, args):
    return jnp.stack([x[1], -x[0] + x[1] * (1.4 - 0.14 * x[1] ** 2) + 4 * u[0]])


def _double_integrator(t, x, u, args):
    return jnp.stack([x[1], u[0]])


def _cart_pole(t, x, u, args):
    # (position, angle from hanging, velocity, angular rate)
    mc, mp, length, g = 1.0, 0.3, 0.5, 9.81
    s, c = jnp.sin(x[1]), jnp.cos(x[1])
    den = mc + mp * s**2
    xdd = (u[0] + mp * s * (length * x[3] ** 2 + g * c)) / den
    thdd = -(u[0] * c + mp * length * x[3] ** 2 * c * s + (mc + mp) * g * s) / (length * den)
    return jnp.stack([x[2], x[3], xdd, thdd])


def _unicycle(t, x, u, args):
    return jnp.stack([u[0] * jnp.cos(x[2]), u[0] * jnp.sin(x[2]), u[1]])


def _pendulum(t, x, u, args):
    return jnp.array([x[1], -jnp.sin(x[0]) + u[0]])


def _steering(t, x, u, args):  # (x, y, vx, vy), unit acceleration along the angle u
    return jnp.array([x[2], x[3], jnp.cos(u[0]), jnp.sin(u[0])])


def _at(target):
    return lambda tf, xf, args: xf - jnp.asarray(target)


def _none(tf, xf, args):
    return jnp.zeros(0)


def problems():
    """(name, problem, control family, tf of the start, constant control of the start)."""
    P = jt.Problem
    quadratic = lambda t, x, u, args: x[0] ** 2 + x[1] ** 2 + u[0] ** 2
    half_u2 = lambda t, x, u, args: 0.5 * u[0] ** 2
    box2 = dict(num_controls=2, control_lower=[0.0, -1.0], control_upper=[1.0, 1.0])
    return [
        ("van-der-pol", P(_van_der_pol, [1.0, 0.0], _at([0.0, 0.0]), ("x1", "x2"), running_cost=quadratic,
                          final_time=5.0), PiecewiseLinear(10), 5.0, 0.0),
        ("van-der-pol-free", P(_van_der_pol, [1.0, 0.0], _none, (), running_cost=quadratic, final_time=5.0),
         PiecewiseLinear(10), 5.0, 0.0),
        ("rayleigh-bounded", P(_rayleigh, [-5.0, -5.0], _none, (), running_cost=lambda t, x, u, args: u[0] ** 2 + x[0] ** 2,
                               final_time=4.5, control_lower=-1.0, control_upper=1.0), PiecewiseLinear(15), 4.5, 0.0),
        ("velocity-cap", P(_double_integrator, [0.0, 0.0], _at([1.0, 0.0]), ("x", "v"), control_lower=-1.0,
                           control_upper=1.0, path=lambda t, x, u, args: x[1:2] - 0.5, path_names=("v max",)),
         PiecewiseConstant(3, free_times=True), 1.0, 0.0),
        ("cart-pole", P(_cart_pole, np.zeros(4), _at([0.0, np.pi, 0.0, 0.0]), ("x", "theta", "v", "omega"),
                        running_cost=half_u2, final_time=2.0, control_lower=-20.0, control_upper=20.0),
         PiecewiseLinear(20), 2.0, 0.0),
        ("unicycle-min-time", P(_unicycle, [0.0, 0.0, 0.0], _at([1.0, 1.0, np.pi / 2]), ("x", "y", "heading"), **box2),
         PiecewiseLinear(10, channels=2), 3.0, 0.5),
        ("terminal-inequality", P(_double_integrator, [0.0, 0.0], lambda tf, xf, args: xf[1:2], ("v",),
                                  running_cost=half_u2, final_time=1.0,
                                  terminal_inequality=lambda tf, xf, args: 1.0 - xf[:1], terminal_inequality_names=("x >= 1",)),
         PiecewiseLinear(10), 1.0, 0.0),
        ("time-plus-energy", P(_double_integrator, [0.0, 0.0], _at([1.0, 0.0]), ("x", "v"),
                               objective=lambda tf, xf, args: tf, running_cost=half_u2), PiecewiseLinear(10), 1.0, 0.0),
        ("unicycle-circle", P(_unicycle, [0.0, 0.0, 0.0], _none, (), **box2,
                              terminal_inequality=lambda tf, xf, args: jnp.sum((xf[:2] - jnp.array([2.0, 1.0])) ** 2)[None] - 0.25,
                              terminal_inequality_names=("in circle",)), PiecewiseLinear(6, channels=2), 3.0, 0.5),
        ("lander-spline", P(lambda t, x, u, args: jnp.array([x[1], u[0] - 1.5]), [10.0, -2.0], _at([0.0, 0.0]), ("h", "v"),
                            running_cost=lambda t, x, u, args: u[0]), SaturatedSpline(8, 2, 0.0, 3.0), 4.0, 1.5),
        ("bryson-denham-free-tf", P(_double_integrator, [0.0, 1.0], _at([0.0, -1.0]), ("x", "v"),
                                    objective=lambda tf, xf, args: tf, running_cost=half_u2, state_upper=[1 / 9, np.inf]),
         PiecewiseLinear(10), 1.0, 0.0),
        ("linear-tangent", P(_steering, [0.0, 0.0, 0.0, 0.0], lambda tf, xf, args: jnp.array([xf[1] - 5.0, xf[2] - 45.0, xf[3]]),
                             ("y", "vx", "vy")), PiecewiseLinear(8), 10.0, 0.5),
        ("pendulum-swing-up", P(_pendulum, [0.0, 0.0], _at([np.pi, 0.0]), ("theta", "omega"), running_cost=half_u2,
                                final_time=5.0, control_lower=-1.0, control_upper=1.0), PiecewiseLinear(20), 5.0, 0.0),
        ("pendulum-min-time", P(_pendulum, [0.0, 0.0], _at([np.pi, 0.0]), ("theta", "omega"), control_lower=-0.5,
                                control_upper=0.5), PiecewiseConstant(6, free_times=True), 10.0, 0.0),
    ]  # fmt: skip


def _baseline(fn, prob, ctrl, a0):
    try:
        r = fn(prob, ctrl, a0, simulator=SIM)
        return f"{r.objective:.8f}" if r.success else "FAILED", r.iterations
    except ImportError:  # IPOPT without the bench extra
        return "n/a", ""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", nargs="*", default=None)
    parser.add_argument("--random", type=int, default=0, help="random starts per problem (default solver)")
    args = parser.parse_args()
    chosen = [p for p in problems() if args.problems is None or p[0] in args.problems]
    print(f"# unseen problems: {platform.machine()}, jax {jax.__version__}; {time.strftime('%Y-%m-%d')}; RK4(40)\n")
    print("| problem | default | objective | its | first call (s) | IPOPT objective | its | SLSQP objective | its |")
    print("|---|---|---|---:|---:|---|---:|---|---:|")
    optima = {}
    for name, prob, family, tf, u in chosen:
        ctrl = prob.parametrize(family)
        a0 = ctrl.initial_guess(tf, u, u)
        t = time.perf_counter()
        sol = jt.solve(prob, ctrl, a0, simulator=SIM, max_steps=2000, progress=False)
        first = time.perf_counter() - t
        optima[name] = float(sol.objective)
        ip, sl = _baseline(solve_ipopt, prob, ctrl, a0), _baseline(solve_slsqp, prob, ctrl, a0)
        print(
            f"| {name} | {jt.status_name(sol.status)} | {float(sol.objective):.8f} | {int(sol.iterations)} | "
            f"{first:.1f} | {ip[0]} | {ip[1]} | {sl[0]} | {sl[1]} |",
            flush=True,
        )
    if not args.random:
        return
    print(f"\n{args.random} random starts (spread 0.5, key 0), default solver:\n")
    print(
        "| problem | at the naive optimum | SUCCESS elsewhere (better / KKT fails) | other statuses | max its | time (s) |"
    )
    print("|---|---:|---|---|---:|---:|")
    for name, prob, family, tf, u in chosen:
        ctrl = prob.parametrize(family)
        a0 = ctrl.initial_guess(tf, u, u)
        starts = jt.random_starts(prob, ctrl, jax.random.key(0), args.random, around=a0, spread=0.5, simulator=SIM)
        t = time.perf_counter()
        sols = jt.solve_batch(prob, ctrl, starts, simulator=SIM, max_steps=2000, progress=False, history=False)
        names, J = jt.status_name(sols.status), np.asarray(sols.objective)
        ref, tol = optima[name], 1e-6 * (1 + abs(optima[name]))
        ok = names == "SUCCESS"
        elsewhere = np.flatnonzero(ok & (np.abs(J - ref) > tol))
        better = int(np.sum(J[elsewhere] < ref - tol))
        false = sum(
            not jt.kkt_report(prob, ctrl, sols.params[i], simulator=SIM).satisfied(1e-8, 1e-5) for i in elsewhere
        )
        others = dict(collections.Counter(str(n) for n in names if n != "SUCCESS"))
        print(
            f"| {name} | {int(np.sum(ok) - elsewhere.size)}/{args.random} | {elsewhere.size} ({better} / {false}) | "
            f"{', '.join(f'{k} {v}' for k, v in sorted(others.items()))} | {int(np.max(sols.iterations))} | "
            f"{time.perf_counter() - t:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
