"""JAX persistent compilation cache (a second run does not recompile)."""

import os
from pathlib import Path

import jax


def cache_dir() -> Path | None:
    if os.environ.get("PCRJAX_NO_CACHE"):
        return None
    d = os.environ.get("PCRJAX_CACHE_DIR") or os.path.join(os.environ.get("XDG_CACHE_HOME", str(Path.home() / ".cache")), "pcrjax", "jax")
    return Path(d)


def enable_compilation_cache() -> Path | None:
    d = cache_dir()
    if d is None:
        return None
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(d))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return d
