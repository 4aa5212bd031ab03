"""Minimum-energy satellite reorientation with a sun keep-out cone (seed 002, issue 8): the
quaternion and the ZYX Euler-angle forms of `jaxtraj.problems.attitude`, each solved with
`jt.AugmentedLagrangian` and `jt.KalmanSQP`, against the unconstrained minimum-energy slew.

The problem (module docs of `jaxtraj.problems.attitude`): J = diag(100, 200, 300) kg m^2,
tf = 500 s, rest to rest through a 26.4 deg rotation, boresight y = (0.750, 0.433, 0.500)
(body) kept out of the 50 deg cone around the sun direction; objective: control energy
int |u|^2 dt. Control: `SaturatedSpline(P, 1)` (continuous piecewise-linear torque per axis on
P equal segments, default P = 8), RK4 with `--rk4-steps` (default 20) steps per segment; the
path constraint is enforced on that grid and checked afterwards on a grid `--grid-factor`
(default 10) times finer (`attitude.cone_margin`). Every solve starts from rest (zero torque)
unless the table says otherwise.

Rows of the table:

* "unconstrained": the same problem with a 0.001 deg cone, which is never active (the
  boresight stays ~50 deg from the sun), so it runs through the same compiled solver as the
  constrained problem; its margin is measured against the 50 deg cone.
* "constrained": the 50 deg cone. KalmanSQP is run from three starts: rest (its default use),
  its own unconstrained optimum (a natural continuation start, 0.71 deg inside the cone), and
  the AugmentedLagrangian optimum (a check that the KKT point holds).

What each solver achieved (default run: P = 8, RK4(20), 600 steps; 68 s on 2 shared CPU cores,
of which ~50 s compilation; 2026-11-22, session 4). The solvers enforce the cone on their grid
widened by 0.001 deg (`cone_backoff_deg`), so it holds between grid points too:

* AugmentedLagrangian solves the constrained slew in both forms from rest: energy 2.265205
  (x 1e-4 N^2 m^2 s), +5.08 % over the unconstrained 2.155796; quaternion 2.265204579 vs Euler
  2.265204551, 1.2e-8 relative; max |E| <= 7.5e-10; worst cone margin on the 10x grid
  +9.67e-4 deg.
* KalmanSQP solves the *unconstrained* slew in 4 iterations (6 integrations), and the
  constrained one from rest in both forms with SUCCESS: 2.265204573 (quaternion and Euler
  agree to 4e-11) in 5 iterations (7 integrations), the same cone margin; from its own
  unconstrained optimum in 3, from the AugmentedLagrangian optimum in 1, SUCCESS in both forms
  (2026-12-02, after the dual active-set QP of issue 20; before it: 175 / 115 iterations from
  rest, STALLED from the two converged starts).

Output: a Markdown table on stdout and in `OUT/results.md`, `OUT/results.json` (every row with
its parameters), `OUT/sky_path.png` (the boresight's path around the sun: stereographic
projection centred on the sun direction, and angle from the sun against azimuth around it,
with the 50 deg cone) and `OUT/torques_rates.png` (u(t) and w(t) of the constrained
solutions).

Run (from the repository root):

    PYTHONPATH=. python examples/attitude.py                 # default: about a minute on 2 CPU cores, mostly compilation
    PYTHONPATH=. python examples/attitude.py --quick         # smoke run (P = 4, RK4(10), 300 steps): about 1.5 minutes
    PYTHONPATH=. python examples/attitude.py --quick --solvers al   # what tests/test_attitude_example.py runs
    PYTHONPATH=. python examples/attitude.py --segments 12 --solvers al

Timing: each (representation, solver) pair is compiled once (the unconstrained and the
constrained problems differ only in their array `args`, and the start is an argument), and
compilation is timed apart; "warm wall" is the faster of two calls of the compiled solve.
"""

import argparse
import json
import os
import platform
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _args import folder, number

