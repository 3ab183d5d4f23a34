"""Independent jobs of one fit spread over the machine's cores, one thread per core.

XLA:CPU runs one execution of a compiled program on one core, and two independent loops in one
program one after the other; only several executions at once use several cores. A compiled
program releases Python's lock while it runs, so threads that call programs (and numpy's LAPACK)
run side by side.

**Programs run side by side must hold no batched LAPACK call.** JAX 0.10's LAPACK kernels split
a batch of matrices over XLA's intra-op threads and wait for the parts on that pool: two
executions that each hold one of its threads (two on a 2-core machine) then wait for each other
for ever. One matrix per call is safe, so the programs run here solve one system at a time
(`jax.lax.map`, not `jax.vmap`, over anything that factorises); `tests/test_identify.py` checks
them on their lowered text.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

WORKERS = max(1, os.cpu_count() or 1)


def map_in_threads(fn: Callable, items: Iterable, first_alone: bool = True) -> Iterator:
    """``fn(x)`` of each of ``items``, yielded in order as they are done, on `WORKERS` threads;
    with ``first_alone``, the first before the others start (it traces and compiles the programs
    ``fn`` calls, once; a caller may go on between the first and the rest)."""
    items = list(items)
    if first_alone and items:
        yield fn(items.pop(0))
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        yield from pool.map(fn, items)
