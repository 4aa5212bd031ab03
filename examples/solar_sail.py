"""Minimum-time solar-sail transfers from Earth's orbit to Mars's, Venus's and Mercury's
(seed 003, issue 7): gradient solvers on the constrained problem against the seed's three
metaheuristics on its penalty functional, with the indirect (Pontryagin) optimum of the
unrestricted problem as the reference.

For every target, with the seed's control `SaturatedSpline(P, p)` (free segment durations):

* (a) `jt.KalmanSQP` on "minimize tf subject to r = r_f, u = 0, v = v_f", from a grid of
  starts (constant pitch +-`--pitches` degrees, outwards for Mars and inwards for Venus and
  Mercury, times durations summing to `--tf-factors` x half of `ss.TF_BOX[target]`; the
  solver is not told the indirect answer); for reference `jt.KalmanSearch` (the thesis's
  method with the sail tuning `ss.kalman_search_solver()`) from the same starts and SciPy's
  SLSQP (`jaxtraj.baselines.solve_slsqp`) from the 35 deg / factor 1 start;
* (b) `jt.GreyWolf`, `jt.Whale` (linear and quadratic decay of a) and `jt.Dragonfly` on the
  seed's penalty functional (eq. 5, `ss.penalty_objective`, weights `ss.DEFAULT_WEIGHTS`)
  over the box `ss.box`, with the same P, p and simulator, over `--seeds` PRNG keys (vmapped),
  every method with the same budget: population x (generations + 1) evaluations per seed;
* (c) `ss.solve_indirect`: the unrestricted optimum (NumPy/SciPy shooting; no jaxtraj code).

Every returned point goes through `ss.diagnose` (terminal miss > 1e-6, more than 2 % of the
time feathered, or tf below the indirect optimum are flagged: such outcomes are reported
as what they are, never as optima). The best run of a method is the one it would pick
itself: for the metaheuristics the lowest penalty value; for the gradient solvers the
shortest unflagged transfer (if every start is flagged, the smallest terminal miss). Terminal
errors are given with the solvers' RK4 and re-checked with an adaptive integrator
(Tsit5, rtol = atol = 1e-12): the saturated spline has kinks inside segments, where RK4's
order drops.

Output: a Markdown table on stdout and in `OUT/results.md` (with per-start and per-seed
details), `OUT/results.json`, and per target `OUT/<target>_orbit.png` (the transfer in the
orbital plane), `OUT/<target>_pitch.png` (the pitch programs) and
`OUT/<target>_convergence.png` (best penalty value against evaluations, per metaheuristic).

Run (from the repository root; the default took 2 minutes on 2 shared CPU cores):

    PYTHONPATH=. python examples/solar_sail.py
    PYTHONPATH=. python examples/solar_sail.py --quick                 # smoke run, about a minute (mostly compilation)
    PYTHONPATH=. python examples/solar_sail.py --targets mars --seeds 10 --generations 1000

Timing notes: each solver is compiled once for all targets (the three problems differ only
in their array `args` and their names, which take no part in compilation), and compilation
is timed apart from the runs. The
gradient solvers run their starts one after another in one compiled loop (`lax.map`, what
`jt.solve_batch` does on CPU); the metaheuristics run their seeds side by side (`vmap`).
"""

import argparse
import dataclasses
import json
import math
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _args import folder, number

# jaxtraj sets XLA:CPU options at import; they take effect as it comes before any JAX computation
import jaxtraj as jt
import jaxtraj.problems.solar_sail as ss
from jaxtraj import metaheuristics as mh
from jaxtraj.baselines import solve_slsqp
from jaxtraj.plot import pyplot

if __name__ == "__main__":
    jt.configure_cpu()  # a CPU device per core and XLA options (before any JAX computation)

