"""solve_batch and multistart: equal to single solves start by start, independent of the
device count and of chunking, robust to bad starts, resumable after an interruption."""

import json
import os
import subprocess
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj._batch import (
    MultistartResult,
    files,
    multistart,
    random_starts,
    solve as batch_solve,
    solve_batch,
    starts as batch_starts,
)
from jaxtraj._fingerprint import fingerprint, problem_fingerprint

PROB, CTRL, A0 = jt.problems.earth_mars.thesis_case(4)
SIM = jt.RK4(20)
SOLVER = jt.KalmanSearch()
MAX_STEPS = 150
CHUNK = 4  # 7 starts -> chunks of 4 and 3 (+1 padding row): one compilation for both
NAN, HOPELESS = 2, 5  # a start with a NaN; one that cannot converge in MAX_STEPS
KW = dict(simulator=SIM, max_steps=MAX_STEPS, chunk_size=CHUNK)
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _starts():
    a = np.array(random_starts(PROB, CTRL, jax.random.key(0), 7, A0, spread=0.05))
    a[NAN, 3] = np.nan
    a[HOPELESS, :6] = 10 * np.asarray(A0)[:6]  # thrust angles 10x: MAX_ITERATIONS at 150 steps
    return a


STARTS = _starts()


def _leaves(sol):
    return [np.asarray(x) for x in jax.tree.leaves(sol)]


def _row(sol, i):
    return jax.tree.map(lambda x: x[i], sol)


def assert_same(got, want, tol=1e-12):
    """Every leaf (parameters, objective, history, status, counters) equal to `tol`. The
    lengths of *rejected* candidates (`history.step_norm`) carry the vmapped program's
    round-off (measured 2e-11 relative) without it reaching any accepted iterate: 1e-9."""
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(want)]
    for path, g, w in zip(paths, _leaves(got), _leaves(want), strict=True):
        assert g.shape == w.shape and g.dtype == w.dtype, path
        if np.issubdtype(w.dtype, np.floating):
            t = max(tol, 1e-9) if "step_norm" in path else tol
            np.testing.assert_allclose(g, w, rtol=t, atol=t, err_msg=path)
        else:
            np.testing.assert_array_equal(g, w, err_msg=path)


@pytest.fixture(scope="module")
def batch():
    """The reference batch: 7 starts, 2 chunks, one device, no folder."""
    return solve_batch(PROB, CTRL, STARTS, SOLVER, progress=False, **KW)


@pytest.fixture(scope="module")
def singles():
    return {
        i: jt.solve(PROB, CTRL, STARTS[i], SOLVER, simulator=SIM, max_steps=MAX_STEPS)
        for i in range(len(STARTS))
        if i != NAN
    }


def test_batch_equals_single_solves(batch, singles):
    assert batch.params.shape == (7, CTRL.num_params)
    assert batch.history.objective.shape == (7, MAX_STEPS)
    good = [i for i in singles if i != HOPELESS]
    for i in good:
        assert_same(_row(batch, i), singles[i])
    # The hopeless start wanders for 150 steps; batching changes the rounding of a few
    # operations (vectorized reductions) at 1e-16, which that walk amplifies (to 1e-8 in
    # the parameters, 1e-3 in its projected gradient): compare its outcome and first steps.
    hope, single = _row(batch, HOPELESS), singles[HOPELESS]
    assert jt.status_name(single.status) == jt.status_name(hope.status) == "MAX_ITERATIONS"
    assert int(single.steps) == int(hope.steps) == MAX_STEPS
    np.testing.assert_allclose(hope.history.objective[:20], single.history.objective[:20], rtol=1e-10)
    assert all(jt.status_name(singles[i].status) == "SUCCESS" for i in good)
    np.testing.assert_allclose(np.asarray(batch.objective)[good], 3.3248883, atol=1e-6)  # case 4's optimum
    assert np.max(np.asarray(batch.max_constraint_error)[good]) < 1e-8


@pytest.mark.slow
def test_bad_starts_fail_alone_in_a_vmapped_group(batch):
    # lanes=3: per chunk, three starts run vmapped and the next one takes the lane of the
    # first to finish (the NaN start 2 ends at once, start 3 replaces it; the hopeless start 5
    # runs beside 4 and 6); the reference batch ran every start on its own (lanes=1).
    grouped = solve_batch(PROB, CTRL, STARTS, SOLVER, progress=False, lanes=3, **KW)
    status = [jt.status_name(_row(grouped, i).status) for i in range(7)]
    assert status[NAN] == "NONFINITE"
    assert status[HOPELESS] == "MAX_ITERATIONS"
    assert int(grouped.steps[HOPELESS]) == MAX_STEPS and int(grouped.steps[NAN]) == 1
    assert [s for i, s in enumerate(status) if i not in (NAN, HOPELESS)] == ["SUCCESS"] * 5
    assert status == [jt.status_name(_row(batch, i).status) for i in range(7)]
    for i in range(7):
        if i not in (NAN, HOPELESS):
            assert_same(_row(grouped, i), _row(batch, i))
    nan_row = _row(grouped, NAN)
    assert np.all(np.isnan(np.asarray(nan_row.params)[[3]])) and int(nan_row.integrations) == 1


