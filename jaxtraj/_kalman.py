"""The sequential Kalman filter update: the one place where the search increment is computed.

Given a prior estimate `da` of the increment with covariance `P`, and scalar observations
z_i = h_i . Da + v_i with independent noise variances r_i, the minimum-variance estimate
(seed 000 eq. 3.1-3.7, Gauss's norm eq. 2.20) is computed one observation at a time, with no
matrix inversion (Bryson & Ho form, seed 000 eq. 3.15 / 2.23):

    k  = P h / (r + h P h)
    da = da + k (z - h da)
    P  = P - (P h)(P h)^T / (r + h P h)

The last line is written as a symmetric outer product, so P stays exactly symmetric.
The result equals the batch formula K = P H^T (H P H^T + R)^-1 for any processing order.
"""

import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float

# Shapes (jaxtyping, documentation only): p parameters, m equality rows, q inequality rows,
# g knot gaps.


def sequential_update(
    da: Float[Array, " p"],
    P: Float[Array, "p p"],
    H: Float[Array, "m p"],
    z: Float[Array, " m"],
    r: Float[Array, " m"],
    active: Bool[Array, " m"] | None = None,
) -> tuple[Float[Array, " p"], Float[Array, "p p"], Float[Array, " m"]]:
    """Absorb the rows of `H` (shape `(m, p)`) one at a time.

    **Arguments:**

    - `da`: prior estimate, shape `(p,)`.
    - `P`: prior covariance, shape `(p, p)`, symmetric positive semi-definite.
    - `H`: observation rows, shape `(m, p)`.
    - `z`: observations, shape `(m,)`.
    - `r`: observation noise variances, shape `(m,)`, > 0.
    - `active`: optional boolean mask `(m,)`; inactive rows are skipped (fixed shapes under
      jit, with a variable number of observations).

    **Returns:** `(da, P, innovation_variances)`: the posterior estimate and covariance, and
    h_i P h_i^T + r_i for each row (the denominators, useful diagnostics).
    """
    if active is None:
        active = jnp.ones(z.shape, dtype=bool)

    def absorb(carry, obs):
        est, cov = carry
        h, zi, ri, on = obs
        ph = cov @ h
        s = ri + h @ ph
        s_safe = jnp.where(on & (s > 0), s, 1.0)
        new_est = est + ph * ((zi - h @ est) / s_safe)
        new_cov = cov - jnp.outer(ph, ph) / s_safe
        keep = on & (s > 0)
        return (jnp.where(keep, new_est, est), jnp.where(keep, new_cov, cov)), s

    (da, P), s = lax.scan(absorb, (da, P), (H, z, r, active))
    return da, P, s


