r"""Tracking a platform path within the actuators' limits.

Direct inverse dynamics (`inverse_dynamics`) gives the actuator motion that makes the platform
follow a path exactly, whatever speed that takes. Where it exceeds the actuators' limits, the
closest feasible motion is wanted. The actuator speeds are parametrised so that they cannot
exceed ``max_speed`` $v_i$:
$$\dot a_i = v_i \tanh\big(w_i(t)/v_i\big), \qquad w_i(t) = \sum_k c_{ki}\,B_k(t/t_\mathrm{end}),$$
with $B_k$ the cubic B-splines on uniform knots over the path's duration, less the first (the
actuators start from rest: a speed that jumps at t = 0 is an unbounded acceleration); $\dot a_i =
w_i$ where the speed is unlimited. The actuator table at the step times is $a_i(0)$ (the direct inverse's
start: the static inverse at the path's first pose) plus the steps' speeds at their midpoints
times δt; between the step times it is linear, as every actuator table, so its speed on each
step is that bounded midpoint value. Range and acceleration limits enter as penalty rows
(`least_squares.limit_rows`). The coefficients minimise the platform's pose error against the
path at every step (positions in metres; the rotation times a lever arm) by Levenberg-Marquardt
through `rollout`, with the Jacobian by forward mode. The start is the least-squares fit of the
direct inverse's speeds, clipped to 95 % of the limit.
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..io.scene_file import with_solver
from ..physics.rotations import exp_map, rotation_vector, transpose_matmul
from ..replay import with_actuator_table
from ..robots.inverse import check_square
from ..robots.signals import PosePath
from ..simulation import inverse_dynamics, rollout, simulate
from .least_squares import levenberg_marquardt, limit_rows
from .moves import default_lever, step_times
from .splines import bspline_basis

SPEED_SHARE = 0.999


class Tracking(eqx.Module):
    """The actuator curves of a tracking design on a scene's steps: the ``path`` (`PosePath`),
    start values ``a0`` (n,), speed limits ``max_speed`` (n,) (inf: unlimited), the speed basis
    ``basis`` (steps, count) at the step midpoints, and the step ``dt`` (s)."""

    path: PosePath
    a0: jnp.ndarray
    max_speed: jnp.ndarray
    basis: jnp.ndarray
    dt: jnp.ndarray

    @property
    def count(self) -> int:
        return self.basis.shape[1]

    def speeds(self, coeffs):
        """(steps, n) actuator speeds on each step for coefficients ``coeffs`` (count, n): within
        99.9 % of ``max_speed``, so that round-off cannot take them past it."""
        w = self.basis @ coeffs
        finite = jnp.isfinite(self.max_speed)
        v = jnp.where(finite, SPEED_SHARE * self.max_speed, 1.0)
        return jnp.where(finite, v * jnp.tanh(w / v), w)

    def actuators(self, coeffs):
        """(steps + 1, n) actuator values at the step times."""
        steps = jnp.cumsum(self.speeds(coeffs) * self.dt, axis=0)
        return self.a0 + jnp.concatenate([jnp.zeros_like(steps[:1]), steps], axis=0)


def plan_tracking(scene, path, count: int):
    """The tracking design of ``path`` (`PosePath`) over the scene's duration with ``count``
    speed B-splines per actuator. Returns (`Tracking`, start coefficients (count, n), the direct
    inverse solution's `Trajectory`); a path that leaves the workspace raises as in
    `inverse_dynamics`."""
    check_square(scene)
    inverse = inverse_dynamics(scene, path)
    t = step_times(scene)
    mid = 0.5 * (t[:-1] + t[1:])
    basis = bspline_basis(mid / t[-1], int(count) + 1, degree=3)[:, 1:]  # the first is the only one not 0 at t = 0
    limits = scene.actuation.limits if scene.actuation is not None else None
    n = inverse.actuators.shape[1]
    vmax = np.full(n, np.inf) if limits is None else np.asarray(limits.max_speed, np.float64)
    dt = float(scene.solver.dt)
    tr = Tracking(path, inverse.actuators[0], jnp.asarray(vmax), jnp.asarray(basis), jnp.asarray(dt, jnp.float64))
    v = np.diff(np.asarray(inverse.actuators), axis=0) / dt
    finite = np.isfinite(vmax)
    vm = np.where(finite, SPEED_SHARE * vmax, 1.0)
    w = np.where(finite, vm * np.arctanh(np.clip(v / vm, -0.95, 0.95)), v)
    start = np.linalg.lstsq(basis, w, rcond=None)[0]
    return tr, jnp.asarray(start), inverse


def tracking_residual(c, scene, tr: Tracking, lever: float):
    """(r, code): the pose error against the path at every step (m; rotations times ``lever``)
    and the range and acceleration penalty rows, for coefficients ``c`` (count * n,)."""
    limits = scene.actuation.limits if scene.actuation is not None else None
    t = jnp.arange(scene.solver.steps + 1) * scene.solver.dt
    want = jax.vmap(tr.path)(t)
    a = tr.actuators(c.reshape(tr.count, -1))
    traj = rollout(with_actuator_table(scene, t, a))
    if tr.path.planar:
        rows = [traj.position[:, :2] - want[:, :2], lever * (traj.rotation_vector[:, 2:3] - want[:, 2:3])]
    else:
        rot = jax.vmap(lambda w, rv: rotation_vector(transpose_matmul(exp_map(w), exp_map(rv))))(
            want[:, 3:], traj.rotation_vector
        )
        rows = [traj.position - want[:, :3], lever * rot]
    r = jnp.concatenate(rows, axis=1).reshape(-1)
    if limits is not None:
        r = jnp.concatenate([r, limit_rows(a, tr.dt, limits, t[-1], speed=False)])
    return r, jnp.max(traj.result)


_residual = eqx.filter_jit(tracking_residual)
_jacobian = eqx.filter_jit(lambda c, scene, tr, lever: jax.jacfwd(lambda c: tracking_residual(c, scene, tr, lever)[0])(c))


def design_tracking(scene, tr: Tracking, start, *, iterations: int = 10, lever: float | None = None, log=print) -> dict:
    """Optimise the tracking coefficients from ``start``. Returns a dict: ``coefficients``
    (count, n), ``objective`` (sum of squares, m^2, per iteration, the start's first),
    ``compile_s``, ``optimise_s``."""
    lever = default_lever(scene) if lever is None else float(lever)
    c = jnp.asarray(start).reshape(-1)
    t0 = time.perf_counter()
    _residual(c, scene, tr, lever)[0].block_until_ready()
    compile_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    c, _, history = levenberg_marquardt(
        lambda c: _residual(c, scene, tr, lever), lambda c: _jacobian(c, scene, tr, lever), c, iterations=iterations, log=log
    )
    return {
        "coefficients": c.reshape(tr.count, -1),
        "objective": history,
        "compile_s": compile_s,
        "optimise_s": time.perf_counter() - t1,
    }


def verify_tracking(scene, tr: Tracking, coeffs, finer: bool = True):
    """Forward run of the designed actuator table on the same grid, or on a finer one (2N nodes,
    dt/2) reading the same table (linear between the design's step times: the same curve)."""
    t = step_times(scene)
    a = tr.actuators(jnp.asarray(coeffs))
    if finer:
        s = scene.solver
        scene = with_solver(scene, nodes=2 * s.nodes, dt=float(s.dt) / 2.0)
    return simulate(with_actuator_table(scene, t, a))
