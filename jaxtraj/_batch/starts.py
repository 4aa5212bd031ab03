"""`jt.random_starts` and `jt.multistart`: reproducible random starts and a summary of the
local optima found."""

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_inputs, check_memory, memory_refusal
from .._driver import AbstractSolver
from .._sensitivity import path_values
from .._simulate import RK4, AbstractSimulator, check_simulator, final_state, simulation_status
from .._solution import Solution
from .._status import STATUS_NAMES, Status
from ..controls import AbstractControl, value_bounds
from .solve import check_int, solve_batch


@eqx.filter_jit
def _draws(control, around, key, n):
    """Knots of `around`, their Jacobian, and the normal draws of `random_starts` (one
    compiled call instead of many small eager ones)."""
    k_dur, k_val = jax.random.split(key)
    z = jax.random.normal(k_dur, (n, control.num_segments), jnp.float64)
    noise = jax.random.normal(k_val, (n, control.num_params), jnp.float64)
    return control.knots(around), jax.jacfwd(control.knots)(around), z, noise


@eqx.filter_jit
def _all_knots(control, a):
    return jax.vmap(control.knots)(a)


@eqx.filter_jit
def _usable(problem, control, starts, simulator):
    """Per start: the integration succeeds and the final state, objective, terminal values
    (and path constraints on the grid) are finite: what a solver's first evaluation needs."""

    def one(a):
        if problem.path is None:
            xf, status = final_state(problem, control, a, simulator)
            ok, values = status == Status.SUCCESS, []
        else:
            xf, (_, C, ok) = path_values(problem, control, a, simulator)
            values = [C]
        tf = control.tf(a)
        ends = (problem.objective, problem.terminal, problem.terminal_inequality)
        values += [fn(tf, xf, problem.args) for fn in ends if fn is not None]
        return simulation_status(ok, xf, *values) == Status.SUCCESS

    return jax.vmap(one)(starts)


def _draw(problem, control, key, n, around, spread):
    """`n` starts from one key (the recipe of `random_starts`), as a NumPy array."""
    t_idx = np.asarray(control.time_indices, int)
    other = np.setdiff1d(np.arange(control.num_params), t_idx)
    knots, jac, z, noise = (np.asarray(x) for x in _draws(control, around, key, n))
    # (a huge spread overflows to inf/NaN: refused below with a clear error, not warned about)
    with np.errstate(over="ignore", invalid="ignore"):
        # times: perturb the knot gaps multiplicatively, solve the time parameters back
        gaps = np.diff(knots)
        jac = jac[:, t_idx]  # knots are linear in the time parameters
        t_spread = float(np.mean(spread[t_idx])) if t_idx.size else 0.0
        new_knots = np.concatenate([np.zeros((n, 1)), np.cumsum(gaps * np.exp(t_spread * z), axis=1)], axis=1)
        if problem.final_time is not None:  # tf fixed: the perturbed gaps shared out over [0, T]
            new_knots *= knots[-1] / new_knots[:, -1:]
        times = np.linalg.lstsq(jac, new_knots.T, rcond=None)[0].T
        # other entries: additive noise on their own scale, then the bounds
        vals = np.asarray(around)[other]
        scale = float(np.sqrt(np.mean(vals**2))) if vals.size and np.any(vals != 0) else 1.0
        starts = np.asarray(around)[None, :] + spread * scale * noise
        starts[:, t_idx] = times
        idx, lo, hi = value_bounds(control, problem.control_lower, problem.control_upper)
        starts[:, idx] = np.clip(starts[:, idx], np.asarray(lo), np.asarray(hi))
        if problem.free_initial_state:  # free initial-state components within their bounds
            idx = np.asarray(control.parameter_indices, int)
            starts[:, idx] = np.clip(starts[:, idx], *problem.initial_state_bounds)
    # check the promise (vectorized version of control.validate's ordering checks)
    kn = np.asarray(_all_knots(control, jnp.asarray(starts)))
    if not (np.all(np.isfinite(starts)) and np.all(np.diff(kn, axis=1) > 0) and np.all(kn[:, -1] > 0)):
        raise ValueError(
            "`around`/`spread`: could not generate valid starts (not finite, or knots not increasing); lower `spread`."
        )
    return starts


