"""Independent reference optima of the classic gallery by direct collocation in CasADi.

Every continuous optimal-control problem of the classic gallery (`jt.problems.classic`) is
restated here in CasADi symbols and transcribed by separated Hermite-Simpson collocation:
node and midpoint states and controls are decision variables (the control is quadratic on each
interval through its node and midpoint values), Simpson's rule integrates the running cost,
a free final time enters as t = tf * tau on a uniform mesh in tau in [0, 1], control bounds
and state path constraints are bounds on the node and midpoint variables (passed to IPOPT as
variable bounds through `detect_simple_bounds`). Each problem is solved with IPOPT on two
meshes, and the table compares the optimum with the reference value the gallery states.

This script does not import jaxtraj: the dynamics, costs and constraints are written out
again from the problem statements, so the optima are independent of the library's code.

Run (about 12 s on one core):

    python benchmarks/collocation.py [--problems lq goddard] [--nodes 100 400]
"""

import argparse
import math
import platform
import sys
import time

import casadi as ca
import numpy as np

# bound_relax_factor 0: IPOPT would otherwise relax every bound by 1e-8 (x <= 1/9 moves Bryson-Denham by 4e-7);
# acceptable_iter 0: no early "acceptable" stop (Goddard's singular arc makes the last iterations slow)
IPOPT = {"print_level": 0, "sb": "yes", "tol": 1e-10, "max_iter": 3000, "bound_relax_factor": 0.0, "acceptable_iter": 0}
G0 = 9.80665  # brachistochrone gravity


class HermiteSimpson:
    """Separated Hermite-Simpson transcription of x' = f(x, u, t), t = tf * tau, on N uniform intervals."""

    def __init__(self, opti, n, nx, nu, rhs, tf):
        self.opti, self.n, self.nx, self.nu, self.tf = opti, n, nx, nu, tf
        self.tau = np.linspace(0.0, 1.0, n + 1)
        self.taum = 0.5 * (self.tau[:-1] + self.tau[1:])
        self.X, self.Xm = opti.variable(nx, n + 1), opti.variable(nx, n)
        self.U, self.Um = opti.variable(nu, n + 1), opti.variable(nu, n)
        x, u, t = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("t")
        self.f = ca.Function("f", [x, u, t], [ca.vertcat(*rhs(x, u, t))])
        fn = self.f.map(n + 1)(self.X, self.U, tf * ca.DM(self.tau).T)
        fm = self.f.map(n)(self.Xm, self.Um, tf * ca.DM(self.taum).T)
        self.h = tf / n
        X, h = self.X, self.h
        opti.subject_to(self.Xm == 0.5 * (X[:, :-1] + X[:, 1:]) + h / 8 * (fn[:, :-1] - fn[:, 1:]))
        opti.subject_to(X[:, 1:] - X[:, :-1] == h / 6 * (fn[:, :-1] + 4 * fm + fn[:, 1:]))

    def integral(self, running):
        """Simpson quadrature of running(x, u, t) over [0, tf]."""
        x, u, t = ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu), ca.SX.sym("t")
        L = ca.Function("L", [x, u, t], [running(x, u, t)])
        ln = L.map(self.n + 1)(self.X, self.U, self.tf * ca.DM(self.tau).T)
        lm = L.map(self.n)(self.Xm, self.Um, self.tf * ca.DM(self.taum).T)
        return self.h / 6 * (ca.sum2(ln[:, :-1] + ln[:, 1:]) + 4 * ca.sum2(lm))

    def bound_state(self, i, lb, ub):
        """lb <= x_i(t) <= ub at every node and midpoint."""
        self.opti.subject_to(self.opti.bounded(lb, self.X[i, :], ub))
        self.opti.subject_to(self.opti.bounded(lb, self.Xm[i, :], ub))

    def bound_control(self, lb, ub):
        """lb <= u(t) <= ub (scalars or length-nu lists) at every node and midpoint."""
        for j in range(self.nu):
            lo, hi = (b[j] if isinstance(b, list | tuple) else b for b in (lb, ub))
            self.opti.subject_to(self.opti.bounded(lo, self.U[j, :], hi))
            self.opti.subject_to(self.opti.bounded(lo, self.Um[j, :], hi))

    def guess(self, x=None, u=None):
        """Initial guess from callables of tau returning arrays (nx or nu, len(tau))."""
        for fun, nodes, mids in ((x, self.X, self.Xm), (u, self.U, self.Um)):
            if fun is not None:
                self.opti.set_initial(nodes, np.atleast_2d(fun(self.tau)))
                self.opti.set_initial(mids, np.atleast_2d(fun(self.taum)))

    def simulate_guess(self, x0, u, tf, substeps=4):
        """Initial guess: the control u(tau) and the states it produces from x0 (RK4 on a finer mesh)."""
        m = self.n * 2 * substeps
        taus = np.linspace(0.0, 1.0, m + 1)
        xs = np.zeros((self.nx, m + 1))
        xs[:, 0] = x0
        dt = tf / m

        def f(k, x, dtau):
            tau = taus[k] + dtau
            return np.array(self.f(x, np.atleast_1d(u(tau)), tf * tau)).ravel()

        for k in range(m):
            x = xs[:, k]
            k1 = f(k, x, 0.0)
            k2 = f(k, x + dt / 2 * k1, 0.5 / m)
            k3 = f(k, x + dt / 2 * k2, 0.5 / m)
            k4 = f(k, x + dt * k3, 1.0 / m)
            xs[:, k + 1] = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        self.opti.set_initial(self.X, xs[:, :: 2 * substeps])
        self.opti.set_initial(self.Xm, xs[:, substeps :: 2 * substeps])
        self.guess(u=lambda tau: np.atleast_2d(u(tau)))


