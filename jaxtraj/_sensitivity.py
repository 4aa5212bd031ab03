"""State sensitivities dx(tf)/da and the restricted-problem evaluation (G, G_a, E, H).

Three independent ways to get dx(tf)/da:

* `"forward"`: forward-mode autodiff (`jax.jacfwd`) through the rescaled-time simulation;
  exact derivative of the discrete map.
* `"unit"`: the unit-solution method of seed 000 appendix A, written from the equations,
  not from autodiff of the integrator: in physical time, the columns p_j = dx/da_j obey
  p_j' = A p_j + B du/da_j [A.25-A.26] (A = df/dx, B = df/du on the nominal trajectory,
  du/da_j the partial derivative at fixed t, zero where the control saturates),
  jump by [f(t_q-) - f(t_q+)] dt_q/da_j at every knot t_q [A.27-A.29], and the final
  sensitivity adds f(tf) dtf/da_j. It is integrated with the same simulator and the same
  step sequence as the state. With RK4 it differs from `"forward"` only by how the step
  size's dependence on the knots is differentiated, an O(h^4) effect (~1e-10 relative at
  100 steps per segment on Earth-Mars).
* `"fd"`: central finite differences of the simulation, step cbrt(eps) max(1, |a_j|).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from ._bounds import bound_rows
from ._checks import check_inputs
from ._kkt import lagrangian_gradient
from ._problem import Problem
from ._simulate import (
    RK4,
    AbstractSimulator,
    check_simulator,
    final_state,
    initial_state,
    integrate_segments,
    rescaled_field,
    segment_data,
    simulation_status,
)
from ._status import Status
from .controls import AbstractControl
from .controls._base import run_concretely

METHODS = ("forward", "unit", "fd")


def _initial(problem, control, a):
    """x(0) and dx(0)/da (zero unless initial-state components are parameters)."""
    return initial_state(problem, control, a), jax.jacfwd(lambda a: initial_state(problem, control, a))(a)


def forward_jacobian(problem, control, a, simulator):
    """Forward-mode autodiff, chained segment by segment (and, for RK4, step by step):
    x_a <- dx1/dx x_a + dx1/dtheta_k theta_k_a with theta_k = row k of `segment_data` and
    theta_a = dtheta/da computed once. Equal to `jax.jacfwd` of the whole simulation to
    round-off (tested); see `AbstractSimulator.integrate_linearized` and
    benchmarks/RESULTS.md for why it is written this way.

    When `segment_data` is affine in a (`control.affine`: every family of `jt.controls`), theta_k only moves in
    the fixed column space of theta_k_a = U_k C_k, so each step is differentiated along the r
    columns of U_k instead of all of theta_k: on Earth-Mars cases 4 and 5 (rows [u_k, u_k+1,
    t_k, h_k] with t_k, h_k both proportional to tf) that is n + 3 tangents instead of n + 4."""
    data = segment_data(control, a)
    data_a = jax.jacfwd(segment_data, argnums=1)(control, a)  # (K, m + 2, np)
    field = rescaled_field(problem, control)
    x0, x0_a = _initial(problem, control, a)
    basis = affine_segment_basis(control, a)
    if basis is None:
        segments = (data, data_a)

        def linearized(x, x_a, theta, theta_a):  # pyright: ignore[reportRedeclaration]  (one per branch)
            return simulator.integrate_linearized(field, theta, theta_a, x, x_a)
    else:
        segments = (data, basis, jnp.einsum("kir,kip->krp", basis, data_a))
        w0 = jnp.zeros(basis.shape[-1], a.dtype)

        def linearized(x, x_a, theta, u, c):
            def reduced(w, tau, y):  # theta + u @ w, as a multiply-sum (see `_chain`)
                return field(theta + jnp.sum(u * w[None, :], axis=1), tau, y)

            return simulator.integrate_linearized(reduced, w0, c, x, x_a)

    def body(carry, segment):
        x1, x1_a, ok = linearized(*carry, *segment)
        return (x1, x1_a), ok

    init = (x0, x0_a)
    (xf, jac), oks = lax.scan(body, init, segments)
    return xf, jac, simulation_status(jnp.all(oks), xf, jac)


_segment_jacobian = jax.jacfwd(segment_data, argnums=1)


def affine_segment_basis(control, a):
    """Orthonormal bases U_k (K, m + 2, r) of the column spaces of dtheta_k/da for a family
    that declares `segment_data` affine in a (`control.affine`), else None. The Jacobian of
    an affine map is the same everywhere, so it is taken at a fixed point at trace time; r is
    the largest rank over the segments, smaller ranks padded with zero columns."""
    if not control.affine:
        return None
    point = np.random.default_rng(0).uniform(0.5, 2.0, a.shape)
    try:
        jac = run_concretely(_segment_jacobian, control, point)
    except jax.errors.JAXTypeError:  # segment_data depends on traced arrays of the control
        return None
    bases = []
    for jk in jac:
        u, s, _ = np.linalg.svd(jk, full_matrices=False)
        bases.append(u[:, : int(np.sum(s > 1e-12 * max(s[0], 1e-300)))])
    r = max(b.shape[1] for b in bases)
    if r >= jac.shape[1]:
        return None
    return jnp.asarray(np.stack([np.pad(b, ((0, 0), (0, r - b.shape[1]))) for b in bases]), a.dtype)


def segment_hessian(problem, control, a, simulator, terminal, basis):
    """The Hessian in `a` of `terminal(tf, x(tf))` (a scalar, e.g. the Lagrangian's terminal
    part G + lambda^T [E; D]) by segments: the discrete second-order adjoint of the chain
    x_(k+1) = Phi_k(x_k, theta_k) with theta_k = row k of `segment_data`, affine in `a` with
    the column bases `basis` (`affine_segment_basis`, not None), so that
    W = Z^T (d^2 terminal) Z + sum_k Y_k^T d^2(p_(k+1) . Phi_k) Y_k, where Y_k = d(x_k, w_k)/da
    (w_k: theta_k's coordinates in its basis), Z = d(tf, x(tf))/da and p_(k+1) the costate
    after segment k. One forward pass chains the segments' Jacobians (n + r tangents, n states,
    r basis columns: the sensitivities Y_k), one backward pass gives the costates, then every
    segment's local Hessian (forward over reverse in n + r variables) is taken at once under
    `vmap`. The same numbers as forward over reverse autodiff of the whole simulation (tested
    to 1e-12), with n + r tangents instead of one per parameter: on hypersensitive (41
    parameters, 40 segments) 4.6x faster, on Earth-Mars case 4 (7 parameters) 0.85x
    (benchmarks/RESULTS.md; `lagrangian_hessian` chooses)."""
    data = segment_data(control, a)
    coords = jnp.einsum("kir,kip->krp", basis, _segment_jacobian(control, a))  # dw_k/da
    field = rescaled_field(problem, control)
    x0, x0_a = _initial(problem, control, a)
    n, r = x0.shape[0], basis.shape[-1]

    def flow(z, theta, u):  # Phi_k at (x, w) = z; theta + u @ w as a multiply-sum (see `_chain`)
        th = theta + jnp.sum(u * z[n:][None, :], axis=1)
        return simulator.integrate(lambda tau, y: field(th, tau, y), z[:n], False)[0]

    def start(x):
        return jnp.concatenate([x, jnp.zeros(r, a.dtype)])

    def forward(carry, segment):
        x, x_a = carry
        theta, u, w_a = segment
        J, x1 = jax.jacfwd(lambda z: (flow(z, theta, u),) * 2, has_aux=True)(start(x))
        Y = jnp.concatenate([x_a, w_a])
        return (x1, J @ Y), (x, Y, J[:, :n])

    (xf, xf_a), (xs, Ys, Jx) = lax.scan(forward, (x0, x0_a), (data, basis, coords))
    tf, tf_a = control.tf(a), jax.grad(control.tf)(a)
    end = jnp.concatenate([tf[None], xf])
    Z = jnp.concatenate([tf_a[None], xf_a])
    value = lambda z: terminal(z[0], z[1:])
    grad_end, hess_end = jax.grad(value)(end), jax.hessian(value)(end)

    def backward(p, J):
        return J.T @ p, p

    _, ps = lax.scan(backward, grad_end[1:], Jx, reverse=True)  # ps[k]: the costate after segment k

    def local(x, theta, u, p):
        return jax.jacfwd(jax.grad(lambda z: p @ flow(z, theta, u)))(start(x))

    T = jax.vmap(local)(xs, data, basis, ps)
    return Z.T @ hess_end @ Z + jnp.einsum("kap,kab,kbq->pq", Ys, T, Ys)


def unit_jacobian(problem, control, a, simulator):
    data = segment_data(control, a)  # rows theta_k = [shape coefficients, t_k, h_k]
    data_a = jax.jacfwd(segment_data, argnums=1)(control, a)
    dknots = jax.jacfwd(control.knots)(a)  # (K + 1, np): dt_q/da
    K = control.num_segments

    def f(t, x, u):
        return problem.dynamics(t, x, u, problem.args)

    dfdx = jax.jacfwd(f, argnums=1)
    dfdu = jax.jacfwd(f, argnums=2)

    def u_at_time(theta, t):
        # The segment's formula at fixed physical t; its theta-derivative is the partial du/da
        # at fixed t (zero where the control saturates).
        return control.local_control(theta[:-2], theta[-1], (t - theta[-2]) / theta[-1])

    du_dtheta = jax.jacfwd(u_at_time)

    def field(segment, tau, y):
        theta, theta_a = segment
        x, p = y
        h = theta[-1]
        t = theta[-2] + h * tau
        u = control.local_control(theta[:-2], h, tau)
        du_da = du_dtheta(theta, t) @ theta_a  # (nu, np)
        dp = dfdx(t, x, u) @ p + dfdu(t, x, u) @ du_da  # [A.25-A.26]
        return h * f(t, x, u), h * dp

    def jump(k, segment, y):
        # [A.27-A.29]: p(t_q+) = p(t_q-) + [f(t_q-) - f(t_q+)] dt_q/da at the start of segment k > 0.
        theta, _ = segment
        x, p = y
        prev = data[jnp.maximum(k - 1, 0)]
        u_minus = control.local_control(prev[:-2], prev[-1], 1.0)
        u_plus = control.local_control(theta[:-2], theta[-1], 0.0)
        df = f(theta[-2], x, u_minus) - f(theta[-2], x, u_plus)
        return x, p + jnp.where(k > 0, jnp.outer(df, dknots[k]), 0.0)

    y0 = _initial(problem, control, a)
    (xf, p), _, ok = integrate_segments(simulator, field, (data, data_a), y0, jump=jump)
    last = data[K - 1]
    f_end = f(last[-2] + last[-1], xf, control.local_control(last[:-2], last[-1], 1.0))
    jac = p + jnp.outer(f_end, dknots[-1])  # the f(tf) dtf/da term
    return xf, jac, simulation_status(ok, xf, jac)


def fd_jacobian(problem, control, a, simulator):
    eps = jnp.finfo(a.dtype).eps ** (1.0 / 3.0) * jnp.maximum(1.0, jnp.abs(a))
    steps = jnp.diag(eps)
    run = jax.vmap(lambda aa: final_state(problem, control, aa, simulator))
    xp, sp = run(a[None, :] + steps)
    xm, sm = run(a[None, :] - steps)
    jac = ((xp - xm) / (2.0 * eps[:, None])).T
    xf, status = final_state(problem, control, a, simulator)
    ok = jnp.all(sp == Status.SUCCESS) & jnp.all(sm == Status.SUCCESS)
    return xf, jac, Status.where(ok, status, Status.NONFINITE)


_JACOBIANS = {"forward": forward_jacobian, "unit": unit_jacobian, "fd": fd_jacobian}


def check_method(method):
    if method not in METHODS:
        raise ValueError(f"`method` must be one of {METHODS}; got {method!r}.")


@eqx.filter_jit
def _sensitivities(problem, control, a, simulator, method):
    return _JACOBIANS[method](problem, control, a, simulator)


def sensitivities(
    problem: Problem,
    control: AbstractControl,
    a,
    method: str = "forward",
    *,
    simulator: AbstractSimulator = RK4(),
):
    """Final state x(tf) and its sensitivities dx(tf)/da.

    **Arguments:**

    - `problem`, `control`, `a`: as in `jt.simulate`.
    - `method`: `"forward"` (autodiff), `"unit"` (unit-solution / variational equations of
      seed 000 appendix A) or `"fd"` (central differences).
    - `simulator`: keyword-only, default `jt.RK4(100)`.

    **Returns:** `(xf, dxf_da)` with shapes `(n,)` and `(n, num_params)`. Use
    `jt.evaluate` for the status and the constraint/objective derivatives.
    """
    check_method(method)
    a = check_inputs(problem, control, a)
    check_simulator(simulator)
    xf, jac, _ = _sensitivities(problem, control, a, simulator, method)
    return xf, jac


class Evaluation(eqx.Module):
    """The restricted problem at one parameter vector (ALGORITHM.md sec. 1):
    objective G and gradient G_a, constraints E = M(tf, x(tf)) and Jacobian H = dE/da, and
    for problems with path constraints their values C (N, q) at the N points of the
    integration grid (times `path_t`) with C_a = dC/da (N, q, np), for problems with
    terminal inequalities D = D(tf, x(tf)) (r,) with D_a = dD/da (r, np), for declared control
    bounds that need them the parameter rows V <= 0 with V_a (`_bounds.py`); None otherwise."""

    # (shapes of one evaluation: n states, p parameters, m equalities, N grid points, q path
    # rows, r terminal inequalities, v bound rows; a batch adds leading axes)
    xf: Float[Array, " n"]
    xf_a: Float[Array, "n p"]
    tf: Float[Array, ""]
    G: Float[Array, ""]
    G_a: Float[Array, " p"]
    E: Float[Array, " m"]
    H: Float[Array, "m p"]
    status: Status
    C: Float[Array, "N q"] | None = None
    C_a: Float[Array, "N q p"] | None = None
    path_t: Float[Array, " N"] | None = None
    D: Float[Array, " r"] | None = None
    D_a: Float[Array, "r p"] | None = None
    V: Float[Array, " v"] | None = None
    V_a: Float[Array, "v p"] | None = None


def path_values(problem, control, a, simulator):
    """`(xf, (t, C))`: the final state and the path constraints C(t, x, u) <= 0 at every point
    of the integration grid, segment after segment (`Trajectory` order: a knot appears as
    the end of one segment and the start of the next, with the control of each side)."""
    field = rescaled_field(problem, control)
    xf, xs, ok = integrate_segments(
        simulator, field, segment_data(control, a), initial_state(problem, control, a), dense=True
    )
    knots = control.knots(a)
    grid = jnp.asarray(simulator.dense_grid())
    K, S = knots.shape[0] - 1, grid.shape[0]
    t = knots[:-1, None] + (knots[1:] - knots[:-1])[:, None] * grid[None, :]
    ks = jnp.broadcast_to(jnp.arange(K)[:, None], (K, S)).reshape(-1)
    taus = jnp.broadcast_to(grid[None, :], (K, S)).reshape(-1)
    u = jax.vmap(lambda k, tau: control.segment_control(a, k, tau))(ks, taus)
    C = jax.vmap(lambda ti, xi, ui: problem.path(ti, xi, ui, problem.args))(t.reshape(-1), xs.reshape(K * S, -1), u)
    return xf, (t.reshape(-1), C, ok)


def _path_jacobian(problem, control, a, simulator):
    """Forward-mode Jacobian of the final state and of the path constraints together (one
    integration with np tangents through the dense simulation)."""

    def run(a):
        xf, (t, C, ok) = path_values(problem, control, a, simulator)
        return (xf, C), (xf, t, C, ok)

    (xf_a, C_a), (xf, t, C, ok) = jax.jacfwd(run, has_aux=True)(a)
    return xf, xf_a, t, C, C_a, simulation_status(ok, xf, xf_a, C, C_a)


def evaluate_restricted(problem, control, a, simulator, method="forward") -> Evaluation:
    """Pure (jit/vmap-able) evaluation; used by every solver."""
    path = {}
    if problem.path is None:
        xf, xf_a, status = _JACOBIANS[method](problem, control, a, simulator)
    else:
        if method != "forward":
            raise ValueError(f"problems with path constraints need method='forward'; got {method!r}.")
        xf, xf_a, t, C, C_a, status = _path_jacobian(problem, control, a, simulator)
        path = {"C": C, "C_a": C_a, "path_t": t}
    tf = control.tf(a)
    tf_a = jax.grad(control.tf)(a)

    def chain(fn):
        value = fn(tf, xf, problem.args)
        d_tf, d_xf = jax.jacfwd(fn, argnums=(0, 1))(tf, xf, problem.args)
        return value, d_xf @ xf_a + jnp.multiply.outer(d_tf, tf_a)

    G, G_a = chain(problem.objective)
    E, H = chain(problem.terminal)
    if problem.terminal_inequality is not None:
        path["D"], path["D_a"] = chain(problem.terminal_inequality)
    rows = bound_rows(problem, control, a)
    if rows is not None:
        path["V"], path["V_a"] = rows
    # C and C_a were checked with the integration; the terminal inequalities are new here
    extra = [path[k] for k in ("D", "D_a") if k in path]
    status = Status.where(status == Status.SUCCESS, simulation_status(True, G, G_a, E, H, *extra), status)
    return Evaluation(xf=xf, xf_a=xf_a, tf=tf, G=G, G_a=G_a, E=E, H=H, status=status, **path)


def unevaluated(fn, *args):
    """Zeros shaped as `fn(*args)` (traced by `jax.eval_shape`: neither compiled nor
    integrated): the placeholder evaluation of a solver state whose first `step` evaluates
    the start, so that the compiled program holds each evaluation kernel once (issue 21)."""
    return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(fn, *args))


evaluate_jitted = eqx.filter_jit(evaluate_restricted)


#: `lagrangian_hessian` takes the Hessian by segments where the parameters are at least this
#: many times a segment's tangents: hypersensitive (41 parameters, 4 tangents) 3x faster per
#: solve, 0.15 s more compile; at ratios 2-3.2 (Goddard, Zermelo, brachistochrone, orbit
#: raising) the compile grew by 0.2-1.2 s for a warm gain of 0-12 ms (benchmarks/RESULTS.md)
SEGMENT_HESSIAN_RATIO = 4


def lagrangian_hessian(problem, control, a, simulator, lam):
    """Hessian of the Lagrangian G + lambda^T [E; C] at `a` (zero if not finite; `lam` holds
    the multipliers of E, then, for a problem with inequalities, those of its inequality rows
    (`_kkt.inequality_rows`: path points, terminal inequalities, then the bound rows, which are
    linear in a and add no curvature)). With RK4: forward over reverse autodiff of the plain
    simulation (dense on the grid where there are path constraints), the RK4 step
    rematerialized in the reverse pass, which compiles faster; 1-5.5x faster warm than forward
    over the forward sensitivities, most where there are many parameters and rows. Without
    path constraints, and where the parameters are at least `SEGMENT_HESSIAN_RATIO` x the
    tangents of a segment (n states + r columns of its `segment_data`'s basis), by segments
    instead (`_sensitivity.segment_hessian`: n + r tangents instead of one per parameter).
    Forward over forward otherwise (diffrax runs with forward-mode adjoints only). Timings:
    benchmarks/RESULTS.md."""
    if isinstance(simulator, RK4):
        m = problem.num_constraints

        def terminal_part(tf, xf, C):
            D = jnp.zeros(0, a.dtype)
            if problem.terminal_inequality is not None:
                D = problem.terminal_inequality(tf, xf, problem.args)
            weights = lam[m : m + C.size + D.shape[0]]
            return (
                problem.objective(tf, xf, problem.args)
                + lam[:m] @ problem.terminal(tf, xf, problem.args)
                + weights @ jnp.concatenate([C.reshape(-1), D])
            )

        basis = affine_segment_basis(control, a) if problem.path is None else None
        if basis is not None and a.shape[0] >= SEGMENT_HESSIAN_RATIO * (problem.num_states + basis.shape[-1]):
            empty = jnp.zeros(0, a.dtype)
            W = segment_hessian(problem, control, a, simulator, lambda tf, xf: terminal_part(tf, xf, empty), basis)
        else:

            def lagrangian(a):
                if problem.path is None:
                    xf, _ = final_state(problem, control, a, simulator)
                    C = jnp.zeros(0, a.dtype)
                else:
                    xf, (_, C, _) = path_values(problem, control, a, simulator)
                return terminal_part(control.tf(a), xf, C)

            W = jax.jacfwd(jax.grad(lagrangian))(a)
    else:

        def gradient(a):
            return lagrangian_gradient(evaluate_jitted(problem, control, a, simulator, "forward"), lam)

        W = jax.jacfwd(gradient)(a)
    W = 0.5 * (W + W.T)
    return jnp.where(jnp.all(jnp.isfinite(W)), W, 0.0)  # a failed integration: no curvature


def evaluate(
    problem: Problem,
    control: AbstractControl,
    a,
    method: str = "forward",
    *,
    simulator: AbstractSimulator = RK4(),
) -> Evaluation:
    """Objective, constraints and their parameter derivatives at `a` (with a status).

    `E = M(tf, x(tf))` (the terminal constraints; the thesis's initial constraints I(a) are
    empty for every problem here), `H = dE/da`, `G`, `G_a = dG/da`, by the chain rule
    through x(tf) and tf(a). See `jt.sensitivities` for the arguments.
    """
    check_method(method)
    a = check_inputs(problem, control, a)
    check_simulator(simulator)
    return evaluate_jitted(problem, control, a, simulator, method)
