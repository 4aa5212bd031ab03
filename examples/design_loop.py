"""A design loop through the optimizer: the solar sail's characteristic acceleration a0 such
that the minimum-time transfer from Earth's orbit to Mars' takes exactly one year.

tf*(a0) is the optimal transfer time, a function of the sail defined by a whole trajectory
optimization. `jt.solve` is differentiable (the implicit function theorem at the returned
optimum, docs/differentiable.md), so Newton's method runs on it directly:

    a0 <- a0 - (tf*(a0) - T) / (dtf*/da0),

each solve warm-started at the previous optimum, one compiled program for the value and the
derivative. The same program then gives the sensitivities of tf* to every number in the
problem's `args` (a0, the target radius r_f, the Sun's mu) along a range of sails, in one
vmapped call: the table a mission report wants, and a figure of tf*(a0) with the tangents
the derivatives predict.

Kelley's transfer (seed 003): normalized units (1 AU, 1 year = 2 pi), PiecewiseLinear(6)
pitch, RK4(20), no pitch bounds (the optimum stays inside them). The transfer has several
local optima; Newton follows the one its start leads to, and the design a0 is checked at the
end by an independent solve from the naive start.

Run: `python examples/design_loop.py [--days 365] [--grid 7] [--out DIR]` (about a minute,
most of it compiling). Writes `design_loop.md` and `design_loop.png` to DIR.
"""

import argparse
import pathlib
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _args import folder, number

import jaxtraj as jt
from jaxtraj.plot import pyplot
from jaxtraj.problems import solar_sail as ss

if __name__ == "__main__":
    jt.configure_cpu()  # a CPU device per core and XLA options (before any JAX computation)

DAYS = ss.DAYS_PER_UNIT
#: the normalized acceleration unit, the Sun's gravity at 1 AU [mm/s^2]
ACCEL_MM_S2 = 5.930


def setup():
    """The sail problem without its pitch bounds, the control, the simulator and a naive start."""
    sail = ss.problem("mars", ss.KELLEY_A0, r_f=ss.KELLEY_RF)
    prob = jt.Problem(sail.dynamics, sail.x0, sail.terminal, sail.constraint_names, args=sail.args, name="sail")
    ctrl = jt.controls.PiecewiseLinear(6)
    alpha = np.radians(20.0)  # (from 35 deg and tf = 7 the solve ends in a local optimum 16 % slower)
    return prob, ctrl, jt.RK4(20), jnp.asarray(ctrl.initial_guess(6.5, alpha, alpha))


def optimum(prob, ctrl, sim):
    """`f(args, start) -> ((tf*, (params, status)), dtf*/dargs)`, jit-compiled once."""

    def tf(args, start):
        sol = jt.solve(eqx.tree_at(lambda p: p.args, prob, args), ctrl, start, simulator=sim, max_steps=300)
        return sol.tf, (sol.params, sol.status)

    return jax.jit(jax.value_and_grad(tf, has_aux=True))