def test_progress_lines(capsys):
    solve_batch(PROB, CTRL, STARTS, SOLVER, progress=True, **KW)
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2
    # start 2 is the NaN one
    assert lines[0].startswith("solve_batch: 4/7 starts (chunk 1/2)") and lines[0].endswith("success 3/4")
    assert lines[1].startswith("solve_batch: 7/7 starts (chunk 2/2)") and lines[1].endswith("success 5/7")
    assert "solves/s" in lines[1]


_SHARDED = """
import json, sys
import jax, numpy as np
import jaxtraj as jt
from jaxtraj._batch import solve as batch_solve
from jaxtraj._fingerprint import fingerprint, problem_fingerprint
assert len(jax.devices()) == 4, jax.devices()
used = []
inner = batch_solve.solve_chunk
def spy(*args):
    out = inner(*args)
    used.append(len(out.params.sharding.device_set))
    return out
batch_solve.solve_chunk = spy
prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
starts = np.load(sys.argv[1])
sols = batch_solve.solve_batch(prob, ctrl, starts, jt.KalmanSearch(), simulator=jt.RK4(20), max_steps=150,
                          chunk_size=5, lanes=2, history=False, progress=False)
np.savez(sys.argv[2], *[np.asarray(x) for x in jax.tree.leaves(sols)])
print(json.dumps({"devices_per_chunk": used, "steps": np.asarray(sols.steps).tolist(),
                  "status": [jt.status_name(jax.tree.map(lambda x: x[i], sols).status) for i in range(7)],
                  "fingerprint": fingerprint((ctrl, jt.KalmanSearch(), jt.RK4(20), 150)),
                  "problem": problem_fingerprint(prob, ctrl, jt.RK4(20))}))
"""


@pytest.mark.slow
def test_sharded_over_4_host_devices_equals_unsharded(batch, tmp_path):
    np.save(tmp_path / "starts.npy", STARTS)
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4", "PYTHONPATH": REPO}
    proc = subprocess.run(
        [sys.executable, "-c", _SHARDED, str(tmp_path / "starts.npy"), str(tmp_path / "out.npz")],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["devices_per_chunk"] == [4, 4]  # 7 starts: chunks of 5 and 2, padded to 8 rows
    # the fingerprint used for resume checks is the same in another process
    assert report["fingerprint"] == fingerprint((CTRL, SOLVER, SIM, MAX_STEPS))
    assert report["problem"] == problem_fingerprint(PROB, CTRL, SIM)
    with np.load(tmp_path / "out.npz") as data:
        sharded = [data[f"arr_{i}"] for i in range(len(data.files))]
    # history=False there: the same solution with (N, 0) history fields
    rows = np.array([i for i in range(7) if i != HOPELESS])  # (the hopeless one: see above)
    for got, ref in zip(sharded, _leaves(batch), strict=True):
        if ref.ndim == 2 and ref.shape[1] == MAX_STEPS:
            assert got.shape == (7, 0)
        elif np.issubdtype(ref.dtype, np.floating):
            np.testing.assert_allclose(got[rows], ref[rows], rtol=1e-12, atol=1e-12)
        else:
            np.testing.assert_array_equal(got[rows], ref[rows])
    assert report["status"] == [jt.status_name(_row(batch, i).status) for i in range(7)]
    assert report["status"][HOPELESS] == "MAX_ITERATIONS" and report["status"][NAN] == "NONFINITE"
    assert report["steps"] == np.asarray(batch.steps).tolist()


class _Killed(BaseException):
    """Stands for the process being killed."""


def test_kill_and_resume(batch, tmp_path, monkeypatch, capsys):
    out = str(tmp_path / "run")
    write = jt.io.atomic_write

    def dies_writing_second_chunk(path, fn):
        if path.endswith("chunk_00001.npz"):

            def partial(f):
                f.write(b"PK\x03\x04 half a file")
                raise _Killed

            return write(path, partial)
        return write(path, fn)

    monkeypatch.setattr(jt.io, "atomic_write", dies_writing_second_chunk)
    with pytest.raises(_Killed):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=out, progress=False, **KW)
    assert sorted(os.listdir(out)) == ["chunk_00000.npz", "manifest.json"]  # no partial file
    monkeypatch.setattr(jt.io, "atomic_write", write)

    calls = []
    solve_chunk = batch_solve.solve_chunk
    monkeypatch.setattr(batch_solve, "solve_chunk", lambda *a: calls.append(1) or solve_chunk(*a))
    resumed = solve_batch(PROB, CTRL, STARTS, SOLVER, out=out, resume=True, **KW)
    assert len(calls) == 1  # only the missing chunk was solved
    err = capsys.readouterr().err
    assert "1/2 chunk(s) already done" in err and "chunk 2/2" in err and "chunk 1/2" not in err
    for got, want in zip(_leaves(resumed), _leaves(batch), strict=True):
        np.testing.assert_array_equal(got, want)  # exactly, NaN history entries included
    assert sorted(os.listdir(out)) == ["chunk_00000.npz", "chunk_00001.npz", "manifest.json"]

    again = solve_batch(PROB, CTRL, STARTS, SOLVER, out=out, resume=True, progress=False, **KW)
    assert len(calls) == 1  # a finished folder is read back, nothing is solved
    for got, want in zip(_leaves(again), _leaves(batch), strict=True):
        np.testing.assert_array_equal(got, want)


