"""`jt.enable_solve_cache` (issue 53): a script run again on an unchanged problem answers from
the exported program on disk without tracing the solve; a changed problem traces again."""

import dataclasses
import glob
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import gain_reach

import jaxtraj as jt

_SCRIPT = """
import json, sys
import numpy as np
import jaxtraj as jt
import jaxtraj._driver as driver
from jaxtraj._fingerprint import problem_fingerprint

folder, gain, x0 = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
jt.enable_compilation_cache(folder + "/xla")
assert jt.enable_solve_cache(folder + "/export")

calls = [0]  # the dynamics runs only when something traces it

def f(t, x, u, args):
    calls[0] += 1
    return gain * u

loops, run_loop = [0], driver.run_loop  # traces of the solver's loop

def counted(*a, **k):
    loops[0] += 1
    return run_loop(*a, **k)

driver.run_loop = counted
problem = jt.Problem(
    f, np.full(1, x0), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",), num_controls=1,
    running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0, name="gain",
)
control = problem.parametrize(jt.controls.PiecewiseLinear(4))
simulator = jt.RK4(5)
start = calls[0]
sol = jt.solve(problem, control, np.zeros(control.num_params), simulator=simulator)
during = calls[0] - start
start = calls[0]
problem_fingerprint(problem, control, simulator)
print(json.dumps({
    "during": during, "fingerprint": calls[0] - start, "loops": loops[0], "status": jt.status_name(sol.status),
    "params": sol.params.tobytes().hex(), "objective": float(sol.objective).hex(), "steps": int(sol.steps),
}))
"""


