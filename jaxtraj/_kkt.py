"""KKT algebra of the restricted problem, shared by every solver: the constraint rows of an
`Evaluation` (terminal equalities, then the inequalities: path, terminal), the active ones,
least-squares multipliers, the gradient of the Lagrangian, the stationarity residual with
multipliers of the right sign, the projected gradient and the SQP termination rule."""

from typing import Literal, overload

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float

from ._bounds import knot_gap_rows

#: Inequality rows with values >= -ACTIVE_TOL may be active (a solver without its own
#: activity tolerance; KalmanSQP's `path_active` otherwise, the same default).
ACTIVE_TOL = 1e-6
#: An inequality row within the activity tolerance whose multiplier's share of the
#: stationarity balance, nu_i |J_i| / (|G_a| + sum_j |lambda_j| |J_j|), is at most this is
#: weakly active: it does not hold the point (the solution map may have a kink there; the
#: implicit function theorem leaves it out of the active set: docs/differentiable.md).
WEAK_TOL = 1e-8


def inequality_rows(ev):
    """The inequality constraints (<= 0) of an `Evaluation` as rows, `(values, Jacobian)`: the
    path constraints on the grid flattened (point after point, N q rows), then the terminal
    inequalities D, then the control-bound rows V; None for a problem without inequalities."""
    parts = []
    if ev.C is not None:
        parts.append((ev.C.reshape(-1), ev.C_a.reshape(ev.C.size, -1)))
    if ev.D is not None:
        parts.append((ev.D, ev.D_a))
    if ev.V is not None:
        parts.append((ev.V, ev.V_a))
    if not parts:
        return None
    return jnp.concatenate([p[0] for p in parts]), jnp.concatenate([p[1] for p in parts])


def with_knot_gaps(control, ev, a):
    """`ev` with the knot gaps t_k - t_{k+1} <= 0 of free knots (the time span t_0 - tf <= 0
    of equally spaced ones) as more parameter rows (`Evaluation.V`, `_bounds.knot_gap_rows`),
    for the KKT and infeasibility tests: a segment shrunk to (nearly) zero length is held by
    its gap, whose multiplier the stationarity residual must see."""
    gaps = knot_gap_rows(control, a)
    if gaps is None:
        return ev
    V, V_a = gaps if ev.V is None else (jnp.concatenate([ev.V, gaps[0]]), jnp.concatenate([ev.V_a, gaps[1]]))
    return eqx.tree_at(lambda e: (e.V, e.V_a), ev, (V, V_a), is_leaf=lambda x: x is None)


def constraint_rows(ev):
    """[H; C_a]: the Jacobian of all constraints, terminal and inequality (`inequality_rows`)."""
    rows = inequality_rows(ev)
    return ev.H if rows is None else jnp.concatenate([ev.H, rows[1]])


def active_rows(ev, tol):
    """[H; C_a of the inequality rows with C >= -tol] (inactive rows zeroed): the constraints
    that the projected gradient of a KKT point has to be orthogonal to."""
    rows = inequality_rows(ev)
    if rows is None:
        return ev.H
    C, C_a = rows
    return jnp.concatenate([ev.H, jnp.where((C >= -tol)[:, None], C_a, 0.0)])


def multipliers(rows: Float[Array, "k p"], g: Float[Array, " p"], rcond=None) -> Float[Array, " k"]:
    """The multipliers lambda that minimize |g + rows^T lambda| (least squares, robust to
    dependent rows): every solver's multiplier estimate is this one solve. `rcond`: singular
    values of `rows` below it relative to the largest count as zero (default: round-off)."""
    return jnp.linalg.lstsq(rows.T, -g, rcond=rcond)[0]


def least_squares_multipliers(ev, path_active):
    """Least-squares multipliers of E and of the inequality rows with C >= -`path_active`
    ([H; C_a]^T lambda ~ -G_a, nu >= 0 by `signed_multipliers`; zero elsewhere):
    started at a converged point, the first active set is the touching one. (One solve with
    the negative nu clipped afterwards is no estimate where neighbouring grid points are
    nearly dependent: their huge multipliers of opposite signs cancel in the solve, and
    clipping leaves the positive halves; benchmarks/RESULTS.md.)"""
    rows = inequality_rows(ev)
    if rows is None:
        return multipliers(ev.H, ev.G_a)
    C, C_a = rows
    return signed_multipliers(ev.G_a, ev.H, C_a, C >= -path_active)[1]


