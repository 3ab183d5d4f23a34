"""BDF-alpha time discretisation (thesis eq. 3.32-3.34, with the endpoints of alpha corrected).

$f_t(t_i) = c_0 f_i + c_1 f_{i-1} + c_2 f_{i-2} + d_1 f_t(t_{i-1}) = c_0 f_i + f^h_i$ with

$c_0 = (1.5+\\alpha)/(\\delta t(1+\\alpha))$, $c_1 = -2/\\delta t$,
$c_2 = (0.5+\\alpha)/(\\delta t(1+\\alpha))$, $d_1 = \\alpha/(1+\\alpha)$, $-0.5 \\le \\alpha \\le 0$.

**alpha = -0.5 is the trapezoidal rule** (no numerical damping) and **alpha = 0 is BDF2**
(strongest damping, high-frequency limit $|\\alpha/(1+\\alpha)|$). The thesis states these
endpoints the other way round; the scheme above is what is implemented and tested.

**The first step is backward Euler** (`starting`). A robot starts at rest, where every rate is
zero; a load released at t = 0 makes the accelerations jump there. BDF-alpha's first step would
take the rest history's rates ($\\dot f_0 = 0$, the rates before the jump) and advance by an
effective $(1+\\alpha)/(1.5+\\alpha)$ of a step: the whole motion then lags by about
$\\delta t/2$, a first-order error (measured: the cantilever released at 1 ms steps lagged
0.50 ms). Backward Euler needs no previous rate; its one step's $O(\\delta t^2)$ error leaves
the scheme second order.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class Coefficients(eqx.Module):
    c0: jnp.ndarray
    c1: jnp.ndarray
    c2: jnp.ndarray
    d1: jnp.ndarray


def coefficients(dt, alpha) -> Coefficients:
    return Coefficients(
        c0=(1.5 + alpha) / (dt * (1.0 + alpha)),
        c1=-2.0 / dt,
        c2=(0.5 + alpha) / (dt * (1.0 + alpha)),
        d1=alpha / (1.0 + alpha),
    )


def starting(dt) -> Coefficients:
    """Backward Euler in BDF-alpha's form, for the first step from rest: $f_t = (f_1 - f_0)/\\delta t$."""
    dt = jnp.asarray(dt, jnp.float64)
    return Coefficients(c0=1.0 / dt, c1=-1.0 / dt, c2=jnp.zeros_like(dt), d1=jnp.zeros_like(dt))


def step_coefficients(dt, alpha, first) -> Coefficients:
    """The coefficients of a step: `starting` where ``first`` (the first step from rest), else
    BDF-alpha's."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(first, a, b), starting(dt), coefficients(dt, alpha))


def next_history(co: Coefficients, z, z_prev, h, now: Coefficients | None = None):
    """History for the next step (scheme ``co``) from this step's values ``z``, the previous
    ``z_prev`` and this step's history ``h`` (this step's scheme ``now``, default ``co``, so
    $z_t = c_0^{now} z + h$): $h' = c_1 z + c_2 z_{prev} + d_1 z_t$."""
    now = co if now is None else now
    return co.c1 * z + co.c2 * z_prev + co.d1 * (now.c0 * z + h)


def rest_history(co: Coefficients, z):
    """History of a system that has rested at ``z`` forever: $(c_1 + c_2) z = -c_0 z$."""
    return (co.c1 + co.c2) * z


def amplification(h_omega: float, alpha: float) -> complex:
    """Dominant root of BDF-alpha applied to $y' = i\\omega y$ at $h = \\omega\\,\\delta t$.

    Pure scheme theory, independent of the rod code: the test oracle for numerical damping.
    The recurrence on $(y_i, y_{i-1}, \\dot y_i)$ is written in companion form and its
    eigenvalue of largest modulus returned; over one true period $2\\pi/\\omega$ the
    amplitude changes by $|z|^{2\\pi/h}$ (0.981 at alpha = -0.4 and h = 0.5).
    """
    dt = 1.0
    lam = 1j * h_omega
    c0 = (1.5 + alpha) / (dt * (1 + alpha))
    c1 = -2.0 / dt
    c2 = (0.5 + alpha) / (dt * (1 + alpha))
    d1 = alpha / (1 + alpha)
    # State (y_i, y_{i-1}, yt_i). Recurrence: lam*y_{i+1} = c0 y_{i+1} + c1 y_i + c2 y_{i-1} + d1 yt_i,
    # yt_{i+1} = lam * y_{i+1}.
    a = 1.0 / (lam - c0)
    M = np.array(
        [
            [a * c1, a * c2, a * d1],
            [1.0, 0.0, 0.0],
            [lam * a * c1, lam * a * c2, lam * a * d1],
        ],
        dtype=complex,
    )
    roots = np.linalg.eigvals(M)
    return roots[np.argmax(np.abs(roots))]
