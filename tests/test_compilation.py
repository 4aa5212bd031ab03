"""Compile once: XLA compilations of `jt.solve` counted from JAX's compile log (issue 21)."""

import contextlib
import logging

import jax
import numpy as np
from helpers import energy_problem

import jaxtraj as jt

SIM = jt.RK4(4)


@contextlib.contextmanager
def compilations():
    """The names of the programs XLA compiles inside the block (`jax_log_compiles`)."""
    names = []

    class Handler(logging.Handler):
        def emit(self, record):
            message = record.getMessage()
            if message.startswith("Finished XLA compilation of "):
                names.append(message.split()[4])

    handler, logger = Handler(), logging.getLogger("jax")
    logger.addHandler(handler)
    jax.config.update("jax_log_compiles", True)
    try:
        yield names
    finally:
        jax.config.update("jax_log_compiles", False)
        logger.removeHandler(handler)


def _solve(problem, control, a0):
    return jax.block_until_ready(jt.solve(problem, control, a0, simulator=SIM))


def test_new_starts_args_and_names_reuse_the_compiled_solver():
    """Once compiled for a problem's functions and a control family, the default solver runs
    new starts, new `args` (another fixed time T) and a problem of another name without any
    compilation; a new segment count compiles the solver once, plus at most three small
    programs of the input checks (the knots of the start, the segment Jacobian's basis)."""
    base = jt.problems.analytic.min_energy_double_integrator(1.0)
    ctrl = jt.controls.PiecewiseLinear(3)
    starts = np.asarray([ctrl.initial_guess(tf, 0.0, 0.0) for tf in (1.2, 0.9, 1.1)])
    renamed = energy_problem(
        state_names=base.state_names, control_names=base.control_names, name="the same problem, renamed"
    )
    first = _solve(base, ctrl, starts[0])
    with compilations() as names:
        second = _solve(base, ctrl, starts[1])
        longer = _solve(jt.problems.analytic.min_energy_double_integrator(2.0), ctrl, starts[2])
        _solve(renamed, ctrl, starts[0])
    assert names == []
    # the runs are real: each reaches its own optimum (energy 6 / T^3)
    np.testing.assert_allclose([float(first.objective), float(second.objective)], [6.0, 6.0], rtol=1e-9)
    np.testing.assert_allclose(float(longer.objective), 6.0 / 8.0, rtol=1e-9)
    four = jt.controls.PiecewiseLinear(4)
    with compilations() as names:
        _solve(base, four, np.asarray(four.initial_guess(1.2, 0.0, 0.0)))
    assert names.count("jit(run)") == 1 and len(names) <= 4, names
