"""KalmanSearch vs KalmanSQP (BFGS and exact Hessian) vs scipy SLSQP on the seven
Earth-Mars cases, all on the same simulate/Jacobian functions (RK4, 100 steps per segment,
forward-mode sensitivities) and the same published starting vectors.

KalmanSQP is the default (`exact_iterations=3`: exact Lagrangian Hessians for the first three
iterations, then BFGS); "pure BFGS" starts BFGS from a0's exact Hessian; "exact" uses exact
Hessians throughout; "trust region" is the exact Hessian with the composite-step trust region
(`globalization="trust-region"`).

Per case and solver: final tf, max |E|, projected gradient, iterations, integrations, first
call (compile + solve) and warm solve time (best of 3), and the warm-time ratio to KalmanSQP
measured in the same run. Also writes `benchmarks/convergence_case5.png`: max |E| and
|tf - tf*| against the number of candidate evaluations for every solver on case 5 (the trust
region also spends one Hessian pass per accepted step, counted in the table's integrations).

CasADi + IPOPT (`jaxtraj.baselines.solve_ipopt`, limited-memory Hessians, on the same compiled
evaluation) is included when CasADi is installed (`pip install -e '.[bench]'`).

Run: `python benchmarks/compare_solvers.py [--cases 4 5] [--no-plot]`.
"""

import argparse
import os
import platform
import time

import jax
import numpy as np

import jaxtraj as jt
from jaxtraj._kkt import projected_gradient
from jaxtraj.baselines import solve_ipopt, solve_slsqp

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

try:
    import casadi  # noqa: F401

    HAVE_CASADI = True
except ImportError:
    HAVE_CASADI = False

EM = jt.problems.earth_mars


def _timed(fn, repeats=3):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    warm = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        warm = min(warm, time.perf_counter() - t0)
    return out, first, warm


def _row(sol):
    return {
        "status": jt.status_name(sol.status),
        "tf": float(sol.tf),
        "maxE": float(sol.max_constraint_error),
        "pg": float(sol.projected_gradient),
        "iterations": int(sol.iterations),
        "integrations": int(sol.integrations),
        "history": (
            np.asarray(sol.history.objective)[: int(sol.steps)],
            np.asarray(sol.history.max_constraint_error)[: int(sol.steps)],
        ),
    }


def run_case(case):
    prob, ctrl, a0 = EM.thesis_case(case)
    solvers = {
        "KalmanSearch": EM.thesis_solver(case),
        "KalmanSQP (default: trust region)": jt.KalmanSQP(),
        "KalmanSQP line search (BFGS)": jt.KalmanSQP(hessian="bfgs", globalization="line-search"),
        "KalmanSQP pure BFGS": jt.KalmanSQP(hessian="bfgs", exact_iterations=0, globalization="line-search"),
        "KalmanSQP exact, line search": jt.KalmanSQP(globalization="line-search"),
    }
    rows = {}
    for name, solver in solvers.items():
        sol, first, warm = _timed(lambda solver=solver: jt.solve(prob, ctrl, a0, solver))
        rows[name] = {**_row(sol), "first": first, "warm": warm}
    baselines = {"SLSQP": lambda: solve_slsqp(prob, ctrl, a0, maxiter=5000)}
    if HAVE_CASADI:
        baselines["IPOPT (CasADi)"] = lambda: solve_ipopt(prob, ctrl, a0)
    for name, run in baselines.items():
        res, first, warm = _timed(run)
        G_a_H = jt.evaluate(prob, ctrl, res.params)
        rows[name] = {
            "status": "SUCCESS" if res.success else "FAILED",
            "tf": res.tf,
            "maxE": res.max_constraint_error,
            "pg": float(projected_gradient(G_a_H.G_a, G_a_H.H)),
            "iterations": res.iterations,
            "integrations": res.evaluations,
            "first": first,
            "warm": warm,
            "history": (res.history_objective, res.history_max_constraint_error),
        }
    return rows


def plot_convergence(rows, tf_star, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, row in rows.items():
        G, maxE = row["history"]
        n = np.arange(1, len(G) + 1)
        ax1.semilogy(n, np.maximum(maxE, 1e-16), label=name)
        ax2.semilogy(n, np.maximum(np.abs(G - tf_star), 1e-16), label=name)
    ax1.set(xlabel="candidate evaluations", ylabel="max |E|", title="constraint error (case 5)")
    ax2.set(xlabel="candidate evaluations", ylabel="|tf - tf*|", title=f"objective error, tf* = {tf_star:.8f}")
    for ax in (ax1, ax2):
        ax.set_xscale("log")
        ax.grid(True, which="both", alpha=0.3)
    ax1.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--cases", type=int, nargs="*", default=list(range(1, 8)))
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args()
    print(
        f"# solver comparison — {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"jax {jax.__version__}, RK4(100), forward sensitivities, published starts"
    )
    print(
        "\n| case | solver | status | tf | max abs E | proj. gradient | iterations | integrations "
        "| first call [s] | warm [ms] | warm / KalmanSQP |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    all_rows = {}
    for case in args.cases:
        rows = run_case(case)
        all_rows[case] = rows
        ref = rows["KalmanSQP (default: trust region)"]["warm"]
        for name, r in rows.items():
            print(
                f"| {case} | {name} | {r['status']} | {r['tf']:.8f} | {r['maxE']:.1e} | {r['pg']:.1e} "
                f"| {r['iterations']} | {r['integrations']} | {r['first']:.1f} | {r['warm'] * 1e3:.1f} "
                f"| {r['warm'] / ref:.2f} |",
                flush=True,
            )
    if 5 in all_rows and not args.no_plot:
        path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "convergence_case5.png")
        tf_star = min(r["tf"] for r in all_rows[5].values() if r["maxE"] < 1e-9)
        plot_convergence(all_rows[5], tf_star, path)
        print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
