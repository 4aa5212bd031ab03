"""Time to the first answer (issue 21): what a user waits for on a new problem.

Per solver, on one Earth-Mars case (default: case 4, RK4 with 100 steps per segment, the
published start): the first call of `jt.solve` split into trace + lower, XLA compile and the
first run of the compiled program, the size of the lowered program (StableHLO lines), and
the warm solve (best of `--repeats`). The in-memory caches are cleared before each solver,
and the persistent compilation cache is off, so each first call is what a fresh process pays
(the library itself is already imported and the JAX backend initialized).

CasADi + IPOPT (optional bench extra) builds its own exact-Hessian single-shooting NLP of the
same problem in the same run: the same RK4 steps and the same piecewise-linear control with
free tf, written out again in CasADi symbols (no jaxtraj code), and solves it from the same
start. Its "first answer" is the build (symbols, `nlpsol`) plus the first solve; the table
gives each solver's first call as a ratio to it.

With `--problem NAME` (a `jt.problems.classic` gallery entry, e.g. `bryson-denham`: path
constraints, bounds, running costs) the same columns for that problem from its naive start with
the gallery's RK4(40), without a CasADi row (its NLP is written out for Earth-Mars only).

`--size` (issue 53): how the default's first call grows with the problem, the free-flying
robot (4 bounded controls, RK4(10)) on 5-30 linear pieces and a chain of bounded integrators
x_i' = u_i (|u_i| <= 1, reach x_i(1) = 1, least energy, RK4(10)) with 1-8 controls on 10
pieces: the lowered program's StableHLO lines and the trace + lower and XLA compile
seconds, with the growth per added segment and per added control (`--no-compile`: lines and
trace time only).

`--pieces` adds the default solver's kernels compiled apart (evaluation, exact Hessian, QP
step): what each costs of the whole program. `--cache` runs the default solver's first call in
three new processes that share one empty folder of `jt.enable_compilation_cache`, and three that
add `jt.enable_solve_cache`: a script run again (`--cache-only`: that table alone).

`--opt-levels 3 1 0` (issue 53): the default's first call and warm run on every gallery problem
with XLA:CPU's backend optimization at each level (one lowering, one compile per level).

Run: `python benchmarks/first_answer.py [--case 4 | --problem bryson-denham] [--repeats 3]
[--pieces] [--cache | --cache-only]` or `python benchmarks/first_answer.py --size [--no-compile]`.
"""

import argparse
import os
import platform
import sys
import time

import jax
import numpy as np

import jaxtraj as jt
from jaxtraj._driver import run
from jaxtraj._kkt import least_squares_multipliers
from jaxtraj._sensitivity import evaluate_restricted, lagrangian_hessian
from jaxtraj._simulate import final_state
from jaxtraj.problems import earth_mars

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

jax.config.update("jax_enable_compilation_cache", False)

try:
    import casadi as ca

    HAVE_CASADI = True
except ImportError:
    HAVE_CASADI = False

SOLVERS = {
    "KalmanSearch": jt.KalmanSearch(),
    "KalmanSQP (default: trust region)": jt.KalmanSQP(),
    "KalmanSQP line search (BFGS)": jt.KalmanSQP(hessian="bfgs", globalization="line-search"),
    "AugmentedLagrangian": jt.AugmentedLagrangian(),
}
MAX_STEPS = 5000  # jt.solve's default


def first_call(solver, problem, control, a0, simulator):
    """(trace + lower, compile, first run, HLO lines, solution) of one solver, caches cleared."""
    jax.clear_caches()
    t0 = time.perf_counter()
    lowered = run.lower(solver, problem, control, a0, simulator, MAX_STEPS, 0)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    sol = compiled(solver, problem, control, a0, simulator, MAX_STEPS, 0)
    jax.block_until_ready(sol.params)
    t3 = time.perf_counter()
    return t1 - t0, t2 - t1, t3 - t2, len(lowered.as_text().splitlines()), sol


