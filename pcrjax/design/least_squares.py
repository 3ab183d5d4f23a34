"""Levenberg-Marquardt on a residual vector through the rollout, and the actuators' limits as
residual rows.

The limits enter designs as penalties: rows that are zero while a table of actuator values stays
inside ``margin`` of each limit and grow with the excess beyond it, in metres (a speed excess
times a time scale, an acceleration excess times its square), so that they weigh against the
design's own residuals in metres. A design is then checked against the limits themselves
(`robots.limits.feasibility`).
"""

from __future__ import annotations

import jax.numpy as jnp

from ..errors import ConvergenceError


def limit_rows(a, dt, limits, time_scale, *, margin: float = 0.98, speed: bool = True):
    """Penalty rows (flat, m) of the table ``a`` (T, n) at step ``dt`` against ``limits``
    (`ActuatorLimits`): range, speed (unless ``speed`` is False) and acceleration excess beyond
    ``margin`` of each limit; speeds and accelerations are differences of the table."""
    low, high = limits.low, limits.high
    finite = jnp.isfinite(low) & jnp.isfinite(high)
    slack = jnp.where(finite, 0.5 * (1.0 - margin) * (high - low), 0.0)
    rows = [jnp.maximum(low + slack - a, 0.0), jnp.maximum(a - high + slack, 0.0)]
    v = jnp.diff(a, axis=0) / dt
    if speed:
        rows.append(time_scale * jnp.maximum(jnp.abs(v) - margin * limits.max_speed, 0.0))
    acc = jnp.diff(v, axis=0) / dt
    rows.append(time_scale**2 * jnp.maximum(jnp.abs(acc) - margin * limits.max_acceleration, 0.0))
    return jnp.concatenate([r.ravel() for r in rows])


def levenberg_marquardt(residual, jacobian, c, *, iterations: int, log, label: str = "LM"):
    """Minimise the sum of squares of ``residual(c) -> (r, code)`` from ``c``, with the Jacobian
    ``jacobian(c)`` (Marquardt's diagonal scaling). Trial steps whose rollout does not converge
    (``code`` not 0) or do not decrease the sum are rejected. Stops after ``iterations``, or when
    an iteration gains less than 0.1 %. Returns (c, r, history of the sums, the start's first);
    a start that does not converge raises `ConvergenceError`."""
    r, code = residual(c)
    if int(code) != 0:
        raise ConvergenceError("the starting trajectory's rollout did not converge", 0.0)
    history = [float(jnp.sum(r**2))]
    lam = 1e-3
    for _ in range(iterations):
        J = jacobian(c)
        g, H = J.T @ r, J.T @ J
        while True:
            step = -jnp.linalg.solve(H + lam * jnp.diag(jnp.diag(H) + 1e-30), g)
            r_new, code = residual(c + step)
            f_new = float(jnp.sum(r_new**2))
            if int(code) == 0 and f_new < history[-1]:
                c, r, lam = c + step, r_new, max(lam / 10.0, 1e-12)
                break
            lam *= 10.0
            if lam > 1e8:
                break
        history.append(float(jnp.sum(r**2)))
        log(f"  {label} {len(history) - 1}: sum of squares {history[-1]:.3e} m^2")
        if lam > 1e8 or history[-1] > 0.999 * history[-2]:
            break
    return c, r, history