def lagrangian_gradient(ev, lam):
    """Gradient of the Lagrangian G + lambda^T [E; C] (terminal and inequality rows)."""
    return ev.G_a + constraint_rows(ev).T @ lam


def scale_free(ev, a, W, lam, tol=1e-8):
    """Whether the problem cannot see the parameters' common scale at `a`: the objective and
    every constraint row flat along `a` (G_a . a = 0, rows a = 0) and the Lagrangian's Hessian
    `W` (multipliers `lam`) with W a = -grad L, the identities of a function homogeneous of
    degree 0 in `a` (a control that enters only as a direction, u / |u|, with every parameter
    a node of it: orbit raising's thrust). Each is tested relative to its terms (`tol`, far
    above round-off and far below what a problem that sees its scale shows:
    benchmarks/RESULTS.md); the Hessian's identity rules out a point where G_a . a = 0 by
    chance. There a model couples the scale to the turn, -beta |g| (1 - alpha) along
    alpha a - beta g / |g| (the same step turns a smaller control further): steps at a
    radius shrink the scale, the gradient grows as 1 / |a| and the KKT
    test, scaled by max(|a_i|, 1), cannot pass. The SQP steps drop the component along `a`
    there (`without_scale`)."""
    rows = constraint_rows(ev)
    g = lagrangian_gradient(ev, lam)
    na = jnp.linalg.norm(a)
    free = jnp.abs(ev.G_a @ a) <= tol * jnp.linalg.norm(ev.G_a) * na
    free = free & (jnp.linalg.norm(rows @ a) <= tol * jnp.linalg.norm(rows) * na)
    free = free & (jnp.linalg.norm(W @ a + g) <= tol * (jnp.linalg.norm(W) * na + jnp.linalg.norm(g)))
    return free & (na > 0.0)


def without_scale(d, a, free):
    """`d` without its component along `a` where `free` (`scale_free`), else `d`."""
    return jnp.where(free, d - (d @ a) / jnp.where(free, a @ a, 1.0) * a, d)


def merit_value(
    G: Float[Array, ""],
    E: Float[Array, " m"],
    C: Float[Array, " q"] | None,
    lam: Float[Array, " m+q"],
    mu,
    on: Bool[Array, " q"] | None = None,
) -> Float[Array, ""]:
    """The augmented-Lagrangian merit of both KalmanSQP globalizations: G + lambda^T E + mu/2
    |E|^2 + sum_j psi(C_j, nu_j) with the PHR inequality term psi = (max(0, nu + mu C)^2 -
    nu^2) / (2 mu) (= nu C + mu/2 C^2 where nu + mu C > 0).

    `on` overrides which rows take the branch nu C + mu/2 C^2 (default nu + mu C > 0): at
    mu = 0 the term is max(nu, 0) C, kinked at nu = 0, and a slope along a step that raises
    a zero multiplier must take that row's branch (`LineSearch.start`)."""
    m = E.shape[0]
    value = G + lam[:m] @ E + 0.5 * mu * (E @ E)
    if C is not None:
        nu = lam[m:]
        on = nu + mu * C > 0 if on is None else on
        off = jnp.where(nu > 0, -(nu**2) / (2.0 * jnp.where(mu > 0, mu, 1.0)), 0.0)  # nu > 0 here implies mu > 0
        value = value + jnp.sum(jnp.where(on, nu * C + 0.5 * mu * C**2, off))
    return value


def merit(ev, lam, mu):
    """`merit_value` at an `Evaluation` (its inequality rows as C)."""
    rows = inequality_rows(ev)
    return merit_value(ev.G, ev.E, None if rows is None else rows[0], lam, mu)


def curvature_error(ev, E_cand: Float[Array, " m"], d: Float[Array, " p"]) -> Float[Array, " m"]:
    """E(a + d) - (E + H d): what the constraints' linear model at `ev` missed along the step
    d, the target of a second-order correction (`KalmanSQP.correction`)."""
    return E_cand - (ev.E + ev.H @ d)


