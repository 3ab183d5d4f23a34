"""pcrjax: differentiable Cosserat-rod dynamics for parallel continuum robots, in JAX.

pcrjax needs float64: enable it before creating any array,
``jax.config.update("jax_enable_x64", True)``; `enable_compilation_cache` turns on JAX's
persistent compilation cache. Importing pcrjax changes no JAX setting.

Layout: ``physics/`` (rotations, rod, rigid platform), ``numerics/`` (BDF-alpha, spatial
integration, shooting, Newton), ``robots/`` (legs, ends, actuation, the one assembly, statics and
dynamics), ``io/`` (scene files, tables, outputs), `simulation` (the public solves), `sweeps`
(batched parameter sweeps; `distributed`: on a Dask cluster), `numerical_damping` (BDF-alpha's
damping against dt, alpha and N), `lumped` (the lumped model of thesis 3.1, with diffrax), `pareto`
(the cost of accuracy), `executables` (compiled code against the memory-map cap), `cli`,
``bench/``.
"""

from .config import enable_compilation_cache
from .errors import ConvergenceError, SceneError
from .executables import release_compiled
from .io.scene_file import load_scene, scene_from_dict, shipped_scenes, with_solver, with_step
from .numerics import results
from .robots.scene import Scene
from .robots.signals import PosePath
from .simulation import StaticResult, Trajectory, inverse_dynamics, rollout, simulate, solve_static
from .sweeps import Sweep, sweep

__all__ = [
    "ConvergenceError",
    "PosePath",
    "Scene",
    "SceneError",
    "StaticResult",
    "Sweep",
    "Trajectory",
    "enable_compilation_cache",
    "inverse_dynamics",
    "load_scene",
    "release_compiled",
    "results",
    "rollout",
    "scene_from_dict",
    "shipped_scenes",
    "simulate",
    "solve_static",
    "sweep",
    "with_solver",
    "with_step",
]
__version__ = "0.1.0"
