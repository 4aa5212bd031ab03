"""Result folders: `summary.json` (inputs, outputs, status) + `arrays.npz` (parameters,
dense trajectory, history). A folder is written whole or not at all (`staged_folder`: the
files go into a temporary folder inside it and are moved into place, the summary last, with
the checksum of the arrays it belongs to), and every file is written atomically (temporary
file + rename). `load(dir)` gives
the Solution and Trajectory back, parameters bit for bit, or a ValueError that names the
damaged file. `folder_lock` keeps two runs out of one folder."""

import contextlib
import hashlib
import json
import math
import os
import shutil
import socket
import tempfile
import zipfile

import jax.numpy as jnp
import numpy as np
import numpy.typing as npt

from ._checks import require_float64
from ._problem import Problem
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


#: The hidden list of the entries the last `staged_folder` put in a folder.
_LISTING = ".jaxtraj-files"
_PARTIAL = ".partial-"


def _remove(path):
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)


def _remove_abandoned_stages(folder):
    """Remove the temporary folders that a killed process of this machine left in `folder`
    (named `.partial-<host>-<pid>-...`, their process gone)."""
    host = socket.gethostname()
    for entry in os.listdir(folder):
        parts = entry[len(_PARTIAL) :].split("-") if entry.startswith(_PARTIAL) else []
        if len(parts) < 3 or "-".join(parts[:-2]) != host or not parts[-2].isdigit():
            continue
        try:
            os.kill(int(parts[-2]), 0)
        except ProcessLookupError:
            _remove(os.path.join(folder, entry))
        except OSError:  # alive (another user's process) or unknowable: keep it
            pass


