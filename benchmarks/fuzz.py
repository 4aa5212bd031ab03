"""Random problems with an independent oracle: the solvers against a convex QP solver.

Linear dynamics x' = A x + B u (random A: stable or not; n = 1..6 states, 1..3 controls),
a fixed final time, piecewise-constant controls on equal segments, a quadratic cost
(1/2 rho |u|^2 integrated, plus 1/2 (xf - target)^T S (xf - target)) and linear constraints:
terminal equalities on some states, terminal half-spaces, control bounds, an upper bound on a
state along the grid (a path constraint), and in some problems the final time fixed the way a
user may state it, by a terminal equality tf - T = 0 over a free tf instead of `final_time=T`.
On jaxtraj's RK4 grid (each segment integrated on rescaled time with `steps` RK4 steps) x at
every grid point is affine in the parameters, so the restricted problem is a convex QP. The oracle builds that affine map with
its own numpy RK4 (the RK4 step of a linear system with a constant input is a matrix
polynomial: no jaxtraj code) and solves the QP with Clarabel through cvxpy, independently of
jaxtraj. A convex QP has one optimal value: a SUCCESS anywhere else, or with a constraint
violated, is a false SUCCESS.

Constraint data are drawn around a random feasible point (so every problem is feasible);
the target is drawn far away in some problems, so that bounds and half-spaces are active at
the optimum, up to as many active rows as parameters (vertex optima).

Classes: `lq` (above), `lq-mixed` (the same with piecewise-constant or continuous
piecewise-linear controls, free initial states with bounds, design parameters, a linear path
row on states and controls together: `MixedProblem`) and `min-time` (least time to a target
set, by bisection over LPs: `MinTimeProblem`).

    python benchmarks/fuzz.py --n 200 --classes lq lq-mixed min-time --solvers default line-search
"""

import argparse
import dataclasses
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxtraj as jt

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

STEPS = 4  # RK4 steps per segment (the oracle's and the solver's grid)


def _dynamics(t, x, u, args):
    return args["A"] @ x + args["B"] @ u


def _terminal(tf, xf, args):
    return args["Pe"] @ xf - args["xe"]


