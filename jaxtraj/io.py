"""Result folders: `summary.json` (inputs, outputs, status) + `arrays.npz` (parameters,
dense trajectory, history). A folder is written whole or not at all (`staged_folder`: the
files go into a temporary folder that is renamed into place), and every file is written
atomically (temporary file + rename); where an existing folder is updated file by file, the
summary, written last, carries the checksum of the arrays it belongs to. `load(dir)` gives
the Solution and Trajectory back, parameters bit for bit, or a ValueError that names the
damaged file. `folder_lock` keeps two runs out of one folder."""

import contextlib
import errno
import hashlib
import json
import math
import os
import shutil
import tempfile
import zipfile

import jax.numpy as jnp
import numpy as np

from ._simulate import Trajectory
from ._solution import History, Solution
from ._status import STATUS_NAMES, Status, status_name

_HISTORY_FIELDS = ("objective", "max_constraint_error", "step_norm", "accepted", "constraint_tolerance")
_DETAIL = "history_detail_"


@contextlib.contextmanager
def folder_lock(folder, what="`out`"):
    """Hold an exclusive lock on `folder` (creating it) for the `with` block: a second run
    that tries the same folder meanwhile gets a one-line ValueError naming `what` instead of
    writing its files between the first run's. The lock is an `flock` on the folder itself
    (no file is added), released when the block ends or the process dies; on systems without
    `flock` there is no lock."""
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"{what}: {folder!r} is a file, not a folder.")
    os.makedirs(folder, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise ValueError(
            f"{what}: {folder!r} is in use by another run (locked); wait for it to end or choose another folder."
        ) from None
    try:
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def _usual_mode(mode):
    """`mode` less the process's umask: the permissions `open` / `mkdir` would give."""
    umask = os.umask(0)
    os.umask(umask)
    return mode & ~umask


def atomic_write(path, write):
    """Call `write(file_object)` on a temporary file in the target folder, then rename."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=os.path.basename(path))
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _usual_mode(0o666))  # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


@contextlib.contextmanager
def staged_folder(folder, what="`folder`"):
    """Write a result folder whole or not at all: yields a new temporary folder beside
    `folder` to write into. When the block ends, the temporary folder becomes `folder` by one
    rename where `folder` is absent or empty (a reader sees no folder or the whole one), and
    otherwise its files replace `folder`'s one by one, `summary.json` last (its checksum ties
    it to its arrays: `load` refuses a mix); other files of `folder` are kept. When the block
    raises, the temporary folder is deleted and `folder` is untouched.

    A rename is what the standard library offers for this (`os.rename` over an empty folder
    is atomic on POSIX); no library writes a folder transactionally.

    **Raises:** `ValueError` naming `what` when `folder` is a file.
    """
    folder = os.path.abspath(os.fspath(folder))
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"{what}: {folder!r} is a file, not a folder.")
    parent, name = os.path.split(folder)
    os.makedirs(parent, exist_ok=True)
    stage = tempfile.mkdtemp(dir=parent, prefix=f".{name}.partial-")
    try:
        yield stage
        os.chmod(stage, _usual_mode(0o777))  # mkdtemp creates 0700
        try:
            os.rename(stage, folder)
            return
        except OSError as e:
            if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
        for entry in sorted(os.listdir(stage), key=lambda n: n == "summary.json"):
            os.replace(os.path.join(stage, entry), os.path.join(folder, entry))
        os.rmdir(stage)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


def _jsonable(value):
    """Plain JSON values: arrays to lists, NumPy scalars to Python, non-finite floats to None
    (strict JSON has no NaN or Infinity)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.ndarray, jnp.ndarray)):
        return _jsonable(np.asarray(value).tolist())
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def save(folder, problem, sol: Solution, traj: Trajectory, *, inputs=None, extra=None):
    """Write `arrays.npz` and `summary.json` into `folder` (created if needed), whole or not
    at all (`staged_folder`).

    `summary.json` records the SHA-256 of `arrays.npz`, so `load` recognizes a pair from two
    different saves (an interrupted update of a folder that holds other files too). The
    summary is strict JSON: a non-finite number is `null`, and its name is listed
    under `"nonfinite"`. `extra`: more JSON-able entries for the summary (e.g. the CLI's
    Monte Carlo results). Returns the summary (a dict).

    **Raises:** `ValueError` naming the entry if `inputs` or `extra` cannot be written as
    JSON (nothing is written then), or when `folder` is a file.
    """
    n = int(sol.steps)
    arrays = {
        "params": np.asarray(sol.params),
        "constraints": np.asarray(sol.constraints),
        **({} if sol.terminal_inequality is None else {"terminal_inequality": np.asarray(sol.terminal_inequality)}),
        "t": np.asarray(traj.t),
        "x": np.asarray(traj.x),
        "u": np.asarray(traj.u),
        "knots": np.asarray(traj.knots),
        "xf": np.asarray(traj.xf),
        **{f"history_{k}": np.asarray(getattr(sol.history, k))[:n] for k in _HISTORY_FIELDS},
        **{f"{_DETAIL}{k}": np.asarray(v)[:n] for k, v in sol.history.details.items()},
    }
    outputs = {
        "tf": float(sol.tf),
        "objective": float(sol.objective),
        "max_constraint_error": float(sol.max_constraint_error),
        "projected_gradient": float(sol.projected_gradient),
    }
    if sol.max_path_constraint is not None:
        outputs["max_path_constraint"] = float(sol.max_path_constraint)
        outputs["max_path_time"] = float(sol.max_path_time)
    summary = {
        "problem": problem.name,
        "inputs": inputs or {},
        "status": status_name(sol.status),
        "message": Status[sol.status] or "converged",
        "trajectory_status": status_name(traj.status),
        **outputs,
        "constraints": {name: float(e) for name, e in zip(problem.constraint_names, np.asarray(sol.constraints))},
        **(
            {}
            if sol.terminal_inequality is None
            else {
                "terminal_inequality": {
                    name: float(d)
                    for name, d in zip(problem.terminal_inequality_names, np.asarray(sol.terminal_inequality))
                }
            }
        ),
        "iterations": int(sol.iterations),
        "integrations": int(sol.integrations),
        "steps": n,
        "params": np.asarray(sol.params).tolist(),
        "nonfinite": [k for k, v in outputs.items() if not math.isfinite(v)],
        **(extra or {}),
    }
    for key in ("inputs", *(extra or {})):
        try:
            json.dumps(_jsonable(summary[key]), allow_nan=False)
        except (TypeError, ValueError) as e:
            raise ValueError(f"`{key}` cannot be written as JSON: {e}") from None
    with staged_folder(folder) as stage:
        arrays_path = os.path.join(stage, "arrays.npz")
        atomic_write(arrays_path, lambda f: np.savez(f, **arrays))
        summary["arrays_sha256"] = _sha256(arrays_path)
        summary = _jsonable(summary)
        text = json.dumps(summary, indent=2, allow_nan=False).encode()
        atomic_write(os.path.join(stage, "summary.json"), lambda f: f.write(text))
    return summary