TARGETS = ("mars", "venus", "mercury")
METHODS = {
    # key: (label, kind)
    "sqp": ("KalmanSQP", "gradient"),
    "search": ("KalmanSearch", "gradient"),
    "slsqp": ("SLSQP", "gradient"),
    "gwo": ("GreyWolf", "population"),
    "woa": ("Whale (linear a)", "population"),
    "woa2": ("Whale (quadratic a)", "population"),
    "da": ("Dragonfly", "population"),
    "indirect": ("indirect (unrestricted)", "indirect"),
}
STATUS_SHORT = {
    "SUCCESS": "S",
    "MAX_ITERATIONS": "M",
    "STALLED": "T",
    "CONSTRAINT_STATIONARY": "C",
    "NONFINITE": "N",
    "SIMULATION_FAILED": "F",
    "DIVERGED": "D",
}
MISS_TOL = 1e-6  # `ss.diagnose`'s default: a terminal miss above it is no transfer
COLLAPSED = 1e-8  # a segment shorter than this [time units] has collapsed


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--targets", nargs="+", choices=TARGETS, default=list(TARGETS))
    p.add_argument(
        "--methods", nargs="+", choices=list(METHODS), default=list(METHODS), help="methods to run (default: all)"
    )
    p.add_argument("--segments", "-P", type=number(int, 1, 1000), default=10, help="spline segments P (default 10)")
    p.add_argument("--degree", "-p", type=int, default=1, choices=(0, 1, 2, 3), help="spline degree p (default 1)")
    p.add_argument(
        "--rk4-steps",
        type=number(int, 1, 10_000),
        default=100,
        help="RK4 steps per segment, every method (default 100)",
    )
    p.add_argument("--seeds", type=number(int, 1, 1000), default=5, help="PRNG seeds per metaheuristic (default 5)")
    p.add_argument(
        "--population",
        type=number(int, 3, 100_000),
        default=30,
        help="population size (default 30; >= 3: GreyWolf and Dragonfly need three members)",
    )
    p.add_argument("--generations", type=number(int, 1, 1_000_000), default=200, help="generations (default 200)")
    p.add_argument(
        "--penalty-weight",
        type=number(float, 0.0, above=True),
        default=ss.DEFAULT_WEIGHTS[1],
        help="lambda_2 = lambda_3 = lambda_4 of the penalty (lambda_1 = 1 per day; default 1e10)",
    )
    p.add_argument(
        "--pitches",
        type=number(float, 0.0, 90.0),
        nargs="+",
        default=[20.0, 35.0, 50.0],
        help="constant starting pitches [deg] in 0..90, sign set by the target (default 20 35 50)",
    )
    p.add_argument(
        "--tf-factors",
        type=number(float, 0.0, 2.0, above=True),
        nargs="+",
        default=[0.8, 1.0, 1.3],
        help="starting tf as multiples of TF_BOX[target] / 2, in (0, 2]: inside the box (default 0.8 1.0 1.3)",
    )
    p.add_argument(
        "--max-steps",
        type=number(int, 1, 1_000_000),
        default=600,
        help="candidate integrations per start (default 600)",
    )
    p.add_argument(
        "--sqp-hessian",
        choices=("bfgs", "exact"),
        default="bfgs",
        help="KalmanSQP's Hessian, with the line search (default bfgs; the runs recorded in docs/results.md)",
    )
    p.add_argument(
        "--slsqp-maxiter", type=number(int, 1, 1_000_000), default=150, help="SLSQP iteration limit (default 150)"
    )
    p.add_argument("--out", type=folder, default=os.path.join("results", "solar_sail"), help="output folder")
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: P = 4, RK4(20), 2 starts, 60 steps, 2 seeds x 10 x 8 (overrides those flags)",
    )
    args = p.parse_args(argv)
    if args.quick:
        args.segments, args.rk4_steps = 4, 20
        args.seeds, args.population, args.generations = 2, 10, 8
        args.pitches, args.tf_factors = [35.0], [1.0, 1.3]
        args.max_steps, args.slsqp_maxiter = 60, 20
    return args


# ---------------------------------------------------------------------------- problems


def target_problem(target):
    # The three problems differ only in `args` (arrays) and their names (which take no part
    # in compilation): code compiled for one target runs the others.
    return ss.problem(target)


def _sign(target):
    return 1.0 if ss.TARGET_RADII[target] > 1.0 else -1.0  # outwards: prograde push


