"""Outcomes under round-off-sized perturbations of the start (issue 17).

A change of CPU, of XLA fusion or vmap-or-not changes the last bits of every number; a solver
whose outcome flips with them cannot be reproduced on another machine. This script solves
each published problem from its start and from `a0 + eps r max(|a0|, 1)` (r a fixed standard
normal vector, two of them; eps in 1e-14, 1e-12, 1e-11, 1e-10, 3e-10: the zero components of
a start at rest move too) and prints, per problem and solver, the statuses, the spread of the
objective between the starts and the largest projected gradient of the successful ones.

    python benchmarks/roundoff.py                 # everything: about 10 min on 2 cores
    python benchmarks/roundoff.py --only sail     # earth-mars | sail | attitude

`--gallery` (issue 49's target: iteration counts within 2x over a start, its perturbations and
two ISA settings) runs the default KalmanSQP (or `--solver`: its line search, with BFGS) on every problem of `jt.problems.classic` and on
the pendulum minimum time of `benchmarks/unseen.py`, from the naive start and its 1e-12 and
1e-10 perturbations, under each `--isa` setting (XLA's `--xla_cpu_max_isa`, a subprocess
each: another CPU's vectorization and FMA use on this one), and prints the iteration counts,
their max/min ratio (> 2: a defect) and the outcomes:

    python benchmarks/roundoff.py --gallery --isa default SSE4_2 AVX   # about 15 min on 2 cores
"""

import argparse
import json
import math
import os
import subprocess
import sys
import time

import jax.numpy as jnp
import numpy as np

import jaxtraj as jt
from jaxtraj.problems import attitude, earth_mars, solar_sail

if __name__ == "__main__":
    jt.configure_cpu()  # the CPU set-up the recorded numbers ran with (a device per core, XLA options)

EPS = (1e-14, 1e-12, 1e-11, 1e-10, 3e-10)


def starts(a0, vectors=2, seed=0):
    """The start and its perturbations, `(1 + vectors * len(EPS), n)`."""
    a0 = np.asarray(a0, dtype=np.float64)
    rng = np.random.default_rng(seed)
    rows = [a0]
    for _ in range(vectors):
        r = rng.standard_normal(a0.shape)
        rows += [a0 + eps * r * np.maximum(np.abs(a0), 1.0) for eps in EPS]
    return jnp.asarray(np.stack(rows))


def cases(only):
    """(problem label, solver label, problem, control, a0, solver, simulator, max_steps,
    objective unit)."""
    if only in (None, "earth-mars"):
        for n in range(1, 8):
            prob, ctrl, a0 = earth_mars.thesis_case(n)
            yield (
                f"earth-mars case {n}",
                "KalmanSearch (published tuning)",
                prob,
                ctrl,
                a0,
                earth_mars.thesis_solver(n),
                jt.RK4(),
                5000,
                1.0,
            )
            yield f"earth-mars case {n}", "KalmanSQP", prob, ctrl, a0, jt.KalmanSQP(), jt.RK4(), 5000, 1.0
    if only in (None, "sail"):
        for target, pitch in (("mars", 20.0), ("venus", -50.0), ("mercury", -50.0)):
            prob, ctrl = solar_sail.problem(target), solar_sail.spline_control(10, 1)
            alpha = math.radians(pitch)
            a0 = jnp.asarray(ctrl.initial_guess(solar_sail.TF_BOX[target] / 2.0, alpha, alpha))
            days = solar_sail.DAYS_PER_UNIT
            yield f"sail {target} [d]", "KalmanSQP", prob, ctrl, a0, jt.KalmanSQP(), jt.RK4(100), 600, days
            yield (
                f"sail {target} [d]",
                "KalmanSearch (sail tuning)",
                prob,
                ctrl,
                a0,
                solar_sail.kalman_search_solver(),
                jt.RK4(100),
                1000,
                days,
            )
    if only in (None, "attitude"):
        for rep in attitude.REPRESENTATIONS:
            prob, ctrl, a0 = attitude.case(rep, 8)
            yield f"attitude {rep}, 50 deg cone", "KalmanSQP", prob, ctrl, a0, jt.KalmanSQP(), jt.RK4(20), 600, 1.0


GALLERY_EPS = (1e-12, 1e-10)


def gallery_cases():
    """(name, problem, control, naive start) of the classic gallery and the unseen pendulum."""
    classic = jt.problems.classic
    for name in classic.names():
        entry = classic.get(name)
        yield name, entry.problem, entry.control, entry.start
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import unseen

    for name, prob, family, tf, u in unseen.problems():
        if name == "pendulum-min-time":
            ctrl = prob.parametrize(family)
            yield name, prob, ctrl, ctrl.initial_guess(tf, u, u)


