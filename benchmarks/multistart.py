"""`jt.multistart` from a naive guess: the solar sail to Mercury of issue 20.

Problem: `jt.problems.solar_sail.problem("mercury", a0=0.1686)`, `SaturatedSpline(10, 1)`
with free durations, RK4(40) per segment. Naive guess: equal durations summing to tf = 5
(canonical units) and a constant pitch of -35 deg (inward). The lower bound of every restricted
control: Pontryagin's minimum time of the unrestricted one (`solar_sail.solve_indirect`,
4.5759 = 266.005 d; issue 20's 264.46 d lies below it, so it is no transfer).
Per solver and spread: how many of `--starts` random starts (key 0) end SUCCESS, the distinct
optima among them (objectives within 1e-6 (1 + |G|) are one), the best transfer time in days
and its gap to the unrestricted optimum, how many starts reach it within 0.01 d, and the wall
time of the batch (compile included).

Run: `python benchmarks/multistart.py [--starts 32] [--spreads 0.1 0.3 0.5]
[--solvers default kalman-search]`.
"""

import argparse
import math
import os
import platform
import time

import jax
import numpy as np

import jaxtraj as jt

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

SAIL = jt.problems.solar_sail
SOLVERS = {
    "default": jt.KalmanSQP(),  # exact Hessian, trust region
    "line-search": jt.KalmanSQP(hessian="bfgs", globalization="line-search"),  # the default until 2026-12-04
    "kalman-search": SAIL.kalman_search_solver(),
    # feasibility first wherever the normal step is cut / never (the default threshold: 0.1)
    "trust-region-feasibility-first": jt.KalmanSQP(globalization=jt.TrustRegion(feasibility_first=0.0)),
    "trust-region-composite": jt.KalmanSQP(globalization=jt.TrustRegion(feasibility_first=float("inf"))),
    "augmented-lagrangian": jt.AugmentedLagrangian(),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--starts", type=int, default=32)
    parser.add_argument("--spreads", type=float, nargs="*", default=[0.1, 0.3, 0.5])
    parser.add_argument("--solvers", nargs="*", default=["default"], choices=list(SOLVERS))
    parser.add_argument("--max-steps", type=int, default=1000)
    args = parser.parse_args()
    prob = SAIL.problem("mercury", a0=0.1686)
    ctrl = SAIL.spline_control(10, 1)
    around = ctrl.initial_guess(5.0, math.radians(-35.0), math.radians(-35.0))
    days = SAIL.DAYS_PER_UNIT
    bound = SAIL.solve_indirect("mercury", a0=0.1686).tf_days
    print(f"# multistart: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__}")
    print(f"# {time.strftime('%Y-%m-%d')}; sail to Mercury, {ctrl!r}, RK4(40), {args.starts} starts, key 0")
    print(f"# unrestricted optimum (solve_indirect): {bound:.3f} d\n")
    print(
        "| solver | spread | SUCCESS | distinct optima | best tf [d] | above the unrestricted | starts at the best | time (s) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in args.solvers:
        for spread in args.spreads:
            t0 = time.perf_counter()
            res = jt.multistart(
                prob,
                ctrl,
                jax.random.key(0),
                args.starts,
                around=around,
                spread=spread,
                solver=SOLVERS[name],
                simulator=jt.RK4(40),
                max_steps=args.max_steps,
                progress=False,
                history=False,
            )
            wall = time.perf_counter() - t0
            J = np.asarray(res.solutions.objective)[np.asarray(res.success)] * days
            best = float(J.min()) if J.size else math.nan
            print(
                f"| {name} | {spread:g} | {int(np.sum(res.success))}/{args.starts} | {len(res.optima)} | "
                f"{best:.3f} | {(best - bound) / bound:.1e} | {int(np.sum(J <= best + 0.01))} | {wall:.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