def starts(target, ctrl, pitches, factors):
    """Starting vectors (constant pitch, equal durations) and their labels."""
    rows, labels = [], []
    for deg in pitches:
        for f in factors:
            alpha = _sign(target) * math.radians(deg)
            rows.append(np.asarray(ctrl.initial_guess(f * ss.TF_BOX[target] / 2.0, alpha, alpha)))
            labels.append(f"{_sign(target) * deg:+.0f} deg, tf x{f:g}")
    return jnp.asarray(np.stack(rows)), labels


# ---------------------------------------------------------------------------- records


@dataclasses.dataclass
class Run:
    """One start (gradient solvers) or one seed (metaheuristics)."""

    label: str
    params: np.ndarray  # durations clipped at 0 (see `_clean_params`)
    tf: float
    objective: float  # tf (gradient) or the penalty value J (metaheuristics)
    status: str
    diag: dict
    evaluations: int  # integrations (gradient: with sensitivities)
    iterations: int = 0
    negative_durations: bool = False
    segments: int = 0

    @property
    def collapsed(self):
        """Segments shorter than `COLLAPSED` (their coefficients have lost their effect)."""
        return int(np.sum(self.params[: self.segments] < COLLAPSED))


@dataclasses.dataclass
class MethodResult:
    target: str
    key: str
    runs: list
    best: int
    wall: float  # run time [s], compilation excluded
    evaluations_total: int
    adaptive_miss: float = float("nan")  # max |E| of the best run, adaptive re-integration
    history: np.ndarray | None = None  # (seeds, generations) best penalty value per generation
    population: int = 0
    note: str = ""

    @property
    def label(self):
        return METHODS[self.key][0]


def _clean_params(ctrl, a):
    """Solvers can return durations a few ulp below 0 (e.g. -6e-17) for a collapsed segment;
    `ss.diagnose` and `jt.simulate` refuse negative ones, so they are set to 0 here and the
    run is marked (`negative_durations`)."""
    a = np.array(a, dtype=np.float64)
    P = ctrl.segments
    neg = bool(np.any(a[:P] < 0))
    a[:P] = np.maximum(a[:P], 0.0)
    return a, neg


def _diagnose(prob, ctrl, a, sim, tf_floor):
    d = ss.diagnose(prob, ctrl, a, simulator=sim, miss_tol=MISS_TOL, tf_floor=tf_floor)
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()}


def _pick_best_gradient(runs):
    clean = [i for i, r in enumerate(runs) if not r.diag["flags"]]
    if clean:
        return min(clean, key=lambda i: runs[i].tf)
    return min(range(len(runs)), key=lambda i: runs[i].diag["max_miss"])


# ---------------------------------------------------------------------------- (a) gradient


def compile_multistart(solver, ctrl, sim, max_steps, n_starts):
    """A compiled `(problem, a0s) -> Solution` running `jt.solve` from every row of `a0s` in
    turn (`lax.map`; on CPU that is what `jt.solve_batch` does, and it avoids batched LAPACK
    calls), for any target's problem. Returns `(compiled, seconds to compile)`."""

    def run(prob, a0s):
        return jax.lax.map(lambda a0: jt.solve(prob, ctrl, a0, solver, simulator=sim, max_steps=max_steps), a0s)

    t0 = time.perf_counter()
    a0s = jnp.zeros((n_starts, ctrl.num_params))
    compiled = eqx.filter_jit(run).lower(target_problem("mars"), a0s).compile()
    return compiled, time.perf_counter() - t0


def run_gradient(key, compiled, target, ctrl, sim, a0s, labels, tf_floor):
    prob = target_problem(target)
    t0 = time.perf_counter()
    sol = compiled(prob, a0s)
    jax.block_until_ready(sol.params)
    wall = time.perf_counter() - t0
    runs = []
    for i, label in enumerate(labels):
        s = jax.tree.map(lambda x, i=i: x[i], sol)
        a, neg = _clean_params(ctrl, s.params)
        runs.append(
            Run(
                label=label,
                params=a,
                tf=float(s.tf),
                objective=float(s.objective),
                status=jt.status_name(s.status),
                diag=_diagnose(prob, ctrl, a, sim, tf_floor),
                evaluations=int(s.integrations),
                iterations=int(s.iterations),
                negative_durations=neg,
                segments=ctrl.segments,
            )
        )
    return MethodResult(target, key, runs, _pick_best_gradient(runs), wall, sum(r.evaluations for r in runs))


