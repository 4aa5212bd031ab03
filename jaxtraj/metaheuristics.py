"""Population metaheuristics for box-constrained minimization: Grey Wolf Optimizer, Whale
Optimization Algorithm (linear or quadratic decay of its parameter a) and Dragonfly
Algorithm with Levy flight, as compared for solar-sail transfers in seed 003.

Each optimizer is an `init` / `step` / `terminate` state machine over an array-only
`PopulationState`; one `step` is one generation, the whole population evaluated with
`jax.vmap(fn)`. `minimize` drives it in a `lax.while_loop` inside one `eqx.filter_jit`:

    res = jt.metaheuristics.minimize(jt.metaheuristics.GreyWolf(), fn, lower, upper, key)

New positions are clipped to the box [lower, upper], a non-finite fn value counts as +inf,
and the best point is the best ever evaluated. The same key gives a bit-identical result,
also inside `jax.vmap` over keys (hence the integer-ratio schedules of `_schedule`).

(The rules common to all three and every decision where seed 003 is unclear or silent:
docs/solvers/metaheuristics.md.)
"""

import abc
import dataclasses
import math

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
from jax import lax

from ._checks import check_memory, is_count, require_float64
from ._status import Status, as_indexable

_DECAYS = ("linear", "quadratic")


class PopulationState(eqx.Module):
    """Array-only state of a population optimizer (one generation per `step`).

    - `population` (NP, n) and `fitness` (NP,): the current positions and their values
      (non-finite values stored as +inf).
    - `best_x`, `best_f`: the best point ever evaluated and its value.
    - `iteration`: generations done; `evaluations`: fn evaluations done.
    - `key`: the PRNG key for the next generation.
    - `history_best` (K,): `best_f` after each generation, NaN where not yet run.
    - `lower`, `upper`: the box.
    - `aux`: algorithm-specific arrays (GWO leaders; DA step vectors and enemy; WOA none).
    """

    population: jax.Array
    fitness: jax.Array
    best_x: jax.Array
    best_f: jax.Array
    iteration: jax.Array
    evaluations: jax.Array
    key: jax.Array
    history_best: jax.Array
    lower: jax.Array
    upper: jax.Array
    aux: tuple


class AbstractPopulationOptimizer(eqx.Module):
    """A population metaheuristic as a state machine over a `PopulationState`.

    Fields hold only static configuration (population size, variant names); changing
    them recompiles `minimize`.
    """

    @abc.abstractmethod
    def init(self, fn, lower, upper, key, max_iterations: int) -> PopulationState:
        """Uniform initial population in [lower, upper], evaluated (no generation yet)."""

    @abc.abstractmethod
    def step(self, fn, state: PopulationState) -> PopulationState:
        """One generation: move every member, clip to the box, evaluate with vmap(fn)."""

    @abc.abstractmethod
    def terminate(self, state: PopulationState) -> jax.Array:
        """Whether the generation budget is spent (bool scalar)."""


# ---------------------------------------------------------------------------------------
# Bookkeeping shared by the optimizers
# ---------------------------------------------------------------------------------------


def _evaluate(fn, x):
    """vmap(fn) over the rows of x, as float64 with non-finite values replaced by +inf."""
    f = jax.vmap(fn)(x)
    if f.shape != x.shape[:1]:
        raise ValueError(f"`fn` must return a scalar for an input of shape {x.shape[1:]}; got shape {f.shape[1:]}.")
    if not jnp.issubdtype(f.dtype, jnp.floating) and not jnp.issubdtype(f.dtype, jnp.integer):
        raise ValueError(f"`fn` must return a real number; got dtype {f.dtype}.")
    f = f.astype(x.dtype)
    return jnp.where(jnp.isfinite(f), f, jnp.inf)


def _uniforms(key, dtype, *shapes):
    """The next key and uniform numbers on [0, 1) of the given shapes, drawn in one call:
    every separate jax.random call adds ~0.3 s of XLA:CPU compile time."""
    key, sub = jax.random.split(key)
    sizes = [math.prod(s) for s in shapes]
    u = jax.random.uniform(sub, (sum(sizes),), dtype=dtype)
    offsets = [sum(sizes[:i]) for i in range(len(sizes) + 1)]
    return key, [u[a:b].reshape(s) for a, b, s in zip(offsets[:-1], offsets[1:], shapes)]


