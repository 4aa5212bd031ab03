"""Derivatives of a solve by the implicit function theorem (issue 50).

At a SUCCESS point a* of the restricted problem, the KKT conditions with the active set A
(the terminal equalities, and the inequality rows at their bound that hold the point: a
positive multiplier)

    grad_a L(a, lambda; theta) = 0,   c_A(a; theta) = 0,   L = G + lambda^T [E; C]

define a*(theta) for every array theta in the problem and its control (`args`, `x0`, the
control's fixed final time, state-bound values). Their tangent along theta_dot is one
linear solve with the KKT matrix [[W, J_A^T], [J_A, 0]] (W the exact Hessian of the
Lagrangian, J_A the active rows' Jacobian), right-hand side the jvp of the two conditions in
theta: linear in theta_dot, so reverse mode follows by transposition. The solver's
iterations are never differentiated, and the start a0 has no derivative.

The KKT matrix is solved by its null-space form: the active rows, each scaled to unit
norm, by an SVD, then W on the rows' null space (positive definite at a strict local
minimum, else singular). Dependent active rows (a boundary arc on the grid) leave the
tangent unique where their change in theta stays in their range and W on that null space
does not depend on how the multipliers are shared among them; both are checked, else NaN.
The tangents themselves use the rows' pseudo-inverse, whose derivative (forward mode over
them: `jax.hessian`) is finite where the SVD's is not (repeated zero singular values). A solve that did not end SUCCESS, a singular KKT matrix or a non-finite
quantity gives NaN tangents, never a silent number (docs/differentiable.md).

Everything here is forward mode in the parameters (`jax.jacfwd`), so that any simulator
works; with one that is not `RK4` the derivatives in theta are explicit Jacobians
(`_jvp`), so that reverse mode can transpose them.
"""

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.flatten_util import ravel_pytree

from ._bounds import bound_rows, knot_gap_rows
from ._kkt import ACTIVE_TOL, parameter_scale, signed_multipliers, weak_rows
from ._sensitivity import lagrangian_hessian, path_values
from ._simulate import RK4, final_state
from ._status import Status

#: Singular values of the unit-scaled active rows below this fraction of the largest make
#: them dependent (`_kkt_point`: their tangents need more checks, and multipliers have none).
RANK_TOL = 1e-9
#: Dependent active rows: W on their null space may change by this fraction of |W| along the
#: multipliers' freedom (`_kkt_point`), else NaN tangents.
SHARE_TOL = 1e-8
#: Dependent active rows: the tangent's rows must stay consistent, their change in theta
#: (along a fixed direction of the differentiated arrays) in the rows' range to this fraction.
CONSISTENT_TOL = 1e-8
#: Eigenvalues of the reduced Hessian (W on the null space of the active rows) below this
#: fraction of |W| make it singular or indefinite (NaN tangents).
CURVATURE_TOL = 1e-10
#: Path rows at one grid point apart whose values and Jacobians agree to this relative
#: tolerance are one constraint counted twice (`_knot_duplicates`).
DUPLICATE_TOL = 1e-10


def restricted_values(problem, control, a, simulator):
    """The restricted problem's values at `a` as a pure function of everything (no
    derivatives taken inside, so that JAX can differentiate them in `a` and in the
    problem's arrays): a dict with `tf`, `G`, `E`, `rows` (the inequality rows <= 0 in the
    order of `_kkt.inequality_rows` after `_kkt.with_knot_gaps`: path points, terminal
    inequalities, bound rows, knot gaps; shape (0,) without), `D` (or None) and `path`
    (`(t, C)` on the grid, or None)."""
    if problem.path is None:
        xf, _ = final_state(problem, control, a, simulator)
        path = None
    else:
        xf, (t, C, _) = path_values(problem, control, a, simulator)
        path = (t, C)
    tf = control.tf(a)
    D = None
    if problem.terminal_inequality is not None:
        D = problem.terminal_inequality(tf, xf, problem.args)
    parts = [path[1].reshape(-1)] if path is not None else []
    parts += [D] if D is not None else []
    gaps = knot_gap_rows(control, a)
    parts += [r for r in (bound_values(problem, control, a), None if gaps is None else gaps[0]) if r is not None]
    return {
        "tf": tf,
        "G": problem.objective(tf, xf, problem.args),
        "E": problem.terminal(tf, xf, problem.args),
        "rows": jnp.concatenate(parts) if parts else jnp.zeros(0, a.dtype),
        "D": D,
        "path": path,
    }