def is_feasible(ev, ctol):
    """max |E| <= `ctol` and every inequality row <= `ctol` (SUCCESS's feasibility)."""
    rows = inequality_rows(ev)
    ok = jnp.max(jnp.abs(ev.E), initial=0.0) <= ctol
    return ok if rows is None else ok & (jnp.max(rows[0]) <= ctol)


def kkt_outcome(feasible, pg, G, gtol, acceptable_gtol, no_progress, streak, acceptable_steps):
    """`(converged, stalled, streak)` of an SQP iteration: converged when `feasible` and the
    projected gradient `pg` <= `gtol` (1 + |G|), or when the point is acceptable (feasible,
    `pg` <= `acceptable_gtol` (1 + |G|)) and either `no_progress` (round-off leaves no
    measurable progress) or it has been acceptable for `acceptable_steps` steps in a row
    (`streak`, returned updated: IPOPT's `acceptable_iter` rule); stalled when progress ended
    short of that. The second level keeps the outcome off the knife edge where the projected
    gradient's round-off floor (set by the sensitivities) meets `gtol`; the streak bounds an
    endgame that moves only the discretization's error along a degenerate valley (equal
    control arcs split among several pieces), whose length would otherwise follow the last
    bits of the start and the CPU (issue 49)."""
    scale = 1.0 + jnp.abs(G)
    acceptable = feasible & (pg <= acceptable_gtol * scale)
    streak = jnp.where(acceptable, streak + 1, 0).astype(jnp.int32)
    converged = (feasible & (pg <= gtol * scale)) | (acceptable & (no_progress | (streak >= acceptable_steps)))
    return converged, ~converged & no_progress, streak


def parameter_scale(a):
    """max(|a_i|, 1): the scale of each parameter in the stationarity test."""
    return jnp.maximum(jnp.abs(a), 1.0)


def stationarity(ev, a, tol):
    """The first-order KKT stationarity residual with multipliers of the right sign, in the
    coordinates a_i / max(|a_i|, 1) (Dennis & Schnabel's relative gradient): |D (G_a + H^T
    lambda + C_a^T nu)| with D = `parameter_scale(a)`, over free lambda (equalities) and
    nu >= 0 on the inequality rows with C >= -`tol` (nu = 0 on the others). Without
    inequalities it is the projected gradient |V D G_a| of the scaled problem. The scale
    keeps a free scale of the parameters (a gauge: a control vector normalized in the
    dynamics) from passing the test by growing them, which shrinks the raw gradient as 1/|a|
    (orbit raising: a false SUCCESS at |a| ~ 1e6, docs/history.md).

    The multipliers are the non-negative least-squares solution on the near-active rows
    (`signed_multipliers`): a row that the gradient pulls the point away from (a negative
    multiplier) does not count as holding the point."""
    return stationarity_multipliers(ev, a, tol)[0]


@overload
def kkt_residual(ev, a, tol, *, with_multipliers: Literal[False] = False) -> jax.Array: ...
@overload
def kkt_residual(ev, a, tol, *, with_multipliers: Literal[True]) -> tuple[jax.Array, jax.Array]: ...
def kkt_residual(ev, a, tol, *, with_multipliers=False):
    """`stationarity`, or the complementarity max_i nu_i max(-C_i, 0) of its multipliers if
    larger: KalmanSQP's SUCCESS test. A row within `tol` of its bound counts as active, and
    with the stationarity residual alone a point that left such a row 1e-7 inside was
    stationary: a vertex optimum (a minimum time with |u| <= 1 and a reach inequality) ended
    SUCCESS 2e-7 from it. nu_i |C_i| bounds what the row still costs the objective (the
    duality gap of a convex problem), in the objective's units as the stationarity test.
    With `with_multipliers`, `(residual, [lambda; nu])`."""
    residual, lam = stationarity_multipliers(ev, a, tol)
    rows = inequality_rows(ev)
    if rows is not None:
        nu = lam[ev.E.shape[0] :]
        residual = jnp.maximum(residual, jnp.max(nu * jnp.maximum(-rows[0], 0.0), initial=0.0))
    return (residual, lam) if with_multipliers else residual


