"""The restricted optimal-control problem: dynamics, initial state, terminal constraints,
objective, optional control bounds and path constraints.

Signatures follow diffrax's ordering (time first, `args` last):

* `dynamics(t, x, u, args) -> dx/dt`, shape `(n,)`;
* `terminal(tf, xf, args) -> M`, shape `(l,)`: terminal equality constraints M = 0;
* `objective(tf, xf, args) -> G`, a scalar (default: `tf`, minimum time);
* `path(t, x, u, args) -> C`, shape `(q,)`: path inequality constraints C <= 0 (optional).

Path constraints are imposed on the points of the simulator's integration grid (a finer
check is up to the problem: e.g. `problems.attitude.cone_margin`), by every solver:
`KalmanSQP` and `KalmanSearch` observe the grid points of an active set (appendix-C style),
`AugmentedLagrangian` carries a multiplier per grid point, and the SciPy SLSQP / IPOPT
baselines impose them as inequalities. Solutions report the worst value and its time
(`max_path_constraint`, `max_path_time`).

Physical constants go in `args` (a pytree of arrays), not in closures, so that changing them
does not recompile anything and they can be traced or vmapped over.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def minimum_time(tf, xf, args):
    """The default objective G = tf."""
    del xf, args
    return tf


class Problem(eqx.Module):
    """A control problem in Mayer form with terminal equality constraints.

    **Arguments:**

    - `dynamics`: `f(t, x, u, args) -> dx/dt`.
    - `x0`: initial state, shape `(n,)`.
    - `terminal`: `M(tf, xf, args) -> (l,)`, the terminal constraints M = 0.
    - `constraint_names`: a short name per component of M, used in reports.
    - `num_controls`: number of control channels `nu` (u has shape `(nu,)`).
    - `objective`: `G(tf, xf, args) -> scalar` to minimize (default: tf).
    - `args`: pytree of constants passed to every function.
    - `state_names`, `control_names`: labels for reports and plots.
    - `control_lower`, `control_upper`: optional bounds on u, shape `(nu,)`.
    - `path`: optional `C(t, x, u, args) -> (q,)` with C <= 0 required along the trajectory.
    - `path_names`: a short name per component of C.
    - `name`: the problem's name, a label for reports, result files and plots.

    !!! note "The name does not take part in compilation"
        Compiled code is keyed by a problem's static structure (functions, sizes) and not
        by its name: problems that differ only in `name` and array values (`x0`, `args`,
        bounds), e.g. `jt.problems.solar_sail.problem("mars")` and `("venus")`, share every
        compiled solver, simulation and sensitivity. For the same reason problems equal in
        everything but their names compare equal (`eqx.tree_equal`), and code inside `jit`
        must not branch on `name` (a cache hit reuses the code traced for the first name).
    """

    dynamics: Callable
    x0: jax.Array
    terminal: Callable
    constraint_names: tuple[str, ...]
    num_controls: int = 1
    objective: Callable = minimum_time
    args: Any = None
    state_names: tuple[str, ...] | None = None
    control_names: tuple[str, ...] | None = None
    control_lower: jax.Array | None = None
    control_upper: jax.Array | None = None
    path: Callable | None = None
    path_names: tuple[str, ...] = ()
    _label: "_Label" = None  # the name; see `name`

    def __init__(
        self,
        dynamics,
        x0,
        terminal,
        constraint_names,
        *,
        num_controls=1,
        objective=minimum_time,
        args=None,
        state_names=None,
        control_names=None,
        control_lower=None,
        control_upper=None,
        path=None,
        path_names=(),
        name="problem",
    ):
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.ndim != 1 or x0.size == 0:
            raise ValueError(f"`x0` must be a non-empty 1-D array; got shape {x0.shape}.")
        if not np.all(np.isfinite(x0)):
            raise ValueError(f"`x0` must be finite; got {x0}.")
        if not (isinstance(num_controls, int) and num_controls >= 1):
            raise ValueError(f"`num_controls` must be an int >= 1; got {num_controls!r}.")
        for fname, fn in (("dynamics", dynamics), ("terminal", terminal), ("objective", objective)):
            if not callable(fn):
                raise ValueError(f"`{fname}` must be callable; got {type(fn).__name__}.")
        self.dynamics = dynamics
        self.x0 = jnp.asarray(x0)
        self.terminal = terminal
        self.constraint_names = _names(constraint_names, "constraint_names")
        self.num_controls = num_controls
        self.objective = objective
        self.args = args
        n = x0.size
        self.state_names = _names(state_names, "state_names") if state_names else tuple(f"x{i + 1}" for i in range(n))
        self.control_names = (
            _names(control_names, "control_names") if control_names else tuple(f"u{i + 1}" for i in range(num_controls))
        )
        self.control_lower = None if control_lower is None else _bound(control_lower, num_controls, "control_lower")
        self.control_upper = None if control_upper is None else _bound(control_upper, num_controls, "control_upper")
        lo, hi = self.control_lower, self.control_upper
        if lo is not None and hi is not None and np.any(np.asarray(lo) > np.asarray(hi)):
            raise ValueError(
                f"`control_lower` must be <= `control_upper` in every channel; got {np.asarray(lo)} > {np.asarray(hi)}."
            )
        self.path = path
        self.path_names = _names(path_names, "path_names")
        if not isinstance(name, str):
            raise ValueError(f"`name` must be a str; got {type(name).__name__}.")
        self._label = _Label(name)
        self._check_signatures()

    @property
    def name(self) -> str:
        """The problem's name (a label; it does not take part in compilation)."""
        return self._label.text

    @property
    def num_states(self) -> int:
        return int(self.x0.shape[0])

    @property
    def num_constraints(self) -> int:
        return len(self.constraint_names)

    def _check_signatures(self):
        """Trace each user function once (no FLOPs) and check its output shape."""
        n, nu = self.num_states, self.num_controls
        t = jax.ShapeDtypeStruct((), jnp.float64)
        x = jax.ShapeDtypeStruct((n,), jnp.float64)
        u = jax.ShapeDtypeStruct((nu,), jnp.float64)
        checks = [
            ("dynamics(t, x, u, args)", lambda t, x, u: self.dynamics(t, x, u, self.args), (n,)),
            ("terminal(tf, xf, args)", lambda t, x, u: self.terminal(t, x, self.args), (self.num_constraints,)),
            ("objective(tf, xf, args)", lambda t, x, u: self.objective(t, x, self.args), ()),
        ]
        if self.path is not None:
            checks.append(
                ("path(t, x, u, args)", lambda t, x, u: self.path(t, x, u, self.args), (len(self.path_names),))
            )
        for label, fn, shape in checks:
            out = jax.eval_shape(fn, t, x, u)
            if getattr(out, "shape", None) != shape:
                raise ValueError(
                    f"`{label}` must return an array of shape {shape} "
                    f"(n={n} states, nu={nu} controls, {self.num_constraints} constraint names); "
                    f"got {getattr(out, 'shape', type(out).__name__)}."
                )


