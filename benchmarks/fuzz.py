"""Random problems with an independent oracle: the solvers against a convex QP solver.

Linear dynamics x' = A x + B u (random A: stable or not; n = 1..6 states, 1..3 controls),
a fixed final time, piecewise-constant controls on equal segments, a quadratic cost
(1/2 rho |u|^2 integrated, plus 1/2 (xf - target)^T S (xf - target)) and linear constraints:
terminal equalities on some states, terminal half-spaces, control bounds. On jaxtraj's RK4
grid (each segment integrated on rescaled time with `steps` RK4 steps) x(tf) is affine in the
parameters, so the restricted problem is a convex QP. The oracle builds that affine map with
its own numpy RK4 (the RK4 step of a linear system with a constant input is a matrix
polynomial: no jaxtraj code) and solves the QP with Clarabel through cvxpy, independently of
jaxtraj. A convex QP has one optimal value: a SUCCESS anywhere else, or with a constraint
violated, is a false SUCCESS.

Constraint data are drawn around a random feasible point (so every problem is feasible);
the target is drawn far away in some problems, so that bounds and half-spaces are active at
the optimum, up to as many active rows as parameters (vertex optima).

    python benchmarks/fuzz.py --n 200 --solvers default line-search
"""

import argparse
import dataclasses
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxtraj as jt

STEPS = 4  # RK4 steps per segment (the oracle's and the solver's grid)


def _dynamics(t, x, u, args):
    return args["A"] @ x + args["B"] @ u


def _terminal(tf, xf, args):
    return args["Pe"] @ xf - args["xe"]


def _inequality(tf, xf, args):
    return args["Ci"] @ xf - args["di"]


def _mayer(tf, xf, args):
    e = xf - args["target"]
    return 0.5 * e @ args["S"] @ e


def _running(t, x, u, args):
    return 0.5 * args["rho"] * (u @ u)


@dataclasses.dataclass
class RandomProblem:
    """One random problem: its data, the jaxtraj problem and control, and the oracle's QP."""

    seed: int
    n: int
    m: int
    K: int
    T: float
    args: dict
    lower: np.ndarray
    upper: np.ndarray
    M: np.ndarray  # xf = M a + c on the RK4 grid
    c: np.ndarray

    @property
    def problem(self):
        ne, ni = self.args["Pe"].shape[0], self.args["Ci"].shape[0]
        return jt.Problem(
            _dynamics,
            jnp.asarray(self.args["x0"]),
            _terminal,
            tuple(f"x{i}" for i in range(ne)),
            num_controls=self.m,
            objective=_mayer,
            running_cost=_running,
            args=jax.tree.map(jnp.asarray, self.args),
            final_time=self.T,
            control_lower=jnp.asarray(self.lower),
            control_upper=jnp.asarray(self.upper),
            terminal_inequality=_inequality if ni else None,
            terminal_inequality_names=tuple(f"half-space {j}" for j in range(ni)),
            name=f"random-{self.seed}",
        )

    @property
    def control(self):
        return self.problem.parametrize(jt.controls.PiecewiseConstant(self.K, free_times=False, channels=self.m))

    def objective(self, a):
        """The cost at parameters `a` (levels, segment after segment), by the oracle's model."""
        a = np.asarray(a, np.float64)
        e = self.M @ a + self.c - self.args["target"]
        return 0.5 * self.args["rho"] * (self.T / self.K) * (a @ a) + 0.5 * e @ self.args["S"] @ e

    def violation(self, a):
        """The largest constraint violation at `a` by the oracle's model."""
        a = np.asarray(a, np.float64)
        xf = self.M @ a + self.c
        lo, hi = np.tile(self.lower, self.K), np.tile(self.upper, self.K)
        parts = [
            np.abs(self.args["Pe"] @ xf - self.args["xe"]),
            self.args["Ci"] @ xf - self.args["di"],
            lo - a,
            a - hi,
        ]
        return max([0.0] + [float(np.max(p)) for p in parts if p.size])

    def oracle(self):
        """`(objective, a)` of the QP's optimum by Clarabel (cvxpy), to 1e-12."""
        import cvxpy as cp

        a = cp.Variable(self.K * self.m)
        xf = self.M @ a + self.c
        L = np.linalg.cholesky(self.args["S"] + 1e-300 * np.eye(self.n)) if np.any(self.args["S"]) else None
        cost = 0.5 * self.args["rho"] * (self.T / self.K) * cp.sum_squares(a)
        if L is not None:
            cost = cost + 0.5 * cp.sum_squares(L.T @ (xf - self.args["target"]))
        cons = [a >= np.tile(self.lower, self.K), a <= np.tile(self.upper, self.K)]
        if self.args["Pe"].shape[0]:
            cons.append(self.args["Pe"] @ xf == self.args["xe"])
        if self.args["Ci"].shape[0]:
            cons.append(self.args["Ci"] @ xf <= self.args["di"])
        qp = cp.Problem(cp.Minimize(cost), cons)
        qp.solve(
            solver=cp.CLARABEL, tol_gap_abs=1e-13, tol_gap_rel=1e-13, tol_feas=1e-13, tol_ktratio=1e-10, max_iter=500
        )
        if qp.status not in ("optimal", "optimal_inaccurate"):
            raise RuntimeError(f"oracle: {qp.status} on random problem {self.seed}")
        return self.objective(a.value), np.asarray(a.value)

    def starts(self, rng):
        """Starts a user writes: zeros (clipped into the bounds), random inside the bounds."""
        lo, hi = np.tile(self.lower, self.K), np.tile(self.upper, self.K)
        return {
            "zeros": np.clip(np.zeros(self.K * self.m), lo, hi),
            "random": lo + (hi - lo) * rng.uniform(size=lo.shape),
        }


