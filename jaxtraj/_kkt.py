"""KKT algebra of the restricted problem, shared by every solver: the constraint rows of an
`Evaluation` (terminal and path), the active ones, least-squares multipliers, the gradient of
the Lagrangian, the projected gradient and the SQP termination rule."""

import jax.numpy as jnp


def path_rows(ev):
    """The path constraints of an `Evaluation` flattened to rows, `(C (N q,), C_a (N q, np))`,
    or None for a problem without them."""
    if ev.C is None:
        return None
    return ev.C.reshape(-1), ev.C_a.reshape(ev.C.size, -1)


def constraint_rows(ev):
    """[H; C_a]: the Jacobian of all constraints, terminal and path (flattened)."""
    rows = path_rows(ev)
    return ev.H if rows is None else jnp.concatenate([ev.H, rows[1]])


def active_rows(ev, tol):
    """[H; C_a of the path points with C >= -tol] (inactive rows zeroed): the constraints
    that the projected gradient of a KKT point has to be orthogonal to."""
    rows = path_rows(ev)
    if rows is None:
        return ev.H
    C, C_a = rows
    return jnp.concatenate([ev.H, jnp.where((C >= -tol)[:, None], C_a, 0.0)])


def multipliers(rows, g):
    """The multipliers lambda that minimize |g + rows^T lambda| (least squares, robust to
    dependent rows): every solver's multiplier estimate is this one solve."""
    return jnp.linalg.lstsq(rows.T, -g)[0]


def least_squares_multipliers(ev, path_active):
    """Least-squares multipliers of E and of the path points with C >= -`path_active`
    ([H; C_a]^T lambda ~ -G_a), the path ones clipped at 0 (zero elsewhere): started at a
    converged point, the first active set is the touching one."""
    lam = multipliers(active_rows(ev, path_active), ev.G_a)
    m = ev.E.shape[0]
    return lam if lam.shape[0] == m else lam.at[m:].set(jnp.maximum(lam[m:], 0.0))


def lagrangian_gradient(ev, lam):
    """Gradient of the Lagrangian G + lambda^T [E; C] (terminal and path rows)."""
    return ev.G_a + constraint_rows(ev).T @ lam


def kkt_outcome(feasible, pg, G, gtol, acceptable_gtol, no_progress):
    """`(converged, stalled)` of an SQP iteration: converged when `feasible` and the projected
    gradient `pg` <= `gtol` (1 + |G|), or, once `no_progress` (round-off leaves no measurable
    progress), <= `acceptable_gtol` (1 + |G|); stalled when progress ended short of that. The
    second level keeps the outcome off the knife edge where the projected gradient's
    round-off floor (set by the sensitivities) meets `gtol`."""
    scale = 1.0 + jnp.abs(G)
    converged = feasible & ((pg <= gtol * scale) | (no_progress & (pg <= acceptable_gtol * scale)))
    return converged, ~converged & no_progress


def projected_gradient(G_a, H):
    """|V G_a|, V = I - H^T (H H^T)^-1 H [3.62] (least squares, robust to dependent rows)."""
    return jnp.linalg.norm(G_a + H.T @ multipliers(H, G_a))