def keep_knots_ordered(
    da: Float[Array, " p"],
    P: Float[Array, "p p"],
    knots: Float[Array, " g+1"],
    dknots: Float[Array, "g+1 p"],
    a_t,
    keep=None,
    collapse=0.0,
) -> tuple[Float[Array, " p"], Float[Array, "p p"]]:
    """Seed 000 appendix C: keep the segment boundaries in order after the increment `da`.

    Each gap g_i = t_{i+1} - t_i that `da` would close (g_i + dg_i/da . da <= 0) becomes one
    more observation, filtered after the regular ones: on h* = -dg_i/da (the *approach* of
    the two knots) z* = g_i / a_t with variance z*^2 / 12 [C.4-C.5] (OCR: the thesis prints
    the observation, not a_t; see `KalmanSearch.a_t`). With `keep` (a fraction in (0, 1)),
    a gap that would still keep less than `keep` of its length is then observed, without
    noise, at exactly that fraction: the gap is held while every other parameter moves on.
    If the order is still violated, `da` is scaled so that every gap keeps at least
    1/(2 a_t) of its length. Gaps are linear in a, so every step `alpha da` with alpha in
    [0, 1] keeps the order too. A gap of at most `collapse` that `da` would close is instead
    closed (observed without noise at its whole length): a segment on its way to length 0
    gets there in one step instead of shrinking by 1/a_t per step (a linear crawl that
    slowed every other parameter with it). A gap of at most `collapse` that `da` opens but
    the observations of the others turn to closing (a covariance coupling its knots with
    theirs) is then held at its length the same way; the final scaling skips gaps already at
    or below their floor (a collapsed gap a hair below 0 gave a factor of -3e-28: a zero step).
    A gap at 0 that `da` leaves at 0 (within 1e-14 of the knots' scale) is settled: not
    observed (the QP's gap rows already hold it) and not a reason to scale the step.

    `knots` `(K + 1,)` and `dknots = dknots/da` `(K + 1, p)` at the current point. Returns
    `(da, P)`.
    """
    gaps = knots[1:] - knots[:-1]
    D = dknots[1:] - dknots[:-1]  # d(gap)/da, (K, p)
    # a gap at 0 that the step leaves at 0, both up to the knots' round-off (`tiny`), is
    # settled: observed again through a covariance that already pins it (the QP's gap rows),
    # its gain is round-off over round-off (it moved a pendulum's bounded levels by 1e-5)
    tiny = 1e-14 * jnp.max(jnp.abs(knots))
    after = gaps + D @ da
    settled = (jnp.abs(gaps) <= tiny) & (jnp.abs(after) <= tiny)
    violated = (after <= 0.0) & ~settled
    close = violated & (gaps <= collapse)
    z_star = jnp.where(close, gaps, gaps / a_t)
    r_star = jnp.where(close, 0.0, (z_star**2) / 12.0) + 1e-300  # closed: noise-free
    da, P, _ = sequential_update(da, P, -D, z_star, r_star, active=violated)
    # a collapsed gap that the observations above turned to closing is held at its length too
    held = ~violated & (gaps <= collapse) & (gaps + D @ da < -tiny)
    da, P, _ = sequential_update(da, P, -D, gaps, jnp.full_like(gaps, 1e-300), active=held)
    close = close | held
    if keep is not None:
        short = (gaps > 0.0) & (gaps + D @ da < keep * gaps)
        r = 1e-12 * jnp.einsum("ip,pq,iq->i", D, P, D) + 1e-300
        da, P, _ = sequential_update(da, P, -D, (1.0 - keep) * gaps, r, active=short)
    closing = D @ da
    # A gap already at 0 (a collapsed segment, a duration h_k = 0 at its bound) is held there
    # by its observation (z* = 0, variance 0) up to round-off; only a real closing scales the
    # step (else one collapsed segment would freeze every other parameter).
    # A settled gap does not scale it either: its round-off crossing (the QP's gap row met to
    # 1e-13) scaled a pendulum's whole step by 3e-17, a zero step that ended the search.
    real = ~settled & (closing < -1e-12 * jnp.linalg.norm(D, axis=1) * jnp.linalg.norm(da))
    floor = jnp.where(close, 0.0, gaps / (2.0 * a_t))
    limit = jnp.where(
        real & (gaps + closing < floor) & (gaps > floor), (gaps - floor) / jnp.maximum(-closing, 1e-300), 1.0
    )
    return da * jnp.min(limit, initial=1.0), P


#: `dual_active_set` forms P_W and M again at every this-many-th row departure and downdates
#: them at the others.
REFACTOR_EVERY = 4


#: KalmanSearch's `dependence` in `observe_worst`: a path row whose variance left by the rows
#: already observed is below this fraction of its prior variance is skipped.
PATH_DEPENDENCE = 1e-4