def opt_levels(levels, repeats):
    """The default's first call on every gallery problem (naive start, RK4(40)) with XLA:CPU's
    backend optimization at each of `levels` (`compiler_options`, one compile per level of
    the same lowered program; XLA's default is 3): trace + lower, compile, first run, and the
    warm run of that compiled program (best of `repeats`)."""
    solver = jt.KalmanSQP()
    cols = " | ".join(f"level {v}: compile / first call / warm (s)" for v in levels)
    print(f"| problem | trace + lower (s) | {cols} | status |")
    print("|---|---:|" + "---|" * len(levels) + "---|")
    for name in jt.problems.classic.names():
        entry = jt.problems.classic.get(name)
        inputs = (solver, entry.problem, entry.control, entry.start, jt.RK4(40), MAX_STEPS, 0)
        jax.clear_caches()
        t0 = time.perf_counter()
        lowered = run.lower(*inputs)
        lower = time.perf_counter() - t0
        cells, statuses = [], set()
        for level in levels:
            t0 = time.perf_counter()
            compiled = lowered.compile(compiler_options={"xla_backend_optimization_level": level})
            t1 = time.perf_counter()
            sol = compiled(*inputs)
            jax.block_until_ready(sol.params)
            first = time.perf_counter() - t1
            best = np.inf
            for _ in range(repeats):
                t2 = time.perf_counter()
                jax.block_until_ready(compiled(*inputs).params)
                best = min(best, time.perf_counter() - t2)
            statuses.add(f"{jt.status_name(sol.status)} {int(sol.iterations)} its")
            cells.append(f"{t1 - t0:.2f} / {lower + t1 - t0 + first:.2f} / {best:.3f}")
        print(f"| {name} | {lower:.2f} | {' | '.join(cells)} | {', '.join(sorted(statuses))} |", flush=True)


def _integrators(m):
    """m bounded integrators x_i' = u_i, |u_i| <= 1, x_i(1) = 1, min 1/2 int |u|^2: the
    control count of the size study, on 10 linear pieces."""
    problem = jt.Problem(
        lambda t, x, u, args: u, np.zeros(m), lambda tf, xf, args: xf - 1.0, tuple(f"x{i}(1) = 1" for i in range(m)),
        num_controls=m, running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0,
        control_lower=[-1.0] * m, control_upper=[1.0] * m, name=f"integrators-{m}",
    )  # fmt: skip
    control = problem.parametrize(jt.controls.PiecewiseLinear(10, channels=m))
    return problem, control, np.zeros(control.num_params)


def size_study(compile_too):
    """The default's first call against the segment count (free-flying robot) and the control
    count (bounded integrators): HLO lines, trace + lower, XLA compile, and the growth per
    added segment / control between the smallest and the largest size."""
    solver, simulator = jt.KalmanSQP(), jt.RK4(10)
    robot = jt.problems.classic.free_flying_robot
    rows = [("segments", k, *(lambda e: (e.problem, e.control, e.start))(robot(k))) for k in (5, 10, 20, 30)]
    rows += [("controls", m, *_integrators(m)) for m in (1, 2, 4, 8)]
    print(
        "| study | size | parameters | HLO lines | trace + lower (s) | XLA compile (s) |\n|---|---:|---:|---:|---:|---:|"
    )
    results = {}
    for study, size, problem, control, a0 in rows:
        jax.clear_caches()
        t0 = time.perf_counter()
        lowered = run.lower(solver, problem, control, np.asarray(a0), simulator, MAX_STEPS, 0)
        t1 = time.perf_counter()
        comp = np.nan
        if compile_too:
            lowered.compile()
            comp = time.perf_counter() - t1
        lines = len(lowered.as_text().splitlines())
        results.setdefault(study, []).append((size, lines, t1 - t0, comp))
        print(f"| {study} | {size} | {np.asarray(a0).size} | {lines} | {t1 - t0:.2f} | {comp:.2f} |", flush=True)
    print("\n| per added | HLO lines | trace + lower (s) | XLA compile (s) |\n|---|---:|---:|---:|")
    for study, r in results.items():
        (s0, l0, t0, c0), (s1, l1, t1, c1) = r[0], r[-1]
        n = s1 - s0
        print(f"| {study[:-1]} | {(l1 - l0) / n:.1f} | {(t1 - t0) / n:.3f} | {(c1 - c0) / n:.3f} |")


def pieces(problem, control, a0, simulator):
    """Trace + lower and XLA compile of the default solver's kernels, each as a program of its
    own: the simulation alone (a floor: no solver compiles less), the evaluation with forward
    sensitivities, the exact Hessian of the Lagrangian
    (`_sensitivity.lagrangian_hessian`, both globalizations' kernel) and the QP step
    (`KalmanSQP.direction`, with B = I)."""
    sqp = jt.KalmanSQP()
    ev = evaluate_restricted(problem, control, a0, simulator, "forward")
    lam = least_squares_multipliers(ev, sqp.path_active)
    kernels = {
        "simulation alone (no sensitivities)": (lambda a: final_state(problem, control, a, simulator)[0], (a0,)),
        "evaluation (forward)": (lambda a: evaluate_restricted(problem, control, a, simulator, "forward"), (a0,)),
        "exact Hessian": (lambda a, lam: lagrangian_hessian(problem, control, a, simulator, lam), (a0, lam)),
        "QP step": (
            lambda ev, B, lam, a: sqp.direction(ev, B, lam, control.knots(a), jax.jacfwd(control.knots)(a), 0.5),
            (ev, np.eye(a0.shape[0]), lam, a0),
        ),
    }
    print("\n| kernel of the default solver | trace + lower (s) | XLA compile (s) | HLO lines |\n|---|---:|---:|---:|")
    for name, (fn, args) in kernels.items():
        jax.clear_caches()
        t0 = time.perf_counter()
        lowered = jax.jit(fn).lower(*args)
        t1 = time.perf_counter()
        lowered.compile()
        t2 = time.perf_counter()
        print(f"| {name} | {t1 - t0:.2f} | {t2 - t1:.2f} | {len(lowered.as_text().splitlines())} |", flush=True)