def _initial_state(fn, lower, upper, key, population, max_iterations, make_aux):
    key, (u,) = _uniforms(key, lower.dtype, (population, lower.shape[0]))
    x = lower[None] + (upper - lower)[None] * u
    f = _evaluate(fn, x)
    i = jnp.argmin(f)
    return PopulationState(
        population=x,
        fitness=f,
        best_x=x[i],
        best_f=f[i],
        iteration=jnp.array(0),
        evaluations=jnp.array(population),
        key=key,
        history_best=jnp.full(max_iterations, jnp.nan, dtype=lower.dtype),
        lower=lower,
        upper=upper,
        aux=make_aux(x, f),
    )


def _advance(fn, state, x, key, update_aux):
    """Clip the moved population `x` to the box, evaluate it, and update the best point,
    counters, history and (through `update_aux(aux, x, f)`) the algorithm's own arrays."""
    x = jnp.where(jnp.isnan(x), state.population, x)  # e.g. 0 * inf from a Levy step
    x = jnp.clip(x, state.lower[None], state.upper[None])
    f = _evaluate(fn, x)
    i = jnp.argmin(f)
    better = f[i] < state.best_f
    best_f = jnp.where(better, f[i], state.best_f)
    return dataclasses.replace(
        state,
        population=x,
        fitness=f,
        best_x=jnp.where(better, x[i], state.best_x),
        best_f=best_f,
        iteration=state.iteration + 1,
        evaluations=state.evaluations + x.shape[0],
        key=key,
        history_best=state.history_best.at[state.iteration].set(best_f),
        aux=update_aux(state.aux, x, f),
    )


def _normal(u):
    """Standard normal numbers from uniform ones on [0, 1) (inverse CDF, as jax.random.normal)."""
    lo = jnp.nextafter(jnp.array(-1.0, u.dtype), 0.0)
    return jnp.sqrt(2.0) * jax.scipy.special.erfinv(jnp.maximum(2.0 * u - 1.0, lo))


def _schedule(state, num, den):
    """A schedule of the generation about to run, k (0-based) of K: num(k, K) / den(K) with
    integer num and den, so that the only floating-point operation is one division.

    (Computed as floats, e.g. 2 (1 - k/K), XLA:CPU may fuse a multiply and an add into one
    rounding in the single program and not in the batched one; a one-ulp difference in a
    then makes a run under vmap differ from the same run alone.)
    """
    k, K, dtype = state.iteration, state.history_best.shape[0], state.population.dtype
    return jnp.asarray(num(k, K)).astype(dtype) / jnp.asarray(den(K), dtype=dtype)


def _budget_spent(state):
    return state.iteration >= state.history_best.shape[0]


def _decay(kind, state):
    """a = 2 (1 - k/K) ("linear") or 2 (1 - k^2/K^2) ("quadratic")."""
    if kind == "linear":
        return _schedule(state, lambda k, K: 2 * (K - k), lambda K: K)
    return _schedule(state, lambda k, K: 2 * (K * K - k * k), lambda K: K * K)


def _check_population(name, population, minimum):
    if not is_count(population, minimum):  # (an int32 count in the compiled state)
        raise ValueError(f"{name}: `population` must be an int in {minimum}..2**31 - 1; got {population!r}.")


def _check_decay(name, decay):
    if decay not in _DECAYS:
        raise ValueError(f"{name}: `decay` must be one of {_DECAYS}; got {decay!r}.")


# ---------------------------------------------------------------------------------------
# Grey Wolf Optimizer
# ---------------------------------------------------------------------------------------


