"""Batched solves: `jt.solve_batch` against a Python loop over single jitted `jt.solve` calls
(Earth-Mars case 4, RK4(100), KalmanSearch, random starts around the published one), the
scaling with the number of host devices, where the time goes under vmap, and peak memory
for N = 10,000 with chunking.

Every throughput is measured in the same run as the loop it is compared with (ratios; the
machine is shared). The loop is timed on the first min(N, 64) starts and extrapolated to N
(the starts are i.i.d., so the per-start mean carries over); solve_batch is timed on all N.
Compilation is excluded from both (warm-up calls: for solve_batch on N NaN starts, which have
the same shapes and end at once).

Run: `python benchmarks/batch.py [memory] [throughput] [where] [scaling] [solvers] [default]
[accelerator] [vmapped]` (the first four by default, about 10 minutes on the 2-core sandbox);
`--skip-memory` leaves out the N = 10,000 runs; `solvers` compares every solver under solve_batch
(N = 256); `vmapped` runs every solver vmapped against a loop of single solves on problems with
and without path constraints (N = 8); `default` runs solve_batch as a
user calls it (no device setup, default solver) against loops of single solves and of CasADi
+ IPOPT solves; `accelerator` runs solve_batch with its default lanes on the default device (a
GPU where there is one) for N = 256, 1024, 4096 against a loop of single solves there.
"""

import os
import platform
import resource
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxtraj as jt
from jaxtraj import _batch
from jaxtraj._batch import random_starts, solve_batch
from jaxtraj._sensitivity import evaluate_restricted

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

PROB, CTRL, A0 = jt.problems.earth_mars.thesis_case(4)
SOLVER = jt.KalmanSearch()
SPREAD = 0.1
LOOP_SUBSET = 64
SOLVERS = {
    "KalmanSearch (published tuning)": SOLVER,
    "KalmanSQP (default: trust region)": jt.KalmanSQP(),
    "KalmanSQP line search (BFGS)": jt.KalmanSQP(hessian="bfgs", globalization="line-search"),
    "AugmentedLagrangian": jt.AugmentedLagrangian(),
}


def starts(n, seed=0):
    return np.asarray(random_starts(PROB, CTRL, jax.random.key(seed), n, A0, SPREAD))


def loop_rate(a0s, solver=SOLVER):
    """Solves per second of a Python loop over jitted single solves (compiled beforehand)."""
    jax.block_until_ready(jt.solve(PROB, CTRL, a0s[0], solver).params)
    t0 = time.perf_counter()
    for a in a0s:
        jax.block_until_ready(jt.solve(PROB, CTRL, a, solver).params)
    return len(a0s) / (time.perf_counter() - t0)


def batch_rate(a0s, solver=SOLVER, **kw):
    """Solves per second of solve_batch (compiled beforehand on NaN starts)."""
    solve_batch(PROB, CTRL, np.full_like(a0s, np.nan), solver, progress=False, **kw)
    t0 = time.perf_counter()
    sols = solve_batch(PROB, CTRL, a0s, solver, progress=False, **kw)
    return len(a0s) / (time.perf_counter() - t0), sols


