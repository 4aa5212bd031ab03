"""Result folders: exact round trips, strict JSON, and damaged or mixed files named, never
silently accepted."""

import json
import shutil

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

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
    ],
    ids=["truncated-summary", "summary-not-an-object", "garbage-arrays", "no-arrays", "no-tf", "unknown-status"],
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
    and no temporary files; a save into a new or empty folder appears by one rename; saving
    into a folder with other files replaces the result's files and keeps the others."""
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

    renames = []
    real_rename = jt.io.os.rename
    monkeypatch.setattr(jt.io.os, "rename", lambda a, b: (renames.append(b), real_rename(a, b)))
    jt.io.save(target, PROB, sol, traj)
    assert renames == [str(target)] and sorted(p.name for p in target.iterdir()) == ["arrays.npz", "summary.json"]

    (target / "notes.txt").write_text("mine")
    other = eqx.tree_at(lambda s: s.params, sol, sol.params + 1.0)
    jt.io.save(target, PROB, other, traj)
    assert (target / "notes.txt").read_text() == "mine"
    np.testing.assert_array_equal(jt.io.load(target)[0].params, other.params)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    with pytest.raises(ValueError, match=r"`folder`: .* is a file, not a folder"):
        jt.io.save(target / "notes.txt", PROB, sol, traj)
