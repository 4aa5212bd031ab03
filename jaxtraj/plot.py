"""Figures (matplotlib, imported lazily; never traced)."""

from typing import NamedTuple

import numpy as np


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


class OrbitLayout(NamedTuple):
    """Where a planar orbit problem keeps its polar coordinates: state indices of the
    `radius` and the `tangential_velocity`, and of the `polar_angle` if it is a state
    (None: theta is integrated from theta' = v_t / r)."""

    radius: int
    tangential_velocity: int
    polar_angle: int | None = None


def orbit_layout(problem) -> OrbitLayout:
    """The `OrbitLayout` of a problem, from its state names "radius", "tangential velocity"
    and (optional) "polar angle" (as in `problems.earth_mars`: radial velocity, radius,
    tangential velocity; and `problems.solar_sail`: radius, polar angle, radial velocity,
    tangential velocity). Raises `ValueError` if the names are not there."""
    names = tuple(problem.state_names)
    missing = [n for n in ("radius", "tangential velocity") if n not in names]
    if missing:
        raise ValueError(
            f"problem {problem.name!r} has no state named {' or '.join(map(repr, missing))} "
            f"(state names {names}); pass an OrbitLayout(radius=..., tangential_velocity=..., polar_angle=...)."
        )
    theta = names.index("polar angle") if "polar angle" in names else None
    return OrbitLayout(names.index("radius"), names.index("tangential velocity"), theta)


def _layout(layout) -> OrbitLayout:
    if isinstance(layout, OrbitLayout):
        return layout
    if hasattr(layout, "state_names"):
        return orbit_layout(layout)
    raise ValueError(f"`layout` must be a jaxtraj Problem or an OrbitLayout; got {type(layout).__name__}.")


def polar_angle(traj, layout):
    """theta(t) of a planar orbit trajectory. `layout`: the problem (see `orbit_layout`) or
    an `OrbitLayout`. A polar-angle state is read directly; otherwise theta' = v_t / r is
    integrated by the trapezoid rule from theta(0) = 0."""
    lay = _layout(layout)
    x = np.asarray(traj.x)
    if lay.polar_angle is not None:
        return x[:, lay.polar_angle].copy()
    t = np.asarray(traj.t)
    rate = x[:, lay.tangential_velocity] / x[:, lay.radius]
    dt = np.diff(t)
    return np.concatenate([[0.0], np.cumsum(0.5 * dt * (rate[1:] + rate[:-1]))])


def orbit_xy(traj, layout):
    """Cartesian coordinates `(x, y)` in the orbital plane (x axis through the start when
    theta(0) = 0)."""
    lay = _layout(layout)
    theta = polar_angle(traj, lay)
    r = np.asarray(traj.x)[:, lay.radius]
    return r * np.cos(theta), r * np.sin(theta)


def orbit_plane(ax, traj, r_target, *, layout, label="transfer", color="C0"):
    """The transfer in the orbital plane, with the initial and target circular orbits.
    `layout`: the problem or an `OrbitLayout` (see `orbit_layout`)."""
    lay = _layout(layout)
    xs, ys = orbit_xy(traj, lay)
    r0 = float(np.asarray(traj.x)[0, lay.radius])
    circle = np.linspace(0, 2 * np.pi, 361)
    ax.plot(r0 * np.cos(circle), r0 * np.sin(circle), color="0.55", lw=1, ls="--", label=f"initial orbit (r = {r0:g})")
    ax.plot(
        r_target * np.cos(circle),
        r_target * np.sin(circle),
        color="C3",
        lw=1,
        ls="--",
        label=f"target orbit (r = {r_target:g})",
    )
    ax.plot(xs, ys, color=color, lw=2, label=label)
    ax.plot([xs[-1]], [ys[-1]], "o", color=color)
    ax.plot([0], [0], marker="*", color="orange", ms=12, ls="none", label="Sun")
    ax.set_aspect("equal")
    ax.set_xlabel("x [r0 = 1 AU]")
    ax.set_ylabel("y [r0 = 1 AU]")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)


