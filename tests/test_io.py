"""Result folders: exact round trips, strict JSON, and damaged or mixed files named, never
silently accepted."""

import hashlib
import json
import os
import pathlib
import shutil
import socket
import subprocess
import sys
import tempfile

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import jaxtraj as jt

PROB = jt.problems.analytic.min_energy_double_integrator()
CTRL = jt.controls.PiecewiseLinear(3)
SIM = jt.RK4(4)


@pytest.fixture(scope="module")
def result():
    a0 = jnp.asarray(CTRL.initial_guess(1.2, 0.0, 0.0))
    sol = jt.solve(PROB, CTRL, a0, jt.KalmanSQP(), simulator=SIM)
    return sol, jt.simulate(PROB, CTRL, sol.params, simulator=SIM)


def _strict(path):
    def refuse(token):
        raise AssertionError(f"{path} holds {token}, not strict JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_round_trip_is_exact(result, tmp_path):
    sol, traj = result
    jt.io.save(tmp_path, PROB, sol, traj, inputs={"a0": np.arange(3.0)})
    back, back_traj, summary = jt.io.load(tmp_path)
    np.testing.assert_array_equal(back.params, sol.params)
    assert jt.status_name(back.status) == jt.status_name(sol.status) == "SUCCESS"
    n = int(sol.steps)
    assert set(back.history.details) == set(sol.history.details) == {"radius", "kind"}
    np.testing.assert_array_equal(back.history.details["radius"], sol.history.details["radius"][:n])
    np.testing.assert_array_equal(back.history.step_norm, sol.history.step_norm[:n])
    np.testing.assert_array_equal(back_traj.x, traj.x)
    np.testing.assert_array_equal(back.multipliers, sol.multipliers)
    assert list(summary["multipliers"]) == list(PROB.constraint_names)
    assert _strict(tmp_path / "summary.json")["inputs"]["a0"] == [0.0, 1.0, 2.0]
    assert summary["nonfinite"] == []


def test_a_failed_solve_is_strict_json_and_keeps_its_status(result, tmp_path):
    sol, traj = result
    failed = eqx.tree_at(
        lambda s: (s.objective, s.projected_gradient, s.status),
        sol,
        (jnp.asarray(jnp.inf), jnp.asarray(jnp.nan), jt.Status.NONFINITE),
    )
    failed_traj = eqx.tree_at(lambda t: t.status, traj, jt.Status.SIMULATION_FAILED)
    jt.io.save(tmp_path, PROB, failed, failed_traj)
    summary = _strict(tmp_path / "summary.json")
    assert summary["objective"] is None and summary["projected_gradient"] is None
    assert summary["nonfinite"] == ["objective", "projected_gradient"]
    back, back_traj, _ = jt.io.load(tmp_path)
    assert jt.status_name(back.status) == "NONFINITE"
    assert jt.status_name(back_traj.status) == "SIMULATION_FAILED"
    assert np.isnan(float(back.objective)) and float(back.tf) == float(sol.tf)


def test_arrays_from_another_save_are_refused(result, tmp_path):
    sol, traj = result
    first, second = tmp_path / "first", tmp_path / "second"
    jt.io.save(first, PROB, sol, traj)
    other = eqx.tree_at(lambda s: s.params, sol, sol.params + 1.0)
    jt.io.save(second, PROB, other, traj)
    shutil.copy(second / "arrays.npz", first / "arrays.npz")
    with pytest.raises(ValueError, match=r"arrays\.npz: does not belong to .*summary\.json"):
        jt.io.load(first)


def test_unserializable_inputs_change_nothing(result, tmp_path):
    sol, traj = result
    jt.io.save(tmp_path, PROB, sol, traj)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(ValueError, match="`inputs` cannot be written as JSON"):
        jt.io.save(tmp_path, PROB, sol, traj, inputs={"solver": object()})
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda d: (d / "summary.json").write_text('{"status": "SUC'), r"summary\.json: damaged"),
        (lambda d: (d / "summary.json").write_text("[1, 2]"), r"summary\.json: damaged"),
        (lambda d: (d / "arrays.npz").write_bytes(b"not a zip"), r"arrays\.npz: does not belong"),
        (lambda d: (d / "arrays.npz").unlink(), r"arrays\.npz: missing"),
        (lambda d: _edit(d, lambda s: s.pop("tf")), r"summary\.json: `tf` is missing"),
        (lambda d: _edit(d, lambda s: s.update(status="DONE")), r"`status` is 'DONE', not a jaxtraj status"),
        # issue 51: a summary that contradicts its arrays, or cannot be checked against them
        (lambda d: _edit(d, lambda s: s.pop("arrays_sha256")), r"`arrays_sha256` is missing, so .* cannot be checked"),
        (lambda d: _edit(d, lambda s: s.update(tf=[1.0, 2.0])), r"`tf` must be a number; got \[1\.0, 2\.0\]"),
        (lambda d: _edit(d, lambda s: s.update(tf=s["tf"] + 1)), r"`tf` = .* contradicts .*last knot"),
        (lambda d: _edit(d, lambda s: s.update(params=s["params"][:-1])), r"`params` contradicts .*5 parameters"),
        (
            lambda d: _edit(d, lambda s: s.update(steps=s["steps"] + 1)),
            r"`steps` = \d+ contradicts .*history of length",
        ),
        (lambda d: _edit(d, lambda s: s.update(iterations=10**6)), r"the counts contradict each other"),
        (lambda d: _edit(d, lambda s: s.update(constraints={})), r"`constraints` contradicts"),
        (lambda d: _edit(d, lambda s: s.update(integrations=10**30)), r"`integrations` must be an int in 0\.\.2\*\*31"),
        (lambda d: _edit(d, lambda s: s.update(max_constraint_error=0.0)), r"`max_constraint_error` contradicts"),
        (lambda d: _edit(d, lambda s: s.update(multipliers={"x": 1.0})), r"`multipliers` contradicts"),
        (lambda d: _edit(d, lambda s: s.pop("multipliers")), r"`multipliers` contradicts .*one file has it"),
        (lambda d: _edit(d, lambda s: s.update(tf=None)), r"`tf` = nan contradicts"),
        (
            lambda d: (d / "summary.json").write_text('{"tf": NaN}'),
            r"summary\.json: damaged \(NaN is not strict JSON\)",
        ),
        (
            lambda d: _edit(d, lambda s: s.update(max_violation=-1.0)),
            r"`max_violation` = -1\.0 is below one of its parts",
        ),
        (lambda d: _edit(d, lambda s: s.update(projected_gradient=-1)), r"`projected_gradient` is a norm; got -1\.0"),
        (
            lambda d: _edit(d, lambda s: s.update(max_violation=0.5)),
            r"status SUCCESS with `max_violation` = 0\.5 contradicts .*constraint tolerance 1e-10 in its history",
        ),
        # the summary's objective, projected gradient and iteration count against the arrays
        (
            lambda d: _edit(d, lambda s: s.update(objective=s["objective"] + 1)),
            r"`objective` = (7\.0|7\.0{10,}\d*|6\.9{10,}\d*) contradicts .*npz",  # (the last bits vary)
        ),
        (
            lambda d: _edit(d, lambda s: s.update(objective=None)),
            r"`objective` = nan contradicts .*\((6\.0|6\.0{10,}\d*|5\.9{10,}\d*) there",
        ),
        (
            lambda d: _edit(d, lambda s: s.update(projected_gradient=1.0)),
            r"`projected_gradient` = 1\.0 contradicts",
        ),
        (
            lambda d: _edit(d, lambda s: s.update(iterations=s["iterations"] - 1)),
            r"`iterations` = 5 contradicts .*\(6 there",
        ),
    ],
    ids=[
        "truncated-summary",
        "summary-not-an-object",
        "garbage-arrays",
        "no-arrays",
        "no-tf",
        "unknown-status",
        "no-checksum",
        "tf-shape",
        "tf-value",
        "params-length",
        "steps",
        "iterations",
        "constraints",
        "huge-count",
        "max-constraint-error",
        "multipliers",
        "multipliers-only-in-arrays",
        "tf-null",
        "nan-literal",
        "max-violation",
        "negative-norm",
        "success-with-violation",
        "objective",
        "objective-null",
        "projected-gradient",
        "iteration-count",
    ],
)
def test_damaged_folders_name_the_file(result, tmp_path, damage, message):
    sol, traj = result
    jt.io.save(tmp_path, PROB, sol, traj)
    damage(tmp_path)
    with pytest.raises(ValueError, match=message):
        jt.io.load(tmp_path)


