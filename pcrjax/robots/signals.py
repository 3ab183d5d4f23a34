"""Time signals of a robot: actuator values and the load on its end (platform centre or free tip).

Actuators (one value each: a leg length for the Stewart-Gough platform, a base displacement
along ``d_i`` for the Triskele-bot) follow ``constant``, ``step``, ``ramp`` or ``smooth_step``
(quintic, zero velocity and acceleration at both ends) from ``initial`` to ``final``, starting at
``start`` (s) over ``duration`` (s); or a CSV table ``t_s,a1..an`` interpolated linearly (held at
its first and last rows outside its time range).

Loads (force N, moment N m, global frame, on the platform centre or the free tip) are held while
``apply_time <= t <= release_time`` (push-and-release: ``release_time = 0``; a step:
``apply_time > 0``), plus an optional CSV table ``t_s,fx_N,fy_N,fz_N,mx_Nm,my_Nm,mz_Nm``.

Every number is a float64 leaf; the kinds are static.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

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


class Actuation(eqx.Module):
    """Actuator values over time (see module doc). Call ``actuation(t)`` for the (n,) values."""

    initial: jnp.ndarray
    final: jnp.ndarray
    start: jnp.ndarray
    duration: jnp.ndarray
    table_t: jnp.ndarray | None = None
    table_a: jnp.ndarray | None = None
    kinds: tuple[str, ...] = eqx.field(static=True, default=())

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