def newton(f, args, start, target, tol=1e-10, max_iter=12):
    """Newton on tf*(a0) = target; returns (args, start, rows) with one row per iteration."""
    rows = []
    for k in range(max_iter):
        (tf, (start, status)), grad = f(args, start)
        if status != jt.Status.SUCCESS:
            raise SystemExit(f"the solve at a0 = {float(args['a0'])} ended {jt.status_name(status)}")
        slope = float(grad["a0"])
        rows.append((k, float(args["a0"]), float(tf) * DAYS, slope * DAYS))
        if abs(float(tf) - target) <= tol * target:
            break
        args = {**args, "a0": args["a0"] - (tf - target) / slope}
    return args, start, rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--days", type=number(float, 0.0, above=True), default=365.0, help="the required transfer time [days]"
    )
    parser.add_argument("--grid", type=number(int, 1, 1000), default=7, help="sails in the sensitivity table")
    parser.add_argument("--out", type=folder, default="results/design_loop")
    args_ = parser.parse_args(argv)
    out = pathlib.Path(args_.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    prob, ctrl, sim, naive = setup()
    f = optimum(prob, ctrl, sim)
    target = args_.days / DAYS
    (tf0, (start, _)), _ = f(prob.args, naive)
    print(f"Kelley's sail (a0 = {ss.KELLEY_A0}): tf* = {float(tf0) * DAYS:.2f} days; wanted {args_.days:g} days")
    args, start, rows = newton(f, prob.args, start, target)
    lines = [
        f"## Newton on tf*(a0) = {args_.days:g} days",
        "",
        "| iteration | a0 | tf* [days] | dtf*/da0 [days] |",
        "|---:|---:|---:|---:|",
        *(f"| {k} | {a:.12f} | {tf:.9f} | {d:.4f} |" for k, a, tf, d in rows),
    ]
    a0 = float(args["a0"])
    # an independent check: a plain solve (no derivative) from the naive start at the design a0
    check = jt.solve(eqx.tree_at(lambda p: p.args, prob, args), ctrl, naive, simulator=sim, max_steps=300)
    lines += [
        "",
        f"Design: a0 = {a0:.10f} ({a0 * ACCEL_MM_S2:.4f} mm/s^2); a re-solve from the naive start: "
        f"tf* = {float(check.tf) * DAYS:.9f} days ({jt.status_name(check.status)}).",
    ]

    # sensitivities along a range of sails: one vmapped call of the same function
    grid = np.linspace(0.8 * a0, 1.25 * a0, args_.grid)
    batch = {**args, "a0": jnp.asarray(grid)}
    (tfs, (_, status)), grads = jax.vmap(f, in_axes=({"a0": 0, "r_f": None, "mu": None}, None))(batch, start)
    lines += [
        "",
        "## Sensitivities of the minimum transfer time (implicit function theorem, per sail)",
        "",
        "| a0 | tf* [days] | dtf*/da0 [days] | dtf*/dr_f [days/AU] | dtf*/dmu [days] | status |",
        "|---:|---:|---:|---:|---:|---|",
        *(
            f"| {a:.4f} | {float(t) * DAYS:.3f} | {float(g0) * DAYS:.2f} | {float(gr) * DAYS:.2f} | "
            f"{float(gm) * DAYS:.2f} | {jt.status_name(s)} |"
            for a, t, g0, gr, gm, s in zip(grid, tfs, grads["a0"], grads["r_f"], grads["mu"], status)
        ),
    ]
    text = "\n".join(lines)
    print(text)
    (out / "design_loop.md").write_text(text + "\n")

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    ax.plot(grid, np.asarray(tfs) * DAYS, "o:", color="C0", lw=1, label="tf*(a0), solved", zorder=3)
    for a, t, g in zip(grid, np.asarray(tfs), np.asarray(grads["a0"])):
        h = 0.04 * a0
        ax.plot([a - h, a + h], [(t - g * h) * DAYS, (t + g * h) * DAYS], color="C1", lw=4, alpha=0.5)
    ax.plot([], [], color="C1", lw=4, alpha=0.5, label="tangents from dtf*/da0")
    ax.axhline(args_.days, color="0.5", ls="--", lw=1)
    ax.plot([a0], [args_.days], "s", color="C3", label=f"design a0 = {a0:.5f}")
    ax.set_xlabel("characteristic acceleration a0 [normalized]")
    ax.set_ylabel("minimum transfer time [days]")
    ax.set_title("Solar sail Earth -> Mars orbit: a design loop through the optimizer")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "design_loop.png", dpi=110)
    plt.close(fig)
    print(f"\nwrote design_loop.md and design_loop.png to {out} ({time.perf_counter() - t0:.1f} s)")
    return {"a0": a0, "check_tf_days": float(check.tf) * DAYS, "check_status": check.status, "rows": rows}


if __name__ == "__main__":
    main()