def _edit(folder, change):
    summary = json.loads((folder / "summary.json").read_text())
    change(summary)
    (folder / "summary.json").write_text(json.dumps(summary))


def test_a_folder_is_written_whole_or_not_at_all(result, tmp_path, monkeypatch):
    """A save that fails midway (here: the disk refuses the second file) leaves no folder
    and no temporary files; saving into a folder with other files replaces the result's
    files and keeps the others; nothing is ever written beside the folder."""
    sol, traj = result
    target = tmp_path / "run"
    real_write = jt.io.atomic_write

    def fail_on_summary(path, write):
        if str(path).endswith("summary.json"):
            raise OSError(28, "No space left on device")
        real_write(path, write)

    monkeypatch.setattr(jt.io, "atomic_write", fail_on_summary)
    with pytest.raises(OSError, match="No space"):
        jt.io.save(target, PROB, sol, traj)
    assert list(tmp_path.iterdir()) == []  # neither the folder nor a leftover temporary one
    monkeypatch.setattr(jt.io, "atomic_write", real_write)

    jt.io.save(target, PROB, sol, traj)
    assert _visible(target) == ["arrays.npz", "summary.json"]

    (target / "notes.txt").write_text("mine")
    other = eqx.tree_at(lambda s: s.params, sol, sol.params + 1.0)
    jt.io.save(target, PROB, other, traj)
    assert (target / "notes.txt").read_text() == "mine"
    np.testing.assert_array_equal(jt.io.load(target)[0].params, other.params)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    with pytest.raises(ValueError, match=r"`folder`: .* is a file, not a folder"):
        jt.io.save(target / "notes.txt", PROB, sol, traj)