def plot_controls(ax, problem, traj):
    t = np.asarray(traj.t)
    for j, name in enumerate(problem.control_names):
        ax.plot(t, np.asarray(traj.u[:, j]), lw=2, label=name)
    for k in np.asarray(traj.knots)[1:-1]:
        ax.axvline(k, color="0.8", lw=0.8, zorder=0)
    ax.set_xlabel("time [normalized units]")
    ax.set_ylabel("control")
    ax.set_title("control history (grey: segment boundaries)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def plot_states(ax, problem, traj):
    t = np.asarray(traj.t)
    for j, name in enumerate(problem.state_names):
        ax.plot(t, np.asarray(traj.x[:, j]), lw=1.5, label=name)
    ax.set_xlabel("time [normalized units]")
    ax.set_ylabel("state [normalized units]")
    ax.set_title("state histories")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def plot_convergence(ax, sol):
    """max |E_i|, the tolerance e_a in force and |G - G_final| per candidate step (log scale)."""
    n = int(sol.steps)
    h = sol.history
    steps = np.arange(1, n + 1)
    G = np.asarray(h.objective[:n])
    ax.semilogy(steps, np.asarray(h.max_constraint_error[:n]), color="C3", lw=1.5, label="max |E_i|")
    ax.semilogy(steps, np.asarray(h.constraint_tolerance[:n]), color="C3", lw=0.8, ls=":", label="e_a in force")
    gap = np.abs(G - float(sol.objective))
    ax.semilogy(steps, np.where(gap > 0, gap, np.nan), color="C0", lw=1.5, label="|objective - final objective|")
    ax.set_xlabel("candidate step (one integration each)")
    ax.set_ylabel("error (normalized units)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(f"convergence (final objective {float(sol.objective):.8g})")


def _check_one(sol, traj):
    """One (unbatched) `jt.Solution` and `jt.Trajectory`, or a ValueError naming the
    argument (a batch, or None, failed deep inside NumPy, JAX or the plotting code)."""
    from ._simulate import Trajectory
    from ._solution import Solution

    if not isinstance(sol, Solution) or np.ndim(sol.tf) != 0:
        batch = f" with a batch axis {np.shape(sol.tf)}" if isinstance(sol, Solution) else ""
        raise ValueError(f"`sol` must be one jt.Solution (a batch's `sols[i]`); got {type(sol).__name__}{batch}.")
    if not isinstance(traj, Trajectory) or np.ndim(traj.knots) != 1:
        batch = f" with a batch axis {np.shape(traj.knots)[:-1]}" if isinstance(traj, Trajectory) else ""
        raise ValueError(
            f"`traj` must be one jt.Trajectory (jt.simulate of `sol.params`); got {type(traj).__name__}{batch}."
        )


def solution_figure(problem, control, sol, traj, path, *, title=None, r_target=None):
    """A 2x2 overview: control history, states, convergence history, and (for orbit
    transfers, when `r_target` is given) the trajectory in the orbital plane, its state
    layout taken from `problem` (`orbit_layout`)."""
    _check_one(sol, traj)
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    plot_controls(axes[0, 0], problem, traj)
    plot_states(axes[0, 1], problem, traj)
    plot_convergence(axes[1, 0], sol)
    if r_target is not None:
        orbit_plane(axes[1, 1], traj, r_target, layout=problem)
        axes[1, 1].set_title("trajectory in the orbital plane")
    else:
        axes[1, 1].axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_figures(folder, problem, control, sol, traj, *, title=None, r_target=None):
    """`solution.png` (overview), `histories.png` (control and states), `convergence.png`
    and, for orbit transfers (`r_target` given; state layout from `problem`, see
    `orbit_layout`), `orbit.png`. Returns the file names written."""
    import os

    plt = pyplot()
    names = ["solution.png"]
    solution_figure(problem, control, sol, traj, os.path.join(folder, "solution.png"), title=title, r_target=r_target)
    fig, axes = plt.subplots(2, 1, figsize=(9, 8), sharex=True)
    plot_controls(axes[0], problem, traj)
    plot_states(axes[1], problem, traj)
    axes[0].set_xlabel("")
    fig.tight_layout()
    fig.savefig(os.path.join(folder, "histories.png"), dpi=110)
    plt.close(fig)
    names.append("histories.png")
    fig, ax = plt.subplots(figsize=(9, 5))
    plot_convergence(ax, sol)
    fig.tight_layout()
    fig.savefig(os.path.join(folder, "convergence.png"), dpi=110)
    plt.close(fig)
    names.append("convergence.png")
    if r_target is not None:
        fig, ax = plt.subplots(figsize=(7, 7))
        orbit_plane(ax, traj, r_target, layout=problem)
        ax.set_title(title or "trajectory in the orbital plane", fontsize=10)
        fig.tight_layout()
        fig.savefig(os.path.join(folder, "orbit.png"), dpi=110)
        plt.close(fig)
        names.append("orbit.png")
    return names


def batch_figure(path, problem, objectives, success, trajectories, *, title=None):
    """Multi-start overview: histogram of the final objectives of the successful starts, and
    the control histories of (up to 50 of) them overlaid. `trajectories`: `jt.Trajectory`s."""
    objectives, success = np.asarray(objectives), np.asarray(success)
    if objectives.ndim != 1 or success.shape != objectives.shape or success.dtype != bool:
        raise ValueError(
            f"`objectives` and `success` must be one value and one bool per start; got {objectives.dtype} "
            f"{objectives.shape} and {success.dtype} {success.shape}."
        )
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    obj = objectives[success]
    if obj.size:
        ax1.hist(obj, bins=min(40, max(5, obj.size // 3)), color="C0", alpha=0.8)
    ax1.set(
        xlabel="final objective", ylabel="starts", title=f"{obj.size} / {np.asarray(success).size} starts successful"
    )
    ax1.grid(alpha=0.3)
    best = np.min(obj) if obj.size else None
    names = problem.control_names or tuple(f"u{j}" for j in range(problem.num_controls))
    for i, traj in enumerate(trajectories):
        u = np.asarray(traj.u)
        for j in range(u.shape[1]):
            ax2.plot(traj.t, u[:, j], color=f"C{j}", lw=0.8, alpha=0.35, label=names[j] if i == 0 else None)
    ax2.set(
        xlabel="t",
        ylabel="u",
        title=f"controls of {len(trajectories)} successful starts"
        + (f" (best objective {best:.6g})" if best is not None else ""),
    )
    ax2.grid(alpha=0.3)
    if trajectories:
        ax2.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
