r"""Spatial integration of the rod ODE as one jitted `lax.scan` over the nodes.

RK4 (thesis eq. 3.39) or explicit Euler. RK4 evaluates the ODE at half steps, where BDF-alpha
needs the history $f^h$. The thesis averages the two nodes there (second order in ds); since the
history is of size $c_0 f$ with $c_0 \propto 1/\delta t$, that error grows as the step shrinks and
broke the trapezoidal rule's energy conservation: the thesis cantilever's first mode *grew* 3 %
in 12 periods at $h = \omega\delta t = 0.5$ and 20 % at $h = 0.1$ (N = 20). pcrjax interpolates
the history cubically (4th order, like RK4): the growth is gone and the first frequency is
within 1e-4 at N = 40. The remaining error is $O(c_0\,ds^4)$, so very small time steps need
more nodes (N growing like $\delta t^{-1/4}$); `rod_history.py` keeps the previous step's value
exactly at every stage point, so that this error multiplies a velocity, not $c_0$.

The scan supports multiple shooting: at the first node of each segment the carried state is replaced by that
segment's unknown start state, and the state arriving there is returned so that the caller can
form continuity residuals.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..physics.rod import rhs

INTEGRATORS = ("rk4", "euler")


def midpoints(history):
    """History at the N half steps by cubic interpolation (one-sided at the ends; linear if N < 3)."""
    h = history
    if h.shape[0] < 4:
        return 0.5 * (h[:-1] + h[1:])
    inner = (-h[:-3] + 9.0 * h[1:-2] + 9.0 * h[2:-1] - h[3:]) / 16.0
    first = (5.0 * h[0] + 15.0 * h[1] - 5.0 * h[2] + h[3]) / 16.0
    last = (5.0 * h[-1] + 15.0 * h[-2] - 5.0 * h[-3] + h[-4]) / 16.0
    return jnp.concatenate([first[None], inner, last[None]])


def stage_histories(history):
    """Histories at RK4's stage points 2, 3, 4 of each interval, (N, 3, 12), interpolated from
    the node histories (used in statics, where they are zero, and by callers without stage data)."""
    hm = midpoints(history)
    return jnp.stack([hm, hm, history[1:]], axis=1)


def integrate(
    y0, history, k, effects, ds, integrator, segment_starts=None, restarts=None, unroll=1, stage_history=None, return_stages=False
):
    r"""Integrate from node 0 to node N.

    **Arguments:**
    - ``y0``: state at s = 0.
    - ``history``: (N+1, 12) BDF-alpha history at the nodes (zeros in statics).
    - ``k``, ``effects``: rod coefficients and effect switches (`rod.py`).
    - ``ds``: step length L/N.
    - ``integrator``: "rk4" or "euler" (static).
    - ``segment_starts``: static tuple of node indices (>0) where a new segment starts.
    - ``restarts``: (len(segment_starts), dim) start states of those segments.
    - ``stage_history``: (N, 3, 12) histories at RK4 stages 2, 3, 4 of each interval (see
      `rod_history.py`); interpolated from ``history`` when None.
    - ``return_stages``: also return the (N, 3, dim) states at which stages 2, 3, 4 were evaluated.

    **Returns:** ``(nodes, arrivals)`` (and ``stages`` if asked): the state at all N+1 nodes (after
    restarts) and the states arriving at each segment start before the restart (or None).
    """
    n_steps = history.shape[0] - 1
    f = lambda y, h: rhs(y, h, k, effects)  # noqa: E731

    def step(y, h0, hs):
        if integrator == "euler":
            return y + ds * f(y, h0), None
        k1 = f(y, h0)
        y2 = y + 0.5 * ds * k1
        k2 = f(y2, hs[0])
        y3 = y + 0.5 * ds * k2
        k3 = f(y3, hs[1])
        y4 = y + ds * k3
        k4 = f(y4, hs[2])
        return y + (ds / 6.0) * (k1 + 2.0 * (k2 + k3) + k4), jnp.stack([y2, y3, y4])

    if integrator == "rk4":
        hs = stage_histories(history) if stage_history is None else stage_history
    else:  # Euler never evaluates between nodes
        hs = jnp.zeros((n_steps, 0, history.shape[1]), history.dtype)
    xs = (history[:-1], hs)
    if segment_starts:
        flags = np.zeros(n_steps + 1, dtype=bool)
        flags[list(segment_starts)] = True
        replace = jnp.zeros((n_steps + 1, y0.shape[0]), y0.dtype).at[np.asarray(segment_starts)].set(restarts)
        xs = xs + (jnp.asarray(flags[:-1]), replace[:-1])

    def body(y, x):
        y_in = jnp.where(x[2], x[3], y) if segment_starts else y
        y_next, stages = step(y_in, x[0], x[1])
        out = (y_in, y) + ((stages,) if return_stages and stages is not None else ())
        return y_next, out

    y_last, outs = jax.lax.scan(body, y0, xs, unroll=unroll)
    ys_in, ys_arrived = outs[0], outs[1]
    nodes = jnp.concatenate([ys_in, y_last[None]])
    arrivals = ys_arrived[np.asarray(segment_starts)] if segment_starts else None
    if return_stages:
        stages = outs[2] if integrator == "rk4" else jnp.zeros((n_steps, 0, y0.shape[0]), y0.dtype)
        return nodes, arrivals, stages
    return nodes, arrivals