def _visible(folder):
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def test_out_as_given(result, tmp_path):
    """Issue 51: a folder reached through a symbolic link is written where the link points;
    staging happens inside the folder (its parent may be read-only: nothing is written
    there); a rerun removes the previous result's files it does not write again (no stale
    figure beside a new summary) and keeps the rest; a temporary folder that a killed
    process left is removed by the next write, a live process's is not."""
    sol, traj = result
    real, link = tmp_path / "real", tmp_path / "link"
    real.mkdir()
    link.symlink_to(real, target_is_directory=True)
    parent_before = sorted(p.name for p in tmp_path.iterdir())
    with jt.io.staged_folder(link) as stage:
        assert os.path.dirname(stage) == str(link)
        jt.io.save(stage, PROB, sol, traj)
        for name in ("solution.png", "history.png"):
            (tmp_path / "link" / os.path.basename(stage) / name).write_bytes(b"png")
        (real / "batch").mkdir()
        (real / "notes.txt").write_text("mine")
    assert sorted(p.name for p in tmp_path.iterdir()) == parent_before and link.is_symlink()
    assert _visible(real) == ["arrays.npz", "batch", "history.png", "notes.txt", "solution.png", "summary.json"]
    np.testing.assert_array_equal(jt.io.load(link)[0].params, sol.params)

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = socket.gethostname()
    (real / f".partial-{host}-{dead.pid}-abc").mkdir()
    (real / f".partial-{host}-{os.getpid()}-abc").mkdir()
    with jt.io.staged_folder(link) as stage:
        jt.io.save(stage, PROB, sol, traj)
        (pathlib.Path(stage) / "solution.png").write_bytes(b"png2")
    assert _visible(real) == ["arrays.npz", "batch", "notes.txt", "solution.png", "summary.json"]
    assert (real / "solution.png").read_bytes() == b"png2"
    assert sorted(p.name for p in real.iterdir() if p.name.startswith(".partial")) == [
        f".partial-{host}-{os.getpid()}-abc"
    ]