def observe_worst(d, P, C, C_a, r, prior_var, dependence, threshold, active, seen, rounds):
    """Inequalities C + C_a d <= 0 the appendix-C way, one row per round: the row the
    current `d` would violate most (above `threshold`, not yet `seen`) is observed at its
    boundary, C_a d = -C with noise `r`, by the same rank-one update (a primal active-set
    QP). A row (nearly) dependent on those already observed (its variance left by them below
    `dependence` x its prior variance `prior_var`: neighbouring grid points) is skipped: it
    would add no freedom, only ill-conditioned gains. Returns `(d, P, active)`."""

    def add_worst(carry, _):
        d, P, active, seen = carry
        v = jnp.where(seen, -jnp.inf, C + C_a @ d)
        j = jnp.argmax(v)
        h = C_a[j]
        wanted = v[j] > threshold
        add = wanted & (h @ P @ h > dependence * prior_var[j])
        d, P, _ = sequential_update(d, P, h[None], -C[j][None], r[j][None], active=add[None])
        return (d, P, active.at[j].set(active[j] | add), seen.at[j].set(seen[j] | wanted)), None

    (d, P, active, _), _ = lax.scan(add_worst, (d, P, active, seen), None, length=rounds)
    return d, P, active


def dual_active_set(
    d: Float[Array, " p"],
    P: Float[Array, "p p"],
    H: Float[Array, "m p"],
    C: Float[Array, " q"],
    C_a: Float[Array, "q p"],
    r: Float[Array, " q"],
    prior_var: Float[Array, " q"],
    dependence,
    threshold,
    max_iter: int,
    num_equalities=None,
    warm: Bool[Array, " q"] | None = None,
    pinned: Bool[Array, " q"] | None = None,
    dual_bound=None,
) -> tuple[Bool[Array, " q"], Float[Array, " q"], Float[Array, " q"], Array, Array]:
    """The inequality QP of an SQP step by Goldfarb & Idnani's dual active-set method (Math.
    Programming 27, 1983) in filter form.

    Starting point: `d` and `P`, the minimum of the quadratic model on the equality rows `H`
    and the covariance left by filtering them (P^-1 = B + H^T R^-1 H, B the model's Hessian,
    R the rows' noise). Sought: the minimum with C + C_a d <= 0 too. The working set W
    starts empty (dual feasible: all multipliers 0); each round takes the row p that d
    violates most (above `threshold`) and moves along z = P_W c_p, P_W the covariance after
    filtering W's rows (noise `r`): the step that lowers row p's value while keeping E's and
    W's, optimal in the metric of B. The multipliers u of W change by t rho, rho the solution
    of [H; C_W]^T rho = B z - c_p (stationarity along the step), whose W part is -(C_W P
    C_W^T + R_W)^-1 C_W P c_p (that of H is not needed). The step length t is the smaller of the full
    step s_p / (c_p^T z), which adds p to W, and the partial step at which a multiplier of W
    reaches 0, which drops that row and retries p. A row (nearly) dependent on W (c_p^T z
    below `dependence` x its prior variance `prior_var`: neighbouring grid points) takes the
    partial step only: it replaces a working row instead of being skipped, so the active set
    cannot cycle between grid neighbours; so does any row once W holds n - m rows (n
    parameters, m rows of `H`), which the noise floor of the filter (`r`) could otherwise
    let pass as independent (`num_equalities`, default m, may count fewer: rows of `H` that
    are zeros). Every round either adds a row or strictly raises
    the dual objective (the method's finite convergence); `max_iter` bounds the rounds.

    A violated row that no step can meet (dependent on W, and no multiplier of W blocks:
    the linearized constraints are inconsistent, or, at a vertex, the row is violated by
    the filter's round-off only) is skipped. Returns `(W, u, excess, rounds, rise)`: the
    working set (boolean, per row), its multipliers, C + C_a d on the rows outside W (-inf on
    W's): its maximum is <= `threshold` unless a row was skipped (round-off, or the
    inconsistency) or the rounds ended early (`max_iter`, `dual_bound`), the rounds taken and
    the dual objective's rise. The caller filters W's rows to get the step itself.

    `warm` (boolean, per row; the rows active in the last QP of an SQP run) starts W there
    instead of empty: its rows are filtered (dependent ones and those past the rank left
    out), and the rows whose multipliers at that minimum are negative are dropped until none
    is (`_warm_start`): a dual feasible start of the same method, so the same solution, in
    far fewer rounds once the active set settles (issue 49: the free-flying robot's QPs took
    300-500 rounds from W empty, a few from the last active set).

    `pinned` (boolean, per row) marks rows that the equality rows alone fix (their variance
    left by them far below the prior's): such a row never joins W, and its value is what
    E's step leaves (reported in the excess). No working row can move it, so its violation
    is E's round-off or an inconsistency; with it in the dual, round-off rho of 1e-13
    dropped a bound from a full W, and the row then joined as independent by 4x its
    `dependence` margin (a terminal inequality implied by the terminal equalities at a
    minimum-time vertex: the final step 0.6 past a bound, an elastic step that raised the
    violation, STALLED; issue 49).

    `dual_bound` (a scalar, default inf): an upper bound on the QP's optimal value minus the
    model's value at `d` (the caller's, from a bounded feasible region). The dual objective
    never exceeds the primal optimum, so once its rise exceeds the bound the QP is
    infeasible and the rounds end there, unfinished. (With its working set full, an
    infeasible QP's rows only replace one another, each swap raising the dual objective
    without bound: the free-flying robot's hard QP at its naive start ran all its 4 n + 20
    rounds, multipliers 1e115 at the end; issue 49.) The rise is tracked as Goldfarb and
    Idnani's: t (s_p - t z^T c / 2) per step of length t (z = 0 where d does not move), and
    (1/2) u^T s at a warm start.
    """
    m, n = H.shape[0], d.shape[0]
    rank_left = n - (m if num_equalities is None else num_equalities)
    # W's rows live in n slots (rows independent of E's and of each other are at most n), with
    # G = C_W P (one slot per row), M = S^-1, S = C_W P C_W^T + R_W, and P_W = P - G^T M G,
    # the covariance after filtering W's rows, kept up to date by rank-one changes when a row
    # joins or leaves (formed again at every `REFACTOR_EVERY`-th departure): a round costs
    # O(n^2) (issue 49: refiltering W's rows and a
    # least-squares solve for the multipliers in every round made a 124-parameter QP of a few
    # hundred rounds take 15 s). Free slots: zero rows of G, unit rows of M.
    # Along z = P_W c the model's gradient changes by B z - c = -C_W^T M G c (B the inverse of
    # P, E's rows with their noise included), so the multipliers of W change by rho = -M G c
    # (the solution of [H; C_W]^T rho = B z - c, exact where those rows are independent).

    def body(state):
        d, W, u, p, it, _, skipped, PW, M, G, slot_row, rise, since = state
        s = C + C_a @ d
        v = jnp.where(W | skipped, -jnp.inf, s)
        worst = jnp.argmax(v)
        pick = p < 0
        finished = pick & (v[worst] <= threshold)
        p = jnp.where(pick, worst, p)
        c = C_a[p]
        z = PW @ c
        zc = c @ z
        independent = (zc > dependence * prior_var[p]) & (jnp.sum(W) < rank_left)  # rank: |W| <= n - m
        w = M @ (G @ c)
        rho = jnp.zeros_like(C).at[jnp.maximum(slot_row, 0)].add(jnp.where(slot_row >= 0, -w, 0.0))
        ratio = jnp.where(W & (rho < 0), u / jnp.where(rho < 0, -rho, 1.0), jnp.inf)
        k = jnp.argmin(ratio)
        t_full = jnp.where(independent, s[p] / jnp.where(independent, zc, 1.0), jnp.inf)
        t = jnp.minimum(ratio[k], t_full)
        move = ~finished & jnp.isfinite(t)
        stuck = ~finished & ~jnp.isfinite(t)
        rise = rise + jnp.where(move, t * (s[p] - 0.5 * t * jnp.where(independent, zc, 0.0)), 0.0)
        d = jnp.where(move & independent, d - t * z, d)
        u = jnp.where(move, u + t * jnp.where(W, rho, 0.0), u)
        u = u.at[p].add(jnp.where(move, t, 0.0))
        full = move & (t_full <= ratio[k])
        drop = move & ~full
        W = W.at[k].set(W[k] & ~drop).at[p].set(W[p] | full)  # k may equal p
        u = u.at[k].set(jnp.where(drop, 0.0, u[k]))
        skipped = skipped.at[p].set(skipped[p] | stuck)
        # p joins W (the filter's rank-one update of P_W; M bordered by the Schur complement
        # zc + r_p of S)
        j = jnp.argmin(slot_row)  # a free slot (-1); W holds fewer than n rows here
        gamma = jnp.where(full, zc + r[p], 1.0)
        e_j = jnp.arange(n) == j
        vj = jnp.where(e_j, -1.0, w)
        PW = jnp.where(full, PW - jnp.outer(z, z) / gamma, PW)
        M = jnp.where(full, M - jnp.diag(e_j.astype(M.dtype)) + jnp.outer(vj, vj) / gamma, M)
        G = jnp.where(full & e_j[:, None], P @ c, G)
        slot_row = jnp.where(full & e_j, p, slot_row)
        # k leaves W: its slot i is freed, and P_W and M lose its row by the exact rank-one
        # downdate (M's column m_i: M - m_i m_i^T / M_ii, P_W + (G^T m_i)(G^T m_i)^T / M_ii).
        # Every `REFACTOR_EVERY`-th departure forms them again instead, from the rows left
        # (the filter over the slots, S inverted): downdates alone drifted over ~120 rounds
        # (a QP of the free-flying robot under SSE4.2 arithmetic ended 404 past a bound, its
        # trust region STALLED; issue 49), and a refactor at every departure cost 3.4 ms at
        # 124 parameters, 100-200 times in the robot's QPs (most of its solve). With a
        # refactor every 4th the robot takes the same 13 iterations from its start and its
        # 1e-12 / 1e-10 perturbations under three ISA settings as with one at every
        # departure; every 8th, 10-21 (docs/history.md, session 43).
        i = jnp.argmax(slot_row == k)
        e_i = jnp.arange(n) == i
        m_i = M[:, i]
        m_ii = jnp.where(drop, M[i, i], 1.0)
        y = G.T @ m_i
        G = jnp.where(drop & e_i[:, None], 0.0, G)
        slot_row = jnp.where(drop & e_i, -1, slot_row)
        downdated = drop & (since + 1 < REFACTOR_EVERY)
        PW = jnp.where(downdated, PW + jnp.outer(y, y) / m_ii, PW)
        M_down = M - jnp.outer(m_i, m_i) / m_ii
        M_down = jnp.where(e_i[:, None] | e_i[None, :], jnp.diag(e_i.astype(M.dtype)), M_down)
        M = jnp.where(downdated, M_down, M)
        since = jnp.where(drop, jnp.where(downdated, since + 1, 0), since)

        def refactor(slot_row):
            valid, at = slot_row >= 0, jnp.maximum(slot_row, 0)
            rows = C_a[at]
            PW = sequential_update(jnp.zeros_like(d), P, rows, jnp.zeros(n, d.dtype), r[at], active=valid)[1]
            return PW, _slot_inverse(rows @ P @ rows.T + jnp.diag(r[at]), valid)

        PW, M = lax.cond(drop & ~downdated, refactor, lambda _: (PW, M), slot_row)
        p = jnp.where(full | finished | stuck, -1, p)
        return d, W, u, p, it + 1, finished, skipped, 0.5 * (PW + PW.T), M, G, slot_row, rise, since

    bound = jnp.asarray(jnp.inf if dual_bound is None else dual_bound, d.dtype)

    def cond(state):
        return ~state[5] & (state[4] < max_iter) & ~(state[11] > bound)

    none = jnp.zeros(C.shape, bool)
    pinned = none if pinned is None else pinned
    at_start = C + C_a @ d
    if warm is None:
        W, u, PW, M, G, slot_row = (
            none,
            jnp.zeros_like(C),
            P,
            jnp.eye(n, dtype=d.dtype),
            jnp.zeros((n, n), d.dtype),
            jnp.full(n, -1),
        )
    else:
        d, W, u, PW, M, G, slot_row = _warm_start(d, P, C, C_a, r, prior_var, dependence, rank_left, warm & ~pinned)
    rise = 0.5 * jnp.sum(jnp.where(W, u * at_start, 0.0))
    init = (d, W, u, jnp.array(-1), jnp.array(0), jnp.array(False), pinned, PW, M, G, slot_row, rise, jnp.array(0))
    d, W, u, _, rounds, *_, rise, _ = lax.while_loop(cond, body, init)
    return W, u, jnp.where(W, -jnp.inf, C + C_a @ d), rounds, rise


