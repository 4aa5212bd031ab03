"""The sequential Kalman update against the batch formula, order invariance, PSD, and
Rosen's projection (seed 000 eq. 3.40-3.54)."""

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings, strategies as st

from jaxtraj._kalman import batch_update, projection_matrix, sequential_update


def _random_problem(seed, m, p):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(p, p))
    P = A @ A.T + 0.1 * np.eye(p)
    H = rng.normal(size=(m, p))
    z = rng.normal(size=m)
    r = rng.uniform(0.01, 2.0, size=m)
    da = rng.normal(size=p)
    return [jnp.asarray(v) for v in (da, P, H, z, r)]


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 6), p=st.integers(1, 9))
def test_sequential_equals_batch_in_any_order(seed, m, p):
    da, P, H, z, r = _random_problem(seed, m, p)
    want_da, want_P = batch_update(da, P, H, z, r)
    perm = np.random.default_rng(seed + 1).permutation(m)
    for order in (np.arange(m), perm, np.arange(m)[::-1]):
        got_da, got_P, _ = sequential_update(da, P, H[order], z[order], r[order])
        scale = 1.0 + float(jnp.max(jnp.abs(want_P)))
        np.testing.assert_allclose(got_da, want_da, rtol=1e-9, atol=1e-9 * scale)
        np.testing.assert_allclose(got_P, want_P, rtol=1e-9, atol=1e-9 * scale)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 8), p=st.integers(1, 9))
def test_covariance_stays_symmetric_psd(seed, m, p):
    da, P, H, z, r = _random_problem(seed, m, p)
    _, P1, s = sequential_update(da, P, H, z, r)
    np.testing.assert_array_equal(P1, P1.T)
    eig = np.linalg.eigvalsh(np.asarray(P1))
    assert eig.min() >= -1e-10 * max(1.0, eig.max())
    # the posterior never exceeds the prior: P - P1 is PSD
    assert np.linalg.eigvalsh(np.asarray(P - P1)).min() >= -1e-9 * float(jnp.max(jnp.abs(P)))
    assert np.all(np.asarray(s) > 0)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 5), extra=st.integers(1, 5))
def test_identity_prior_small_noise_gives_rosen_projection(seed, m, extra):
    p = m + extra  # rows of H independent (almost surely)
    rng = np.random.default_rng(seed)
    H = jnp.asarray(rng.normal(size=(m, p)))
    r = jnp.full(m, 1e-13)
    _, P1, _ = sequential_update(jnp.zeros(p), jnp.eye(p), H, jnp.zeros(m), r)
    V = projection_matrix(H)
    np.testing.assert_allclose(P1, V, atol=1e-9 * float(np.linalg.cond(np.asarray(H))) ** 2)
    np.testing.assert_allclose(np.asarray(H) @ np.asarray(P1), 0.0, atol=1e-8)


def test_minimum_norm_correction_with_zero_prior():
    """P = I, R -> 0, prior 0: the estimate is the minimum-norm solution of H da = z."""
    H = jnp.array([[1.0, 2.0, 0.0], [0.0, 1.0, -1.0]])
    z = jnp.array([1.0, -2.0])
    da, _, _ = sequential_update(jnp.zeros(3), jnp.eye(3), H, z, jnp.full(2, 1e-14))
    np.testing.assert_allclose(da, np.linalg.pinv(np.asarray(H)) @ np.asarray(z), atol=1e-10)


def test_inactive_rows_are_skipped():
    da, P, H, z, r = _random_problem(3, 4, 5)
    active = jnp.array([True, False, True, False])
    got = sequential_update(da, P, H, z, r, active)
    want = sequential_update(da, P, H[active], z[active], r[active])
    np.testing.assert_allclose(got[0], want[0], rtol=1e-12)
    np.testing.assert_allclose(got[1], want[1], rtol=1e-12, atol=1e-14)


#: The three free knots t1, t2, t3 as the parameters: dknots/da for the knot-ordering tests.
_DKNOTS = jnp.concatenate([jnp.zeros((1, 3)), jnp.eye(3)])
_D_MIDDLE = np.array([[-1.0, 1.0, 0.0]])  # d(t2 - t1)/da: the middle gap


