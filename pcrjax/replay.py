"""Checks of an inverse-dynamics solution: replay its actuator values in forward dynamics and
measure how far the platform strays from the prescribed path.

The replay is the same scene with the solved actuator values as a table (`Actuation` with
``table_t``, ``table_a``): linear interpolation between rows is exact at the step times, the
only times forward dynamics reads it. At the same step and grid the replay solves the same
equations as the inverse solve, so its path error is the solver tolerance's; on a finer grid
it is the discretisation error of the inverse solution.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .physics.rotations import exp_map, rotation_vector, transpose_matmul
from .robots.signals import Actuation, PosePath
from .simulation import Trajectory, simulate


def with_actuator_table(scene, t, a):
    """``scene`` with its actuators driven by the table ``t`` (T,), ``a`` (T, n) (its limits kept)."""
    t, a = jnp.asarray(t, jnp.float64), jnp.asarray(a, jnp.float64)
    n = a.shape[1]
    limits = scene.actuation.limits if scene.actuation is not None else None
    act = Actuation(
        initial=a[0], final=a[0], start=jnp.zeros(n), duration=jnp.ones(n), table_t=t, table_a=a, kinds=(), limits=limits
    )
    return eqx.tree_at(lambda s: s.actuation, scene, act, is_leaf=lambda x: x is None)


def path_errors(path: PosePath, traj: Trajectory) -> dict:
    """Position and rotation errors of ``traj`` against ``path`` at its times: ``position_m``
    (T,), ``rotation_rad`` (T,), the motion's ``amplitude_m`` (largest distance from the first
    pose) and the largest position error relative to it."""
    want = np.asarray(jax.vmap(path)(traj.t))
    p = np.asarray(traj.position)
    rv = np.asarray(traj.rotation_vector)
    if path.planar:
        dp = p[:, :2] - want[:, :2]
        ang = np.abs(rv[:, 2] - want[:, 2])
        amp = np.linalg.norm(want[:, :2] - want[:1, :2], axis=1).max()
    else:
        dp = p - want[:, :3]
        rel = jax.vmap(lambda a, b: rotation_vector(transpose_matmul(exp_map(a), exp_map(b))))(
            jnp.asarray(want[:, 3:]), jnp.asarray(rv)
        )
        ang = np.linalg.norm(np.asarray(rel), axis=1)
        amp = np.linalg.norm(want[:, :3] - want[:1, :3], axis=1).max()
    err = np.linalg.norm(dp, axis=1)
    return {
        "position_m": err,
        "rotation_rad": ang,
        "amplitude_m": float(amp),
        "max_position_error_m": float(err.max()),
        "max_rotation_error_rad": float(ang.max()),
        "relative_error": float(err.max() / amp) if amp > 0 else float("nan"),
    }


def replay(scene, traj: Trajectory, **kwargs) -> Trajectory:
    """Forward dynamics of ``scene`` driven by ``traj``'s actuator values (`simulate` kwargs)."""
    return simulate(with_actuator_table(scene, traj.t, traj.actuators), **kwargs)
