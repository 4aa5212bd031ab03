"""The main job: solve Earth-Mars thesis case 4 (5 continuous line segments, nodes at fixed
fractions of tf) with the thesis's Kalman-filter search, print a summary table and write a
figure (control, states, convergence, the transfer in the orbital plane).

Run: `make run` (or `python examples/earth_mars_main.py [CASE] [OUTDIR]`).
"""

import os
import sys
import time

import jax
import numpy as np

import jaxtraj as jt
from jaxtraj.plot import solution_figure

EM = jt.problems.earth_mars


def main(case=4, outdir="results"):
    prob, ctrl, a0 = EM.thesis_case(case)
    solver = EM.thesis_solver(case)
    print(f"Earth-Mars thesis case {case}: {ctrl!r}, {ctrl.num_params} parameters")
    print("compiling the solver (first call) ...", flush=True)
    t0 = time.perf_counter()
    sol = jax.block_until_ready(jt.solve(prob, ctrl, a0, solver))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = jax.block_until_ready(jt.solve(prob, ctrl, a0, solver))
    warm = time.perf_counter() - t0
    traj = jt.simulate(prob, ctrl, sol.params)

    pub_tf, pub_it = EM.PUBLISHED[case]
    rows = [
        ("status", jt.status_name(sol.status)),
        ("tf [normalized]", f"{float(sol.tf):.8f}   (published {pub_tf}, {pub_it} iterations; unrestricted optimum {EM.TF_UNRESTRICTED})"),
        ("tf [days]", f"{float(sol.tf) * EM.DAYS_PER_UNIT:.3f}"),
        ("max |E_i|", f"{float(sol.max_constraint_error):.2e}"),
    ]
    for name, e in zip(prob.constraint_names, np.asarray(sol.constraints)):
        rows.append((f"  E: {name}", f"{e:+.2e}"))
    rows += [
        ("projected gradient", f"{float(sol.projected_gradient):.2e}"),
        ("iterations (accepted)", f"{int(sol.iterations)}"),
        ("integrations", f"{int(sol.integrations)}"),
        ("wall time (warm)", f"{warm:.3f} s"),
        ("first call (compile+run)", f"{first:.2f} s"),
    ]
    width = max(len(k) for k, _ in rows)
    print()
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")
    os.makedirs(outdir, exist_ok=True)
    path = os.path.join(outdir, f"earth-mars-case{case}.png")
    solution_figure(prob, ctrl, sol, traj, path, r_target=float(prob.args["rf"]),
                    title=f"Earth-Mars, thesis case {case}: tf = {float(sol.tf):.6f} "
                          f"({float(sol.tf) * EM.DAYS_PER_UNIT:.1f} days), KalmanSearch")
    print(f"\nfigure written to {path}")
    return 0 if sol.status == jt.Status.SUCCESS else 1


if __name__ == "__main__":
    case = int(sys.argv[1]) if len(sys.argv) > 1 else 4
    outdir = sys.argv[2] if len(sys.argv) > 2 else "results"
    sys.exit(main(case, outdir))
