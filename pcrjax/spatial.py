r"""Spatial integration of the rod ODE as one jitted `lax.scan` over the nodes.

RK4 (thesis eq. 3.39) or explicit Euler. RK4 evaluates the ODE at half steps, where BDF-alpha
needs the history $f^h$. The thesis averages the two nodes there (second order in ds); since the
history is of size $c_0 f$ with $c_0 \propto 1/\delta t$, that error grows as the step shrinks and
broke the trapezoidal rule's energy conservation: the thesis cantilever's first mode *grew* 3 %
in 12 periods at $h = \omega\delta t = 0.5$ and 20 % at $h = 0.1$ (N = 20). pcrjax interpolates
the history cubically (4th order, like RK4): the growth is gone and the first frequency is
within 1e-4 at N = 40. The remaining error is $O(c_0\,ds^4)$, so very small time steps need
more nodes (N growing like $\delta t^{-1/4}$). Giving each stage point its own history instead
(tried) made the trapezoidal scheme unstable (a parasitic mode that alpha = -0.5 does not damp). The scan supports
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


def _cubic_weights(n_intervals: int, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """Static interpolation of node histories at sub-step points.

    For interval i the points are at fractions j/(2K), j = 0..2K (sub-step starts, midpoints and
    ends); each is a cubic Lagrange interpolation through 4 nodes starting at ``base[i]``
    (one-sided near the ends, linear if there are fewer than 4 nodes). Returns (base, weights)
    with weights of shape (N, 2K+1, 4).
    """
    K = substeps
    frac = np.arange(2 * K + 1) / (2 * K)
    if n_intervals < 3:
        base = np.arange(n_intervals)
        w = np.zeros((n_intervals, 2 * K + 1, 4))
        w[:, :, 0] = 1 - frac
        w[:, :, 1] = frac
        return base, w
    base = np.clip(np.arange(n_intervals) - 1, 0, n_intervals - 3)
    x = (np.arange(n_intervals) - base)[:, None] + frac[None, :]  # position within the stencil
    w = np.ones((n_intervals, 2 * K + 1, 4))
    for m in range(4):
        for q in range(4):
            if q != m:
                w[:, :, m] *= (x - q) / (m - q)
    return base, w


def substep_history(history, substeps: int):
    """History at the sub-step points of every interval: (N, 2K+1, 12). With K = 1 the middle
    point is the classic cubic midpoint $(-h_{i-1} + 9h_i + 9h_{i+1} - h_{i+2})/16$."""
    n = history.shape[0] - 1
    base, w = _cubic_weights(n, substeps)
    idx = base[:, None] + np.arange(4)[None, :]
    idx = np.minimum(idx, n)
    stencil = history[idx]  # (N, 4, 12)
    return jnp.einsum("ijm,imk->ijk", jnp.asarray(w, history.dtype), stencil)


def stable_substeps(lam_ds: float, integrator: str) -> int:
    """Sub-steps per interval keeping $\lambda\,ds/K$ inside the explicit method's real-axis
    stability interval (RK4: 2.78, Euler: 2), with margin."""
    limit = 2.0 if integrator == "rk4" else 1.0
    return max(1, int(np.ceil(lam_ds / limit)))


def integrate(y0, history, k, effects, ds, integrator, segment_starts=None, restarts=None, unroll=1, substeps=1):
    r"""Integrate from node 0 to node N.

    **Arguments:**
    - ``y0``: state at s = 0.
    - ``history``: (N+1, 12) BDF-alpha history at the nodes (zeros in statics).
    - ``k``, ``effects``: rod coefficients and effect switches (`rod.py`).
    - ``ds``: step length L/N.
    - ``integrator``: "rk4" or "euler" (static).
    - ``segment_starts``: static tuple of node indices (>0) where a new segment starts.
    - ``restarts``: (len(segment_starts), dim) start states of those segments.
    - ``substeps``: static number of sub-steps per interval (history interpolated cubically);
      used when the boundary layer $1/\lambda$ is thinner than the node spacing, where one
      explicit step would amplify the decaying solution instead of damping it.

    **Returns:** ``(nodes, arrivals)``: the state at all N+1 nodes (after restarts) and the
    states arriving at each segment start before the restart (or None).
    """
    n_steps = history.shape[0] - 1
    f = lambda y, h: rhs(y, h, k, effects)  # noqa: E731

    K = substeps
    dsk = ds / K

    def one(y, h0, hm, h1):
        if integrator == "euler":
            return y + dsk * f(y, h0)
        k1 = f(y, h0)
        k2 = f(y + 0.5 * dsk * k1, hm)
        k3 = f(y + 0.5 * dsk * k2, hm)
        k4 = f(y + dsk * k3, h1)
        return y + (dsk / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)

    def step(y, hsub):
        # hsub: (2K+1, 12) history at the sub-step starts, midpoints and ends.
        if K == 1:
            return one(y, hsub[0], None, None) if integrator == "euler" else one(y, hsub[0], hsub[1], hsub[2])
        triples = jnp.stack([hsub[0:-1:2], hsub[1::2], hsub[2::2]], axis=1)  # (K, 3, 12)
        y, _ = jax.lax.scan(lambda yy, h: (one(yy, h[0], h[1], h[2]), None), y, triples)
        return y

    hsub = substep_history(history, K) if (integrator == "rk4" or K > 1) else history[:-1, None, :]

    if not segment_starts:

        def body(y, hh):
            y_next = step(y, hh)
            return y_next, y_next

        _, ys = jax.lax.scan(body, y0, hsub, unroll=unroll)
        return jnp.concatenate([y0[None], ys]), None

    flags = np.zeros(n_steps + 1, dtype=bool)
    flags[list(segment_starts)] = True
    replace = jnp.zeros((n_steps + 1, y0.shape[0]), y0.dtype).at[np.asarray(segment_starts)].set(restarts)

    def body_ms(y, xs):
        hh, flag, rep = xs
        y_in = jnp.where(flag, rep, y)
        y_next = step(y_in, hh)
        return y_next, (y_in, y)

    y_last, (ys_in, ys_arrived) = jax.lax.scan(
        body_ms, y0, (hsub, jnp.asarray(flags[:-1]), replace[:-1]), unroll=unroll
    )
    nodes = jnp.concatenate([ys_in, y_last[None]])
    arrivals = ys_arrived[np.asarray(segment_starts)]
    return nodes, arrivals