def run_slsqp(target, ctrl, sim, a0, label, maxiter, tf_floor):
    prob = target_problem(target)
    res = solve_slsqp(prob, ctrl, a0, simulator=sim, maxiter=maxiter)
    a, neg = _clean_params(ctrl, res.params)
    run = Run(
        label=label,
        params=a,
        tf=res.tf,
        objective=res.objective,
        status="SUCCESS" if res.success else ("MAX_ITERATIONS" if "Iteration limit" in res.message else res.message),
        diag=_diagnose(prob, ctrl, a, sim, tf_floor),
        evaluations=res.evaluations,
        iterations=res.iterations,
        negative_durations=neg,
        segments=ctrl.segments,
    )
    return MethodResult(target, "slsqp", [run], 0, res.wall_time, res.evaluations, note=res.message)


# ---------------------------------------------------------------------------- (b) metaheuristics


def make_optimizer(key, population):
    return {
        "gwo": jt.GreyWolf(population=population),
        "woa": jt.Whale(population=population, decay="linear"),
        "woa2": jt.Whale(population=population, decay="quadratic"),
        "da": jt.Dragonfly(population=population),
    }[key]


def compile_population(optimizer, ctrl, sim, weights, generations, seeds):
    """A compiled `(problem, lower, upper, keys) -> PopulationResult` (one run per key,
    vmapped) on the penalty functional of any target's problem. Returns
    `(compiled, seconds to compile)`."""

    def run(prob, lower, upper, keys):
        J = ss.penalty_objective(prob, ctrl, simulator=sim, weights=weights)
        return jax.vmap(lambda k: mh.minimize(optimizer, J, lower, upper, k, max_iterations=generations))(keys)

    t0 = time.perf_counter()
    lower, upper = ss.box(ctrl, "mars")
    compiled = eqx.filter_jit(run).lower(target_problem("mars"), lower, upper, seed_keys(seeds)).compile()
    return compiled, time.perf_counter() - t0


def seed_keys(n):
    return jax.vmap(jax.random.key)(jnp.arange(n))


def run_population(key, compiled, target, ctrl, sim, seeds, population, tf_floor):
    prob = target_problem(target)
    lower, upper = ss.box(ctrl, target)
    t0 = time.perf_counter()
    res = compiled(prob, lower, upper, seed_keys(seeds))
    jax.block_until_ready(res.x)
    wall = time.perf_counter() - t0
    runs = []
    for i in range(seeds):
        a, neg = _clean_params(ctrl, res.x[i])
        runs.append(
            Run(
                label=f"seed {i}",
                params=a,
                tf=float(ctrl.tf(jnp.asarray(a))),
                objective=float(res.f[i]),
                status=jt.status_name(jax.tree.map(lambda x, i=i: x[i], res.status)),
                diag=_diagnose(prob, ctrl, a, sim, tf_floor),
                evaluations=int(res.evaluations[i]),
                iterations=int(res.iterations[i]),
                negative_durations=neg,
                segments=ctrl.segments,
            )
        )
    best = int(np.argmin([r.objective for r in runs]))
    return MethodResult(
        target,
        key,
        runs,
        best,
        wall,
        int(np.sum(res.evaluations)),
        history=np.asarray(res.history_best),
        population=population,
    )


# ---------------------------------------------------------------------------- report


def _fmt_e(x):
    return "—" if x is None or not np.isfinite(x) else f"{x:.1e}"


def _statuses(runs):
    counts = {}
    for r in runs:
        s = STATUS_SHORT.get(r.status, "?")
        counts[s] = counts.get(s, 0) + 1
    return " ".join(f"{k}{v}" for k, v in sorted(counts.items(), key=lambda kv: "SMTCNF?".index(kv[0])))


