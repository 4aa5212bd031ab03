"""Status codes shared by simulation, sensitivities and every solver."""

import equinox as eqx
import jax
import numpy as np


class _Iterable(type(eqx.Enumeration)):
    """Equinox's enumeration metaclass, plus iteration over the items in declaration order."""

    def __iter__(cls):
        return (getattr(cls, name) for name in STATUS_NAMES)


class Status(eqx.Enumeration, metaclass=_Iterable):
    """Outcome of a simulation or a solve. Each item's value is the message a user reads.

    Compare with `==` (`sol.status == jt.Status.SUCCESS`); under `vmap` the comparison is
    element-wise. Combine with `Status.where(pred, a, b)`. `list(jt.Status)` gives the items,
    `len(jt.Status)` their number.
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


STATUS_NAMES = ("SUCCESS", "MAX_ITERATIONS", "STALLED", "NONFINITE", "SIMULATION_FAILED", "CONSTRAINT_STATIONARY")


def status_name(status):
    """The name (e.g. "SUCCESS") of a concrete `Status` item.

    For an unbatched status (`jt.solve`) a `str`. For a batched one (`jax.vmap` of a solve,
    `jt.solve_batch`) a NumPy array of names with the batch shape:
    `jt.status_name(sols.status)[i]` is start i's name and
    `jt.status_name(sols.status) == "SUCCESS"` a boolean mask. (`sols.status` itself cannot
    be indexed; index the Solution instead: `jt.status_name(sols[i].status)`.)

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