def _run(folder, gain, x0=0.0):
    proc = subprocess.run(
        [sys.executable, "-c", _SCRIPT, str(folder), str(gain), str(x0)],
        capture_output=True,
        text=True,
        env=dict(os.environ),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # (six new processes, each tracing or loading the solve: ~35 s)
def test_rerun_answers_from_disk_and_a_changed_problem_traces_again(tmp_path):
    """A second process on an unchanged problem traces neither the solve's loop nor (beyond the
    fingerprint) the dynamics, and answers bit for bit; a new initial state is an input of the
    same program; another constant in the dynamics traces again; a truncated or scrambled
    entry is ignored."""
    first = _run(tmp_path, 2.0)
    assert first["status"] == "SUCCESS"
    assert first["loops"] == 1 and first["during"] > first["fingerprint"]  # traced and exported
    assert len(glob.glob(str(tmp_path / "export" / "solve-*.jaxexport"))) == 1

    again = _run(tmp_path, 2.0)
    assert again["loops"] == 0  # the solve was not traced
    assert again["during"] == again["fingerprint"]  # the dynamics was traced by the key only
    for field in ("params", "objective", "steps", "status"):
        assert again[field] == first[field]  # bit for bit

    start = _run(tmp_path, 2.0, x0=0.5)  # another initial state: the program's input, not part of it
    assert start["loops"] == 0 and start["during"] == start["fingerprint"]
    assert start["status"] == "SUCCESS" and start["params"] != first["params"]
    assert len(glob.glob(str(tmp_path / "export" / "solve-*.jaxexport"))) == 1

    changed = _run(tmp_path, 3.0)  # another constant in the dynamics
    assert changed["loops"] == 1 and changed["during"] > changed["fingerprint"]
    assert changed["params"] != first["params"]
    assert len(glob.glob(str(tmp_path / "export" / "solve-*.jaxexport"))) == 2

    entries = glob.glob(str(tmp_path / "export" / "solve-*.jaxexport"))
    for corrupt in (_truncate, _scramble_header):  # a corrupt entry is ignored: traced again, the same answer
        for entry in entries:
            corrupt(entry)
        after = _run(tmp_path, 2.0)
        assert after["loops"] == 1
        assert after["params"] == first["params"] and after["objective"] == first["objective"]


def _truncate(path):
    with open(path, "r+b") as f:
        f.truncate(2 * os.path.getsize(path) // 3)


def _scramble_header(path):
    with open(path, "r+b") as f:
        f.seek(40)
        f.write(b"garbage" * 10)


@pytest.mark.slow  # (the solve exported, its gradient twice: ~11 s)
def test_cached_solve_is_the_plain_solve_and_derivatives_take_the_plain_path(tmp_path):
    """In one process: the cached solve's every leaf equals the plain solve's; under `jax.grad`
    the ordinary, differentiable path runs (the same gradient, no entry written)."""

    def problem(gain):
        return jt.Problem(
            lambda t, x, u, args: args["gain"] * u, np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",),
            num_controls=1, running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0, args={"gain": gain},
        )  # fmt: skip

    control = problem(2.0).parametrize(jt.controls.PiecewiseLinear(4))
    a0, simulator = np.zeros(control.num_params), jt.RK4(5)
    solve = lambda gain: jt.solve(problem(gain), control, a0, simulator=simulator)
    grad = jax.grad(lambda gain: solve(gain).objective)
    plain, plain_grad = solve(jnp_float(2.0)), grad(jnp_float(2.0))
    try:
        assert jt.enable_solve_cache(tmp_path) == str(tmp_path)
        cached = solve(jnp_float(2.0))
        assert len(list(tmp_path.glob("solve-*.jaxexport"))) == 1
        same = jax.tree.map(lambda x, y: np.array_equal(x, y, equal_nan=True), plain, cached)
        assert all(jax.tree.leaves(same)) and type(cached.status) is type(plain.status)
        assert grad(jnp_float(2.0)) == plain_grad != 0.0  # (under grad: the differentiable path, no entry)
        assert len(list(tmp_path.glob("solve-*.jaxexport"))) == 1
    finally:
        jt.disable_solve_cache()


def jnp_float(x):
    return jnp.asarray(x, jnp.float64)


def _jitted_gain_problem(gain):
    G = jnp.array([gain])

    @jax.jit  # (a helper of the user's own: its closed-over constant is not printed in the jaxpr)
    def rhs(u):
        return G * u

    return jt.Problem(
        lambda t, x, u, args: rhs(u), np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",), num_controls=1,
        running_cost=lambda t, x, u, args: 0.5 * (u @ u), final_time=1.0,
    )  # fmt: skip


def test_problems_differing_only_in_a_jitted_helpers_constant_have_other_fingerprints():
    from jaxtraj._fingerprint import problem_fingerprint

    simulator = jt.RK4(5)
    two, four = _jitted_gain_problem(2.0), _jitted_gain_problem(4.0)
    control = two.parametrize(jt.controls.PiecewiseLinear(4))
    assert problem_fingerprint(two, control, simulator) != problem_fingerprint(four, control, simulator)
    assert problem_fingerprint(two, control, simulator) == problem_fingerprint(
        _jitted_gain_problem(2.0), control, simulator
    )


def test_problems_differing_only_in_a_jitted_helpers_constant_do_not_share_an_entry(tmp_path):
    """min 0.5 int u^2 subject to int gain u = 1: the objective is 0.5 / gain**2, cached or not."""
    try:
        assert jt.enable_solve_cache(tmp_path) == str(tmp_path)
        for gain in (2.0, 4.0):
            problem = _jitted_gain_problem(gain)
            control = problem.parametrize(jt.controls.PiecewiseLinear(4))
            sol = jt.solve(problem, control, np.zeros(control.num_params), simulator=jt.RK4(5))
            assert jt.status_name(sol.status) == "SUCCESS"
            assert float(sol.objective) == pytest.approx(0.5 / gain**2, rel=1e-9)
        assert len(list(tmp_path.glob("solve-*.jaxexport"))) == 2
    finally:
        jt.disable_solve_cache()


def test_an_entry_whose_program_constant_was_changed_on_disk_is_ignored(tmp_path):
    """A changed byte of the stored program (here the dynamics' gain 2.0 -> 3.0) that still
    deserializes and runs is caught by the entry's checksum: the solve traces again."""
    import struct

    problem, control = gain_reach()
    solve = lambda: jt.solve(problem, control, np.zeros(control.num_params), simulator=jt.RK4(5))
    try:
        jt.enable_solve_cache(tmp_path)
        assert float(solve().objective) == pytest.approx(0.125, rel=1e-9)
        (entry,) = tmp_path.glob("solve-*.jaxexport")
        data = entry.read_bytes()
        assert struct.pack("<d", 2.0) in data
        entry.write_bytes(data.replace(struct.pack("<d", 2.0), struct.pack("<d", 3.0)))
        jt.disable_solve_cache()
        jt.enable_solve_cache(tmp_path)  # (a new process: nothing in memory)
        assert float(solve().objective) == pytest.approx(0.125, rel=1e-9)
    finally:
        jt.disable_solve_cache()


@pytest.mark.parametrize("enable", [jt.enable_solve_cache, jt.enable_compilation_cache])
@pytest.mark.parametrize("kind", ["a file", "a path through a file", "empty", "a NUL byte"])
def test_a_folder_argument_that_is_no_folder_is_named_and_changes_nothing(enable, kind, tmp_path):
    """A file, a path through one, "" or a NUL byte returned None (a file, "") as if the system
    had refused the folder, or raised os' error naming no argument (NUL)."""
    (tmp_path / "file").write_text("x")
    folder = {"a file": tmp_path / "file", "a path through a file": tmp_path / "file" / "sub"}.get(
        kind, {"empty": "", "a NUL byte": "a\0b"}.get(kind)
    )
    before = jax.config.jax_compilation_cache_dir
    with pytest.raises(ValueError, match=r"^`folder` must be"):
        enable(folder)
    assert jax.config.jax_compilation_cache_dir == before
    assert (tmp_path / "file").read_text() == "x"


def test_a_new_nested_folder_is_created(tmp_path):
    try:
        folder = tmp_path / "a" / "b" / "c"
        assert jt.enable_solve_cache(folder) == str(folder) and folder.is_dir()
    finally:
        jt.disable_solve_cache()


def test_the_default_folder_is_inside_jaxtraj_cache_dir(tmp_path, monkeypatch):
    """The documented `$JAXTRAJ_CACHE_DIR/export`, not a sibling of the user's folder."""
    monkeypatch.setenv("JAXTRAJ_CACHE_DIR", str(tmp_path / "cache"))
    try:
        assert jt.enable_solve_cache() == str(tmp_path / "cache" / "export")
        assert not (tmp_path / "export").exists()
    finally:
        jt.disable_solve_cache()


def _bounded_problem(lower, upper):
    """x' = u, x(1) = 1, min 0.5 int (u - 3t)^2: the unbounded optimum u = 3t - 0.5 leaves
    [lower, upper] at both ends."""
    return jt.Problem(
        lambda t, x, u, args: u, np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",), num_controls=1,
        running_cost=lambda t, x, u, args: 0.5 * jnp.sum((u - 3.0 * t) ** 2), final_time=1.0,
        control_lower=np.array([lower]), control_upper=np.array([upper]),
    )  # fmt: skip


@pytest.mark.slow  # (four solves of a bounded problem, two exported: ~30 s)
def test_a_problem_with_control_bounds_is_cached_and_other_bounds_are_another_entry(tmp_path):
    """The key's stand-in arrays (zeros) were refused as changed control bounds: a bounded
    problem silently never used the cache. Now it does, with the plain solve's answer, and
    other bound values (static structure of the program) get their own entry."""
    bounds = ((-0.3, 1.5), (-0.2, 1.6))
    solve = lambda p: jt.solve(p, p.parametrize(jt.controls.PiecewiseLinear(6)), np.zeros(7), simulator=jt.RK4(5))
    plain = [float(solve(_bounded_problem(*b)).objective) for b in bounds]
    assert plain[0] != plain[1]
    try:
        jt.enable_solve_cache(tmp_path)
        for b, expected in zip(bounds, plain):
            sol = solve(_bounded_problem(*b))
            assert jt.status_name(sol.status) == "SUCCESS" and float(sol.objective) == expected
        assert len(list(tmp_path.glob("solve-*.jaxexport"))) == 2
    finally:
        jt.disable_solve_cache()


def test_a_failed_write_leaves_no_temporary_file_and_the_solve_goes_on(tmp_path, monkeypatch):
    """A full disk (here: the final rename refused) left a `.tmp-*` file behind per solve."""

    def refuse(*args, **kwargs):
        raise OSError(28, "No space left on device")

    problem, control = gain_reach()
    try:
        jt.enable_solve_cache(tmp_path)
        monkeypatch.setattr(os, "replace", refuse)
        sol = jt.solve(problem, control, np.zeros(control.num_params), simulator=jt.RK4(5))
        assert float(sol.objective) == pytest.approx(0.125, rel=1e-9)
        assert list(tmp_path.iterdir()) == []
    finally:
        jt.disable_solve_cache()


def _scaled_search(factor):
    """A user's own solver (the same class name for every factor): the objective times `factor`."""

    class Scaled(jt.KalmanSearch):
        def postprocess(self, problem, control, simulator, state):
            sol = super().postprocess(problem, control, simulator, state)
            return dataclasses.replace(sol, objective=sol.objective * factor)

    return Scaled()


def test_a_users_own_solver_class_is_not_cached(tmp_path):
    """The key saw a user's solver by its class name and fields: two of one name (or one edited
    between runs) shared an entry, and the second answered with the first one's program."""
    problem, control = gain_reach()
    try:
        jt.enable_solve_cache(tmp_path)
        for factor in (1.0, 2.0):
            sol = jt.solve(problem, control, np.zeros(control.num_params), _scaled_search(factor), simulator=jt.RK4(5))
            assert float(sol.objective) == pytest.approx(0.125 * factor, rel=1e-6)
        assert list(tmp_path.glob("solve-*.jaxexport")) == []
    finally:
        jt.disable_solve_cache()


@pytest.mark.slow  # (three augmented-Lagrangian solves, two exported: ~10 s)
def test_solvers_differing_only_in_an_array_tolerance_do_not_share_an_entry(tmp_path):
    """The key had the solver's arrays by dtype and shape only, but they are constants of the
    program: `ctol=jnp.asarray(1e-12)` answered with the program of `ctol=jnp.asarray(0.1)`
    (its steps, its constraint error 1e-6)."""
    problem = jt.Problem(
        lambda t, x, u, args: u + 0.5 * jnp.sin(3 * x), np.zeros(1), lambda tf, xf, args: xf - 1.0, ("x(1) = 1",),
        num_controls=1, running_cost=lambda t, x, u, args: 0.5 * (u @ u) + jnp.cos(u[0]), final_time=1.0,
    )  # fmt: skip
    control = problem.parametrize(jt.controls.PiecewiseLinear(4))
    solve = lambda ctol: jt.solve(
        problem, control, np.zeros(control.num_params), jt.AugmentedLagrangian(ctol=jnp.asarray(ctol)),
        simulator=jt.RK4(5),
    )  # fmt: skip
    plain = solve(1e-12)
    assert float(plain.max_constraint_error) < 1e-11
    try:
        jt.enable_solve_cache(tmp_path)
        assert float(solve(0.1).max_constraint_error) > 1e-8
        cached = solve(1e-12)
        assert int(cached.steps) == int(plain.steps) and float(cached.max_constraint_error) < 1e-11
    finally:
        jt.disable_solve_cache()


def test_a_default_folder_that_is_a_file_names_the_variable(tmp_path, monkeypatch):
    """No argument was given: the error names `$JAXTRAJ_CACHE_DIR`, not `folder`."""
    (tmp_path / "file").write_text("x")
    monkeypatch.setenv("JAXTRAJ_CACHE_DIR", str(tmp_path / "file"))
    with pytest.raises(ValueError, match=r"^The default folder \(`\$JAXTRAJ_CACHE_DIR`.* is a file"):
        jt.enable_solve_cache()
    assert (tmp_path / "file").read_text() == "x"


def _program_text(path):
    data = path.read_bytes()
    blob = data[len(b"JAXTRAJ-EXPORT\n") :].partition(b"\n")[2]
    return jax.export.deserialize(bytearray(blob)).mlir_module()


def test_a_program_exported_under_another_matmul_precision_is_not_served(tmp_path):
    """The key left out JAX's options: a solve under `jax.default_matmul_precision("highest")`
    was answered by the program exported under the default precision (and the other way
    round), in this process and from disk."""
    problem, control = gain_reach()
    solve = lambda: jt.solve(problem, control, np.zeros(control.num_params), simulator=jt.RK4(5))
    try:
        jt.enable_solve_cache(tmp_path)
        assert float(solve().objective) == pytest.approx(0.125, rel=1e-9)
        with jax.default_matmul_precision("highest"):
            assert float(solve().objective) == pytest.approx(0.125, rel=1e-9)
        entries = sorted(tmp_path.glob("solve-*.jaxexport"), key=os.path.getmtime)
        assert len(entries) == 2
        # (the default leaves most products' precision to the backend; "highest" names it on each)
        assert _program_text(entries[1]).count("HIGHEST") > _program_text(entries[0]).count("HIGHEST")
    finally:
        jt.disable_solve_cache()
