"""Outcomes under round-off-sized perturbations of the start (issue 17).

A change of CPU, of XLA fusion or vmap-or-not changes the last bits of every number; a solver
whose outcome flips with them cannot be reproduced on another machine. This script solves
each published problem from its start and from `a0 + eps r max(|a0|, 1)` (r a fixed standard
normal vector, two of them; eps in 1e-14, 1e-12, 1e-11, 1e-10, 3e-10: the zero components of
a start at rest move too) and prints, per problem and solver, the statuses, the spread of the
objective between the starts and the largest projected gradient of the successful ones.

    python benchmarks/roundoff.py                 # everything: about 10 min on 2 cores
    python benchmarks/roundoff.py --only sail     # earth-mars | sail | attitude
"""

import argparse
import math
import time

import jax.numpy as jnp
import numpy as np

import jaxtraj as jt
from jaxtraj.problems import attitude, earth_mars, solar_sail

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


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", choices=["earth-mars", "sail", "attitude"])
    args = p.parse_args(argv)
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