class GreyWolf(AbstractPopulationOptimizer):
    """Grey Wolf Optimizer (Mirjalili, Mirjalili & Lewis 2014; seed 003).

    With the leaders x_m, m in {alpha, beta, gamma} (the three best points so far), every
    wolf j moves to

        D_m = |C_m * x_m - x_j|,   x_{j,m} = x_m - A_m * D_m,
        x_j(k + 1) = (x_{j,alpha} + x_{j,beta} + x_{j,gamma}) / 3,

    with fresh A_m = 2 a r1 - a, C_m = 2 r2 (r1, r2 uniform on [0, 1], per wolf, leader
    and component; * is the element-wise product) and a = 2 (1 - k/K) ("linear") or
    2 (1 - k^2/K^2) ("quadratic", the seed's modification).

    **Arguments:** `population` (int >= 3, default 30); `decay` ("linear" default).
    """

    population: int = 30
    decay: str = "linear"

    def __check_init__(self):
        _check_population("GreyWolf", self.population, 3)
        _check_decay("GreyWolf", self.decay)

    def init(self, fn, lower, upper, key, max_iterations):
        def leaders(x, f):
            order = jnp.argsort(f)[:3]
            return x[order], f[order]

        return _initial_state(fn, lower, upper, key, self.population, max_iterations, leaders)

    def step(self, fn, state):
        lead_x, _ = state.aux
        shape = (self.population, 3, lead_x.shape[-1])
        key, (r1, r2) = _uniforms(state.key, lead_x.dtype, shape, shape)
        a = _decay(self.decay, state)
        A, C = 2.0 * a * r1 - a, 2.0 * r2
        D = jnp.abs(C * lead_x[None] - state.population[:, None])
        x = jnp.mean(lead_x[None] - A * D, axis=1)

        def update(aux, x, f):
            # Previous leaders compete with the new wolves (stable sort: ties keep leaders).
            all_x, all_f = jnp.concatenate([aux[0], x]), jnp.concatenate([aux[1], f])
            order = jnp.argsort(all_f, stable=True)[:3]
            return all_x[order], all_f[order]

        return _advance(fn, state, x, key, update)

    def terminate(self, state):
        return _budget_spent(state)


# ---------------------------------------------------------------------------------------
# Whale Optimization Algorithm
# ---------------------------------------------------------------------------------------


class Whale(AbstractPopulationOptimizer):
    """Whale Optimization Algorithm (Mirjalili & Lewis 2016; seed 003).

    For every whale j draw p ~ U[0, 1], A = 2 a r1 - a, C = 2 r2 (vectors, r1, r2 uniform
    per component) and l ~ U[-1, 1]; with x* the best point so far:

    - p < 0.5 and |A| < 1 (Euclidean norm): exploitation around the prey,
      D = |C * x* - x_j|, x_j(k + 1) = x* - A * D;
    - p < 0.5 and |A| >= 1: exploration around a random member x_rand of the population,
      D = |C * x_rand - x_j|, x_j(k + 1) = x_rand - A * D;
    - p >= 0.5: the spiral, D' = |x* - x_j|, x_j(k + 1) = D' e^(b l) cos(2 pi l) + x*.

    a = 2 (1 - k/K) ("linear") or 2 (1 - k^2/K^2) ("quadratic").

    **Arguments:** `population` (int >= 2, default 30); `decay` ("linear" or
    "quadratic"); `spiral`: the logarithmic-spiral constant b (default 1).
    """

    population: int = 30
    decay: str = "linear"
    spiral: float = 1.0

    def __check_init__(self):
        _check_population("Whale", self.population, 2)
        _check_decay("Whale", self.decay)
        if not (isinstance(self.spiral, int | float) and math.isfinite(self.spiral)):
            raise ValueError(f"Whale: `spiral` must be a finite number; got {self.spiral!r}.")

    def init(self, fn, lower, upper, key, max_iterations):
        return _initial_state(fn, lower, upper, key, self.population, max_iterations, lambda x, f: ())

    def step(self, fn, state):
        x, best = state.population, state.best_x
        n_pop = x.shape[0]
        key, (p, r1, r2, ul, ur) = _uniforms(state.key, x.dtype, (n_pop, 1), x.shape, x.shape, (n_pop, 1), (n_pop,))
        a = _decay(self.decay, state)
        A, C, ell = 2.0 * a * r1 - a, 2.0 * r2, 2.0 * ul - 1.0  # ell: the spiral variable l
        x_rand = x[jnp.minimum(jnp.floor(ur * n_pop).astype(int), n_pop - 1)]
        target = jnp.where(jnp.linalg.norm(A, axis=1, keepdims=True) < 1.0, best[None], x_rand)
        encircle = target - A * jnp.abs(C * target - x)
        spiral = jnp.abs(best[None] - x) * jnp.exp(self.spiral * ell) * jnp.cos(2.0 * jnp.pi * ell) + best[None]
        return _advance(fn, state, jnp.where(p < 0.5, encircle, spiral), key, lambda aux, x, f: ())

    def terminate(self, state):
        return _budget_spent(state)


