"""Time signals of a parallel robot: actuator values and platform loads.

Actuators (one value each: a leg length for the Stewart-Gough platform, a base displacement
along ``d_i`` for the Triskele-bot) follow ``constant``, ``step``, ``ramp`` or ``smooth_step``
(quintic, zero velocity and acceleration at both ends) from ``initial`` to ``final``, starting at
``start`` (s) over ``duration`` (s); or a CSV table ``t_s,a1..an`` interpolated linearly (held at
its first and last rows outside its time range).

Platform loads (force N, moment N m, on the platform centre, global frame) are held while
``apply_time <= t <= release_time`` (push-and-release: ``release_time = 0``; a step:
``apply_time > 0``), plus an optional CSV table ``t_s,fx_N,fy_N,fz_N,mx_Nm,my_Nm,mz_Nm``.

Every number is a float64 leaf; the kinds are static.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

KINDS = ("constant", "step", "ramp", "smooth_step")
LOAD_COLUMNS = ("t_s", "fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")


class TableError(ValueError):
    """A CSV time series that cannot be used; the message names the file and the cause."""


def read_table(path, columns: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Read a CSV time series with exactly the header ``columns`` (first one ``t_s``).

    Returns ``(t (K,), values (K, len(columns) - 1))``. Raises `TableError` for a missing file,
    a wrong header, empty cells (gaps), non-numeric or non-finite values, fewer than two rows,
    or times that do not strictly increase.
    """
    p = Path(path)
    if not p.is_file():
        raise TableError(f"{p}: no such file")
    try:
        with p.open(newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except UnicodeDecodeError:
        raise TableError(f"{p}: not a text file") from None
    if not rows:
        raise TableError(f"{p}: empty file")
    header = [c.strip() for c in rows[0]]
    if tuple(header) != tuple(columns):
        raise TableError(f"{p}: header must be {','.join(columns)} ({len(columns) - 1} value columns), got {','.join(header)}")
    data = []
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != len(columns):
            raise TableError(f"{p}: line {i}: expected {len(columns)} columns, got {len(r)}")
        vals = []
        for name, c in zip(columns, r):
            c = c.strip()
            if c == "":
                raise TableError(f"{p}: line {i}: column {name} is empty (gap in the series)")
            try:
                v = float(c)
            except ValueError:
                raise TableError(f"{p}: line {i}: column {name}: not a number: {c!r}") from None
            if not math.isfinite(v):
                raise TableError(f"{p}: line {i}: column {name}: not finite: {c}")
            vals.append(v)
        data.append(vals)
    if len(data) < 2:
        raise TableError(f"{p}: needs at least two rows of data, got {len(data)}")
    a = np.asarray(data)
    t = a[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0])
        raise TableError(f"{p}: times must strictly increase: line {i + 3} has t = {t[i + 1]} after t = {t[i]}")
    return t, a[:, 1:]


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


class PlatformLoad(eqx.Module):
    """External force and moment on the platform centre (global frame) over time."""

    force: jnp.ndarray
    moment: jnp.ndarray
    apply_time: jnp.ndarray
    release_time: jnp.ndarray
    table_t: jnp.ndarray | None = None
    table_w: jnp.ndarray | None = None

    def __call__(self, t):
        on = (t >= self.apply_time) & (t <= self.release_time)
        F = jnp.where(on, self.force, 0.0)
        M = jnp.where(on, self.moment, 0.0)
        if self.table_t is not None:
            w = _interp(t, self.table_t, self.table_w)
            F, M = F + w[0:3], M + w[3:6]
        return F, M
