"""Status codes shared by simulation, sensitivities and every solver."""

from typing import TYPE_CHECKING, cast

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np


class _Iterable(type(eqx.Enumeration)):
    """Equinox's enumeration metaclass, plus the item names in declaration order (`names`:
    the string attributes of the class body, the ones equinox makes items) and iteration
    over the items."""

    names: tuple[str, ...]  # (set by `__new__`)

    def __new__(mcs, name, bases, namespace, **kwargs):
        names = tuple(k for k, v in namespace.items() if isinstance(v, str) and not k.startswith("__"))
        cls = super().__new__(mcs, name, bases, namespace, **kwargs)
        type.__setattr__(cls, "names", names)
        return cls

    def __iter__(cls):
        return (getattr(cls, name) for name in cls.names)


class Status(eqx.Enumeration, metaclass=_Iterable):
    """Outcome of a simulation or a solve. Each item's value is the message a user reads.

    Compare with `==` (`sol.status == jt.Status.SUCCESS`); under `vmap` the comparison is
    element-wise. Combine with `Status.where(pred, a, b)`. `list(jt.Status)` gives the items,
    `len(jt.Status)` their number. The status of a batched result (`jt.solve_batch`,
    `jax.vmap` of a solve) indexes and iterates along its starts like the result itself:
    `sols.status[i]`, `sols.status[mask]`, `for s in sols.status` (`as_indexable`).
    """

    SUCCESS = ""
    MAX_ITERATIONS = "Reached the iteration limit before the convergence tests were met."
    STALLED = "The search could not make progress (repeated rejected steps)."
    NONFINITE = "A non-finite value appeared in the states, parameters or derivatives."
    SIMULATION_FAILED = "The adaptive integrator failed (step limit or step-size underflow)."
    CONSTRAINT_STATIONARY = (
        "The constraint error stopped decreasing while still above tolerance "
        "(a stationary point of the constraint norm)."
    )
    DIVERGED = (
        "The parameters or the objective grew past 1e20 without success "
        "(the problem may be unbounded below, or the search left the region where it is defined)."
    )


#: |G| or a parameter beyond this ends a solve as DIVERGED unless it succeeded (IPOPT's
#: `diverging_iterates_tol`, 1e20): without it an unbounded problem ends STALLED or at the
#: step limit with numbers like -1e305.
DIVERGENCE = 1e20


def diverged(G, a):
    """Whether the objective `G` or a parameter of `a` is beyond `DIVERGENCE` in magnitude."""
    return (jnp.abs(G) > DIVERGENCE) | (jnp.max(jnp.abs(a)) > DIVERGENCE)


def without_point(status, iterations):
    """Whether a solve ended NONFINITE before its first accepted step: it has no finite point,
    so its point values (objective, constraint errors) are reported as NaN, not as the zeros
    of a placeholder evaluation."""
    return (status == Status.NONFINITE) & (iterations == 0)


def failed(status):
    """The status of an evaluation found unusable: its own failure, or NONFINITE where the
    integration succeeded but a value derived from it (merit, multipliers) is not finite."""
    return Status.where(status == Status.SUCCESS, Status.NONFINITE, status)


if TYPE_CHECKING:  # (equinox declares its items to type checkers as members of an `enum.Enum`)
    from equinox._enum import EnumerationItem as _Item
else:
    _Item = type(Status.SUCCESS)  # equinox's EnumerationItem (not exported by name)


class _IndexableItem(_Item):
    """A `Status` item whose value may carry batch axes, indexed along the first one.

    Equinox's item has no `__getitem__`; this subclass keeps everything else (`==`,
    `Status.where`, `isinstance(x, jt.Status)`, the pytree layout), so a result's status
    can be indexed like the result. No `__len__`: an unbatched status must stay truthy-safe.
    """

    if TYPE_CHECKING:  # the dataclass's constructor (equinox declares a one-argument one to type checkers)

        def __init__(self, _value, _enumeration): ...

    def _batch_size(self, what: str) -> int:
        if jnp.ndim(self._value) == 0:
            raise TypeError(
                f"{what} needs a batched status (from jax.vmap of a solve or jt.solve_batch); this one is a "
                "single status."
            )
        return jnp.shape(self._value)[0]

    def __getitem__(self, index):
        n = self._batch_size("Indexing")
        if isinstance(index, int | np.integer) and not -n <= index < n:
            raise IndexError(f"start {index} out of range for a batch of {n}.")
        if isinstance(index, _Item):
            raise TypeError("index a status with integers, slices or boolean masks, not with a status.")
        return _IndexableItem(self._value[index], self._enumeration)

    def __iter__(self):
        for i in range(self._batch_size("Iteration")):
            yield self[i]


def as_indexable(status) -> Status:
    """`status` as an item that indexes along its batch axis (`sols.status[i]`): the
    converter of every result's `status` field. Anything else is returned unchanged (the
    field's own checks report it)."""
    if isinstance(status, _Item) and not isinstance(status, _IndexableItem):
        status = _IndexableItem(status._value, status._enumeration)
    # (an item of `Status` is one still: equinox's `isinstance` checks the item's enumeration)
    return cast(Status, status)


#: The item names in declaration order ("SUCCESS", "MAX_ITERATIONS", ...).
STATUS_NAMES = Status.names


def status_name(status):
    """The name (e.g. "SUCCESS") of a concrete `Status` item.

    For an unbatched status (`jt.solve`) a `str`. For a batched one (`jax.vmap` of a solve,
    `jt.solve_batch`) a NumPy array of names with the batch shape:
    `jt.status_name(sols.status)[i]` is start i's name and
    `jt.status_name(sols.status) == "SUCCESS"` a boolean mask; `jt.status_name(sols.status[i])`
    is the same name.

    **Raises:** `ValueError` for anything but a concrete `Status` item (e.g. inside `jit`).
    """
    if not isinstance(status, Status):
        raise ValueError(f"`status` must be a jaxtraj Status item (e.g. `sol.status`); got {status!r}.")
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(status)):
        raise ValueError(
            "`status` must be concrete: status_name cannot be used inside jit/vmap; compare with "
            "`status == jt.Status.SUCCESS` there."
        )
    masks = [np.asarray(status == getattr(Status, name)) for name in STATUS_NAMES]
    if masks[0].ndim == 0:
        for name, mask in zip(STATUS_NAMES, masks):
            if mask:
                return name
        raise ValueError(f"not a valid jaxtraj Status value: {status!r}")
    if not np.all(np.any(masks, axis=0)):
        raise ValueError(f"not a valid jaxtraj Status value: {status!r}")
    return np.select(masks, STATUS_NAMES, default="")