def _terminal_tf(tf, xf, args):
    return jnp.concatenate([args["Pe"] @ xf - args["xe"], jnp.reshape(tf - args["T"], (1,))])


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
    points: list  # (M, c) of every grid point
    state_upper: np.ndarray | None  # a path constraint x <= state_upper on the grid (inf: free)
    tf_equality: bool  # tf a parameter, fixed by the terminal equality tf - T = 0

    @property
    def problem(self):
        ne, ni = self.args["Pe"].shape[0], self.args["Ci"].shape[0]
        names = tuple(f"x{i}" for i in range(ne))
        return jt.Problem(
            _dynamics,
            jnp.asarray(self.args["x0"]),
            _terminal_tf if self.tf_equality else _terminal,
            (*names, "tf = T") if self.tf_equality else names,
            num_controls=self.m,
            objective=_mayer,
            running_cost=_running,
            args=jax.tree.map(jnp.asarray, dict(self.args, T=self.T)),
            final_time=None if self.tf_equality else self.T,
            control_lower=jnp.asarray(self.lower),
            control_upper=jnp.asarray(self.upper),
            state_upper=None if self.state_upper is None else jnp.asarray(self.state_upper),
            terminal_inequality=_inequality if ni else None,
            terminal_inequality_names=tuple(f"half-space {j}" for j in range(ni)),
            name=f"random-{self.seed}",
        )

    @property
    def control(self):
        family = jt.controls.PiecewiseConstant(self.K, free_times=False, channels=self.m)
        return family if self.tf_equality else self.problem.parametrize(family)

    def levels(self, a):
        """The control levels of a parameter vector (without tf where tf is a parameter)."""
        a = np.asarray(a, np.float64)
        return a[:-1] if self.tf_equality else a

    def objective(self, a):
        """The cost at parameters `a` (levels, segment after segment), by the oracle's model."""
        a = self.levels(a)
        e = self.M @ a + self.c - self.args["target"]
        return 0.5 * self.args["rho"] * (self.T / self.K) * (a @ a) + 0.5 * e @ self.args["S"] @ e

    def violation(self, a):
        """The largest constraint violation at `a` by the oracle's model."""
        tf_error = abs(float(np.asarray(a)[-1]) - self.T) if self.tf_equality else 0.0
        a = self.levels(a)
        xf = self.M @ a + self.c
        lo, hi = np.tile(self.lower, self.K), np.tile(self.upper, self.K)
        parts = [
            np.abs(self.args["Pe"] @ xf - self.args["xe"]),
            self.args["Ci"] @ xf - self.args["di"],
            lo - a,
            a - hi,
        ]
        if self.state_upper is not None:
            j = int(np.argmin(np.isinf(self.state_upper)))
            parts.append(np.array([Mp[j] @ a + cp_[j] - self.state_upper[j] for Mp, cp_ in self.points]))
        return max([tf_error] + [float(np.max(p)) for p in parts if p.size])

    def oracle(self):
        """`(objective, params)` of the QP's optimum by Clarabel (cvxpy), to 1e-12."""
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
        if self.state_upper is not None:
            j = int(np.argmin(np.isinf(self.state_upper)))
            cons += [Mp[j] @ a + cp_[j] <= self.state_upper[j] for Mp, cp_ in self.points]
        qp = cp.Problem(cp.Minimize(cost), cons)
        qp.solve(
            solver=cp.CLARABEL, tol_gap_abs=1e-13, tol_gap_rel=1e-13, tol_feas=1e-13, tol_ktratio=1e-10, max_iter=500
        )
        if qp.status not in ("optimal", "optimal_inaccurate"):
            raise RuntimeError(f"oracle: {qp.status} on random problem {self.seed}")
        params = np.append(a.value, self.T) if self.tf_equality else np.asarray(a.value)
        return self.objective(params), params

    def starts(self, rng):
        """Starts a user writes: zeros (clipped into the bounds), random inside the bounds
        (the state bound may be violated there; tf, where a parameter, T and 1.2 T)."""
        lo, hi = np.tile(self.lower, self.K), np.tile(self.upper, self.K)
        starts = {
            "zeros": np.clip(np.zeros(self.K * self.m), lo, hi),
            "random": lo + (hi - lo) * rng.uniform(size=lo.shape),
            "outside": outside(lo, hi, rng),
        }
        if self.tf_equality:  # tf as the user knows it, and 20 % off
            starts = {k: np.append(v, self.T if k == "zeros" else 1.2 * self.T) for k, v in starts.items()}
        return starts


def outside(lo, hi, rng):
    """A start a user may write that breaks the control bounds: uniform in the box widened
    by half its width on each side, its first entry past the upper bound."""
    w = hi - lo
    a = lo - 0.5 * w + 2.0 * w * rng.uniform(size=lo.shape)
    a[0] = hi[0] + 0.25 * w[0]
    return a


def rk4_affine(A, B, x0, T, K, m, steps=STEPS, grid=False):
    """x(T) = M a + c for piecewise-constant levels `a` on K equal segments, by numpy RK4 on
    jaxtraj's grid (each segment on rescaled time, `steps` steps): one RK4 step of x' = h (A x
    + B u) with a constant u is x+ = Phi x + Gamma u, Z = h dt A, Phi = I + Z + Z^2/2 + Z^3/6
    + Z^4/24, Gamma = h dt (I + Z/2 + Z^2/6 + Z^3/24) B. With `grid`, also the list of (M, c)
    of every grid point, segment after segment (steps + 1 points each, its ends included: the
    points where jaxtraj evaluates path constraints)."""
    n = A.shape[0]
    h, dt = T / K, 1.0 / steps
    Z = h * dt * A
    I = np.eye(n)
    Phi = I + Z + Z @ Z / 2 + Z @ Z @ Z / 6 + Z @ Z @ Z @ Z / 24
    Gam = h * dt * (I + Z / 2 + Z @ Z / 6 + Z @ Z @ Z / 24) @ B
    M = np.zeros((n, K * m))
    c = x0.copy()
    points = []
    for k in range(K):
        points.append((M.copy(), c.copy()))
        for _ in range(steps):
            M = Phi @ M
            M[:, k * m : (k + 1) * m] += Gam
            c = Phi @ c
            points.append((M.copy(), c.copy()))
    return (M, c, points) if grid else (M, c)


def _system(rng, n, m, K, sizes):
    """A random linear system and its control box, drawn from `rng` in a fixed order: sizes
    (n < sizes[0], m < sizes[1], K in range(*sizes[2]), unless given), T, A (stable or not),
    B, x0, and bounds lower < 0 < upper per channel."""
    n = n or int(rng.integers(1, sizes[0]))
    m = m or int(rng.integers(1, sizes[1]))
    K = K or int(rng.integers(*sizes[2]))
    T = float(rng.uniform(0.5, 3.0))
    A = rng.standard_normal((n, n)) / np.sqrt(n) + rng.uniform(-0.8, 0.5) * np.eye(n)
    B = rng.standard_normal((n, m))
    x0 = rng.standard_normal(n)
    bound = rng.uniform(0.3, 2.0, m)
    return n, m, K, T, A, B, x0, -bound * rng.uniform(0.5, 1.5, m), bound


def make(seed, n=None, m=None, K=None):
    """Random problem number `seed` (sizes drawn unless given)."""
    rng = np.random.default_rng(seed)
    n, m, K, T, A, B, x0, lower, upper = _system(rng, n, m, K, (7, 4, (2, 7)))
    M, c, points = rk4_affine(A, B, x0, T, K, m, grid=True)
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
    # an upper bound on one state along the grid, at (or 0.1 above) the feasible trajectory's
    # largest value: often active at the optimum, where the target lies beyond it
    bounded = int(rng.integers(0, n)) if rng.uniform() < 0.4 else None
    state_upper = None
    if bounded is not None:
        state_upper = np.full(n, np.inf)
        state_upper[bounded] = max(Mj[bounded] @ a_feas + cj[bounded] for Mj, cj in points) + rng.choice([0.0, 0.1])
    args = dict(A=A, B=B, x0=x0, Pe=Pe, xe=Pe @ xf_feas, Ci=Ci, di=di, target=target, S=S, rho=rho)
    tf_equality = bool(rng.uniform() < 0.25)
    return RandomProblem(seed, n, m, K, T, args, lower, upper, M, c, points, state_upper, tf_equality)


