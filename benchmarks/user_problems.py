"""Classic problems from other toolkits' suites, restated by hand as a new user would write them
(issue 49): the default solver (`jt.solve`, KalmanSQP), `jt.AugmentedLagrangian()`, IPOPT and SLSQP
(`jaxtraj.baselines`) on the same restricted problem (RK4(20) per segment), from a naive start.

* `robot-arm`: COPS 3.0 problem 8 (Dolan, More & Munson, "Benchmarking optimization software
  with COPS 3.0", Argonne tech. memo ANL/MCS-TM-273, 2004; the data as in MadNLP/COPSBenchmark.jl
  `src/robot.jl`, whose test checks IPOPT against COPS's table). A bar of length L = 5 held at
  rho from its grip: states (rho, theta, phi, rho', theta', phi'), L rho'' = u_rho,
  I_theta theta'' = u_theta, I_phi phi'' = u_phi, I_phi = ((L - rho)^3 + rho^3) / 3,
  I_theta = I_phi sin(phi)^2, |u| <= 1 per channel, 0 <= rho <= L, |theta| <= pi,
  0 <= phi <= pi; from (4.5, 0, pi/4) at rest to (4.5, 2 pi/3, pi/4) at rest in least time.
  Published optimum tf = 9.14138 (COPS 3.0 table, nh = 200; COPSBenchmark.jl's test).
  Start: COPS's tf = 1, zero controls.
* `goddard-user`: COPS 3.0's Goddard rocket written from the paper's data rather than the
  gallery's folded constants: h0 = m0 = g0 = 1, hc = 500, vc = 620, mc = 0.6, Tc = 3.5,
  c = 0.5 sqrt(g0 h0), Dc = 0.5 vc m0 / g0, Tmax = Tc m0 g0, mf = mc m0 (as in
  COPSBenchmark.jl `src/rocket.jl`), D = Dc v^2 exp(-hc (h - h0) / h0), g = g0 (h0 / h)^2,
  h' = v, v' = (T - D) / m - g, m' = -T / c, 0 <= T <= Tmax, the final mass m(tf) = mf as a
  terminal *equality*, COPS's bounds h >= h0, v >= 0, mf <= m <= m0 as state bounds, tf free,
  max h(tf). Published optimum h(tf) = 1.01283 (COPS 3.0 table, nh = 400; COPSBenchmark.jl).
  Start: COPS's T = Tmax / 2, with tf = 0.1 (the lower end of PROPT's 0.1 <= tf <= 1) so
  that the start burns less than the fuel (COPS's own tf = 1 empties the tank 3.5 times over).
* `tumor`: tumor anti-angiogenesis (Ledzewicz & Schaettler, "Analysis of optimal controls for
  a mathematical model of tumour anti-angiogenesis", Optim. Control Appl. Meth. 29, 2008; as
  in Betts (2010) example 6.17, PSOPT/PROPT/GPOPS examples and pycollo's
  `examples/tumour_anti_angiogenesis`): p' = -xi p ln(p / q), q' = q (b - (mu + d p^(2/3) +
  G u)), y' = u, xi = 0.084, b = 5.85, d = 0.00873, G = 0.15, mu = 0.02, 0 <= u <= a = 75,
  p(0) = pbar / 2, q(0) = qbar / 4 with pbar = qbar = ((b - mu) / d)^(3/2), the drug budget
  y(tf) <= A = 15 as a terminal inequality, tf free in [0.1, 5] (pycollo's bounds), min p(tf).
  Published optimum p(tf) = 7571.6712, tf = 1.1961336 (Betts 2010, quoted "as per the book" by
  opty's example of this problem). Start: tf = 1, u = 10 (uses 10 of the 15 units: feasible).
* `obstacle-min-time`: PSOPT's `examples/obstacle` (after PROPT's user guide): x' = V cos
  theta, y' = V sin theta, V = 2.138, from (0, 0) to (1.2, 1.6) outside the two disks
  (x - 0.4)^2 + (y - 0.5)^2 >= 0.1 and (x - 0.8)^2 + (y - 1.5)^2 >= 0.1 (path constraints),
  made a minimum-time problem (PSOPT fixes tf = 1 and minimizes int V^2, a constant). No
  published optimum; the straight line (length 2, time 0.935) crosses both disks. Start:
  PSOPT's guess, tf = 1 and theta = 0.

Variants (a user's other first tries): `robot-arm-pwc` and `goddard-user-pwc` use
`PiecewiseConstant(10)` (free switch times, the family's default) for the bang-bang and
bang-singular-coast optima, the rocket from full thrust for tf = 0.2 (a start that empties the
tank: m(tf) = -0.4); `obstacle-min-time-up` starts heading straight up (theta = pi/2).

Measured 2026-12-06 (x86-64, 2 shared cores): the default solver STALLED on `robot-arm` at the
restricted optimum that IPOPT and SLSQP reach (a degenerate vertex: 30 active control bounds
and 6 terminal equalities for 34 parameters, where the least-squares rounds of the stationarity
test leave 9.2e-2 while exact non-negative least squares gives 7e-16), and on
`goddard-user-pwc` at a non-KKT point (a collapsed segment, m = mf on every coast grid point).

Run: `python benchmarks/user_problems.py [--problems robot-arm tumor] [--kkt] [--progress 1]`.
"""

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxtraj as jt
from jaxtraj.baselines import solve_ipopt, solve_slsqp
from jaxtraj.controls import PiecewiseConstant, PiecewiseLinear

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