# jaxtraj sets XLA:CPU options at import; they take effect as it comes before any JAX computation
import jaxtraj as jt
from jaxtraj.plot import pyplot
from jaxtraj.problems import attitude

if __name__ == "__main__":
    jt.configure_cpu()  # a CPU device per core and XLA options (before any JAX computation)

REPS = attitude.REPRESENTATIONS  # ("quaternion", "euler")
SOLVERS = {"al": "AugmentedLagrangian", "sqp": "KalmanSQP"}
UNCONSTRAINED_CONE_DEG = 1e-3  # a cone that is never active: the unconstrained slew
REL_AGREEMENT = 1e-4  # quaternion vs Euler objectives, relative (issue 8)


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--segments", "-P", type=number(int, 1, 1000), default=8, help="torque segments P (default 8)")
    p.add_argument("--rk4-steps", type=number(int, 1, 10_000), default=20, help="RK4 steps per segment (default 20)")
    p.add_argument(
        "--grid-factor", type=number(int, 1, 1000), default=10, help="refinement of the cone check grid (default 10)"
    )
    p.add_argument(
        "--max-steps",
        type=number(int, 1, 1_000_000),
        default=600,
        help="solver steps (integrations) per solve (default 600)",
    )
    p.add_argument("--solvers", nargs="+", choices=list(SOLVERS), default=list(SOLVERS), help="default: al sqp")
    p.add_argument("--representations", nargs="+", choices=list(REPS), default=list(REPS))
    p.add_argument("--out", type=folder, default=os.path.join("results", "attitude"), help="output folder")
    p.add_argument("--quick", action="store_true", help="smoke run: P = 4, RK4(10), 300 steps (overrides those flags)")
    args = p.parse_args(argv)
    if args.quick:
        args.segments, args.rk4_steps, args.max_steps = 4, 10, 300
    return args


# ---------------------------------------------------------------------------- solving


def _solver(key):
    return jt.AugmentedLagrangian() if key == "al" else jt.KalmanSQP()


def compile_solve(base, ctrl, solver, sim, max_steps):
    """A compiled `(args, a0) -> Solution` for `base` with any `args` (same structure).
    Returns `(compiled, seconds to compile)`."""

    def run(args, a0):
        return jt.solve(eqx.tree_at(lambda q: q.args, base, args), ctrl, a0, solver, simulator=sim, max_steps=max_steps)

    t0 = time.perf_counter()
    compiled = jax.jit(run).lower(base.args, jnp.zeros(ctrl.num_params)).compile()
    return compiled, time.perf_counter() - t0


def run_solve(compiled, prob, a0, repeats=2):
    """`repeats` calls of the compiled (ahead-of-time, so already warm) solve; the warm wall
    time is the fastest (the machine may be shared)."""
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sol = compiled(prob.args, a0)
        jax.block_until_ready(sol.params)
        walls.append(time.perf_counter() - t0)
    return sol, min(walls)


def check(prob50, ctrl, sol, sim, grid_factor):
    """Post-solve diagnostics on the solver grid and on a `grid_factor`x finer one."""
    a = sol.params
    margin, t_margin = attitude.cone_margin(prob50, ctrl, a, grid_factor=grid_factor, simulator=sim)
    fine = jt.RK4(sim.steps * grid_factor)  # the grid cone_margin used: shares its compilation
    traj = jt.simulate(prob50, ctrl, a, simulator=fine)
    E_fine = np.asarray(prob50.terminal(traj.tf, traj.xf, prob50.args))
    return {
        "margin_deg": margin,
        "margin_t_s": t_margin * float(prob50.args["time_unit"]),
        "max_E_fine": float(np.max(np.abs(E_fine))),
        "max_u": float(np.max(np.abs(np.asarray(traj.u)))),
        "traj": traj,
    }


