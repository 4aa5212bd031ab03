"""End-to-end tests of the command line: one full run in a subprocess (`python -m jaxtraj`: the
entry point, the figures, the files that load back), the others in this process through the
same `main` (`run_here`; a subprocess costs ~4 s of start-up and compiles anew)."""

import json
import os
import subprocess
import sys

import jax
import matplotlib.image
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import jaxtraj as jt
from jaxtraj import _cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(*args, tmp_path, env=()):
    env = {**os.environ, "JAXTRAJ_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": ROOT, **dict(env)}
    return subprocess.run(
        [sys.executable, "-m", "jaxtraj", *args], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600
    )


#: what the command may change in this process's JAX configuration (its compilation cache)
_CACHE_OPTIONS = (
    "jax_compilation_cache_dir",
    "jax_persistent_cache_min_compile_time_secs",
    "jax_persistent_cache_min_entry_size_bytes",
)


@pytest.fixture
def run_here(tmp_path, monkeypatch, capsys):
    """`run` in this process, through the same `main` as `python -m jaxtraj` (a subprocess
    costs ~4 s of start-up); the command changes nothing else of the process's state."""

    def call(*args):
        monkeypatch.chdir(tmp_path)
        monkeypatch.setenv("JAXTRAJ_CACHE_DIR", str(tmp_path / "cache"))
        saved = {name: getattr(jax.config, name) for name in _CACHE_OPTIONS}
        capsys.readouterr()
        try:
            code = _cli.main(list(args))
        finally:
            for name, value in saved.items():
                jax.config.update(name, value)
        out = capsys.readouterr()
        return subprocess.CompletedProcess(args, code, out.out, out.err)

    return call