SIM = jt.RK4(20)

# ------------------------------------------------------------------------------- robot arm


def _robot(t, x, u, args):
    L = args["L"]
    rho, phi = x[0], x[2]
    i_phi = ((L - rho) ** 3 + rho**3) / 3.0
    i_theta = i_phi * jnp.sin(phi) ** 2
    return jnp.stack([x[3], x[4], x[5], u[0] / L, u[1] / i_theta, u[2] / i_phi])


def _robot_target(tf, xf, args):
    return xf - jnp.array([4.5, 2 * jnp.pi / 3, jnp.pi / 4, 0.0, 0.0, 0.0])


def robot_arm(family=PiecewiseLinear(10, channels=3), name="robot-arm"):
    """COPS 3.0 robot arm (see the module docs); published tf* = 9.14138."""
    names = ("rho", "theta", "phi", "rho'", "theta'", "phi'")
    prob = jt.Problem(
        _robot, [4.5, 0.0, np.pi / 4, 0.0, 0.0, 0.0], _robot_target, names, num_controls=3,
        args={"L": jnp.asarray(5.0)}, state_names=names, control_names=("u_rho", "u_theta", "u_phi"),
        control_lower=[-1.0] * 3, control_upper=[1.0] * 3,
        state_lower=[0.0, -np.pi, 0.0, -np.inf, -np.inf, -np.inf], state_upper=[5.0, np.pi, np.pi, np.inf, np.inf, np.inf],
        name=name,
    )  # fmt: skip
    ctrl = prob.parametrize(family)
    return name, prob, ctrl, ctrl.initial_guess(1.0, 0.0, 0.0), 9.14138


# --------------------------------------------------------------------------------- Goddard


def _rocket(t, x, u, args):
    h, v, m = x[0], x[1], x[2]
    drag = args["Dc"] * v**2 * jnp.exp(-args["hc"] * (h - args["h0"]) / args["h0"])
    gravity = args["g0"] * (args["h0"] / h) ** 2
    return jnp.stack([v, (u[0] - drag) / m - gravity, -u[0] / args["c"]])


def _rocket_mass(tf, xf, args):
    return xf[2:3] - args["mf"]


def goddard_user(family=PiecewiseLinear(10), tf=0.1, thrust=0.5, name="goddard-user"):
    """COPS 3.0 Goddard rocket, the final mass a terminal equality (see the module docs);
    published h(tf)* = 1.01283, i.e. objective -1.01283. The start: `thrust` x Tmax for `tf`."""
    h0, m0, g0, hc, vc, mc, Tc = 1.0, 1.0, 1.0, 500.0, 620.0, 0.6, 3.5
    consts = dict(h0=h0, g0=g0, hc=hc, c=0.5 * np.sqrt(g0 * h0), Dc=0.5 * vc * m0 / g0, mf=mc * m0)
    Tmax = Tc * m0 * g0
    prob = jt.Problem(
        _rocket, [h0, 0.0, m0], _rocket_mass, ("m(tf) = mf",), objective=lambda tf, xf, args: -xf[0],
        args={k: jnp.asarray(v) for k, v in consts.items()}, state_names=("h", "v", "m"), control_names=("T",),
        control_lower=0.0, control_upper=Tmax, state_lower=[h0, 0.0, mc * m0], state_upper=[np.inf, np.inf, m0],
        name=name,
    )  # fmt: skip
    ctrl = prob.parametrize(family)
    return name, prob, ctrl, ctrl.initial_guess(tf, thrust * Tmax, thrust * Tmax), -1.01283


# ----------------------------------------------------------------------------------- tumor


def _tumor(t, x, u, args):
    p, q = x[0], x[1]
    dp = -args["xi"] * p * jnp.log(p / q)
    dq = q * (args["b"] - (args["mu"] + args["d"] * p ** (2.0 / 3.0) + args["G"] * u[0]))
    return jnp.stack([dp, dq, u[0]])


def tumor():
    """Tumor anti-angiogenesis (see the module docs); published p(tf)* = 7571.6712."""
    xi, b, d, G, mu, a, A = 0.084, 5.85, 0.00873, 0.15, 0.02, 75.0, 15.0
    pbar = ((b - mu) / d) ** 1.5
    prob = jt.Problem(
        _tumor, [pbar / 2, pbar / 4, 0.0], lambda tf, xf, args: jnp.zeros(0), (),
        objective=lambda tf, xf, args: xf[0],
        args={k: jnp.asarray(v) for k, v in dict(xi=xi, b=b, d=d, G=G, mu=mu, A=A).items()},
        state_names=("p", "q", "y"), control_names=("u",), control_lower=0.0, control_upper=a,
        terminal_inequality=lambda tf, xf, args: xf[2:3] - args["A"], terminal_inequality_names=("y(tf) <= A",),
        tf_bounds=(0.1, 5.0), name="tumor",
    )  # fmt: skip
    ctrl = prob.parametrize(PiecewiseLinear(10))
    return "tumor", prob, ctrl, ctrl.initial_guess(1.0, 10.0, 10.0), 7571.6712