_CACHED_RUN = """
import sys, time
import jax, jaxtraj as jt
from jaxtraj.problems import earth_mars
jt.enable_compilation_cache(sys.argv[1] + "/xla")
if sys.argv[3] == "export":
    jt.enable_solve_cache(sys.argv[1] + "/export")
problem, control, a0 = earth_mars.thesis_case(int(sys.argv[2]))
t = time.perf_counter()
sol = jt.solve(problem, control, a0, simulator=jt.RK4(100))
jax.block_until_ready(sol.params)
print(time.perf_counter() - t, jt.status_name(sol.status))
"""


def cached_runs(case, runs=3):
    """The default solver's first call in `runs` new processes sharing one empty folder, with
    `jt.enable_compilation_cache` alone (a script run again loads its compiled programs from
    disk, but traces and lowers them) and with `jt.enable_solve_cache` too (it loads the
    exported solve: no trace), the two kinds of process alternating."""
    import subprocess
    import tempfile

    print("\n| process (one folder per column) | compilation cache (s) | + solve cache (s) | status |")
    print("|---|---:|---:|---|")
    with tempfile.TemporaryDirectory() as xla, tempfile.TemporaryDirectory() as both:
        for k in range(runs):
            row = []
            for folder, mode in ((xla, "xla"), (both, "export")):
                out = subprocess.run(
                    [sys.executable, "-c", _CACHED_RUN, folder, str(case), mode],
                    capture_output=True,
                    text=True,
                    check=True,
                ).stdout.split()
                row.append(out)
            first = " (empty folder)" if k == 0 else ""
            status = "/".join(sorted({r[1] for r in row}))
            print(f"| {k + 1}{first} | {float(row[0][0]):.2f} | {float(row[1][0]):.2f} | {status} |", flush=True)


def warm(solver, problem, control, a0, simulator, repeats):
    jt.solve(problem, control, a0, solver, simulator=simulator).params.block_until_ready()
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jt.solve(problem, control, a0, solver, simulator=simulator).params.block_until_ready()
        best = min(best, time.perf_counter() - t)
    return best


