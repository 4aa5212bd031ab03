"""Compile and warm time of the Hessian-of-the-Lagrangian kernels (issue 21).

Per kernel, on one Earth-Mars case (RK4 with 100 steps per segment, the published start,
multipliers (0.3, -1.2, 0.7)): lowering, XLA compile (in-memory caches cleared, persistent
cache off), the best of 20 warm calls and the StableHLO size. The first-order evaluation
(the simulation with forward sensitivities) is the reference; the trust region's Hessian is
forward over reverse autodiff of the plain simulation, the line search's forward over the
forward sensitivities.

Run: `python benchmarks/hessian_compile.py [--case 4]`.
"""

import argparse
import time

import jax
import jax.numpy as jnp

import jaxtraj as jt
from jaxtraj._kkt import lagrangian_gradient
from jaxtraj._sensitivity import evaluate_restricted, lagrangian_hessian

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

jax.config.update("jax_enable_compilation_cache", False)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", type=int, default=4, choices=range(1, 8))
    args = parser.parse_args()
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(args.case)
    sim, lam = jt.RK4(100), jnp.array([0.3, -1.2, 0.7])
    kernels = {
        "first-order evaluation": lambda a: evaluate_restricted(prob, ctrl, a, sim, "forward"),
        "Hessian, forward over reverse": lambda a: lagrangian_hessian(prob, ctrl, a, sim, lam),
        "Hessian, forward over forward": jax.jacfwd(
            lambda a: lagrangian_gradient(evaluate_restricted(prob, ctrl, a, sim), lam)
        ),
    }
    print(f"Earth-Mars case {args.case}, RK4(100), jax {jax.__version__}")
    print("| kernel | lower (s) | XLA compile (s) | warm (ms) | HLO lines |")
    print("|---|---:|---:|---:|---:|")
    for name, f in kernels.items():
        jax.clear_caches()
        t0 = time.perf_counter()
        lowered = jax.jit(f).lower(a0)
        t1 = time.perf_counter()
        compiled = lowered.compile()
        t2 = time.perf_counter()
        jax.block_until_ready(compiled(a0))
        warm = []
        for _ in range(20):
            t3 = time.perf_counter()
            jax.block_until_ready(compiled(a0))
            warm.append(time.perf_counter() - t3)
        lines = len(lowered.as_text().splitlines())
        print(f"| {name} | {t1 - t0:.2f} | {t2 - t1:.2f} | {1e3 * min(warm):.2f} | {lines} |")


if __name__ == "__main__":
    main()
