"""Reference solvers built on jaxtraj's evaluation, for cross-checking the library's own
search.

`solve_slsqp` hands the restricted problem "minimize G(a) subject to E(a) = 0" to
`scipy.optimize.minimize(method="SLSQP")`, with G, G_a, E and H = dE/da from
`evaluate_restricted` (one jit-compiled function, one integration per distinct `a`). Path
constraints C(t, x, u) <= 0 of the problem become inequalities at every point of the
integration grid (as `jt.KalmanSQP` and `jt.AugmentedLagrangian` see them), with their
Jacobian from the same evaluation.
`solve_ipopt` hands the same problem, with the same functions, to IPOPT through CasADi
(an optional extra: `pip install jaxtraj[bench]`; IPOPT with limited-memory Hessians, since
CasADi sees the JAX evaluation as a black box with first derivatives).
"""

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from ._bounds import require_rows
from ._checks import check_inputs
from ._kkt import inequality_rows
from ._problem import Problem
from ._sensitivity import check_method, evaluate_jitted
from ._simulate import RK4, AbstractSimulator, check_simulator
from ._status import Status
from .controls import AbstractControl

#: Minimum gap between consecutive knots (node/switch times) imposed on the search.
MIN_KNOT_GAP = 1e-6


@dataclasses.dataclass(frozen=True)
class SLSQPResult:
    """Outcome of `solve_slsqp` (and of `solve_ipopt`, with IPOPT's iterations and message).

    - `params`: final parameter vector (float64 numpy).
    - `tf`: final time tf(params).
    - `objective`: G(params).
    - `constraints`: E(params) = M(tf, x(tf)).
    - `max_constraint_error`: max |E(params)|.
    - `max_path_constraint`: max C over the grid (path constraints C <= 0; -inf without).
    - `iterations`: SLSQP major iterations (`nit`).
    - `evaluations`: number of distinct parameter vectors integrated.
    - `success`: SLSQP reported convergence and the final evaluation is finite.
    - `message`: SLSQP's message (or the simulation status message on failure).
    - `wall_time`: seconds for the whole call, compilation included.
    - `history_objective`, `history_max_constraint_error`: G and max |E| at every integrated
      point, in order (for convergence plots against the number of integrations).
    """

    params: np.ndarray
    tf: float
    objective: float
    constraints: np.ndarray
    max_constraint_error: float
    max_path_constraint: float
    iterations: int
    evaluations: int
    success: bool
    message: str
    wall_time: float
    history_objective: np.ndarray
    history_max_constraint_error: np.ndarray


class _CachedEvaluation:
    """Calls the compiled evaluation at most once per distinct `a` (the last one is kept),
    so that SLSQP's separate fun / jac / constraint calls at one point cost one integration."""

    def __init__(self, problem, control, simulator, method):
        self._fn = lambda a: evaluate_jitted(problem, control, a, simulator, method)
        self._key = None
        self._value: dict[str, Any] = {}  # the evaluation at `_key` (set by the first call: no key is None)
        self.count = 0
        self.history = []

    def __call__(self, a):
        a = np.asarray(a, dtype=np.float64)
        key = a.tobytes()
        if key != self._key:
            ev = self._fn(jnp.asarray(a))
            path = inequality_rows(ev)
            self._value = {
                "tf": float(ev.tf),
                "G": float(ev.G),
                "G_a": np.asarray(ev.G_a, dtype=np.float64),
                "E": np.asarray(ev.E, dtype=np.float64),
                "H": np.asarray(ev.H, dtype=np.float64),
                "C": np.asarray(path[0], dtype=np.float64) if path else np.zeros(0),
                "C_a": np.asarray(path[1], dtype=np.float64) if path else np.zeros((0, a.size)),
                "ok": bool(ev.status == Status.SUCCESS),
                "status": ev.status,
            }
            self._key = key
            self.count += 1
            self.history.append((self._value["G"], float(np.max(np.abs(self._value["E"]), initial=0.0))))
        return self._value


def _prepare(problem, control, a0, simulator, method):
    """The control the baselines work with, the checked start, and the cached evaluation
    shared by both baselines (default RK4())."""
    simulator = RK4() if simulator is None else simulator
    check_method(method)
    a0 = check_inputs(problem, control, a0)
    check_simulator(simulator)
    require_rows(problem, control, "the SLSQP / IPOPT baselines")
    return control, a0, _CachedEvaluation(problem, control, simulator, method)