@dataclasses.dataclass
class MinTimeProblem:
    """A random least-time problem: x' = A x + B u from x0, control bounds, piecewise-constant
    levels on K equal segments over a free tf, to a target set (terminal equalities on some
    states and/or half-spaces), drawn around a point that a random control reaches at a
    random time (so the set is reachable). The oracle: for a fixed tf the reachable set is a
    polyhedron (x(tf) affine in the levels, numpy RK4), so "can the target be met at tf" is a
    linear program; the least tf by a scan of (0, T] and bisection (the least feasible tf: a
    SUCCESS above it is a local minimum, one below it or infeasible a false SUCCESS)."""

    seed: int
    n: int
    m: int
    K: int
    T: float  # a time at which the target set is reachable
    args: dict
    lower: np.ndarray
    upper: np.ndarray

    @property
    def problem(self):
        ne, ni = self.args["Pe"].shape[0], self.args["Ci"].shape[0]
        return jt.Problem(
            _dynamics,
            jnp.asarray(self.args["x0"]),
            _terminal,
            tuple(f"x{i}" for i in range(ne)),
            num_controls=self.m,
            args=jax.tree.map(jnp.asarray, self.args),
            tf_bounds=(0.0, np.inf),
            control_lower=jnp.asarray(self.lower),
            control_upper=jnp.asarray(self.upper),
            terminal_inequality=_inequality if ni else None,
            terminal_inequality_names=tuple(f"half-space {j}" for j in range(ni)),
            name=f"random-min-time-{self.seed}",
        )

    @property
    def control(self):
        return jt.controls.PiecewiseConstant(self.K, free_times=False, channels=self.m)

    def objective(self, a):
        return float(np.asarray(a)[-1])

    def violation(self, a):
        a = np.asarray(a, np.float64)
        M, c = rk4_affine(self.args["A"], self.args["B"], self.args["x0"], a[-1], self.K, self.m)
        xf = M @ a[:-1] + c
        lo, hi = np.tile(self.lower, self.K), np.tile(self.upper, self.K)
        parts = [np.abs(self.args["Pe"] @ xf - self.args["xe"]), self.args["Ci"] @ xf - self.args["di"]]
        parts += [lo - a[:-1], a[:-1] - hi, np.array([-a[-1]])]
        return max([0.0] + [float(np.max(p)) for p in parts if p.size])

    def reachable(self, tf, near=None, radius=None):
        """Whether some levels within the bounds meet the target set at `tf` (an LP, HiGHS);
        with `near`, levels within `radius` of those."""
        import scipy.optimize

        M, c = rk4_affine(self.args["A"], self.args["B"], self.args["x0"], tf, self.K, self.m)
        Pe, Ci = self.args["Pe"], self.args["Ci"]
        lo, hi = np.tile(self.lower, self.K), np.tile(self.upper, self.K)
        if near is not None:
            lo, hi = np.maximum(lo, near - radius), np.minimum(hi, near + radius)
        res = scipy.optimize.linprog(
            np.zeros(self.K * self.m),
            A_ub=Ci @ M if Ci.shape[0] else None,
            b_ub=self.args["di"] - Ci @ c if Ci.shape[0] else None,
            A_eq=Pe @ M if Pe.shape[0] else None,
            b_eq=self.args["xe"] - Pe @ c if Pe.shape[0] else None,
            bounds=list(zip(lo, hi)),
            method="highs",
            options={"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10},
        )
        return res.status == 0

    def oracle(self, scan=400):
        """`(least tf, None)`: the first reachable tf of a scan of (0, T], then 60 bisections."""
        grid = np.linspace(0.0, self.T, scan + 1)[1:]
        k = next(i for i, tf in enumerate(grid) if self.reachable(tf))
        lo, hi = (0.0 if k == 0 else grid[k - 1]), grid[k]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if self.reachable(mid) else (mid, hi)
        return hi, None

    def locally_least(self, a):
        """Whether no levels within 1e-3 of the range of `a`'s meet the target set at a time
        1e-6 shorter (an LP): the least time of its own window, a local minimum; else the
        solve stopped where the time could still shrink."""
        a = np.asarray(a, np.float64)
        radius = 1e-3 * np.tile(self.upper - self.lower, self.K)
        return not self.reachable(a[-1] * (1.0 - 1e-6), near=a[:-1], radius=radius)

    def starts(self, rng):
        """The levels at 0 (clipped into the bounds), random inside them or outside them
        (`outside`); tf = T or 2 T."""
        lo, hi = np.tile(self.lower, self.K), np.tile(self.upper, self.K)
        return {
            "zeros": np.append(np.clip(np.zeros(self.K * self.m), lo, hi), self.T),
            "random": np.append(lo + (hi - lo) * rng.uniform(size=lo.shape), 2.0 * self.T),
            "outside": np.append(outside(lo, hi, rng), 2.0 * self.T),
        }


def make_min_time(seed, n=None, m=None, K=None):
    """Random least-time problem number `seed` (sizes drawn unless given)."""
    rng = np.random.default_rng(seed)
    n, m, K, T, A, B, x0, lower, upper = _system(rng, n, m, K, (5, 3, (1, 5)))
    # a bang-bang-ish control reaches the target point: levels near the bounds
    a_feas = np.where(rng.uniform(size=K * m) < 0.5, np.tile(lower, K), np.tile(upper, K)) * rng.uniform(
        0.7, 1.0, K * m
    )
    M, c = rk4_affine(A, B, x0, T, K, m)
    xf = M @ a_feas + c
    ne = int(rng.integers(0, min(n, K * m) + 1))  # fewer equalities than parameters (K m + 1)
    Pe = np.eye(n)[rng.permutation(n)[:ne]]
    ni = int(rng.integers(0 if ne else 1, 3))  # some target constraint
    Ci = rng.standard_normal((ni, n))
    di = Ci @ xf + rng.choice([0.0, 0.05], ni)
    args = dict(A=A, B=B, x0=x0, Pe=Pe, xe=Pe @ xf, Ci=Ci, di=di)
    return MinTimeProblem(seed, n, m, K, T, args, lower, upper)


def _path_row(t, x, u, args):
    return args["Px"] @ x + args["Pu"] @ u - args["r"]


def _control_map(family, K, m, p):
    """`U(k, tau)`: the (m, p) matrix with u = U a on segment k at rescaled time tau, for
    piecewise-constant levels (K m entries first) or continuous piecewise-linear nodes ((K + 1)
    m entries first) on equal segments; the other p - those entries are not control values."""

    def U(k, tau):
        out = np.zeros((m, p))
        if family == "constant":
            out[:, k * m : (k + 1) * m] = np.eye(m)
        else:
            out[:, k * m : (k + 1) * m] = (1.0 - tau) * np.eye(m)
            out[:, (k + 1) * m : (k + 2) * m] += tau * np.eye(m)
        return out

    return U


def rk4_affine_points(A, B, E0, c0, T, K, U, steps=STEPS):
    """Every grid point's (M, c, Mu) with x = M a + c and u = Mu a, by numpy RK4 on jaxtraj's
    grid (each segment on rescaled time, `steps` steps; steps + 1 points per segment, its ends
    included, with that segment's control), for x' = h (A x + B u(tau)), x(0) = E0 a + c0 and
    the control map `U(k, tau)` (`_control_map`): each stage of the RK4 step is affine in a."""
    h, dt = T / K, 1.0 / steps
    M, c = E0.astype(np.float64), c0.astype(np.float64)
    points = []
    for k in range(K):
        points.append((M, c, U(k, 0.0)))
        for j in range(steps):
            tau = j * dt

            def f(Mx, cx, s):
                return h * (A @ Mx + B @ U(k, s)), h * (A @ cx)

            k1 = f(M, c, tau)
            k2 = f(M + 0.5 * dt * k1[0], c + 0.5 * dt * k1[1], tau + 0.5 * dt)
            k3 = f(M + 0.5 * dt * k2[0], c + 0.5 * dt * k2[1], tau + 0.5 * dt)
            k4 = f(M + dt * k3[0], c + dt * k3[1], tau + dt)
            M = M + dt / 6.0 * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0])
            c = c + dt / 6.0 * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1])
            points.append((M, c, U(k, tau + dt)))
    return points