def free_time(opti, guess, lb, ub):
    """A free final time variable with bounds."""
    tf = opti.variable()
    opti.subject_to(opti.bounded(lb, tf, ub))
    opti.set_initial(tf, guess)
    return tf


def solve(opti, objective):
    """Minimize with IPOPT; (objective value, IPOPT return status)."""
    opti.minimize(objective)
    opti.solver("ipopt", {"print_time": False, "detect_simple_bounds": True}, IPOPT)
    try:
        sol = opti.solve()
        value = float(sol.value(objective))
    except RuntimeError:
        value = float(opti.debug.value(objective))
    return value, opti.stats()["return_status"]


# ----------------------------------------------------------------------------------------------------- problems


def lq(n):
    """x' = u, x(0) = 1, tf = 1, min 1/2 ∫(x² + u²)."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 1, 1, lambda x, u, t: [u[0]], 1.0)
    o.subject_to(hs.X[0, 0] == 1)
    return solve(o, hs.integral(lambda x, u, t: 0.5 * (x[0] ** 2 + u[0] ** 2)))


def bryson_denham(n):
    """Double integrator (0, 1) -> (0, -1) on [0, 1], x <= 1/9, min 1/2 ∫u²."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 2, 1, lambda x, u, t: [x[1], u[0]], 1.0)
    o.subject_to(hs.X[:, 0] == [0, 1])
    o.subject_to(hs.X[:, -1] == [0, -1])
    hs.bound_state(0, -ca.inf, 1 / 9)
    hs.guess(x=lambda tau: np.vstack([0.1 * tau * (1 - tau), 1 - 2 * tau]), u=lambda tau: -2 + 0 * tau)
    return solve(o, hs.integral(lambda x, u, t: 0.5 * u[0] ** 2))


def min_time_double_integrator(n):
    """Double integrator, |u| <= 1, rest at 0 -> rest at 1, min tf."""
    o = ca.Opti()
    tf = free_time(o, 2.5, 0.1, 10)
    hs = HermiteSimpson(o, n, 2, 1, lambda x, u, t: [x[1], u[0]], tf)
    o.subject_to(hs.X[:, 0] == [0, 0])
    o.subject_to(hs.X[:, -1] == [1, 0])
    hs.bound_control(-1, 1)
    hs.guess(x=lambda tau: np.vstack([tau, 0.5 + 0 * tau]), u=lambda tau: 1 - 2 * tau)
    return solve(o, tf)


def brachistochrone(n):
    """x' = v sin θ, y' = -v cos θ, v' = g cos θ, (0, 10, 0) -> (10, 5, free), min tf."""
    o = ca.Opti()
    tf = free_time(o, 2.0, 0.1, 10)
    hs = HermiteSimpson(o, n, 3, 1, lambda x, u, t: [x[2] * ca.sin(u[0]), -x[2] * ca.cos(u[0]), G0 * ca.cos(u[0])], tf)
    o.subject_to(hs.X[:, 0] == [0, 10, 0])
    o.subject_to(hs.X[:2, -1] == [10, 5])
    hs.bound_control(0, math.pi)
    hs.guess(x=lambda tau: np.vstack([10 * tau, 10 - 5 * tau, 10 + 0 * tau]), u=lambda tau: 0.3 + 2 * tau)
    return solve(o, tf)


