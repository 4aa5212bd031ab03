"""Reference optima of the seven Earth-Mars thesis cases, computed with SciPy's SLSQP.

For each case (`jt.problems.earth_mars.thesis_case(n)`) the restricted problem
"minimize tf subject to x(tf) on the Mars orbit" is solved with `jaxtraj.baselines.solve_slsqp`
(RK4, 100 steps per segment, forward-mode sensitivities) from

* the published starting vector,
* the straight-line start `control.initial_guess(3.4, 0.0, 1.5 pi)`,
* random perturbations of the published start (fixed seed): control values + N(0, 0.3) rad,
  times x (1 + N(0, 0.03)), redrawn until the times are ordered. Cases 6 and 7 (piecewise
  constant, free switch times) have many local minima and get more starts.

A run counts as converged when max|E| <= 1e-10 at its last point; the table also says how
many of them SLSQP itself declared successful (the others hit the iteration limit, mostly
while repeating rejected line searches at the optimum with |E| ~ 1e-12, unable to meet
ftol = 1e-14). The best converged parameter vector of each case is then re-solved with
RK4(400) and with `jt.Diffrax()` (Tsit5, rtol = atol = 1e-12) to show the discretization
error of the optimal tf.

SLSQP needs up to ~2700 iterations on cases 1, 2 and 7 (it crawls along ill-conditioned
valleys), hence the iteration limits below; on the other cases the successful runs need
at most a few hundred and the limit only cuts those line-search loops short.

Usage (about 5-10 minutes on a 2-core CPU):

    PYTHONPATH=. python benchmarks/reference_optima.py [--workers 2] [--cases 1 4]
"""

import argparse
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

SEED = 20261121
VALUE_SIGMA = 0.3  # rad
TIME_SIGMA = 0.03  # relative
STARTS = {1: 8, 2: 8, 3: 8, 4: 8, 5: 8, 6: 20, 7: 20}  # published + straight line + perturbations
MAXITER = {1: 3000, 2: 3000, 3: 1000, 4: 1000, 5: 1000, 6: 1000, 7: 3000}
E_TOL = 1e-10
# Longest first, so that the pool stays busy.
ORDER = (7, 2, 1, 6, 5, 3, 4)


def make_starts(case, count, rng):
    """[(label, a0)]: published, straight line, then `count - 2` perturbations."""
    import jaxtraj as jt

    _, ctrl, a0 = jt.problems.earth_mars.thesis_case(case)
    a0 = np.asarray(a0)
    starts = [("published", a0), ("straight line", np.asarray(ctrl.initial_guess(3.4, 0.0, 1.5 * np.pi)))]
    times = np.zeros(a0.shape, bool)
    times[list(ctrl.time_indices)] = True
    while len(starts) < count:
        a = a0.copy()
        a[~times] += VALUE_SIGMA * rng.standard_normal(int((~times).sum()))
        a[times] *= 1.0 + TIME_SIGMA * rng.standard_normal(int(times.sum()))
        try:
            ctrl.validate(a)
        except ValueError:
            continue  # times out of order: draw again
        starts.append((f"perturbed {len(starts) - 1}", a))
    return starts


def _worker_init():
    import jaxtraj  # noqa: F401  (float64)


def run_start(case, label, a0):
    import jaxtraj as jt
    from jaxtraj.baselines import solve_slsqp

    prob, ctrl, _ = jt.problems.earth_mars.thesis_case(case)
    r = solve_slsqp(prob, ctrl, a0, simulator=jt.RK4(100), maxiter=MAXITER[case])
    return {"case": case, "label": label, "result": r, "pid": os.getpid()}


def run_check(case, params):
    """Re-solve from `params` with RK4(400) and with adaptive Tsit5 (rtol = atol = 1e-12)."""
    import jaxtraj as jt
    from jaxtraj.baselines import solve_slsqp

    prob, ctrl, _ = jt.problems.earth_mars.thesis_case(case)
    out = {"case": case}
    for key, sim in (("rk4_400", jt.RK4(400)), ("diffrax", jt.Diffrax(rtol=1e-12, atol=1e-12))):
        out[key] = solve_slsqp(prob, ctrl, params, simulator=sim, maxiter=MAXITER[case])
    return out


def converged(runs):
    return [d for d in runs if d["result"].max_constraint_error <= E_TOL]


def pick_best(runs):
    """Lowest tf; among runs within 1e-8 of it, prefer SLSQP successes, then the smallest
    max|E| (a run stopped at the iteration limit can sit at tf - 1e-11 with |E| ~ 1e-12)."""
    tf_min = min(d["result"].tf for d in runs)
    near = [d for d in runs if d["result"].tf <= tf_min + 1e-8]
    return min(near, key=lambda d: (not d["result"].success, d["result"].max_constraint_error, d["result"].tf))