def bound_values(problem, control, a):
    """The values of `_bounds.bound_rows` (None without rows) with the control bounds read
    from the problem's arrays `control_lower` / `control_upper` instead of its static copy
    of them (the same numbers), so that they have derivatives: each row is +-(a_i - bound)
    with i and the sign from its Jacobian (a row of +-I), the bound of the channel of
    entry i (`control.value_indices`); a row on a free initial state keeps its static bound."""
    rows = bound_rows(problem, control, a)
    if rows is None:
        return None
    V, V_a = rows
    idx, channel = control.value_indices
    if not len(idx):
        return V
    of = np.full(a.shape[0], -1)
    of[np.asarray(idx, int)] = np.asarray(channel, int)
    entry = jnp.argmax(jnp.abs(V_a), axis=1)
    sign = V_a[jnp.arange(V.shape[0]), entry]
    ch = jnp.asarray(of)[entry]
    nu = problem.num_controls
    lo = jnp.full(nu, -jnp.inf) if problem.control_lower is None else problem.control_lower
    hi = jnp.full(nu, jnp.inf) if problem.control_upper is None else problem.control_upper
    at = jnp.maximum(ch, 0)
    return jnp.where(ch >= 0, sign * (a[entry] - jnp.where(sign > 0, hi[at], lo[at])), V)


def solution_values(problem, control, a, simulator):
    """The float fields of a `Solution` that are functions of (a, theta), by field name
    (`Solution.from_evaluation`'s formulas); the others have zero tangents."""
    v = restricted_values(problem, control, a, simulator)
    out = {
        "params": a,
        "tf": v["tf"],
        "objective": v["G"],
        "constraints": v["E"],
        "max_constraint_error": jnp.max(jnp.abs(v["E"]), initial=0.0),
        "max_violation": jnp.maximum(jnp.max(jnp.abs(v["E"]), initial=0.0), jnp.max(v["rows"], initial=0.0)),
    }
    if v["D"] is not None:
        out["terminal_inequality"] = v["D"]
    if v["path"] is not None:
        t, C = v["path"]
        worst = jnp.max(C, axis=1)
        out["max_path_constraint"] = jnp.max(worst)
        out["max_path_time"] = t[jnp.argmax(worst)]
    return out


def _first_order(problem, control, a, simulator):
    """`(G_a, E, H, rows, J)`: the objective's gradient, the equalities and the inequality
    rows with their Jacobians in `a` (forward mode: works with every simulator)."""

    def values(a):
        v = restricted_values(problem, control, a, simulator)
        return (v["G"], v["E"], v["rows"]), (v["E"], v["rows"])

    (G_a, H, J), (E, rows) = jax.jacfwd(values, has_aux=True)(a)
    return G_a, E, H, rows, J


def _num_path_rows(problem, control, simulator):
    """How many of the inequality rows are path points (`path_values`' grid x the path
    constraints; they come first)."""
    if problem.path is None:
        return 0
    return control.num_segments * len(simulator.dense_grid()) * len(problem.path_names)


def _knot_duplicates(problem, control, simulator, rows, J, active):
    """Active path rows that repeat the active row one grid point earlier (a knot is the
    end of one segment and the start of the next, `path_values`): the same constraint at
    the same point (the same value and Jacobian, to round-off, where the control is
    continuous or the constraint does not see it). They keep their multipliers in the
    Lagrangian but count once in the active set, whose rows must be independent."""
    if problem.path is None:
        return jnp.zeros(rows.shape[0], bool)
    q, num = len(problem.path_names), _num_path_rows(problem, control, simulator)
    same = jnp.linalg.norm(J[q:num] - J[: num - q], axis=1) <= DUPLICATE_TOL * jnp.linalg.norm(J[: num - q], axis=1)
    same = same & (jnp.abs(rows[q:num] - rows[: num - q]) <= DUPLICATE_TOL * (1.0 + jnp.abs(rows[: num - q])))
    same = same & active[q:num] & active[: num - q]
    return jnp.concatenate([jnp.zeros(q, bool), same, jnp.zeros(rows.shape[0] - num, bool)])