def test_load_needs_float64(result, tmp_path):
    """Issue 51: with JAX's float64 mode off, load refuses (as every entry point) instead of
    returning float32 parameters."""
    sol, traj = result
    jt.io.save(tmp_path, PROB, sol, traj)
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(RuntimeError, match="jaxtraj needs float64"):
            jt.io.load(tmp_path)
    finally:
        jax.config.update("jax_enable_x64", True)
    assert jt.io.load(tmp_path)[0].params.dtype == jnp.float64


_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**20), 10**20) | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=6,
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_load_of_a_mutated_folder_refuses_or_agrees(result, data):
    """Issue 51, property: whatever one entry of summary.json or of arrays.npz is changed to
    (the arrays' checksum updated, as a forged save would), `load` either raises a
    ValueError naming the file, or returns a Solution that agrees with the arrays."""
    sol, traj = result
    with tempfile.TemporaryDirectory() as folder:
        summary = jt.io.save(folder, PROB, sol, traj)
        path = os.path.join(folder, "summary.json")
        if data.draw(st.booleans(), label="mutate the summary"):
            key = data.draw(st.sampled_from(sorted(summary)), label="key")
            if data.draw(st.booleans(), label="delete"):
                del summary[key]
            else:
                summary[key] = data.draw(_JSON, label="value")
        else:
            with np.load(os.path.join(folder, "arrays.npz")) as f:
                arrays = dict(f)
            key = data.draw(st.sampled_from(sorted(arrays)), label="array")
            shape = data.draw(st.sampled_from([(), (0,), (2,), (*arrays[key].shape[:1], 1), arrays[key].shape]))
            dtype = data.draw(st.sampled_from([np.float64, np.float32, np.int64, bool]))
            arrays[key] = np.ones(shape, dtype)
            np.savez(os.path.join(folder, "arrays.npz"), **arrays)
            summary["arrays_sha256"] = jt.io._sha256(os.path.join(folder, "arrays.npz"))
        with open(path, "w") as f:
            json.dump(summary, f)
        try:
            back, _, _ = jt.io.load(folder)
        except ValueError as e:
            assert "summary.json" in str(e) or "arrays.npz" in str(e), e
            return
        with np.load(os.path.join(folder, "arrays.npz")) as f:
            np.testing.assert_array_equal(back.params, f["params"])
            np.testing.assert_array_equal(back.constraints, f["constraints"])
            assert int(back.steps) == f["history_objective"].shape[0]
            # the summary's numbers agree with their copies in the arrays (the saved ones)
            for key in ("objective", "projected_gradient", "iterations"):
                saved = f[key] if key in f.files else getattr(sol, key)
                assert getattr(back, key) == saved or (np.isnan(getattr(back, key)) and not np.isfinite(saved)), key
        assert back.params.dtype == jnp.float64 and back.tf.shape == ()


