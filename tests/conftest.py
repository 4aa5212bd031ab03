import gc
import shutil
import tempfile

import jax
import pytest

import jaxtraj

# The CPU set-up jaxtraj is tuned for (a device per core: the sharded-batch tests need
# several; XLA options that halve compile times), before any JAX computation.
jaxtraj.configure_cpu()

jax.config.update("jax_numpy_rank_promotion", "raise")
# Strict dtype promotion (issue 52): an implicit array-array dtype mix (float64 * bool,
# float64 + int32, float32 with float64) is an error, so the library casts explicitly.
jax.config.update("jax_numpy_dtype_promotion", "strict")

# A persistent compilation cache private to this test process (one per xdist worker: JAX's
# file cache does not guard a reader against another process's half-written entry). The
# module fixture below drops the in-memory caches; programs that several modules compile
# again (the same problem, solver and shapes, and the thousands of small programs of eager
# operations, hence no minimum compile time) then come from disk instead of XLA.
_CACHE_DIR = tempfile.mkdtemp(prefix="jaxtraj-test-cache-")
jax.config.update("jax_compilation_cache_dir", _CACHE_DIR)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def pytest_unconfigure(config):
    shutil.rmtree(_CACHE_DIR, ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop the compiled programs of each test module when it ends: the suite compiles
    hundreds of distinct programs, and keeping them all held ~10 GB by the last modules."""
    yield
    jax.clear_caches()
    gc.collect()