def moon_lander(n):
    """h' = v, v' = u - 1.5, 0 <= u <= 3, (10, -2) -> (0, 0), tf free, min ∫u."""
    o = ca.Opti()
    tf = free_time(o, 4.0, 0.1, 20)
    hs = HermiteSimpson(o, n, 2, 1, lambda x, u, t: [x[1], u[0] - 1.5], tf)
    o.subject_to(hs.X[:, 0] == [10, -2])
    o.subject_to(hs.X[:, -1] == [0, 0])
    hs.bound_control(0, 3)
    hs.guess(x=lambda tau: np.vstack([10 * (1 - tau), -2 * (1 - tau)]), u=lambda tau: 1.5 + 0 * tau)
    return solve(o, hs.integral(lambda x, u, t: u[0]))


def singular_arc(n):
    """x' = u, |u| <= 1, x(0) = 1, tf = 2, min ∫x²."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 1, 1, lambda x, u, t: [u[0]], 2.0)
    o.subject_to(hs.X[0, 0] == 1)
    hs.bound_control(-1, 1)
    return solve(o, hs.integral(lambda x, u, t: x[0] ** 2))


def max_range(n):
    """Double integrator from rest, |u| <= 1, v(1) = 0, min -x(1)."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 2, 1, lambda x, u, t: [x[1], u[0]], 1.0)
    o.subject_to(hs.X[:, 0] == [0, 0])
    o.subject_to(hs.X[1, -1] == 0)
    hs.bound_control(-1, 1)
    return solve(o, -hs.X[0, -1])


def two_channel(n):
    """Planar double integrator, rest at 0 -> rest at (1, 2), tf = 1, min 1/2 ∫|u|²."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 4, 2, lambda x, u, t: [x[2], x[3], u[0], u[1]], 1.0)
    o.subject_to(hs.X[:, 0] == [0, 0, 0, 0])
    o.subject_to(hs.X[:, -1] == [1, 2, 0, 0])
    return solve(o, hs.integral(lambda x, u, t: 0.5 * ca.sumsqr(u)))


def design_parameter(n):
    """x' = u, x(0) = 0, x(1) = p, p in [0, 5] free, min 1/2 ∫u² + (p - 2)²/2."""
    o = ca.Opti()
    p = o.variable()
    o.subject_to(o.bounded(0, p, 5))
    hs = HermiteSimpson(o, n, 1, 1, lambda x, u, t: [u[0]], 1.0)
    o.subject_to(hs.X[0, 0] == 0)
    o.subject_to(hs.X[0, -1] == p)
    return solve(o, hs.integral(lambda x, u, t: 0.5 * u[0] ** 2) + 0.5 * (p - 2) ** 2)


def free_initial_state(n):
    """x' = u, x(0) free, x(1) = 1, min 1/2 ∫(x² + u²)."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 1, 1, lambda x, u, t: [u[0]], 1.0)
    o.subject_to(hs.X[0, -1] == 1)
    return solve(o, hs.integral(lambda x, u, t: 0.5 * (x[0] ** 2 + u[0] ** 2)))


def capped_terminal(n):
    """x' = u, x(0) = 0, x(1) <= 1, min 1/2 ∫u² - 2 x(1)."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 1, 1, lambda x, u, t: [u[0]], 1.0)
    o.subject_to(hs.X[0, 0] == 0)
    o.subject_to(hs.X[0, -1] <= 1)
    return solve(o, hs.integral(lambda x, u, t: 0.5 * u[0] ** 2) - 2 * hs.X[0, -1])


def hypersensitive(n):
    """x' = -x³ + u, x(0) = 1.5, x(20) = 1, min 1/2 ∫(x² + u²)."""
    o = ca.Opti()
    hs = HermiteSimpson(o, n, 1, 1, lambda x, u, t: [-(x[0] ** 3) + u[0]], 20.0)
    o.subject_to(hs.X[0, 0] == 1.5)
    o.subject_to(hs.X[0, -1] == 1)
    hs.guess(x=lambda tau: 1.5 * np.exp(-20 * tau) + np.exp(-20 * (1 - tau)))
    return solve(o, hs.integral(lambda x, u, t: 0.5 * (x[0] ** 2 + u[0] ** 2)))


def goddard(n):
    """COPS 3.0 rocket: max h(tf) with drag, inverse-square gravity, m(tf) = 0.6, 0 <= T <= 3.5, tf free."""

    def rhs(x, u, t):
        h, v, m = x[0], x[1], x[2]
        drag = 310 * v**2 * ca.exp(-500 * (h - 1))
        return [v, (u[0] - drag) / m - 1 / h**2, -u[0] / 0.5]

    o = ca.Opti()
    tf = free_time(o, 0.2, 0.05, 1.0)
    hs = HermiteSimpson(o, n, 3, 1, rhs, tf)
    o.subject_to(hs.X[:, 0] == [1, 0, 1])
    o.subject_to(hs.X[2, -1] == 0.6)
    hs.bound_control(0, 3.5)
    hs.bound_state(0, 1, ca.inf)
    hs.bound_state(1, 0, ca.inf)
    hs.bound_state(2, 0.6, 1)
    # full thrust until the fuel is gone (t = 0.4 / 7), then coast
    hs.simulate_guess([1, 0, 1], lambda tau: np.where(tau < 0.4 / 7 / 0.2, 3.5, 0.0), 0.2)
    return solve(o, -hs.X[0, -1])


