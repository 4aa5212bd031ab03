"""Result folders of a batch: the run's fingerprint, `manifest.json` and the chunk files,
written atomically and checked on resume."""

import hashlib
import json
import os
import re

import jax
import numpy as np

from .. import io as _io

#: Format tag of `manifest.json`.
FORMAT = "jaxtraj-batch-1"


def fingerprint(tree) -> str:
    """SHA-256 of a pytree's structure and leaves that is stable across processes: array
    leaves by dtype, shape and bytes; functions by module and qualified name; others by repr
    (memory addresses removed)."""
    leaves, treedef = jax.tree.flatten(tree)
    h = hashlib.sha256(re.sub(r" at 0x[0-9a-fA-F]+", "", str(treedef)).encode())
    for leaf in leaves:
        if isinstance(leaf, (np.ndarray, jax.Array, np.generic)):
            arr = np.ascontiguousarray(np.asarray(leaf))
            h.update(f"array {arr.dtype} {arr.shape}".encode() + arr.tobytes())
        elif callable(leaf) and hasattr(leaf, "__qualname__"):
            h.update(f"callable {getattr(leaf, '__module__', '?')}.{leaf.__qualname__}".encode())
        else:
            h.update(re.sub(r" at 0x[0-9a-fA-F]+", "", repr(leaf)).encode())
    return h.hexdigest()


def chunk_path(out, k):
    return os.path.join(out, f"chunk_{k:05d}.npz")


def write_chunk(out, k, leaves):
    arrays = {f"leaf_{i:03d}": x for i, x in enumerate(leaves)}
    _io.atomic_write(chunk_path(out, k), lambda f: np.savez(f, **arrays))


def read_chunk(out, k, rows, spec):
    path = chunk_path(out, k)
    with np.load(path) as data:
        leaves = [data[f"leaf_{i:03d}"] for i in range(len(spec))] if len(data.files) == len(spec) else None
    if leaves is None or any(x.shape != (rows, *s) or x.dtype != d for x, (s, d) in zip(leaves, spec)):
        raise ValueError(
            f"`out`: {path} does not hold {rows} solutions of this batch's layout; delete it to recompute it."
        )
    return leaves


def prepare_out(out, manifest, resume, writer):
    """Create `out` and its manifest (process 0), or check an existing manifest against
    this run's."""
    path = os.path.join(out, "manifest.json")
    if os.path.exists(path):
        if not resume:
            if writer:  # (other processes may see the manifest process 0 just wrote)
                raise ValueError(
                    f"`out`: {out!r} already holds a batch run (manifest.json); pass resume=True to "
                    "continue it, or choose another folder."
                )
            return
        with open(path) as f:
            old = json.load(f)
        diff = [k for k in manifest if k != "description" and old.get(k) != manifest[k]]
        if diff:
            details = "; ".join(f"{k}: on disk {old.get(k)!r}, now {manifest[k]!r}" for k in diff)
            raise ValueError(
                f"`resume`: the run in {out!r} was started with different inputs ({details}). "
                "Use the same a0s, problem, control, solver, simulator, max_steps, chunk_size and "
                "history, or another `out` folder."
            )
        return
    if not writer:
        return
    os.makedirs(out, exist_ok=True)
    text = json.dumps(manifest, indent=2).encode()
    _io.atomic_write(path, lambda f: f.write(text))
