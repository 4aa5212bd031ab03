"""`jt.enable_solve_cache`: a solve's program kept on disk as a `jax.export` artifact, so
that a script run again on an unchanged problem neither traces nor lowers it (issue 53).

Opt-in and process-wide, like `jt.enable_compilation_cache`: `jt.solve` keeps its
signature, and with the cache off nothing changes. With it on, a `jt.solve` whose inputs are
all concrete (not under the user's `jit`, `vmap` or a derivative, `progress=0`) runs the
exported program of `_driver.run` keyed on the problem's fingerprint (`_fingerprint.
problem_fingerprint`: what the problem computes, not its names), the static configuration
of problem and control, the solver, the simulator, `max_steps`, the shapes and dtypes of the
arrays (not their values: they are the program's inputs), the JAX and jaxlib versions,
JAX's options that change the traced program (`_OPTIONS`: matmul precision, ...),
jaxtraj's source and the backend. A miss exports the program once (the trace and lowering a
solve pays anyway) and writes it atomically (a temporary file renamed). A corrupt (its
program is checked by SHA-256), foreign or unreadable entry is ignored: the solve traces as
it would without the cache. Its XLA compile is kept by the compilation cache, which this
turns on.

A function rather than a `cache=` argument of `jt.solve`: a script turns it on once, as it
does the compilation cache it relies on; `jt.solve`'s signature, its jitted body and its
derivative rule stay as they are (the cached path is a branch before them); and every call
site of a script (examples, helper code) gains it without being edited.

The cached path serves the primal solve only: a derivative of `jt.solve` (its arguments are
tracers then) takes the ordinary, differentiable path. Entries are JAX's own serialization
(flatbuffers) with a JSON header, never pickles.
"""

import dataclasses
import functools
import hashlib
import importlib.util
import json
import os
import re
import tempfile
from typing import cast

import equinox as eqx
import jax
import jax.core
import numpy as np

from ._cache import DEFAULT_FOLDER, default_export_folder, enable_compilation_cache, make_folder
from ._fingerprint import fingerprint, problem_fingerprint, static_fingerprint
from ._solution import History, Solution
from ._status import Status

#: The entry format; an entry of another format is ignored.
FORMAT = "jaxtraj-solve-cache 2"
_MAGIC = b"JAXTRAJ-EXPORT\n"

_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
_folder: str | None = None
#: Exported programs of this process by the static part of the solve (what `jax.jit` keys
#: on: functions by identity), so that a warm solve pays no fingerprint.
_memory: dict = {}
_UNEXPORTABLE = object()


def enable_solve_cache(folder: str | os.PathLike | None = None) -> str | None:
    """Keep every solve's program on disk as a `jax.export` artifact, so that a new Python
    process that runs an unchanged problem again (same functions by what they compute, same
    arrays' shapes, control family, solver settings, simulator and `max_steps`; any start,
    any array values) neither traces nor lowers it: `jt.solve` loads the program and its
    compiled code (the compilation cache, turned on here in its default folder unless JAX
    already has one).

    Only a `jt.solve` outside the user's `jax.jit` / `jax.vmap` / derivatives, with
    `progress=0` and with jaxtraj's own solver, simulator and control classes uses it
    (derivatives take the ordinary path: the cached program is the primal solve; a class of
    the user's would be known by its name only, not its code). The key is the problem's fingerprint (what it computes: each call pays
    it, ~0.05 s, once per process per problem), so a changed constant in a dynamics function
    traces again; a host callback's Python body is not seen by it (see
    `_fingerprint.problem_fingerprint`). Call it before the first solve.

    **Arguments:**

    - `folder`: where the programs go (created if missing). Default `$JAXTRAJ_CACHE_DIR/
      export`, else `$XDG_CACHE_HOME/jaxtraj/export` (`~/.cache/jaxtraj/export`).

    **Returns:** the folder, or None if it cannot be created (no permission, a full disk) or
    JAX's serializer is missing (the `flatbuffers` package); nothing is changed then.

    **Raises:** `ValueError` when `folder` is neither None nor a path, is empty, or names a
    file (or a path through one).
    """
    global _folder
    what = "`folder`" if folder is not None else DEFAULT_FOLDER
    folder = make_folder(default_export_folder() if folder is None else folder, what)
    if folder is None or importlib.util.find_spec("flatbuffers") is None:  # (jax.export's serializer needs it)
        return None
    if not jax.config.jax_compilation_cache_dir:  # pyright: ignore[reportAttributeAccessIssue]
        try:
            enable_compilation_cache()
        except ValueError:  # (`$JAXTRAJ_CACHE_DIR` no folder: the programs are kept, not their compiles)
            pass
    _folder = folder
    _memory.clear()
    return folder


def disable_solve_cache() -> None:
    """Turn the solve cache off (the compilation cache stays as it is)."""
    global _folder
    _folder = None
    _memory.clear()