def _knot_gap_constraint(control, a0):
    """Linear inequality `D a + c >= MIN_KNOT_GAP` with rows knots[k+1] - knots[k]."""
    J = np.asarray(jax.jacfwd(control.knots)(a0), dtype=np.float64)  # (K + 1, np)
    offset = np.asarray(control.knots(a0), dtype=np.float64) - J @ np.asarray(a0, dtype=np.float64)
    # The knots of every family are linear in a; check it on a second point.
    probe = np.asarray(a0, dtype=np.float64) + 0.01 * np.arange(1, J.shape[1] + 1)
    if not np.allclose(np.asarray(control.knots(jnp.asarray(probe))), J @ probe + offset, rtol=1e-12, atol=1e-12):
        raise ValueError(f"`control.knots` is not affine in `a` for {control!r}; solve_slsqp needs it to be.")
    D = J[1:] - J[:-1]
    c = offset[1:] - offset[:-1] - MIN_KNOT_GAP
    free = np.any(D != 0, axis=1)  # gaps fixed by a fixed final time are no constraint
    D, c = D[free], c[free]
    return {"type": "ineq", "fun": lambda a: D @ a + c, "jac": lambda a: D}


def solve_slsqp(
    problem: Problem,
    control: AbstractControl,
    a0,
    *,
    simulator: AbstractSimulator | None = None,
    method: str = "forward",
    ftol: float = 1e-14,
    maxiter: int = 500,
) -> SLSQPResult:
    """Solve the restricted problem "minimize G(a) subject to E(a) = 0" with SciPy's SLSQP.

    The objective G, its gradient G_a, the terminal constraints E = M(tf, x(tf)) and their
    Jacobian H = dE/da come from one jit-compiled `evaluate_restricted`; SLSQP's calls at
    the same `a` share one integration. Consecutive knots (node/switch times, tf) are kept
    ordered by the linear inequalities knots[k+1] - knots[k] >= 1e-6, k = 0..K-1, built
    from the (affine) map `control.knots`; without them a free-time search can cross two
    switch times.

    **Arguments:**

    - `problem`: a `jt.Problem`.
    - `control`: a control parametrization (`jt.controls.*`).
    - `a0`: starting parameter vector, shape `(control.num_params,)`.
    - `simulator`: keyword-only, default `jt.RK4()` (100 steps per segment).
    - `method`: sensitivity method, `"forward"` (default), `"unit"` or `"fd"`.
    - `ftol`: SLSQP's tolerance on the objective change (default 1e-14).
    - `maxiter`: SLSQP's iteration limit (default 500).

    **Returns:** an `SLSQPResult` (params, tf, objective, constraints, max_constraint_error,
    iterations, evaluations, success, message, wall_time).

    **Raises:** `ValueError` for invalid inputs (as `jt.evaluate`).
    """
    start = time.perf_counter()
    control, a0, ev = _prepare(problem, control, a0, simulator, method)
    constraints = [{"type": "eq", "fun": lambda a: ev(a)["E"], "jac": lambda a: ev(a)["H"]}]
    gaps = _knot_gap_constraint(control, a0)
    if gaps["jac"](None).shape[0]:
        constraints.append(gaps)
    if ev(a0)["C"].size:  # inequalities (path, terminal); SLSQP's are fun >= 0
        constraints.append({"type": "ineq", "fun": lambda a: -ev(a)["C"], "jac": lambda a: -ev(a)["C_a"]})
    res = scipy.optimize.minimize(
        lambda a: ev(a)["G"],
        np.asarray(a0, dtype=np.float64),
        jac=lambda a: ev(a)["G_a"],
        method="SLSQP",
        constraints=constraints,
        options={"ftol": ftol, "maxiter": maxiter},
    )
    return _result(ev, res.x, int(res.nit), bool(res.success), str(res.message), start)


def _result(ev, x, iterations, success, message, start) -> SLSQPResult:
    """The result at the optimizer's final point `x`, re-evaluated (cached) by `ev`."""
    x = np.asarray(x, dtype=np.float64).ravel()
    final = ev(x)
    if not final["ok"]:
        message = f"{message} (final evaluation: {Status[final['status']]})"
    E = final["E"].copy()
    return SLSQPResult(
        params=x.copy(),
        tf=final["tf"],
        objective=final["G"],
        constraints=E,
        max_constraint_error=float(np.max(np.abs(E))) if E.size else 0.0,
        max_path_constraint=float(np.max(final["C"], initial=-np.inf)),
        iterations=iterations,
        evaluations=ev.count,
        success=success and final["ok"],
        message=message,
        wall_time=time.perf_counter() - start,
        history_objective=np.array([h[0] for h in ev.history]),
        history_max_constraint_error=np.array([h[1] for h in ev.history]),
    )


