"""Spatial integration of the rod ODE as one jitted `lax.scan` over the nodes.

RK4 (thesis eq. 3.39: history averaged at the half step) or explicit Euler. The scan supports
multiple shooting: at the first node of each segment the carried state is replaced by that
segment's unknown start state, and the state arriving there is returned so that the caller can
form continuity residuals.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .rod import rhs

INTEGRATORS = ("rk4", "euler")


def integrate(y0, history, k, effects, ds, integrator, segment_starts=None, restarts=None, unroll=1):
    """Integrate from node 0 to node N.

    **Arguments:**
    - ``y0``: state at s = 0.
    - ``history``: (N+1, 12) BDF-alpha history at the nodes (zeros in statics).
    - ``k``, ``effects``: rod coefficients and effect switches (`rod.py`).
    - ``ds``: step length L/N.
    - ``integrator``: "rk4" or "euler" (static).
    - ``segment_starts``: static tuple of node indices (>0) where a new segment starts.
    - ``restarts``: (len(segment_starts), dim) start states of those segments.

    **Returns:** ``(nodes, arrivals)``: the state at all N+1 nodes (after restarts) and the
    states arriving at each segment start before the restart (or None).
    """
    n_steps = history.shape[0] - 1
    f = lambda y, h: rhs(y, h, k, effects)  # noqa: E731

    def step(y, h0, h1):
        if integrator == "euler":
            return y + ds * f(y, h0)
        hm = 0.5 * (h0 + h1)
        k1 = f(y, h0)
        k2 = f(y + 0.5 * ds * k1, hm)
        k3 = f(y + 0.5 * ds * k2, hm)
        k4 = f(y + ds * k3, h1)
        return y + (ds / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)

    if not segment_starts:

        def body(y, hh):
            y_next = step(y, hh[0], hh[1])
            return y_next, y_next

        _, ys = jax.lax.scan(body, y0, (history[:-1], history[1:]), unroll=unroll)
        return jnp.concatenate([y0[None], ys]), None

    flags = np.zeros(n_steps + 1, dtype=bool)
    flags[list(segment_starts)] = True
    replace = jnp.zeros((n_steps + 1, y0.shape[0]), y0.dtype).at[np.asarray(segment_starts)].set(restarts)

    def body_ms(y, xs):
        h0, h1, flag, rep = xs
        y_in = jnp.where(flag, rep, y)
        y_next = step(y_in, h0, h1)
        return y_next, (y_in, y)

    y_last, (ys_in, ys_arrived) = jax.lax.scan(
        body_ms, y0, (history[:-1], history[1:], jnp.asarray(flags[:-1]), replace[:-1]), unroll=unroll
    )
    nodes = jnp.concatenate([ys_in, y_last[None]])
    arrivals = ys_arrived[np.asarray(segment_starts)]
    return nodes, arrivals