def _gap_curvature(control, a, nu_gaps):
    """nu^T d^2(knot gaps)/da^2 (zero for the built-in families, whose knots are affine)."""
    if nu_gaps.shape[0] == 0:
        return 0.0
    # (rows exist: `nu_gaps` has one multiplier per row, and is not empty)
    return jax.hessian(lambda a: nu_gaps @ knot_gap_rows(control, a)[0])(a)  # pyright: ignore[reportOptionalSubscript]


class KKTPoint(eqx.Module):
    """The KKT system at a solution (`kkt_point`), which `kkt_tangents` solves.

    - `multipliers`: [lambda; nu], of the terminal equalities and of the inequality rows
      (`restricted_values`' order), least squares with nu >= 0; nu = 0 off the active set.
    - `active`: per inequality row, whether it is in the active set A (within the activity
      tolerance of its bound, and its multiplier holds the point).
    - `weakly_active`: per inequality row, within the activity tolerance but left out of A
      (its multiplier about zero, `WEAK_TOL`): where the solution map may have a kink, and
      the derivative is the one-sided one that lets the row go.
    - `independent`: the active rows are independent (`RANK_TOL`); where they are not, the
      multipliers' tangents are NaN and the others need the rows to stay consistent in
      theta (`kkt_tangents`).
    - `curved`: the reduced Hessian is positive definite (`CURVATURE_TOL`).
    - `differentiable`: SUCCESS, `curved`, finite values and, for dependent rows, W on their
      null space the same for another sharing of their multipliers (`SHARE_TOL`): the
      derivatives are numbers, not NaN (but for the consistency along theta).

    The rest is the factorization: `W` the Hessian of the Lagrangian; `rows_on` the rows of
    A (equalities first) and `row_scale` their norms; `Vt`, `s`, `rank` the SVD of the
    unit-scaled rows of A (padded to n rows).
    """

    multipliers: jax.Array
    active: jax.Array
    weakly_active: jax.Array
    independent: jax.Array
    curved: jax.Array
    differentiable: jax.Array
    W: jax.Array
    rows_on: jax.Array
    row_scale: jax.Array
    Vt: jax.Array
    s: jax.Array
    rank: jax.Array


