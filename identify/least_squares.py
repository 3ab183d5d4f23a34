"""Least-squares minimisers of ``0.5 |r(theta)|^2``: Levenberg-Marquardt (the fit's) and optax
Adam (for comparison), and the Gauss-Newton covariance at an optimum."""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


class FitError(RuntimeError):
    """The fit cannot go on (a simulation that does not converge at the values it must start from)."""


def covariance(J):
    """(J^T J)^{-1}, the Gauss-Newton covariance of unit-variance residuals, inverted with the
    columns scaled to unit norm (unknowns of very different sizes)."""
    JtJ = J.T @ J
    d = 1.0 / np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    return d[:, None] * np.linalg.pinv(d[:, None] * JtJ * d[None, :], rcond=1e-14) * d[None, :]


def levenberg_marquardt(
    rf: Callable,
    rj: Callable,
    theta0,
    max_iter=30,
    xtol=1e-8,
    ftol=1e-10,
    max_step=0.5,
    start: dict | None = None,
    save=None,
    progress=None,
    initial=None,
):
    """Minimise ``0.5 |rf(theta)|^2``, with ``rj(theta) = (residual, Jacobian)``.

    Steps are bounded to ``max_step`` (a number, or one per unknown: they are O(1), logs and
    typical units), a trust region that keeps the first steps from a poor guess out of far minima. ``start`` (a
    state that ``save`` was given) resumes an interrupted run; ``save(state)`` is called after
    every accepted step; ``initial``, ``rj(theta0)`` if already known. Returns (theta, J, r,
    iterations, converged, history)."""
    theta = np.asarray(theta0, float)
    lam, history, it0 = 1e-3, [], 0
    if start is not None:
        theta, lam, history, it0 = np.asarray(start["theta"], float), start["lam"], list(start["history"]), start["iteration"]
    r, J = (np.asarray(a) for a in (rj(jnp.asarray(theta)) if initial is None or start is not None else initial))
    cost = 0.5 * float(r @ r)
    if not (np.isfinite(cost) and np.all(np.isfinite(J))):
        raise FitError(
            "the residual or its Jacobian at the start is not finite (a simulation whose Newton solves did not converge)"
        )
    if not history:
        history.append(cost)
    converged = False
    it = it0
    for it in range(it0 + 1, max_iter + 1):
        g = J.T @ r
        A = J.T @ J
        accepted = False
        scale = np.diag(np.diag(A) + 1e-12 * np.max(np.diag(A)))
        for _ in range(12):
            step = np.linalg.solve(A + lam * scale, -g)
            while np.any(np.abs(step) > max_step):  # raise the damping until the step fits the region
                lam *= 4.0
                step = np.linalg.solve(A + lam * scale, -g)
            r_t = np.asarray(rf(jnp.asarray(theta + step)))
            cost_t = 0.5 * float(r_t @ r_t) if np.all(np.isfinite(r_t)) else math.inf
            if cost_t < cost:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            converged = True  # no decrease along any damped step: a minimum to the precision of the model
            it -= 1
            break
        rel = (cost - cost_t) / max(cost, 1e-300)
        theta = theta + step
        lam = max(lam / 10.0, 1e-12)
        r, J = (np.asarray(a) for a in rj(jnp.asarray(theta)))
        cost = 0.5 * float(r @ r)
        history.append(cost)
        if save is not None:
            save(dict(theta=theta.tolist(), lam=lam, history=history, iteration=it))
        if progress is not None:
            progress(it, cost, float(np.max(np.abs(step))))
        if rel < ftol or np.max(np.abs(step)) < xtol * (1.0 + np.max(np.abs(theta))):
            converged = True
            break
    return theta, J, r, it, converged, history


def adam(fun: Callable, theta0, steps=300, learning_rate=3e-2, progress=None):
    """Minimise ``0.5 |fun(theta)|^2`` with optax Adam (reverse-mode gradients); for comparison.
    Stops at a non-finite loss (a step into parameters where the simulation fails: Adam has no
    way to reject a step), the NaN last in the history."""
    import optax

    loss = jax.jit(jax.value_and_grad(lambda th: 0.5 * jnp.sum(fun(th) ** 2)))
    opt = optax.adam(learning_rate)
    theta = jnp.asarray(theta0)
    state = opt.init(theta)
    history = []
    for k in range(steps):
        val, g = loss(theta)
        history.append(float(val))
        if not np.isfinite(history[-1]):
            break
        upd, state = opt.update(g, state)
        theta = optax.apply_updates(theta, upd)
        if progress is not None:
            progress(k + 1, float(val), float(jnp.max(jnp.abs(upd))))
    return np.asarray(theta), history


def standard_errors_theta(J, chi2: float):
    """Standard errors of theta from the Gauss-Newton covariance rescaled by ``chi2``."""
    return np.sqrt(np.maximum(np.diag(covariance(J) * chi2), 0.0))