def test_save_refuses_what_load_could_not_trust(result, tmp_path):
    """Issue 51: `save` refuses a batch, a trajectory of other parameters (another tf, or the
    same tf and another final state), and `extra` entries that would replace the summary's
    own (they made a folder load as SUCCESS with violation 0, or one that `load` then
    refused): nothing is written."""
    sol, traj = result
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), sol)
    with pytest.raises(ValueError, match=r"`sol` must be one jt.Solution .* got Solution with a batch axis \(2,\)"):
        jt.io.save(tmp_path / "a", PROB, batch, traj)
    other = jt.simulate(PROB, CTRL, sol.params.at[-1].set(2.0), simulator=SIM)
    with pytest.raises(ValueError, match=r"`traj` ends at t = 2\.0, `sol` at tf = 1\.0"):
        jt.io.save(tmp_path / "b", PROB, sol, other)
    # another parameter vector with the same tf: its final state misses (it was accepted)
    same_tf = jt.simulate(PROB, CTRL, sol.params.at[0].add(0.5), simulator=SIM)
    with pytest.raises(
        ValueError, match=r"`traj` is not the trajectory of `sol\.params`: its final state gives constr"
    ):
        jt.io.save(tmp_path / "e", PROB, sol, same_tf)
    with pytest.raises(
        ValueError, match=r"`extra` may not replace the summary's own entries; got \['params', 'status'\]"
    ):
        jt.io.save(tmp_path / "c", PROB, sol, traj, extra={"status": "SUCCESS", "params": [0], "mine": 1})
    assert list(tmp_path.iterdir()) == []
    jt.io.save(tmp_path / "d", PROB, sol, traj, extra={"mine": 1})
    assert jt.io.load(tmp_path / "d")[2]["mine"] == 1
    jt.io.save(tmp_path / "f", PROB, sol, jt.simulate(PROB, CTRL, sol.params))  # a finer simulator: the same


def test_terminal_inequality_multipliers_round_trip_and_older_folders_load(tmp_path):
    """The capped terminal problem (min 1/2 int u^2 - 2 x(1), x(1) <= 1): its cap's multiplier
    nu = 1 (u = 2 - nu = 1, closed form) is saved and loaded by name; a folder saved before
    the multipliers were (both files without them) loads with them NaN."""
    entry = jt.problems.classic.get("capped-terminal")
    sol = jt.solve(entry.problem, entry.control, entry.start, simulator=SIM)
    assert abs(float(sol.terminal_inequality_multipliers[0]) - 1.0) < 1e-8
    traj = jt.simulate(entry.problem, entry.control, sol.params, simulator=SIM)
    summary = jt.io.save(tmp_path, entry.problem, sol, traj)
    assert summary["terminal_inequality_multipliers"] == {"x(1) cap": float(sol.terminal_inequality_multipliers[0])}
    back = jt.io.load(tmp_path)[0]
    np.testing.assert_array_equal(back.terminal_inequality_multipliers, sol.terminal_inequality_multipliers)

    with np.load(tmp_path / "arrays.npz") as data:
        old_keys = ("objective", "projected_gradient", "iterations")  # (issue 51's copies: not yet saved)
        arrays = {k: data[k] for k in data.files if "multipliers" not in k and k not in old_keys}
    np.savez(tmp_path / "arrays.npz", **arrays)
    _edit(tmp_path, lambda s: [s.pop(k) for k in ("multipliers", "terminal_inequality_multipliers")])
    _edit(
        tmp_path, lambda s: s.update(arrays_sha256=hashlib.sha256((tmp_path / "arrays.npz").read_bytes()).hexdigest())
    )
    old = jt.io.load(tmp_path)[0]
    assert old.multipliers.shape == (0,) and np.isnan(old.terminal_inequality_multipliers).all()
    np.testing.assert_array_equal(old.params, sol.params)


def test_a_solve_without_a_finite_point_is_saved_with_the_starts_trajectory(result, tmp_path):
    """A NONFINITE solve before any accepted step reports tf = NaN (dynamics NaN at the start:
    `jaxtraj solve` then died in `save`, its table printed); its trajectory is the start's,
    which ends elsewhere. Saved and loaded as such; a NaN tf with another status is refused."""
    sol, traj = result
    nan = jnp.asarray(jnp.nan)
    failed = eqx.tree_at(lambda s: (s.tf, s.objective, s.status), sol, (nan, nan, jt.Status.NONFINITE))
    jt.io.save(tmp_path / "failed", PROB, failed, traj)
    back = jt.io.load(tmp_path / "failed")[0]
    assert jt.status_name(back.status) == "NONFINITE" and np.isnan(float(back.tf))
    with pytest.raises(ValueError, match=r"`sol` at tf = nan"):
        jt.io.save(tmp_path / "other", PROB, eqx.tree_at(lambda s: s.status, failed, jt.Status.STALLED), traj)