def test_resume_with_other_inputs_is_refused(tmp_path):
    out = str(tmp_path / "run")
    os.makedirs(out)
    manifest = {
        "format": files.FORMAT,
        "num_starts": 7,
        "chunk_size": CHUNK,
        "num_chunks": 2,
        "history": True,
        "a0s_sha256": fingerprint(STARTS),
        "problem_sha256": problem_fingerprint(PROB, CTRL, SIM),
        "control_sha256": fingerprint(CTRL),
        "solver_sha256": fingerprint(SOLVER),
        "simulator_sha256": fingerprint(SIM),
        "max_steps": MAX_STEPS,
    }
    with open(os.path.join(out, "manifest.json"), "w") as f:
        json.dump(manifest, f)
    other = STARTS.copy()
    other[0, 0] += 1e-9
    with pytest.raises(ValueError, match=r"different inputs \(a0s changed\)"):
        solve_batch(PROB, CTRL, other, SOLVER, out=out, resume=True, **KW)
    with pytest.raises(ValueError, match=r"different inputs \(solver changed\)"):
        solve_batch(PROB, CTRL, STARTS, jt.KalmanSearch(rho=0.5), out=out, resume=True, **KW)
    with pytest.raises(ValueError, match=r"different inputs \(max_steps: on disk 150, now 151\)"):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=out, resume=True, **{**KW, "max_steps": 151})
    with pytest.raises(ValueError, match=r"chunk_size: on disk 4, now 3"):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=out, resume=True, **{**KW, "chunk_size": 3})
    other_prob = jt.problems.earth_mars.problem(mu=1.01)
    with pytest.raises(ValueError, match=r"different inputs \(problem changed\)"):
        solve_batch(other_prob, CTRL, STARTS, SOLVER, out=out, resume=True, **KW)
    with pytest.raises(ValueError, match=r"different inputs \(problem changed; control changed; simulator changed\)"):
        other_ctrl = jt.controls.PiecewiseLinear(3, continuous=False)  # also 7 parameters
        solve_batch(PROB, other_ctrl, STARTS, SOLVER, out=out, resume=True, **{**KW, "simulator": jt.RK4(21)})
    with pytest.raises(ValueError, match=r"already holds a batch run"):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=out, **KW)
    # one run at a time in a folder; a file is not a folder
    with jt.io.folder_lock(out):
        with pytest.raises(ValueError, match=r"is in use by another run"):
            solve_batch(PROB, CTRL, STARTS, SOLVER, out=out, resume=True, **KW)
    (tmp_path / "a-file").write_text("x")
    with pytest.raises(ValueError, match=r"is a file, not a folder"):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=str(tmp_path / "a-file"), **KW)


def _reach(target, gain=None):
    """x'' = u from rest to (target, 0) in time 1, min int u^2 / 2: a new lambda each call;
    `gain` (a closed-over Python number) changes the dynamics' body."""
    dynamics = (
        (lambda t, x, u, args: jnp.stack([x[1], u[0]]))
        if gain is None
        else (lambda t, x, u, args: jnp.stack([x[1], gain * u[0]]))
    )
    return jt.Problem(
        dynamics,
        jnp.zeros(2),
        lambda tf, xf, args: xf - jnp.array([target, 0.0]),
        ("x", "v"),
        num_controls=1,
        running_cost=lambda t, x, u, args: 0.5 * u[0] ** 2,
        final_time=1.0,
    )


def test_resume_checks_what_the_problem_computes(tmp_path, monkeypatch):
    """Issue 51: the problem is fingerprinted by what it computes, not by its functions' names:
    a changed lambda body or captured constant is refused, the same problem rebuilt (new
    function objects) resumes."""
    out, sim = str(tmp_path / "run"), jt.RK4(4)
    ctrl = _reach(1.0).parametrize(jt.controls.PiecewiseLinear(2))
    starts = np.zeros((2, ctrl.num_params))
    kw = dict(simulator=sim, max_steps=30, chunk_size=1, progress=False)
    first = solve_batch(_reach(1.0), ctrl, starts, out=out, **kw)
    assert np.all(np.asarray(first.status == jt.Status.SUCCESS))
    np.testing.assert_allclose(first.objective, 6.0, rtol=1e-9)  # 6 target^2, PWL is exact here
    assert len({problem_fingerprint(p, ctrl, sim) for p in (_reach(1.0), _reach(1.5), _reach(1.0, 2.0))}) == 3
    for other in (_reach(1.5), _reach(1.0, gain=2.0)):  # a factory's constant, a lambda's body
        with pytest.raises(ValueError, match=r"different inputs \(problem changed\)"):
            solve_batch(other, ctrl, starts, out=out, resume=True, **kw)
    monkeypatch.setattr(batch_solve, "solve_chunk", lambda *a: pytest.fail("solved again"))
    again = solve_batch(_reach(1.0), ctrl, starts, out=out, resume=True, **kw)
    np.testing.assert_array_equal(again.params, first.params)