# ---------------------------------------------------------------------------------------
# Dragonfly Algorithm
# ---------------------------------------------------------------------------------------


class Dragonfly(AbstractPopulationOptimizer):
    """Dragonfly Algorithm with Levy flight (Mirjalili 2016, eqs. 3.1-3.10; seed 003).

    Neighbours N_i of dragonfly i: the others within the radius r in the box-normalized
    max-norm, |x_j - x_i| / (upper - lower) <= r component-wise (r = 1/4 + 2 k/K, as in
    the reference code; from k/K = 3/8 on everyone is a neighbour). With food x+ (best
    point so far), enemy x- (worst point so far) and M = |N_i|:

        S = -sum_N (x_i - x_j)          separation
        A = mean_N dx_j                 alignment (dx: step vectors)
        C = mean_N x_j - x_i            cohesion
        F = x+ - x_i,  E = x- + x_i     food, enemy (E as printed in eq. 3.5)

    - M > 1 (the seed: "if their number exceeds one"):
      dx_i <- s S + a A + c C + f F + e E + w dx_i, clipped to +-(upper - lower)/10 (the
      reference code's velocity limit), and x_i <- x_i + dx_i;
    - otherwise the Levy flight x_i <- x_i + Levy(n) * x_i, dx_i <- 0, with Mantegna's
      Levy(n) = 0.01 u / |v|^(1/beta), u ~ N(0, sigma^2), v ~ N(0, 1),
      sigma = (Gamma(1 + beta) sin(pi beta / 2) / (Gamma((1 + beta)/2) beta 2^((beta - 1)/2)))^(1/beta)
      (the reference code draws u, v uniform on [0, 1]; we use Mantegna's normals).

    Weights (the reference code's schedule, t = k/K): w = 0.9 - 0.5 t,
    c_t = max(0.1 - 0.2 t, 0), s, a, c = 2 U c_t (one U ~ U[0, 1] each per generation),
    f = 2 U, e = c_t. Step vectors start at zero.

    **Arguments:** `population` (int >= 3, default 30); `levy_beta`: the Levy exponent
    beta in (0, 2) (default 1.5).
    """

    population: int = 30
    levy_beta: float = 1.5

    def __check_init__(self):
        _check_population("Dragonfly", self.population, 3)
        if not (isinstance(self.levy_beta, int | float) and 0.0 < self.levy_beta < 2.0):
            raise ValueError(f"Dragonfly: `levy_beta` must be in (0, 2); got {self.levy_beta!r}.")

    def init(self, fn, lower, upper, key, max_iterations):
        def aux(x, f):
            worst = jnp.argmax(f)
            return jnp.zeros_like(x), x[worst], f[worst]

        return _initial_state(fn, lower, upper, key, self.population, max_iterations, aux)

    def step(self, fn, state):
        x, (dx, enemy, _) = state.population, state.aux
        key, (uw, uu, uv) = _uniforms(state.key, x.dtype, (4,), x.shape, x.shape)
        width = (state.upper - state.lower)[None]  # (1, n)
        radius = _schedule(state, lambda k, K: K + 8 * k, lambda K: 4 * K)  # 1/4 + 2 k/K
        w = _schedule(state, lambda k, K: 9 * K - 5 * k, lambda K: 10 * K)  # 0.9 - 0.5 k/K
        ct = _schedule(state, lambda k, K: jnp.maximum(K - 2 * k, 0), lambda K: 10 * K)  # max(0.1 - 0.2 k/K, 0)
        s, a, c, f = uw * jnp.stack([2 * ct, 2 * ct, 2 * ct, 2.0])

        dist = jnp.max(jnp.abs(x[:, None] - x[None]) / width[None], axis=-1)
        near = (dist <= radius) & (dist > 0)  # excludes itself (and exact duplicates)
        m = jnp.sum(near, axis=1, keepdims=True).astype(x.dtype)  # M_i
        sum_x = jnp.sum(jnp.where(near[..., None], x[None], 0.0), axis=1)
        sum_dx = jnp.sum(jnp.where(near[..., None], dx[None], 0.0), axis=1)
        mm = jnp.maximum(m, 1.0)
        separation = sum_x - m * x
        alignment = sum_dx / mm
        cohesion = sum_x / mm - x
        food, enemy_term = state.best_x[None] - x, enemy[None] + x
        # s S + a A + c C + f F + e E + w dx as one contraction: written out, XLA:CPU fuses
        # its multiply-adds differently with and without vmap (one-ulp differences that
        # the swarm amplifies); as a dot product the batched and single runs agree.
        weights = jnp.stack([s, a, c, f, ct, w])
        swarm = jnp.tensordot(weights, jnp.stack([separation, alignment, cohesion, food, enemy_term, dx]), axes=1)
        swarm = jnp.clip(swarm, -width / 10, width / 10)

        beta = self.levy_beta
        sigma = (
            math.gamma(1 + beta)
            * math.sin(math.pi * beta / 2)
            / (math.gamma((1 + beta) / 2) * beta * 2 ** ((beta - 1) / 2))
        ) ** (1 / beta)
        u, v = sigma * _normal(uu), _normal(uv)
        levy = 0.01 * u / jnp.abs(v) ** (1 / beta)

        flock = m > 1
        new_x = jnp.where(flock, x + swarm, x + levy * x)
        new_dx = jnp.where(flock, swarm, 0.0)

        def update(aux, x, fx):
            _, enemy_x, enemy_f = aux
            i = jnp.argmax(fx)
            worse = fx[i] > enemy_f
            return new_dx, jnp.where(worse, x[i], enemy_x), jnp.where(worse, fx[i], enemy_f)

        return _advance(fn, state, new_x, key, update)

    def terminate(self, state):
        return _budget_spent(state)


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------