GALLERY_SOLVERS = {
    "default": jt.KalmanSQP(),
    "line-search": jt.KalmanSQP(globalization="line-search"),
    "bfgs-line-search": jt.KalmanSQP(hessian="bfgs", globalization="line-search"),
}


def gallery_rows(solver_name):
    """One JSON line per problem: iterations, statuses and objectives from the start and its
    perturbations (`a0 + eps r max(|a0|, 1)`, eps in GALLERY_EPS, one fixed r)."""
    solver = GALLERY_SOLVERS[solver_name]
    for name, prob, ctrl, a0 in gallery_cases():
        a0 = np.asarray(a0, dtype=np.float64)
        r = np.random.default_rng(0).standard_normal(a0.shape)
        rows = [a0] + [a0 + eps * r * np.maximum(np.abs(a0), 1.0) for eps in GALLERY_EPS]
        sols = [jt.solve(prob, ctrl, jnp.asarray(a), solver, simulator=jt.RK4(40), max_steps=5000) for a in rows]
        print(
            json.dumps(
                {
                    "problem": name,
                    "iterations": [int(s.iterations) for s in sols],
                    "status": [str(jt.status_name(s.status)) for s in sols],
                    "objective": [float(s.objective) for s in sols],
                }
            ),
            flush=True,
        )


def gallery_table(isas, solver_name):
    """Run `gallery_rows` under each ISA setting (a subprocess each) and print the table."""
    runs = {}
    for isa in isas:
        env = dict(os.environ)
        if isa != "default":
            env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_cpu_max_isa={isa}".strip()
        out = subprocess.run(
            [sys.executable, os.path.abspath(__file__), "--gallery-rows", "--solver", solver_name],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        runs[isa] = {
            row["problem"]: row for row in (json.loads(line) for line in out.splitlines() if line.startswith("{"))
        }
    starts = "/".join(["start", *(f"{eps:.0e}" for eps in GALLERY_EPS)])
    print(
        f"| problem | {' | '.join(f'iterations {isa} ({starts})' for isa in isas)} | max/min | outcomes | objective spread |"
    )
    print("|---|" + "---:|" * len(isas) + "---:|---|---:|")
    for name in runs[isas[0]]:
        rows = [runs[isa][name] for isa in isas]
        its = [i for row in rows for i in row["iterations"]]
        statuses = [s for row in rows for s in row["status"]]
        objective = np.array([o for row in rows for o in row["objective"]])
        ok = np.array(statuses) == "SUCCESS"
        outcomes = ", ".join(f"{k} {v}" for k, v in zip(*np.unique(statuses, return_counts=True)))
        spread = np.ptp(objective[ok]) if ok.any() else float("nan")
        cells = " | ".join("/".join(str(i) for i in row["iterations"]) for row in rows)
        print(f"| {name} | {cells} | {max(its) / max(min(its), 1):.1f} | {outcomes} | {spread:.1e} |", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", choices=["earth-mars", "sail", "attitude"])
    p.add_argument("--gallery", action="store_true", help="the gallery's iteration spread (see above)")
    p.add_argument("--isa", nargs="*", default=["default"], help="XLA ISA settings for --gallery")
    p.add_argument("--solver", choices=list(GALLERY_SOLVERS), default="default", help="the solver of --gallery")
    p.add_argument("--gallery-rows", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.gallery_rows:
        return gallery_rows(args.solver)
    if args.gallery:
        return gallery_table(args.isa, args.solver)
    print(
        "| problem | solver | SUCCESS / starts | other outcomes | objective spread | "
        "max proj. grad. (SUCCESS) | time [s] |"
    )
    print("|---|---|---:|---|---:|---:|---:|")
    for label, name, prob, ctrl, a0, solver, sim, max_steps, unit in cases(args.only):
        t = time.perf_counter()
        sols = jt.solve_batch(
            prob, ctrl, starts(a0), solver, simulator=sim, max_steps=max_steps, progress=False, history=False
        )
        elapsed = time.perf_counter() - t
        names = jt.status_name(sols.status)
        ok = names == "SUCCESS"
        others = ", ".join(f"{k} {v}" for k, v in zip(*np.unique(names[~ok], return_counts=True))) or "-"
        objective = np.asarray(sols.objective) * unit
        spread = np.ptp(objective[ok]) if ok.any() else float("nan")
        pg = np.max(np.asarray(sols.projected_gradient)[ok]) if ok.any() else float("nan")
        print(
            f"| {label} | {name} | {ok.sum()} / {len(names)} | {others} | {spread:.1e} | {pg:.1e} | {elapsed:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