@pytest.mark.slow
def test_solve_writes_results_that_load_back(tmp_path):
    out = tmp_path / "case4"
    r = run("solve", "earth-mars", "--case", "4", "--steps", "40", "--out", str(out), tmp_path=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "SUCCESS" in r.stdout and "radial velocity" in r.stdout
    assert "step " in r.stdout and "max|E|" in r.stdout  # progress lines from the compiled loop
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "SUCCESS"
    # the case-4 optimum (RK4 with 40 steps per segment is within 1e-6 of the 100-step one)
    assert abs(summary["tf"] - 3.32488832) < 1e-5
    assert set(summary["constraints"]) == {"radial velocity", "radius", "tangential velocity"}
    assert summary["max_constraint_error"] <= 1e-8
    assert summary["inputs"]["rk4_steps"] == 40 and "jax" in summary["inputs"]["versions"]
    with np.load(out / "arrays.npz") as data:
        assert data["x"].shape[1] == 3 and data["t"].shape[0] == data["u"].shape[0]
    for name in ("solution.png", "histories.png", "convergence.png", "orbit.png"):
        image = matplotlib.image.imread(out / name)
        assert image.ndim == 3 and min(image.shape[:2]) > 300 and float(np.var(image)) > 0, name
    sol, traj, _ = jt.io.load(out)
    np.testing.assert_array_equal(np.asarray(sol.params), np.asarray(summary["params"]))
    assert sol.status == jt.Status.SUCCESS
    assert np.asarray(traj.x).shape[1] == 3


def test_problems_lists_the_problems(run_here):
    r = run_here("problems")
    assert r.returncode == 0 and "linear:K" in r.stdout and "file.py:function" in r.stdout
    for name in ("earth-mars", "min-energy", "solar-sail", "attitude", *jt.problems.classic.names()):
        assert name in r.stdout


@pytest.mark.slow
def test_solve_runs_a_gallery_problem(tmp_path, run_here):
    out = tmp_path / "max-range"
    r = run_here("solve", "max-range", "--steps", "40", "--out", str(out))
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    # u = +1 then -1 over [0, 1] from rest: x(1) = 1/4 (the objective is -x(1))
    assert summary["status"] == "SUCCESS" and abs(summary["objective"] + 0.25) < 1e-9


USER_PROBLEM = """
import jax.numpy as jnp
import jaxtraj as jt


def plane():
    # rest to rest in the plane in time 1, min 1/2 int |u|^2: J* = 6 |(1, 2)|^2 = 30
    return jt.Problem(
        lambda t, x, u, args: jnp.concatenate([x[2:], u]),
        [0.0, 0.0, 0.0, 0.0],
        lambda tf, xf, args: jnp.concatenate([xf - jnp.array([1.0, 2.0, 0.0, 0.0]), jnp.array([tf - 1.0])]),
        ("x", "y", "vx", "vy", "tf"),
        num_controls=2,
        running_cost=lambda t, x, u, args: 0.5 * jnp.sum(u**2),
        name="plane",
    )


def broken():
    raise RuntimeError("bad model")


class Stop(BaseException):
    pass


def stops():
    raise Stop("halt")
"""


def test_solve_runs_a_users_own_problem_from_a_file(tmp_path, run_here):
    (tmp_path / "mine.py").write_text(USER_PROBLEM)
    out = tmp_path / "plane"
    r = run_here("solve", "mine.py:plane", "--control", "linear:4:2", "--steps", "20", "--out", str(out))
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "SUCCESS" and summary["problem"] == "plane"
    assert abs(summary["objective"] - 30.0) < 1e-8
    assert summary["inputs"]["control"] == "PiecewiseLinear(segments=4, channels=2)"
    assert (out / "solution.png").exists()
    r = run_here("solve", "mine.py:broken", "--out", str(out))
    assert r.returncode == 2 and r.stderr.strip() == "jaxtraj: error: mine.py:broken raised RuntimeError: bad model"
    r = run_here("solve", "mine.py:stops", "--out", str(out))  # a BaseException of the user's: a traceback before
    assert r.returncode == 2 and r.stderr.strip() == "jaxtraj: error: mine.py:stops raised Stop: halt"
    r = run_here("solve", "mine.py:plane", "--tf", "-2", "--out", str(out))
    assert (
        r.returncode == 2 and r.stderr.strip() == "jaxtraj: error: --tf -2: `tf` must be a finite number > 0; got -2.0."
    )


_REACH_FILE = """
import jax.numpy as jnp
import jaxtraj as jt

TARGET = {target}


def reach():
    # x'' = u from rest to (TARGET, 0) in time 1, min int u^2 / 2: J* = 6 TARGET^2
    return jt.Problem(
        lambda t, x, u, args: jnp.stack([x[1], u[0]]),
        jnp.zeros(2),
        lambda tf, xf, args: xf - jnp.array([TARGET, 0.0]),
        ("x", "v"),
        num_controls=1,
        running_cost=lambda t, x, u, args: 0.5 * u[0] ** 2,
        final_time=1.0,
    )
"""


@pytest.mark.slow
def test_resume_of_a_users_problem_file(tmp_path, run_here):
    """Issue 51: --resume of `file.py:function` is accepted in a new process (the module's
    name no longer follows Python's salted `hash`) and refused once a module constant of
    the file has changed (the problem is fingerprinted by what it computes)."""
    mine = tmp_path / "mine.py"
    mine.write_text(_REACH_FILE.format(target="1.0"))
    argv = ("solve", "mine.py:reach", "--control", "linear:2", "--steps", "4", "--starts", "2", "--no-plot")
    argv += ("--out", str(tmp_path / "o"))
    r = run_here(*argv)
    assert r.returncode == 0, r.stderr
    mine.write_text(_REACH_FILE.format(target="1.5"))
    r = run_here(*argv, "--resume")
    assert r.returncode == 2 and "different inputs (problem changed)" in r.stderr, r.stderr
    mine.write_text(_REACH_FILE.format(target="1.0"))
    r = run(*argv, "--resume", tmp_path=tmp_path, env={"PYTHONHASHSEED": "12345"})
    assert r.returncode == 0 and "2/2 chunk(s) already done" in r.stderr, r.stderr
    assert abs(json.loads((tmp_path / "o" / "summary.json").read_text())["objective"] - 6.0) < 1e-9


_ODD_FILE = """
import sys
import jax.numpy as jnp
import jaxtraj as jt


def base(**kw):
    return jt.Problem(lambda t, x, u, args: jnp.stack([x[1], u[0]]), jnp.zeros(2),
                      lambda tf, xf, args: xf - jnp.array([1.0, 0.0]), ("x", "v"), num_controls=1, **kw)


def text_start():
    p = base()
    return p, p.parametrize(jt.controls.PiecewiseLinear(2)), "hello"


def complex_dynamics():
    return jt.Problem(lambda t, x, u, args: jnp.stack([x[1], u[0]]).astype(jnp.complex128) * (1 + 1j), jnp.zeros(2),
                      lambda tf, xf, args: xf - jnp.array([1.0, 0.0]), ("x", "v"), num_controls=1)


def bounded():
    return base(control_lower=[-1.0], control_upper=[1.0])


def fixed_time():
    return base(running_cost=lambda t, x, u, a: u[0] ** 2, final_time=1.0)


def leaves():
    sys.exit(0)
"""


def test_a_spline_on_a_fixed_final_time_solves(tmp_path, run_here):
    """`--control spline:...` on a problem with a fixed final time was refused with advice,
    `SaturatedSpline(free_durations=False)`, that no spec can express (issue 51, third
    audit): the CLI makes that spline. x'' = u from rest to (1, 0) in time 1, min int u^2:
    J* = 12 (u = 6 - 12 t, within the spline's +-10, linear: exact for degree 1)."""
    (tmp_path / "odd.py").write_text(_ODD_FILE)
    out = tmp_path / "o"
    r = run_here(
        "solve", "odd.py:fixed_time", "--control", "spline:4:1:-10:10", "--steps", "4", "--no-plot", "--out", str(out)
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "SUCCESS" and abs(summary["objective"] - 12.0) < 1e-6
    assert "free_durations=False" in summary["inputs"]["control"]


@pytest.mark.parametrize(
    "args, message",
    [
        (("odd.py:text_start",), "odd.py:text_start: `a` must be a real numeric array"),
        (("odd.py:complex_dynamics",), "must return real numbers; got dtype complex128"),
        (("odd.py:bounded", "--control", "parabolic:3"), "PiecewiseParabolic cannot take the problem's control_lower"),
        (("odd.py:bounded", "--control", "parabolic:3", "--starts", "2"), "so KalmanSQP cannot honor them"),
        (("odd.py:leaves",), "odd.py:leaves called sys.exit(0); nothing was solved"),
        (("odd.py:fixed_time", "--tf", "2"), "--tf: odd.py:fixed_time has a fixed final_time (1)"),
        (("odd.py:bounded", "--tf", "1e308"), "--tf 1e+308: `a` must be finite"),
        (("odd.py:bounded", "--resume"), "--resume continues a batch of starts (--starts N > 1)"),
        (("odd.py:bounded", "--seed", "3"), "--seed draws the extra starts"),
        (("sub/uses_helper.py:bounded", "--control", "parabolic:3"), "PiecewiseParabolic cannot take"),
        (("exits.py:f",), "importing 'exits.py' called sys.exit(0); nothing was solved"),
    ],
)
def test_a_users_odd_problem_gets_one_line(args, message, tmp_path, run_here):
    """Issue 51: what a user's problem file can get wrong is a one-line error, exit 2, before
    any work, and leaves no --out folder (it used to be tracebacks, and exit 0 for sys.exit)."""
    (tmp_path / "odd.py").write_text(_ODD_FILE)
    (tmp_path / "exits.py").write_text("import sys\nsys.exit(0)\n")
    (tmp_path / "sub").mkdir()  # a problem file that imports a module beside it
    (tmp_path / "sub" / "helper_mod.py").write_text(_ODD_FILE)
    (tmp_path / "sub" / "uses_helper.py").write_text("from helper_mod import bounded\n")
    r = run_here("solve", *args, "--no-plot", "--out", str(tmp_path / "o"))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert len(lines) == 1 and lines[0].startswith("jaxtraj: error:") and message in lines[0], r.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (("solve", "mars"), "unknown problem 'mars'"),
        (("solve", "earth-mars", "--control", "wiggly:3"), "unknown control 'wiggly'"),
        (("solve", "earth-mars", "--control", "linear:x"), "malformed control spec 'linear:x'"),
        (("solve", "earth-mars", "--starts", "0"), "--starts must be >= 1; got 0"),
        (("solve", "earth-mars", "--case", "9"), "--case must be in 1..7; got 9"),
        (("solve", "earth-mars", "--solver", "magic"), "unknown solver 'magic'"),
        (("frobnicate",), "invalid choice"),
        (("solve", "earth-mars", "--starts", "2000000000"), "--starts must be <= 1,000,000; got 2,000,000,000"),
        (("solve", "earth-mars", "--control", "linear:100000"), "at most 1,000 segments; got 100,000"),
        (("solve", "earth-mars", "--max-steps", "10000000000"), "--max-steps must be <= 1,000,000"),
        (("solve", "earth-mars", "--control", ""), "--control must not be empty"),
        (("solve", "earth-mars", "--monte-carlo", "1"), "--monte-carlo must be 0 (none) or 2..1,000,000 runs; got 1"),
        (("solve", "earth-mars", "--monte-carlo", "1000000000"), "runs; got 1,000,000,000"),
        (("solve", "earth-mars", "--seed", str(2**70)), "--seed must be in 0..2**63 - 1; got 1180591620717411303424"),
        (("solve", "no_such_file.py:make"), "problem file 'no_such_file.py' not found"),
        (("solve", "no_such_module_xyz:make"), "importing 'no_such_module_xyz' failed: ModuleNotFoundError"),
        (("solve", "json:nothing"), "'json' has no function 'nothing'"),
        (("solve", "earth-mars", "--control", "linear:4:2.5"), "malformed control spec 'linear:4:2.5'"),
        (("solve", "earth-mars", "--control", "linear:4:2"), "2 channel(s) but `problem` 'earth-mars'"),
        # issue 51: a huge channel count reached NumPy (a traceback)
        (
            ("solve", "min-energy", "--control", f"linear:3:{2**70}"),
            f"--control 'linear:3:{2**70}': at most 1,000 channels",
        ),
        (("solve", "min-energy", "--control", "constant:3:1001"), "at most 1,000 channels; got 1,001"),
    ],
)
def test_bad_input_gives_one_line_error(args, message, tmp_path, run_here):
    r = run_here(*args, "--out", str(tmp_path / "o")) if args[0] == "solve" else run_here(*args)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxtraj: error:") and message in lines[0], r.stderr
    assert not (tmp_path / "o").exists()  # a failed run leaves no (empty) --out folder behind


