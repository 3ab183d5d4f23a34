"""Why a solve stopped, as data: integer codes that travel through `jit`, `vmap` and `lax.scan`
and are turned into one message outside the trace (as optimistix's ``RESULTS``)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

SUCCESSFUL = 0
MAX_ITERATIONS = 1
LINE_SEARCH_FAILED = 2
NONFINITE = 3
STALE_STRUCTURE = 4

MESSAGES = {
    SUCCESSFUL: "converged",
    MAX_ITERATIONS: "Newton reached its maximum number of iterations without meeting the tolerance",
    LINE_SEARCH_FAILED: "Newton's line search found no step that lowers the residual",
    NONFINITE: "the residual is not finite (NaN or inf: the rods' integration overflowed)",
    STALE_STRUCTURE: (
        "the scene's numbers no longer fit its compiled structure (a length, modulus, density, dt or alpha was "
        "changed after the scene was built, and it now needs more shooting segments or a finer internal grid): "
        "rebuild it with pcrjax.with_solver(scene)"
    ),
}


def message(code) -> str:
    return MESSAGES.get(int(code), f"unknown result code {int(code)}")


def worst(*codes):
    """The first failure among ``codes`` (elementwise), else SUCCESSFUL."""
    out = jnp.asarray(codes[-1])
    for c in reversed(codes[:-1]):
        out = jnp.where(jnp.asarray(c) != SUCCESSFUL, c, out)
    return out


def first_failure(codes) -> int | None:
    """Index of the first non-successful entry of a concrete array of codes, or None."""
    bad = np.flatnonzero(np.asarray(codes) != SUCCESSFUL)
    return int(bad[0]) if bad.size else None