class PopulationResult(eqx.Module):
    """Outcome of `minimize`. Under `vmap` every field gains a leading batch axis.

    - `x`, `f`: the best point ever evaluated and its value (+inf if no value was finite).
    - `evaluations`: fn evaluations, `population * (iterations + 1)`.
    - `iterations`: generations run (fewer than `max_iterations` if `target` was reached).
    - `history_best`: (max_iterations,) best value after each generation, NaN-padded.
    - `status`: a `jt.Status`: `SUCCESS` if `f <= target` (with `target=None`: the budget
      was run and some value was finite); `MAX_ITERATIONS` if a `target` was given and not
      reached; `NONFINITE` if fn was never finite.
    """

    x: jax.Array
    f: jax.Array
    evaluations: jax.Array
    iterations: jax.Array
    history_best: jax.Array
    status: Status = eqx.field(converter=as_indexable)


@eqx.filter_jit
def _run(optimizer, fn, lower, upper, key, max_iterations, target):
    state = optimizer.init(fn, lower, upper, key, max_iterations)
    goal = -jnp.inf if target is None else target

    def cond(s):
        return ~optimizer.terminate(s) & ~(s.best_f <= goal)

    state = lax.while_loop(cond, lambda s: optimizer.step(fn, s), state)
    finite = jnp.isfinite(state.best_f)
    reached = finite if target is None else state.best_f <= target
    status = Status.where(reached, Status.SUCCESS, Status.where(finite, Status.MAX_ITERATIONS, Status.NONFINITE))
    return PopulationResult(
        x=state.best_x,
        f=state.best_f,
        evaluations=state.evaluations,
        iterations=state.iteration,
        history_best=state.history_best,
        status=status,
    )


def _check_bound(name, value):
    if isinstance(value, jax.core.Tracer):  # e.g. under vmap over bounds: no value checks
        if value.ndim != 1 or not jnp.issubdtype(value.dtype, jnp.floating):
            raise ValueError(f"`{name}` must be a 1-D float array; got shape {value.shape}, dtype {value.dtype}.")
        return value.astype(jnp.float64)
    try:
        arr = jnp.asarray(value)
    except TypeError as err:
        raise ValueError(f"`{name}` must be a 1-D array of real numbers; got {type(value).__name__}.") from err
    if arr.dtype == jnp.bool_ or not (
        jnp.issubdtype(arr.dtype, jnp.floating) or jnp.issubdtype(arr.dtype, jnp.integer)
    ):
        raise ValueError(f"`{name}` must hold real numbers; got dtype {arr.dtype}.")
    if arr.ndim != 1 or arr.shape[0] == 0:
        raise ValueError(f"`{name}` must be a non-empty 1-D array; got shape {arr.shape}.")
    arr = arr.astype(jnp.float64)
    if not bool(jnp.all(jnp.isfinite(arr))):
        raise ValueError(f"`{name}` must be finite; got {arr}.")
    return arr