def random_starts(
    problem,
    control: AbstractControl,
    key,
    n: int,
    around,
    spread=0.1,
    *,
    simulator: AbstractSimulator = RK4(),
    redraws: int = 8,
):
    """`n` reproducible random starting vectors around `around`, valid for `control`.

    - Segment durations (knot gaps) are multiplied by independent factors exp(spread z), and
      the time parameters are solved back from the new knots (exact for node-time and
      duration layouts; a least-squares fit of tf when only tf is free). Times therefore stay
      increasing and tf > 0 by construction.
    - Every other entry gets additive noise spread * s * z, with s the RMS of those entries
      of `around` (1 if they are all zero); `spread` may also be an array `(num_params,)`.
    - Control values (the family's `value_indices`) are clipped to the bounds of the problem
      (`control_lower/upper`) and the family's own `limits`, free initial-state components
      to theirs.
    - Each start is integrated once with `simulator` (keyword-only, default `jt.RK4(100)`,
      `jt.solve`'s): a start whose integration fails, or whose final state, objective,
      terminal or path values are not finite, cannot begin a search (its solve would end
      NONFINITE at step 0). It is replaced by the next usable start of up to `redraws`
      further rounds of `n` draws (keys `jax.random.fold_in(key, r)`, r = 1, 2, ...); the
      usable starts of the first round keep their places. A start still unusable after
      them is returned as drawn. `redraws=0` skips the check.
    """
    around = check_inputs(problem, control, around)
    n = check_int("n", n, 1)
    check_memory("n", 8 * n * control.num_params, f"{n:,} starts of {control.num_params} parameters")
    typed = isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key) and key.shape == ()
    raw = isinstance(key, (jax.Array, np.ndarray)) and key.dtype == np.uint32 and key.shape == (2,)
    if not (typed or raw):
        raise ValueError(f"`key` must be a JAX PRNG key (jax.random.key(seed)); got {key!r}.")
    try:
        spread = np.broadcast_to(np.asarray(spread, dtype=np.float64), (control.num_params,))
    except (TypeError, ValueError):
        raise ValueError(
            f"`spread` must be a number or {control.num_params} numbers (one per parameter); got {spread!r}."
        ) from None
    if not np.all(np.isfinite(spread) & (spread >= 0)):
        raise ValueError(f"`spread` must be >= 0 and finite; got {spread}.")
    redraws = check_int("redraws", redraws, 0)
    check_simulator(simulator)
    with memory_refusal("jt.random_starts", "use a smaller n"):
        starts = _draw(problem, control, key, n, around, spread)
        if redraws:
            bad = ~np.asarray(_usable(problem, control, jnp.asarray(starts), simulator))
            for r in range(1, redraws + 1):
                if not bad.any():
                    break
                more = _draw(problem, control, jax.random.fold_in(key, r), n, around, spread)
                good = np.flatnonzero(np.asarray(_usable(problem, control, jnp.asarray(more), simulator)))
                slots = np.flatnonzero(bad)[: good.size]
                starts[slots] = more[good[: slots.size]]
                bad[slots] = False
        return jnp.asarray(starts)