def _knot_steps(base_step):
    """20 random SPD covariances `P` (3 x 3), each with `base_step` plus a 0.01-sized random
    perturbation as the step `da`."""
    for seed in range(20):
        rng = np.random.default_rng(seed)
        A = rng.normal(size=(3, 3))
        yield A @ A.T + 0.1 * np.eye(3), np.asarray(base_step) + 0.01 * rng.normal(size=3)


def test_knot_ordering_holds_a_collapsed_segment_without_freezing_the_step():
    """Appendix C with a segment already collapsed (knots 0, 1, 1, 2; the parameters are the
    three free knots): a step closing that zero gap is corrected to keep it at 0 (its
    observation z* = 0 has variance 0), i.e. to the P-metric projection of the step onto
    t2 - t1 = const, and the rest of the step survives. (It used to be scaled to 0 whole
    when round-off left the held gap at -1e-17: 7 of these 20 covariances, and solar-sail
    runs stalled on a collapsed duration.)"""
    from jaxtraj._kalman import keep_knots_ordered

    knots = jnp.array([0.0, 1.0, 1.0, 2.0])
    dknots, D = _DKNOTS, _D_MIDDLE
    for P, da in _knot_steps([0.1, 0.0, 0.5]):  # t1 up: the zero gap would close
        d, _ = keep_knots_ordered(jnp.asarray(da), jnp.asarray(P), knots, dknots, 10.0)
        reference = da - P @ D.T @ np.linalg.solve(D @ P @ D.T, D @ da)
        np.testing.assert_allclose(d, reference, atol=1e-12)
        gaps = np.diff(np.asarray(knots + dknots @ d))
        assert abs(gaps[1]) < 1e-12 and np.all(gaps >= -1e-15)


def test_keep_knots_ordered_closes_a_gap_within_collapse():
    """With `collapse`, a gap no longer than it that the step would close is closed exactly:
    the step becomes the P-metric projection onto t2 - t1 = 0 (the batch formula), and no
    scaling throttles the rest; a longer gap keeps the appendix-C behaviour (it keeps at least
    1/(2 a_t) of its length)."""
    from jaxtraj._kalman import keep_knots_ordered

    dknots, D = _DKNOTS, _D_MIDDLE
    for P, da in _knot_steps([0.1, 0.0, 0.5]):  # t1 up: the middle gap would close
        knots = jnp.array([0.0, 1.0, 1.0 + 1e-8, 2.0])
        d, _ = keep_knots_ordered(jnp.asarray(da), jnp.asarray(P), knots, dknots, 10.0, collapse=1e-6)
        reference = da - P @ D.T @ np.linalg.solve(D @ P @ D.T, D @ da + 1e-8)
        np.testing.assert_allclose(d, reference, atol=1e-12)
        gaps = np.diff(np.asarray(knots + dknots @ d))
        assert abs(gaps[1]) < 1e-15 and np.all(gaps >= -1e-15)
        # the same gap with collapse below its length: not closed, at least 1/(2 a_t) kept
        d0, _ = keep_knots_ordered(jnp.asarray(da), jnp.asarray(P), knots, dknots, 10.0, collapse=1e-9)
        assert float(np.diff(np.asarray(knots + dknots @ d0))[1]) >= 1e-8 / 20 * (1 - 1e-9)


def test_keep_knots_ordered_does_not_scale_a_step_for_a_settled_gap():
    """A collapsed segment (gap 3.5e-30, held by the QP's gap row) that the step crosses by
    its round-off (1.25e-13, within 1e-14 of the knots' scale): settled, so the step is left
    as it is. It used to scale the whole step by (gap - floor) / 1.25e-13 = 2.5e-17: a zero
    step that ended a pendulum's minimum time STALLED at an infeasible point."""
    from jaxtraj._kalman import keep_knots_ordered

    knots = jnp.array([0.0, 3.5e-30, 12.69])
    dknots = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    da = jnp.array([-1.25e-13, 7.2e-3])
    d, _ = keep_knots_ordered(da, jnp.eye(2), knots, dknots, 10.0, collapse=1e-6)
    np.testing.assert_allclose(d, da, rtol=0, atol=1e-15)