def read_json(path) -> dict:
    """The JSON object in `path`, or a ValueError naming the file ("damaged") when it is not
    one (truncated, empty, not an object)."""
    try:
        with open(path) as f:
            value = json.load(f)
        if not isinstance(value, dict):
            raise ValueError("not a JSON object")
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: damaged ({e}).") from None
    return value


def _status(name, path, field):
    if name not in STATUS_NAMES:
        raise ValueError(f"{path}: `{field}` is {name!r}, not a jaxtraj status ({', '.join(STATUS_NAMES)}).")
    return getattr(Status, name)


def load(folder):
    """`(Solution, Trajectory, summary)` from a folder written by `save` (or the CLI),
    parameters bit for bit and statuses as saved.

    **Raises:** `ValueError` naming the file and what is wrong when a file is missing,
    damaged, or `arrays.npz` does not belong to `summary.json`.
    """
    summary_path = os.path.join(folder, "summary.json")
    arrays_path = os.path.join(folder, "arrays.npz")
    for path in (summary_path, arrays_path):
        if not os.path.isfile(path):
            raise ValueError(f"{path}: missing (not a jaxtraj result folder, or an interrupted save).")
    summary = read_json(summary_path)
    expected = summary.get("arrays_sha256")
    if expected is not None and _sha256(arrays_path) != expected:
        raise ValueError(
            f"{arrays_path}: does not belong to {summary_path} (checksum differs: another or an interrupted save)."
        )
    try:
        with np.load(arrays_path) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{arrays_path}: damaged ({e}).") from None

    def need(source, key, path):
        if key not in source:
            raise ValueError(f"{path}: `{key}` is missing.")
        value = source[key]
        return jnp.asarray(jnp.nan if value is None else value)

    history = History(
        **{k: need(arrays, f"history_{k}", arrays_path) for k in _HISTORY_FIELDS},
        details={k[len(_DETAIL) :]: jnp.asarray(v) for k, v in arrays.items() if k.startswith(_DETAIL)},
    )
    sol = Solution(
        params=need(arrays, "params", arrays_path),
        tf=need(summary, "tf", summary_path),
        objective=need(summary, "objective", summary_path),
        constraints=need(arrays, "constraints", arrays_path),
        max_constraint_error=need(summary, "max_constraint_error", summary_path),
        projected_gradient=need(summary, "projected_gradient", summary_path),
        iterations=need(summary, "iterations", summary_path),
        integrations=need(summary, "integrations", summary_path),
        steps=need(summary, "steps", summary_path),
        status=_status(summary.get("status"), summary_path, "status"),
        history=history,
        max_path_constraint=None
        if "max_path_constraint" not in summary
        else need(summary, "max_path_constraint", summary_path),
        max_path_time=None if "max_path_time" not in summary else need(summary, "max_path_time", summary_path),
        terminal_inequality=None
        if "terminal_inequality" not in arrays
        else need(arrays, "terminal_inequality", arrays_path),
    )
    traj = Trajectory(
        t=need(arrays, "t", arrays_path),
        x=need(arrays, "x", arrays_path),
        u=need(arrays, "u", arrays_path),
        knots=need(arrays, "knots", arrays_path),
        xf=need(arrays, "xf", arrays_path),
        status=_status(summary.get("trajectory_status", "SUCCESS"), summary_path, "trajectory_status"),
    )
    return sol, traj, summary