def throughput():
    print("## solve_batch vs a Python loop of jitted single solves (1 device)")
    print()
    print(
        f"Loop timed on the first min(N, {LOOP_SUBSET}) starts and extrapolated. `lanes` = starts vmapped "
        "together per device (default on CPU: 1, a compiled loop of single solves)."
    )
    print()
    print(
        "| N | loop [solves/s] | solve_batch default (lanes=1) [solves/s] | ratio | lanes=8 | ratio "
        "| lanes=32 | ratio | lanes=64 | ratio | success | mean / max steps |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in (1, 16, 256, 1024):
        a0s = starts(n)
        loop = loop_rate(a0s[:LOOP_SUBSET])
        default, sols = batch_rate(a0s)
        cells = [f"{default:.1f}", f"{default / loop:.2f}x"]
        for lanes in (8, 32, 64):
            if lanes > n:
                cells += ["-", "-"]
                continue
            rate, _ = batch_rate(a0s, lanes=lanes)
            cells += [f"{rate:.1f}", f"{rate / loop:.2f}x"]
        ok = np.asarray(sols.status == jt.Status.SUCCESS)
        steps = np.asarray(sols.steps)
        print(
            f"| {n} | {loop:.1f}{' (extrapolated)' if n > LOOP_SUBSET else ''} | "
            + " | ".join(cells)
            + f" | {ok.mean():.0%} | {steps.mean():.0f} / {steps.max()} |",
            flush=True,
        )
    print()


def default(n=256, subset=32):
    """`jt.solve_batch` as a user calls it: no device setup, the default solver; against a
    loop of single solves and a loop of CasADi + IPOPT solves (its own single-shooting NLP,
    exact Hessian, built once; `first_answer.casadi_nlp`) on the same starts."""
    devices = len(jax.devices())
    print(
        f"## solve_batch with no configuration (N = {n}, default solver, {devices} CPU device(s) after "
        f"`import jaxtraj`; loops timed on {subset} starts)"
    )
    print()
    a0s = starts(n)
    solver = jt.KalmanSQP()
    loop = loop_rate(a0s[:subset], solver)
    rate, sols = batch_rate(a0s, solver)
    ok = np.asarray(sols.status == jt.Status.SUCCESS)
    rows = [("loop of jt.solve", loop), (f"jt.solve_batch ({devices} devices)", rate)]
    try:
        from first_answer import casadi_nlp

        nlp, _ = casadi_nlp(CTRL, 100)
        nlp(x0=np.asarray(a0s[0]), lbg=0.0, ubg=0.0)
        t0, solved = time.perf_counter(), 0
        for a in a0s[:subset]:
            nlp(x0=np.asarray(a), lbg=0.0, ubg=0.0)
            solved += bool(nlp.stats()["success"])
        rows.append((f"loop of CasADi + IPOPT ({solved}/{subset} solved)", subset / (time.perf_counter() - t0)))
    except ImportError:
        pass
    print("| run | solves/s | solve_batch / this |")
    print("|---|---:|---:|")
    for name, r in rows:
        print(f"| {name} | {r:.1f} | {rate / r:.2f}x |")
    print(f"\nsolve_batch: {ok.mean():.0%} SUCCESS\n", flush=True)


def solvers(n=256, subset=32):
    print(f"## The solvers under solve_batch (N = {n}, 1 device; loop timed on {subset} starts)")
    print()
    print("| solver | loop [solves/s] | lanes=1 | ratio | lanes=32 | ratio | success |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    a0s = starts(n)
    for name, solver in SOLVERS.items():
        loop = loop_rate(a0s[:subset], solver)
        cells, ok = [], []
        for lanes in (1, 32):
            rate, sols = batch_rate(a0s, solver, lanes=lanes)
            cells += [f"{rate:.1f}", f"{rate / loop:.2f}x"]
            ok.append(np.mean(np.asarray(sols.status == jt.Status.SUCCESS)))
        print(f"| {name} | {loop:.1f} | " + " | ".join(cells) + f" | {min(ok):.0%} |", flush=True)
    print()


def vmapped(n=8):
    """Every solver vmapped (`solve_batch(lanes=n)` on one device) against a loop of single
    solves on the same n starts, on a problem without path constraints (Earth-Mars case 4) and
    two with them (the attitude slew's keep-out cone, Bryson-Denham's state bound): a lane's
    data-dependent work (a Hessian, a fallback test) must not cost every lane every step
    (issue 21). "tail": n x the most steps of a start / the steps of all n (a vmapped group
    iterates until its slowest start is done; a longer queue of starts amortizes it); "per
    step": (vmapped / loop) / tail, the cost of a vmapped lane-step against a single step."""
    from jaxtraj.problems import attitude

    entry = jt.problems.classic.get("bryson-denham")
    problems = [
        ("Earth-Mars case 4, RK4(100)", PROB, CTRL, A0, jt.RK4(100)),
        ("attitude slew, 50 deg cone, RK4(20)", *attitude.case("quaternion", 8), jt.RK4(20)),
        ("Bryson-Denham, x <= 1/9, RK4(40)", entry.problem, entry.control, entry.start, jt.RK4(40)),
    ]
    one = [jax.devices()[0]]
    print(f"## Every solver vmapped: solve_batch(lanes={n}) on one device against a loop of single solves")
    print()
    print(
        "| problem | solver | loop (s) | vmapped (s) | vmapped / loop | tail | per step | iterations loop / vmapped "
        "| SUCCESS loop / vmapped |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---|---|")
    for title, prob, ctrl, a0, sim in problems:
        a0s = np.asarray(random_starts(prob, ctrl, jax.random.key(0), n, a0, SPREAD, simulator=sim))
        for name, solver in SOLVERS.items():
            jax.block_until_ready(jt.solve(prob, ctrl, a0s[0], solver, simulator=sim).params)
            t0 = time.perf_counter()
            singles = [jt.solve(prob, ctrl, a, solver, simulator=sim) for a in a0s]
            jax.block_until_ready(singles[-1].params)
            loop = time.perf_counter() - t0
            kw = dict(simulator=sim, devices=one, progress=False, history=False, lanes=n)
            solve_batch(prob, ctrl, np.full_like(a0s, np.nan), solver, **kw)
            t0 = time.perf_counter()
            sols = solve_batch(prob, ctrl, a0s, solver, **kw)
            batch = time.perf_counter() - t0
            its = (np.mean([int(s.iterations) for s in singles]), np.mean(np.asarray(sols.iterations)))
            steps = np.array([int(s.steps) for s in singles])
            tail = n * steps.max() / steps.sum()  # a vmapped group runs until its slowest lane is done
            ok = (
                sum(int(s.status == jt.Status.SUCCESS) for s in singles),
                int(np.sum(sols.status == jt.Status.SUCCESS)),
            )
            print(
                f"| {title} | {name} | {loop:.2f} | {batch:.2f} | {batch / loop:.2f} | {tail:.2f} "
                f"| {batch / loop / tail:.2f} | {its[0]:.0f} / {its[1]:.0f} "
                f"| {ok[0]} / {ok[1]} of {n} |",
                flush=True,
            )
    print()


def accelerator(sizes=(256, 1024, 4096), subset=8):
    """solve_batch as a user calls it on the default device (lanes: its whole slice on an
    accelerator), against a loop of single solves on the same device."""
    dev = jax.devices()[0]
    print(f"## solve_batch on {dev.platform} ({dev.device_kind}), default lanes, loop timed on {subset} starts")
    print()
    print("| solver | loop [solves/s] | N | solves/s | vs the loop | first call [s] | success |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    a0s = starts(max(sizes))
    for name, solver in [("KalmanSearch (published tuning)", SOLVER), ("KalmanSQP (default)", jt.KalmanSQP())]:
        loop = loop_rate(a0s[:subset], solver)
        for n in sizes:
            t0 = time.perf_counter()
            rate, sols = batch_rate(a0s[:n], solver)
            first = time.perf_counter() - t0 - n / rate  # the NaN warm-up: compile
            ok = np.mean(np.asarray(sols.status == jt.Status.SUCCESS))
            print(
                f"| {name} | {loop:.1f} | {n} | {rate:.1f} | {rate / loop:.1f}x | {first:.1f} | {ok:.0%} |", flush=True
            )
    print()


def where_time_goes():
    print("## Where the time goes under vmap")
    print()
    sim = jt.RK4()
    ev = jax.jit(lambda a: jax.vmap(lambda x: evaluate_restricted(PROB, CTRL, x, sim))(a))
    a0s = starts(256)
    print("Per-lane cost of one evaluation (simulation + forward Jacobian + G, E, H), vmapped over B starts:")
    print()
    print("| B | per lane [us] |")
    print("|---:|---:|")
    for b in (1, 4, 16, 64, 256):
        a = jnp.asarray(a0s[:b])
        jax.block_until_ready(ev(a))
        best = min(_timed(lambda a=a: jax.block_until_ready(ev(a))) for _ in range(5))
        print(f"| {b} | {best / b * 1e6:.0f} |", flush=True)
    print()
    steps = np.asarray(solve_batch(PROB, CTRL, a0s, SOLVER, progress=False, history=False).steps)
    print(
        "Useful share of the lane-iterations (sum of steps / (lanes x loop iterations)) for these 256 "
        "starts: a vmapped group of whole solves iterates as long as its slowest start; the queue of "
        "`solve_batch` (lanes > 1) refills finished lanes (replayed here from the measured steps):"
    )
    print()
    print("| lanes | 4 | 16 | 32 | 64 | 256 |")
    print("|---|---:|---:|---:|---:|---:|")
    groups = [steps.sum() / (g * steps.reshape(-1, g).max(axis=1).sum()) for g in (4, 16, 32, 64, 256)]
    queue = [steps.sum() / (g * _queue_iterations(steps, g)) for g in (4, 16, 32, 64, 256)]
    print("| vmapped groups | " + " | ".join(f"{s:.0%}" for s in groups) + " |")
    print("| queue | " + " | ".join(f"{s:.0%}" for s in queue) + " |")
    print()


def _queue_iterations(steps, lanes):
    """Loop iterations of `_batch._solve_queue` for starts taking `steps` steps each."""
    r = _batch._refill_width(lanes)
    left = list(steps[:lanes])
    active = [True] * lanes
    queue, iterations = lanes, 0
    while any(a and n > 0 for a, n in zip(active, left)):
        iterations += 1
        left = [n - 1 if a and n > 0 else n for a, n in zip(active, left)]
        done = [i for i in range(lanes) if active[i] and left[i] <= 0]
        if queue < len(steps) and len(done) >= r:
            for i in done[:r]:
                if queue < len(steps):
                    left[i], queue = steps[queue], queue + 1
                else:
                    active[i] = False
    return iterations


def _timed(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


_SCALING = """
import sys, time, jax, numpy as np
sys.path.insert(0, sys.argv[1])
from benchmarks.batch import batch_rate, starts, loop_rate
a0s = starts(int(sys.argv[2]))
loop = loop_rate(a0s[:32])
for k in range(1, len(jax.devices()) + 1):
    rate, _ = batch_rate(a0s, devices=jax.devices()[:k])
    print(f"{k} {rate:.2f} {loop:.2f}", flush=True)
"""


def scaling(n=256, counts=(2,)):
    print(
        f"## Scaling with host devices (N = {n}, lanes=1; one process per row group, "
        "`XLA_FLAGS=--xla_force_host_platform_device_count=D`, first D devices used)"
    )
    print()
    print(
        "| host devices in process | devices used | solve_batch [solves/s] | loop in same process [solves/s] "
        "| ratio to loop | speed-up over 1 device |"
    )
    print("|---:|---:|---:|---:|---:|---:|")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for d in counts:
        env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={d}"}
        proc = subprocess.run([sys.executable, "-c", _SCALING, root, str(n)], env=env, capture_output=True, text=True)
        if proc.returncode:
            print(proc.stderr[-2000:])
            continue
        rows = [line.split() for line in proc.stdout.strip().splitlines()]
        one = float(rows[0][1])
        for k, rate, loop in rows:
            print(
                f"| {d} | {k} | {float(rate):.1f} | {float(loop):.1f} | {float(rate) / float(loop):.2f}x "
                f"| {float(rate) / one:.2f}x |",
                flush=True,
            )
    print()


_MEMORY = """
import resource, sys, time
sys.path.insert(0, sys.argv[1])
from benchmarks.batch import PROB, CTRL, SOLVER, starts
from jaxtraj._batch import solve_batch
import numpy as np
n, chunk, history = int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
a0s = starts(n)
t0 = time.perf_counter()
sols = solve_batch(PROB, CTRL, a0s, SOLVER, chunk_size=chunk, history=history, progress=False)
wall = time.perf_counter() - t0
ok = float(np.mean(np.asarray(sols.status == __import__("jaxtraj").Status.SUCCESS)))
with open("/proc/self/status") as f:
    hwm = [int(line.split()[1]) for line in f if line.startswith("VmHWM")][0] / 1024
print(n, chunk, history, hwm, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, wall, ok)
"""


def memory(runs):
    print("## Peak memory with chunking (fresh process per row; includes JAX, compilation and the result)")
    print()
    print(
        "Peak RSS is the child's VmHWM (/proc/self/status). Its `ru_maxrss` is also shown: on Linux it "
        "carries over the parent's peak through fork + exec, so it is only meaningful when the parent is small."
    )
    print()
    print(
        "| N | chunk_size | history | peak RSS (VmHWM) [MiB] | ru_maxrss [MiB] | wall incl. compile [s] "
        "| solves/s | success |"
    )
    print("|---:|---:|---|---:|---:|---:|---:|---:|")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for n, chunk, history in runs:
        proc = subprocess.run(
            [sys.executable, "-c", _MEMORY, root, str(n), str(chunk), "1" if history else "0"],
            capture_output=True,
            text=True,
        )
        if proc.returncode:
            print(proc.stderr[-2000:])
            continue
        _, _, _, hwm, rss, wall, ok = proc.stdout.split()[-7:]
        print(
            f"| {n} | {chunk} | {history} | {float(hwm):.0f} | {float(rss):.0f} | {float(wall):.1f} "
            f"| {n / float(wall):.1f} | {float(ok):.1%} |",
            flush=True,
        )
    print()


SECTIONS = {
    "throughput": throughput,
    "where": where_time_goes,
    "scaling": scaling,
    "solvers": solvers,
    "default": default,
    "accelerator": accelerator,
    "vmapped": vmapped,
}


def main():
    print(
        f"# solve_batch benchmark — {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}, "
        f"{len(jax.devices())} device(s), x64, case 4, RK4(100), KalmanSearch, spread {SPREAD}"
    )
    print()
    t0 = time.perf_counter()
    sections = [a for a in sys.argv[1:] if not a.startswith("--")] or ["memory", "throughput", "where", "scaling"]
    for name in sections:  # memory first, while this (parent) process is still small
        if name == "memory" and "--skip-memory" not in sys.argv:
            memory([(1000, 1000, False), (10000, 1000, False), (1000, 1000, True), (4000, 1000, True)])
        elif name != "memory":
            SECTIONS[name]()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"(total {time.perf_counter() - t0:.0f} s; this process peaked at {rss:.0f} MiB)")


if __name__ == "__main__":
    main()
