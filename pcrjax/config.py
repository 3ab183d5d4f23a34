"""JAX settings pcrjax needs (float64) or benefits from (the persistent compilation cache).

Importing pcrjax changes no global JAX setting. The command-line tools call `configure`; a
library user enables float64 before creating any array,
``jax.config.update("jax_enable_x64", True)`` (pcrjax refuses to build a scene otherwise), and
may call `enable_compilation_cache` so that a second process does not compile again.
"""

import os
from pathlib import Path

import jax

from .errors import SceneError


def require_x64():
    """Raise `SceneError` unless float64 is enabled (float32 cannot hold the solve: residual floor ~1e-7)."""
    if not jax.config.jax_enable_x64:
        raise SceneError('pcrjax needs float64: call jax.config.update("jax_enable_x64", True) before creating any array')


def cache_dir() -> Path | None:
    if os.environ.get("PCRJAX_NO_CACHE"):
        return None
    d = os.environ.get("PCRJAX_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", str(Path.home() / ".cache")), "pcrjax", "jax"
    )
    return Path(d)


_traces: Path | None = None


def trace_cache_dir() -> Path | None:
    """Where `pcrjax.traces` keeps traced programs: beside the compilation cache, once
    `enable_compilation_cache` has turned that on (None before)."""
    return _traces


def enable_compilation_cache() -> Path | None:
    """JAX's persistent compilation cache in ``PCRJAX_CACHE_DIR`` (default ``~/.cache/pcrjax/jax``;
    ``PCRJAX_NO_CACHE=1``: off), and the traced programs of `pcrjax.traces` beside it (the same
    folder's name + ``-traces``). Returns the compilation cache's folder, or None."""
    global _traces
    d = cache_dir()
    if d is None:
        return None
    traces = d.with_name(d.name + "-traces")
    try:
        d.mkdir(parents=True, exist_ok=True)
        traces.mkdir(exist_ok=True)
    except OSError:
        return None
    _traces = traces
    jax.config.update("jax_compilation_cache_dir", str(d))
    # every program, however small: the eager array operations that build a scene, a fit's
    # problem or the outputs compile in milliseconds each, but there are about a hundred of them
    # a process, which every warm process would otherwise compile again
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return d


def configure():
    """What the command-line tools set before anything else: float64 and the compilation cache."""
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