@dataclasses.dataclass
class MixedProblem:
    """A random fixed-time LQ problem with every constraint kind of the `lq` class and more:
    piecewise-constant or continuous piecewise-linear controls, free initial states with
    bounds, design parameters (states with zero rates and a bounded free initial value that
    enter the dynamics), and a linear path constraint on states and controls together. The
    restricted problem is still a convex QP on the RK4 grid (`rk4_affine_points`); the cost
    of 1/2 rho |u|^2 is integrated exactly by RK4 (Simpson's rule on each step, exact for a
    quadratic in time), so the oracle takes it in closed form."""

    seed: int
    n: int  # states, design parameters included
    m: int
    K: int
    T: float
    family: str  # "constant" or "linear"
    args: dict
    lower: np.ndarray
    upper: np.ndarray
    free: tuple  # free initial states (indices), bounds below
    free_lower: np.ndarray
    free_upper: np.ndarray
    points: list  # (M, c, Mu) of every grid point
    state_upper: np.ndarray | None
    path: bool

    @property
    def num_levels(self):
        return (self.K if self.family == "constant" else self.K + 1) * self.m

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
            state_upper=None if self.state_upper is None else jnp.asarray(self.state_upper),
            path=_path_row if self.path else None,
            path_names=("path row",) if self.path else (),
            terminal_inequality=_inequality if ni else None,
            terminal_inequality_names=tuple(f"half-space {j}" for j in range(ni)),
            free_initial_state={i: (lo, hi) for i, lo, hi in zip(self.free, self.free_lower, self.free_upper)},
            name=f"random-mixed-{self.seed}",
        )

    @property
    def control(self):
        if self.family == "constant":
            family = jt.controls.PiecewiseConstant(self.K, free_times=False, channels=self.m)
        else:
            family = jt.controls.PiecewiseLinear(self.K, channels=self.m)
        return self.problem.parametrize(family)

    def _cost_matrix(self):
        """R with the integral of |u|^2 = a^T R a (exact: Gram matrix of the control basis)."""
        h, m, p = self.T / self.K, self.m, self.num_levels
        if self.family == "constant":
            return h * np.eye(p)
        R = np.zeros((p, p))
        for k in range(self.K):
            i, j = slice(k * m, (k + 1) * m), slice((k + 1) * m, (k + 2) * m)
            R[i, i] += h / 3.0 * np.eye(m)
            R[j, j] += h / 3.0 * np.eye(m)
            R[i, j] += h / 6.0 * np.eye(m)
            R[j, i] += h / 6.0 * np.eye(m)
        return R

    def objective(self, a):
        a = np.asarray(a, np.float64)
        M, c, _ = self.points[-1]
        e = M @ a + c - self.args["target"]
        u = a[: self.num_levels]
        return 0.5 * self.args["rho"] * u @ self._cost_matrix() @ u + 0.5 * e @ self.args["S"] @ e

    def _rows(self):
        """The constraints as (G, h, kind): G a <= h ("ineq") or G a = h ("eq")."""
        p = self.num_levels + len(self.free)
        M, c, _ = self.points[-1]
        I = np.eye(p)
        levels, tail = I[: self.num_levels], I[self.num_levels :]
        reps = self.num_levels // self.m
        rows = [
            (-levels, -np.tile(self.lower, reps), "ineq"),
            (levels, np.tile(self.upper, reps), "ineq"),
            (-tail, -self.free_lower, "ineq"),
            (tail, self.free_upper, "ineq"),
            (self.args["Pe"] @ M, self.args["xe"] - self.args["Pe"] @ c, "eq"),
            (self.args["Ci"] @ M, self.args["di"] - self.args["Ci"] @ c, "ineq"),
        ]
        if self.state_upper is not None:
            j = int(np.argmin(np.isinf(self.state_upper)))
            rows.append(
                (
                    np.array([Mp[j] for Mp, _, _ in self.points]),
                    np.array([self.state_upper[j] - cp_[j] for _, cp_, _ in self.points]),
                    "ineq",
                )
            )
        if self.path:
            Px, Pu, r = self.args["Px"][0], self.args["Pu"][0], self.args["r"][0]
            rows.append(
                (
                    np.array([Px @ Mp + Pu @ Mu for Mp, _, Mu in self.points]),
                    np.array([r - Px @ cp_ for _, cp_, _ in self.points]),
                    "ineq",
                )
            )
        return [(G, h, kind) for G, h, kind in rows if G.shape[0]]

    def violation(self, a):
        a = np.asarray(a, np.float64)
        return max(
            [0.0] + [float(np.max(np.abs(G @ a - h) if kind == "eq" else G @ a - h)) for G, h, kind in self._rows()]
        )

    def oracle(self):
        import cvxpy as cp

        p = self.num_levels + len(self.free)
        a = cp.Variable(p)
        M, c, _ = self.points[-1]
        L = np.linalg.cholesky(self.args["S"])
        R = np.linalg.cholesky(self._cost_matrix())
        cost = 0.5 * self.args["rho"] * cp.sum_squares(R.T @ a[: self.num_levels])
        cost = cost + 0.5 * cp.sum_squares(L.T @ (M @ a + c - self.args["target"]))
        cons = [(G @ a == h) if kind == "eq" else (G @ a <= h) for G, h, kind in self._rows()]
        qp = cp.Problem(cp.Minimize(cost), cons)
        qp.solve(
            solver=cp.CLARABEL, tol_gap_abs=1e-13, tol_gap_rel=1e-13, tol_feas=1e-13, tol_ktratio=1e-10, max_iter=500
        )
        if qp.status not in ("optimal", "optimal_inaccurate"):
            raise RuntimeError(f"oracle: {qp.status} on random problem {self.seed}")
        return self.objective(a.value), np.asarray(a.value)

    def starts(self, rng):
        """Zeros (clipped into the bounds), random inside the bounds and, for linear pieces, the
        straight line from the lower to the upper bound; free initial states at x0."""
        reps = self.num_levels // self.m
        lo, hi = np.tile(self.lower, reps), np.tile(self.upper, reps)
        x0 = np.asarray(self.args["x0"])[list(self.free)]
        starts = {
            "zeros": np.append(np.clip(np.zeros(lo.shape), lo, hi), x0),
            "random": np.append(lo + (hi - lo) * rng.uniform(size=lo.shape), x0),
            "outside": np.append(outside(lo, hi, rng), x0),
        }
        if self.family == "linear":
            w = np.repeat(np.linspace(0.0, 1.0, reps), self.m)
            starts["line"] = np.append(lo + (hi - lo) * w, x0)
        return starts