def _check_key(key):
    if not isinstance(key, jax.Array):
        raise ValueError(f"`key` must be a JAX PRNG key (jax.random.key(seed)); got {type(key).__name__}.")
    typed = jnp.issubdtype(key.dtype, jax.dtypes.prng_key) and key.shape == ()
    raw = key.dtype == jnp.uint32 and key.shape == (2,)
    if not (typed or raw):
        raise ValueError(
            f"`key` must be one PRNG key (jax.random.key(seed) or jax.random.PRNGKey(seed)); "
            f"got shape {key.shape}, dtype {key.dtype}."
        )


def minimize(
    optimizer: AbstractPopulationOptimizer,
    fn,
    lower,
    upper,
    key,
    *,
    max_iterations: int = 200,
    target=None,
) -> PopulationResult:
    """Minimize `fn` over the box [lower, upper] with a population metaheuristic.

    **Arguments:**

    - `optimizer`: `GreyWolf(...)`, `Whale(...)` or `Dragonfly(...)`.
    - `fn`: maps a float64 vector of shape (n,) to a real scalar; it must be traceable
      (it is called under `jax.vmap`). A non-finite value counts as +inf. Pass the same
      function object on every call: a new `lambda` is a new compilation.
    - `lower`, `upper`: 1-D bounds of equal shape (n,), finite, lower < upper.
    - `key`: a PRNG key; the same key gives the same result.
    - `max_iterations`: keyword-only, generations at most (static: changing it recompiles).
    - `target`: keyword-only; stop as soon as the best value is <= target.

    **Returns:** a `PopulationResult`. The loop is a `lax.while_loop` inside one
    `eqx.filter_jit`, compiled once per (optimizer, fn, n, max_iterations, target given or
    not); new keys, bounds or target values reuse it. Call under `jax.vmap` over keys for
    several seeds at once.

    **Raises:** `ValueError` for bad input (outside jit); `RuntimeError` if float64 is off.
    """
    require_float64()
    if not isinstance(optimizer, AbstractPopulationOptimizer):
        raise ValueError(
            f"`optimizer` must be a jaxtraj population optimizer (GreyWolf, Whale, Dragonfly); "
            f"got {type(optimizer).__name__}."
        )
    if not callable(fn):
        raise ValueError(f"`fn` must be callable; got {type(fn).__name__}.")
    lower, upper = _check_bound("lower", lower), _check_bound("upper", upper)
    if lower.shape != upper.shape:
        raise ValueError(f"`lower` and `upper` must have the same shape; got {lower.shape} and {upper.shape}.")
    if not isinstance(lower, jax.core.Tracer) and not isinstance(upper, jax.core.Tracer):
        bad = jnp.nonzero(~(lower < upper))[0]
        if bad.size:
            raise ValueError(f"`lower` must be < `upper` element-wise; fails at index {[int(i) for i in bad]}.")
    _check_key(key)
    if not is_count(max_iterations, 1):
        raise ValueError(f"`max_iterations` must be an int in 1..2**31 - 1; got {max_iterations!r}.")
    # (refused before the work: XLA's RESOURCE_EXHAUSTED deep in JAX otherwise)
    check_memory("max_iterations", 8 * max_iterations, f"the history of {max_iterations:,} generations")
    population = getattr(optimizer, "population", 0)
    check_memory(
        "optimizer", 2 * 8 * population * lower.shape[0], f"a population of {population:,} x {lower.shape[0]:,} values"
    )
    if target is not None:
        try:
            target = jnp.asarray(target, dtype=jnp.float64)
        except (TypeError, ValueError):  # (JAX's message named no argument)
            raise ValueError(f"`target` must be None or a real scalar; got {target!r}.") from None
        if target.shape != () or (not isinstance(target, jax.core.Tracer) and bool(jnp.isnan(target))):
            raise ValueError(f"`target` must be None or a real scalar; got {target!r}.")
    return _run(optimizer, fn, lower, upper, key, max_iterations, target)