def test_bad_arguments():
    def call(a0s=STARTS, **kw):
        return solve_batch(PROB, CTRL, a0s, SOLVER, **{**KW, **kw})

    with pytest.raises(ValueError, match=r"`a0s` must have shape \(N, 7\).*got \(7,\)"):
        call(STARTS[0])
    with pytest.raises(ValueError, match=r"`a0s` must have shape \(N, 7\).*got \(7, 6\)"):
        call(STARTS[:, :6])
    with pytest.raises(ValueError, match=r"`a0s` must have shape.*got \(0, 7\)"):
        call(STARTS[:0])
    with pytest.raises(ValueError, match=r"`a0s` must be a real numeric array"):
        call(STARTS.astype(complex))
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match=r"`chunk_size` must be an int >= 1"):
            call(chunk_size=bad)
    with pytest.raises(ValueError, match=r"`devices`"):
        call(devices=[])
    with pytest.raises(ValueError, match=r"`devices`"):
        call(devices=["cpu"])
    with pytest.raises(ValueError, match=r"`resume=True` needs `out`"):
        call(resume=True)
    with pytest.raises(ValueError, match=r"`progress` must be True or False"):
        call(progress=1)
    with pytest.raises(ValueError, match=r"`max_steps`"):
        call(max_steps=0)
    with pytest.raises(ValueError, match=r"`around` is required"):
        multistart(PROB, CTRL, jax.random.key(0), 4)
    with pytest.raises(ValueError, match=r"`n` must be an int >= 1"):
        random_starts(PROB, CTRL, jax.random.key(0), 0, A0)
    with pytest.raises(ValueError, match=r"`key` must be a JAX PRNG key"):
        random_starts(PROB, CTRL, 0, 3, A0)
    with pytest.raises(ValueError, match=r"`spread` must be >= 0"):
        random_starts(PROB, CTRL, jax.random.key(0), 3, A0, spread=-0.1)
    # a spread of the wrong length was a NumPy broadcast error (issue 51)
    with pytest.raises(ValueError, match=r"`spread` must be a number or \d+ numbers"):
        random_starts(PROB, CTRL, jax.random.key(0), 3, A0, spread=[0.1, 0.2])
    # a huge spread overflowed in NumPy (a RuntimeWarning) before the error (issue 51)
    with pytest.raises(ValueError, match=r"could not generate valid starts \(not finite"):
        random_starts(PROB, CTRL, jax.random.key(0), 3, A0, spread=1e300)
    with pytest.raises(ValueError, match=r"`redraws` must be an int >= 0"):
        random_starts(PROB, CTRL, jax.random.key(0), 3, A0, redraws=-1)
    with pytest.raises(ValueError, match=r"`simulator`"):
        random_starts(PROB, CTRL, jax.random.key(0), 3, A0, simulator="rk4")


C = jt.controls


@pytest.mark.slow
@pytest.mark.parametrize(
    "ctrl",
    [
        C.PiecewiseLinear(4, continuous=True, free_times=True),
        C.PiecewiseLinear(3, continuous=False, free_times=True),
        C.PiecewiseParabolic(2),
        C.PiecewiseConstant(3, free_times=False),
        C.SaturatedSpline(4, 2, 0.0, 4.0),
    ],
    ids=lambda c: repr(c)[:60],
)
def test_random_starts_are_valid_and_bounded(ctrl):
    prob = jt.problems.earth_mars.problem()
    bounded = jt.Problem(
        prob.dynamics,
        prob.x0,
        prob.terminal,
        prob.constraint_names,
        args=prob.args,
        control_lower=[0.0],
        control_upper=[4.0],
    )
    around = ctrl.initial_guess(3.4, 0.0, 1.5 * np.pi)
    starts = np.asarray(random_starts(bounded, ctrl, jax.random.key(3), 40, around, spread=0.5))
    assert starts.shape == (40, ctrl.num_params) and starts.dtype == np.float64
    for a in starts:
        ctrl.validate(a)  # times increasing, tf > 0
    idx, _, _ = jt.controls.value_bounds(ctrl, bounded.control_lower, bounded.control_upper)
    assert idx.size > 0 and np.all(starts[:, idx] >= 0.0) and np.all(starts[:, idx] <= 4.0)
    assert np.any(starts[:, idx] == 0.0) and np.any(starts[:, idx] == 4.0)  # clipping happened
    t = list(ctrl.time_indices)
    assert np.std(starts[:, t], axis=0).min() > 0.01  # the times are perturbed too
    tf = np.asarray(jax.vmap(ctrl.tf)(jnp.asarray(starts)))
    assert 0.8 * 3.4 < np.median(tf) < 1.2 * 3.4
    again = np.asarray(random_starts(bounded, ctrl, jax.random.key(3), 40, around, spread=0.5))
    np.testing.assert_array_equal(starts, again)