def _casadi_function(ev, n, m):
    """A CasADi Callback a -> [G; E; C] with its Jacobian [G_a; H; C_a], all from `ev` (one
    integration per distinct a; m = number of E and C rows)."""
    import casadi as ca

    class Dense(ca.Callback):
        """Dense inputs/outputs of the given shapes."""

        inputs: tuple = ()
        output: tuple = ()

        def __init__(self, name, opts):
            ca.Callback.__init__(self)
            self.construct(name, opts)

        def get_n_in(self):
            return len(self.inputs)

        def get_n_out(self):
            return 1

        def get_sparsity_in(self, i):
            return ca.Sparsity.dense(*self.inputs[i])

        def get_sparsity_out(self, i):
            return ca.Sparsity.dense(*self.output)

    class Jacobian(Dense):
        inputs, output = ((n, 1), (1 + m, 1)), (1 + m, n)  # (a, nominal output) -> d[G; E]/da

        def eval(self, arg):
            v = ev(np.asarray(arg[0]).ravel())
            return [np.vstack([v["G_a"][None, :], v["H"], v["C_a"]])]

    class Values(Dense):
        inputs, output = ((n, 1),), (1 + m, 1)

        def eval(self, arg):
            v = ev(np.asarray(arg[0]).ravel())
            return [np.concatenate([[v["G"]], v["E"], v["C"]])]

        def has_jacobian(self):
            return True

        def get_jacobian(self, name, inames, onames, opts):
            self._jacobian = Jacobian(name, opts)  # CasADi keeps no reference: we do
            return self._jacobian

    return Values("jaxtraj_restricted", {"enable_fd": False})


def solve_ipopt(
    problem: Problem,
    control: AbstractControl,
    a0,
    *,
    simulator: AbstractSimulator | None = None,
    method: str = "forward",
    tol: float = 1e-10,
    max_iter: int = 3000,
) -> SLSQPResult:
    """Solve "minimize G(a) subject to E(a) = 0" (knots ordered and path constraints on the
    grid as in `solve_slsqp`) with IPOPT through CasADi, on the same compiled evaluation as
    `solve_slsqp`.

    CasADi is an optional dependency (`pip install jaxtraj[bench]` or `pip install casadi`);
    `ImportError` with that hint if it is missing. IPOPT runs with `hessian_approximation =
    limited-memory` (only first derivatives cross the JAX/CasADi boundary), `tol` and
    `constr_viol_tol` = `tol`, at most `max_iter` iterations, no output. Returns an
    `SLSQPResult` (same fields; `iterations` are IPOPT's, `message` its return status).
    """
    try:
        import casadi as ca
    except ImportError as err:  # pragma: no cover - exercised only without the extra
        raise ImportError("solve_ipopt needs CasADi: `pip install jaxtraj[bench]` (or `pip install casadi`).") from err
    start = time.perf_counter()
    control, a0, ev = _prepare(problem, control, a0, simulator, method)
    n, m = int(a0.shape[0]), problem.num_constraints
    p = ev(a0)["C"].size  # path constraint rows (grid points x components)
    gaps = _knot_gap_constraint(control, a0)
    D = gaps["jac"](None)
    c = gaps["fun"](np.zeros(n))
    fn = _casadi_function(ev, n, m + p)
    x = ca.MX.sym("a", n)
    values = fn(x)
    rows = ([values[1:]] if m + p else []) + ([ca.mtimes(ca.DM(D), x) + ca.DM(c)] if D.shape[0] else [])
    nlp = {"x": x, "f": values[0], "g": ca.vertcat(*rows) if rows else ca.MX(0, 1)}
    options = {
        "ipopt.hessian_approximation": "limited-memory",
        "ipopt.tol": tol,
        "ipopt.constr_viol_tol": tol,
        "ipopt.max_iter": max_iter,
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",  # no banner
        "print_time": False,
    }
    solver = ca.nlpsol("jaxtraj_ipopt", "ipopt", nlp, options)
    K = D.shape[0]
    lbg = np.concatenate([np.zeros(m), np.full(p, -np.inf), np.zeros(K)])
    ubg = np.concatenate([np.zeros(m + p), np.full(K, np.inf)])
    res = solver(x0=np.asarray(a0, dtype=np.float64), lbg=lbg, ubg=ubg)
    stats = solver.stats()
    return _result(ev, res["x"], int(stats["iter_count"]), bool(stats["success"]), str(stats["return_status"]), start)


__all__ = ["SLSQPResult", "solve_ipopt", "solve_slsqp"]
