"""Monte Carlo throughput: `jaxtraj.feedback.monte_carlo` runs per second on Earth-Mars case 5.

The nominal is the KalmanSQP optimum of case 5 (PiecewiseLinear(7), RK4(100): 700 control
samples per run, 2,800 dynamics evaluations); the closed loop uses the sampled LQR gains of
`examples/closed_loop.py` and 1 % thrust-magnitude and 1 degree pointing errors drawn per
sample. Each row is one jitted, vmapped call for N runs: "first call" includes compilation;
"warm" is the best of `--repeat` calls (each with a fresh key, `jax.block_until_ready`).
Open-loop rows (no gains) are given for comparison; `--trajectories` adds rows with
`return_trajectories=True` (percentile bands of all states at 101 of the 701 sample times,
`dispersion_stride=7`, as in examples/closed_loop.py).

Run: `python benchmarks/monte_carlo.py [--n 1000 10000] [--repeat 3] [--trajectories]`.
"""

import argparse
import os
import platform
import time

import jax
import numpy as np

import jaxtraj as jt
from jaxtraj import feedback as fb

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)


def machine():
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    dev = jax.devices()[0]
    return (
        f"{cpu}, {os.cpu_count()} cores visible, {platform.system()} {platform.release()}; "
        f"jax {jax.__version__} on {dev.platform} ({dev.device_kind}), float64"
    )


def run(prob, ctrl, a, seed, n, kw):
    return fb.monte_carlo(prob, ctrl, a, jax.random.key(seed), n, **kw)


def timed(fn, *args):
    """Wall time of fn(*args) including `jax.block_until_ready`."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[1000, 10000])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--trajectories", action="store_true")
    args = p.parse_args(argv)

    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(5)
    sol = jt.solve(prob, ctrl, a0, jt.KalmanSQP())
    a = sol.params
    errors = fb.ThrustErrors(0.01, 1.0)
    lin = fb.linearize(prob, ctrl, a, execution=errors)
    gains = fb.tracking_lqr(lin, *fb.bryson_weights(lin, 1e-3, 0.05, 1e-4))

    print(f"# Monte Carlo throughput, Earth-Mars case 5 — {machine()}")
    print()
    print("| loop | trajectories | N | first call [s] | warm [s] | runs/s | us per run-sample |")
    print("|---|---|---:|---:|---:|---:|---:|")
    configs = [("closed", False), ("open", False)]
    if args.trajectories:
        configs += [("closed", True)]
    samples = lin.dt.shape[0]
    for loop, traj in configs:
        for n in args.n:
            kw = {"execution": errors, "return_trajectories": traj, "dispersion_stride": 7}
            if loop == "closed":
                kw["gains"] = gains
            times = [timed(run, prob, ctrl, a, s, n, kw) for s in range(args.repeat + 1)]
            first, warm = times[0], min(times[1:])
            print(
                f"| {loop} | {'bands (101 times)' if traj else 'no'} | {n:,} | {first:.2f} | {warm:.3f} | "
                f"{n / warm:,.0f} | {1e6 * warm / (n * samples):.3f} |",
                flush=True,
            )
    r = fb.monte_carlo(prob, ctrl, a, jax.random.key(0), args.n[-1], gains=gains, execution=errors)
    print()
    print(
        f"Sanity (closed loop, N = {args.n[-1]:,}): terminal std "
        f"{np.array2string(np.asarray(r.terminal_std), precision=3)}, failed {int(r.num_failed)}."
    )


if __name__ == "__main__":
    main()