def stationarity_multipliers(ev, a, tol):
    """`(residual, [lambda; nu])`: `stationarity`'s residual and the multipliers that give it
    (in the units of the constraints: the scale multiplies the residual, not them)."""
    D = parameter_scale(a)
    rows = inequality_rows(ev)
    C, C_a = (jnp.zeros(0, a.dtype), jnp.zeros((0, a.shape[0]), a.dtype)) if rows is None else rows
    return signed_multipliers(ev.G_a * D, ev.H * D[None], C_a * D[None], C >= -tol)


def infeasibility_stationarity(ev, tol):
    """The same residual for the constraint violation phi = 1/2 |E|^2 + 1/2 |max(C, 0)|^2
    (no equality rows): |grad phi + V_a^T nu| over nu >= 0 on the parameter rows V (bounds,
    knot gaps, time span: no solver crosses them) with |V| <= `tol` (met, or violated by no
    more than round-off: a final time pressed to 0 from above ends at V = +3e-15). Zero
    (relative to |H| |E|) at a point where no step that keeps those rows can lower the
    violation to first order: locally infeasible. A path or terminal row at its bound holds
    nothing: crossing it costs phi only to second order (a least time whose half-space held
    the point was called infeasible where a step through it lowers the violation; issue 49)."""
    rows = inequality_rows(ev)
    grad = ev.H.T @ ev.E
    if rows is None:
        return jnp.linalg.norm(grad)
    C, C_a = rows
    grad = grad + C_a.T @ jnp.maximum(C, 0.0)
    if ev.V is None:
        return jnp.linalg.norm(grad)
    return signed_multipliers(grad, ev.H[:0], ev.V_a, jnp.abs(ev.V) <= tol, exact=False)[0]


def locally_infeasible(ev, tol, rtol):
    """Whether `ev` violates its constraints at a stationary point of the violation
    (`infeasibility_stationarity` <= `rtol` x (|H| |E| + |C_a| |max(C, 0)|)): a local minimum
    of the violation that no solver started here can leave, reported as CONSTRAINT_STATIONARY
    instead of STALLED."""
    rows = inequality_rows(ev)
    scale = jnp.linalg.norm(ev.H) * jnp.linalg.norm(ev.E)
    if rows is not None:
        scale = scale + jnp.linalg.norm(rows[1]) * jnp.linalg.norm(jnp.maximum(rows[0], 0.0))
    return (scale > 0.0) & (infeasibility_stationarity(ev, tol) <= rtol * scale)


