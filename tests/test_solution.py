"""Batched Solutions: per-start access (`sols[i]`, iteration, masks) and status names;
problem names do not take part in compilation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from tests.helpers import counting_problem

SOLVER = jt.KalmanSearch()  # quick to compile


@pytest.fixture(scope="module")
def batch():
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl = jt.controls.PiecewiseLinear(3)
    a0 = jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0))
    a0s = jnp.stack([a0, a0 + 0.05, a0.at[1].set(jnp.nan)])  # the last start cannot be simulated
    sols = jax.vmap(lambda a: jt.solve(prob, ctrl, a, SOLVER, max_steps=300))(a0s)
    singles = [jt.solve(prob, ctrl, a, SOLVER, max_steps=300) for a in a0s[:2]]
    return sols, singles


def test_status_name_of_batched_and_single_statuses(batch):
    sols, singles = batch
    names = jt.status_name(sols.status)
    assert isinstance(names, np.ndarray) and names.shape == (3,)
    assert names.tolist() == ["SUCCESS", "SUCCESS", "NONFINITE"]
    np.testing.assert_array_equal(names == "SUCCESS", np.asarray(sols.status == jt.Status.SUCCESS))
    assert jt.status_name(singles[0].status) == "SUCCESS" and isinstance(jt.status_name(singles[0].status), str)
    for name in ("SUCCESS", "MAX_ITERATIONS", "STALLED", "NONFINITE", "SIMULATION_FAILED", "CONSTRAINT_STATIONARY"):
        assert jt.status_name(getattr(jt.Status, name)) == name
    with pytest.raises(ValueError, match="Status"):
        jt.status_name(0)
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda s: jt.status_name(s))(singles[0].status)


def test_indexing_a_batched_solution(batch):
    sols, singles = batch
    for i, single in enumerate(singles):
        s = sols[i]
        assert isinstance(s, jt.Solution) and jt.status_name(s.status) == "SUCCESS"
        assert s.params.shape == single.params.shape and s.history.objective.shape == single.history.objective.shape
        # the same as the tree.map idiom, and the same numbers as the unbatched solve
        ref = jax.tree.map(lambda x, i=i: x[i], sols)
        assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b, equal_nan=True)), s, ref))
        np.testing.assert_allclose(np.asarray(s.params), np.asarray(single.params), rtol=1e-12, atol=1e-14)
        assert int(s.iterations) == int(single.iterations)
    assert jt.status_name(sols[-1].status) == "NONFINITE"
    # slices, index arrays and boolean masks keep a batch
    ok = sols[sols.status == jt.Status.SUCCESS]
    assert ok.tf.shape == (2,) and jt.status_name(ok.status).tolist() == ["SUCCESS", "SUCCESS"]
    assert sols[1:].params.shape == (2, sols.params.shape[1])
    assert jt.status_name(sols[jnp.array([2, 0])].status).tolist() == ["NONFINITE", "SUCCESS"]
    # iteration yields the starts in order
    assert [jt.status_name(s.status) for s in sols] == ["SUCCESS", "SUCCESS", "NONFINITE"]
    with pytest.raises(IndexError, match="out of range"):
        sols[3]
    with pytest.raises(TypeError, match="batched"):
        singles[0][0]
    with pytest.raises(TypeError, match="batched"):
        list(singles[0])
    # inside jit, a traced index works too
    tf = jax.jit(lambda s, i: s[i].tf)(sols, 1)
    assert float(tf) == float(sols.tf[1])


def test_solve_batch_solution_is_indexable():
    prob = jt.problems.analytic.min_energy_double_integrator()
    ctrl = jt.controls.PiecewiseLinear(3)
    a0 = jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0))
    sols = jt.solve_batch(prob, ctrl, jnp.stack([a0, a0 + 0.05]), solver=SOLVER, max_steps=300)
    assert [jt.status_name(s.status) for s in sols] == list(jt.status_name(sols.status))
    assert float(sols[1].objective) == float(sols.objective[1])


def test_problem_name_does_not_recompile():
    base, counter = counting_problem(jt.problems.analytic.min_energy_double_integrator())
    ctrl = jt.controls.PiecewiseLinear(3)
    a0 = jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0))
    probs = [
        jt.Problem(base.dynamics, base.x0, base.terminal, base.constraint_names, args=base.args, name=name)
        for name in ("first", "second")
    ]
    assert [p.name for p in probs] == ["first", "second"]
    counter["traces"] = 0
    jt.simulate(probs[0], ctrl, a0)
    traced = counter["traces"]
    assert traced > 0
    traj = jt.simulate(probs[1], ctrl, a0)
    assert counter["traces"] == traced  # the second name reuses the compiled simulation
    assert traj.x.shape[1] == probs[1].num_states
    # the name survives pytree operations and stays a plain str
    p = jax.tree.map(lambda x: x, probs[1])
    assert p.name == "second" and isinstance(p.name, str)
    with pytest.raises(ValueError, match="name"):
        jt.Problem(base.dynamics, base.x0, base.terminal, base.constraint_names, args=base.args, name=3)
