"""The classic-problem gallery (`jt.problems.classic`): every problem from its naive start
with every solver, against the problem's independent reference optimum.

Per problem and solver: status, objective, gap to the reference (objective - reference; the
continuous optimum, so a restricted control may sit above it by up to the problem's `gap`),
whether the run is "at the reference" (SUCCESS and -tol <= gap <= the problem's `gap` + tol,
tol = 1e-6 (1 + |reference|)), iterations, first call (compile + solve), warm time (best of
2), and the warm time per iteration in evaluations of the values and Jacobian (`jt.evaluate`,
jitted, warm): what an iteration costs beyond its one or two evaluations. A SUCCESS outside that band is flagged `FALSE-SUCCESS?`: a SUCCESS must be a local
optimum of the restricted problem, so it should be checked against the others.

Solvers: KalmanSQP (default: exact Hessian, trust region; `line-search`: BFGS and the merit line
search, the default until 2026-12-04), KalmanSearch, AugmentedLagrangian, SciPy SLSQP and, when CasADi
is installed, IPOPT (both on the same compiled evaluation). A solver that cannot honor a
problem's constraints raises; the table says `refused`.

With `--random N`, every solver also runs the same N random starts per problem
(`jt.random_starts` around the naive start, `--spread`, key 0, draws that the solves'
simulator cannot integrate replaced by further draws; jaxtraj's solvers by `jt.solve_batch`
with at most `--max-steps` steps, the baselines one start after another with their own
iteration limits) and a second table counts them: at the reference, SUCCESS elsewhere that
passes an independent KKT check (`jt.kkt_report` with the solver's own tolerances, `ctol` or
`e_a` and `acceptable_gtol` or `gtol`, for the baselines the default KalmanSQP's, loosened
tenfold: another local optimum), false SUCCESS (fails it), and the other statuses.

Run: `python benchmarks/gallery.py [--problems lq bryson-denham] [--solvers default slsqp]
[--random 32 --spread 0.5]`.
"""

import argparse
import os
import platform
import time

import jax
import numpy as np

import jaxtraj as jt
from jaxtraj.baselines import solve_ipopt, solve_slsqp

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

try:
    import casadi  # noqa: F401

    HAVE_CASADI = True
except ImportError:
    HAVE_CASADI = False

CLASSIC = jt.problems.classic
SIM = jt.RK4(40)


def _run_jaxtraj(solver):
    def run(entry):
        sol = jt.solve(entry.problem, entry.control, entry.start, solver, simulator=SIM)
        return jt.status_name(sol.status), float(sol.objective), int(sol.iterations)

    run.solver = solver
    return run


def _at_reference(entry, status, J):
    """SUCCESS and -tol <= J - reference <= gap + tol (module docs)."""
    tol = 1e-6 * (1 + abs(entry.reference))  # the solvers' own accuracy (KalmanSearch's is looser)
    return status == "SUCCESS" and -tol <= J - entry.reference <= entry.gap + tol


def draw_starts(entry, n, spread):
    """The `n` random starts of a problem, the same for every solver."""
    return jt.random_starts(
        entry.problem, entry.control, jax.random.key(0), n, around=entry.start, spread=spread, simulator=SIM
    )


def random_starts(entry, run, starts, max_steps):
    """Counts over the random `starts`: (at the reference, SUCCESS at another KKT point,
    false SUCCESS (the KKT check fails), {other status: count}). jaxtraj's solvers run them as
    one `jt.solve_batch`, the baselines one after another."""
    if hasattr(run, "solver"):
        sols = jt.solve_batch(
            entry.problem,
            entry.control,
            starts,
            run.solver,
            simulator=SIM,
            max_steps=max_steps,
            progress=False,
            history=False,
        )
        names, J, params = jt.status_name(sols.status), np.asarray(sols.objective), sols.params
        solver = run.solver
        ctol = getattr(solver, "ctol", getattr(solver, "e_a", 1e-9))
        gtol = getattr(solver, "acceptable_gtol", getattr(solver, "gtol", 1e-6))
    else:
        results = [run.fn(entry.problem, entry.control, a, simulator=SIM) for a in starts]
        names = np.asarray(["SUCCESS" if r.success else "FAILED" for r in results])
        J, params = np.asarray([r.objective for r in results]), [r.params for r in results]
        ctol, gtol = 1e-9, 1e-6  # the default KalmanSQP's: what "another local optimum" must pass
    at = [_at_reference(entry, s, j) for s, j in zip(names, J)]
    elsewhere = [i for i, s in enumerate(names) if s == "SUCCESS" and not at[i]]
    # a SUCCESS off the reference is another local optimum only if it passes an independent
    # KKT check (`jt.kkt_report`, the solver's own tolerances loosened tenfold); else it is false
    false = sum(
        not jt.kkt_report(entry.problem, entry.control, params[i], simulator=SIM).satisfied(10 * ctol, 10 * gtol)
        for i in elsewhere
    )
    others = {k: int(np.sum(names == k)) for k in sorted(set(names) - {"SUCCESS"})}
    return sum(at), len(elsewhere) - false, false, others