def _row(slew, rep, key, start, prob50, sol, wall, diag):
    obj = float(sol.objective)
    return {
        "slew": slew,
        "representation": rep,
        "solver": SOLVERS[key],
        "solver_key": key,
        "start": start,
        "status": jt.status_name(sol.status),
        "objective": obj,
        "energy_si": attitude.energy_si(prob50, obj),
        "max_E": float(sol.max_constraint_error),
        "max_E_fine": diag["max_E_fine"],
        "max_C_solver_grid": None if sol.max_path_constraint is None else float(sol.max_path_constraint),
        "margin_deg": diag["margin_deg"],
        "margin_t_s": diag["margin_t_s"],
        "max_u_mNm": diag["max_u"],
        "projected_gradient": float(sol.projected_gradient),
        "iterations": int(sol.iterations),
        "integrations": int(sol.integrations),
        "steps": int(sol.steps),
        "wall": wall,
        "params": np.asarray(sol.params).tolist(),
    }


# ---------------------------------------------------------------------------- report


def _unc_reference(rows, rep):
    """The unconstrained energy of `rep` (the best successful unconstrained row)."""
    vals = [
        r["objective"]
        for r in rows
        if r["slew"] == "unconstrained" and r["representation"] == rep and r["status"] == "SUCCESS"
    ]
    return min(vals) if vals else None


def table(rows):
    lines = [
        (
            "| slew | repr. | solver (start) | status | energy [(mN m)^2 100 s] | energy [N^2 m^2 s] | vs unconstr. "
            "| worst cone margin [deg] (10x grid) at t [s] | max C (solver grid) | max abs E (solver / 10x grid) "
            "| proj. grad. | iterations | integrations | warm wall [s] |"
        ),
        "|" + "---|" * 14,
    ]
    for r in rows:
        ref = _unc_reference(rows, r["representation"])
        vs = "—" if ref is None else f"{100 * (r['objective'] / ref - 1):+.3f} %"
        c = "—" if r["max_C_solver_grid"] is None else f"{r['max_C_solver_grid']:.1e}"
        lines.append(
            f"| {r['slew']} | {r['representation']} | {r['solver']} ({r['start']}) | {r['status']} | {r['objective']:.9g} "
            f"| {r['energy_si']:.6e} | {vs} | {r['margin_deg']:+.2e} at {r['margin_t_s']:.0f} | {c} "
            f"| {r['max_E']:.1e} / {r['max_E_fine']:.1e} | {r['projected_gradient']:.1e} | {r['iterations']} "
            f"| {r['integrations']} | {r['wall']:.2f} |"
        )
    return lines


def agreement(rows):
    """Quaternion vs Euler relative objective differences, per (slew, solver, start)."""
    out = []
    keys = sorted({(r["slew"], r["solver"], r["start"]) for r in rows}, key=lambda k: (k[0] != "unconstrained", k))
    for slew, solver, start in keys:
        pair = {r["representation"]: r for r in rows if (r["slew"], r["solver"], r["start"]) == (slew, solver, start)}
        if len(pair) < 2:
            continue
        q, e = pair["quaternion"], pair["euler"]
        rel = abs(q["objective"] - e["objective"]) / abs(e["objective"])
        both = q["status"] == "SUCCESS" and e["status"] == "SUCCESS"
        out.append(
            {
                "slew": slew,
                "solver": solver,
                "start": start,
                "quaternion": q["objective"],
                "euler": e["objective"],
                "relative_difference": rel,
                "both_success": both,
                "agree": bool(both and rel <= REL_AGREEMENT),
            }
        )
    return out


def verdicts(rows):
    """One honest sentence per (representation, solver) on the constrained problem."""
    lines = []
    for r in rows:
        if r["slew"] != "constrained":
            continue
        ref = _unc_reference(rows, r["representation"])
        ok = r["status"] == "SUCCESS" and r["max_E"] <= 1e-8 and (r["max_C_solver_grid"] or 0.0) <= 1e-8
        what = "solved" if ok else "NOT solved"
        extra = "" if ref is None else f", energy {100 * (r['objective'] / ref - 1):+.2f} % vs unconstrained"
        lines.append(
            f"- {r['representation']}, {r['solver']} from {r['start']}: {what} ({r['status']}{extra}, worst cone "
            f"margin {r['margin_deg']:+.2e} deg on the 10x grid, max |E| {r['max_E']:.1e}, projected gradient "
            f"{r['projected_gradient']:.1e})."
        )
    return lines


