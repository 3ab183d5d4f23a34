import os
import sys

sys.path.insert(0, os.path.dirname(__file__))

import jax  # noqa: E402

import pcrjax  # noqa: E402,F401  (enables x64 and the compilation cache)

jax.config.update("jax_numpy_rank_promotion", "allow")