def usable(problem, control, a0, progress, solver, simulator) -> bool:
    """Whether this solve may take the cached path: the cache is on, `progress` is 0, no
    input is a tracer, and the problem, control, solver and simulator are jaxtraj's own
    classes (`_ours`; the problem's functions may be anything)."""
    if _folder is None or progress:
        return False
    # (the problem's functions, an equinox module of the user's among them, are keyed by what
    # they compute: `problem_fingerprint`)
    if not (_ours((control, solver, simulator)) and _library_class(problem)):
        return False
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((problem, control, a0)))


#: Whose classes may be in a cached solve: jaxtraj's, and the libraries' of `jt.Diffrax` (their
#: versions are in the key).
_LIBRARIES = ("jaxtraj", "diffrax", "equinox", "lineax", "optimistix")


def _library_class(x) -> bool:
    return type(x).__module__.partition(".")[0] in _LIBRARIES


def _ours(x) -> bool:
    """Whether every equinox module in `x` (and in those it holds) is a class of jaxtraj's (or
    of a library of `_LIBRARIES`): the key sees another class by its name and fields only
    (`static_fingerprint`), not by what its methods compute, so a user's own solver, simulator or control (or a subclass),
    edited between runs or two of one name, shared an entry and answered with the other's
    program. Those solve as without the cache."""
    if isinstance(x, eqx.Module):
        if not _library_class(x):
            return False
        return all(_ours(getattr(x, f.name, None)) for f in dataclasses.fields(x))
    if isinstance(x, tuple | list):
        return all(_ours(v) for v in x)
    if isinstance(x, dict):
        return all(_ours(v) for v in x.values())
    return True


#: JAX's options that change what a traced program computes (`jax.jit` keys on them too): a
#: program exported under `jax.default_matmul_precision("bfloat16")` was served under the
#: default precision, and the other way round.
_OPTIONS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion")


def _options() -> str:
    """The values of `_OPTIONS` now (a context manager's included)."""
    return "; ".join(f"{name}={getattr(jax.config, name)}" for name in _OPTIONS)


def _key(solver, a0, simulator, max_steps, dynamic, static) -> str:
    h = hashlib.sha256(FORMAT.encode())
    for part in (jax.__version__, _library_versions(), _version(), jax.default_backend(), str(max_steps), _options()):
        h.update(part.encode() + b"\0")
    # the problem's and control's arrays are the program's inputs, not part of it: their
    # values (zeros here) stay out of the key, so that new `args` or `x0` hit the entry
    problem, control = eqx.combine(jax.tree.map(lambda x: np.zeros(np.shape(x), x.dtype), dynamic), static)
    h.update(problem_fingerprint(_built_bounds(problem), control, simulator).encode())
    # (the arrays by dtype and shape: their values are the program's inputs)
    h.update(static_fingerprint((static, dynamic, a0)).encode())
    # the solver's and simulator's arrays (e.g. `ctol=jnp.asarray(1e-12)`) are constants of the
    # program, not inputs: their values too, or another tolerance answered with this program
    h.update(fingerprint((solver, simulator)).encode())
    return h.hexdigest()


def _built_bounds(problem):
    """`problem` with its control-bound arrays at the values it was built with (its static
    copy, in the key already): zeros there are refused as changed bounds (`_checks.
    BOUNDS_CHANGED`), and a bounded problem never used the cache."""
    for name, box in zip(("control_lower", "control_upper"), problem._control_box):
        value = getattr(problem, name)
        if value is not None:
            built = np.asarray(box, np.dtype(value.dtype)).reshape(np.shape(value))
            problem = eqx.tree_at(lambda p, name=name: getattr(p, name), problem, built)
    return problem


@functools.cache
def _library_versions() -> str:
    from importlib.metadata import PackageNotFoundError, version

    parts = []
    for name in ("jaxlib", *_LIBRARIES[1:]):  # (a library's classes are seen by name: its version too)
        try:
            parts.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            parts.append(f"{name} -")
    return "; ".join(parts)


@functools.cache
def _version() -> str:
    """SHA-256 of jaxtraj's own source files: a program exported by other solver code (another
    version, or a checkout edited since) is never used."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for folder, dirs, files in sorted(os.walk(root)):
        dirs.sort()
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            h.update(os.path.relpath(path, root).encode() + b"\0")
            with open(path, "rb") as f:
                h.update(f.read())
    return h.hexdigest()


def _template(layout):
    """A `Solution` of placeholder leaves with `layout`'s structure (`_layout`), built
    without tracing anything."""
    z = cast(jax.Array, np.zeros(()))  # (a placeholder leaf: no JAX array, no dispatch)
    history = History(
        **{f.name: z for f in dataclasses.fields(History) if f.name != "details"},
        details={k: z for k in layout["details"]},
    )
    fields = {f.name: (None if f.name in layout["none"] else z) for f in dataclasses.fields(Solution)}
    return Solution(**{**fields, "status": Status.SUCCESS, "history": history})


def _layout(sol) -> dict:
    return {
        "none": sorted(f.name for f in dataclasses.fields(Solution) if getattr(sol, f.name) is None),
        "details": list(sol.history.details),
    }


def _structure(layout) -> str:
    return _ADDRESS.sub("", str(jax.tree.structure(_template(layout))))


def _path(key) -> str:
    assert _folder is not None
    return os.path.join(_folder, f"solve-{key}.jaxexport")


def _write(key, layout, exported) -> None:
    tmp = None
    try:
        blob = bytes(exported.serialize())
        digest = hashlib.sha256(blob).hexdigest()  # (a changed byte of the program: its constants too)
        header = json.dumps(
            {"format": FORMAT, "key": key, "layout": layout, "structure": _structure(layout), "sha256": digest}
        )
        fd, tmp = tempfile.mkstemp(dir=_folder, prefix=".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(_MAGIC + header.encode() + b"\n" + blob)
        os.replace(tmp, _path(key))
        tmp = None
    except Exception:
        pass  # (a read-only or full disk, a program JAX cannot serialize: the solve goes on without the entry)
    finally:
        if tmp is not None:  # (a half-written file was left in the folder for good)
            try:
                os.remove(tmp)
            except OSError:
                pass


def _read(key, args):
    """`(exported, layout)` of the entry for `key`, or None: missing, corrupt, foreign (another
    key, format or structure) or for other argument shapes."""
    try:
        with open(_path(key), "rb") as f:
            data = f.read()
        if not data.startswith(_MAGIC):
            return None
        header, _, blob = data[len(_MAGIC) :].partition(b"\n")
        meta = json.loads(header)
        if meta.get("format") != FORMAT or meta.get("key") != key:
            return None
        if meta.get("sha256") != hashlib.sha256(blob).hexdigest():  # (a flipped constant ran)
            return None
        layout = meta["layout"]
        if _structure(layout) != meta["structure"]:
            return None
        exported = jax.export.deserialize(bytearray(blob))
        avals = [(tuple(a.shape), np.dtype(a.dtype)) for a in exported.in_avals]
        if avals != [(tuple(np.shape(x)), np.dtype(x.dtype)) for x in args]:
            return None
        return exported, layout
    except Exception:  # (any unreadable entry: trace instead)
        return None


def _memo_key(solver, simulator, max_steps, treedef, static, args):
    """This process' key of the program (as `jax.jit` keys its static arguments), or None
    where the static part is unhashable (then the disk only)."""
    try:
        static_leaves, static_def = jax.tree.flatten(static)
        shapes = tuple((np.shape(x), x.dtype, getattr(x, "weak_type", False)) for x in args)
        memo_key = (treedef, static_def, tuple(static_leaves), solver, simulator, max_steps, shapes, _options())
        hash(memo_key)
    except TypeError:
        return None
    return memo_key


def _export(run, solver, simulator, max_steps, treedef, static, args):
    """`(exported, layout)` of the driver's program at `args`, or None where it cannot be
    exported (a host callback) or rebuilt from its layout."""
    seen = {}

    def flat(a0, *leaves):
        p, c = eqx.combine(jax.tree.unflatten(treedef, leaves), static)
        sol = run(solver, p, c, a0, simulator, max_steps)
        seen["layout"] = _layout(sol)
        seen["structure"] = _ADDRESS.sub("", str(jax.tree.structure(sol)))
        return jax.tree.leaves(sol)

    try:
        exported = jax.export.export(jax.jit(flat))(*args)
    except Exception:
        return None
    if seen["structure"] != _structure(seen["layout"]):
        return None
    return exported, seen["layout"]


def _remove(key) -> None:
    try:
        os.remove(_path(key))
    except OSError:
        pass


def cached_solve(run, solver, problem, control, a0, simulator, max_steps):
    """`run(solver, problem, control, a0, simulator, max_steps)` (the driver) through the
    exported program: from this process' memory, else from disk, else exported now and
    written. Returns None where the program cannot be exported (the caller solves as usual)."""
    dynamic, static = eqx.partition((problem, control), eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    args = [a0, *leaves]
    memo_key = _memo_key(solver, simulator, max_steps, treedef, static, args)
    entry = _memory.get(memo_key) if memo_key is not None else None
    if entry is _UNEXPORTABLE:
        return None
    if entry is not None:
        call, structure = entry
        return jax.tree.unflatten(structure, call(*args))
    try:
        key = _key(solver, a0, simulator, max_steps, dynamic, static)
    except Exception:  # (e.g. a function closing over a tracer, under the user's grad)
        return None
    found = _read(key, args)
    if found is None:
        found = _export(run, solver, simulator, max_steps, treedef, static, args)
        if found is None:
            if memo_key is not None:  # (not tried again in this process)
                _memory[memo_key] = _UNEXPORTABLE
            return None
        _write(key, found[1], found[0])
    exported, layout = found
    call, structure = jax.jit(exported.call), jax.tree.structure(_template(layout))
    try:
        out = call(*args)  # (the first call lowers the stored module: it may be corrupt)
    except Exception:
        _remove(key)  # (so that the next run exports it again)
        return None
    if memo_key is not None:
        _memory[memo_key] = call, structure
    return jax.tree.unflatten(structure, out)