def make_mixed(seed, n=None, m=None, K=None):
    """Random mixed problem number `seed` (sizes drawn unless given)."""
    rng = np.random.default_rng(seed)
    nx, m, K, T, A, B, x0, lower, upper = _system(rng, n, m, K, (5, 3, (2, 6)))
    family = "constant" if rng.uniform() < 0.5 else "linear"
    nd = int(rng.integers(0, 3))  # design parameters: states with zero rates entering the dynamics
    n = nx + nd
    Aa = np.zeros((n, n))
    Aa[:nx, :nx] = A
    Aa[:nx, nx:] = rng.standard_normal((nx, nd))
    Ba = np.vstack([B, np.zeros((nd, m))])
    x0 = np.append(x0, rng.standard_normal(nd))
    free = sorted(rng.permutation(nx)[: int(rng.integers(0, min(nx, 2) + 1))].tolist()) + list(range(nx, n))
    width = rng.uniform(0.2, 1.5, (2, len(free)))
    free_lower, free_upper = x0[free] - width[0], x0[free] + width[1]
    levels = (K if family == "constant" else K + 1) * m
    p = levels + len(free)
    E0 = np.zeros((n, p))
    E0[free, levels + np.arange(len(free))] = 1.0
    c0 = x0.copy()
    c0[free] = 0.0
    points = rk4_affine_points(Aa, Ba, E0, c0, T, K, _control_map(family, K, m, p))
    reps = levels // m
    a_feas = np.append(
        np.tile(lower, reps) + np.tile(upper - lower, reps) * rng.uniform(0.1, 0.9, levels),
        free_lower + (free_upper - free_lower) * rng.uniform(0.1, 0.9, len(free)),
    )
    Mf, cf, _ = points[-1]
    xf_feas = Mf @ a_feas + cf
    ne = int(rng.integers(0, min(nx, p - 1) + 1))
    Pe = np.eye(n)[rng.permutation(nx)[:ne]]
    ni = int(rng.integers(0, 3))
    Ci = np.hstack([rng.standard_normal((ni, nx)), np.zeros((ni, nd))])
    di = Ci @ xf_feas + rng.choice([0.0, 0.1, 1.0], ni)
    far = rng.uniform() < 0.5
    target = xf_feas + (5.0 if far else 0.5) * rng.standard_normal(n)
    W = rng.standard_normal((n, n))
    S = W @ W.T / n + 0.1 * np.eye(n)
    rho = float(10.0 ** rng.uniform(-3, 0))
    on_grid = [(Mp @ a_feas + cp_, Mu @ a_feas) for Mp, cp_, Mu in points]
    state_upper = None
    if rng.uniform() < 0.3:
        j = int(rng.integers(0, nx))
        state_upper = np.full(n, np.inf)
        state_upper[j] = max(x[j] for x, _ in on_grid) + rng.choice([0.0, 0.1])
    path = bool(rng.uniform() < 0.4)  # a row on states and controls, through the feasible point
    Px, Pu = np.hstack([rng.standard_normal((1, nx)), np.zeros((1, nd))]), rng.standard_normal((1, m))
    r = np.array([max(Px[0] @ x + Pu[0] @ u for x, u in on_grid) + rng.choice([0.0, 0.1])])
    x0_start = x0.copy()  # the problem's x0: free components at their start values (inside their bounds)
    args = dict(A=Aa, B=Ba, x0=x0_start, Pe=Pe, xe=Pe @ xf_feas, Ci=Ci, di=di, target=target, S=S, rho=rho)
    args.update(Px=Px, Pu=Pu, r=r)
    return MixedProblem(
        seed, n, m, K, T, family, args, lower, upper, tuple(free), free_lower, free_upper, points, state_upper, path
    )