def summary_rows(results, indirect):
    header = (
        "| target | method | tf best [d] | vs indirect | tf median [d] | max abs E best (RK4 / adaptive) "
        "| feathered | flags of best | unflagged | status | evaluations | wall [s] |"
    )
    lines = [header, "|" + "---|" * 12]
    for target in indirect:
        ind = indirect[target]
        if ind is not None:
            lines.append(
                f"| {target} | {METHODS['indirect'][0]} | {ind.tf_days:.3f} | ref. | — | "
                f"{np.max(np.abs(ind.residual[:3])):.1e} (DOP853) | 0 | {'' if ind.success else 'not converged'} | — | "
                f"{'S' if ind.success else 'failed'} | {ind.starts} start(s) | {ind.wall_time:.1f} |"
            )
        for m in (r for r in results if r.target == target):
            b = m.runs[m.best]
            tfs = np.array([r.tf for r in m.runs]) * ss.DAYS_PER_UNIT
            gap = "—" if ind is None else f"{100.0 * (b.tf / ind.tf - 1.0):+.4f} %"
            flags = ", ".join(b.diag["flags"]) or "none"
            clean = sum(not r.diag["flags"] for r in m.runs)
            if METHODS[m.key][1] == "population":
                evals = f"{m.population} x {m.history.shape[1] + 1} = {b.evaluations} per seed x {len(m.runs)}"
                status = "—"
            else:
                evals = f"{b.evaluations} (best) / {m.evaluations_total} (all)"
                status = f"{_statuses(m.runs)} (best: {STATUS_SHORT.get(b.status, b.status)})"
            lines.append(
                f"| {target} | {m.label} | {b.tf * ss.DAYS_PER_UNIT:.3f} | {gap} | {np.median(tfs):.3f} | "
                f"{_fmt_e(b.diag['max_miss'])} / {_fmt_e(m.adaptive_miss)} | {b.diag['feathered_fraction']:.3f} | "
                f"{flags} | {clean}/{len(m.runs)} | {status} | {evals} | {m.wall:.1f} |"
            )
    return lines


def detail_rows(results):
    lines = [
        (
            "| target | method | run | status | tf [d] | objective | max abs E | collapsed segments | feathered "
            "| flags | iterations | evaluations |"
        ),
        "|" + "---|" * 12,
    ]
    for m in results:
        for r in m.runs:
            col = f"{r.collapsed}" + (" (h < 0 clipped)" if r.negative_durations else "")
            # a population run's SUCCESS only says that the budget was spent with a finite value
            status = "budget spent" if METHODS[m.key][1] == "population" and r.status == "SUCCESS" else r.status
            lines.append(
                f"| {m.target} | {m.label} | {r.label} | {status} | {r.tf * ss.DAYS_PER_UNIT:.3f} | "
                f"{r.objective:.6g} | {_fmt_e(r.diag['max_miss'])} | {col} | {r.diag['feathered_fraction']:.3f} | "
                f"{', '.join(r.diag['flags']) or 'none'} | {r.iterations} | {r.evaluations} |"
            )
    return lines


# ---------------------------------------------------------------------------- figures


def _trajectory(target, ctrl, a, sim):
    traj = jt.simulate(target_problem(target), ctrl, jnp.asarray(a), simulator=sim)
    return np.asarray(traj.t), np.asarray(traj.x), np.degrees(np.asarray(traj.u[:, 0]))


def _best_of(results, target, kind):
    """The best run of the first method of `kind` with an unflagged best run, else of the
    method whose best run misses least."""
    ms = [m for m in results if m.target == target and METHODS[m.key][1] == kind]
    if not ms:
        return None
    clean = [m for m in ms if not m.runs[m.best].diag["flags"]]
    if clean:
        return min(clean, key=lambda m: m.runs[m.best].tf)
    return min(ms, key=lambda m: m.runs[m.best].diag["max_miss"])