def _kkt_point(problem, control, simulator, a, status, first, active_tol) -> KKTPoint:
    """The `KKTPoint` at `a` (a solve's result of `status`) from `_first_order`'s `first`."""
    G_a, E, H, rows, J = first
    n, m, r = a.shape[0], E.shape[0], rows.shape[0]
    # multipliers and the active set: least squares with nu >= 0 on the near-active rows
    # (in the solver's scaled parameters), then only the rows that hold the point
    keep = rows >= -active_tol
    if m + r:
        D = parameter_scale(a)
        _, lam = signed_multipliers(G_a * D, H * D[None], J * D[None], keep)
    else:
        lam = jnp.zeros(0, a.dtype)
    Jall = jnp.concatenate([H, J])
    norms = jnp.linalg.norm(Jall, axis=1)
    active = keep & ~weak_rows(G_a, H, J, rows, lam, active_tol)
    lam = lam.at[m:].set(jnp.where(active, lam[m:], 0.0))
    if m + r:
        lam = _with_smooth_tangent(lam, G_a, Jall, jnp.concatenate([jnp.ones(m, bool), active]), parameter_scale(a))
    on = jnp.concatenate([jnp.ones(m, bool), active & ~_knot_duplicates(problem, control, simulator, rows, J, active)])

    # W: the exact Hessian of the Lagrangian with the active multipliers (`lagrangian_hessian`
    # takes the rows without the knot gaps, whose curvature is added here)
    gaps = knot_gap_rows(control, a)
    num_gaps = 0 if gaps is None else gaps[0].shape[0]
    # the active rows scaled to unit norm, their rank and null space
    safe = jnp.where(on & (norms > 0), norms, 1.0)
    Js = jnp.where(on[:, None], Jall / safe[:, None], 0.0)
    _, s, Vt = jnp.linalg.svd(jnp.concatenate([Js, jnp.zeros((n, n), a.dtype)]), full_matrices=False)
    rank = jnp.sum(s > RANK_TOL * jnp.maximum(s[0], 1e-300))
    independent = (rank == jnp.sum(on)) & jnp.all(~on | (norms > 0))
    z = jnp.arange(n) >= rank

    # Dependent active rows (a boundary arc: the path rows of its grid points outnumber the
    # parameters that move it) leave the multipliers free along the rows' left null space, and
    # W with them. The tangent is still unique where W on the rows' null space does not depend
    # on that freedom (rows linear in a, as a state bound of linear dynamics): W at lam and at
    # lam + nu (nu a fixed combination of the left null space, as large as lam) must agree
    # there to `SHARE_TOL` x |W|; else the derivative depends on which multiplier the
    # perturbation selects, and is NaN. (One Hessian of the Lagrangian for both, vmapped.)
    inv_s2 = jnp.where(~z, 1.0 / jnp.where(~z, s**2, 1.0), 0.0)
    w = jnp.where(on, 1.0 + 0.5 * jnp.sin(jnp.arange(m + r, dtype=a.dtype)), 0.0)
    left_null = jnp.where(on, w - Js @ (Vt.T @ (inv_s2 * (Vt @ (Js.T @ w)))), 0.0) / safe
    size = jnp.linalg.norm(jnp.where(on, lam, 0.0)) / jnp.maximum(jnp.linalg.norm(left_null), 1e-300)
    shared = jax.lax.stop_gradient(lam + size * left_null)

    def hessian(lam):
        W = lagrangian_hessian(problem, control, a, simulator, lam[: m + r - num_gaps])
        return W + _gap_curvature(control, a, lam[m + r - num_gaps :])

    W, W_shared = jax.vmap(hessian)(jnp.stack([lam, shared]))
    scale = jnp.maximum(jnp.linalg.norm(W), 1e-300)
    on_null = z[:, None] & z[None, :]
    unique = independent | (jnp.linalg.norm(jnp.where(on_null, Vt @ (W_shared - W) @ Vt.T, 0.0)) <= SHARE_TOL * scale)
    Mz = jnp.where(on_null, Vt @ W @ Vt.T, scale * jnp.eye(n, dtype=a.dtype))
    curved = jnp.min(jnp.linalg.eigvalsh(Mz)) > CURVATURE_TOL * scale
    finite = jnp.all(jnp.isfinite(W)) & jnp.all(jnp.isfinite(Jall)) & jnp.all(jnp.isfinite(G_a))
    return KKTPoint(
        multipliers=lam,
        active=active,
        weakly_active=keep & ~active,
        independent=independent,
        curved=curved,
        differentiable=(status == Status.SUCCESS) & unique & curved & finite,
        W=W,
        rows_on=on,
        row_scale=safe,
        Vt=Vt,
        s=s,
        rank=rank,
    )


@jax.custom_jvp
def _with_smooth_tangent(lam, G_a, Jall, held, D):
    """`lam` (the multipliers of the rows `held`, by `signed_multipliers`), with the tangent of
    the least-norm least-squares multipliers of those rows (in the parameters scaled by `D`)
    instead of its own: the same numbers at a KKT point, but `signed_multipliers`' solve (an
    SVD with zero columns) has an infinite derivative where two rows are out, and forward
    mode over the tangent computation (`jax.hessian`) met it in the Hessian of the
    Lagrangian. (Only a derivative of this pays the pseudo-inverse.)"""
    return lam


@_with_smooth_tangent.defjvp
def _with_smooth_tangent_jvp(primals, tangents):
    lam, G_a, Jall, held, D = primals
    _, dG_a, dJall, _, dD = tangents

    def smooth(G_a, Jall, D):
        A = jnp.where(held[:, None], Jall * D[None], 0.0)
        return jnp.where(held, -(jnp.linalg.pinv(A).T @ (G_a * D)), 0.0)

    return lam, jax.jvp(smooth, (G_a, Jall, D), (dG_a, dJall, dD))[1]


@jax.custom_jvp
def _pinv(J, Vt, inv_s2):
    """The pseudo-inverse of `J` from its SVD's `Vt` and 1/s^2 (zero past its rank), with
    Golub and Pereyra's derivative (at a constant rank, as `jnp.linalg.pinv`'s) instead of
    the SVD's, which is infinite where singular values repeat (two zeros: most problems),
    so that forward mode over the tangent computation (`jax.hessian`) is no NaN."""
    return Vt.T @ (inv_s2[:, None] * (Vt @ J.T))


