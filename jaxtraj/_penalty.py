"""The merit penalty's cap near feasibility, shared by KalmanSQP's globalizations (the trust
region and the line search; `TrustRegion.mu_max` and `LineSearch.mu_max` document the rule,
docs/solvers/kalman-sqp.md its history)."""

import equinox as eqx
import jax
import jax.numpy as jnp

from ._kkt import inequality_rows


def violation(E, C=None):
    """|E|^2/2 + |max(C, 0)|^2/2: what the merit's penalty term weighs."""
    return 0.5 * (E @ E) + (0.0 if C is None else 0.5 * jnp.sum(jnp.maximum(C, 0.0) ** 2))


def violation_of(ev):
    rows = inequality_rows(ev)
    return violation(ev.E, None if rows is None else rows[0])


def natural_scale(B, rows):
    """|B|_F / |rows|_F^2: the penalty at which mu rows^T rows weighs as much as the curvature
    B, invariant to the units of the objective, the constraints and the parameters."""
    return jnp.linalg.norm(B) / jnp.maximum(jnp.linalg.norm(rows) ** 2, 1e-300)


def far_from_feasible(ev, a, ratio):
    """The linearized constraints ask for a relative change of the parameters of at least
    `ratio`: |E| > ratio |H|_F |a|."""
    return jnp.linalg.norm(ev.E) > ratio * jnp.linalg.norm(ev.H) * jnp.linalg.norm(a)


class PenaltyCap(eqx.Module):
    """Where the penalty was last capped: the violation and the objective there, and whether
    a step has raised the penalty since."""

    violation: jax.Array
    objective: jax.Array
    raised: jax.Array

    @classmethod
    def none(cls):
        return cls(jnp.asarray(jnp.inf, jnp.float64), jnp.asarray(jnp.inf, jnp.float64), jnp.array(False))

    def carried(self, mu, natural, viol, G, eligible, mu_max, progress, ctol):
        """`(penalty carried to the next step, whether it was capped)`: at most `mu_max` x
        `natural` where `eligible`, once the violation `viol` has halved since the last cap
        or is below that of one row at `ctol` (a violation at round-off cannot halve: a
        least time capped at 2.5e-30 kept a penalty of 1e18, set where the Hessian was 1e16
        times larger, and crawled to MAX_ITERATIONS; issue 49), or where no step has raised
        the penalty since and the objective `G` has fallen by `progress` x (1 + |G|) since
        then (so that caps happen finitely often away from feasibility)."""
        progressed = ~self.raised & (G <= self.objective - progress * (1.0 + jnp.abs(self.objective)))
        halved = (viol <= 0.5 * self.violation) | (viol <= 0.5 * ctol**2)
        cap = eligible & (progressed | halved) & (mu > mu_max * natural)
        return jnp.where(cap, mu_max * natural, mu), cap

    def update(self, cap, viol, G, raised):
        """After a step that capped (`cap`) at (`viol`, `G`) or not; `raised`: whether the
        step raised the penalty above what it carried."""
        return PenaltyCap(
            jnp.where(cap, viol, self.violation),
            jnp.where(cap, G, self.objective),
            jnp.where(cap, raised, self.raised | raised),
        )