# ---------------------------------------------------------------------------- figures


def _sky(prob, traj):
    """Boresight direction along `traj` as (azimuth around the sun [deg], angle from the sun
    [deg]); azimuth 0 is the start boresight's direction."""
    args = prob.args
    s = np.asarray(args["sun"])
    y = np.asarray(jax.vmap(lambda x: attitude.attitude_matrix(prob, x) @ args["boresight"])(traj.x))
    y0 = np.asarray(attitude.attitude_matrix(prob, prob.x0) @ args["boresight"])
    e1 = y0 - (y0 @ s) * s
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(s, e1)
    theta = np.degrees(np.arctan2(np.linalg.norm(np.cross(s, y), axis=1), y @ s))
    phi = np.degrees(np.arctan2(y @ e2, y @ e1))
    return phi, theta


def sky_figure(path, prob50, cone_deg, curves):
    """`curves`: list of (label, problem, trajectory, line style dict)."""
    plt = pyplot()
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 5.8), width_ratios=(1, 1.3))
    circle = np.linspace(0, 2 * np.pi, 721)
    rho_c = 2 * np.tan(np.radians(cone_deg) / 2)
    ax0.fill(rho_c * np.cos(circle), rho_c * np.sin(circle), color="gold", alpha=0.25, lw=0)
    ax0.plot(
        rho_c * np.cos(circle),
        rho_c * np.sin(circle),
        color="darkorange",
        lw=1.2,
        label=f"{cone_deg:g} deg keep-out cone",
    )
    ax0.plot([0], [0], "*", color="orange", ms=14, label="sun direction")
    ax1.axhspan(0, cone_deg, color="gold", alpha=0.25, lw=0)
    ax1.axhline(cone_deg, color="darkorange", lw=1.2, label=f"cone boundary ({cone_deg:g} deg)")
    thetas = []
    for label, prob, traj, style in curves:
        phi, theta = _sky(prob, traj)
        rho = 2 * np.tan(np.radians(theta) / 2)
        xs, ys = rho * np.cos(np.radians(phi)), rho * np.sin(np.radians(phi))
        ax0.plot(xs, ys, label=label, **style)
        ax1.plot(phi, theta, label=label, **style)
        thetas.append(theta)
        for ax, (u, v) in ((ax0, (xs, ys)), (ax1, (phi, theta))):
            ax.plot(u[0], v[0], "o", color="k", ms=5)
            ax.plot(u[-1], v[-1], "s", color="k", ms=5)
    ax0.plot([], [], "o", color="k", ms=5, label="start")
    ax0.plot([], [], "s", color="k", ms=5, label="end")
    lim = 1.05 * max(float(np.max(2 * np.tan(np.radians(t) / 2))) for t in thetas)
    ax0.set_xlim(-lim, lim)
    ax0.set_ylim(-lim, lim)
    ax0.set_aspect("equal")
    ax0.grid(alpha=0.3)
    ax0.set_title(
        "boresight on the sky: stereographic projection\ncentred on the sun (radius 2 tan(angle/2))", fontsize=10
    )
    ax0.legend(fontsize=7, loc="lower left")
    lo = min(float(np.min(t)) for t in thetas)
    hi = max(float(np.max(t)) for t in thetas)
    ax1.set_ylim(min(lo, cone_deg) - 0.15, hi + 0.3)
    ax1.set_xlabel("azimuth around the sun direction [deg] (0: start boresight)")
    ax1.set_ylabel("angle between boresight and sun [deg]")
    ax1.grid(alpha=0.3)
    ax1.set_title("zoom: angle from the sun along the slew (shaded: inside the cone)", fontsize=10)
    ax1.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rates_figure(path, prob50, curves):
    """`curves`: list of (label, trajectory, line style dict); torque in mN m, rates in deg/s."""
    plt = pyplot()
    tu = float(prob50.args["time_unit"])
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    for label, traj, style in curves:
        t = np.asarray(traj.t) * tu
        u = np.asarray(traj.u) * float(prob50.args["torque_unit"]) * 1e3  # mN m
        xw = np.asarray(traj.x)
        w = np.degrees(xw[:, -4:-1] / tu)  # the rates are the three states before the energy
        for i in range(3):
            axes[0, i].plot(t, u[:, i], label=label, **style)
            axes[1, i].plot(t, w[:, i], label=label, **style)
    for i in range(3):
        axes[0, i].set_title(f"torque u{i + 1}")
        axes[0, i].set_ylabel("u [mN m]")
        axes[1, i].set_ylabel(f"w{i + 1} [deg/s]")
        axes[1, i].set_xlabel("t [s]")
        for ax in axes[:, i]:
            ax.grid(alpha=0.3)
            ax.axhline(0, color="k", lw=0.5)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8)
    fig.suptitle("constrained minimum-energy slews (50 deg keep-out cone): torques and body rates", fontsize=11)
    fig.tight_layout(rect=(0, 0.09, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- main


def main(argv=None):
    args = parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    sim = jt.RK4(args.rk4_steps)
    total_start = time.perf_counter()
    cone_deg = 50.0
    print(
        f"Attitude reorientation with a {cone_deg:g} deg sun keep-out cone: SaturatedSpline(P={args.segments}, p=1) "
        f"per axis, RK4({args.rk4_steps}) per segment, cone checked on a {args.grid_factor}x finer grid; "
        f"max {args.max_steps} steps per solve",
        flush=True,
    )
    rows, compile_times, trajs = [], {}, {}
    for rep in args.representations:
        prob50, ctrl, a_rest = attitude.case(rep, args.segments)
        prob_unc = attitude.problem(rep, cone_deg=UNCONSTRAINED_CONE_DEG)
        found = {}
        for key in ("al", "sqp"):  # AL first: its optimum is one of KalmanSQP's starts
            if key not in args.solvers:
                continue
            compiled, compile_times[f"{rep}/{SOLVERS[key]}"] = compile_solve(
                prob50, ctrl, _solver(key), sim, args.max_steps
            )
            runs = [("unconstrained", "rest", prob_unc, a_rest), ("constrained", "rest", prob50, a_rest)]
            if key == "sqp":
                runs.append(("constrained", "own unconstrained optimum", prob50, None))
                if "al" in found:
                    runs.append(("constrained", "AugmentedLagrangian optimum", prob50, found["al"]))
            for slew, start, prob, a0 in runs:
                if a0 is None:
                    a0 = found[key]
                sol, wall = run_solve(compiled, prob, a0)
                diag = check(prob50, ctrl, sol, sim, args.grid_factor)
                row = _row(slew, rep, key, start, prob50, sol, wall, diag)
                rows.append(row)
                trajs[(slew, rep, key, start)] = diag["traj"]
                if slew == "unconstrained":
                    found[key] = sol.params
                elif start == "rest" and key == "al":
                    found["al"] = sol.params
                print(
                    f"  {rep:10s} {SOLVERS[key]:19s} {slew:13s} from {start}: {row['status']}, energy {row['objective']:.9g}, "
                    f"margin {row['margin_deg']:+.2e} deg, max|E| {row['max_E']:.1e}, {row['integrations']} integrations, "
                    f"{wall:.2f} s",
                    flush=True,
                )
    agree = agreement(rows)
    notes = [
        "",
        "Quaternion vs Euler (relative difference of the objectives): "
        + "; ".join(
            f"{a['slew']} {a['solver']} ({a['start']}): {a['quaternion']:.10g} vs {a['euler']:.10g}, "
            f"{a['relative_difference']:.1e}{'' if a['both_success'] else ' (not both SUCCESS)'}"
            for a in agree
        )
        + ".",
        "",
        "Constrained slew, solver by solver:",
        *verdicts(rows),
        "",
        (
            f"Energy in solver units ((1 mN m)^2 x 100 s) and in N^2 m^2 s (`attitude.energy_si`). Cone margin: "
            f"angle between boresight and sun minus {cone_deg:g} deg (< 0: inside the cone), minimum over a grid "
            f"{args.grid_factor}x finer than the solver's (`attitude.cone_margin`); max C: the solver's path "
            "constraint s.(R y) - cos(50 deg + 0.001 deg) on its own grid (<= 0: outside; the 0.001 deg backoff keeps "
            "the cone between grid points). 'unconstrained' = a 0.001 deg cone "
            "(never active), margin measured against the 50 deg cone. 'vs unconstr.': energy relative to the "
            "unconstrained optimum of the same representation. Max abs E: the 7 terminal conditions "
            "(attitude, rates, tf). Wall times exclude compilation; compile times [s]: "
            + ", ".join(f"{k} {v:.1f}" for k, v in compile_times.items())
            + "."
        ),
    ]
    lines = table(rows) + notes
    print()
    print("\n".join(lines), flush=True)

    figs = []
    colors = {("quaternion", "al"): "C0", ("euler", "al"): "C3", ("quaternion", "sqp"): "C2", ("euler", "sqp"): "C1"}
    sky, rates = [], []
    unc_key = "al" if "al" in args.solvers else "sqp"
    for rep in args.representations:
        prob = attitude.problem(rep)
        traj = trajs.get(("unconstrained", rep, unc_key, "rest"))
        if traj is not None:
            style = {"color": "0.45", "ls": "--" if rep == "euler" else "-", "lw": 1.4}
            sky.append((f"unconstrained, {rep} ({SOLVERS[unc_key]})", prob, traj, style))
        for key in ("al", "sqp"):
            traj = trajs.get(("constrained", rep, key, "rest"))
            if traj is None:
                continue
            row = next(
                x
                for x in rows
                if (x["slew"], x["representation"], x["solver_key"], x["start"]) == ("constrained", rep, key, "rest")
            )
            good = row["status"] == "SUCCESS"
            label = f"constrained, {rep}, {SOLVERS[key]} from rest ({row['status']}, energy {row['objective']:.4g})"
            style = {
                "color": colors[rep, key],
                "ls": ("-" if rep == "quaternion" else "--") if good else ":",
                "lw": 1.8 if good else 1.1,
                "alpha": 1.0 if good else 0.75,
            }
            sky.append((label, prob, traj, style))
            rates.append((label, traj, style))
    if sky:
        prob50 = attitude.problem(args.representations[0])
        sky_figure(os.path.join(args.out, "sky_path.png"), prob50, cone_deg, sky)
        figs.append("sky_path.png")
        rates_figure(os.path.join(args.out, "torques_rates.png"), prob50, rates)
        figs.append("torques_rates.png")
    total = time.perf_counter() - total_start

    with open(os.path.join(args.out, "results.md"), "w") as f:
        f.write("# Satellite reorientation with a sun keep-out cone (seed 002): quaternion vs Euler, two solvers\n\n")
        f.write(
            f"Command arguments: `{' '.join(argv) if argv is not None else ''}` (defaults otherwise); total {total:.0f} s; "
        )
        f.write(f"{platform.processor() or platform.machine()}, jax {jax.__version__}.\n\n")
        f.write("\n".join(lines) + "\n\nFigures: " + ", ".join(figs) + "\n")
    record = {
        "arguments": vars(args),
        "compile_times": compile_times,
        "total_seconds": total,
        "rows": rows,
        "agreement": agree,
        "figures": figs,
    }
    with open(os.path.join(args.out, "results.json"), "w") as f:
        json.dump(record, f, indent=1, default=float)
    print(f"\nWrote {args.out}/results.md, results.json and {len(figs)} figures in {total:.0f} s total.")
    return record


if __name__ == "__main__":
    main()