# -------------------------------------------------------------------------------- obstacle


def _planar(t, x, u, args):
    return args["V"] * jnp.stack([jnp.cos(u[0]), jnp.sin(u[0])])


def _outside_disks(t, x, u, args):
    return args["r2"] - jnp.stack([(x[0] - 0.4) ** 2 + (x[1] - 0.5) ** 2, (x[0] - 0.8) ** 2 + (x[1] - 1.5) ** 2])


def obstacle_min_time(heading=0.0, name="obstacle-min-time"):
    """PSOPT's obstacle avoidance in least time (see the module docs); no published optimum.
    The start: tf = 1 and the constant heading `heading`."""
    prob = jt.Problem(
        _planar, [0.0, 0.0], lambda tf, xf, args: xf - jnp.array([1.2, 1.6]), ("x", "y"),
        args={"V": jnp.asarray(2.138), "r2": jnp.asarray(0.1)}, state_names=("x", "y"), control_names=("theta",),
        path=_outside_disks, path_names=("obstacle 1", "obstacle 2"), name=name,
    )  # fmt: skip
    ctrl = prob.parametrize(PiecewiseLinear(10))
    return name, prob, ctrl, ctrl.initial_guess(1.0, heading, heading), None


def problems():
    """(name, problem, control, naive start, published optimum of the continuous problem or None)."""
    return [
        robot_arm(),
        robot_arm(PiecewiseConstant(10, channels=3), "robot-arm-pwc"),
        goddard_user(),
        goddard_user(PiecewiseConstant(10), 0.2, 1.0, "goddard-user-pwc"),
        tumor(),
        obstacle_min_time(),
        obstacle_min_time(np.pi / 2, "obstacle-min-time-up"),
    ]


# ------------------------------------------------------------------------------------ table


def _baseline(fn, prob, ctrl, a0):
    try:
        r = fn(prob, ctrl, a0, simulator=SIM)
        return (f"{r.objective:.8g}" if r.success else f"FAILED ({r.objective:.6g})"), r.iterations
    except ImportError:  # IPOPT without the bench extra
        return "n/a", ""


def _jaxtraj(prob, ctrl, a0, solver, max_steps, progress):
    t = time.perf_counter()
    sol = jt.solve(prob, ctrl, a0, solver, simulator=SIM, max_steps=max_steps, progress=progress)
    jax.block_until_ready(sol.params)
    return sol, time.perf_counter() - t


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", nargs="*", default=None)
    parser.add_argument("--max-steps", type=int, default=2000)
    parser.add_argument("--progress", type=int, default=0, help="default solver's progress line every N steps")
    parser.add_argument("--kkt", action="store_true", help="print jt.kkt_report at the default solver's end point")
    parser.add_argument("--no-baselines", action="store_true", help="skip AugmentedLagrangian, IPOPT and SLSQP")
    args = parser.parse_args()
    chosen = [p for p in problems() if args.problems is None or p[0] in args.problems]
    print(
        f"# user problems: {platform.machine()}, jax {jax.__version__}; {time.strftime('%Y-%m-%d')}; RK4(20); "
        f"jaxtraj from {jt.__file__}\n"
    )
    print(
        "| problem | default | objective | its | first call (s) | AugLag | objective | its | s | "
        "IPOPT objective | its | SLSQP objective | its | published |"
    )
    print("|---|---|---|---:|---:|---|---|---:|---:|---|---:|---|---:|---|")
    for name, prob, ctrl, a0, published in chosen:
        sol, secs = _jaxtraj(prob, ctrl, a0, None, args.max_steps, args.progress)
        if args.kkt:
            print(jt.kkt_report(prob, ctrl, sol.params, simulator=SIM), flush=True)
        if args.no_baselines:
            al_cells, ip, sl = "| | | |", ("", ""), ("", "")
        else:
            al, al_secs = _jaxtraj(prob, ctrl, a0, jt.AugmentedLagrangian(), args.max_steps, 0)
            al_cells = (
                f"{jt.status_name(al.status)} | {float(al.objective):.8g} | {int(al.iterations)} | {al_secs:.1f} |"
            )
            ip, sl = _baseline(solve_ipopt, prob, ctrl, a0), _baseline(solve_slsqp, prob, ctrl, a0)
        print(
            f"| {name} | {jt.status_name(sol.status)} | {float(sol.objective):.8g} | {int(sol.iterations)} | "
            f"{secs:.1f} | {al_cells} {ip[0]} | {ip[1]} | {sl[0]} | {sl[1]} | "
            f"{'—' if published is None else f'{published:g}'} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