def casadi_nlp(control, steps):
    """The case's single-shooting NLP in CasADi with IPOPT (exact Hessian, tol 1e-10, silent):
    `(nlp, build s)`; solve with `nlp(x0=a0, lbg=0.0, ubg=0.0)`.

    Written the way CasADi is used for speed: one RK4 step as an SX function, `mapaccum` over
    the steps of a segment, the segments chained in MX."""
    c = earth_mars.CONSTANTS
    K = control.num_segments
    t0 = time.perf_counter()
    x, ua, ub, tau, k, H = (ca.SX.sym(n, 3 if n == "x" else 1) for n in ("x", "ua", "ub", "tau", "k", "H"))
    h = H / steps

    def f(t, x, tau):
        u = ua + (ub - ua) * tau  # linear on the segment
        accel = c["thrust"] / (c["m0"] - c["mdot"] * t)
        return ca.vertcat(
            x[2] ** 2 / x[1] - c["mu"] / x[1] ** 2 + accel * ca.sin(u), x[0], -x[0] * x[2] / x[1] + accel * ca.cos(u)
        )

    t, dtau = (k + tau) * H, 1.0 / steps
    k1 = f(t, x, tau)
    k2 = f(t + h / 2, x + h / 2 * k1, tau + dtau / 2)
    k3 = f(t + h / 2, x + h / 2 * k2, tau + dtau / 2)
    k4 = f(t + h, x + h * k3, tau + dtau)
    rk4 = ca.Function("rk4", [x, ua, ub, tau, k, H], [x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    segment = rk4.mapaccum("segment", steps)
    a = ca.MX.sym("a", K + 2)  # u_0..u_K, tf (PiecewiseLinear(K), equally spaced nodes)
    H_seg = a[K + 1] / K
    taus = ca.DM(np.arange(steps) / steps).T
    xk = ca.DM([0.0, 1.0, 1.0])

    def rep(v):  # one column per step
        return ca.repmat(v, 1, steps)

    for seg in range(K):
        xs = segment(xk, rep(a[seg]), rep(a[seg + 1]), taus, rep(float(seg)), rep(H_seg))
        xk = xs[:, -1]
    g = ca.vertcat(xk[0], xk[1] - c["rf"], xk[2] - np.sqrt(c["mu"] / c["rf"]))
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.tol": 1e-10}
    nlp = ca.nlpsol("nlp", "ipopt", {"x": a, "f": a[K + 1], "g": g}, opts)
    return nlp, time.perf_counter() - t0


def casadi_single_shooting(control, a0, steps):
    """Build and solve the case's single-shooting NLP (`casadi_nlp`): (build s, solve s, tf, status)."""
    nlp, build = casadi_nlp(control, steps)
    t0 = time.perf_counter()
    res = nlp(x0=np.asarray(a0), lbg=0.0, ubg=0.0)
    return build, time.perf_counter() - t0, float(res["x"][control.num_segments + 1]), nlp.stats()["return_status"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", type=int, default=4, choices=[4, 5])  # the cases with equally spaced nodes
    parser.add_argument("--problem", choices=jt.problems.classic.names(), help="a gallery problem instead")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--pieces", action="store_true", help="also the default solver's kernels, compiled apart")
    parser.add_argument(
        "--cache", action="store_true", help="also the default's first call in new processes with the caches on disk"
    )
    parser.add_argument("--cache-only", action="store_true", help="--cache without the solvers' table")
    parser.add_argument("--size", action="store_true", help="the first call against segments and controls (issue 53)")
    parser.add_argument("--no-compile", action="store_true", help="with --size: HLO lines and trace time only")
    parser.add_argument(
        "--opt-levels", type=int, nargs="+", metavar="LEVEL", help="the gallery's first call at these XLA:CPU levels"
    )
    args = parser.parse_args()
    if args.opt_levels:
        print(
            f"# the gallery, the default solver, RK4(40), naive starts, XLA:CPU backend optimization levels; "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}; "
            f"command: python {' '.join(sys.argv)}; {time.strftime('%Y-%m-%d')}\n"
        )
        opt_levels(args.opt_levels, args.repeats)
        return
    if args.size:
        print(
            f"# size study, the default solver, RK4(10); {platform.processor() or platform.machine()}, "
            f"{os.cpu_count()} cores, jax {jax.__version__}; command: python {' '.join(sys.argv)}; "
            f"{time.strftime('%Y-%m-%d')}\n"
        )
        size_study(not args.no_compile)
        return
    if args.cache_only:
        print(f"# Earth-Mars case {args.case}, RK4(100), the default; {platform.processor() or platform.machine()}, ")
        print(
            f"# {os.cpu_count()} cores, jax {jax.__version__}; command: python {' '.join(sys.argv)}; {time.strftime('%Y-%m-%d')}"
        )
        cached_runs(args.case, runs=4)
        return
    if args.problem:
        entry = jt.problems.classic.get(args.problem)
        problem, control, a0, simulator = entry.problem, entry.control, entry.start, jt.RK4(40)
        title = f"{args.problem} from its naive start, RK4(40)"
    else:
        problem, control, a0 = earth_mars.thesis_case(args.case)
        simulator = jt.RK4(100)
        title = f"Earth-Mars case {args.case}, RK4(100)"
    print(
        f"# {title}, first call of jt.solve per solver (caches cleared); "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}; "
        f"command: python {' '.join(sys.argv)}; {time.strftime('%Y-%m-%d')}"
    )
    reference = None
    if HAVE_CASADI and not args.problem:
        build, solve, tf, status = casadi_single_shooting(control, a0, simulator.steps)
        reference = build + solve
        print(
            f"# CasADi {ca.__version__} + IPOPT single shooting: build {build:.2f} s, first solve {solve:.2f} s, "
            f"tf {tf:.8f} ({status})"
        )
    print()
    print(
        "| solver | first call (s) | trace + lower (s) | XLA compile (s) | first run (s) | HLO lines | warm (s) "
        "| first / CasADi | status | objective |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|---|")
    if reference is not None:
        print(
            f"| CasADi + IPOPT | {reference:.2f} | {build:.2f} (build) | | {solve:.2f} | | | 1.00 | {status} | "
            f"{tf:.8f} |"
        )
    for name, solver in SOLVERS.items():
        lower, comp, first, lines, sol = first_call(solver, problem, control, a0, simulator)
        total = lower + comp + first
        w = warm(solver, problem, control, a0, simulator, args.repeats)
        ratio = f"{total / reference:.2f}" if reference else ""
        print(
            f"| {name} | {total:.2f} | {lower:.2f} | {comp:.2f} | {first:.3f} | {lines} | {w:.3f} | {ratio} "
            f"| {jt.status_name(sol.status)} | {float(sol.objective):.8f} |",
            flush=True,
        )
    if args.pieces:
        pieces(problem, control, a0, simulator)
    if args.cache and not args.problem:
        cached_runs(args.case)


if __name__ == "__main__":
    main()