@contextlib.contextmanager
def staged_folder(folder, what="`folder`"):
    """Write a result folder whole: yields a new temporary folder inside `folder` (created
    if missing, through a symbolic link as given) to write into. When the block ends, its
    entries replace `folder`'s one by one, `summary.json` last (its checksum ties it to its
    arrays: `load` refuses a mix), and the entries of the previous result that this one does
    not have (a figure it did not draw) are removed; other entries of `folder` (a batch to
    resume, a user's file) are kept. When the block raises, the temporary folder is deleted
    and `folder` is untouched (not created, if it was missing). Staging inside `folder` needs nothing of its parent (it may be
    read-only); a temporary folder left by a killed process is removed by the next write.

    Renames are what the standard library offers for this (`os.replace` within a folder is
    atomic on POSIX); no library writes a folder transactionally.

    **Raises:** `ValueError` naming `what` when `folder` is a file.
    """
    folder = os.path.abspath(os.fspath(folder))
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"{what}: {folder!r} is a file, not a folder.")
    created = not os.path.lexists(folder)
    os.makedirs(folder, exist_ok=True)
    _remove_abandoned_stages(folder)
    stage = tempfile.mkdtemp(dir=folder, prefix=f"{_PARTIAL}{socket.gethostname()}-{os.getpid()}-")
    try:
        yield stage
        new = sorted((e for e in os.listdir(stage) if e != _LISTING), key=lambda n: n == "summary.json")
        try:
            with open(os.path.join(folder, _LISTING)) as f:
                old = set(json.load(f))
        except (OSError, ValueError):
            old = set()
        for entry in new:
            target = os.path.join(folder, entry)
            if os.path.isdir(target) and not os.path.islink(target):  # a folder is not replaced by a rename
                shutil.rmtree(target)
            os.replace(os.path.join(stage, entry), target)
        for entry in old - set(new):
            if entry and os.sep not in entry and not entry.startswith("."):
                _remove(os.path.join(folder, entry))
        atomic_write(os.path.join(folder, _LISTING), lambda f: f.write(json.dumps(new).encode()))
        shutil.rmtree(stage)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(folder)  # a failed first write leaves no (empty) folder
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
    Monte Carlo results; its keys may not replace the summary's own). Returns the summary (a
    dict).

    **Raises:** `ValueError` naming the argument when `problem` is not a `jt.Problem`, `sol`
    is not one (unbatched) `jt.Solution`, `traj` not a `jt.Trajectory` of its parameters
    (another tf, or a final state whose terminal constraints, objective or terminal
    inequalities differ from `sol`'s by more than 1e-6 relative: simulate `sol.params` with
    the solve's simulator), `inputs` or `extra` cannot be written as JSON or `extra` names a key of the
    summary (nothing is written then), or when `folder` is a file.
    """
    if not isinstance(folder, str | os.PathLike):  # (os' TypeError named no argument)
        raise ValueError(f"`folder` must be a path (str or os.PathLike); got {type(folder).__name__}.")
    if not isinstance(problem, Problem):
        raise ValueError(f"`problem` must be the jt.Problem that `sol` solves; got {type(problem).__name__}.")
    if extra is not None and not isinstance(extra, dict):
        raise ValueError(f"`extra` must be a dict of more summary entries (or None); got {type(extra).__name__}.")
    if not isinstance(sol, Solution) or np.shape(sol.tf) != ():
        raise ValueError(f"`sol` must be one jt.Solution (a batch's `sols[i]`); got {_describe(sol)}.")
    if not isinstance(traj, Trajectory) or np.ndim(traj.knots) != 1:
        raise ValueError(f"`traj` must be one jt.Trajectory (jt.simulate of `sol.params`); got {_describe(traj)}.")
    # (a NONFINITE solve without a finite point reports tf = NaN: its trajectory is the start's)
    pointless = sol.status == Status.NONFINITE and np.isnan(float(sol.tf))
    if not pointless and not np.array_equal(np.asarray(traj.knots)[-1:], np.asarray(sol.tf)[None], equal_nan=True):
        raise ValueError(
            f"`traj` ends at t = {float(np.asarray(traj.knots)[-1])!r}, `sol` at tf = {float(sol.tf)!r}: "
            "save the trajectory of `sol.params` (jt.simulate(problem, control, sol.params))."
        )
    if not pointless:
        _check_trajectory_values(problem, sol, traj)
    n = int(sol.steps)
    arrays = {
        "params": np.asarray(sol.params),
        "constraints": np.asarray(sol.constraints),
        "multipliers": np.asarray(sol.multipliers),
        **({} if sol.terminal_inequality is None else {"terminal_inequality": np.asarray(sol.terminal_inequality)}),
        **(
            {}
            if sol.terminal_inequality_multipliers is None
            else {"terminal_inequality_multipliers": np.asarray(sol.terminal_inequality_multipliers)}
        ),
        "t": np.asarray(traj.t),
        "x": np.asarray(traj.x),
        "u": np.asarray(traj.u),
        "knots": np.asarray(traj.knots),
        "xf": np.asarray(traj.xf),
        # (the summary's numbers again, exact: `load` checks the summary against them)
        "objective": np.asarray(sol.objective, dtype=np.float64),
        "projected_gradient": np.asarray(sol.projected_gradient, dtype=np.float64),
        "iterations": np.asarray(int(sol.iterations), dtype=np.int64),
        **{f"history_{k}": np.asarray(getattr(sol.history, k))[:n] for k in _HISTORY_FIELDS},
        **{f"{_DETAIL}{k}": np.asarray(v)[:n] for k, v in sol.history.details.items()},
    }
    outputs = {
        "tf": float(sol.tf),
        "objective": float(sol.objective),
        "max_constraint_error": float(sol.max_constraint_error),
        "max_violation": float(sol.max_violation),
        "projected_gradient": float(sol.projected_gradient),
    }
    if sol.max_path_constraint is not None:
        outputs["max_path_constraint"] = float(sol.max_path_constraint)
        outputs["max_path_time"] = float(sol.max_path_time)  # pyright: ignore[reportArgumentType]  (set with max_path_constraint)
    named = lambda names, values: {name: float(v) for name, v in zip(names, np.asarray(values))}
    inequalities = problem.terminal_inequality_names
    summary = {
        "problem": problem.name,
        "inputs": inputs or {},
        "status": status_name(sol.status),
        "message": Status[sol.status] or "converged",
        "trajectory_status": status_name(traj.status),
        **outputs,
        "constraints": named(problem.constraint_names, sol.constraints),
        "multipliers": named(problem.constraint_names, sol.multipliers),
        **(
            {}
            if sol.terminal_inequality is None
            else {"terminal_inequality": named(inequalities, sol.terminal_inequality)}
        ),
        **(
            {}
            if sol.terminal_inequality_multipliers is None
            else {"terminal_inequality_multipliers": named(inequalities, sol.terminal_inequality_multipliers)}
        ),
        "weakly_active": bool(sol.weakly_active),
        "iterations": int(sol.iterations),
        "integrations": int(sol.integrations),
        "steps": n,
        "params": np.asarray(sol.params).tolist(),
        "nonfinite": [k for k, v in outputs.items() if not math.isfinite(v)],
    }
    clash = sorted(set(extra or {}) & (set(summary) | {"arrays_sha256", "max_path_constraint", "max_path_time"}))
    if clash:
        raise ValueError(f"`extra` may not replace the summary's own entries; got {clash}.")
    summary.update(extra or {})
    for key in ("inputs", *(extra or {})):
        try:
            json.dumps(_jsonable(summary[key]), allow_nan=False)
        except (TypeError, ValueError) as e:
            raise ValueError(f"`{key}` cannot be written as JSON: {e}") from None
    with staged_folder(folder) as stage:
        arrays_path = os.path.join(stage, "arrays.npz")
        # (the checker matches `**arrays` to savez's `allow_pickle` too; no key is "allow_pickle")
        atomic_write(arrays_path, lambda f: np.savez(f, **arrays))  # pyright: ignore[reportArgumentType]
        summary["arrays_sha256"] = _sha256(arrays_path)
        summary = _jsonable(summary)
        text = json.dumps(summary, indent=2, allow_nan=False).encode()
        atomic_write(os.path.join(stage, "summary.json"), lambda f: f.write(text))
    return summary


#: How far the values at `traj`'s final state may be from `sol`'s, relative to max(1, |value|):
#: round-off between the solver's and `jt.simulate`'s compiled integration (about 1e-15), or a
#: somewhat finer simulator; another parameter vector moves them by far more.
_TRAJECTORY_RTOL = 1e-6


def _check_trajectory_values(problem, sol, traj):
    """`traj` is the trajectory of `sol.params`: its final state gives `sol`'s terminal
    constraints, objective and terminal inequalities (the problem's functions at (tf, xf);
    no integration). A value `sol` does not know (non-finite) is not compared."""
    tf, xf = jnp.asarray(traj.knots)[-1], jnp.asarray(traj.xf)
    pairs = [("constraints", problem.terminal, sol.constraints), ("objective", problem.objective, sol.objective)]
    if problem.terminal_inequality is not None and sol.terminal_inequality is not None:
        pairs.append(("terminal_inequality", problem.terminal_inequality, sol.terminal_inequality))
    for name, fn, value in pairs:
        value = np.atleast_1d(np.asarray(value, dtype=np.float64))
        try:
            got = np.atleast_1d(np.asarray(fn(tf, xf, problem.args), dtype=np.float64))
        except Exception as e:  # a trajectory of another problem (another state size)
            raise ValueError(
                f"`traj` does not fit `problem` ({type(e).__name__} evaluating its {name} at the final state)."
            ) from None
        known = np.isfinite(value)
        off = known & ~(np.abs(got - value) <= _TRAJECTORY_RTOL * np.maximum(1.0, np.abs(value)))
        if got.shape != value.shape or off.any():
            i = int(np.argmax(off)) if got.shape == value.shape else 0
            raise ValueError(
                f"`traj` is not the trajectory of `sol.params`: its final state gives {name} "
                f"{got.tolist() if got.shape != value.shape else float(got[i])!r}, `sol` has "
                f"{value.tolist() if got.shape != value.shape else float(value[i])!r} (it ends at the same tf: "
                "another parameter vector). Save jt.simulate(problem, control, sol.params) with the solve's simulator."
            )


def _describe(value) -> str:
    # (np.shape(None) is (): NumPy's annotations leave None out)
    shape = np.shape(getattr(value, "tf", getattr(value, "knots", None)))  # pyright: ignore[reportArgumentType, reportCallIssue]
    return f"{type(value).__name__}" + (f" with a batch axis {shape}" if shape else "")


def _refuse_constant(token):
    raise ValueError(f"{token} is not strict JSON")


def read_json(path) -> dict:
    """The JSON object in `path`, or a ValueError naming the file ("damaged") when it is not
    one (truncated, empty, not an object)."""
    try:
        with open(path) as f:
            value = json.load(f, parse_constant=_refuse_constant)
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

    The summary and the arrays are checked against each other before anything is returned:
    the arrays' checksum (a summary without one is refused), the parameters, constraint and
    terminal-inequality values written in both, the objective, projected gradient and
    iteration count against their copies in the arrays (a NaN of a non-finite solve equals
    NaN; a folder saved before the copies existed has none to check), `max_constraint_error`
    against the constraints, tf against the last knot, the trajectory's shapes and knot
    order, the step counts against the history's length (iterations <= steps <=
    integrations); the summary must be strict JSON. A folder written before `max_violation`, `weakly_active` and the
    multipliers existed loads with them NaN (unknown) and False.

    **Raises:** `ValueError` naming the file and what is wrong when a file is missing,
    damaged, or `arrays.npz` does not belong to `summary.json`; `RuntimeError` when JAX's
    float64 mode is off (as every entry point).
    """
    require_float64()
    if not isinstance(folder, str | os.PathLike):
        raise ValueError(f"`folder` must be a path (str or os.PathLike); got {type(folder).__name__}.")
    summary_path = os.path.join(folder, "summary.json")
    arrays_path = os.path.join(folder, "arrays.npz")
    for path in (summary_path, arrays_path):
        if not os.path.isfile(path):
            raise ValueError(f"{path}: missing (not a jaxtraj result folder, or an interrupted save).")
    summary = read_json(summary_path)
    expected = summary.get("arrays_sha256")
    if not isinstance(expected, str):
        raise ValueError(
            f"{summary_path}: `arrays_sha256` is missing, so {arrays_path} cannot be checked against it "
            "(not written by jaxtraj.io.save, or edited)."
        )
    if _sha256(arrays_path) != expected:
        raise ValueError(
            f"{arrays_path}: does not belong to {summary_path} (checksum differs: another or an interrupted save)."
        )
    try:
        # (opened here: `np.load` of a cut zip raises with its own file left open)
        with open(arrays_path, "rb") as handle, np.load(handle) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{arrays_path}: damaged ({e}).") from None

    def array(key, ndim, dtype: npt.DTypeLike = np.float64):
        if key not in arrays:
            raise ValueError(f"{arrays_path}: `{key}` is missing.")
        value = arrays[key]
        if value.ndim != ndim or value.dtype != dtype:
            raise ValueError(
                f"{arrays_path}: `{key}` must be a {ndim}-d {np.dtype(dtype)} array; got {value.dtype} {value.shape}."
            )
        return value

    def number(key, default=None):
        if key not in summary and default is None:
            raise ValueError(f"{summary_path}: `{key}` is missing.")
        value = summary.get(key, default)
        if value is None:  # a non-finite number (strict JSON)
            return np.float64(np.nan)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{summary_path}: `{key}` must be a number; got {value!r}.")
        return np.float64(value)

    def count(key):
        value = summary.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**31:
            raise ValueError(f"{summary_path}: `{key}` must be an int in 0..2**31 - 1; got {value!r}.")
        return value

    def flag(key):  # (False in folders saved before the flag existed)
        value = summary.get(key, False)
        if not isinstance(value, bool):
            raise ValueError(f"{summary_path}: `{key}` must be true or false; got {value!r}.")
        return value

    def floats(values):  # JSON numbers (null: non-finite) as float64, else None
        if not all(v is None or (isinstance(v, int | float) and not isinstance(v, bool)) for v in values):
            return None
        return np.array([np.nan if v is None else v for v in values], dtype=np.float64)

    def same(listed, values):
        listed = floats(listed)
        return listed is not None and np.array_equal(listed, values, equal_nan=True)

    def contradicts(what, detail):
        raise ValueError(f"{summary_path}: {what} contradicts {arrays_path} ({detail}; another or an edited save).")

    params, constraints = array("params", 1), array("constraints", 1)
    listed = summary.get("params")
    if not isinstance(listed, list) or not same(listed, params):
        contradicts("`params`", f"{len(params)} parameters there")
    named = summary.get("constraints")
    if not isinstance(named, dict) or not same(list(named.values()), constraints):
        contradicts("`constraints`", f"{len(constraints)} constraint values there")
    history = {k: array(f"history_{k}", 1, bool if k == "accepted" else np.float64) for k in _HISTORY_FIELDS}
    details = {k[len(_DETAIL) :]: array(k, 1) for k in arrays if k.startswith(_DETAIL)}
    steps, iterations, integrations = count("steps"), count("iterations"), count("integrations")
    lengths = {v.shape[0] for v in (*history.values(), *details.values())}
    if lengths != {steps}:
        contradicts(f"`steps` = {steps}", f"history of length {sorted(lengths)}")
    if not iterations <= steps <= integrations:
        raise ValueError(
            f"{summary_path}: the counts contradict each other (iterations {iterations} <= steps {steps} "
            f"<= integrations {integrations} does not hold; an edited save)."
        )
    if not np.array_equal(number("max_constraint_error"), np.max(np.abs(constraints), initial=0.0), equal_nan=True):
        contradicts("`max_constraint_error`", "max |constraints| there")
    tf, knots = number("tf"), array("knots", 1)
    pointless = summary.get("status") == "NONFINITE" and np.isnan(tf)  # (as `save`)
    if not knots.size or not (pointless or np.array_equal(tf, knots[-1], equal_nan=True)):
        contradicts(f"`tf` = {float(tf)!r}", f"last knot {float(knots[-1]) if knots.size else None!r}")
    if np.any(np.diff(knots) < 0):
        contradicts("the trajectory", "its knots are out of order")
    # (within round-off: folders saved before the segments ended at their knots exactly have
    # a segment's last time an ulp past the next segment's first)
    dt = np.diff(array("t", 1))
    if np.any(dt < -1e-12 * np.sum(np.abs(dt))):
        contradicts("the trajectory", "its times are out of order")
    t, x, u, xf = array("t", 1), array("x", 2), array("u", 2), array("xf", 1)
    if not (t.shape[0] == x.shape[0] == u.shape[0] and x.shape[1] == xf.shape[0]):
        contradicts("the trajectory", f"t {t.shape}, x {x.shape}, u {u.shape}, xf {xf.shape} do not fit together")
    terminal_inequality = None
    if ("terminal_inequality" in arrays) != ("terminal_inequality" in summary):
        contradicts("`terminal_inequality`", "one file has it, the other not")
    if "terminal_inequality" in arrays:
        terminal_inequality = array("terminal_inequality", 1)
        named = summary["terminal_inequality"]
        if not isinstance(named, dict) or not same(list(named.values()), terminal_inequality):
            contradicts("`terminal_inequality`", f"{len(terminal_inequality)} values there")
        terminal_inequality = jnp.asarray(terminal_inequality)

    # multipliers (NaN, unknown, in folders saved before they were saved)
    def multipliers(key, size):
        if (key in arrays) != (key in summary):
            contradicts(f"`{key}`", "one file has it, the other not")
        if key not in arrays:
            return jnp.full(size, jnp.nan)
        values, named = array(key, 1), summary[key]
        if values.shape[0] != size or not isinstance(named, dict) or not same(list(named.values()), values):
            contradicts(f"`{key}`", f"{len(values)} values there for {size} constraints")
        return jnp.asarray(values)

    lam = multipliers("multipliers", constraints.shape[0])
    nu = (
        None
        if terminal_inequality is None
        else multipliers("terminal_inequality_multipliers", terminal_inequality.shape[0])
    )
    # the summary's own numbers: max_violation is the largest of its parts, a norm is >= 0
    max_violation, projected_gradient = number("max_violation", default=np.nan), number("projected_gradient")
    parts = [number("max_constraint_error"), 0.0]
    parts += [] if terminal_inequality is None else list(np.asarray(terminal_inequality))
    parts += [number("max_path_constraint")] if "max_path_constraint" in summary else []
    if np.isfinite(max_violation) and not max_violation >= np.nanmax(parts):
        raise ValueError(
            f"{summary_path}: `max_violation` = {float(max_violation)!r} is below one of its parts "
            f"(the largest: {float(np.nanmax(parts))!r}; an edited save)."
        )
    if projected_gradient < 0:
        raise ValueError(f"{summary_path}: `projected_gradient` is a norm; got {float(projected_gradient)!r}.")
    # the summary's objective, projected gradient and iteration count against their exact
    # copies in the arrays (folders saved before those copies existed have none)
    for key, value in (
        ("objective", number("objective")),
        ("projected_gradient", number("projected_gradient")),
        ("iterations", iterations),
    ):
        if key not in arrays:
            continue
        stored = array(key, 0, np.int64 if key == "iterations" else np.float64)
        # (null in the summary stands for any non-finite number: NaN or +-inf)
        if not (stored == value or (np.isnan(value) and not np.isfinite(stored))):
            contradicts(f"`{key}` = {np.asarray(value).item()!r}", f"{stored.item()!r} there")
    # SUCCESS promises feasibility within the solver's tolerance (the history's last entry)
    status = _status(summary.get("status"), summary_path, "status")
    tol = history["constraint_tolerance"][-1] if steps else np.nan
    if status == Status.SUCCESS and np.isfinite(tol) and np.isfinite(max_violation) and max_violation > tol:
        contradicts(
            f"status SUCCESS with `max_violation` = {float(max_violation)!r}",
            f"the solver's constraint tolerance {float(tol)!r} in its history",
        )
    sol = Solution(
        params=jnp.asarray(params),
        tf=jnp.asarray(tf),
        objective=jnp.asarray(number("objective")),
        constraints=jnp.asarray(constraints),
        max_constraint_error=jnp.asarray(number("max_constraint_error")),
        max_violation=jnp.asarray(max_violation),
        multipliers=lam,
        weakly_active=jnp.asarray(flag("weakly_active")),
        projected_gradient=jnp.asarray(projected_gradient),
        iterations=jnp.asarray(iterations),
        integrations=jnp.asarray(integrations),
        steps=jnp.asarray(steps),
        status=status,
        history=History(
            **{k: jnp.asarray(v) for k, v in history.items()}, details={k: jnp.asarray(v) for k, v in details.items()}
        ),
        max_path_constraint=None
        if "max_path_constraint" not in summary
        else jnp.asarray(number("max_path_constraint")),
        max_path_time=None if "max_path_time" not in summary else jnp.asarray(number("max_path_time")),
        terminal_inequality=terminal_inequality,
        terminal_inequality_multipliers=nu,
    )
    traj = Trajectory(
        t=jnp.asarray(t),
        x=jnp.asarray(x),
        u=jnp.asarray(u),
        knots=jnp.asarray(knots),
        xf=jnp.asarray(xf),
        status=_status(summary.get("trajectory_status", "SUCCESS"), summary_path, "trajectory_status"),
    )
    return sol, traj, summary
