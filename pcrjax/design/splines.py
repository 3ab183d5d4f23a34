"""Smooth curves for actuator trajectories: clamped uniform B-splines and the quintic smooth step."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def bspline_basis(u, n_basis: int, degree: int = 5) -> np.ndarray:
    """(len(u), n_basis) clamped uniform B-spline basis of ``degree`` on [0, 1] (Cox-de Boor)."""
    u = np.clip(np.asarray(u, np.float64), 0.0, 1.0)
    inner = np.linspace(0.0, 1.0, n_basis - degree + 1)
    knots = np.concatenate([np.zeros(degree), inner, np.ones(degree)])
    B = np.zeros((u.size, knots.size - 1))
    for j in range(knots.size - 1):
        B[:, j] = (knots[j] <= u) & (u < knots[j + 1])
    B[u >= 1.0, n_basis - 1] = 1.0  # the right end belongs to the last non-empty span
    B[u >= 1.0, n_basis:] = 0.0
    for d in range(1, degree + 1):
        for j in range(knots.size - 1 - d):
            left = knots[j + d] - knots[j]
            right = knots[j + d + 1] - knots[j + 1]
            a = (u - knots[j]) / left * B[:, j] if left > 0 else 0.0
            b = (knots[j + d + 1] - u) / right * B[:, j + 1] if right > 0 else 0.0
            B[:, j] = a + b
    return B[:, :n_basis]


def correction_basis(t, duration: float, count: int) -> np.ndarray:
    """(len(t), count) smooth corrections on [0, duration], zero with their first two derivatives
    at both ends and outside: the interior quintic B-splines of ``count + 6`` on [0, 1]."""
    t = np.asarray(t, np.float64)
    B = bspline_basis(t / duration, count + 6)[:, 3:-3]
    return np.where(((t >= 0.0) & (t <= duration))[:, None], B, 0.0)


def smooth_step(u):
    """The quintic step from 0 to 1 on [0, 1], with zero velocity and acceleration at both ends."""
    u = jnp.clip(u, 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)