SOLVERS = {
    "default": jt.KalmanSQP(),
    "line-search": jt.KalmanSQP(globalization="line-search"),
    "augmented-lagrangian": jt.AugmentedLagrangian(),
}


CLASSES = {"lq": make, "min-time": make_min_time, "lq-mixed": make_mixed}


def check(rp, solver, a0, reference, max_steps=500):
    """One solve against the oracle: 'ok' (SUCCESS at the optimum: objective within 1e-8
    relative, constraints within 1e-8), 'false SUCCESS' (SUCCESS infeasible, below the
    optimum, or above it on a convex problem or where the time could still shrink), 'local
    minimum' (SUCCESS above the least time of a min-time problem, which is not convex, at the
    least time of its own window: `locally_least`), or the status name. Returns (outcome,
    iterations, relative objective error)."""
    sol = jt.solve(rp.problem, rp.control, jnp.asarray(a0), solver=solver, simulator=jt.RK4(STEPS), max_steps=max_steps)
    status = jt.status_name(sol.status)
    a = np.asarray(sol.params)
    err = (rp.objective(a) - reference) / (1.0 + abs(reference))
    if status != "SUCCESS":
        return status, int(sol.iterations), err
    if rp.violation(a) > 1e-8 or err < -1e-8:
        return "false SUCCESS", int(sol.iterations), err
    if err > 1e-8:
        local = isinstance(rp, MinTimeProblem) and rp.locally_least(a)
        return ("local minimum" if local else "false SUCCESS"), int(sol.iterations), err
    return "ok", int(sol.iterations), err


