"""`jt.enable_compilation_cache`: compiled solvers kept on disk across Python processes."""

import os

import jax


def _jaxtraj_cache_home() -> str:
    return os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "jaxtraj")


def default_cache_folder() -> str:
    """`$JAXTRAJ_CACHE_DIR`, else `$XDG_CACHE_HOME/jaxtraj/xla` (`~/.cache/jaxtraj/xla`)."""
    return os.environ.get("JAXTRAJ_CACHE_DIR") or os.path.join(_jaxtraj_cache_home(), "xla")


def default_export_folder() -> str:
    """`$JAXTRAJ_CACHE_DIR/export`, else `$XDG_CACHE_HOME/jaxtraj/export` (the solve cache's;
    the parent of `default_cache_folder()` put it beside `$JAXTRAJ_CACHE_DIR`, outside it)."""
    env = os.environ.get("JAXTRAJ_CACHE_DIR")
    return os.path.join(env, "export") if env else os.path.join(_jaxtraj_cache_home(), "export")


def make_folder(folder, what: str = "`folder`") -> str | None:
    """`folder` (a str or os.PathLike) as a str, created if missing; None where the system
    refuses it (permissions, a full disk). A `ValueError` naming `what` (the argument, or the
    default folder's variable) for what is no folder at all: another type, an empty path, a
    NUL byte, a file or a path through one."""
    if not isinstance(folder, str | os.PathLike):  # (os' TypeError named no argument)
        raise ValueError(f"{what} must be None or a path (str or os.PathLike); got {type(folder).__name__}.")
    path = os.fspath(folder)
    if not isinstance(path, str) or not path or "\0" in path:  # (b"..." paths; "" was a silent None)
        raise ValueError(f"{what} must be a non-empty path without NUL bytes; got {folder!r}.")
    try:
        os.makedirs(path, exist_ok=True)
    except (FileExistsError, NotADirectoryError):  # (exist_ok: a file where the folder would be)
        raise ValueError(f"{what} must be a folder; {path!r} is a file or a path through one.") from None
    except OSError:
        return None
    return path


#: How `make_folder` names a default folder that is no folder (set by the environment).
DEFAULT_FOLDER = "The default folder (`$JAXTRAJ_CACHE_DIR`, else `$XDG_CACHE_HOME/jaxtraj`)"


def enable_compilation_cache(folder: str | os.PathLike | None = None) -> str | None:
    """Keep every compiled program on disk, so that a new Python process that runs the same
    solve again (same problem functions, control family and segment count, solver settings,
    simulator; any start) loads it instead of compiling it.

    A new problem still compiles: what this saves is the XLA compile of a script run again
    (on case 4, the default solver's first call 2.3 s -> about 0.8 s, the trace of the program
    that remains; benchmarks/RESULTS.md). This is JAX's persistent compilation cache
    (`jax_compilation_cache_dir`), with every program kept whatever its size or compile
    time; JAX keys each entry by the program, the backend and the JAX version, so a stale
    entry is never used. The `jaxtraj` command calls it for every run. Call it before the
    first solve of the process.

    **Arguments:**

    - `folder`: where the programs go (created if missing). Default: the folder JAX was
      already given (`jax.config.jax_compilation_cache_dir`), else `$JAXTRAJ_CACHE_DIR`, else
      `$XDG_CACHE_HOME/jaxtraj/xla` (`~/.cache/jaxtraj/xla`).

    **Returns:** the folder, or None if it cannot be created (no permission, a full disk;
    nothing is changed then).

    **Raises:** `ValueError` when `folder` is neither None nor a path, is empty, or names a
    file (or a path through one).
    """
    what = "`folder`" if folder is not None else DEFAULT_FOLDER
    if folder is None:
        folder = jax.config.jax_compilation_cache_dir or default_cache_folder()  # pyright: ignore[reportAttributeAccessIssue]  (JAX config options are dynamic attributes)
    folder = make_folder(folder, what)
    if folder is None:
        return None
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder
