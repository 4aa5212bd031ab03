"""The cost of a derivative of a solution (issue 50): Earth-Mars case 4 (`KalmanSQP`, RK4(100)),
the minimum time tf* as a function of the problem's 8 numbers (`args`: mu, m0, mdot, thrust,
rf; the initial state x0: r, u, v).

Rows, each the median of `--repeat` warm calls of one compiled program:

* a warm solve from the published start (the value alone);
* value and gradient (`jax.value_and_grad`: the solve, then one reverse pass of the implicit
  function theorem), and a JVP along one direction (`jax.jvp`): their extra over the solve;
* the whole Jacobian (8 numbers) by the implicit function theorem, against central finite
  differences of re-solves (16 solves) warm-started at the optimum (the cheapest a user
  without derivatives could run) and from the published start, with the largest relative
  difference between the two.

Run: `python benchmarks/derivatives.py [--repeat 7]`.
"""

import argparse
import platform
import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import jaxtraj as jt

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)


def timed(fn, repeat):
    jax.block_until_ready(fn())  # compile
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    opts = parser.parse_args(argv)
    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    theta0 = {"args": prob.args, "x0": prob.x0}

    def tf(theta, start):
        p = eqx.tree_at(lambda p: (p.args, p.x0), prob, (theta["args"], theta["x0"]))
        return jt.solve(p, ctrl, start).tf

    optimum = jt.solve(prob, ctrl, a0).params
    value = jax.jit(tf)
    grad = jax.jit(jax.value_and_grad(tf))
    direction = jax.tree.map(jnp.ones_like, theta0)
    jvp = jax.jit(lambda th, s: jax.jvp(lambda t: tf(t, s), (th,), (direction,)))
    flat, unflatten = ravel_pytree(theta0)

    def fd(start):
        h = 1e-6 * np.maximum(np.abs(np.asarray(flat)), 1.0)
        cols = []
        for i in range(flat.size):
            e = np.zeros(flat.size)
            e[i] = h[i]
            up, down = value(unflatten(flat + e), start), value(unflatten(flat - e), start)
            cols.append((up - down) / (2 * h[i]))
        return jnp.stack(cols)

    rows = {
        "warm solve (value)": timed(lambda: value(theta0, a0), opts.repeat),
        "value and gradient (8 numbers)": timed(lambda: grad(theta0, a0), opts.repeat),
        "value and JVP (one direction)": timed(lambda: jvp(theta0, a0), opts.repeat),
        "gradient by central differences (16 re-solves from the optimum)": timed(lambda: fd(optimum), opts.repeat),
        "gradient by central differences (16 re-solves from the start)": timed(lambda: fd(a0), opts.repeat),
    }
    solve = rows["warm solve (value)"]
    ift = np.asarray(ravel_pytree(grad(theta0, a0)[1])[0])
    diff = np.max(np.abs(ift - np.asarray(fd(optimum))) / np.maximum(np.abs(ift), 1e-12))
    print(
        f"Earth-Mars case 4, KalmanSQP, RK4(100); {platform.processor() or platform.machine()}, jax {jax.__version__}"
    )
    print("| what | time [ms] | / warm solve | derivative's own cost / warm solve |")
    print("|---|---:|---:|---:|")
    for name, t in rows.items():
        own = f"{(t - solve) / solve:.2f}" if name.startswith("value and") else ""
        print(f"| {name} | {1e3 * t:.1f} | {t / solve:.2f} | {own} |")
    ift_time = rows["value and gradient (8 numbers)"]
    print()
    for start in ("optimum", "start"):
        fd_time = rows[f"gradient by central differences (16 re-solves from the {start})"]
        print(f"gradient by the IFT vs central differences from the {start}: {fd_time / ift_time:.1f}x faster")
    # both need the optimum first: the derivative's own cost against the differences', and the
    # whole (solve + derivative) against (solve + differences warm-started at its optimum)
    fd_warm = rows["gradient by central differences (16 re-solves from the optimum)"]
    print(f"the derivative's own cost vs the warm differences: {fd_warm / (ift_time - solve):.1f}x less")
    print(f"solve + gradient vs solve + warm differences: {(solve + fd_warm) / ift_time:.1f}x faster")
    print(f"largest relative difference between the IFT and the differences: {diff:.1e}")


if __name__ == "__main__":
    main()
