import os
import sys

sys.path.insert(0, os.path.dirname(__file__))

import jax  # noqa: E402

import pcrjax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "allow")
pcrjax.enable_compilation_cache()