def test_random_starts_replace_starts_that_do_not_integrate():
    """Goddard's rocket from its naive start with spread 0.5: a third of the draws give a
    non-finite trajectory (measured 10 of 32; their solves end NONFINITE at step 0). By
    default each is replaced by a usable draw of a further round, checked here by an
    independent integration (`jt.simulate`); the usable draws keep their places."""
    entry = jt.problems.classic.get("goddard")
    sim = jt.RK4(40)

    def integrates(a):
        traj = jt.simulate(entry.problem, entry.control, a, simulator=sim)
        return traj.status == jt.Status.SUCCESS and bool(np.all(np.isfinite(np.asarray(traj.xf))))

    draw = lambda **kw: np.asarray(
        random_starts(entry.problem, entry.control, jax.random.key(0), 32, entry.start, 0.5, simulator=sim, **kw)
    )
    raw, starts = draw(redraws=0), draw()
    ok_raw = np.array([integrates(a) for a in raw])
    assert 5 <= np.sum(~ok_raw) <= 16
    assert all(integrates(a) for a in starts)
    np.testing.assert_array_equal(starts[ok_raw], raw[ok_raw])
    assert not np.any(np.all(starts[~ok_raw][:, None] == raw[None], axis=2))  # new draws there
    np.testing.assert_array_equal(starts, draw())  # reproducible


def test_cluster_objectives():
    values = np.array([3.0, 3.0 + 1e-9, 4.1, 3.0 - 2e-9, 4.1 + 3e-7, 5.0])
    optima = batch_starts._cluster(values, np.arange(6) + 10, 1e-7)
    assert optima == ((3.0 - 2e-9, 3, 13), (4.1, 2, 12), (5.0, 1, 15))


def test_multistart_reproducible(batch):
    kw = dict(around=A0, spread=0.05, solver=SOLVER, progress=False, **KW)
    r1 = multistart(PROB, CTRL, jax.random.key(7), 7, **kw)
    r2 = multistart(PROB, CTRL, jax.random.key(7), 7, **kw)
    r3 = multistart(PROB, CTRL, jax.random.key(8), 7, **kw)
    assert isinstance(r1, MultistartResult)
    np.testing.assert_array_equal(r1.starts, r2.starts)
    for got, want in zip(_leaves(r1.solutions), _leaves(r2.solutions), strict=True):
        np.testing.assert_array_equal(got, want)
    assert not np.any(np.asarray(r1.starts) == np.asarray(r3.starts))
    for a in np.asarray(r1.starts):
        CTRL.validate(a)
    ok = np.asarray(r1.solutions.status == jt.Status.SUCCESS)
    np.testing.assert_array_equal(r1.success, ok)
    assert r1.success_rate == ok.mean() > 0.5
    obj = np.asarray(r1.solutions.objective)
    assert r1.best_index == int(np.flatnonzero(ok)[np.argmin(obj[ok])])
    assert float(r1.best.objective) == obj[ok].min()
    assert abs(float(r1.best.objective) - 3.3248883) < 1e-6
    assert sum(c for _, c, _ in r1.optima) == ok.sum()
    assert r1.optima[0][0] == obj[ok].min() and r1.optima[0][2] == r1.best_index
    text = str(r1)
    assert f"{ok.sum()} SUCCESS" in text and "| optimum |" in text and f"{r1.optima[0][0]:.10g}" in text
    assert r1.wall_time > 0 and r1.solves_per_second > 0


_HOST = """
import sys
import equinox as eqx
import jax
jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.distributed.initialize(f"localhost:{sys.argv[1]}", num_processes=2, process_id=int(sys.argv[2]))
import numpy as np
import jaxtraj as jt
from jaxtraj._batch import solve_batch
assert len(jax.devices()) == 2 and len(jax.local_devices()) == 1
prob, ctrl, a0 = jt.problems.earth_mars.thesis_case(4)
sols = solve_batch(prob, ctrl, np.load(sys.argv[3]), jt.KalmanSearch(), simulator=jt.RK4(20), max_steps=150,
                   chunk_size=4, out=sys.argv[4], progress=True)
np.savez(sys.argv[5], *[np.asarray(x) for x in jax.tree.leaves(sols)])
"""


