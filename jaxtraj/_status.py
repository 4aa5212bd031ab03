"""Status codes shared by simulation, sensitivities and every solver."""

import equinox as eqx


class Status(eqx.Enumeration):
    """Outcome of a simulation or a solve. Each item's value is the message a user reads.

    Compare with `==` (`sol.status == jt.Status.SUCCESS`); under `vmap` the comparison is
    element-wise. Combine with `Status.where(pred, a, b)`.
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


def status_name(status) -> str:
    """The name (e.g. "SUCCESS") of a concrete, unbatched `Status` item."""
    for name in STATUS_NAMES:
        if bool(status == getattr(Status, name)):
            return name
    raise ValueError(f"not a concrete jaxtraj Status: {status!r}")
