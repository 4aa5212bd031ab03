"""Per-call cost of the simulation kernel and of its Jacobian, and vmap throughput.

Prints three tables:
1. per-call time of x(tf) (simulation) and of x(tf) + dx(tf)/da ("forward" autodiff and the
   "unit" variational method) for Earth-Mars cases 4 and 5, RK4 (100 steps per segment) vs
   diffrax Tsit5 (rtol 1e-10): medians over ROUNDS interleaved rounds, and the median of the
   per-round Jacobian/simulation ratios;
2. vmap throughput of the full restricted evaluation (G, G_a, E, H) for batch sizes
   1, 16, 256, 1024 (case 5, RK4 100);
3. compile times.

Run: `python benchmarks/kernel.py` (x64 is on: jaxtraj turns it on at import).
"""

import os
import platform
import time

os.environ.setdefault("EQX_ON_ERROR", "nan")

import jax
import numpy as np

import jaxtraj as jt
from jaxtraj._sensitivity import evaluate_restricted, forward_jacobian, unit_jacobian
from jaxtraj._simulate import final_state

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

ROUNDS = 7


def timeit(fn, arg, *, min_time=0.3, repeats=5):
    """Best-of-`repeats` per-call seconds, each repeat running >= min_time / repeats."""
    jax.block_until_ready(fn(arg))
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            out = fn(arg)
        jax.block_until_ready(out)
        if time.perf_counter() - t0 > min_time / repeats:
            break
        n *= 2
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            out = fn(arg)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - t0) / n)
    return best


def compile_time(fn, arg):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(arg))
    return time.perf_counter() - t0


def main():
    print(
        f"# jaxtraj kernel benchmark — {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores, jax {jax.__version__}, backend {jax.default_backend()}, x64"
    )
    sims = {"RK4(100)": jt.RK4(100), "Tsit5 rtol1e-10": jt.Diffrax(rtol=1e-10, atol=1e-12)}
    compiles = []
    print(
        "\n| case | integrator | simulation [us] | sim + Jacobian, forward [us] | ratio | sim + Jacobian, unit [us] | ratio |"
    )
    print("|---|---|---:|---:|---:|---:|---:|")
    for case in (4, 5):
        prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
        for name, sim in sims.items():
            fns = {
                "sim": jax.jit(lambda a, sim=sim: final_state(prob, ctrl, a, sim)[0]),
                "forward": jax.jit(lambda a, sim=sim: forward_jacobian(prob, ctrl, a, sim)[:2]),
                "unit": jax.jit(lambda a, sim=sim: unit_jacobian(prob, ctrl, a, sim)[:2]),
            }
            for key, fn in fns.items():
                compiles.append((case, name, key, compile_time(fn, a0)))
            # Interleaved rounds, medians: the machine is shared, and a ratio is only meaningful
            # between timings taken close together.
            rounds = [{key: timeit(fn, a0, min_time=0.1) * 1e6 for key, fn in fns.items()} for _ in range(ROUNDS)]
            t = {key: float(np.median([r[key] for r in rounds])) for key in fns}
            ratio = {key: float(np.median([r[key] / r["sim"] for r in rounds])) for key in ("forward", "unit")}
            print(
                f"| {case} | {name} | {t['sim']:.0f} | {t['forward']:.0f} | {ratio['forward']:.1f}x "
                f"| {t['unit']:.0f} | {ratio['unit']:.1f}x |"
            )

    print("\n| batch N | simulation [evals/s] | sim + Jacobian + G, E, H [evals/s] | per evaluation [us] |")
    print("|---:|---:|---:|---:|")
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(5)
    sim = jt.RK4(100)
    f_sim = jax.jit(jax.vmap(lambda a: final_state(prob, ctrl, a, sim)[0]))
    f_eval = jax.jit(jax.vmap(lambda a: evaluate_restricted(prob, ctrl, a, sim)))
    for n in (1, 16, 256, 1024):
        batch = a0[None, :] + 0.01 * jax.random.normal(jax.random.PRNGKey(n), (n, a0.shape[0]))
        ts = timeit(f_sim, batch, min_time=0.5, repeats=3)
        te = timeit(f_eval, batch, min_time=0.5, repeats=3)
        print(f"| {n} | {n / ts:.0f} | {n / te:.0f} | {te / n * 1e6:.0f} |")

    print("\n| case | integrator | function | first call (compile + run) [s] |")
    print("|---|---|---|---:|")
    for case, name, key, t in compiles:
        print(f"| {case} | {name} | {key} | {t:.2f} |")


if __name__ == "__main__":
    main()