@pytest.mark.slow
def test_two_hosts_with_jax_distributed(batch, tmp_path):
    """The multi-host recipe of docs/api/batch.md, with two processes on this machine: each
    returns the whole batch; only process 0 prints and writes the folder."""
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = str(s.getsockname()[1])
    np.save(tmp_path / "starts.npy", STARTS)
    env = {**os.environ, "PYTHONPATH": REPO}
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                _HOST,
                port,
                str(i),
                str(tmp_path / "starts.npy"),
                str(tmp_path / "run"),
                str(tmp_path / f"out{i}.npz"),
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    assert "solve_batch: 7/7 starts" in outs[0][1] and "solve_batch:" not in outs[1][1]
    assert sorted(os.listdir(tmp_path / "run")) == ["chunk_00000.npz", "chunk_00001.npz", "manifest.json"]
    for i in range(2):
        with np.load(tmp_path / f"out{i}.npz") as data:
            got = [data[f"arr_{j}"] for j in range(len(data.files))]
        for g, w in zip(got, _leaves(batch), strict=True):
            np.testing.assert_array_equal(g, w)


def _python(code, **env):
    """The stdout of `python -c code` in a process without the user's CPU and XLA settings
    (XLA_FLAGS, JAX_NUM_CPU_DEVICES, JAXTRAJ_*), plus `env`."""
    drop = ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES", "JAXTRAJ_CPU_DEVICES", "JAXTRAJ_NO_XLA_TUNING")
    base = {k: v for k, v in os.environ.items() if k not in drop}
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env={**base, **env, "PYTHONPATH": REPO},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def _cpu_devices(code, **env):
    return int(_python(code + "; print(len(jax.devices('cpu')))", **env).strip().split()[-1])


def test_import_changes_nothing_global_but_float64():
    """`import jaxtraj` leaves JAX's devices, its CPU device option and XLA_FLAGS as they were
    (issue 52: a user's own JAX program is not reshaped by an import); only float64 is on."""
    code = (
        "import os, jax; {} print(os.environ.get('XLA_FLAGS', '<unset>')); "
        "print(jax.config.jax_num_cpu_devices, jax.config.jax_enable_x64, len(jax.devices('cpu')))"
    )
    runs = [_python(code.format(imports)).split("\n")[:2] for imports in ("", "import jaxtraj;")]
    (flags_jax, line_jax), (flags_jt, line_jt) = runs
    assert flags_jt == flags_jax == "<unset>"
    assert line_jax.split()[::2] == line_jt.split()[::2] == ["-1", "1"]  # option unset, one device here
    assert (line_jax.split()[1], line_jt.split()[1]) == ("False", "True")


@pytest.mark.slow
def test_configure_cpu_splits_the_cpu_into_one_device_per_core_unless_the_user_chose():
    """`jt.configure_cpu()` gives JAX one CPU device per core (solve_batch and multistart then
    use every core); the user's own count wins: `devices=N`, JAX_NUM_CPU_DEVICES, XLA_FLAGS,
    JAXTRAJ_CPU_DEVICES. After a JAX computation it refuses, saying why, unless an earlier
    call set up what it asks for. (With jaxlib >=
    0.11, where KalmanSQP's sharded batch program crashed, one device unless asked.)"""
    import jaxlib

    auto = 1 if tuple(int(x) for x in jaxlib.__version__.split(".")[:2]) >= (0, 11) else len(os.sched_getaffinity(0))
    setup = "import jax, jaxtraj; jaxtraj.configure_cpu({})"
    assert _cpu_devices(setup.format("")) == auto
    assert _cpu_devices(setup.format(""), JAXTRAJ_CPU_DEVICES="2") == 2
    assert _cpu_devices(setup.format("3")) == 3
    assert _cpu_devices(setup.format(""), JAX_NUM_CPU_DEVICES="3") == 3
    assert _cpu_devices(setup.format(""), XLA_FLAGS="--xla_force_host_platform_device_count=3") == 3
    assert _cpu_devices(setup.format(""), JAXTRAJ_CPU_DEVICES="1") == 1
    late = (
        "import jax, jaxtraj; jax.numpy.ones(1)\ntry:\n jaxtraj.configure_cpu(2)\nexcept RuntimeError as e:\n print(e)"
    )
    assert _cpu_devices(late) == 1
    again = "import jax, jaxtraj; jaxtraj.configure_cpu(2); jax.numpy.ones(1); jaxtraj.configure_cpu(2)"
    assert _cpu_devices(again) == 2  # a second call that asks for what is set does nothing
    with pytest.raises(AssertionError, match="must run before the first JAX computation"):
        _cpu_devices("import jax, jaxtraj; jaxtraj.configure_cpu(2); jax.numpy.ones(1); jaxtraj.configure_cpu(3)")
    with pytest.raises(ValueError, match="devices must be a positive int"):
        jt.configure_cpu(0)