def _slot_inverse(S, valid):
    """M = S^-1 over the occupied slots `valid`, unit rows and columns on the free ones."""
    eye = jnp.eye(S.shape[0], dtype=S.dtype)
    return jnp.linalg.inv(jnp.where(valid[:, None] & valid[None, :], S, eye))


def _warm_start(d, P, C, C_a, r, prior_var, dependence, rank_left, keep):
    """`dual_active_set`'s start from the rows `keep`: they are filtered into slots in
    order (a row whose variance left is below `dependence` x its prior variance, or one past
    `rank_left` rows, is left out), the multipliers at the minimum on them are u = M s, s their
    values at `d` (the filter's step d - G^T u meets them: stationarity along C_W^T u), and
    the rows with u < 0 are dropped and the rest filtered again until none is negative.
    Returns `(d, W, u, P_W, M, G, slot_row)` in `dual_active_set`'s terms."""
    n = d.shape[0]
    slots = jnp.arange(n)

    def fill(keep):
        idx = jnp.nonzero(keep, size=n, fill_value=0)[0]
        valid = slots < jnp.sum(keep)

        def add(carry, j):
            PW, count = carry
            p = idx[j]
            z = PW @ C_a[p]
            zc = C_a[p] @ z
            take = valid[j] & (zc > dependence * prior_var[p]) & (count < rank_left)
            PW = jnp.where(take, PW - jnp.outer(z, z) / jnp.where(take, zc + r[p], 1.0), PW)
            return (PW, count + take.astype(count.dtype)), take

        (PW, _), taken = lax.scan(add, (P, 0), slots)
        slot_row = jnp.where(taken, idx, -1)
        at = jnp.maximum(slot_row, 0)
        G = jnp.where(taken[:, None], C_a[at] @ P, 0.0)
        M = _slot_inverse(G @ C_a[at].T + jnp.diag(r[at]), taken)
        u = M @ jnp.where(taken, C[at] + C_a[at] @ d, 0.0)
        kept = jnp.zeros(C.shape, jnp.int32).at[at].max((taken & (u >= 0)).astype(jnp.int32)) > 0
        return kept, 0.5 * (PW + PW.T), M, G, slot_row, u

    def again(state):
        keep, passes, (kept, *_) = state
        return jnp.any(kept != keep) & (passes < n)

    first = fill(keep & jnp.isfinite(C))
    _, _, (_, PW, M, G, slot_row, u) = lax.while_loop(
        again, lambda s: (s[2][0], s[1] + 1, fill(s[2][0])), (keep & jnp.isfinite(C), 0, first)
    )
    at = jnp.maximum(slot_row, 0)
    valid = slot_row >= 0
    W = jnp.zeros(C.shape, jnp.int32).at[at].max(valid.astype(jnp.int32)) > 0
    u_rows = jnp.zeros_like(C).at[at].add(jnp.where(valid, u, 0.0))
    return d - G.T @ u, W, u_rows, PW, M, G, slot_row