def signed_multipliers(
    g: Float[Array, " p"], H: Float[Array, "m p"], C_a: Float[Array, "q p"], keep: Bool[Array, " q"], exact=True
) -> tuple[Float[Array, ""], Float[Array, " m+q"]]:
    """`(residual, [lambda; nu])`: min |g + H^T lambda + C_a^T nu| over free lambda and
    nu >= 0 (nu = 0 off `keep`), and the multipliers that give it.

    First the least-squares rounds of `stationarity` (each drops the rows with a negative
    multiplier: one or two rounds at most points), then Lawson and Hanson's active-set
    method for non-negative least squares from there, which brings back a dropped row
    while it lowers the residual: the rounds drop every negative row at once, and at a
    degenerate vertex (a COPS robot arm's optimum: 30 active control bounds and 6 terminal
    equalities for 34 parameters) they ended at a residual of 9e-2 where the exact minimum
    is 7e-16, and the SUCCESS test rejected a KKT point. (Written here, not taken from
    SciPy's `nnls`, so that it runs inside the compiled solvers, under `vmap`, with free
    lambda.) With `exact=False` the rounds alone (an upper bound of the residual, for the
    estimates where that suffices: it keeps a second loop out of the compiled step)."""
    m = H.shape[0]
    A = jnp.concatenate([H, C_a]).T  # columns: the rows' gradients
    free = jnp.arange(A.shape[1]) < m

    def solve(passive):
        return jnp.where(passive, multipliers(jnp.where(passive[:, None], A.T, 0.0), g), 0.0)

    # the rounds: round 0 solves on `keep`; each later one drops the rows with a negative
    # multiplier (one trace of `solve`, in the loop body)
    def cond(carry):
        keep, lam, rounds = carry
        return (rounds == 0) | (jnp.any(keep & (lam[m:] < 0.0)) & (rounds <= keep.shape[0]))

    def body(carry):
        keep, lam, rounds = carry
        keep = jnp.where(rounds == 0, keep, keep & (lam[m:] >= 0.0))
        return keep, solve(jnp.concatenate([jnp.ones(m, bool), keep])), rounds + 1

    kept, lam, _ = lax.while_loop(cond, body, (keep, jnp.zeros(m + keep.shape[0], g.dtype), 0))

    if keep.shape[0] == 0 or not exact:  # (no sign constraints: the least-squares solve is exact)
        return jnp.linalg.norm(g + A @ lam), lam

    # Lawson-Hanson from the rounds' point: the passive set holds the free multipliers and
    # the positive nu; a kept row whose multiplier would lower the residual (w_j > tol)
    # enters, and an inner loop steps back to the feasible segment while a passive nu turns
    # non-positive (that row leaves)
    lam = jnp.where(free, lam, jnp.maximum(lam, 0.0))
    passive = free | jnp.concatenate([jnp.zeros(m, bool), kept & (lam[m:] > 0.0)])
    candidates = jnp.concatenate([jnp.zeros(m, bool), keep])
    scale = jnp.max(jnp.sum(jnp.abs(A), axis=0), initial=0.0) * jnp.linalg.norm(g)
    tol = 10.0 * max(A.shape[0], A.shape[1], 1) * jnp.finfo(g.dtype).eps * scale

    def inner_cond(carry):
        passive, _, z, steps = carry
        return jnp.any(passive & ~free & (z <= 0.0)) & (steps <= A.shape[1])

    def inner_body(carry):
        passive, lam, z, steps = carry
        bad = passive & ~free & (z <= 0.0)
        ratio = jnp.where(bad, lam / jnp.where(bad, lam - z, 1.0), jnp.inf)
        j = jnp.argmin(ratio)
        lam = lam + ratio[j] * (z - lam)
        passive = passive.at[j].set(False) & (free | (lam > 0.0))
        return passive, jnp.where(passive, lam, 0.0), solve(passive), steps + 1

    def outer_cond(carry):
        passive, lam, iters, stuck = carry
        w = A.T @ (-g - A @ lam)
        return jnp.any(candidates & ~passive & (w > tol)) & (iters < 3 * A.shape[1]) & ~stuck

    def outer_body(carry):
        passive, lam, iters, _ = carry
        w = A.T @ (-g - A @ lam)
        t = jnp.argmax(jnp.where(candidates & ~passive, w, -jnp.inf))
        passive = passive.at[t].set(True)
        passive, lam, z, _ = lax.while_loop(inner_cond, inner_body, (passive, lam, solve(passive), 0))
        # (round-off can send the entering row straight out again: then nothing changes)
        return passive, z, iters + 1, ~passive[t]

    _, lam, _, _ = lax.while_loop(outer_cond, outer_body, (passive, lam, 0, jnp.array(False)))
    lam = jnp.where(free, lam, jnp.maximum(lam, 0.0))
    return jnp.linalg.norm(g + A @ lam), lam


def projected_gradient(G_a: Float[Array, " p"], H: Float[Array, "m p"]) -> Float[Array, ""]:
    """|V G_a|, V = I - H^T (H H^T)^-1 H [3.62] (least squares, robust to dependent rows)."""
    return jnp.linalg.norm(G_a + H.T @ multipliers(H, G_a))


def weak_rows(G_a, H, J, rows, multipliers, tol):
    """Per inequality row (values `rows`, Jacobian `J`): within `tol` of active while its
    multiplier (`multipliers` = [lambda; nu], of `H`'s and `J`'s rows) carries at most
    `WEAK_TOL` of the stationarity balance: weakly active."""
    m = H.shape[0]
    norms = jnp.linalg.norm(jnp.concatenate([H, J]), axis=1)
    balance = jnp.linalg.norm(G_a) + jnp.sum(jnp.abs(multipliers) * norms)
    return (rows >= -tol) & ~(multipliers[m:] * norms[m:] > WEAK_TOL * balance)