def test_arguments_of_the_wrong_type_are_named(result, tmp_path):
    """Issue 51's re-audit: `save` with a problem's name for the problem, `load(None)`."""
    sol, traj = result
    with pytest.raises(ValueError, match=r"`problem` must be the jt.Problem that `sol` solves; got str"):
        jt.io.save(tmp_path, "prob", sol, traj)
    with pytest.raises(ValueError, match=r"`folder` must be a path .*got NoneType"):
        jt.io.load(None)
    # os' and dict's TypeErrors named no argument (issue 51, fourth audit)
    with pytest.raises(ValueError, match=r"`folder` must be a path .*got int"):
        jt.io.save(3, PROB, sol, traj)
    with pytest.raises(ValueError, match=r"`extra` must be a dict .*got list"):
        jt.io.save(tmp_path, PROB, sol, traj, extra=[1, 2])
    with pytest.raises(ValueError, match=r"`out` must be None or a folder path .*got int"):
        jt.solve_batch(PROB, CTRL, sol.params[None], simulator=SIM, out=5, progress=False)
    assert not os.listdir(tmp_path)


def test_a_trajectory_whose_segment_ends_round_past_the_next_knot_loads(result, tmp_path):
    """Issue 51's fourth audit: t_k + h_k rounded an ulp past t_{k+1} (10 segments to tf =
    0.3), so a dense trajectory went backwards there and `load` refused the folder `jaxtraj
    solve` had just written ("its times are out of order"). Segments end at their knots
    exactly now; a folder saved before that loads."""
    ctrl = jt.controls.PiecewiseLinear(10)
    traj = jt.simulate(PROB, ctrl, ctrl.initial_guess(0.3, 0.0, 0.0))
    t = np.asarray(traj.t)
    assert np.all(np.diff(t) >= 0)
    ends = t.reshape(10, -1)
    assert np.array_equal(ends[:, -1], np.asarray(traj.knots)[1:]) and np.array_equal(ends[:, 0], traj.knots[:-1])
    sol, traj = result
    t = np.asarray(traj.t).copy()
    per = t.size // CTRL.num_segments
    t[per - 1] = np.nextafter(t[per], np.inf)  # an older save: segment 0 ends an ulp past t_1
    jt.io.save(tmp_path, PROB, sol, eqx.tree_at(lambda tr: tr.t, traj, jnp.asarray(t)))
    assert np.array_equal(np.asarray(jt.io.load(tmp_path)[1].t), t)


def test_figures_name_a_batch_or_a_missing_trajectory(result, tmp_path):
    """Issue 51's fourth audit: a batched solution, no trajectory or one success flag short
    failed deep inside JAX, NumPy or the plotting code."""
    import jaxtraj.plot

    sol, traj = result
    batch = jax.tree.map(lambda x: x[None], sol)
    with pytest.raises(ValueError, match=r"`sol` must be one jt.Solution .*with a batch axis \(1,\)"):
        jaxtraj.plot.write_figures(tmp_path, PROB, CTRL, batch, traj)
    with pytest.raises(ValueError, match=r"`traj` must be one jt.Trajectory .*got NoneType"):
        jaxtraj.plot.solution_figure(PROB, CTRL, sol, None, tmp_path / "x.png")
    with pytest.raises(ValueError, match=r"`objectives` and `success` must be one value and one bool per start"):
        jaxtraj.plot.batch_figure(tmp_path / "b.png", PROB, np.ones(3), np.ones(2, bool), [])
    assert not os.listdir(tmp_path)
