"""pcrjax: differentiable Cosserat-rod dynamics for parallel continuum robots, in JAX.

Importing pcrjax enables float64 (before any array exists) and, unless ``PCRJAX_NO_CACHE`` is
set, JAX's persistent compilation cache (``PCRJAX_CACHE_DIR``, default ``~/.cache/pcrjax``).
"""

import jax

jax.config.update("jax_enable_x64", True)

from ._cache import enable_compilation_cache  # noqa: E402

enable_compilation_cache()

from .scene import Scene, SceneError, load_scene, shipped_scenes, with_solver  # noqa: E402
from .simulation import ConvergenceError, StaticResult, Trajectory, rollout, simulate, solve_static  # noqa: E402

__all__ = [
    "ConvergenceError",
    "Scene",
    "SceneError",
    "StaticResult",
    "Trajectory",
    "load_scene",
    "rollout",
    "shipped_scenes",
    "simulate",
    "solve_static",
    "with_solver",
]
__version__ = "0.1.0"