def test_empty_out_is_refused(run_here):
    r = run_here("solve", "earth-mars", "--out", "")
    assert r.returncode == 2 and r.stderr.strip() == "jaxtraj: error: --out must not be empty", r.stderr


def test_a_problem_file_that_is_a_folder_is_named_so(tmp_path, run_here):
    """(It was reported "not found", though it is there: issue 51's third audit.)"""
    (tmp_path / "p.py").mkdir()
    r = run_here("solve", f"{tmp_path / 'p.py'}:make", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == f"jaxtraj: error: problem file '{tmp_path / 'p.py'}' is a folder, not a file", r.stderr


def test_unwritable_out(tmp_path, run_here):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = run_here("solve", "earth-mars", "--out", str(blocker / "sub"))
    assert r.returncode == 2 and "cannot write to --out" in r.stderr and "Traceback" not in r.stderr


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "x.json"

    def failing(f):
        f.write(b"partial")
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        jt.io.atomic_write(str(target), failing)
    assert not target.exists() and list(tmp_path.iterdir()) == []


def test_multistart_batch_reports_progress_and_best(tmp_path, run_here):
    out = tmp_path / "batch"
    r = run_here(
        "solve",
        "min-energy",
        "--control",
        "linear:2",
        "--starts",
        "3",
        "--seed",
        "2",
        "--steps",
        "4",
        "--no-plot",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    assert "solve_batch: 3/3 starts" in r.stderr and "3 / 3 starts successful" in r.stdout
    assert sorted(p.name for p in (out / "batch").iterdir()) == [
        "chunk_00000.npz",
        "chunk_00001.npz",
        "chunk_00002.npz",
        "manifest.json",
    ]
    again = run_here(
        "solve",
        "min-energy",
        "--control",
        "linear:2",
        "--starts",
        "3",
        "--seed",
        "2",
        "--steps",
        "4",
        "--no-plot",
        "--out",
        str(out),
        "--resume",
    )
    assert again.returncode == 0 and "3/3 chunk(s) already done" in again.stderr, again.stderr
    assert abs(json.loads((out / "summary.json").read_text())["objective"] - 6.0) < 1e-6
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "SUCCESS" and summary["inputs"]["starts"] == 3
    assert abs(summary["objective"] - 6.0) < 1e-6  # analytic optimum of the min-energy problem
    # user errors about the batch folder are one line with exit 2, never a traceback
    same = ("solve", "min-energy", "--control", "linear:2", "--starts", "3", "--steps", "4", "--no-plot")
    cases = [
        ((*same, "--seed", "2", "--out", str(out)), "already holds a batch run (manifest.json); pass --resume"),
        ((*same, "--seed", "3", "--out", str(out), "--resume"), "was started with different inputs (a0s changed)"),
    ]
    (out / "batch" / "chunk_00001.npz").write_bytes(b"")
    cases.append(((*same, "--seed", "2", "--out", str(out), "--resume"), "chunk_00001.npz is damaged"))
    for argv, message in cases:
        r = run_here(*argv)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert lines[-1].startswith("jaxtraj: error:") and message in lines[-1], r.stderr
    # issue 51: a later single-start run into the same --out leaves nothing of the batch run
    # (its batch/ folder was kept beside the new summary: mixed results)
    (out / "notes.txt").write_text("mine")
    single = run_here("solve", "min-energy", "--control", "linear:2", "--steps", "4", "--no-plot", "--out", str(out))
    assert single.returncode == 0, single.stderr
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "arrays.npz",
        "notes.txt",
        "summary.json",
    ]
    assert json.loads((out / "summary.json").read_text())["inputs"]["starts"] == 1


@pytest.mark.parametrize("solver", ["sqp", "sqp-tr"])
def test_solve_with_kalman_sqp(tmp_path, run_here, solver):
    out = tmp_path / "sqp"
    r = run_here(
        "solve",
        "min-energy",
        "--control",
        "linear:3",
        "--solver",
        solver,
        "--steps",
        "4",
        "--no-plot",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "SUCCESS" and "KalmanSQP" in summary["inputs"]["solver"]
    assert abs(summary["objective"] - 6.0) < 1e-10 and summary["max_constraint_error"] < 1e-10


@pytest.mark.slow
def test_monte_carlo_after_a_solve(tmp_path, run_here):
    out = tmp_path / "mc"
    r = run_here(
        "solve",
        "earth-mars",
        "--case",
        "4",
        "--solver",
        "sqp",
        "--steps",
        "30",
        "--no-plot",
        "--monte-carlo",
        "300",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    mc = json.loads((out / "summary.json").read_text())["monte_carlo"]
    assert mc["runs"] == 300 and mc["open loop"]["failed"] == 0 and mc["closed loop"]["failed"] == 0
    assert mc["trace_ratio"] < 0.1  # the feedback shrinks the terminal dispersion (~0.01 on case 5)
    bad = run_here("solve", "min-energy", "--monte-carlo", "10", "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "earth-mars only" in bad.stderr


def test_a_locked_out_folder_is_refused(tmp_path, run_here):
    """Two runs cannot write one folder at once: while another run holds --out, the command
    stops at once with a one-line error."""
    out = tmp_path / "busy"
    with jt.io.folder_lock(str(out)):
        r = run_here("solve", "earth-mars", "--out", str(out))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert (
        r.stderr.strip()
        == f"jaxtraj: error: --out: {str(out)!r} is in use by another run (locked); wait for it to end or choose another folder."
    )


@pytest.mark.parametrize("where", ["figures", "chunks"])
def test_a_full_disk_is_one_line(where, tmp_path, run_here, monkeypatch):
    """Issue 51: the disk filling up while the figures or the batch chunks are written is a
    one-line error (it was a raw OSError traceback), and nothing half-written is left."""
    import jaxtraj.plot

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    if where == "figures":
        monkeypatch.setattr(jaxtraj.plot, "write_figures", full)
    else:
        real = jt.io.atomic_write
        monkeypatch.setattr(jt.io, "atomic_write", lambda path, fn: full() if "chunk_" in path else real(path, fn))
    out = tmp_path / "o"
    argv = ("solve", "min-energy", "--control", "linear:2", "--steps", "4", "--out", str(out))
    r = run_here(*argv, *(("--no-plot", "--starts", "2") if where == "chunks" else ()))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert lines[-1].startswith("jaxtraj: error: writing") and "No space left on device" in lines[-1], r.stderr
    assert not (out / "summary.json").exists()
    assert not list(out.rglob(".*")) if out.exists() else True  # no temporary file or folder


_OPTIONS = {  # (valid values, invalid values) for `solve min-energy`
    "--starts": (["1", "2"], ["0", "-1", "x", "2000000000", ""]),
    "--steps": (["4"], ["0", "abc", "100000", "4.5"]),
    "--max-steps": (["50"], ["0", "1e3", "10000000000"]),
    "--seed": (["0", "7"], ["-1", str(2**70), "s"]),
    "--monte-carlo": (["0"], ["1", "-3", "1000000000", "2"]),
    "--control": (
        ["linear:2"],
        ["", "wiggly:3", "linear:x", "linear:100000", "linear:2:3", "spline:1", f"linear:3:{2**70}"],
    ),
    "--tf": ([], ["-2", "nan", "1.0", "x"]),
    "--solver": (["sqp", "kalman"], ["magic", ""]),
}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_bad_option_is_one_line(data, tmp_path, run_here):
    """Issue 51, property: `solve` with any mix of options of which at least one is wrong
    ends with exit 2 and one line naming an option or value, never a traceback or a run."""
    names = sorted(_OPTIONS)
    bad = data.draw(st.sampled_from(names), label="wrong option")
    argv = [bad, data.draw(st.sampled_from(_OPTIONS[bad][1]), label="wrong value")]
    for name in data.draw(st.lists(st.sampled_from(names), unique=True, max_size=4), label="others"):
        if name != bad:
            argv += [name, data.draw(st.sampled_from(_OPTIONS[name][0] + _OPTIONS[name][1]), label=name)]
    r = run_here("solve", "min-energy", *argv, "--no-plot", "--out", str(tmp_path / "o"))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and "Traceback" not in r.stderr, (argv, r.stderr)
    assert len(lines) == 1 and lines[0].startswith("jaxtraj: error:"), (argv, r.stderr)
    assert not (tmp_path / "o").exists()


def test_default_result_folders_do_not_collide(tmp_path, monkeypatch):
    """Two runs started in the same second without --out get a folder each (the second was
    refused as "in use")."""
    monkeypatch.chdir(tmp_path)
    first, second = (_cli._new_folder(os.path.join("results", "p-20261206-120000")) for _ in range(2))
    assert (first, second) == (
        os.path.join("results", "p-20261206-120000"),
        os.path.join("results", "p-20261206-120000-2"),
    )
    assert sorted(os.listdir(tmp_path / "results")) == ["p-20261206-120000", "p-20261206-120000-2"]


@pytest.mark.slow
def test_a_reader_that_leaves_loses_no_result(tmp_path):
    """`jaxtraj solve ... | head -2`: the reader closes the pipe while the command still prints;
    the finished solve is written all the same, and the command ends with 141 (SIGPIPE's)."""
    env = {**os.environ, "JAXTRAJ_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": ROOT}
    out = tmp_path / "max-range"
    command = [sys.executable, "-m", "jaxtraj", "solve", "max-range", "--steps", "40", "--out", str(out), "--no-plot"]
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=tmp_path) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        proc.stdout.readline()
        proc.stdout.close()  # the reader leaves after the first line
        err = proc.stderr.read().decode()
        code = proc.wait(timeout=600)
    assert code == 141, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "SUCCESS" and abs(summary["objective"] + 0.25) < 1e-9


@pytest.mark.slow
def test_stdout_that_fails_loses_no_result(tmp_path, monkeypatch):
    """stdout on a full disk (`jaxtraj solve ... > file`): the result is written all the same
    and the command says so in one line, exit status 1 (it was a traceback; issue 51)."""

    class Full:
        def __init__(self, handle):
            self.handle = handle

        def write(self, text):
            raise OSError(28, "No space left on device")

        def flush(self):
            pass

        def fileno(self):
            return self.handle.fileno()

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("JAXTRAJ_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "max-range"
    saved = {name: getattr(jax.config, name) for name in _CACHE_OPTIONS}  # (as `run_here`)
    try:
        with open(os.devnull, "w") as sink:
            monkeypatch.setattr(sys, "stdout", Full(sink))
            code = _cli.main(["solve", "max-range", "--steps", "40", "--out", str(out), "--no-plot"])
    finally:
        for name, value in saved.items():
            jax.config.update(name, value)
    assert code == 1
    assert json.loads((out / "summary.json").read_text())["status"] == "SUCCESS"


@pytest.mark.slow
def test_a_slow_solve_is_not_run_twice_for_its_warm_time(tmp_path, run_here, monkeypatch):
    """The warm time came from solving again, which doubled a slow run (344 s for a 172 s
    solve; issue 51): past `WARM_RERUN_LIMIT` seconds the solve runs once."""
    calls = []
    solve = jt.solve
    monkeypatch.setattr(jt, "solve", lambda *a, **k: calls.append(1) or solve(*a, **k))
    monkeypatch.setattr(_cli, "WARM_RERUN_LIMIT", 0.0)
    r = run_here("solve", "max-range", "--steps", "40", "--out", str(tmp_path / "o"), "--no-plot")
    assert r.returncode == 0, r.stderr
    assert len(calls) == 1 and "not run (first call > 0 s)" in r.stdout


def test_a_large_monte_carlo_runs_in_chunks_with_progress(monkeypatch, capsys):
    """`--monte-carlo 1000000` ran for minutes without a word (issue 51, third audit): above
    `MONTE_CARLO_CHUNK` runs the study runs in 10 chunks of the same runs (`first_run`), a
    line each on stderr, with the statistics of one `jt.monte_carlo` call."""
    import types

    prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
    sim, errors, key = jt.RK4(5), jt.ThrustErrors(0.01, 1.0), jax.random.key(3)
    monkeypatch.setattr(_cli, "MONTE_CARLO_CHUNK", 8)
    capsys.readouterr()
    got = _cli._monte_carlo_runs("open loop", prob, ctrl, types.SimpleNamespace(params=a0), key, 25, None, errors, sim)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 9 and lines[-1].startswith("monte carlo, open loop: 25/25 runs (chunk 9/9)")
    one = jt.monte_carlo(prob, ctrl, a0, key, 25, execution=errors, simulator=sim)
    np.testing.assert_allclose(got["mean"], one.terminal_mean, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(got["covariance"], one.terminal_covariance, rtol=1e-9, atol=1e-18)
    assert got["failed"] == int(one.num_failed) == 0
    part = jt.monte_carlo(prob, ctrl, a0, key, 5, execution=errors, simulator=sim, first_run=20)
    np.testing.assert_allclose(part.terminal_errors, one.terminal_errors[20:], rtol=1e-10)  # (vmap round-off)
    with pytest.raises(ValueError, match="`first_run` must be an int >= 0"):
        jt.monte_carlo(prob, ctrl, a0, key, 5, execution=errors, simulator=sim, first_run=-1)
