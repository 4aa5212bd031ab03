import gc

import jax
import pytest

import jaxtraj  # noqa: F401  (turns on float64)

jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop the compiled programs of each test module when it ends: the suite compiles
    hundreds of distinct programs, and keeping them all held ~10 GB by the last modules."""
    yield
    jax.clear_caches()
    gc.collect()