def control_name(ctrl):
    return repr(ctrl).replace("\n", " ")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--cases", type=int, nargs="*", default=list(ORDER))
    args = parser.parse_args(argv)

    import jaxtraj as jt

    published = jt.problems.earth_mars.PUBLISHED
    rng = np.random.default_rng(SEED)
    starts = {case: make_starts(case, STARTS[case], rng) for case in range(1, 8)}  # same draws whatever --cases
    cases = [c for c in ORDER if c in args.cases]
    total = sum(len(starts[c]) for c in cases)
    print(f"{total} SLSQP runs on {args.workers} worker process(es); RK4(100), maxiter per case {MAXITER}", flush=True)

    t_start = time.perf_counter()
    runs = {c: [] for c in cases}
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.workers, mp_context=ctx, initializer=_worker_init) as pool:
        futures = [pool.submit(run_start, c, label, a) for c in cases for label, a in starts[c]]
        for i, fut in enumerate(as_completed(futures), 1):
            d = fut.result()
            r = d["result"]
            runs[d["case"]].append(d)
            print(
                f"[{i:3d}/{total}] case {d['case']} {d['label']:13s} tf = {r.tf:.10f}  max|E| = {r.max_constraint_error:.1e}"
                f"  it = {r.iterations:4d}  evals = {r.evaluations:5d}  {r.wall_time:6.1f} s  {r.message}",
                flush=True,
            )
        t_search = time.perf_counter() - t_start

        best = {}
        for c in cases:
            ok = converged(runs[c])
            if ok:
                best[c] = pick_best(ok)
        print("re-solving the best points with RK4(400) and Diffrax(Tsit5, 1e-12) ...", flush=True)
        checks = {}
        futures = [pool.submit(run_check, c, best[c]["result"].params) for c in cases if c in best]
        for fut in as_completed(futures):
            d = fut.result()
            checks[d["case"]] = d
            print(
                f"  case {d['case']}: RK4(400) tf = {d['rk4_400'].tf:.12f} ({d['rk4_400'].iterations} it, "
                f"{d['rk4_400'].wall_time:.1f} s), Diffrax tf = {d['diffrax'].tf:.12f} "
                f"({d['diffrax'].iterations} it, {d['diffrax'].wall_time:.1f} s)",
                flush=True,
            )
    t_total = time.perf_counter() - t_start

    print()
    print(
        "| case | control | best tf (RK4 100) | max\\|E\\| | converged / starts (SLSQP success) "
        "| tf spread (converged) | within 1e-8 of best | best from | published tf |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for c in sorted(cases):
        _, ctrl, _ = jt.problems.earth_mars.thesis_case(c)
        ok = converged(runs[c])
        n_all = len(runs[c])
        n_succ = sum(d["result"].success for d in ok)
        if c not in best:
            print(f"| {c} | `{control_name(ctrl)}` | (none converged) | | 0 / {n_all} | | | | {published[c][0]:.5f} |")
            continue
        b = best[c]["result"]
        tfs = np.array([d["result"].tf for d in ok])
        print(
            f"| {c} | `{control_name(ctrl)}` | {b.tf:.8f} | {b.max_constraint_error:.1e} | {len(ok)} / {n_all} ({n_succ}) "
            f"| {tfs.max() - tfs.min():.1e} | {int(np.sum(tfs - b.tf <= 1e-8))} | {best[c]['label']} "
            f"| {published[c][0]:.5f} |"
        )

    print()
    print(
        "| case | tf RK4(100) | tf RK4(400) | tf Diffrax Tsit5 1e-12 | RK4(100) - Diffrax | max\\|E\\| RK4(400) / Diffrax |"
    )
    print("|---|---|---|---|---|---|")
    for c in sorted(cases):
        if c not in checks:
            continue
        b, r4, rd = best[c]["result"], checks[c]["rk4_400"], checks[c]["diffrax"]
        flag = "" if (r4.success and rd.success) else " (re-solve not converged)"
        print(
            f"| {c} | {b.tf:.12f} | {r4.tf:.12f} | {rd.tf:.12f} | {b.tf - rd.tf:.1e} "
            f"| {r4.max_constraint_error:.1e} / {rd.max_constraint_error:.1e}{flag} |"
        )

    print()
    print("| case | published start: tf, max\\|E\\|, iterations, evaluations, s | runs' wall time (s, summed) |")
    print("|---|---|---|")
    for c in sorted(cases):
        pub = next(d["result"] for d in runs[c] if d["label"] == "published")
        conv = pub.max_constraint_error <= E_TOL
        print(
            f"| {c} | {pub.tf:.8f}, {pub.max_constraint_error:.1e}, {pub.iterations}, {pub.evaluations}, "
            f"{pub.wall_time:.1f}{'' if conv else ' (not converged)'} | {sum(d['result'].wall_time for d in runs[c]):.0f} |"
        )

    print()
    print("best parameter vectors (RK4 100):")
    for c in sorted(best):
        print(
            f"  case {c}: {np.array2string(best[c]['result'].params, precision=10, separator=', ', max_line_width=10**6)}"
        )
    print(f"\nsearch {t_search:.0f} s, checks {t_total - t_search:.0f} s, total {t_total:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
