"""Shared test helpers."""

import functools

import jax.numpy as jnp
import numpy as np

import jaxtraj as jt

ALL_CASES = range(1, 8)

#: Relative perturbations of a start the size of a change of CPU or XLA fusion (issue 17).
ROUNDOFF_EPS = (0.0, 1e-12, 1e-10)
#: KalmanSQP with the trust-region globalization (exact Hessians): the default
TRUST_REGION = jt.KalmanSQP()
#: KalmanSQP with BFGS and the merit line search (the default until 2026-12-04)
LINE_SEARCH = jt.KalmanSQP(hessian="bfgs", globalization="line-search")


def perturbed_starts(a0, seed=17, absolute=False):
    """`a0 * (1 + eps r)` for each eps of `ROUNDOFF_EPS`, r a fixed standard normal vector:
    the starts a solver must treat alike (SUCCESS every time, the same optimum within its
    stated tolerance). With `absolute`, `a0 + eps r max(|a0|, 1)` instead, which also moves
    the zero components (a start at rest). Shape `(len(ROUNDOFF_EPS), a0.size)`."""
    a0 = np.asarray(a0, dtype=np.float64)
    r = np.random.default_rng(seed).standard_normal(a0.shape)
    if absolute:
        return jnp.asarray(np.stack([a0 + eps * r * np.maximum(np.abs(a0), 1.0) for eps in ROUNDOFF_EPS]))
    return jnp.asarray(np.stack([a0 * (1.0 + eps * r) for eps in ROUNDOFF_EPS]))


def rel_err(got, want):
    """Max-abs difference relative to the max-abs of the reference."""
    got, want = np.asarray(got), np.asarray(want)
    return float(np.max(np.abs(got - want)) / max(np.max(np.abs(want)), 1e-300))


def family_examples():
    """One Earth-Mars-compatible (problem, control, a) per control family and layout, with
    parameters away from the straight line so that every parameter matters."""
    prob = jt.problems.earth_mars.problem()
    rng = np.random.default_rng(0)
    out = []
    controls = [
        jt.controls.PiecewiseLinear(4),
        jt.controls.PiecewiseLinear(4, continuous=True, free_times=True),
        jt.controls.PiecewiseLinear(3, continuous=False, free_times=True),
        jt.controls.PiecewiseLinear(3, continuous=False, free_times=False),
        jt.controls.PiecewiseParabolic(2),
        jt.controls.PiecewiseParabolic(2, free_times=False),
        jt.controls.PiecewiseConstant(3),
        jt.controls.PiecewiseConstant(3, free_times=False),
        jt.controls.SaturatedSpline(4, 0, -1.0, 6.0),
        jt.controls.SaturatedSpline(4, 1, -1.0, 6.0),
        jt.controls.SaturatedSpline(4, 2, -1.0, 6.0),
        jt.controls.SaturatedSpline(4, 3, -1.0, 6.0),
        jt.controls.SaturatedSpline(3, 3, -1.0, 6.0, free_durations=False),
    ]
    for ctrl in controls:
        a = np.asarray(ctrl.initial_guess(3.4, 0.0, 1.5 * np.pi))
        noise = 0.05 * rng.standard_normal(a.shape)
        noise[list(ctrl.time_indices)] *= 0.2  # keep the times ordered
        out.append((prob, ctrl, jnp.asarray(a + noise)))
    # Saturation active on whole segments (degree 0: levels (c_k + c_{k+1}) / 2): the first
    # level is clipped at 0.5 and the last at 3.0, so du/da = 0 there. (With degree >= 1 a
    # saturation kink falls inside an RK4 step, where fixed-step integration drops to low
    # order and the unit/forward agreement is only O(h); see SaturatedSpline.)
    sat = jt.controls.SaturatedSpline(4, 0, 0.5, 3.0)
    out.append((prob, sat, jnp.array([0.8, 0.9, 0.85, 0.8, -0.5, 0.9, 2.2, 3.4, 4.0])))
    return out


def counting_problem(prob):
    """A copy of `prob` whose dynamics count how often they are traced: returns
    `(problem, counter)` with `counter["traces"]`."""
    counter = {"traces": 0}
    base = prob.dynamics

    def counting(t, x, u, args):
        counter["traces"] += 1
        return base(t, x, u, args)

    return jt.Problem(counting, prob.x0, prob.terminal, prob.constraint_names, args=prob.args), counter


def load_script(folder, name):
    """Import `<folder>/<name>.py` (`examples`, `benchmarks`: scripts, not a package) as a
    module, with the folder on `sys.path` as when the script runs (`examples/_args.py`)."""
    import importlib.util
    import os
    import sys

    where = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), folder)
    if where not in sys.path:
        sys.path.append(where)
    path = os.path.join(where, f"{name}.py")
    spec = importlib.util.spec_from_file_location(f"{name}_{folder}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_example(name):
    """`examples/<name>.py` as a module."""
    return load_script("examples", name)


@functools.cache
def load_benchmark(name):
    """`benchmarks/<name>.py` as a module, once per process."""
    return load_script("benchmarks", name)


def energy_problem(**changes):
    """`jt.problems.analytic.min_energy_double_integrator()` rebuilt as a `jt.Problem` from its
    functions, with `changes` (bounds, names, ...) as more keywords."""
    base = jt.problems.analytic.min_energy_double_integrator(1.0)
    return jt.Problem(
        base.dynamics,
        base.x0,
        base.terminal,
        base.constraint_names,
        objective=base.objective,
        args=base.args,
        **changes,
    )


def moved_start(name, seed):
    """`(problem, control, start)` of Earth-Mars case `case-N` or of a gallery problem, the
    start moved by 5 % of max(|a_i|, 1) in a random direction (a point off every symmetry
    of the start, for derivative checks)."""
    if name.startswith("case-"):
        prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(int(name[5:]))
    else:
        entry = jt.problems.classic.get(name)
        prob, ctrl, a0 = entry.problem, entry.control, entry.start
    rng = np.random.default_rng(seed)
    return prob, ctrl, jnp.asarray(a0 + 0.05 * rng.normal(size=a0.shape) * np.maximum(1.0, np.abs(a0)))


def reach_problem():
    """x'' = u, x(0) = v(0) = 0, |u| <= 1, reach x(tf) >= 1 (a terminal inequality), v free,
    least tf: u = 1 throughout, tf* = sqrt(2) (closed form); the optimum has as many active
    rows (the reach and the upper bounds) as parameters (issue 49's textbook case)."""
    return jt.Problem(
        lambda t, x, u, args: jnp.array([x[1], u[0]]),
        jnp.zeros(2),
        lambda tf, xf, args: jnp.zeros(0),
        (),
        terminal_inequality=lambda tf, xf, args: jnp.array([1.0 - xf[0]]),
        terminal_inequality_names=("reach",),
        control_lower=-1.0,
        control_upper=1.0,
    )


def gain_reach():
    """`(problem, control)`: x' = 2 u from 0 to x(1) = 1 at least energy, u = 1/2, objective
    0.125 (closed form), on 4 linear pieces."""
    problem = jt.Problem(
        lambda t, x, u, args: 2.0 * u, np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",), num_controls=1,
        running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0,
    )  # fmt: skip
    return problem, problem.parametrize(jt.controls.PiecewiseLinear(4))