def inequality_step(
    d: Float[Array, " p"],
    P: Float[Array, "p p"],
    H: Float[Array, "m p"],
    C: Float[Array, " q"],
    C_a: Float[Array, "q p"],
    r: Float[Array, " q"],
    prior_var: Float[Array, " q"],
    dependence,
    threshold,
    max_iter: int,
    equalities: tuple[Float[Array, "p p"], Float[Array, " m"], Float[Array, " m"]],
    num_equalities=None,
    warm: Bool[Array, " q"] | None = None,
    pinned: Bool[Array, " q"] | None = None,
    dual_bound=None,
):
    """The QP step with inequalities: from the equality-constrained step `d` with covariance
    `P` (E's rows `H` filtered), the working set of `dual_active_set`, then its rows
    filtered as observations C_a d = -C (noise `r`), with one refinement pass (the same
    update with the first estimate as prior mean) over E's first `num_equalities` rows and the
    working rows together, from `equalities = (P0, E, r_E)`: P0 the covariance before E's
    rows, r_E their noise. The step then meets both to round-off of its own size; refined
    through P alone, E's rows kept the round-off of the intermediate estimates, which are huge
    where B has directions of nearly zero curvature (variance 1e8) before the working rows
    take the step back (|H d + E| as large as |E|: a pendulum's minimum time STALLED above
    `ctol`; RESULTS.md). Returns `(d, P, W, u, excess)`: the step, its covariance, and
    `dual_active_set`'s working set, multipliers and excess (`warm`: its start; `pinned`:
    rows that cannot join it; `dual_bound`: where it gives up)."""
    W, u, excess, _, _ = dual_active_set(
        d, P, H, C, C_a, r, prior_var, dependence, threshold, max_iter, num_equalities, warm, pinned, dual_bound
    )
    # W's rows gathered in their order into n slots (at most n are independent): the same
    # updates as a scan over every row that skips the others, at a fraction of the rounds
    n = d.shape[0]
    idx = jnp.nonzero(W, size=n, fill_value=0)[0]
    valid = jnp.arange(n) < jnp.sum(W)
    d1, _, _ = sequential_update(d, P, C_a[idx], -C[idx], r[idx], active=valid)
    P0, E, r_E = equalities
    m = E.shape[0]
    on = jnp.arange(m) < (m if num_equalities is None else num_equalities)
    rows, z, noise = jnp.concatenate([H, C_a[idx]]), jnp.concatenate([-E, -C[idx]]), jnp.concatenate([r_E, r[idx]])
    d1, P1, _ = sequential_update(d1, P0, rows, z, noise, active=jnp.concatenate([on, valid]))
    return d1, P1, W, u, excess


def batch_update(
    da: Float[Array, " p"], P: Float[Array, "p p"], H: Float[Array, "m p"], z: Float[Array, " m"], r: Float[Array, " m"]
) -> tuple[Float[Array, " p"], Float[Array, "p p"]]:
    """The same estimate by the batch formula (for tests and reference only)."""
    S = H @ P @ H.T + jnp.diag(r)
    K = jnp.linalg.solve(S, H @ P).T
    return da + K @ (z - H @ da), P - K @ H @ P


def projection_matrix(H: Float[Array, "m p"]) -> Float[Array, "p p"]:
    """Rosen's projection V = I - H^T (H H^T)^-1 H onto the null space of H (rows independent)."""
    p = H.shape[1]
    return jnp.eye(p, dtype=H.dtype) - H.T @ jnp.linalg.solve(H @ H.T, H)


__all__ = [
    "batch_update",
    "dual_active_set",
    "inequality_step",
    "keep_knots_ordered",
    "observe_worst",
    "projection_matrix",
    "sequential_update",
]
