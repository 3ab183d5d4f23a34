"""Memory budgets for batched programs.

A sweep's batch of members runs as one compiled program whose buffers (the stacked scenes, every
member's trajectory, the temporaries of its solves) grow with the batch. XLA reports what a
compiled program needs (`program_bytes`); a sweep splits a batch that needs more than its budget
into smaller ones (`pcrjax.sweeps.run_members`). The default budget is half of the memory the
system has available now (the accelerator's own memory on a GPU).
"""

from __future__ import annotations

import os
import re

import jax

from .errors import SceneError

_UNITS = {"": 1, "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12, "kib": 2**10, "mib": 2**20, "gib": 2**30}
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([a-zA-Z]*)\s*$")


def parse_size(text) -> int:
    """Bytes from ``text``: a number of bytes, or with a unit (``500MB``, ``2GiB``, ``1.5GB``)."""
    m = _SIZE.match(str(text))
    unit = m.group(2).lower() if m else ""
    if not m or unit not in _UNITS:
        raise SceneError(f"memory {text!r}: write bytes or a size such as 500MB or 2GiB")
    size = int(float(m.group(1)) * _UNITS[unit])
    if size <= 0:
        raise SceneError(f"memory {text!r}: must be positive")
    return size


def available_bytes() -> int | None:
    """Memory available now to the default device's programs: the accelerator's free memory, or
    the host's available memory (Linux ``MemAvailable``, else free physical pages); None if the
    system does not say."""
    stats = jax.local_devices()[0].memory_stats()
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def default_budget() -> int | None:
    """Half of `available_bytes` (None: no budget)."""
    free = available_bytes()
    return None if free is None else free // 2


def program_bytes(compiled) -> int:
    """Bytes a compiled program's run holds at once: arguments, outputs and temporaries."""
    m = compiled.memory_analysis()
    if m is None:
        return 0
    return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes)