def _int_at_least(low):
    """An argparse type: an int >= `low` (argparse names the argument in its one-line error)."""

    def parse(text):
        value = int(text)  # (a ValueError: argparse's "invalid ... value")
        if value < low:
            raise argparse.ArgumentTypeError(f"must be an int >= {low}; got {value}")
        return value

    parse.__name__ = "int"  # (argparse: "invalid int value")
    return parse


def parse_args(argv=None):
    """The command line's arguments (argparse's one-line error, exit status 2, for a bad one)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=_int_at_least(1), default=100, help="random problems per class")
    # (NumPy's generators take seeds >= 0 only)
    parser.add_argument("--seed", type=_int_at_least(0), default=0, help="first problem's seed")
    parser.add_argument("--classes", nargs="+", default=list(CLASSES), choices=list(CLASSES))
    parser.add_argument("--solvers", nargs="+", default=["default"], choices=sorted(SOLVERS))
    parser.add_argument("--verbose", action="store_true", help="a line per solve")
    args = parser.parse_args(argv)
    # (a class or solver named twice ran twice into one row: its problem count doubled)
    args.classes, args.solvers = list(dict.fromkeys(args.classes)), list(dict.fromkeys(args.solvers))
    return args


def main(argv=None):
    args = parse_args(argv)
    print(f"# fuzz: {args.n} random problems per class from seed {args.seed}; {platform.machine()}, ")
    print(f"# jax {jax.__version__}; {time.strftime('%Y-%m-%d')}; RK4({STEPS}); oracles: Clarabel (cvxpy), HiGHS LPs\n")
    counts = {}
    t0 = time.perf_counter()
    for cls in args.classes:
        for seed in range(args.seed, args.seed + args.n):
            rp = CLASSES[cls](seed)
            try:
                reference, _ = rp.oracle()
            except Exception as error:  # (Clarabel failed on lq seed 1138 and ended the run)
                print(f"{cls} seed {seed}: no oracle ({type(error).__name__}); skipped", flush=True)
                counts.setdefault((cls, "oracle", "-"), {}).setdefault("no oracle", 0)
                counts[(cls, "oracle", "-")]["no oracle"] += 1
                continue
            if cls == "min-time" and reference < 0.05 * rp.T:
                continue  # the start already (nearly) in the target set: nothing to solve
            for kind, a0 in rp.starts(np.random.default_rng(10_000 + seed)).items():
                for name in args.solvers:
                    outcome, its, err = check(rp, SOLVERS[name], a0, reference)
                    key = (cls, name, kind)
                    counts.setdefault(key, {}).setdefault(outcome, 0)
                    counts[key][outcome] += 1
                    if args.verbose or outcome != "ok":
                        print(
                            f"{cls} seed {seed} n={rp.n} m={rp.m} K={rp.K} {name} {kind}: {outcome} its {its} err {err:.1e}",
                            flush=True,
                        )
            # every problem compiles its own solvers (the control bounds are static structure):
            # without dropping them, a run of a few hundred problems filled 24 GB
            jax.clear_caches()
            if (seed - args.seed + 1) % 25 == 0:
                print(f"# {cls}: {seed - args.seed + 1} problems, {time.perf_counter() - t0:.0f} s", flush=True)
    print(f"\n({time.perf_counter() - t0:.0f} s)\n")
    print("| class | solver | start | problems | SUCCESS at the optimum | false SUCCESS | other outcomes |")
    print("|---|---|---|---:|---:|---:|---|")
    for (cls, name, kind), c in counts.items():
        others = ", ".join(f"{k} {v}" for k, v in sorted(c.items()) if k not in ("ok", "false SUCCESS")) or "-"
        print(
            f"| {cls} | {name} | {kind} | {sum(c.values())} | {c.get('ok', 0)} | {c.get('false SUCCESS', 0)} | {others} |"
        )


if __name__ == "__main__":
    main()