def orbit_raising(n):
    """Bryson & Ho p. 66: max r(3.32) on a circular final orbit, thrust 0.1405, mass 1 - 0.0749 t."""

    def rhs(x, u, t):
        r, vr, vt = x[0], x[1], x[2]
        a = 0.1405 / (1 - 0.0749 * t)
        return [vr, vt**2 / r - 1 / r**2 + a * ca.sin(u[0]), -vr * vt / r + a * ca.cos(u[0])]

    o = ca.Opti()
    hs = HermiteSimpson(o, n, 3, 1, rhs, 3.32)
    o.subject_to(hs.X[:, 0] == [1, 0, 1])
    o.subject_to(hs.X[1, -1] == 0)
    o.subject_to(hs.X[2, -1] ** 2 * hs.X[0, -1] == 1)
    hs.bound_state(0, 0.5, 5)
    # thrust forward-outward in the first half, backward-outward in the second
    hs.simulate_guess([1, 0, 1], lambda tau: 0.5 + 2.5 * tau, 3.32)
    return solve(o, -hs.X[0, -1])


def zermelo(n):
    """x' = cos θ - y, y' = sin θ, (3.66, -1.86) -> (0, 0), min tf."""
    o = ca.Opti()
    tf = free_time(o, 5.5, 1, 20)
    hs = HermiteSimpson(o, n, 2, 1, lambda x, u, t: [ca.cos(u[0]) - x[1], ca.sin(u[0])], tf)
    o.subject_to(hs.X[:, 0] == [3.66, -1.86])
    o.subject_to(hs.X[:, -1] == [0, 0])
    # tan θ linear in time on the branch (π/2, 3π/2): up, then against x, then down
    hs.simulate_guess([3.66, -1.86], lambda tau: math.pi / 2 + 0.3 + (math.pi - 0.6) * tau, 5.5)
    return solve(o, tf)


PROBLEMS = {
    "lq": (lq, math.tanh(1) / 2),
    "bryson-denham": (bryson_denham, 4.0),
    "min-time-double-integrator": (min_time_double_integrator, 2.0),
    "brachistochrone": (brachistochrone, 1.8016031225),
    "moon-lander": (moon_lander, math.sqrt(68)),
    "singular-arc": (singular_arc, 1 / 3),
    "max-range": (max_range, -0.25),
    "two-channel": (two_channel, 30.0),
    "design-parameter": (design_parameter, 1.0),
    "free-initial-state": (free_initial_state, math.tanh(1) / 2),
    "capped-terminal": (capped_terminal, -1.5),
    "hypersensitive": (hypersensitive, 1.3308069),
    "goddard": (goddard, -1.012837),
    "orbit-raising": (orbit_raising, -1.5252777),
    "zermelo": (zermelo, 5.45786526),
}

SHORT_STATUS = {"Solve_Succeeded": "ok", "Solved_To_Acceptable_Level": "acceptable"}


def main():
    """Solve the chosen problems on every mesh and print the Markdown table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", nargs="+", choices=list(PROBLEMS), default=list(PROBLEMS))
    parser.add_argument("--nodes", nargs="+", type=int, default=[100, 400], help="numbers of mesh intervals")
    args = parser.parse_args()

    rows = []
    for name in args.problems:
        fun, ref = PROBLEMS[name]
        cells = [name, f"{ref:.10g}"]
        for n in args.nodes:
            start = time.perf_counter()
            value, status = fun(n)
            seconds = time.perf_counter() - start
            cells += [f"{value:.10g}", f"{value - ref:+.2e}", SHORT_STATUS.get(status, status), f"{seconds:.2f}"]
            print(
                f"{name:28s} N={n:<5d} J={value:.10g}  J-ref={value - ref:+.2e}  {status}  {seconds:.2f}s", flush=True
            )
        rows.append(cells)

    header = ["problem", "stated ref"]
    for n in args.nodes:
        header += [f"J (N={n})", f"J-ref (N={n})", f"IPOPT (N={n})", f"s (N={n})"]
    print()
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for cells in rows:
        print("| " + " | ".join(cells) + " |")
    print()
    print(
        f"machine: {platform.processor() or platform.machine()}, Python {platform.python_version()}, "
        f"casadi {ca.__version__}; command: python {' '.join(sys.argv)}"
    )


if __name__ == "__main__":
    main()