class _Label:
    """A string carried through pytree operations as a static leaf that takes no part in
    equality or hashing: all labels compare equal. `eqx.filter_jit` (and so every jaxtraj
    solver) keys its compilation cache on the static leaves' equality and hash, so a
    problem's name never causes a recompilation."""

    __slots__ = ("text",)

    def __init__(self, text: str):
        self.text = text

    def __eq__(self, other):
        return isinstance(other, _Label)

    def __hash__(self):
        return hash(_Label)

    def __repr__(self):
        return repr(self.text)


def _bound(value, nu, name):
    """A control bound as a float64 `(nu,)` array (a scalar applies to every channel)."""
    try:
        b = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a number or {nu} numbers; got {value!r}.") from None
    if b.ndim > 1 or (b.ndim == 1 and b.shape[0] not in (1, nu)):
        raise ValueError(f"`{name}` must be a scalar or have {nu} entries (num_controls); got shape {b.shape}.")
    b = np.broadcast_to(b, (nu,))
    if np.any(np.isnan(b)):
        raise ValueError(f"`{name}` must not contain NaN; got {b}.")
    return jnp.asarray(b)


def _names(value, name):
    """A tuple of str; a lone string is refused (it would become one name per character)."""
    if isinstance(value, str):
        raise ValueError(f"`{name}` must be a sequence of names, not one string; got {value!r} (write ({value!r},)).")
    names = tuple(value)
    if not all(isinstance(v, str) for v in names):
        raise ValueError(f"`{name}` must contain strings; got {names!r}.")
    return names
