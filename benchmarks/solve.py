"""KalmanSearch on the seven Earth-Mars thesis cases: warm solve time, first-call (compile)
time, integrations, and the share of the solve spent outside integration + Jacobians.

The share is estimated as 1 - integrations * t_eval / t_solve, with t_eval the warm time of
one jitted evaluation (simulation + forward-mode Jacobian + G, E, H) measured in the same
run. The thesis reports > 80 % of its time in integration; the target here is < 20 % for
the solver's own work.

Run: `python benchmarks/solve.py`.
"""

import os
import platform
import time

import jax

import jaxtraj as jt
from jaxtraj._sensitivity import evaluate_restricted

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

EM = jt.problems.earth_mars


def best_time(fn, repeats=3):
    jax.block_until_ready(fn())
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def main():
    print(
        f"# KalmanSearch solve benchmark — {platform.machine()}, {os.cpu_count()} cores, "
        f"jax {jax.__version__}, x64, RK4(100)"
    )
    print()
    print(
        "| case | status | integrations | first call [s] | warm solve [s] | per integration [ms] "
        "| one evaluation [ms] | share outside integration + Jacobians |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    sim = jt.RK4()
    for n in range(1, 8):
        prob, ctrl, a0 = EM.thesis_case(n)
        solver = EM.thesis_solver(n)
        t0 = time.perf_counter()
        sol = jax.block_until_ready(jt.solve(prob, ctrl, a0, solver))
        first = time.perf_counter() - t0
        warm = best_time(lambda: jt.solve(prob, ctrl, a0, solver).params)
        ev = jax.jit(lambda a: evaluate_restricted(prob, ctrl, a, sim))
        t_eval = best_time(lambda: ev(a0), repeats=20)
        k = int(sol.integrations)
        share = max(0.0, 1.0 - k * t_eval / warm)
        print(
            f"| {n} | {jt.status_name(sol.status)} | {k} | {first:.1f} | {warm:.3f} | {warm / k * 1e3:.2f} "
            f"| {t_eval * 1e3:.2f} | {share:.0%} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
