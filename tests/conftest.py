import os
import sys

sys.path.insert(0, os.path.dirname(__file__))

import jax  # noqa: E402
import pytest  # noqa: E402

import pcrjax  # noqa: E402
from pcrjax import executables  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "allow")
pcrjax.enable_compilation_cache()


@pytest.fixture(autouse=True)
def _headroom_for_executables():
    """A worker runs many tests in one process: release compiled code before it nears the kernel's
    cap on memory mappings (see `pcrjax.executables`), which would crash the worker."""
    yield
    executables.make_room(0.4, warn=False)