def rk4_affine(A, B, x0, T, K, m, steps=STEPS):
    """x(T) = M a + c for piecewise-constant levels `a` on K equal segments, by numpy RK4 on
    jaxtraj's grid (each segment on rescaled time, `steps` steps): one RK4 step of x' = h (A x
    + B u) with a constant u is x+ = Phi x + Gamma u, Z = h dt A, Phi = I + Z + Z^2/2 + Z^3/6
    + Z^4/24, Gamma = h dt (I + Z/2 + Z^2/6 + Z^3/24) B."""
    n = A.shape[0]
    h, dt = T / K, 1.0 / steps
    Z = h * dt * A
    I = np.eye(n)
    Phi = I + Z + Z @ Z / 2 + Z @ Z @ Z / 6 + Z @ Z @ Z @ Z / 24
    Gam = h * dt * (I + Z / 2 + Z @ Z / 6 + Z @ Z @ Z / 24) @ B
    # over one segment: x+ = Phi^s x + sum_j Phi^j Gamma u
    Phis = np.linalg.matrix_power(Phi, steps)
    Gs = sum(np.linalg.matrix_power(Phi, j) for j in range(steps)) @ Gam
    M = np.zeros((n, K * m))
    c = x0.copy()
    for k in range(K):
        M = Phis @ M
        M[:, k * m : (k + 1) * m] += Gs
        c = Phis @ c
    return M, c