def _run_baseline(fn):
    def run(entry):
        res = fn(entry.problem, entry.control, entry.start, simulator=SIM)
        return ("SUCCESS" if res.success else "FAILED"), float(res.objective), int(res.iterations)

    run.fn = fn
    return run


SOLVERS = {
    "default": _run_jaxtraj(None),  # KalmanSQP(): exact Hessian, trust region
    # the default until 2026-12-04: BFGS and the merit line search
    "line-search": _run_jaxtraj(jt.KalmanSQP(hessian="bfgs", globalization="line-search")),
    # feasibility first wherever the normal step is cut / never (the default threshold: 0.1)
    "trust-region-feasibility-first": _run_jaxtraj(jt.KalmanSQP(globalization=jt.TrustRegion(feasibility_first=0.0))),
    "trust-region-composite": _run_jaxtraj(jt.KalmanSQP(globalization=jt.TrustRegion(feasibility_first=float("inf")))),
    "kalman-search": _run_jaxtraj(jt.KalmanSearch()),
    "augmented-lagrangian": _run_jaxtraj(jt.AugmentedLagrangian()),
    "slsqp": _run_baseline(solve_slsqp),
}
if HAVE_CASADI:
    SOLVERS["ipopt"] = _run_baseline(solve_ipopt)


def measure(entry, run):
    t0 = time.perf_counter()
    try:
        status, J, its = run(entry)
    except ValueError as err:
        return {"status": "refused", "why": str(err).split(".")[0][:60]}
    first = time.perf_counter() - t0
    warm = float("inf")
    for _ in range(2):
        t0 = time.perf_counter()
        run(entry)
        warm = min(warm, time.perf_counter() - t0)
    gap = J - entry.reference
    at = _at_reference(entry, status, J)
    if status == "SUCCESS" and not at:
        status = "FALSE-SUCCESS?"
    return {"status": status, "J": J, "gap": gap, "at": at, "its": its, "first": first, "warm": warm}


def jacobian_seconds(entry):
    """Warm seconds of one evaluation of the values and the forward-mode Jacobian at the
    start (jitted, best of 5): the unit of the per-iteration cost (issue 49)."""
    evaluate = jax.jit(lambda a: jt.evaluate(entry.problem, entry.control, a, simulator=SIM))
    jax.block_until_ready(evaluate(entry.start))
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(evaluate(entry.start))
        best = min(best, time.perf_counter() - t0)
    return best


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--problems", nargs="*", default=list(CLASSIC.names()))
    parser.add_argument("--solvers", nargs="*", default=list(SOLVERS))
    parser.add_argument("--random", type=int, default=0, help="random starts per problem (every solver)")
    parser.add_argument("--spread", type=float, default=0.5, help="jt.random_starts spread")
    parser.add_argument("--max-steps", type=int, default=2000, help="steps per random start")
    parser.add_argument("--no-naive", action="store_true", help="only the random starts")
    args = parser.parse_args()
    print(f"# gallery: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__}")
    print(f"# {time.strftime('%Y-%m-%d')}; RK4(40) per segment; naive starts")
    header = (
        "| problem | reference | solver | status | objective | gap | at ref | its | first (s) | warm (s) | "
        "warm / its / Jacobian |"
    )
    if not args.no_naive:
        print(header)
        print("|" + "---|" * (header.count("|") - 1))
    tally = {s: 0 for s in args.solvers}
    for name in args.problems if not args.no_naive else ():
        entry = CLASSIC.get(name)
        jacobian = jacobian_seconds(entry)
        for sname in args.solvers:
            r = measure(entry, SOLVERS[sname])
            if r["status"] == "refused":
                print(f"| {name} | {entry.reference:.7g} | {sname} | refused | | | | | | | |")
                continue
            tally[sname] += bool(r["at"])
            print(
                f"| {name} | {entry.reference:.7g} | {sname} | {r['status']} | {r['J']:.9g} | {r['gap']:.2e} | "
                f"{'yes' if r['at'] else 'no'} | {r['its']} | {r['first']:.2f} | {r['warm']:.3f} | "
                f"{r['warm'] / max(r['its'], 1) / jacobian:.1f} |",
                flush=True,
            )
    n = len(args.problems)
    if not args.no_naive:
        print("\nat the reference from the naive start: " + ", ".join(f"{s} {k}/{n}" for s, k in tally.items()))
    if args.random:
        print(f"\n{args.random} random starts (spread {args.spread}, key 0, max_steps {args.max_steps}):\n")
        print(
            "| problem | solver | at ref | SUCCESS at another KKT point | false SUCCESS | other statuses | time (s) |"
        )
        print("|---|---|---:|---:|---:|---|---:|")
        for name in args.problems:
            entry = CLASSIC.get(name)
            starts = draw_starts(entry, args.random, args.spread)
            for sname in args.solvers:
                t0 = time.perf_counter()
                try:
                    at, elsewhere, false, others = random_starts(entry, SOLVERS[sname], starts, args.max_steps)
                except ValueError:
                    print(f"| {name} | {sname} | refused | | | | |")
                    continue
                rest = ", ".join(f"{k} {v}" for k, v in others.items())
                print(
                    f"| {name} | {sname} | {at}/{args.random} | {elsewhere} | {false} | {rest} | "
                    f"{time.perf_counter() - t0:.1f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
