"""Batched solves at scale: `solve_batch` (vmap + device sharding + chunks + resumable
result folders) and `multistart` (random starts around a vector, solved as one batch, with
a summary of the local optima found).

One compiled program solves one *chunk* of starts: `jax.shard_map` gives every device its
own slice of it, which runs on `lanes` vmapped lanes fed from a queue (`lanes.py`). With
`out=FOLDER` each finished chunk is written atomically next to a manifest of the inputs'
fingerprints (`files.py`), and `resume=True` solves only the rest, returning exactly what an
uninterrupted run does. Several hosts: the same script on every host, after
`jax.distributed.initialize`.

(How a batch runs, CPU devices and the multi-host recipe: docs/api/batch.md.)
"""

from .solve import solve_batch as solve_batch
from .starts import (
    MultistartResult as MultistartResult,
    multistart as multistart,
    random_starts as random_starts,
)
