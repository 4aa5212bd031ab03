"""Result folders of a batch: `manifest.json` and the chunk files,
written atomically and checked on resume."""

import hashlib
import json
import os
import zipfile

import numpy as np

from .. import io as _io

#: Format tag of `manifest.json`.
FORMAT = "jaxtraj-batch-2"


def chunk_path(out, k):
    return os.path.join(out, f"chunk_{k:05d}.npz")


def run_id(manifest) -> str:
    """The identity of a run: SHA-256 of its manifest (without the description)."""
    body = {k: v for k, v in manifest.items() if k != "description"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def _leaves_sha256(leaves):
    h = hashlib.sha256()
    for x in leaves:
        x = np.ascontiguousarray(x)
        h.update(f"{x.dtype.str}{x.shape}".encode())
        h.update(x.tobytes())
    return h.hexdigest()


def write_chunk(out, k, leaves, run):
    """Chunk `k` of the run `run` (`run_id`): the solution leaves, the run's identity, the
    chunk's index and a checksum of the leaves, written atomically."""
    arrays = {f"leaf_{i:03d}": x for i, x in enumerate(leaves)}
    meta = {"run": np.asarray(run), "index": np.asarray(k), "sha256": np.asarray(_leaves_sha256(leaves))}
    _io.atomic_write(chunk_path(out, k), lambda f: np.savez(f, **arrays, **meta))


def read_chunk(out, k, rows, spec, run):
    """The leaves of chunk `k`, after checking that the file belongs to this run (`run`), is
    chunk `k`, and is whole (checksum, layout); else a one-line ValueError naming the file."""
    path = chunk_path(out, k)
    fix = "delete it to recompute that chunk"
    try:
        # (opened here: `np.load` of a cut zip raises with its own file left open)
        with open(path, "rb") as handle, np.load(handle) as data:
            files = set(data.files)
            meta = {key: str(data[key]) for key in ("run", "index", "sha256") if key in files}
            leaves = [data[f"leaf_{i:03d}"] for i in range(len(spec)) if f"leaf_{i:03d}" in files]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"`out`: {path} is damaged ({type(e).__name__}: {e}); {fix}.") from None
    if meta.get("run") != run:
        raise ValueError(f"`out`: {path} belongs to another run (not this manifest's); {fix}.")
    if meta.get("index") != str(k):
        raise ValueError(f"`out`: {path} holds chunk {meta.get('index')}, not chunk {k} (a copied file?); {fix}.")
    layout_ok = len(leaves) == len(spec) and all(
        x.shape == (rows, *s) and x.dtype == d for x, (s, d) in zip(leaves, spec)
    )
    if not layout_ok or meta.get("sha256") != _leaves_sha256(leaves):
        raise ValueError(f"`out`: {path} is damaged (its solutions do not match their checksum or layout); {fix}.")
    return leaves


def prepare_out(out, manifest, resume, writer):
    """Create `out` and its manifest (process 0), or check an existing manifest against
    this run's."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"`out`: {out!r} is a file, not a folder.")
    path = os.path.join(out, "manifest.json")
    if os.path.exists(path):
        if not resume:
            if writer:  # (other processes may see the manifest process 0 just wrote)
                raise ValueError(
                    f"`out`: {out!r} already holds a batch run (manifest.json); pass resume=True to "
                    "continue it, or choose another folder."
                )
            return
        try:
            old = _io.read_json(path)
        except ValueError as e:
            raise ValueError(f"`out`: {e} Delete the folder to start the run anew.") from None
        diff = [k for k in manifest if k != "description" and old.get(k) != manifest[k]]
        if diff:
            details = "; ".join(
                f"{k.removesuffix('_sha256')} changed"
                if k.endswith("_sha256")
                else f"{k}: on disk {old.get(k)!r}, now {manifest[k]!r}"
                for k in diff
            )
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