@_pinv.defjvp
def _pinv_jvp(primals, tangents):
    J, Vt, inv_s2 = primals
    dJ = tangents[0]
    p = _pinv(J, Vt, inv_s2)
    s = (p @ p.T) @ dJ.T
    t = (dJ.T @ p.T) @ p
    return p, -(p @ dJ) @ p + s - (s @ J) @ p + t - (p @ J) @ t


@eqx.filter_jit
def kkt_point(problem, control, sol, simulator=RK4(), active_tol=ACTIVE_TOL) -> KKTPoint:
    """The `KKTPoint` of a `Solution` of `jt.solve(problem, control, ..., simulator=...)`:
    the active set, weakly active rows and whether the derivatives are numbers there."""
    first = _first_order(problem, control, sol.params, simulator)
    return _kkt_point(problem, control, simulator, sol.params, sol.status, first, active_tol)


def _jvp(fn, primals, tangents, explicit):
    """`jax.jvp(fn, primals, tangents)`, or with `explicit` by the Jacobian (`jax.jacfwd` in
    the flattened primals) times the tangents: the same numbers, but a matrix product that
    reverse mode can transpose where the jvp of `fn` cannot be (the while loops of an
    adaptive diffrax integration). Its cost grows with the number of primals."""
    if not explicit:
        return jax.jvp(fn, primals, tangents)
    flat, unravel = ravel_pytree(primals)
    jac, out = jax.jacfwd(lambda v: (fn(*unravel(v)),) * 2, has_aux=True)(flat)
    dflat, _ = ravel_pytree(tangents)
    return out, jax.tree.map(lambda J: J @ dflat, jac)


@eqx.filter_jit
def kkt_tangents(problem, control, simulator, sol, active_tol, dtheta, differentiated):
    """The tangents of the float fields of `sol` (a `Solution` of `problem`, `control`)
    along `dtheta` (tangents of the inexact arrays of `(problem, control)`, None elsewhere),
    by the implicit function theorem at `sol.params` (module docs); linear in `dtheta`.
    `active_tol`: inequality rows with values >= -`active_tol` may be active.
    `differentiated`: `dtheta`'s structure, True where its tangent may be nonzero."""
    theta, rest = eqx.partition((problem, control), eqx.is_inexact_array)
    a = sol.params

    def first_order(theta):
        p, c = eqx.combine(theta, rest)
        return _first_order(p, c, a, simulator)

    # the KKT conditions and their jvp in theta at a* (primal and linear parts together)
    explicit = not isinstance(simulator, RK4)
    first, (dG_a, dE, dH, drows, dJ) = _jvp(first_order, (theta,), (dtheta,), explicit)
    k = _kkt_point(problem, control, simulator, a, sol.status, first, active_tol)
    m = dE.shape[0]

    # right-hand sides: d/dtheta grad_a L and d/dtheta c_A (multipliers held)
    r1 = dG_a + dH.T @ k.multipliers[:m] + dJ.T @ k.multipliers[m:]
    r2 = jnp.where(k.rows_on, jnp.concatenate([dE, drows]) / k.row_scale, 0.0)

    # null-space solve of [[W, J_A^T], [J_A, 0]] [da; dlam] = -[r1; r2]: da = dy + dz, dy on
    # the active rows' range (the least-norm solution of J_A dy = -r2), dz on their null
    # space. By the pseudo-inverse (`_pinv`), whose derivative (forward mode over this: `jax.
    # hessian`) is finite where the SVD's is not.
    n = a.shape[0]
    Js = jnp.where(k.rows_on[:, None], jnp.concatenate([first[2], first[4]]) / k.row_scale[:, None], 0.0)
    y = jnp.arange(n) < k.rank
    Jp = _pinv(Js, k.Vt, jnp.where(y, 1.0 / jnp.where(y, k.s**2, 1.0), 0.0))
    null = jnp.eye(n, dtype=a.dtype) - Jp @ Js  # the projector onto the null space
    dy = -(Jp @ r2)
    dz = jnp.linalg.solve(null @ k.W @ null + (jnp.eye(n, dtype=a.dtype) - null), -(null @ (r1 + k.W @ dy)))
    # Dependent active rows: their change in theta must stay in the rows' range (the rows can
    # all stay active: a bound that moves as one along an arc), else some leave and the
    # tangent that keeps them all is none. Checked along a fixed direction of the arrays
    # differentiated here, not along `dtheta`: the tangent must stay linear in it.
    consistent = jax.lax.cond(
        k.independent,
        lambda: jnp.array(True),
        lambda: _consistent(simulator, a, theta, rest, differentiated, k, Js, Jp, explicit),
    )
    ok = k.differentiable & consistent
    nan_unless_ok = jnp.where(ok, 1.0, jnp.nan)  # a factor, not a select: it survives transposition
    da = (dy + dz) * nan_unless_ok

    def values(a, theta):
        p, c = eqx.combine(theta, rest)
        return solution_values(p, c, a, simulator)

    _, tangents = _jvp(values, (a, theta), (da, dtheta), explicit)
    # the multipliers' tangent from the first block row: J_A^T dlam_A = -(r1 + W da), least
    # squares in the unit-scaled rows, w = row_scale x dlam_A; zero off the active set
    w = -(Jp.T @ (r1 + k.W @ da))
    dlam = jnp.where(k.rows_on, w / k.row_scale, 0.0)
    dlam = dlam * jnp.where(k.independent, 1.0, jnp.nan)  # (dependent rows share them freely)
    tangents["multipliers"] = dlam[:m]
    if problem.terminal_inequality is not None:
        start = m + _num_path_rows(problem, control, simulator)
        tangents["terminal_inequality_multipliers"] = dlam[start : start + tangents["terminal_inequality"].shape[0]]
    return jax.tree.map(lambda t: t * nan_unless_ok, tangents)


def _consistent(simulator, a, theta, rest, differentiated, k, Js, Jp, explicit):
    """Whether the active rows' change in theta (the values' jvp at `a`, no Jacobian in a),
    along a fixed direction of the arrays that are differentiated (`differentiated`), lies in
    the range of their unit-scaled Jacobian `Js` (`Jp` its pseudo-inverse) to `CONSISTENT_TOL`."""
    direction = jax.tree.map(
        lambda x, on: jnp.cos(jnp.arange(x.size, dtype=x.dtype).reshape(x.shape) + 1.0) * float(on),
        theta,
        differentiated,
    )
    a = jax.lax.stop_gradient(a)

    def values(theta):
        p, c = eqx.combine(theta, rest)
        v = restricted_values(p, c, a, simulator)
        return jnp.concatenate([v["E"], v["rows"]])

    _, dvalues = _jvp(values, (jax.lax.stop_gradient(theta),), (jax.lax.stop_gradient(direction),), explicit)
    change = jnp.where(k.rows_on, dvalues / k.row_scale, 0.0)
    outside = change - Js @ (Jp @ change)
    return jnp.linalg.norm(outside) <= CONSISTENT_TOL * jnp.maximum(jnp.linalg.norm(change), 1e-300)


def _zero_tangent(x):
    x = jnp.asarray(x) if not isinstance(x, np.ndarray) else x
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(np.shape(x), dtype=jax.dtypes.float0)


def differentiable_solve(run, problem, control, a0, simulator, active_tol):
    """`run(problem, control, a0)` (a solve returning a `Solution`, everything else closed
    over) as a function that `jax.jvp`, `jax.grad`, `jax.jacfwd`/`jacrev` and `jax.vmap`
    differentiate by the implicit function theorem (`kkt_tangents`, `simulator` the solve's)
    with respect to the inexact arrays of `problem` and `control`; `a0`'s tangent is
    dropped. Without differentiation it is `run` itself: a `custom_jvp` evaluates its
    function as it is, so an ordinary solve is unchanged."""
    arrays, static = eqx.partition((problem, control), eqx.is_array)

    @jax.custom_jvp
    def solve(arrays, a0):
        return run(*eqx.combine(arrays, static), a0)

    def solve_jvp(primals, tangents):
        arrays, (dtheta, differentiated) = _floats_as_arrays(primals[0]), _dense(tangents[0], primals[0])
        a0 = primals[1]
        sol = solve(arrays, a0)  # itself: a second derivative meets this rule again
        p, c = eqx.combine(arrays, static)
        dtheta = _theta_tangents(p, c, static, dtheta)
        computed = kkt_tangents(p, c, simulator, sol, active_tol, dtheta, _theta_tangents(p, c, static, differentiated))
        return sol, _solution_tangent(sol, computed)

    solve.defjvp(solve_jvp, symbolic_zeros=True)

    return solve(arrays, a0)


