"""Fingerprints that are stable across Python processes: of a pytree's data, and of what a
problem computes (so that a resumed run, or a program kept on disk, is refused or recomputed
when the problem's functions change, not only when their names do)."""

import hashlib
import re

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import ClosedJaxpr, Jaxpr

from ._bounds import bound_rows
from ._sensitivity import path_values
from ._simulate import final_state

_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _update(h, leaf, *, functions: bool):
    if isinstance(leaf, (np.ndarray, jax.Array, np.generic)):
        arr = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"array {arr.dtype} {arr.shape}".encode() + arr.tobytes())
    elif callable(leaf) and hasattr(leaf, "__qualname__"):
        if functions:
            h.update(f"callable {getattr(leaf, '__module__', '?')}.{leaf.__qualname__}".encode())
    else:
        h.update(_ADDRESS.sub("", repr(leaf)).encode())


def fingerprint(tree) -> str:
    """SHA-256 of a pytree's structure and leaves: array leaves by dtype, shape and bytes;
    functions by module and qualified name; others by repr (memory addresses removed)."""
    leaves, treedef = jax.tree.flatten(tree)
    h = hashlib.sha256(_ADDRESS.sub("", str(treedef)).encode())
    for leaf in leaves:
        _update(h, leaf, functions=True)
    return h.hexdigest()


def static_fingerprint(tree) -> str:
    """`fingerprint` with functions left out (a problem's functions enter a key by what they
    compute: `problem_fingerprint`), and array leaves by dtype and shape only."""
    leaves, treedef = jax.tree.flatten(tree)
    h = hashlib.sha256(_ADDRESS.sub("", str(treedef)).encode())
    for leaf in leaves:
        if isinstance(leaf, (np.ndarray, jax.Array, np.generic)):
            h.update(f"array {leaf.dtype} {np.shape(leaf)} {getattr(leaf, 'weak_type', False)}".encode())
        else:
            _update(h, leaf, functions=False)
    return h.hexdigest()


def _nested_consts(jaxpr, seen=None):
    """The constants of the closed jaxprs nested in `jaxpr`'s equations (a `jax.jit` helper's,
    a `cond` branch's): its printed form shows their types, not their values. Each nested
    jaxpr once (a helper called in many places is one object: its calls are in the printed
    form)."""
    seen = set() if seen is None else seen
    for eqn in jaxpr.eqns:
        for param in eqn.params.values():
            for sub in param if isinstance(param, tuple | list) else (param,):
                if isinstance(sub, ClosedJaxpr | Jaxpr) and id(sub) not in seen:
                    seen.add(id(sub))
                    if isinstance(sub, ClosedJaxpr):
                        yield from sub.consts
                    yield from _nested_consts(sub.jaxpr if isinstance(sub, ClosedJaxpr) else sub, seen)


def problem_fingerprint(problem, control, simulator) -> str:
    """SHA-256 of what `problem` computes under `control` and `simulator`: the jaxpr of the
    final state, path rows, objective, terminal equalities and inequalities and bound rows at
    parameters of the control's shape, together with their forward-mode derivatives (so a
    `jax.custom_jvp` rule is in it), and every array it closes over (`args`, `x0`, captured
    constants, those of a `jax.jit` helper included). Functions enter by what they compute,
    not by name: two lambdas with other bodies, or one factory closing over other constants,
    differ; the same file loaded again
    in another process, or the problem renamed (its `name`, state or constraint names), does
    not. An array's dtype or weak type counts (`jnp.array(1.0)` is weakly typed,
    `np.array(1.0)` is not: XLA compiles them differently). Not seen: a host callback's
    Python body (the jaxpr names it, it does not contain it)."""

    def values(a):
        if problem.path is None:
            xf, _ = final_state(problem, control, a, simulator)
            rows = ()
        else:
            xf, (_, rows, _) = path_values(problem, control, a, simulator)
        tf = control.tf(a)
        ends = [
            fn(tf, xf, problem.args)
            for fn in (problem.objective, problem.terminal, problem.terminal_inequality)
            if fn is not None
        ]
        bounds = bound_rows(problem, control, a)
        return xf, rows, ends, () if bounds is None else bounds[0]

    # NumPy arrays as JAX arrays (both are the same data to a solve, which jits them alike;
    # a NumPy array closed over would be inlined in the jaxpr, a JAX array a constant)
    problem = jax.tree.map(lambda x: jnp.asarray(x) if isinstance(x, np.ndarray | np.generic) else x, problem)
    a = jax.ShapeDtypeStruct((control.num_params,), jnp.float64)
    closed = jax.make_jaxpr(lambda a, t: jax.jvp(values, (a,), (t,)))(a, a)
    h = hashlib.sha256(_ADDRESS.sub("", str(closed.jaxpr)).encode())
    for const in (*closed.consts, *_nested_consts(closed.jaxpr)):
        _update(h, const, functions=False)
    return h.hexdigest()