def figures(out, target, results, ind, ctrl, sim, weights):
    plt = pyplot()
    names = []
    grad, pop = _best_of(results, target, "gradient"), _best_of(results, target, "population")
    ms = [m for m in results if m.target == target]

    # transfer in the orbital plane
    fig, ax = plt.subplots(figsize=(7, 7))
    circle = np.linspace(0.0, 2.0 * np.pi, 361)
    r_f = ss.TARGET_RADII[target]
    ax.plot(np.cos(circle), np.sin(circle), color="0.55", lw=1, ls="--", label="Earth's orbit (r = 1 AU)")
    ax.plot(
        r_f * np.cos(circle),
        r_f * np.sin(circle),
        color="C3",
        lw=1,
        ls="--",
        label=f"{target.title()}'s orbit (r = {r_f:g} AU)",
    )
    if ind is not None:
        ax.plot(
            ind.x[:, 0] * np.cos(ind.x[:, 1]),
            ind.x[:, 0] * np.sin(ind.x[:, 1]),
            color="0.5",
            lw=5,
            alpha=0.4,
            label=f"indirect optimum, {ind.tf_days:.2f} d",
        )
    for m, color in ((grad, "C0"), (pop, "C1")):
        if m is None:
            continue
        b = m.runs[m.best]
        _, x, _ = _trajectory(target, ctrl, b.params, sim)
        flag = f" [{', '.join(b.diag['flags'])}]" if b.diag["flags"] else ""
        xs, ys = x[:, 0] * np.cos(x[:, 1]), x[:, 0] * np.sin(x[:, 1])
        ax.plot(xs, ys, color=color, lw=2, label=f"{m.label} ({b.label}), {b.tf * ss.DAYS_PER_UNIT:.2f} d{flag}")
        ax.plot(xs[-1], ys[-1], "o", color=color)
    ax.plot([1.0], [0.0], "s", color="0.3", label="start")
    ax.plot([0], [0], marker="*", color="orange", ms=14, ls="none", label="Sun")
    ax.set_aspect("equal")
    ax.set_xlabel("x [AU]")
    ax.set_ylabel("y [AU]")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=7)
    ax.set_title(f"Earth -> {target.title()} orbit, SaturatedSpline(P={ctrl.segments}, p={ctrl.degree})", fontsize=10)
    fig.tight_layout()
    names.append(f"{target}_orbit.png")
    fig.savefig(os.path.join(out, names[-1]), dpi=110)
    plt.close(fig)

    # pitch programs (the best run of every method)
    fig, ax = plt.subplots(figsize=(9, 5))
    if ind is not None:
        ax.plot(
            ind.t * ss.DAYS_PER_UNIT,
            np.degrees(ind.alpha),
            color="0.5",
            lw=5,
            alpha=0.4,
            label=f"indirect optimum, {ind.tf_days:.1f} d",
        )
    for i, m in enumerate(ms):
        b = m.runs[m.best]
        t, _, alpha = _trajectory(target, ctrl, b.params, sim)
        flag = f" [{', '.join(b.diag['flags'])}]" if b.diag["flags"] else ""
        style = "-" if METHODS[m.key][1] == "gradient" else "--"
        ax.plot(
            t * ss.DAYS_PER_UNIT,
            alpha,
            color=f"C{i}",
            lw=1.5,
            ls=style,
            label=f"{m.label}, {b.tf * ss.DAYS_PER_UNIT:.1f} d{flag}",
        )
    ax.axhline(90, color="0.7", lw=0.8)
    ax.axhline(-90, color="0.7", lw=0.8)
    ax.set_xlabel("time [days]")
    ax.set_ylabel("pitch angle alpha [deg]")
    ax.set_ylim(-95, 95)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(
        f"pitch programs, Earth -> {target.title()} (dashed: metaheuristics; +-90 deg: edge-on;\n"
        "a spike inside a collapsed segment has no effect on the flight)",
        fontsize=10,
    )
    fig.tight_layout()
    names.append(f"{target}_pitch.png")
    fig.savefig(os.path.join(out, names[-1]), dpi=110)
    plt.close(fig)

    # convergence of the metaheuristics
    pops = [m for m in ms if METHODS[m.key][1] == "population"]
    if pops:
        fig, ax = plt.subplots(figsize=(9, 5))
        for i, m in enumerate(pops):
            h = m.history  # (seeds, generations)
            evals = m.population * (np.arange(h.shape[1]) + 2)  # initial population + one per generation
            ax.fill_between(evals, np.min(h, axis=0), np.max(h, axis=0), color=f"C{i}", alpha=0.15)
            ax.plot(
                evals,
                np.median(h, axis=0),
                color=f"C{i}",
                lw=1.8,
                label=f"{m.label} (median, range over {h.shape[0]} seeds)",
            )
        if grad is not None:
            b = grad.runs[grad.best]
            J = weights[0] * b.tf * ss.DAYS_PER_UNIT + float(
                np.sum(np.asarray(weights[1:]) * np.asarray(b.diag["miss"]) ** 2)
            )
            ax.axhline(J, color="k", lw=1, ls="--", label=f"penalty at the {grad.label} solution ({J:.2f})")
        ax.set_yscale("log")
        ax.set_xlabel("penalty evaluations (one integration each)")
        ax.set_ylabel("best penalty value J")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
        ax.set_title(f"metaheuristics on the penalty functional, Earth -> {target.title()}", fontsize=10)
        fig.tight_layout()
        names.append(f"{target}_convergence.png")
        fig.savefig(os.path.join(out, names[-1]), dpi=110)
        plt.close(fig)
    return names