def make(seed, n=None, m=None, K=None):
    """Random problem number `seed` (sizes drawn unless given)."""
    rng = np.random.default_rng(seed)
    n = n or int(rng.integers(1, 7))
    m = m or int(rng.integers(1, 4))
    K = K or int(rng.integers(2, 7))
    T = float(rng.uniform(0.5, 3.0))
    A = rng.standard_normal((n, n)) / np.sqrt(n) + rng.uniform(-0.8, 0.5) * np.eye(n)  # stable or not
    B = rng.standard_normal((n, m))
    x0 = rng.standard_normal(n)
    bound = rng.uniform(0.3, 2.0, m)
    lower, upper = -bound * rng.uniform(0.5, 1.5, m), bound
    M, c = rk4_affine(A, B, x0, T, K, m)
    a_feas = np.tile(lower, K) + (np.tile(upper - lower, K)) * rng.uniform(0.1, 0.9, K * m)
    xf_feas = M @ a_feas + c
    p = K * m
    ne = int(rng.integers(0, min(n, p - 1) + 1))  # terminal equalities on some states
    Pe = np.eye(n)[rng.permutation(n)[:ne]]
    ni = int(rng.integers(0, 3))  # half-spaces through or near the feasible point
    Ci = rng.standard_normal((ni, n))
    di = Ci @ xf_feas + rng.choice([0.0, 0.1, 1.0], ni)
    far = rng.uniform() < 0.5  # a target far away: many active rows at the optimum
    target = xf_feas + (5.0 if far else 0.5) * rng.standard_normal(n)
    W = rng.standard_normal((n, n))
    S = W @ W.T / n + 0.1 * np.eye(n)
    rho = float(10.0 ** rng.uniform(-3, 0))
    args = dict(A=A, B=B, x0=x0, Pe=Pe, xe=Pe @ xf_feas, Ci=Ci, di=di, target=target, S=S, rho=rho)
    return RandomProblem(seed, n, m, K, T, args, lower, upper, M, c)


SOLVERS = {
    "default": jt.KalmanSQP(),
    "line-search": jt.KalmanSQP(globalization="line-search"),
    "augmented-lagrangian": jt.AugmentedLagrangian(),
}


def check(rp, solver, a0, reference, max_steps=500):
    """One solve against the oracle: 'ok' (SUCCESS at the optimum: objective within 1e-8
    relative, constraints within 1e-8), 'false SUCCESS' (SUCCESS elsewhere or infeasible), or
    the status name. Returns (outcome, iterations, objective error)."""
    sol = jt.solve(rp.problem, rp.control, jnp.asarray(a0), solver=solver, simulator=jt.RK4(STEPS), max_steps=max_steps)
    status = jt.status_name(sol.status)
    a = np.asarray(sol.params)
    err = (rp.objective(a) - reference) / (1.0 + abs(reference))
    if status != "SUCCESS":
        return status, int(sol.iterations), err
    ok = abs(err) <= 1e-8 and rp.violation(a) <= 1e-8
    return ("ok" if ok else "false SUCCESS"), int(sol.iterations), err


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100, help="random problems")
    parser.add_argument("--seed", type=int, default=0, help="first problem's seed")
    parser.add_argument("--solvers", nargs="*", default=["default"], choices=sorted(SOLVERS))
    parser.add_argument("--verbose", action="store_true", help="a line per solve")
    args = parser.parse_args()
    print(f"# fuzz: {args.n} random LQ problems from seed {args.seed}; {platform.machine()}, jax {jax.__version__}; ")
    print(f"# {time.strftime('%Y-%m-%d')}; RK4({STEPS}); oracle Clarabel via cvxpy\n")
    counts = {}
    t0 = time.perf_counter()
    for seed in range(args.seed, args.seed + args.n):
        rp = make(seed)
        reference, _ = rp.oracle()
        for kind, a0 in rp.starts(np.random.default_rng(10_000 + seed)).items():
            for name in args.solvers:
                outcome, its, err = check(rp, SOLVERS[name], a0, reference)
                key = (name, kind)
                counts.setdefault(key, {}).setdefault(outcome, 0)
                counts[key][outcome] += 1
                if args.verbose or outcome != "ok":
                    print(
                        f"seed {seed} n={rp.n} m={rp.m} K={rp.K} {name} {kind}: {outcome} its {its} err {err:.1e}",
                        flush=True,
                    )
    print(
        f"\n| solver | start | problems | SUCCESS at the optimum | false SUCCESS | other statuses |  ({time.perf_counter() - t0:.0f} s)"
    )
    print("|---|---|---:|---:|---:|---|")
    for (name, kind), c in counts.items():
        others = ", ".join(f"{k} {v}" for k, v in sorted(c.items()) if k not in ("ok", "false SUCCESS")) or "-"
        print(f"| {name} | {kind} | {sum(c.values())} | {c.get('ok', 0)} | {c.get('false SUCCESS', 0)} | {others} |")


if __name__ == "__main__":
    main()