@pytest.mark.slow
def test_configure_cpu_sets_the_xla_cpu_options_xla_accepts():
    """`jt.configure_cpu()` raises XLA:CPU's small-while-loop threshold and, on a jaxlib that
    knows the flag (0.5.3 to 0.10), turns the fusion emitters off; XLA accepts both (it aborts
    on an unknown flag: jaxlib 0.11.2 does on this one). `xla_options=False` or
    JAXTRAJ_NO_XLA_TUNING=1 leave XLA_FLAGS alone; an option the user set stays theirs."""
    import jaxlib

    version = tuple(int(x) for x in jaxlib.__version__.split(".")[:3])
    legacy = (0, 5, 3) <= version < (0, 11)
    code = (
        "import os, jax.numpy as jnp, jaxtraj; jaxtraj.configure_cpu({}); "
        "print(float(jnp.sin(jnp.arange(3.0)).sum())); print(os.environ.get('XLA_FLAGS', ''))"
    )
    threshold = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000"
    cases = [  # (argument, extra environment, XLA_FLAGS expected after the call)
        ("", {}, [threshold] + ["--xla_cpu_use_fusion_emitters=false"] * legacy),
        ("xla_options=False", {}, []),
        ("", {"JAXTRAJ_NO_XLA_TUNING": "1"}, []),
    ]
    if legacy:  # the user's own value of the flag stays
        cases.append(
            ("", {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}, ["--xla_cpu_use_fusion_emitters=true", threshold])
        )
    for argument, extra, expected in cases:
        value, flags = _python(code.format(argument), **extra).split("\n")[:2]
        assert float(value) == pytest.approx(np.sin(1.0) + np.sin(2.0), rel=1e-15)
        assert flags.split() == expected


def test_resume_refuses_foreign_or_damaged_chunks(tmp_path):
    """Every chunk file carries its run's identity, its index and a checksum: a resume
    refuses, naming the file, a chunk copied over another, one left from another run (the
    manifest lost and the run restarted with other starts), a damaged one, and a damaged
    manifest."""
    import shutil

    out = tmp_path / "run"
    solve_batch(PROB, CTRL, STARTS, SOLVER, out=str(out), progress=False, **KW)
    assert sorted(os.listdir(out)) == ["chunk_00000.npz", "chunk_00001.npz", "manifest.json"]
    resumed = solve_batch(PROB, CTRL, STARTS, SOLVER, out=str(out), resume=True, progress=False, **KW)
    assert int(resumed.steps[0]) > 0  # the intact folder loads

    def damaged(name, damage):
        folder = tmp_path / name
        shutil.copytree(out, folder)
        damage(folder)
        return str(folder)

    copied = damaged("copied", lambda d: shutil.copy(d / "chunk_00000.npz", d / "chunk_00001.npz"))
    with pytest.raises(ValueError, match=r"chunk_00001\.npz holds chunk 0, not chunk 1"):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=copied, resume=True, progress=False, **KW)
    lost = damaged("lost", lambda d: (d / "manifest.json").unlink())
    with pytest.raises(ValueError, match=r"chunk_00000\.npz belongs to another run"):
        solve_batch(PROB, CTRL, STARTS * 1.01, SOLVER, out=lost, resume=True, progress=False, **KW)
    cut = damaged("cut", lambda d: (d / "chunk_00001.npz").write_bytes((d / "chunk_00001.npz").read_bytes()[:300]))
    with pytest.raises(ValueError, match=r"chunk_00001\.npz is damaged"):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=cut, resume=True, progress=False, **KW)
    bad_manifest = damaged("manifest", lambda d: (d / "manifest.json").write_text('{"format": '))
    with pytest.raises(ValueError, match=r"manifest\.json: damaged"):
        solve_batch(PROB, CTRL, STARTS, SOLVER, out=bad_manifest, resume=True, progress=False, **KW)


def test_only_where_runs_its_work_only_where_a_lane_needs_it():
    """`only_where` equals `lax.cond` lane by lane, and under `vmap` it skips `fn` in a
    step where no lane needs it. Measured by time against a second of work in `fn`, with a
    10x margin: `lax.cond` under vmap, or a loop whose invariant work XLA hoists out of it,
    pays it anyway (the line search's vmapped solves cost 9-14x their loop before, issue 21)."""
    from jax import lax

    from jaxtraj._driver import only_where

    def work(m):  # ~1 s of matrix products
        return lax.fori_loop(0, 300, lambda i, m: jnp.cos(m @ m / m.shape[0]), m)

    m = jax.random.normal(jax.random.key(0), (2, 300, 300))
    kept = jnp.zeros((2, 300, 300))
    batched = jax.jit(jax.vmap(lambda p, m, z: only_where(p, work, z, m)))
    conds = jax.jit(jax.vmap(lambda p, m, z: lax.cond(p, work, lambda m: z, m)))

    def timed(fn, *args):
        jax.block_until_ready(fn(*args))  # compiled
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        return time.perf_counter() - t, out

    t_one, out = timed(batched, jnp.array([True, False]), m, kept)
    np.testing.assert_array_equal(out, timed(conds, jnp.array([True, False]), m, kept)[1])
    assert np.all(np.asarray(out[1]) == 0.0) and np.any(np.asarray(out[0]) != 0.0)
    t_none, out = timed(batched, jnp.array([False, False]), m, kept)
    assert np.all(np.asarray(out) == 0.0)
    assert t_none < 0.1 * t_one, (t_none, t_one)


