"""Result folders: `summary.json` (inputs, outputs, status) + `arrays.npz` (parameters,
dense trajectory, history). Every file is written atomically (temporary file + rename), so an
interrupted run never leaves a truncated file. `load(dir)` gives the Solution and Trajectory
back, parameters bit for bit."""

import json
import os
import tempfile

import jax.numpy as jnp
import numpy as np

from ._simulate import Trajectory
from ._solution import History, Solution
from ._status import STATUS_NAMES, Status, status_name

_HISTORY_FIELDS = ("objective", "max_constraint_error", "step_norm", "accepted", "constraint_tolerance")
_DETAIL = "history_detail_"


def atomic_write(path, write):
    """Call `write(file_object)` on a temporary file in the target folder, then rename."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=os.path.basename(path))
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.ndarray, jnp.ndarray)):
        return np.asarray(value).tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return value


def save(folder, problem, sol: Solution, traj: Trajectory, *, inputs=None):
    """Write `summary.json` and `arrays.npz` into `folder` (created if needed)."""
    os.makedirs(folder, exist_ok=True)
    n = int(sol.steps)
    arrays = {
        "params": np.asarray(sol.params),
        "constraints": np.asarray(sol.constraints),
        "t": np.asarray(traj.t),
        "x": np.asarray(traj.x),
        "u": np.asarray(traj.u),
        "knots": np.asarray(traj.knots),
        "xf": np.asarray(traj.xf),
        **{f"history_{k}": np.asarray(getattr(sol.history, k))[:n] for k in _HISTORY_FIELDS},
        **{f"{_DETAIL}{k}": np.asarray(v)[:n] for k, v in sol.history.details.items()},
    }
    atomic_write(os.path.join(folder, "arrays.npz"), lambda f: np.savez(f, **arrays))
    summary = {
        "problem": problem.name,
        "inputs": _jsonable(inputs or {}),
        "status": status_name(sol.status),
        "message": Status[sol.status] or "converged",
        "tf": float(sol.tf),
        "objective": float(sol.objective),
        "max_constraint_error": float(sol.max_constraint_error),
        "constraints": {name: float(e) for name, e in zip(problem.constraint_names, np.asarray(sol.constraints))},
        "projected_gradient": float(sol.projected_gradient),
        "iterations": int(sol.iterations),
        "integrations": int(sol.integrations),
        "steps": n,
        "params": np.asarray(sol.params).tolist(),
    }
    if sol.max_path_constraint is not None:
        summary["max_path_constraint"] = float(sol.max_path_constraint)
        summary["max_path_time"] = float(sol.max_path_time)
    text = json.dumps(summary, indent=2).encode()
    atomic_write(os.path.join(folder, "summary.json"), lambda f: f.write(text))
    return summary


def load(folder):
    """`(Solution, Trajectory, summary)` from a folder written by `save` (or the CLI)."""
    with open(os.path.join(folder, "summary.json")) as f:
        summary = json.load(f)
    with np.load(os.path.join(folder, "arrays.npz")) as data:
        arrays = {k: data[k] for k in data.files}
    status = getattr(Status, summary["status"]) if summary["status"] in STATUS_NAMES else Status.NONFINITE
    history = History(
        **{k: jnp.asarray(arrays[f"history_{k}"]) for k in _HISTORY_FIELDS},
        details={k[len(_DETAIL) :]: jnp.asarray(v) for k, v in arrays.items() if k.startswith(_DETAIL)},
    )
    sol = Solution(
        params=jnp.asarray(arrays["params"]),
        tf=jnp.asarray(summary["tf"]),
        objective=jnp.asarray(summary["objective"]),
        constraints=jnp.asarray(arrays["constraints"]),
        max_constraint_error=jnp.asarray(summary["max_constraint_error"]),
        projected_gradient=jnp.asarray(summary["projected_gradient"]),
        iterations=jnp.asarray(summary["iterations"]),
        integrations=jnp.asarray(summary["integrations"]),
        steps=jnp.asarray(summary["steps"]),
        status=status,
        history=history,
        max_path_constraint=None
        if "max_path_constraint" not in summary
        else jnp.asarray(summary["max_path_constraint"]),
        max_path_time=None if "max_path_time" not in summary else jnp.asarray(summary["max_path_time"]),
    )
    traj = Trajectory(
        t=jnp.asarray(arrays["t"]),
        x=jnp.asarray(arrays["x"]),
        u=jnp.asarray(arrays["u"]),
        knots=jnp.asarray(arrays["knots"]),
        xf=jnp.asarray(arrays["xf"]),
        status=Status.SUCCESS,
    )
    return sol, traj, summary
