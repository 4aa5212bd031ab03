"""Population metaheuristics (`jaxtraj.metaheuristics`): convergence on test functions with
known minima, bookkeeping, box constraints, non-finite values, input errors, compilation
and vmap over keys.

Thresholds were measured on 30 seeds (jax.random.key(0..29)) with the settings below
(max_iterations=1000; population 30 for GWO and WOA, 60 for DA); each bound leaves a
margin of >= 2x over the worst of those 30 runs unless stated otherwise.

Compilation dominates the run time (~1.5 s per optimizer and input shape, the runs take
5-200 ms), so all benchmarks go through one test function, `Benchmark`, whose choice of
function, shift and box are arrays: per optimizer there is one compilation in 5-D and one
in 2-D.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.metaheuristics import (
    AbstractPopulationOptimizer,
    Dragonfly,
    GreyWolf,
    PopulationResult,
    Whale,
    minimize,
)

K = 1000
SEEDS = (0, 1, 2)
OPTIMIZERS = {
    "gwo": GreyWolf(30),
    "woa-linear": Whale(30),
    "woa-quadratic": Whale(30, decay="quadratic"),
    "da": Dragonfly(60),
}


def sphere(z):
    return jnp.sum(z**2)


def rosenbrock(z):
    return jnp.sum(100.0 * (z[1:] - z[:-1] ** 2) ** 2 + (1.0 - z[:-1]) ** 2)


def rastrigin(z):
    return 10.0 * z.shape[0] + jnp.sum(z**2 - 10.0 * jnp.cos(2.0 * jnp.pi * z))


class Benchmark(eqx.Module):
    """x -> g(x - center) with g = sphere, rosenbrock or rastrigin (`which` one-hot), inside
    the box [lower, upper]; outside it the value is -1, below every value inside, so a
    result with f < 0 would reveal that a point outside the box was evaluated.

    GWO and WOA are biased towards the origin (the move x_m - A |C x_m - x| shrinks towards
    0): on the *centered* sphere GWO gets below 1e-100 and on the centered Rastrigin GWO and
    WOA land exactly on 0. The shifted functions show their real accuracy.
    """

    which: jax.Array
    center: jax.Array
    lower: jax.Array
    upper: jax.Array

    def __call__(self, x):
        z = x - self.center
        value = jnp.sum(self.which * jnp.stack([sphere(z), rosenbrock(z), rastrigin(z)]))
        inside = jnp.all((x >= self.lower) & (x <= self.upper))
        return jnp.where(inside, value, -1.0)


def solve(name, function, center, lower, upper, seed):
    which = jnp.array({"sphere": [1.0, 0, 0], "rosenbrock": [0, 1.0, 0], "rastrigin": [0, 0, 1.0]}[function])
    fn = Benchmark(which, jnp.asarray(center, dtype=float), lower, upper)
    res = minimize(OPTIMIZERS[name], fn, lower, upper, jax.random.key(seed), max_iterations=K)
    check_bookkeeping(res, OPTIMIZERS[name].population, lower, upper)
    # f is fn(x) (recomputed outside the loop: equal up to rounding, ~1e-14 for Rastrigin)
    assert float(res.f) == pytest.approx(float(fn(res.x)), rel=1e-9, abs=1e-12)
    return res


def check_bookkeeping(res, population, lower, upper):
    assert isinstance(res, PopulationResult)
    assert res.x.dtype == jnp.float64 and res.f.dtype == jnp.float64
    assert int(res.iterations) == K
    assert int(res.evaluations) == population * (K + 1)
    h = np.asarray(res.history_best)
    assert h.shape == (K,) and np.all(np.isfinite(h))
    assert np.all(np.diff(h) <= 0.0)  # elitist: the best value never gets worse
    assert h[-1] == float(res.f)
    assert float(res.f) >= 0.0  # no evaluation outside the box (see Benchmark)
    assert np.all(np.asarray(res.x) >= np.asarray(lower)) and np.all(np.asarray(res.x) <= np.asarray(upper))
    assert res.status == jt.Status.SUCCESS


def box(n, b):
    return -b * jnp.ones(n), b * jnp.ones(n)


C5 = np.array([1.0, -2.0, 0.5, 3.0, -1.5])
# Worst f over 30 seeds (sphere shifted to C5, dim 5): GWO 4.3e-6, WOA 4.8e-7 (linear) and
# 1.2e-6 (quadratic), DA 6.3e-11.
SPHERE_TOL = {"gwo": 1e-5, "woa-linear": 1e-5, "woa-quadratic": 1e-5, "da": 1e-9}


@pytest.mark.parametrize("name", OPTIMIZERS)
def test_sphere_5d(name):
    lower, upper = box(5, 5.12)
    for seed in SEEDS:
        res = solve(name, "sphere", C5, lower, upper, seed)
        assert float(res.f) < SPHERE_TOL[name]  # the minimum is 0 at C5
        assert np.max(np.abs(np.asarray(res.x) - C5)) < np.sqrt(SPHERE_TOL[name])


@pytest.mark.parametrize("name", OPTIMIZERS)
def test_sphere_minimum_on_the_box_boundary(name):
    # The center C5 lies outside this box: the constrained minimizer is clip(C5), f = 2.5.
    lower = jnp.array([-1.0, -1.0, -1.0, -1.0, -1.0])
    upper = jnp.array([2.0, 2.0, 0.0, 2.0, 2.0])
    res = solve(name, "sphere", C5, lower, upper, 0)
    assert 2.5 <= float(res.f) < 2.5 + SPHERE_TOL[name]
    np.testing.assert_allclose(np.asarray(res.x), [1.0, -1.0, 0.0, 2.0, -1.0], rtol=0, atol=np.sqrt(SPHERE_TOL[name]))


# Worst over 30 seeds: f <= 8.2e-7 (GWO), 1.4e-8 (WOA), 1.2e-12 (DA); max |x_i - 1| <= 1.8e-3.
@pytest.mark.parametrize("name", OPTIMIZERS)
def test_rosenbrock_2d(name):
    lower, upper = box(2, 5.0)
    for seed in SEEDS:
        res = solve(name, "rosenbrock", [0.0, 0.0], lower, upper, seed)
        assert float(res.f) < 1e-5  # the minimum is 0 at (1, 1)
        assert np.linalg.norm(np.asarray(res.x) - 1.0) < 1e-2


# Success = the global basin: f < 0.5, since every other local minimum has f >= 0.995.
# Successes out of 30 seeds, centered / shifted to (1.3, -0.7): GWO 30 / 23, WOA 30 / 30
# (both decays), DA 23 / 21; out of the 10 seeds used here: GWO 10 / 8, WOA 10 / 10, DA
# 9 / 10. The counts required follow the 30-seed rates, so that a change of rounding
# (another XLA version reshuffles which seeds succeed) is unlikely to fail them: with a
# success rate of 0.7, P(fewer than 4 of 10) = 1%.
RASTRIGIN_SEEDS = range(10)
RASTRIGIN_REQUIRED = {"gwo": (9, 5), "woa-linear": (9, 9), "woa-quadratic": (9, 9), "da": (4, 4)}
# Worst f of the successes over 30 seeds: GWO 2.6e-6, WOA 2.7e-8, DA 1.6e-4.
RASTRIGIN_TOL = {"gwo": 1e-5, "woa-linear": 1e-6, "woa-quadratic": 1e-6, "da": 1e-3}


@pytest.mark.parametrize("name", OPTIMIZERS)
def test_rastrigin_2d(name):
    lower, upper = box(2, 5.12)
    for center, required in zip(([0.0, 0.0], [1.3, -0.7]), RASTRIGIN_REQUIRED[name]):
        results = [solve(name, "rastrigin", center, lower, upper, seed) for seed in RASTRIGIN_SEEDS]
        values = [float(res.f) for res in results]
        # At worst a local minimum of the first two rings around the global one (0.995,
        # 1.99); measured worst over 30 seeds: 1.99 (DA), 0.995 (GWO).
        assert max(values) < 2.5, values
        found = [res for res in results if float(res.f) < 0.5]
        assert len(found) >= required, values
        for res in found:
            assert float(res.f) < RASTRIGIN_TOL[name]
            assert np.max(np.abs(np.asarray(res.x) - np.array(center))) < 1e-2


# Two of the four (each vmap is a compilation): WOA-quadratic and DA are the two whose
# batched runs differed by rounding until their schedules and the DA swarm sum were
# written to round identically (see jaxtraj.metaheuristics).
@pytest.mark.parametrize("name", ["woa-quadratic", "da"])
def test_vmap_over_keys_equals_single_runs(name):
    lower, upper = box(5, 5.12)
    fn = Benchmark(jnp.array([1.0, 0, 0]), jnp.asarray(C5), lower, upper)
    keys = jnp.stack([jax.random.key(s) for s in SEEDS])
    batch = jax.vmap(lambda k: minimize(OPTIMIZERS[name], fn, lower, upper, k, max_iterations=K))(keys)
    assert batch.x.shape == (3, 5) and batch.history_best.shape == (3, K)
    assert bool(jnp.all(batch.status == jt.Status.SUCCESS))
    for i, seed in enumerate(SEEDS):
        single = minimize(OPTIMIZERS[name], fn, lower, upper, jax.random.key(seed), max_iterations=K)
        # To round-off (bit for bit at XLA's default optimization level; at level 0, which
        # `make test` compiles at, the vmapped arithmetic differs in the last bits)
        for got, want in ((batch.x[i], single.x), (batch.f[i], single.f), (batch.history_best[i], single.history_best)):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=1e-12)
        assert int(batch.evaluations[i]) == int(single.evaluations) and int(batch.iterations[i]) == K
    # Same key, same result (bit for bit); different keys, different runs.
    again = minimize(OPTIMIZERS[name], fn, lower, upper, keys[2], max_iterations=K)
    assert np.array_equal(np.asarray(again.history_best), np.asarray(single.history_best))
    assert not np.array_equal(np.asarray(batch.x[0]), np.asarray(batch.x[1]))


def test_no_recompilation_and_target():
    traces = {"n": 0}

    def counted(x):
        traces["n"] += 1  # runs only while JAX traces fn
        return jnp.sum((x - C5) ** 2)

    opt = Whale(20)
    lower, upper = box(5, 5.12)
    res = minimize(opt, counted, lower, upper, jax.random.key(0), max_iterations=300, target=1e-3)
    n = traces["n"]
    assert n >= 1
    # Early stop at the target: status, iteration and evaluation counts, NaN padding.
    it = int(res.iterations)
    assert 1 < it < 300 and res.status == jt.Status.SUCCESS
    assert float(res.f) <= 1e-3
    assert int(res.evaluations) == 20 * (it + 1)
    h = np.asarray(res.history_best)
    assert np.all(np.isfinite(h[:it])) and np.all(np.isnan(h[it:])) and h[it - 1] == float(res.f)
    assert h[it - 2] > 1e-3  # it stopped at the first generation that reached the target

    # New key, bounds and target values (Python lists and ints included): no new trace.
    res2 = minimize(opt, counted, [-6, -5, -5, -5, -5], upper + 2.0, jax.random.key(7), max_iterations=300, target=-1)
    assert traces["n"] == n
    assert int(res2.iterations) == 300 and res2.status == jt.Status.MAX_ITERATIONS  # f >= 0 > target
    assert int(res2.evaluations) == 20 * 301
    assert res2.x.dtype == jnp.float64 and float(res2.f) < 1e-5


class NanBelow(eqx.Module):
    """Sphere centered at (1, 1, 1) that is NaN where x[0] < threshold."""

    threshold: jax.Array

    def __call__(self, x):
        return jnp.where(x[0] < self.threshold, jnp.nan, jnp.sum((x - 1.0) ** 2))


def test_nonfinite_values_are_never_best():
    lower, upper = box(3, 4.0)
    opt = GreyWolf(20)
    res = minimize(opt, NanBelow(jnp.array(0.5)), lower, upper, jax.random.key(0), max_iterations=300)
    assert np.isfinite(float(res.f)) and float(res.f) < 1e-4 and float(res.x[0]) >= 0.5
    assert np.all(np.isfinite(np.asarray(res.history_best)))
    assert res.status == jt.Status.SUCCESS
    # NaN everywhere: the best value is +inf and the status says so.
    res = minimize(opt, NanBelow(jnp.array(jnp.inf)), lower, upper, jax.random.key(0), max_iterations=300)
    assert float(res.f) == np.inf and res.status == jt.Status.NONFINITE
    assert int(res.evaluations) == 20 * 301


def test_bad_bounds_and_arguments():
    opt, key = Whale(10), jax.random.key(0)
    cases = [
        (dict(lower=jnp.array([0.0, 1.0]), upper=jnp.array([1.0, 1.0])), r"`lower` must be < `upper`.*index \[1\]"),
        (dict(lower=jnp.array([2.0, 0.0])), r"`lower` must be < `upper`.*index \[0\]"),
        (dict(lower=jnp.zeros(3)), r"`lower` and `upper` must have the same shape"),
        (dict(upper=jnp.ones((2, 1))), r"`upper` must be a non-empty 1-D array"),
        (dict(lower=jnp.zeros(0), upper=jnp.zeros(0)), r"`lower` must be a non-empty 1-D array"),
        (dict(lower=jnp.array([-jnp.inf, 0.0])), r"`lower` must be finite"),
        (dict(upper=jnp.array([jnp.nan, 1.0])), r"`upper` must be finite"),
        (dict(upper=jnp.array([1.0 + 1j, 1.0])), r"`upper` must hold real numbers"),
        (dict(lower=np.array([True, False])), r"`lower` must hold real numbers"),
        (dict(lower="ab"), r"`lower`"),
        (dict(key=0), r"`key` must be a JAX PRNG key"),
        (dict(key=jax.random.split(key, 2)), r"`key` must be one PRNG key"),
        (dict(max_iterations=0), r"`max_iterations` must be an int in 1..2\*\*31 - 1"),
        (dict(max_iterations=10.0), r"`max_iterations` must be an int in 1"),
        # XLA's RESOURCE_EXHAUSTED deep in JAX (the fourth audit, issue 51)
        (dict(max_iterations=2**40), r"`max_iterations` must be an int in 1..2\*\*31 - 1"),
        (dict(optimizer=Whale(2**31 - 1), lower=jnp.zeros(10**4), upper=jnp.ones(10**4)), r"`optimizer`: a population"),
        (dict(target=jnp.array([1.0, 2.0])), r"`target` must be None or a real scalar"),
        (dict(target=float("nan")), r"`target` must be None or a real scalar"),
        (dict(target="x"), r"`target` must be None or a real scalar; got 'x'"),  # (JAX's message, issue 51)
        (dict(optimizer=jt.KalmanSearch()), r"`optimizer` must be a jaxtraj population optimizer"),
        (dict(fn=3.0), r"`fn` must be callable"),
        (dict(fn=lambda x: x), r"`fn` must return a scalar"),  # found while tracing
    ]
    for override, match in cases:
        kw = dict(optimizer=opt, fn=sphere, lower=jnp.zeros(2), upper=jnp.ones(2), key=key, max_iterations=5)
        kw.update(override)
        with pytest.raises(ValueError, match=match):
            minimize(kw.pop("optimizer"), kw.pop("fn"), kw.pop("lower"), kw.pop("upper"), kw.pop("key"), **kw)


def test_configuration_is_validated():
    for make, match in [
        (lambda: GreyWolf(2), r"GreyWolf: `population` must be an int in 3..2\*\*31 - 1"),
        (lambda: GreyWolf(2**40), r"GreyWolf: `population` must be an int in 3..2\*\*31 - 1"),  # (accepted)
        (lambda: GreyWolf(30, decay="cubic"), r"GreyWolf: `decay` must be one of \('linear', 'quadratic'\)"),
        (lambda: Whale(1), r"Whale: `population` must be an int in 2"),
        (lambda: Whale(30.0), r"Whale: `population` must be an int"),
        (lambda: Whale(True), r"Whale: `population` must be an int"),
        (lambda: Whale(decay="exponential"), r"Whale: `decay` must be one of"),
        (lambda: Whale(spiral=float("inf")), r"Whale: `spiral` must be a finite number"),
        (lambda: Dragonfly(2), r"Dragonfly: `population` must be an int in 3"),
        (lambda: Dragonfly(levy_beta=2.5), r"Dragonfly: `levy_beta` must be in \(0, 2\)"),
    ]:
        with pytest.raises(ValueError, match=match):
            make()
    for opt in OPTIMIZERS.values():
        assert isinstance(opt, AbstractPopulationOptimizer)


def test_manual_stepping_init_step_terminate():
    """The init/step/terminate state machine driven by hand (DA: its Levy flights and
    velocities overshoot most; the other optimizers' box checks are in `Benchmark`): the
    population stays in the box after every generation (the minimum lies outside it), and
    the counters, best point, enemy and history follow."""
    lower, upper = jnp.array([-1.0, 0.0]), jnp.array([0.5, 3.0])

    def fn(x):
        return jnp.sum((x - jnp.array([4.0, -5.0])) ** 2)

    opt = Dragonfly(6)
    init, step = eqx.filter_jit(opt.init), eqx.filter_jit(opt.step)
    state = init(fn, lower, upper, jax.random.key(3), 4)
    assert state.population.shape == (6, 2) and int(state.evaluations) == 6
    assert np.all(np.isnan(np.asarray(state.history_best)))
    steps = 0
    while not bool(opt.terminate(state)):
        state = step(fn, state)
        steps += 1
        pop = np.asarray(state.population)
        assert np.all(pop >= np.asarray(lower)) and np.all(pop <= np.asarray(upper))
        assert float(state.best_f) == float(jnp.min(state.history_best[:steps]))
        assert float(state.best_f) <= float(jnp.min(state.fitness))
        assert float(state.best_f) == pytest.approx(float(fn(state.best_x)), rel=1e-12)
        _, enemy_x, enemy_f = state.aux  # the worst point so far
        assert float(enemy_f) >= float(jnp.max(state.fitness))
        assert float(enemy_f) == pytest.approx(float(fn(enemy_x)), rel=1e-12)
    assert steps == 4 and int(state.iteration) == 4 and int(state.evaluations) == 6 * 5
