import jax

import jaxtraj  # noqa: F401  (turns on float64)

jax.config.update("jax_numpy_rank_promotion", "raise")
