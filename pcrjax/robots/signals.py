"""Time signals of a robot: actuator values and the load on its end (platform centre or free tip).

Actuators (one value each: a leg length for the Stewart-Gough platform, a base displacement
along ``d_i`` for the Triskele-bot) follow ``constant``, ``step``, ``ramp`` or ``smooth_step``
(quintic, zero velocity and acceleration at both ends) from ``initial`` to ``final``, starting at
``start`` (s) over ``duration`` (s); or a CSV table ``t_s,a1..an`` interpolated linearly (held at
its first and last rows outside its time range).

Loads (force N, moment N m, global frame, on the platform centre or the free tip) are held while
``apply_time <= t <= release_time`` (push-and-release: ``release_time = 0``; a step:
``apply_time > 0``), plus an optional CSV table ``t_s,fx_N,fy_N,fz_N,mx_Nm,my_Nm,mz_Nm``.

The end's prescribed pose for inverse dynamics (`PosePath`) is a cubic spline through a table
``t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad`` (planar: ``t_s,x_m,y_m,theta_rad``).

Every number is a float64 leaf; the kinds are static.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..physics.rotations import exp_map, rotz

KINDS = ("constant", "step", "ramp", "smooth_step")


def _interp(t, ts, vals):
    """Linear interpolation of each column of ``vals`` at scalar ``t`` (clamped at the ends)."""
    return jnp.stack([jnp.interp(t, ts, vals[:, j]) for j in range(vals.shape[1])])


def _shape(kind: str, u):
    if kind == "ramp":
        return u
    if kind == "smooth_step":
        return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)
    raise ValueError(f"unknown actuation kind {kind!r}: expected one of {', '.join(KINDS)}")


class ActuatorLimits(eqx.Module):
    """What the actuators can do (checked on inverse-dynamics and designed trajectories):
    ``low``, ``high`` (n,) the range of values, ``max_speed`` and ``max_acceleration`` (n,)
    (units of the values per s and s^2; inf where unlimited)."""

    low: jnp.ndarray
    high: jnp.ndarray
    max_speed: jnp.ndarray
    max_acceleration: jnp.ndarray


class Actuation(eqx.Module):
    """Actuator values over time (see module doc). Call ``actuation(t)`` for the (n,) values."""

    initial: jnp.ndarray
    final: jnp.ndarray
    start: jnp.ndarray
    duration: jnp.ndarray
    table_t: jnp.ndarray | None = None
    table_a: jnp.ndarray | None = None
    kinds: tuple[str, ...] = eqx.field(static=True, default=())
    limits: ActuatorLimits | None = None

    @property
    def size(self) -> int:
        return self.initial.shape[0]

    def __call__(self, t):
        if self.table_t is not None:
            return _interp(t, self.table_t, self.table_a)
        out = []
        for i, kind in enumerate(self.kinds):
            a0, a1 = self.initial[i], self.final[i]
            if kind == "constant":
                out.append(a0)
            elif kind == "step":
                out.append(jnp.where(t > self.start[i], a1, a0))
            else:
                u = jnp.clip((t - self.start[i]) / self.duration[i], 0.0, 1.0)
                out.append(a0 + (a1 - a0) * _shape(kind, u))
        return jnp.stack(out)


class Load(eqx.Module):
    """External force and moment on a robot's end (global frame) over time."""

    force: jnp.ndarray
    moment: jnp.ndarray
    apply_time: jnp.ndarray
    release_time: jnp.ndarray
    table_t: jnp.ndarray | None = None
    table_w: jnp.ndarray | None = None

    @classmethod
    def held_until(cls, force, moment, release_time):
        """A load held from the start until ``release_time``."""
        inf = jnp.asarray(jnp.inf, jnp.float64)
        return cls(force=force, moment=moment, apply_time=-inf, release_time=release_time)

    def __call__(self, t):
        on = (t >= self.apply_time) & (t <= self.release_time)
        F = jnp.where(on, self.force, 0.0)
        M = jnp.where(on, self.moment, 0.0)
        if self.table_t is not None:
            w = _interp(t, self.table_t, self.table_w)
            F, M = F + w[0:3], M + w[3:6]
        return F, M


def natural_spline_moments(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Second derivatives (K, c) at the knots ``t`` (K,) of the natural cubic splines through the
    columns of ``y`` (K, c): zero at both ends, continuous second derivative between."""
    K = t.shape[0]
    M = np.zeros_like(y)
    if K < 3:
        return M
    h = np.diff(t)
    A = np.zeros((K - 2, K - 2))
    idx = np.arange(K - 2)
    A[idx, idx] = 2.0 * (h[:-1] + h[1:])
    A[idx[1:], idx[:-1]] = h[1:-1]
    A[idx[:-1], idx[1:]] = h[1:-1]
    slopes = np.diff(y, axis=0) / h[:, None]
    M[1:-1] = np.linalg.solve(A, 6.0 * np.diff(slopes, axis=0))
    return M


class PosePath(eqx.Module):
    """A prescribed pose of a robot's end over time: natural cubic splines (C2: continuous
    velocity and acceleration, which BDF-alpha then differentiates) through knots ``t`` (K,) of
    ``values`` (K, 6) [x, y, z (m), rotation vector (rad)], or (K, 3) [x, y, theta_z] on a planar
    bearing. Held at the first and last knots outside their time range. ``moments`` are the
    splines' second derivatives at the knots (`natural_spline_moments`)."""

    t: jnp.ndarray
    values: jnp.ndarray
    moments: jnp.ndarray

    @classmethod
    def from_samples(cls, t, values):
        t = np.asarray(t, np.float64)
        values = np.asarray(values, np.float64)
        return cls(jnp.asarray(t), jnp.asarray(values), jnp.asarray(natural_spline_moments(t, values)))

    @property
    def planar(self) -> bool:
        return self.values.shape[1] == 3

    def __call__(self, t):
        """Spline values (c,) at time ``t``."""
        tk, y, M = self.t, self.values, self.moments
        tc = jnp.clip(t, tk[0], tk[-1])
        i = jnp.clip(jnp.searchsorted(tk, tc, side="right") - 1, 0, tk.shape[0] - 2)
        h = tk[i + 1] - tk[i]
        a, b = (tk[i + 1] - tc) / h, (tc - tk[i]) / h
        return a * y[i] + b * y[i + 1] + ((a**3 - a) * M[i] + (b**3 - b) * M[i + 1]) * h**2 / 6.0

    def pose(self, t, z):
        """(p (3,), R (3, 3)) at time ``t``; a planar path sits at height ``z``."""
        v = self(t)
        if self.planar:
            return jnp.stack([v[0], v[1], z]), rotz(v[2])
        return v[0:3], exp_map(v[3:6])
