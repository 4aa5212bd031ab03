"""Compile once: XLA compilations of `jt.solve` counted from JAX's compile log (issue 21)."""

import contextlib
import logging
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
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


_RUN_TWICE = """
import jax, jaxtraj as jt
events = []
jax.monitoring.register_event_listener(lambda event, **kw: events.append(event))
folder = jt.enable_compilation_cache()
e = jt.problems.classic.get("lq")
s = jt.solve(e.problem, e.control, e.start, simulator=jt.RK4(10))
count = lambda tail: sum(name.endswith(tail) for name in events)
print(folder, count("/compile_requests_use_cache"), count("/cache_hits"), repr(float(s.objective)), jt.status_name(s.status))
"""


@pytest.mark.slow
def test_compilation_cache_serves_a_new_process(tmp_path):
    """`jt.enable_compilation_cache()` (folder from $JAXTRAJ_CACHE_DIR): a second process running
    the same solve loads every program it compiles from disk (JAX's cache-hit events), with the
    same result; the first found none there."""
    env = {
        **os.environ,
        "JAXTRAJ_CACHE_DIR": str(tmp_path / "cache"),
        "PYTHONPATH": os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    }
    runs = []
    for _ in range(2):
        r = subprocess.run([sys.executable, "-c", _RUN_TWICE], capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr
        runs.append(r.stdout.split())
    (folder, requests, hits, objective, status), again = runs
    assert folder == str(tmp_path / "cache") and os.listdir(folder)
    assert int(requests) >= 1 and int(hits) == 0
    assert again[0] == folder and again[1] == requests and again[2] == requests  # every program from disk
    assert again[3:] == [objective, status] and status == "SUCCESS"