def test_only_where_loops_as_long_as_the_lanes_that_need_it():
    """Under `vmap`, a lane that does not need `fn` runs it on the inputs of one that does:
    a loop inside `fn` iterates as long as the lanes that need it (here 3 rounds), not as
    long as a lane's stale data would make it (1000 rounds; KalmanSearch's re-tuning loop
    on a finished lane: 5x the batch's step time on Bryson-Denham). `fn` closes over a
    per-lane value (`scale`)."""
    from jax import lax

    from jaxtraj._driver import only_where

    rounds = []

    def solve(pred, n, scale):
        def count(n):
            def body(i):
                jax.debug.callback(lambda i: rounds.append(np.max(i)), i)
                return i + 1

            return lax.while_loop(lambda i: i < n, body, 0) * scale

        return only_where(pred, count, -1, n)

    preds, ns, scales = jnp.array([False, True, False]), jnp.array([1000, 3, 7]), jnp.array([1, 10, 100])
    out = jax.jit(jax.vmap(solve))(preds, ns, scales)
    jax.effects_barrier()
    np.testing.assert_array_equal(out, [-1, 30, -1])
    assert max(rounds) == 2, max(rounds)
    np.testing.assert_array_equal(jax.jit(solve)(True, 5, 2), 10)  # unbatched: fn itself
    np.testing.assert_array_equal(jax.jit(solve)(False, 5, 2), -1)


@pytest.mark.slow
@pytest.mark.parametrize(
    "solver",
    [jt.KalmanSearch(), jt.KalmanSQP(), jt.KalmanSQP(hessian="bfgs", globalization="line-search")],
    ids=["search", "trust-region", "line-search"],
)
def test_a_finished_lane_asks_for_no_work(solver, monkeypatch):
    """Under `vmap` a finished lane still runs the step (its result is dropped): marked done,
    it must ask `only_where` for none of the work its state would ask for when live, or a
    batch pays a finished lane's re-tuning, QP or stationarity test every step until its
    slowest lane is done (KalmanSearch on Bryson-Denham, 8 lanes: 3.9x a single solve's
    cost per lane-step). The state: Bryson-Denham (a path constraint) after one step."""
    from jaxtraj import _driver, _kalman_search, _line_search, _trust_region

    calls = []

    def counting(pred, fn, otherwise, *operands):
        def counted(*args):
            jax.debug.callback(lambda: calls.append(1))
            return fn(*args)

        return _driver.only_where(pred, counted, otherwise, *operands)

    for module in (_kalman_search, _line_search, _trust_region):
        monkeypatch.setattr(module, "only_where", counting)
    entry = jt.problems.classic.get("bryson-denham")
    prob, ctrl, sim = entry.problem, entry.control, jt.RK4(20)
    state = eqx.filter_jit(lambda a: _driver.run_loop(solver, prob, ctrl, a, sim, 1, history=False))(entry.start)
    assert int(state.num_steps) == 1 and not bool(state.done)
    step = eqx.filter_jit(eqx.filter_vmap(lambda s: solver.step(prob, ctrl, sim, s)))
    lanes = jax.tree.map(lambda x: jnp.stack([x, x]) if eqx.is_array(x) else x, state)
    for done in (False, True):
        calls.clear()
        jax.block_until_ready(step(eqx.tree_at(lambda s: s.done, lanes, jnp.array([done, done]))))
        jax.effects_barrier()
        # live, the state asks for work (else the finished lanes' check would prove nothing)
        assert bool(calls) == (not done), (done, len(calls))


def test_solve_batch_says_once_when_a_batch_leaves_cores_idle():
    """The line `solve_batch`'s progress prints on one CPU device of a host with several
    cores (no `jt.configure_cpu()`): once per process; nothing with a device per core (this
    test process)."""
    import jaxlib

    from jaxtraj import _configure

    cpu = jax.devices("cpu")
    assert _configure.unused_cores_hint(cpu[:1]) is None  # conftest split the CPU: nothing idle
    code = (
        "import jax, numpy as np, jaxtraj as jt\n"
        "from jaxtraj import _configure\n"
        "d = jax.devices('cpu')\n"
        "print(repr(_configure.unused_cores_hint(d)))\n"
        "print(repr(_configure.unused_cores_hint(d)))\n"
    )
    first, second = _python(code).splitlines()[:2]
    cores = len(os.sched_getaffinity(0))
    splits = tuple(int(x) for x in jaxlib.__version__.split(".")[:2]) < (0, 11) and cores > 1
    if splits:
        assert f"one CPU device on {cores} cores" in first and "jt.configure_cpu()" in first
    else:
        assert first == "None"
    assert second == "None"