def test_keep_knots_ordered_holds_a_collapsed_gap_that_another_gap_turns_to_closing():
    """A collapsed gap (t2 - t1 = -1e-17, round-off below 0) that the step opens, and a gap
    the step closes whose observation, through a covariance coupling t2 with t3, turns the
    collapsed one to closing: it is held at its length (a second, noise-free observation), so
    the step is the batch update on both rows. It used to scale the step by (g - floor) /
    -closing with g below its floor: by -3e-28, a zero step that the trust region accepted
    and then called no progress (a pendulum's minimum time: 3 of 32 random starts STALLED)."""
    from jaxtraj._kalman import batch_update, keep_knots_ordered

    knots = jnp.array([0.0, 1.0, 1.0 - 1e-17, 2.0])
    D = np.diff(np.asarray(_DKNOTS), axis=0)
    P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.9], [0.0, 0.9, 1.0]])
    gaps = np.diff(np.asarray(knots))
    for da in ([0.0, 0.05, -1.5], [0.0, 0.02, -1.2], [0.0, 0.1, -2.0]):  # t2 up, t3 down past t2
        d, _ = keep_knots_ordered(jnp.asarray(da), jnp.asarray(P), knots, _DKNOTS, 10.0, collapse=1e-6)
        # the last gap observed at 1/a_t of its length (variance z*^2 / 12), the middle one at its own
        z = np.array([gaps[2] / 10.0, gaps[1]])
        reference, _ = batch_update(np.asarray(da), P, -D[[2, 1]], z, np.array([z[0] ** 2 / 12.0, 1e-300]))
        np.testing.assert_allclose(d, reference, atol=1e-12)
        new_gaps = np.diff(np.asarray(knots + _DKNOTS @ d))
        assert abs(new_gaps[1]) < 1e-15 and new_gaps[2] > gaps[2] / 20.0


def test_keep_knots_ordered_leaves_a_settled_collapsed_gap_alone():
    """A collapsed gap (3e-26) that the step leaves at its length up to the knots' round-off
    (here -1e-20 after the step: the QP's gap row holds it) is not observed again: the step
    comes back unchanged, bit for bit. Observed again through the QP's covariance, which
    already pins that direction, the gain was round-off over round-off: it moved a
    pendulum's bounded levels by 1e-5 and the step lost its E rows (4 of 32 random starts)."""
    from jaxtraj._kalman import keep_knots_ordered

    knots = jnp.array([0.0, 1.0, 1.0 + 3e-26, 2.0])
    for P, da in _knot_steps([0.05, 0.05, -0.02]):
        da = np.asarray(da)
        da[0], da[1] = 0.0, -3e-26 - 1e-20  # t1 stays, t2 closes the middle gap to -1e-20
        d, _ = keep_knots_ordered(jnp.asarray(da), jnp.asarray(P), knots, _DKNOTS, 10.0, collapse=1e-6)
        np.testing.assert_array_equal(np.asarray(d), da)


def test_keep_knots_ordered_holds_half_a_closing_gap():
    """With `keep`, a gap the step would shrink below that fraction is held at exactly the
    fraction by a noise-free observation (the minimum-P^-1-norm change of the step, as the
    batch projection gives), so the other parameters are not throttled; gaps the step leaves
    alone are untouched."""
    from jaxtraj._kalman import keep_knots_ordered

    knots = jnp.array([0.0, 1.0, 1.5, 3.0])  # gaps 1, 0.5, 1.5 (t1, t2, t3 = a0, a1, a2)
    dknots, D = _DKNOTS, _D_MIDDLE
    for P, da in _knot_steps([0.45, 0.05, 0.3]):  # the middle gap shrinks by ~80 %
        d, _ = keep_knots_ordered(jnp.asarray(da), jnp.asarray(P), knots, dknots, 10.0, keep=0.5)
        gaps = np.diff(np.asarray(knots + dknots @ d))
        np.testing.assert_allclose(gaps[1], 0.25, rtol=1e-9)  # half of 0.5 kept
        target = -0.25  # the middle gap's change
        reference = da - P @ D.T @ np.linalg.solve(D @ P @ D.T, D @ da - target)
        np.testing.assert_allclose(d, reference, atol=1e-9)
        assert np.all(gaps > 0)
