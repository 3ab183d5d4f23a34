"""Compiled executables against the process's memory-map limit.

XLA:CPU loads each fused kernel of an executable into pages of its own (code, constants, data:
three memory mappings a kernel, whether compiled here or loaded from the persistent cache), so
one rollout chunk holds 900-1 500 of the process's mappings. Linux caps a process at
``vm.max_map_count`` mappings (65 530 by default). Past the cap LLVM's JIT fails with "Cannot
allocate memory" and XLA crashes the process (a segfault, not an exception): a long session that
compiles many structures (a notebook, a sweep over node counts, a test run) reaches it after
some 50 executables. `make_room` releases every executable this process holds once the mappings
in use pass a share of the cap; they compile again (or load from the persistent cache) on next
use. `release_compiled` does so unconditionally.
"""

import gc
import warnings

import jax

_MAPS = "/proc/self/maps"
_LIMIT = "/proc/sys/vm/max_map_count"


def map_count() -> int | None:
    """Memory mappings this process holds (Linux), or None where the system does not say."""
    try:
        with open(_MAPS, "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


def map_limit() -> int | None:
    """The kernel's cap on a process's memory mappings (Linux), or None."""
    try:
        with open(_LIMIT) as f:
            return int(f.read())
    except (OSError, ValueError):
        return None


def release_compiled():
    """Drop every compiled executable pcrjax and JAX hold in this process."""
    from . import simulation, sweeps

    simulation.release_compiled()
    sweeps.release_compiled()
    jax.clear_caches()
    gc.collect()


def make_room(share: float = 0.6, warn: bool = True) -> bool:
    """Release compiled executables when the mappings in use pass ``share`` of the cap (with a
    warning unless ``warn`` is False); True if it did. Call it outside traces only (between solves)."""
    used, cap = map_count(), map_limit()
    if used is None or cap is None or used < share * cap:
        return False
    if warn:
        warnings.warn(
            f"pcrjax: compiled code holds {used} of this process's {cap} memory mappings (vm.max_map_count); "
            "releasing all compiled executables (they compile again, or load from the persistent cache, when next used)",
            RuntimeWarning,
            stacklevel=2,
        )
    release_compiled()
    return True