@dataclasses.dataclass(frozen=True)
class MultistartResult:
    """Outcome of `jt.multistart`.

    - `starts`: `(n, num_params)` starting vectors; `solutions`: the batch `Solution`.
    - `success`: bool `(n,)`; `success_rate`: their mean.
    - `best_index`: the successful start with the lowest objective (-1 if none); `best`:
      its `Solution` (unbatched) or None.
    - `optima`: distinct local optima among the successful starts, best first, as
      `(objective, count, index of its best start)`; objectives closer than
      `tol (1 + |G|)` (chained) are one optimum.
    - `wall_time`: seconds for the whole call (including compilation); `solves_per_second`.
    """

    starts: jax.Array
    solutions: Solution
    success: np.ndarray
    best_index: int
    optima: tuple
    tol: float
    wall_time: float

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.success))

    @property
    def solves_per_second(self) -> float:
        return len(self.success) / self.wall_time

    @property
    def best(self) -> Solution | None:
        if self.best_index < 0:
            return None
        return jax.tree.map(lambda x: x[self.best_index], self.solutions)

    def summary(self) -> str:
        """A readable report: counts, timing, status breakdown and the table of optima."""
        n = len(self.success)
        sols = self.solutions
        lines = [
            f"multistart: {n} starts, {int(self.success.sum())} SUCCESS ({self.success_rate:.1%}), "
            f"{self.wall_time:.2f} s ({self.solves_per_second:.1f} solves/s, compilation included)",
        ]
        counts = {name: int(np.sum(np.asarray(sols.status == getattr(Status, name)))) for name in STATUS_NAMES}
        lines.append("status: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v))
        b = self.best  # (None exactly when best_index < 0)
        if b is not None:
            lines.append(
                f"best: start {self.best_index}, objective {float(b.objective):.10g}, "
                f"max|E| {float(b.max_constraint_error):.2e}, {int(b.iterations)} iterations"
            )
            lines.append("")
            lines.append(f"| optimum | objective (tol {self.tol:g}) | starts | share of successes | best start |")
            lines.append("|---:|---:|---:|---:|---:|")
            ns = max(int(self.success.sum()), 1)
            for i, (g, c, j) in enumerate(self.optima):
                lines.append(f"| {i + 1} | {g:.10g} | {c} | {c / ns:.1%} | {j} |")
        return "\n".join(lines)

    def __str__(self):
        return self.summary()


def _cluster(values, indices, tol):
    """Sort and chain objectives within tol (1 + |G|) of their neighbour: `(best, count, index)`."""
    order = np.argsort(values, kind="stable")
    groups = []
    for j in order:
        g = values[j]
        if groups and g - groups[-1][3] <= tol * (1.0 + abs(g)):
            groups[-1][1] += 1
            groups[-1][3] = g
        else:
            groups.append([g, 1, int(indices[j]), g])  # best value, count, best index, last value
    return tuple((float(g), c, i) for g, c, i, _ in groups)


def multistart(
    problem,
    control: AbstractControl,
    key,
    n: int,
    *,
    around=None,
    spread=0.1,
    solver: AbstractSolver | None = None,
    tol: float = 1e-6,
    **solve_batch_kwargs,
) -> MultistartResult:
    """Solve from `n` random starts around `around` and summarize the optima found.

    **Arguments:**

    - `key`: a JAX PRNG key; the same key gives the same starts (and results).
    - `n`: number of starts.
    - `around`: the centre vector (required), e.g. `control.initial_guess(tf, u0, u1)`.
    - `spread`: relative size of the perturbation (see `jt.random_starts`, which draws the
      starts and replaces those that the solves' `simulator` cannot integrate).
    - `solver`: as for `jt.solve`; `tol`: objectives closer than `tol (1 + |G|)` count as
      one local optimum.
    - other keywords go to `jt.solve_batch` (`chunk_size`, `devices`, `out`, `max_steps`, ...).

    **Returns:** a `MultistartResult`; `print(result)` shows the summary table.
    """
    if around is None:
        raise ValueError(
            "`around` is required: the vector to perturb, e.g. control.initial_guess(tf, u_start, u_end) "
            "or a previous solution's params."
        )
    if not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and 0 <= tol < math.inf):
        raise ValueError(f"`tol` must be a finite number >= 0; got {tol!r}.")
    t0 = time.perf_counter()
    simulator = solve_batch_kwargs.get("simulator", RK4())
    starts = random_starts(problem, control, key, n, around, spread, simulator=simulator)
    sols = solve_batch(problem, control, starts, solver, **solve_batch_kwargs)
    wall = time.perf_counter() - t0
    ok = np.asarray(sols.status == Status.SUCCESS)
    obj = np.asarray(sols.objective)
    idx = np.flatnonzero(ok)
    best = int(idx[np.argmin(obj[idx])]) if idx.size else -1
    optima = _cluster(obj[idx], idx, float(tol)) if idx.size else ()
    return MultistartResult(starts, sols, ok, best, optima, float(tol), wall)


__all__ = ["MultistartResult", "multistart", "random_starts", "solve_batch"]