def _floats_as_arrays(tree):
    """`tree` with its Python floats as arrays. A weakly typed input of the user's `jax.jvp` /
    `jax.grad` (`jax.grad(f)(2.0)`) reaches a `custom_jvp` rule as a Python float, primal and
    tangent; as a float it is no inexact array of the problem, and `args=k` had the
    derivative 0."""
    return jax.tree.map(lambda x: jnp.asarray(x) if isinstance(x, float) else x, tree)


def _dense(tangents, primals):
    """`(tangents, differentiated)`: the tangents of a `custom_jvp` rule with symbolic zeros,
    as arrays (`_floats_as_arrays`; zeros for a symbolic zero), and per leaf whether it is
    differentiated (not a symbolic zero)."""
    is_zero = lambda t: isinstance(t, SymbolicZero)
    dense = jax.tree.map(
        lambda t, p: jnp.zeros(jnp.shape(p), jnp.result_type(p)) if is_zero(t) else t,
        tangents,
        primals,
        is_leaf=is_zero,
    )
    return _floats_as_arrays(dense), jax.tree.map(lambda t: not is_zero(t), tangents, is_leaf=is_zero)


def _theta_tangents(problem, control, static, tangents):
    """The tangents of the arrays of `(problem, control)` as `kkt_tangents`' `dtheta`: those
    of the inexact arrays, None elsewhere (or any tree of those leaves: `_dense`'s flags)."""
    mask = jax.tree.map(eqx.is_inexact_array, (problem, control))
    return eqx.filter(eqx.combine(tangents, static), mask)


def _solution_tangent(sol, computed):
    """The tangent of `sol` (a `Solution`, or a batch of them): `computed` (`kkt_tangents`'
    fields, by name) where the field is present, zero elsewhere."""
    names = [k for k in computed if getattr(sol, k) is not None]
    zeros = jax.tree.map(_zero_tangent, sol)
    return eqx.tree_at(lambda s: [getattr(s, k) for k in names], zeros, [computed[k] for k in names])


#: Why `jt.solve_batch` refuses a traced problem or control.
OUTSIDE_JIT = (
    "solve_batch runs outside jax.jit and jax.vmap (its problem and control must be "
    "concrete; they may be differentiated): inside them, vmap jt.solve."
)


def differentiable_batch(run, problem, control, simulator, active_tol):
    """`run(problem, control)` (a batch of solves returning a `Solution` with a leading
    start axis, e.g. `jt.solve_batch`'s driver with its starts closed over; host code that
    needs concrete arrays) as a function that `jax.grad`, `jax.jvp` and `jax.jacfwd` /
    `jax.jacrev` differentiate with respect to the inexact arrays of `problem` and
    `control`, shared by all the starts: the tangent is `jax.vmap` over the starts of
    `kkt_tangents` (each at its own solution and active set; NaN for a start that did not
    end SUCCESS), the problem's tangent shared. Not under `jax.jit` or `jax.vmap` (`run`
    is not traceable); without differentiation it is `run` itself."""
    arrays, static = eqx.partition((problem, control), eqx.is_array)

    @jax.custom_jvp
    def solve(arrays):
        # a derivative calls this with concrete arrays (the rule below); `jit` or `vmap` would not
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(arrays)):
            raise ValueError(OUTSIDE_JIT)
        return run(*eqx.combine(arrays, static))

    def solve_jvp(primals, tangents):
        arrays, (darrays, differentiated) = _floats_as_arrays(primals[0]), _dense(tangents[0], primals[0])
        sols = solve(arrays)
        p, c = eqx.combine(arrays, static)
        dtheta = _theta_tangents(p, c, static, darrays)
        mask = _theta_tangents(p, c, static, differentiated)
        computed = jax.vmap(lambda sol: kkt_tangents(p, c, simulator, sol, active_tol, dtheta, mask))(sols)
        return sols, _solution_tangent(sols, computed)

    solve.defjvp(solve_jvp, symbolic_zeros=True)

    return solve(arrays)