# ---------------------------------------------------------------------------- main


def main(argv=None):
    args = parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    ctrl = ss.spline_control(args.segments, args.degree)
    sim = jt.RK4(args.rk4_steps)
    weights = (ss.DEFAULT_WEIGHTS[0],) + (args.penalty_weight,) * 3
    methods = [k for k in METHODS if k in args.methods]
    total_start = time.perf_counter()
    compile_times = {}
    print(
        f"Solar-sail transfers: targets {', '.join(args.targets)}; SaturatedSpline(P={args.segments}, p={args.degree}), "
        f"RK4({args.rk4_steps}) per segment; penalty weights {weights}",
        flush=True,
    )

    # (c) the unrestricted optimum first: the floor for every restricted result
    indirect = {t: None for t in args.targets}
    if "indirect" in methods:
        for t in args.targets:
            indirect[t] = ss.solve_indirect(t)
            print(
                f"  indirect {t}: {indirect[t].tf_days:.4f} d ({'converged' if indirect[t].success else 'NOT converged'})",
                flush=True,
            )

    def floor(t):
        ind = indirect[t]
        return ind.tf * (1.0 - 1e-9) if ind is not None and ind.success else None

    results = []
    # (a) gradient solvers, every start
    grad_solvers = {
        "sqp": jt.KalmanSQP(hessian=args.sqp_hessian, globalization="line-search"),
        "search": ss.kalman_search_solver(),
    }
    n_starts = len(args.pitches) * len(args.tf_factors)
    for key in ("sqp", "search"):
        if key not in methods:
            continue
        compiled, compile_times[key] = compile_multistart(grad_solvers[key], ctrl, sim, args.max_steps, n_starts)
        for t in args.targets:
            a0s, labels = starts(t, ctrl, args.pitches, args.tf_factors)
            results.append(run_gradient(key, compiled, t, ctrl, sim, a0s, labels, floor(t)))
            m = results[-1]
            print(f"  {m.label} {t}: {_statuses(m.runs)} in {m.wall:.1f} s", flush=True)
    if "slsqp" in methods:
        t0 = time.perf_counter()
        a0s, labels = starts(args.targets[0], ctrl, [35.0], [1.0])
        jax.block_until_ready(jt.evaluate(target_problem(args.targets[0]), ctrl, a0s[0], simulator=sim).G)  # compile
        compile_times["slsqp"] = time.perf_counter() - t0
        for t in args.targets:
            a0s, labels = starts(t, ctrl, [35.0], [1.0])
            results.append(run_slsqp(t, ctrl, sim, a0s[0], labels[0], args.slsqp_maxiter, floor(t)))
            print(f"  SLSQP {t}: {results[-1].note} in {results[-1].wall:.1f} s", flush=True)

    # (b) metaheuristics, same budget each
    for key in ("gwo", "woa", "woa2", "da"):
        if key not in methods:
            continue
        opt = make_optimizer(key, args.population)
        compiled, compile_times[key] = compile_population(opt, ctrl, sim, weights, args.generations, args.seeds)
        for t in args.targets:
            results.append(run_population(key, compiled, t, ctrl, sim, args.seeds, args.population, floor(t)))
            m = results[-1]
            print(f"  {m.label} {t}: best J {m.runs[m.best].objective:.6g} in {m.wall:.1f} s", flush=True)

    # adaptive re-check of every method's best run
    checker = jt.Diffrax(rtol=1e-12, atol=1e-12)
    for m in results:
        b = m.runs[m.best]
        m.adaptive_miss = float(
            np.max(np.asarray(ss.terminal_miss(target_problem(m.target), ctrl, b.params, simulator=checker)))
        )

    summary = summary_rows(results, indirect)
    details = detail_rows(results)
    budget = args.population * (args.generations + 1)
    notes = [
        "",
        (
            f"Evaluation budget of every metaheuristic: population {args.population} x (generations "
            f"{args.generations} + 1) = {budget} penalty evaluations per seed, {args.seeds} seeds. Gradient "
            "solvers: trajectory integrations with first-order sensitivities (KalmanSQP also second-order ones "
            f"for its exact Hessians), {n_starts} starts each (SLSQP: one), at most {args.max_steps} per start."
        ),
        "Status: S success, M iteration limit, T stalled, C constraint stationary, N non-finite, F simulation "
        "failed. 'unflagged': runs without a diagnose() flag "
        f"(terminal miss > {MISS_TOL:g}, feathered > 2 %, tf below the indirect optimum). "
        "Wall times exclude compilation; compile times [s]: "
        + ", ".join(f"{METHODS[k][0]} {v:.1f}" for k, v in compile_times.items())
        + ".",
    ]
    print()
    print("\n".join(summary + notes), flush=True)

    figs = []
    for t in args.targets:
        figs += figures(args.out, t, results, indirect[t], ctrl, sim, weights)
    total = time.perf_counter() - total_start

    with open(os.path.join(args.out, "results.md"), "w") as f:
        f.write("# Solar-sail transfers (seed 003): gradient solvers vs metaheuristics\n\n")
        f.write(
            f"Command arguments: `{' '.join(argv) if argv is not None else ''}` (defaults otherwise); total {total:.0f} s.\n\n"
        )
        f.write("\n".join(summary + notes) + "\n\n## Every start and seed\n\n" + "\n".join(details) + "\n\n")
        f.write("Figures: " + ", ".join(figs) + "\n")
    record = {
        "arguments": vars(args),
        "compile_times": compile_times,
        "total_seconds": total,
        "indirect": {
            t: None
            if r is None
            else {"tf": r.tf, "tf_days": r.tf_days, "success": r.success, "residual": r.residual.tolist()}
            for t, r in indirect.items()
        },
        "results": [
            {
                "target": m.target,
                "method": m.label,
                "best": m.best,
                "wall": m.wall,
                "evaluations_total": m.evaluations_total,
                "adaptive_miss": m.adaptive_miss,
                "runs": [
                    {
                        "label": r.label,
                        "status": r.status,
                        "tf": r.tf,
                        "tf_days": r.tf * ss.DAYS_PER_UNIT,
                        "objective": r.objective,
                        "evaluations": r.evaluations,
                        "iterations": r.iterations,
                        "collapsed_segments": r.collapsed,
                        "negative_durations": r.negative_durations,
                        "diagnose": r.diag,
                        "params": r.params.tolist(),
                    }
                    for r in m.runs
                ],
                "history_best": None if m.history is None else m.history.tolist(),
            }
            for m in results
        ],
    }
    with open(os.path.join(args.out, "results.json"), "w") as f:
        json.dump(record, f, indent=1, default=float)
    print(f"\nWrote {args.out}/results.md, results.json and {len(figs)} figures in {total:.0f} s total.")
    return record


if __name__ == "__main__":
    main()
