"""The restricted optimal-control problem: dynamics, initial state, terminal constraints,
objective (Mayer and running cost), optional control and state bounds and path constraints.

Signatures follow diffrax's ordering (time first, `args` last):

* `dynamics(t, x, u, args) -> dx/dt`, shape `(n,)`;
* `terminal(tf, xf, args) -> M`, shape `(l,)`: terminal equality constraints M = 0;
* `objective(tf, xf, args) -> G`, a scalar (default: `tf`, minimum time);
* `running_cost(t, x, u, args) -> L`, a scalar (optional): adds the integral of L over [0, tf]
  to the objective;
* `path(t, x, u, args) -> C`, shape `(q,)`: path inequality constraints C <= 0 (optional);
* `terminal_inequality(tf, xf, args) -> D`, shape `(r,)`: terminal inequality constraints
  D <= 0 (optional).

A running cost is carried as one more state, the accumulated cost (last, named
`"running cost"`, starting at 0), and the objective becomes G(tf, x(tf)) + its final value:
the Mayer form every solver works on, so that the cost's sensitivities (first and second
order, forward-mode or unit-solution) are those of the state, exact. The user's functions
keep their signatures (they see the user's state, without the cost). State bounds
(`state_lower`, `state_upper`) are path constraints on the user's states, named
`"<state> upper bound"` / `"<state> lower bound"`, after the user's `path` rows.

Physical constants go in `args` (a pytree of arrays), not in closures, so that changing them
does not recompile anything and they can be traced or vmapped over. Path constraints hold on
the integration grid (how each solver imposes them: docs/own-problem.md, "Things to know").
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.experimental import checkify

from .controls import AbstractControl, FixedFinalTime, FreeInitialState


def minimum_time(tf, xf, args):
    """The default objective G = tf."""
    del xf, args
    return tf


_INDEXING = frozenset({"dynamic_slice", "dynamic_update_slice", "gather", "scatter", "scatter-add"})


def _indexes_by_value(jaxpr) -> bool:
    """Whether a jaxpr (or one inside it) indexes an array by a traced value."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in _INDEXING:
            return True
        for param in eqn.params.values():
            for sub in param if isinstance(param, (tuple, list)) else (param,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns") and _indexes_by_value(inner):
                    return True
    return False


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


class Problem(eqx.Module):
    """A control problem with terminal equality constraints, in Mayer form (a running cost
    becomes one more state; see the module docs).

    **Arguments:**

    - `dynamics`: `f(t, x, u, args) -> dx/dt`.
    - `x0`: initial state, shape `(n,)`.
    - `terminal`: `M(tf, xf, args) -> (l,)`, the terminal constraints M = 0.
    - `constraint_names`: a short name per component of M, used in reports.
    - `num_controls`: number of control channels `nu` (u has shape `(nu,)`).
    - `objective`: `G(tf, xf, args) -> scalar` to minimize. Default: tf (minimum time), or 0
      when a `running_cost` is given. To maximize J, minimize -J.
    - `running_cost`: optional `L(t, x, u, args) -> scalar`; the objective is then
      G(tf, x(tf)) + the integral of L from 0 to tf.
    - `args`: pytree of constants passed to every function.
    - `state_names`, `control_names`: labels for reports and plots.
    - `control_lower`, `control_upper`: optional bounds on u, shape `(nu,)`.
    - `state_lower`, `state_upper`: optional bounds on x along the trajectory, shape `(n,)`
      (or a scalar); -inf (lower) or +inf (upper) leaves a component free, the other
      infinity (no value meets it) is refused, for control bounds too. Imposed as named
      path constraints.
    - `path`: optional `C(t, x, u, args) -> (q,)` with C <= 0 required along the trajectory.
    - `path_names`: a short name per component of C.
    - `terminal_inequality`: optional `D(tf, xf, args) -> (r,)` with D <= 0 required at tf.
    - `terminal_inequality_names`: a short name per component of D.
    - `final_time`: optional fixed final time T > 0. Then tf is no decision parameter:
      parameter vectors have no tf entry (the control is `parametrize(family)`, a
      `jt.controls.FixedFinalTime`). Needs an `objective` or a `running_cost`.
    - `tf_bounds`: optional `(lower, upper)` on the free final time (either may be +-inf):
      terminal inequalities `lower - tf <= 0`, `tf - upper <= 0` named `"tf lower bound"` /
      `"tf upper bound"`, after the user's. Read back as `problem.tf_bounds`: 0-d arrays
      (None for an absent side), with derivatives: `eqx.tree_at(lambda p: p.tf_bounds[1],
      problem, T)` puts in another, traced, upper bound (docs/differentiable.md).
    - `free_initial_state`: initial-state components that are decision parameters too, as
      a sequence of state names (or indices), or a dict `{name: (lower, upper)}` with
      bounds (either may be +-inf). `x0` holds their start values. Parameter vectors then
      end with these components (the control is `parametrize(family)`, a
      `jt.controls.FreeInitialState`). A static design parameter p is a state with
      dp/dt = 0 and a free initial value.
    - `name`: the problem's name, a label for reports, result files and plots.

    With a running cost the fields describe the Mayer form: `x0`, `num_states`,
    `state_names` and the trajectories have the accumulated cost as a last component, and
    `dynamics`, `objective`, `terminal` and `path` are the wrapped functions of that state
    (`running_cost` is the user's L). State bounds make `path` and `path_names` include them.

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
    state_names: tuple[str, ...] = ()  # (set by `__init__`: the given names, else x1, x2, ...)
    control_names: tuple[str, ...] = ()  # (set by `__init__`: the given names, else u1, u2, ...)
    control_lower: jax.Array | None = None
    control_upper: jax.Array | None = None
    path: Callable | None = None
    path_names: tuple[str, ...] = ()
    running_cost: Callable | None = None
    terminal_inequality: Callable | None = None
    terminal_inequality_names: tuple[str, ...] = ()
    final_time: jax.Array | None = None
    free_initial_state: tuple[int, ...] = eqx.field(static=True, default=())
    _initial_box: tuple[tuple[float, ...], tuple[float, ...]] = eqx.field(static=True, default=((), ()), repr=False)
    _control_box: tuple[tuple[float, ...], tuple[float, ...]] = eqx.field(static=True, default=((), ()), repr=False)
    _label: _Label = _Label("problem")  # the name; see `name`

    def __init__(
        self,
        dynamics,
        x0,
        terminal,
        constraint_names,
        *,
        num_controls=1,
        objective=None,
        running_cost=None,
        args=None,
        state_names=None,
        control_names=None,
        control_lower=None,
        control_upper=None,
        path=None,
        path_names=(),
        state_lower=None,
        state_upper=None,
        terminal_inequality=None,
        terminal_inequality_names=(),
        tf_bounds=None,
        final_time=None,
        free_initial_state=(),
        name="problem",
    ):
        for label, value in (("x0", x0), ("final_time", final_time)):
            if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(value)):
                # (it was refused as "must be real numbers" / "a finite number", which it may be)
                route = {
                    "x0": "problem.x0.at[:n].set(value))` (`problem.x0` holds a running cost's state too)",
                    "final_time": "value)`, then `problem.parametrize(family)` again",
                }[label]
                raise ValueError(
                    f"`{label}` is traced (a variable of jax.grad, jax.jit or jax.vmap): jt.Problem takes concrete "
                    f"numbers there. Build the problem with concrete ones and put the traced value in with "
                    f"`eqx.tree_at(lambda p: p.{label}, problem, {route}; see docs/differentiable.md."
                )
        try:
            if np.iscomplexobj(x0):  # (a cast to float64 drops the imaginary part with a warning only)
                raise TypeError
            x0 = np.asarray(x0, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"`x0` must be real numbers (the initial state); got {x0!r}.") from None
        if x0.ndim != 1 or x0.size == 0:
            raise ValueError(f"`x0` must be a non-empty 1-D array; got shape {x0.shape}.")
        if not np.all(np.isfinite(x0)):
            raise ValueError(f"`x0` must be finite; got {x0}.")
        if not (isinstance(num_controls, int) and not isinstance(num_controls, bool) and 1 <= num_controls <= 10_000):
            raise ValueError(f"`num_controls` must be an int in 1..10000; got {num_controls!r}.")
        if final_time is not None:
            try:
                T = np.asarray(final_time, dtype=np.float64)
            except (TypeError, ValueError):
                T = np.asarray(np.nan)
            if T.shape != () or not (np.isfinite(T) and T > 0):
                raise ValueError(f"`final_time` must be a finite number > 0; got {final_time!r}.")
            if tf_bounds is not None:
                raise ValueError("`tf_bounds` bounds a free final time; give either `final_time` or `tf_bounds`.")
            if objective is None and running_cost is None:
                raise ValueError(
                    "`final_time` is fixed, so the default objective (minimum time) is a constant: "
                    "give an `objective` or a `running_cost`."
                )
            self.final_time = jnp.asarray(float(T), dtype=jnp.float64)
        if objective is None:
            objective = minimum_time if running_cost is None else no_mayer_term
        for fname, fn in (("dynamics", dynamics), ("terminal", terminal), ("objective", objective)):
            if not callable(fn):
                raise ValueError(f"`{fname}` must be callable; got {type(fn).__name__}.")
        for fname, fn in (("running_cost", running_cost), ("path", path), ("terminal_inequality", terminal_inequality)):
            if fn is not None and not callable(fn):
                raise ValueError(f"`{fname}` must be callable or None; got {type(fn).__name__}.")
        self.dynamics = dynamics
        self.x0 = jnp.asarray(x0)
        self.terminal = terminal
        self.constraint_names = _names(constraint_names, "constraint_names")
        self.num_controls = num_controls
        self.objective = objective
        self.running_cost = running_cost
        self.args = args
        n = x0.size
        self.state_names = _names(state_names, "state_names") if state_names else tuple(f"x{i + 1}" for i in range(n))
        if len(self.state_names) != n:
            raise ValueError(f"`state_names` must have {n} entries (one per state); got {len(self.state_names)}.")
        self.control_names = (
            _names(control_names, "control_names") if control_names else tuple(f"u{i + 1}" for i in range(num_controls))
        )
        if len(self.control_names) != num_controls:
            raise ValueError(
                f"`control_names` must have {num_controls} entries (one per control); got {len(self.control_names)}."
            )
        self.control_lower = None if control_lower is None else _bound(control_lower, num_controls, "control_lower")
        self.control_upper = None if control_upper is None else _bound(control_upper, num_controls, "control_upper")
        lo, hi = self.control_lower, self.control_upper
        if lo is not None and hi is not None and np.any(np.asarray(lo) > np.asarray(hi)):
            raise ValueError(
                f"`control_lower` must be <= `control_upper` in every channel; got {np.asarray(lo)} > {np.asarray(hi)}."
            )
        # the bounds' values as static data: which channels are bounded, and whether a family
        # saturates within them, decide the structure of the compiled solvers (`_bounds.py`)
        box_lo, box_hi = (
            tuple(float(v) for v in (np.full(num_controls, fill) if b is None else np.asarray(b)))
            for b, fill in ((lo, -np.inf), (hi, np.inf))
        )
        self._control_box = (box_lo, box_hi)
        self.path = path
        self.path_names = _names(path_names, "path_names")
        self.terminal_inequality = terminal_inequality
        self.terminal_inequality_names = _names(terminal_inequality_names, "terminal_inequality_names")
        for names, fname, fn in (
            ("path_names", "path", path),
            ("terminal_inequality_names", "terminal_inequality", terminal_inequality),
        ):
            if fn is None and getattr(self, names):  # (a declared row without its function: ignored)
                raise ValueError(f"`{names}` names the rows of `{fname}`, which is None; got {getattr(self, names)!r}.")
        if not isinstance(name, str):
            raise ValueError(f"`name` must be a str; got {type(name).__name__}.")
        self._label = _Label(name)
        self._check_signatures()
        self._set_free_initial_state(free_initial_state)
        if state_lower is not None or state_upper is not None:
            self._add_state_bounds(state_lower, state_upper)
        if tf_bounds is not None:
            self._add_tf_bounds(tf_bounds)
        if running_cost is not None:
            self._add_running_cost(running_cost)
        # a user's name that is also one jt.Problem gives a row it adds: one would hide the
        # other in reports, and a saved result (rows by name) would not load
        for field, added in (
            ("path_names", "the rows of `state_lower` / `state_upper`"),
            ("terminal_inequality_names", "the rows of `tf_bounds`"),
            ("state_names", "the accumulated `running_cost`"),
        ):
            names = getattr(self, field)
            repeated = sorted({v for v in names if names.count(v) > 1})
            if repeated:
                raise ValueError(f"`{field}`: {repeated} is also the name jt.Problem gives {added}; rename yours.")

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
        """Trace each user function once (no FLOPs) and check its output shape and that it is
        real (a complex or boolean result is refused here, not deep inside a solve)."""
        n, nu = self.num_states, self.num_controls
        t = jax.ShapeDtypeStruct((), jnp.float64)
        x = jax.ShapeDtypeStruct((n,), jnp.float64)
        u = jax.ShapeDtypeStruct((nu,), jnp.float64)
        checks = [
            ("dynamics(t, x, u, args)", lambda t, x, u: self.dynamics(t, x, u, self.args), (n,)),
            ("terminal(tf, xf, args)", lambda t, x, u: self.terminal(t, x, self.args), (self.num_constraints,)),
            ("objective(tf, xf, args)", lambda t, x, u: self.objective(t, x, self.args), ()),
        ]
        path, running_cost, terminal_inequality = self.path, self.running_cost, self.terminal_inequality
        if path is not None:
            checks.append(("path(t, x, u, args)", lambda t, x, u: path(t, x, u, self.args), (len(self.path_names),)))
        if running_cost is not None:
            checks.append(("running_cost(t, x, u, args)", lambda t, x, u: running_cost(t, x, u, self.args), ()))
        if terminal_inequality is not None:
            checks.append(
                (
                    "terminal_inequality(tf, xf, args)",
                    lambda t, x, u: terminal_inequality(t, x, self.args),
                    (len(self.terminal_inequality_names),),
                )
            )
        indexed = []
        for label, fn, shape in checks:
            jaxpr, out = jax.make_jaxpr(fn, return_shape=True)(t, x, u)
            if _indexes_by_value(jaxpr.jaxpr):
                indexed.append((label, fn))
            if getattr(out, "shape", None) != shape:
                raise ValueError(
                    f"`{label}` must return an array of shape {shape} "
                    f"(n={n} states, nu={nu} controls, {self.num_constraints} constraint names); "
                    f"got {getattr(out, 'shape', type(out).__name__)}."
                )
            if not (jnp.issubdtype(out.dtype, jnp.floating) or jnp.issubdtype(out.dtype, jnp.integer)):
                raise ValueError(f"`{label}` must return real numbers; got dtype {out.dtype}.")
        # An index past an array's end (u[3] with 2 controls) is clamped by JAX, silently: a
        # function that indexes by value (a dynamic slice or gather: how such an index is
        # traced; u[1] is a static slice) runs once at x0 (u = 0, t = 0) with checkify's
        # index checks, where the arrays are concrete (a problem built under a
        # transformation is not checked).
        traced = any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves((self.x0, self.args)))
        if indexed and not traced:
            x0, u0 = jnp.asarray(self.x0, jnp.float64), jnp.zeros(nu, jnp.float64)
            for label, fn in indexed:
                error, _ = checkify.checkify(fn, errors=checkify.index_checks)(jnp.float64(0.0), x0, u0)
                message = error.get()
                if message is not None:
                    raise ValueError(f"`{label}` indexes outside an array: {message.strip()}")

    @property
    def initial_state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """`(lower, upper)`, one entry per `free_initial_state` component (+-inf: unbounded)."""
        return np.asarray(self._initial_box[0], float), np.asarray(self._initial_box[1], float)

    @property
    def tf_bounds(self):
        """`(lower, upper)` of a bounded free final time, 0-d arrays (None on a side without
        a bound, or for both: no `tf_bounds`)."""
        fn = self.terminal_inequality
        while isinstance(fn, _OnUserState):
            fn = fn.fn
        return (fn.lower, fn.upper) if isinstance(fn, _TimeBounds) else None

    def parametrize(self, family: AbstractControl) -> AbstractControl:
        """The control the solvers optimize for this problem, from a control family: the
        family itself, or for a fixed `final_time` `FixedFinalTime(family, T)` (no tf entry),
        then for a `free_initial_state` `FreeInitialState(..., indices, x0[indices])` (those
        components appended). Pass it to every entry point and evaluate u with it:
        `ctrl = prob.parametrize(jt.controls.PiecewiseLinear(10))`,
        `a0 = ctrl.initial_guess(T, u0, u1)`, `ctrl(sol.params, t)`."""
        if not isinstance(family, AbstractControl) or isinstance(family, (FixedFinalTime, FreeInitialState)):
            raise ValueError(f"`family` must be a control family (jt.controls.*); got {family!r}.")
        control = family if self.final_time is None else FixedFinalTime(family, self.final_time)
        if self.free_initial_state:
            control = FreeInitialState(control, self.free_initial_state, self.x0[np.asarray(self.free_initial_state)])
        return control

    def _set_free_initial_state(self, free):
        """`free_initial_state` (names or indices, or a dict of them to bounds) as indices and
        static bounds (they fix the bound rows at trace time, as `_control_box`)."""
        if isinstance(free, str):
            raise ValueError(f"`free_initial_state` must be a sequence of state names, not one string; got {free!r}.")
        items = list(free.items()) if isinstance(free, dict) else [(k, (-np.inf, np.inf)) for k in free]
        indices, lower, upper = [], [], []
        for key, bounds in items:
            if isinstance(key, str) and key in self.state_names:
                i = self.state_names.index(key)
            elif isinstance(key, (int, np.integer)) and not isinstance(key, bool) and 0 <= key < self.num_states:
                i = int(key)
            else:
                raise ValueError(
                    f"`free_initial_state`: {key!r} is no state (names {self.state_names}, or indices "
                    f"0..{self.num_states - 1})."
                )
            try:
                lo, hi = (float(v) for v in bounds)
            except (TypeError, ValueError):
                raise ValueError(
                    f"`free_initial_state`: the bounds of {key!r} must be a pair (lower, upper); got {bounds!r}."
                ) from None
            if np.isnan(lo) or np.isnan(hi) or lo > hi or not lo <= float(self.x0[i]) <= hi:
                raise ValueError(
                    f"`free_initial_state`: {key!r} needs lower <= x0 <= upper; got ({lo}, {hi}) with "
                    f"x0 = {float(self.x0[i])}."
                )
            if i in indices:
                raise ValueError(f"`free_initial_state`: {key!r} is given twice.")
            indices.append(i)
            lower.append(lo)
            upper.append(hi)
        self.free_initial_state = tuple(indices)
        self._initial_box = (tuple(lower), tuple(upper))

    def _add_state_bounds(self, lower, upper):
        """Append x_i - upper_i <= 0 and lower_i - x_i <= 0 (finite bounds only) to `path`."""
        n = self.num_states
        lo = np.full(n, -np.inf) if lower is None else np.asarray(_bound(lower, n, "state_lower", "states"))
        hi = np.full(n, np.inf) if upper is None else np.asarray(_bound(upper, n, "state_upper", "states"))
        if np.any(lo > hi):
            raise ValueError(f"`state_lower` must be <= `state_upper` in every component; got {lo} > {hi}.")
        above, below = tuple(np.flatnonzero(np.isfinite(hi))), tuple(np.flatnonzero(np.isfinite(lo)))
        if not above and not below:
            return
        upper, lower = jnp.asarray(hi[list(above)]), jnp.asarray(lo[list(below)])
        self.path = _StateBounds(self.path, tuple(map(int, above)), upper, tuple(map(int, below)), lower)
        self.path_names = (
            self.path_names
            + tuple(f"{self.state_names[i]} upper bound" for i in above)
            + tuple(f"{self.state_names[i]} lower bound" for i in below)
        )

    def _add_tf_bounds(self, tf_bounds):
        """Append lower - tf <= 0 and tf - upper <= 0 (finite ones) to `terminal_inequality`."""
        try:  # (a text "12" was the bounds (1, 2), a set in any order, bools 0 and 1)
            if not isinstance(tf_bounds, tuple | list | np.ndarray | jax.Array):
                raise TypeError
            if any(isinstance(v, str | bytes | bool | np.bool_) for v in tf_bounds):
                raise TypeError
            lo, hi = (float(v) for v in tf_bounds)
        except (TypeError, ValueError):
            raise ValueError(f"`tf_bounds` must be a pair (lower, upper) of numbers; got {tf_bounds!r}.") from None
        if np.isnan(lo) or np.isnan(hi) or not lo < hi or hi <= 0:
            raise ValueError(f"`tf_bounds` must have lower < upper and upper > 0; got {tf_bounds!r}.")
        above, below = np.isfinite(hi), np.isfinite(lo) and lo > 0
        if not (above or below):
            return
        as_array = lambda v: np.asarray(v, dtype=np.float64)  # (arrays: they have derivatives)
        self.terminal_inequality = _TimeBounds(
            self.terminal_inequality, as_array(lo) if below else None, as_array(hi) if above else None
        )
        self.terminal_inequality_names = (
            self.terminal_inequality_names
            + (("tf lower bound",) if below else ())
            + (("tf upper bound",) if above else ())
        )

    def _add_running_cost(self, running_cost: Callable):
        """The Mayer form: the accumulated cost as the last state (see the module docs);
        `running_cost` is `self.running_cost`, not None."""
        self.dynamics = _CostDynamics(self.dynamics, running_cost)
        self.objective = _CostObjective(self.objective)
        self.terminal = _OnUserState(self.terminal)
        if self.path is not None:
            self.path = _OnUserState(self.path)
        if self.terminal_inequality is not None:
            self.terminal_inequality = _OnUserState(self.terminal_inequality)
        self.x0 = jnp.append(self.x0, 0.0)
        self.state_names = (*self.state_names, "running cost")


def no_mayer_term(tf, xf, args):
    """G = 0: the default Mayer term of a problem with a running cost."""
    del xf, args
    return jnp.zeros((), jnp.result_type(tf, float))


class _CostDynamics(eqx.Module):
    """[f(t, x, u); L(t, x, u)] on the state (x, accumulated cost)."""

    dynamics: Callable
    running_cost: Callable

    def __call__(self, t, y, u, args):
        x = y[:-1]
        return jnp.concatenate([self.dynamics(t, x, u, args), jnp.reshape(self.running_cost(t, x, u, args), (1,))])


class _CostObjective(eqx.Module):
    """G(tf, x(tf)) + the accumulated cost."""

    objective: Callable

    def __call__(self, tf, yf, args):
        return self.objective(tf, yf[:-1], args) + yf[-1]


class _OnUserState(eqx.Module):
    """A user function of (time, x, ...) called on the state without the accumulated cost."""

    fn: Callable

    def __call__(self, t, y, *rest):
        return self.fn(t, y[:-1], *rest)


class _StateBounds(eqx.Module):
    """The user's path constraints (if any), then x[above] - upper, then lower - x[below]."""

    path: Callable | None
    above: tuple[int, ...] = eqx.field(static=True)
    upper: jax.Array
    below: tuple[int, ...] = eqx.field(static=True)
    lower: jax.Array

    def __call__(self, t, x, u, args):
        own = [] if self.path is None else [jnp.asarray(self.path(t, x, u, args))]
        idx_hi, idx_lo = np.asarray(self.above, int), np.asarray(self.below, int)
        return jnp.concatenate([*own, x[idx_hi] - self.upper, self.lower - x[idx_lo]])


class _TimeBounds(eqx.Module):
    """The user's terminal inequalities (if any), then lower - tf and tf - upper (0-d float64
    arrays, so that a solve is differentiable in them and one compiled solver takes any
    values; read them as `Problem.tf_bounds`)."""

    terminal_inequality: Callable | None
    lower: np.ndarray | jax.Array | None = None
    upper: np.ndarray | jax.Array | None = None

    def __call__(self, tf, xf, args):
        rows = [] if self.terminal_inequality is None else [jnp.asarray(self.terminal_inequality(tf, xf, args))]
        rows += [] if self.lower is None else [jnp.reshape(self.lower - tf, (1,))]
        rows += [] if self.upper is None else [jnp.reshape(tf - self.upper, (1,))]
        return jnp.concatenate(rows)


def _bound(value, nu, name, what="num_controls"):
    """A bound as a float64 `(nu,)` array (a scalar applies to every channel or state)."""
    try:
        b = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a number or {nu} numbers; got {value!r}.") from None
    if b.ndim > 1 or (b.ndim == 1 and b.shape[0] not in (1, nu)):
        raise ValueError(f"`{name}` must be a scalar or have {nu} entries ({what}); got shape {b.shape}.")
    b = np.broadcast_to(b, (nu,))
    if np.any(np.isnan(b)):
        raise ValueError(f"`{name}` must not contain NaN; got {b}.")
    impossible = np.inf if name.endswith("lower") else -np.inf  # no value meets it: never "free"
    if np.any(b == impossible):
        raise ValueError(f"`{name}` must not contain {impossible} (no value satisfies it); got {b}.")
    return jnp.asarray(b)


def _names(value, name):
    """A tuple of str; a lone string is refused (it would become one name per character)."""
    if isinstance(value, str):
        raise ValueError(f"`{name}` must be a sequence of names, not one string; got {value!r} (write ({value!r},)).")
    names = tuple(value)
    if not all(isinstance(v, str) for v in names):
        raise ValueError(f"`{name}` must contain strings; got {names!r}.")
    repeated = sorted({v for v in names if names.count(v) > 1})
    if repeated:  # (results, reports and saved folders name each row: one would hide another)
        raise ValueError(f"`{name}` must name each row once; {repeated} repeat(s) in {names!r}.")
    return names


def check_bound_shapes(problem: Problem):
    """The arrays of the state bounds and `tf_bounds` (which `eqx.tree_at` may replace, to
    differentiate in them) keep their shapes: a state bound with more entries than bounded
    states was more path rows, silently (a SUCCESS, then NaN derivatives)."""
    fn, tf_fn, where = problem.path, problem.terminal_inequality, "problem.path"
    while isinstance(fn, _OnUserState):
        fn, where = fn.fn, where + ".fn"
    while isinstance(tf_fn, _OnUserState):
        tf_fn = tf_fn.fn
    wants = []
    if isinstance(fn, _StateBounds):
        for side, value, idx in (("upper", fn.upper, fn.above), ("lower", fn.lower, fn.below)):
            shown = f"({len(idx)},) (one per state with an {side} bound) or ()"
            wants.append((f"{where}.{side}", value, {(len(idx),), ()}, shown))
    if isinstance(tf_fn, _TimeBounds):
        for i, value in enumerate((tf_fn.lower, tf_fn.upper)):
            if value is not None:
                wants.append((f"problem.tf_bounds[{i}]", value, {(), (1,)}, "()"))
    for name, value, shapes, shown in wants:
        if np.shape(value) not in shapes:
            raise ValueError(f"`{name}` must have shape {shown}; got shape {np.shape(value)}.")
